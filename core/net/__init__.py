"""Master and slaves on the LAN: the wire protocol (protocol.py; channels with deadlines,
channel.py; a tile's passes on the wire, tile_payloads.py), finding slaves with zeroconf
(discovery.py), a frame's tiles (tiles.py), the master's render jobs (master.py) and each
slave's colour (slave_colors.py)."""
