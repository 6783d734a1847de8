"""State that lives from enabling the add-on to disabling it: local slaves, built kd-trees and the
LAN browser. Created in register(), closed in unregister() (and at Blender's exit)."""
from __future__ import annotations

import pathlib
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

from ..core.accel.compact import compact_tree
from ..core.accel.kdtree_cl import build_standard, opencl_builder
from ..core.net.slave_colors import slave_color
from ..core.scene.model import SceneError
from ..core.scene.scene import checked_depth, tree_digest
from ..core.scene.spatial_order import spatial_order
from ..core.scene.tree_files import TreeFiles
from .local_slaves import LocalSlaves


class TreeCache:
    """Built kd-trees in the compact layout, by (geometry hash, mode, the settings the mode uses),
    so a re-render of unchanged geometry with unchanged kd-tree settings does not rebuild. The
    standard SAH tree of a geometry is kept too, so another mode or threshold only redoes the
    compaction. An instanced scene keeps a tree per mesh (docs/instances.md): the capacity
    counts trees. With a folder (`use_disk`), compact trees are also kept on disk
    (core/scene/tree_files.py), so they outlive Blender."""

    def __init__(self, capacity: int = 8):
        self.capacity = capacity
        self.builds = 0        # how many standard trees were built (tests count rebuilds with it)
        self.compactions = 0   # how many compact trees were made from them
        self.disk: TreeFiles | None = None
        self.disk_problem = ""  # why a tree of this render could not be written to disk
        self._trees: OrderedDict = OrderedDict()      # key -> CompactTree
        self._standard: OrderedDict = OrderedDict()   # geometry hash -> KDTree
        self._lock = threading.Lock()

    def use_disk(self, folder, limit_mib: int):
        """Keep trees in `folder` too, up to limit_mib MiB; None or a limit of 0: memory only.
        OSError when the folder cannot be made. Called at each render: the last render's
        disk problem is forgotten here."""
        self.disk_problem = ""
        if not folder or limit_mib <= 0:
            self.disk = None
        elif (self.disk is None or self.disk.files.folder != pathlib.Path(folder)
              or self.disk.files.limit_bytes != limit_mib << 20):
            self.disk = TreeFiles(folder, limit_mib << 20)

    def get(self, geometry, mode: str, settings: dict, progress=None, device="auto"):
        """(compact tree, where from): "memory", "disk" or "built" (anything had to be built
        or compacted). `settings`: compact_tree's keyword arguments
        (core.accel.compact.user_settings). progress(fraction, message) covers both steps:
        the SAH build 0-0.8, compaction 0.8-1. Both run on the OpenCL device `device` (the
        preferences' local slave device) when there is one, else with numpy; the tree's stats
        say which builder ran where."""
        report = progress or (lambda fraction, message: None)
        key = (geometry.content_hash(), mode, tuple(sorted(settings.items())))
        with self._lock:
            if key in self._trees:
                self._trees.move_to_end(key)
                return self._trees[key], "memory"
            standard = self._standard.get(key[0])
        disk, name = self.disk, None
        if disk is not None:
            name = disk.key(key[0], mode, settings)
            report(0.0, "reading the kd-tree from disk")
            compact = disk.read(name, geometry.triangle_count,
                                lambda: report(0.0, "checking the kd-tree read from disk"))
            if compact is not None:
                with self._lock:
                    self._remember(self._trees, key, compact)
                return compact, "disk"
        if standard is None:
            standard, builder = build_standard(geometry.vertices, geometry.triangles, device,
                                               progress=lambda f, m: report(0.8 * f, m))
            with self._lock:
                self.builds += 1
                self._remember(self._standard, key[0], standard)
        else:
            builder = opencl_builder(device)[0]
        compact = compact_tree(standard, geometry.triangle_count, mode, **settings,
                               progress=lambda f, m: report(0.8 + 0.2 * f, m), device=builder)
        compact.stats.update({k: standard.stats[k] for k in ("builder", "device", "build_seconds")})
        # The scene's checks of the tree and its digest, done here where Esc is heard (12
        # dragons': 3-4 s); the scene finds them done.
        checking = lambda: report(1.0, "checking the kd-tree")      # noqa: E731
        try:
            checked_depth(compact, geometry.triangle_count, checking)
        except ValueError as error:
            raise SceneError(f"invalid kd-tree: {error}") from None
        tree_digest(compact, checking)
        with self._lock:
            self.compactions += 1
            self._remember(self._trees, key, compact)
        if disk is not None:
            try:
                disk.write(name, compact, geometry.triangle_count)
            except OSError as error:    # a full disk costs a build after a restart, no more
                self.disk_problem = f"cannot keep the kd-tree in {disk.files.folder}: {error}"
        return compact, "built"

    def clear(self):
        """Forget every tree held in memory (the disk's are the caller's to delete)."""
        with self._lock:
            self._trees.clear()
            self._standard.clear()

    def _remember(self, store, key, value):
        store[key] = value
        store.move_to_end(key)
        while len(store) > self.capacity:
            store.popitem(last=False)


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
    delivered (counted by the render thread). draw() only reads it."""

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


class Session:
    def __init__(self):
        self.local_slaves = LocalSlaves()
        self.trees = TreeCache()
        self._browser = None
        self._browser_started = 0.0   # time.monotonic() when the browser started
        self.last_render: dict = {}  # timings and tiles per slave of the last render, for reports
        self.last_warnings: list = []  # what the last export could not render as Cycles would
        self.legend: Legend | None = None
        self.local_reason = ""       # why the last render started local slaves ("": it did not)
        self.joined: list = []       # endpoints the LAN browser found during the last frame
        self.last_scene = None       # (key, Scene) of the last render (render.frame_scene)
        self.mesh_orders: list = []  # each exported mesh's triangle order (order_meshes)

    def order_meshes(self, meshes) -> tuple[list, int]:
        """The exported meshes with their triangles in spatial order (core/scene/spatial_order.py:
        the builder, the compaction and the tracer then find neighbouring triangles in the same
        cache lines), and how many kept the last render's content hash. A mesh that, put in the
        order of the last render's mesh of its place, is that mesh bit for bit (an F12 of an
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

    def start_legend(self, master) -> Legend:
        self.legend = Legend(master)
        return self.legend

    def browser(self):
        """The zeroconf browser on every interface, started on first use: while KD Trace is the
        render engine (addon/browsing.py), at F12 at the latest. It runs on zeroconf's own
        threads and keeps what it has seen, so F12 uses it at once."""
        if self._browser is None:
            from ..core.net.discovery import SlaveBrowser, all_ipv4_addresses
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


_session: Session | None = None


def current() -> Session:
    global _session
    if _session is None:
        _session = Session()
    return _session


def close():
    global _session
    if _session is not None:
        _session.close()
        _session = None

