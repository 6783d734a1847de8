"""One F12: export, build (or reuse) the kd-tree, find slaves, hand out tiles, write them as they
arrive. Runs on Blender's render thread; all socket work happens on the master's threads and
comes back through job.next_result()."""
from __future__ import annotations

import time

import numpy as np

from ..core.master import Master, MasterError
from ..core.scene import SceneError
from . import session
from .export import export_view
from .properties import preferences

POLL_SECONDS = 0.05  # how often the render thread checks for Esc while waiting for tiles


class RenderFailed(Exception):
    """A problem the user must see in Blender's report, not a traceback."""


def parse_hosts(text: str) -> list[tuple[str, int]]:
    """'host:port, host:port' -> [(host, port)], with a message that names a bad entry."""
    endpoints = []
    for entry in text.replace(";", ",").split(","):
        entry = entry.strip()
        if not entry:
            continue
        host, sep, port = entry.rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise RenderFailed(f"manual host '{entry}' is not host:port")
        endpoints.append((host.strip("[]"), int(port)))
    return endpoints


def find_slaves(engine, context_settings, prefs) -> list[tuple[str, int]]:
    """Manual hosts, then slaves found on the LAN; local slaves if none (or if asked to)."""
    state = session.current()
    endpoints = parse_hosts(context_settings.manual_hosts)
    if context_settings.use_zeroconf:
        engine.update_stats("", "KD Trace | Looking for slaves on the LAN")
        browser = state.browser()
        deadline = time.monotonic() + context_settings.discovery_seconds
        while time.monotonic() < deadline and not engine.test_break():
            if browser.slaves() and not endpoints:
                # Give the others that answer a moment too, then go.
                deadline = min(deadline, time.monotonic() + 0.3)
            time.sleep(POLL_SECONDS)
        endpoints += [(s.host, s.port) for s in browser.slaves() if (s.host, s.port) not in endpoints]
    if (not endpoints or context_settings.use_local_slaves_always) and context_settings.local_slaves:
        engine.update_stats("", f"KD Trace | Starting {context_settings.local_slaves} local slave(s)")
        endpoints += state.local_slaves.ensure(context_settings.local_slaves, prefs.slave_python,
                                               prefs.slave_device)
    if not endpoints:
        raise RenderFailed("no slave is reachable: none answered on the LAN, no host is listed "
                           "and local slaves are off")
    return endpoints


def render(engine, depsgraph):
    settings = depsgraph.scene.kdtrace
    prefs = preferences(engine_context())
    started = time.perf_counter()
    try:
        engine.update_stats("", "KD Trace | Exporting scene")
        geometry, view, _ = export_view(depsgraph)
        geometry.validate(len(view.shading.materials))
        exported = time.perf_counter()

        def tree_progress(fraction, message):
            engine.update_progress(0.5 * fraction)
            engine.update_stats("", f"KD Trace | Building kd-tree: {message}")

        engine.update_stats("", f"KD Trace | Building kd-tree over {geometry.triangle_count:,} triangles")
        tree, built = session.current().trees.get(geometry, tree_progress)
        tree_done = time.perf_counter()
        if engine.test_break():
            return
        endpoints = find_slaves(engine, settings, prefs)
        with Master(endpoints) as master:
            master.connect()
            engine.update_stats("", f"KD Trace | Sending scene to {len(master.slaves)} slave(s)")
            master.load_scene(geometry, tree)
            for problem in master.errors:
                engine.report({"WARNING"}, f"KD Trace: {problem}")
            job = master.render(view, settings.tile_size)
            per_slave = _receive_tiles(engine, job, view)
            for problem in job.errors:
                engine.report({"WARNING"}, f"KD Trace: {problem}")
        finished = time.perf_counter()
    except (SceneError, RenderFailed, MasterError, OSError, RuntimeError) as error:
        engine.report({"ERROR"}, f"KD Trace: {error}")
        engine.error_set(f"KD Trace: {error}")
        return
    tree_note = "built" if built else "reused"
    summary = (f"export {exported - started:.2f} s, kd-tree {tree_note} {tree_done - exported:.2f} s "
               f"({tree.stats['nodes']:,} nodes), render {finished - tree_done:.2f} s; tiles: "
               + ", ".join(f"{name} {count}" for name, count in sorted(per_slave.items())))
    session.current().last_render = {
        "export_seconds": exported - started, "tree_seconds": tree_done - exported,
        "tree_built": built, "tree_stats": dict(tree.stats), "render_seconds": finished - tree_done,
        "triangles": geometry.triangle_count, "tiles_per_slave": per_slave}
    engine.update_stats("", f"KD Trace | Done: {summary}")
    engine.report({"INFO"}, f"KD Trace: {summary}")


def engine_context():
    import bpy
    return bpy.context


def _receive_tiles(engine, job, view) -> dict:
    """Write tiles into Blender's result as they arrive; stop promptly on Esc."""
    per_slave: dict[str, int] = {}
    done, total = 0, len(job.tiles)
    while not job.finished:
        if engine.test_break():
            job.cancel()
            return per_slave
        tile = job.next_result(POLL_SECONDS)
        if tile is None:
            continue
        _write_tile(engine, view, tile)
        done += 1
        per_slave[tile.slave_name] = per_slave.get(tile.slave_name, 0) + 1
        engine.update_progress(0.5 + 0.5 * done / total)
        engine.update_stats("", f"KD Trace | Tile {done}/{total} from {tile.slave_name}")
    if job.error:
        raise RenderFailed(job.error)
    return per_slave


def _write_tile(engine, view, tile):
    """Copy one tile's passes into Blender's result (bottom-left origin, relative to the border)."""
    x0, y0, x1, y1 = view.region
    left = tile.x - x0
    bottom = (y1 - y0) - (tile.y - y0 + tile.h)
    result = engine.begin_result(left, bottom, tile.w, tile.h)
    passes = result.layers[0].passes
    arrays = {"Combined": tile.passes["combined"], "Depth": tile.passes["depth"],
              "Normal": tile.passes["normal"]}
    for name, array in arrays.items():
        blender_pass = passes.find(name)
        if blender_pass >= 0:
            passes[blender_pass].rect.foreach_set(np.ascontiguousarray(array[::-1]).ravel())
    engine.end_result(result)
