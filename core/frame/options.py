"""A frame's settings beside the scene: how the kd-tree is built, how slaves are found and
tiles handed out. Each default and range has its home here or in the module named beside it;
the add-on's panel reads them."""
from __future__ import annotations

from dataclasses import dataclass, field

from ..accel.compact import compact_params, user_settings
from ..net import protocol
from ..net.master import DEFAULT_TILE_SIZE, DEFAULT_TILES_IN_FLIGHT
from ..scene.tree_files import DEFAULT_LIMIT_MIB
from .denoising import DenoiseSettings

DISCOVERY_SECONDS = 3.0           # how long F12 waits for a young LAN browser's first slave
DISCOVERY_SECONDS_RANGE = (0.1, 30.0)
LOCAL_SLAVES = 2                  # local slaves started when no other slave is known
LOCAL_SLAVES_RANGE = (0, 64)


def _default_tree_settings() -> dict:
    tree = compact_params()
    return user_settings(tree.mode, tree.tau_occu, tree.tau_freq, tree.refs_per_path)


@dataclass
class FrameOptions:
    # kd-tree: a mode of core.accel.compact and the settings it uses (compact.user_settings)
    tree_mode: str = field(default_factory=lambda: compact_params().mode)
    tree_settings: dict = field(default_factory=_default_tree_settings)
    tree_folder: str | None = None    # kd-trees kept on disk there (None: in memory only)
    tree_cache_mib: int = DEFAULT_LIMIT_MIB
    # slaves: listed hosts, the LAN, local slave processes
    hosts: list = field(default_factory=list)    # (host, port) pairs
    use_zeroconf: bool = True
    discovery_seconds: float = DISCOVERY_SECONDS
    local_slaves: int = LOCAL_SLAVES
    local_slaves_always: bool = False
    slave_python: str = ""            # the Python of local slaves ("": this one)
    slave_device: str = "auto"        # their OpenCL device, and the kd-tree builder's
    # trust (core/net/trust.py): the farm secret, the slaves the user approved (IDs), and the
    # folder of this master's identity (None: one for the session only)
    secret: bytes | None = None
    approved_slaves: tuple = ()
    identity_folder: str | None = None
    # tiles (core.net.master.Master.render's arguments)
    tile_size: int = DEFAULT_TILE_SIZE
    tiles_in_flight: int = DEFAULT_TILES_IN_FLIGHT
    partition: int | None = None
    model: str = protocol.DEFAULT_MODEL
    payload: str = "f32"
    compress: bool = False
    passes: tuple = ("combined",)     # the passes the host shows
    # the master's denoising of the finished frame (core/frame/denoising.py)
    denoise: DenoiseSettings = field(default_factory=DenoiseSettings)

    def job_options(self) -> dict:
        """Master.render's keyword arguments (the passes: those the host shows; an F12 frame
        adds the denoiser's guides, render_frame)."""
        return {"tile_size": self.tile_size, "tiles_in_flight": self.tiles_in_flight,
                "partition": self.partition, "model": self.model, "payload": self.payload,
                "compress": self.compress, "passes": list(self.passes),
                "hold_when_stranded": bool(self.local_slaves)}
