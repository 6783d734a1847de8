"""What lives from one frame to the next: built kd-trees, each mesh's triangle order, the last
scene, local slaves and the LAN browser; and what the last frame left to show (its report, its
warnings, who rendered what). One per Blender session (addon/session.py holds it), or per
program that renders without Blender (tests, benchmarks)."""
from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass

import numpy as np

from ..net.slave_colors import slave_color
from ..scene.scene import Scene
from ..scene.spatial_order import spatial_order
from .denoising import FrameDenoiser
from .local_slaves import LocalSlaves
from .tree_cache import TreeCache


@dataclass
class SlaveStatus:
    """One line of the panel's legend."""
    name: str
    color: tuple
    device: str
    tiles: int = 0
    render_ms: float = 0.0
    # What the master last heard (core.net.master.SlaveState): connecting, uploading, idle,
    # waiting, loading, compiling, rendering, reconnecting or lost.
    state: str = "idle"

    @property
    def ms_per_tile(self) -> float:
        return self.render_ms / self.tiles if self.tiles else 0.0


class Legend:
    """Which slave renders what, for the panel: what each slave is doing, read live from the
    master (its threads keep it current, also while the scene uploads), and the tiles each
    delivered (counted by the frame's thread). A panel only reads it."""

    def __init__(self, master):
        self._master = master
        self._tiles: dict = {}      # slave name -> [tiles, render ms]

    @property
    def slaves(self) -> dict:
        out = {}
        for state in self._master.slave_states():
            tiles, render_ms = self._tiles.get(state.name, (0, 0.0))
            out[state.name] = SlaveStatus(state.name, slave_color(state.name), state.device,
                                          tiles, render_ms, state.state)
        return out

    def tile_done(self, tile):
        counts = self._tiles.setdefault(tile.slave_name, [0, 0.0])
        counts[0] += 1
        counts[1] += tile.render_ms

    def render_ms(self) -> float:
        """The slaves' own render time of every tile delivered, summed."""
        return sum(render_ms for _, render_ms in self._tiles.values())

    def tiles_per_slave(self) -> dict:
        return {name: tiles for name, (tiles, _) in self._tiles.items() if tiles}


class FrameSession:
    def __init__(self):
        self.local_slaves = LocalSlaves()
        self.trees = TreeCache()
        self._browser = None
        self._browser_started = 0.0   # time.monotonic() when the browser started
        self.last_render: dict = {}  # timings and tiles per slave of the last frame, for reports
        self.last_warnings: list = []  # what the last export could not render as Cycles would
        self.legend: Legend | None = None
        self.local_reason = ""       # why the last frame started local slaves ("": it did not)
        self.joined: list = []       # endpoints the LAN browser found during the last frame
        self.last_scene = None       # (key, Scene) of the last frame (frame_scene)
        self.mesh_orders: list = []  # each exported mesh's triangle order (order_meshes)
        # Slaves refused as not approved (endpoint -> ID; the last frame's and the LAN's),
        # for the panel's Approve buttons.
        self.unapproved: dict = {}
        self._identity = None        # this master's (master_identity)
        self.denoiser = FrameDenoiser()  # Open Image Denoise, made at the first denoised frame

    def master_identity(self, folder=None):
        """This master's identity: kept in `folder` (the add-on: its user folder), made there
        on first use; without a folder, one for this session only."""
        from ..net.identity import Identity
        if self._identity is None or (folder is not None and
                                      str(self._identity.folder) != str(folder)):
            self._identity = (Identity.load_or_create(folder, "master") if folder is not None
                              else Identity.ephemeral("master"))
        return self._identity

    def identity_if_loaded(self):
        """This master's identity if it is loaded (the panel shows it; drawing makes none)."""
        return self._identity

    def trusted_lan_endpoints(self, approved, has_secret: bool) -> list:
        """(host, port) of the LAN slaves this master may send scenes to: approved ones by the
        ID they advertise (checked again in TLS), or any when the farm secret decides. The
        others are remembered in `unapproved` for the panel; no connection is made to them."""
        endpoints = []
        for slave in self.discovered_slaves():
            advertised = slave.properties.get("id", "")
            if has_secret or approved.allows(advertised):
                endpoints.append(slave.endpoint)
            elif advertised:
                self.unapproved[slave.endpoint] = advertised
        return endpoints

    def order_meshes(self, meshes) -> tuple[list, int]:
        """The exported meshes with their triangles in spatial order (core/scene/spatial_order.py:
        the builder, the compaction and the tracer then find neighbouring triangles in the same
        cache lines), and how many kept the last frame's content hash. A mesh that, put in the
        order of the last frame's mesh of its place, is that mesh bit for bit (an F12 of an
        unchanged scene, an animation frame where objects only moved) takes its order and its
        hash: neither sorted nor hashed again (the tree cache and the frame's scene key by the
        hash). Compared against the arrays the last scene holds anyway (of those the mesh had: a
        scene fills in normals and UVs for meshes without, and a flat scene carries the
        textures); only the orders are kept besides."""
        held, last_meshes = [], []
        if self.last_scene is not None:
            (last_meshes, *_), last = self.last_scene
            held = ([last.geometry] if last.instances is None
                    else [geometry for geometry, _ in last.mesh_parts or ()])
        ordered, orders, reused = [], [], 0
        for place, mesh in enumerate(meshes):
            if place < min(len(held), len(last_meshes), len(self.mesh_orders)):
                (digest, names), arrays = last_meshes[place], held[place].arrays()
                order = self.mesh_orders[place]
                if (set(names) <= arrays.keys()
                        and mesh.triangle_count == held[place].triangle_count):
                    candidate = mesh if order is None else spatial_order(mesh, order)[0]
                    if candidate.take_hash(digest, {name: arrays[name] for name in names}):
                        ordered.append(candidate)
                        orders.append(order)
                        reused += 1
                        continue
            mesh, order = spatial_order(mesh)
            ordered.append(mesh)
            orders.append(order)
        self.mesh_orders = orders
        return ordered, reused

    def frame_scene(self, meshes, trees, exported, tree_key) -> Scene:
        """This frame's scene. Where its meshes, their kd-tree settings and the textures are the
        last frame's (an animation frame in which objects only moved), the last scene placed by
        this frame's instances: the meshes' arrays and their checks are reused, only the
        instances are checked and the top level built, and the slaves that hold the meshes are
        sent only the instances (docs/instances.md, "Scene deltas"); a flat scene placed flat
        again is the last scene itself."""
        textures = hashlib.blake2b(digest_size=16)
        for array in (exported.texels, exported.texture_sizes):
            textures.update(b"-" if array is None else np.ascontiguousarray(array).tobytes())
        key = (tuple((m.content_hash(), tuple(m.arrays())) for m in meshes), tree_key,
               textures.hexdigest())
        last_key, last = self.last_scene or (None, None)
        if key == last_key:
            if last.instances is not None:
                return last.placed(exported.instance_mesh, exported.to_world,
                                   to_world_end=exported.to_world_end)
            if Scene.places_flat(len(meshes), exported.instance_mesh, exported.to_world,
                                 exported.to_world_end):
                return last     # the same flat scene (an F12 of an unchanged scene)
        scene = Scene.from_instances(list(zip(meshes, trees)), exported.instance_mesh,
                                     exported.to_world, texels=exported.texels,
                                     texture_sizes=exported.texture_sizes,
                                     to_world_end=exported.to_world_end)
        self.last_scene = (key, scene)
        return scene

    def start_legend(self, master) -> Legend:
        self.legend = Legend(master)
        return self.legend

    def browser(self):
        """The zeroconf browser on every interface, started on first use (the add-on starts it
        while KD Trace is the render engine, a frame at the latest). It runs on zeroconf's own
        threads and keeps what it has seen, so a frame uses it at once."""
        if self._browser is None:
            from ..net.discovery import SlaveBrowser, all_ipv4_addresses
            self._browser = SlaveBrowser(interfaces=all_ipv4_addresses())
            self._browser_started = time.monotonic()
        return self._browser

    @property
    def browsing(self) -> bool:
        return self._browser is not None

    def browsing_seconds(self) -> float:
        """How long the browser has been looking (0 when it is not running)."""
        return time.monotonic() - self._browser_started if self._browser is not None else 0.0

    def stop_browser(self):
        if self._browser is not None:
            self._browser.close()
            self._browser = None

    def restart_browser(self):
        self.stop_browser()
        self.browser()

    def discovered_slaves(self) -> list:
        return self._browser.slaves() if self._browser is not None else []

    def lan_endpoints(self) -> list:
        """(host, port) of every slave the browser knows now."""
        return [slave.endpoint for slave in self.discovered_slaves()]

    def close(self):
        self.stop_browser()
        self.local_slaves.stop_all()
        self.denoiser.close()
