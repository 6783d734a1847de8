"""One F12: export, build (or reuse) the kd-tree, find slaves, hand out tiles, show them as they
arrive. Runs on Blender's render thread; all socket work happens on the master's threads and
comes back through job.next_result()."""
from __future__ import annotations

import hashlib
import time
import traceback

import numpy as np

from ..core.accel.compact import user_settings
from ..core.net.master import Master, MasterError
from ..core.net.protocol import AuthError, ProtocolError, load_secret
from ..core.scene.model import SceneError
from ..core.scene.scene import Scene, memory_report, memory_summary
from ..core.net.slave_colors import slave_color
from . import session
from .export import export_instanced_view
from .properties import preferences, tree_folder

POLL_SECONDS = 0.05  # how often the render thread checks for Esc while waiting for tiles
SETTLE_SECONDS = 0.3  # after the first slave answers a young browser, for the others to answer
FRAME_PIXELS = 2     # width of the slave-coloured frame drawn around tiles while rendering


class RenderFailed(Exception):
    """A problem the user must see in Blender's report, not a traceback."""


class RenderCancelled(Exception):
    """The user pressed Esc during a long step (kd-tree build, starting slaves)."""


def listed_hosts(settings) -> list[tuple[str, int]]:
    """The enabled entries of the panel's host list, with a message that names a bad one."""
    endpoints = []
    for number, entry in enumerate(settings.hosts, 1):
        if not entry.enabled:
            continue
        host = entry.host.strip().strip("[]")
        if not host or any(c.isspace() for c in host):
            raise RenderFailed(f"host {number} in the slave list has no valid address: {entry.host!r}")
        endpoints.append((host, entry.port))
    return endpoints


def shared_secret(prefs) -> bytes | None:
    """The secret from the preferences' file, else $KDTRACE_SECRET, else None."""
    try:
        return load_secret(bpy_path(prefs.secret_file) if prefs.secret_file else None)
    except AuthError as error:
        raise RenderFailed(str(error)) from None


def bpy_path(path: str) -> str:
    import bpy
    return bpy.path.abspath(path)


def find_slaves(engine, settings, prefs, secret) -> list[tuple[str, int]]:
    """Listed hosts and every slave the LAN browser knows; local slaves only when no other slave
    is known (or when asked to always use them). The browser runs in the background while KD
    Trace is the engine (browsing.py), so slaves seen before F12 are used at once: only a
    browser younger than the discovery time is waited for, until a slave answers."""
    state = session.current()
    endpoints = listed_hosts(settings)
    if settings.use_zeroconf:
        state.browser()
        settle_until = None
        while state.browsing_seconds() < settings.discovery_seconds and not engine.test_break():
            if endpoints or state.lan_endpoints():
                # Give the others that answer a moment too, then go.
                settle_until = settle_until or time.monotonic() + SETTLE_SECONDS
                if time.monotonic() >= settle_until:
                    break
            engine.update_stats("", "KD Trace | Looking for slaves on the LAN")
            time.sleep(POLL_SECONDS)
        endpoints += [e for e in state.lan_endpoints() if e not in endpoints]
    state.local_reason = local_slaves_reason(settings, endpoints, state.browsing_seconds())
    state.joined = []
    if state.local_reason:
        engine.update_stats("", f"KD Trace | Starting {settings.local_slaves} local slave(s): "
                                f"{state.local_reason}")
        endpoints += state.local_slaves.ensure(settings.local_slaves, prefs.slave_python,
                                               prefs.slave_device, secret,
                                               cancelled=engine.test_break)
    if not endpoints:
        raise RenderFailed("no slave is reachable: none answered on the LAN, no host is listed "
                           "and local slaves are off")
    return endpoints


def local_slaves_reason(settings, known: list, browsed_seconds: float) -> str:
    """Why this render starts local slaves, for the panel and the report ("": it does not)."""
    if not settings.local_slaves:
        return ""
    if settings.use_local_slaves_always:
        return "Always Use Local Slaves is on"
    if known:
        return ""
    if settings.use_zeroconf:
        return f"no slave answered on the LAN in {browsed_seconds:.1f} s and no host is listed"
    return "LAN discovery is off and no host is listed"


def join_new_lan_slaves(master) -> None:
    """A slave the LAN browser sees during a frame joins it (Master.join connects, uploads and
    hands it tiles on the master's threads)."""
    state = session.current()
    for endpoint in state.lan_endpoints():
        if endpoint not in master.endpoints:
            state.joined.append(endpoint)
            master.join(*endpoint)


def job_options(settings, view_layer) -> dict:
    """The panel's tile and network settings as Master.render() arguments; only the passes the
    view layer shows travel (Combined always, Depth and Normal where enabled)."""
    passes = ["combined"] + (["depth"] if view_layer.use_pass_z else []) \
        + (["normal"] if view_layer.use_pass_normal else [])
    return {"tile_size": settings.tile_size, "tiles_in_flight": settings.tiles_in_flight,
            "partition": None if settings.tile_partition == "SIZE" else int(settings.tile_partition),
            "model": settings.interaction,
            "payload": settings.payload.split("_")[0].lower(),
            "compress": settings.payload.endswith("ZLIB"), "passes": passes}


def render(engine, depsgraph):
    import bpy
    settings = depsgraph.scene.kdtrace
    prefs = preferences(bpy.context)
    state = session.current()
    started = time.perf_counter()
    steps = Steps()
    try:
        if settings.use_zeroconf:
            state.browser()   # if not running yet: it looks while the scene exports and builds
        engine.update_stats("", "KD Trace | Exporting scene")
        exported_geometry, view, info = export_instanced_view(
            depsgraph, every_object=bool(engine.is_animation))
        meshes, hashes_reused = state.order_meshes(exported_geometry.meshes)
        state.last_warnings = info["warnings"]
        for warning in info["warnings"]:
            engine.report({"WARNING"}, f"KD Trace: {warning}")
        exported = steps.mark("export")

        def tree_progress(fraction, message):
            if engine.test_break():
                raise RenderCancelled
            engine.update_progress(0.5 * fraction)
            engine.update_stats("", f"KD Trace | Building kd-tree: {message}")

        stored = sum(m.triangle_count for m in meshes)
        engine.update_stats("", f"KD Trace | Building kd-trees over {stored:,} triangles "
                                f"({len(meshes)} mesh(es))")
        tree_settings = user_settings(settings.kdtree_mode, settings.tau_occu,
                                      settings.tau_freq, settings.refs_per_path)
        # One tree per mesh (docs/instances.md), each cached by its mesh's content.
        try:
            state.trees.use_disk(tree_folder(prefs), prefs.tree_cache_mib)
        except OSError as error:
            state.trees.use_disk(None, 0)
            engine.report({"WARNING"}, f"KD Trace: no kd-tree cache on disk: {error}")
        trees, sources, done = [], [], 0.0
        for mesh in meshes:
            share = mesh.triangle_count / max(stored, 1)     # of the progress bar

            def mesh_progress(fraction, message, done=done, share=share):
                tree_progress(done + share * fraction, message)
            tree, source = state.trees.get(mesh, settings.kdtree_mode, tree_settings,
                                           mesh_progress, device=prefs.slave_device)
            trees.append(tree)
            sources.append(source)
            done += share
        if state.trees.disk_problem:
            engine.report({"WARNING"}, f"KD Trace: {state.trees.disk_problem}")
        built = "built" in sources
        steps.mark("kd-tree cache")
        scene = frame_scene(state, meshes, trees, exported_geometry,
                            (settings.kdtree_mode, tuple(sorted(tree_settings.items()))))
        steps.mark("scene")
        scene.check_view(view)
        memory = memory_report(scene)
        tree_done = steps.mark("view check")
        if engine.test_break():
            return
        secret = shared_secret(prefs)
        endpoints = find_slaves(engine, settings, prefs, secret)
        steps.mark("find slaves")
        with Master(endpoints, secret=secret) as master:
            legend = state.start_legend(master)   # the panel follows each slave from here on
            master.connect()
            steps.mark("connect")
            engine.update_stats("", f"KD Trace | Sending scene to {len(master.slaves)} slave(s)")
            master.load_scene(scene)
            steps.mark("scene query")
            for problem in master.errors:
                engine.report({"WARNING"}, f"KD Trace: {problem}")
            job = master.render(view, **job_options(settings, depsgraph.view_layer),
                                hold_when_stranded=bool(settings.local_slaves))
            canvas = TileCanvas(engine, job)
            steps.mark("frame start")
            try:
                _receive_tiles(engine, job, canvas, legend, master,
                               local_takeover(engine, settings, prefs, secret, master), steps)
                steps.mark("other tiles")
            finally:
                canvas.finish()
                steps.mark("image")
            for problem in job.errors:
                engine.report({"WARNING"}, f"KD Trace: {problem}")
            if job.error and not job.cancelled:
                raise RenderFailed(job.error)
            uploaded_to, scene_bytes = list(master.uploaded_to), dict(master.scene_bytes)
        finished = steps.mark("close")
    except RenderCancelled:
        return
    except (SceneError, RenderFailed, MasterError, ProtocolError, AuthError, OSError, RuntimeError) as error:
        _fail(engine, str(error))
        return
    except Exception as error:      # a defect: the render ends with a report, Blender lives on
        traceback.print_exc()
        _fail(engine, f"internal error, {type(error).__name__}: {error} (the traceback is in "
                      "the system console; please report it)")
        return
    per_slave = legend.tiles_per_slave()
    state.last_render = {
        "export_seconds": exported - started, "tree_seconds": tree_done - exported,
        "tree_built": built, "tree_sources": sources, "tree_stats": dict(trees[0].stats),
        "render_seconds": finished - tree_done,
        "mesh_hashes_reused": hashes_reused,
        "steps": steps.seconds, "tile_render_ms": legend.render_ms(),
        "triangles": memory["triangles_referenced"], "memory": memory,
        "tiles_per_slave": per_slave,
        "slave_colors": {name: slave_color(name) for name in per_slave},
        "uploaded_to": uploaded_to, "scene_bytes": scene_bytes, "cancelled": job.cancelled,
        "local_reason": state.local_reason,
        "joined_during_frame": [f"{host}:{port}" for host, port in state.joined]}
    how = ("built" if built else "read from disk" if "disk" in sources else "reused")
    summary = (f"export {exported - started:.2f} s, kd-tree {how} "
               f"{tree_done - exported:.2f} s ({trees[0].stats['mode']}: "
               f"{sum(t.stats['nodes'] for t in trees):,} nodes, "
               f"{sum(t.nbytes for t in trees) / 1e6:.1f} MB; {trees[0].stats['builder']} builder on "
               f"{trees[0].stats['device']}); {memory_summary(memory)}; render "
               f"{finished - tree_done:.2f} s; tiles: "
               + ", ".join(f"{name} {count}" for name, count in sorted(per_slave.items()))
               + (f"; local slaves started: {state.local_reason}" if state.local_reason else "")
               + ("; joined during the frame: " + ", ".join(state.last_render["joined_during_frame"])
                  if state.joined else ""))
    engine.update_stats("", f"KD Trace | Done: {summary}")
    engine.report({"INFO"}, f"KD Trace: {summary}")


def _fail(engine, message: str) -> None:
    engine.report({"ERROR"}, f"KD Trace: {message}")
    engine.error_set(f"KD Trace: {message}")


def frame_scene(state, meshes, trees, exported, tree_key) -> Scene:
    """This frame's scene. Where its meshes, their kd-tree settings and the textures are the
    last render's (an animation frame in which objects only moved), the last scene placed by
    this frame's instances: the meshes' arrays and their checks are reused, only the instances
    are checked and the top level built, and the slaves that hold the meshes are sent only the
    instances (docs/instances.md, "Scene deltas"); a flat scene placed flat again is the last
    scene itself."""
    textures = hashlib.blake2b(digest_size=16)
    for array in (exported.texels, exported.texture_sizes):
        textures.update(b"-" if array is None else np.ascontiguousarray(array).tobytes())
    key = (tuple((m.content_hash(), tuple(m.arrays())) for m in meshes), tree_key,
           textures.hexdigest())
    last_key, last = state.last_scene or (None, None)
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
    state.last_scene = (key, scene)
    return scene


def local_takeover(engine, settings, prefs, secret, master):
    """What to do when every slave is lost and none could be reconnected: once, local slaves
    (where enabled) join the frame. The returned function says False when nothing is left."""
    tried = []

    def take_over() -> bool:
        if tried or not settings.local_slaves:
            return False
        tried.append(True)
        engine.update_stats("", f"KD Trace | Every slave lost: starting {settings.local_slaves} "
                                "local slave(s)")
        try:
            endpoints = session.current().local_slaves.ensure(
                settings.local_slaves, prefs.slave_python, prefs.slave_device, secret,
                cancelled=engine.test_break)
        except RuntimeError as error:
            engine.report({"WARNING"}, f"KD Trace: local slaves did not start: {error}")
            return False
        for host, port in endpoints:
            master.join(host, port)
        return True

    return take_over


def _receive_tiles(engine, job, canvas, legend, master, take_over, steps):
    """Show tiles as they arrive; stop promptly on Esc. `steps` marks the first tile."""
    done, total = 0, len(job.tiles)
    while not job.finished:
        if engine.test_break():
            job.cancel()
            return
        if job.stranded and not take_over():
            job.give_up()    # its error names every slave and why it was lost
        tiles = job.next_results(POLL_SECONDS)
        if not tiles:
            join_new_lan_slaves(master)
            continue
        for tile in tiles:
            canvas.add(tile)
            legend.tile_done(tile)
        if done == 0:
            steps.mark("first tile")
        done += len(tiles)
        engine.update_progress(0.5 + 0.5 * done / total)
        engine.update_stats("", f"KD Trace | Tile {done}/{total} from {tile.slave_name}")


class Steps:
    """Wall seconds of a render's steps, each from the previous mark (the report's breakdown:
    state.last_render["steps"], in order)."""

    def __init__(self):
        self.seconds: dict = {}
        self._last = time.perf_counter()

    def mark(self, name: str) -> float:
        now = time.perf_counter()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - self._last
        self._last = now
        return now


class TileCanvas:
    """The rendered region, filled tile by tile.

    The master writes each tile's passes straight into the job's frame (job.image); the canvas
    adds the Slave pass and, while rendering, shows each tile with a frame in its slave's
    colour. When the frame is over the clean image (and the Slave pass, each tile filled with
    its slave's colour) is written in one go, so the final Combined pass carries no frames.
    """

    BLENDER_PASSES = {"combined": "Combined", "depth": "Depth", "normal": "Normal"}

    def __init__(self, engine, job):
        x0, y0, x1, y1 = job.view.region
        self.engine, self.origin = engine, (x0, y0)
        self.width, self.height = x1 - x0, y1 - y0
        self.passes = {self.BLENDER_PASSES[name]: image for name, image in job.image.items()}
        self.passes["Slave"] = np.zeros((self.height, self.width, 4), np.float32)
        self.received = 0

    def add(self, tile):
        left, top = tile.x - self.origin[0], tile.y - self.origin[1]
        color = (*slave_color(tile.slave_name), 1.0)
        self.passes["Slave"][top:top + tile.h, left:left + tile.w] = color
        framed = tile.passes["combined"].copy()
        f = min(FRAME_PIXELS, tile.w // 4, tile.h // 4)
        for edge in (np.s_[:f], np.s_[-f:]) if f else ():
            framed[edge] = color
            framed[:, edge] = color
        self._write(left, top, tile.w, tile.h, {"Combined": framed})
        self.received += 1

    def finish(self):
        """Write the clean region (what arrived; the rest stays empty on a cancel)."""
        if self.received:
            self._write(0, 0, self.width, self.height, self.passes)

    def _write(self, left, top, w, h, arrays):
        """Write (h, w) arrays by pass name at (left, top) of the region."""
        # Blender's result rectangles are relative to the border, with the origin bottom-left.
        bottom = self.height - (top + h)
        result = self.engine.begin_result(left, bottom, w, h)
        passes = result.layers[0].passes
        for name, array in arrays.items():
            index = passes.find(name)
            if index >= 0:
                passes[index].rect.foreach_set(np.ascontiguousarray(array[::-1]).ravel())
        self.engine.end_result(result)
