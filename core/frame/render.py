"""One frame through the slaves, for any host: build (or reuse) the kd-trees of the exported
meshes, assemble the frame's scene, find slaves, hand out tiles and pass each tile to the host
as it arrives. Runs on the host's thread (Blender's render thread for F12); all socket work
happens on the master's threads and comes back through job.next_results()."""
from __future__ import annotations

import time

from ..net.master import LoadCancelled, Master, MasterError
from ..net.protocol import ProtocolError
from ..net.slave_colors import slave_color
from ..net.trust import AllowList, AuthError
from ..scene.model import SceneError
from ..scene.scene import memory_report, memory_summary
from .denoising import denoise_frame, with_guides
from .options import FrameOptions
from .session import FrameSession

POLL_SECONDS = 0.05  # how often the frame checks for a cancel while waiting for tiles
SETTLE_SECONDS = 0.3  # after the first slave answers a young browser, for the others to answer


class FrameError(Exception):
    """A problem the user must see as a message, not a traceback."""


class FrameCancelled(Exception):
    """The host cancelled during a long step (kd-tree build, starting slaves)."""


# What ends a frame with a message for the user (anything else is a defect).
FRAME_ERRORS = (FrameError, SceneError, MasterError, ProtocolError, AuthError, OSError,
                RuntimeError)


class FrameHost:
    """What a frame asks of whoever shows it: the F12 engine (addon/render.py), a viewport, a
    test's scripted host. Every method may be left as it is here."""

    def cancelled(self) -> bool:
        """Polled often: True stops the frame (Esc)."""
        return False

    def status(self, message: str) -> None:
        """What the frame is doing now, in a few words."""

    def progress(self, fraction: float) -> None:
        """0 to 1: kd-trees up to 0.5, tiles after."""

    def report(self, level: str, message: str) -> None:
        """A message for the user: level "INFO" or "WARNING"."""

    def begin(self, job) -> None:
        """Tiles are about to arrive: job.view.region is the image, job.image its passes."""

    def tile(self, tile) -> None:
        """A tile arrived (core.net.master.TileResult); its pixels are in job.image already."""

    def denoised(self, job, noisy) -> None:
        """The master denoised job.image's Combined pass in place (after the last tile, before
        end); `noisy` is the image before (Blender's Noisy Image pass)."""

    def end(self, job) -> None:
        """The frame is over (finished, cancelled or failed): job.image is the image."""


def render_frame(session: FrameSession, exported, view, options: FrameOptions, host: FrameHost,
                 warnings=(), started: float | None = None) -> dict | None:
    """Render `view` of `exported` (core.frame.exported.InstancedExport: meshes, instances and
    textures) through the slaves. `warnings`: the export's, reported first. `started`: the
    time.perf_counter() at which the host began the frame (before its export: the report's
    export step counts from there). Returns the frame's report (also session.last_render),
    None when cancelled; raises FRAME_ERRORS."""
    started = time.perf_counter() if started is None else started
    steps = Steps(started)
    session.last_warnings = list(warnings)
    for warning in warnings:
        host.report("WARNING", f"KD Trace: {warning}")
    try:
        if options.use_zeroconf:
            session.browser()   # if not running yet: it looks while the kd-trees build
        scene, trees, sources, hashes_reused = frame_scene(session, exported, options, host,
                                                           steps)
        exported_at = steps.seconds["export"] + started
        scene.check_view(view)
        memory = memory_report(scene)
        tree_done = steps.mark("view check")
        if host.cancelled():
            return None
        with master_for(session, options, host) as master:
            legend = session.legend
            steps.mark("find slaves and connect")
            host.status(f"Sending scene to {len(master.slaves)} slave(s)")
            master.load_scene(scene, cancelled=host.cancelled)
            steps.mark("scene query")
            for problem in master.errors:
                host.report("WARNING", f"KD Trace: {problem}")
            job = master.render(view, **with_guides(options.job_options(), options.denoise))
            host.begin(job)
            steps.mark("frame start")
            try:
                _receive_tiles(session, host, job, legend, master,
                               local_takeover(session, options, host, master), steps)
                steps.mark("other tiles")
                denoised = denoise_frame(session.denoiser, options.denoise, job, host)
                steps.mark("denoise")
            finally:
                host.end(job)
                steps.mark("image")
            for problem in job.errors:
                host.report("WARNING", f"KD Trace: {problem}")
            session.unapproved.update(master.unapproved)
            if job.error and not job.cancelled:
                raise FrameError(job.error)
            uploaded_to, scene_bytes = list(master.uploaded_to), dict(master.scene_bytes)
        finished = steps.mark("close")
    except (FrameCancelled, LoadCancelled):
        return None
    per_slave = legend.tiles_per_slave()
    built = "built" in sources
    session.last_render = {
        "export_seconds": exported_at - started, "tree_seconds": tree_done - exported_at,
        "tree_built": built, "tree_sources": sources, "tree_stats": dict(trees[0].stats),
        "tree_nodes": sum(t.stats["nodes"] for t in trees),
        "tree_bytes": sum(t.nbytes for t in trees),
        "render_seconds": finished - tree_done,
        "mesh_hashes_reused": hashes_reused,
        "steps": steps.seconds, "tile_render_ms": legend.render_ms(),
        "triangles": memory["triangles_referenced"], "memory": memory,
        "tiles_per_slave": per_slave,
        "slave_colors": {name: slave_color(name) for name in per_slave},
        "uploaded_to": uploaded_to, "scene_bytes": scene_bytes, "cancelled": job.cancelled,
        "local_reason": session.local_reason, **denoised,
        "joined_during_frame": [f"{host}:{port}" for host, port in session.joined]}
    return session.last_render


def frame_scene(session, exported, options, host, steps) -> tuple:
    """The frame's Scene from the export: each mesh in spatial order, its kd-tree from the
    cache or built, and the scene assembled (FrameSession.frame_scene: the last scene placed
    anew where only instances moved). Returns (scene, trees, where each tree came from, meshes
    whose hash was reused); `steps` marks "export", "kd-tree cache" and "scene"."""
    meshes, hashes_reused = session.order_meshes(exported.meshes)
    steps.mark("export")
    trees, sources = _trees(session, meshes, options, host)
    steps.mark("kd-tree cache")
    scene = session.frame_scene(meshes, trees, exported, (
        options.tree_mode, tuple(sorted(options.tree_settings.items()))))
    steps.mark("scene")
    return scene, trees, sources, hashes_reused


def master_for(session, options, host) -> Master:
    """A Master connected to the slaves of this frame: those found (find_slaves) that the user
    approved, the local slaves started for this master, or (with the farm secret) those that
    prove it (core/net/trust.py). The session's legend follows it; slaves refused as not
    approved reach the panel, which offers Approve and Pair. The caller closes it."""
    identity = session.master_identity(options.identity_folder)
    approved = AllowList(options.approved_slaves)
    endpoints = find_slaves(session, options, host, identity, approved)
    for local_id in session.local_slaves.ids():
        approved.add(local_id)
    master = Master(endpoints, secret=options.secret, identity=identity,
                    approved_slaves=approved)
    session.start_legend(master)   # the panel follows each slave from here on
    try:
        master.connect()
    except BaseException:
        master.close()
        raise
    finally:
        session.unapproved.update(master.unapproved)
    return master


def summary(report: dict) -> str:
    """A frame's report (render_frame's) in one line for the user: where the time went, who
    rendered what."""
    trees, stats = report["tree_sources"], report["tree_stats"]
    how = "built" if report["tree_built"] else "read from disk" if "disk" in trees else "reused"
    per_slave = report["tiles_per_slave"]
    return (f"export {report['export_seconds']:.2f} s, kd-tree {how} "
            f"{report['tree_seconds']:.2f} s ({stats['mode']}: {report['tree_nodes']:,} nodes, "
            f"{report['tree_bytes'] / 1e6:.1f} MB; {stats['builder']} builder on "
            f"{stats['device']}); {memory_summary(report['memory'])}; render "
            f"{report['render_seconds']:.2f} s"
            + (f" (denoised in {report['denoise_seconds']:.2f} s)" if report.get("denoised")
               else "") + "; tiles: "
            + ", ".join(f"{name} {count}" for name, count in sorted(per_slave.items()))
            + (f"; local slaves started: {report['local_reason']}" if report["local_reason"] else "")
            + ("; joined during the frame: " + ", ".join(report["joined_during_frame"])
               if report["joined_during_frame"] else ""))


def _trees(session, meshes, options, host) -> tuple[list, list]:
    """A compact kd-tree per mesh (docs/instances.md), each cached by its mesh's content, and
    where each came from ("memory", "disk", "built")."""
    stored = sum(m.triangle_count for m in meshes)
    host.status(f"Building kd-trees over {stored:,} triangles ({len(meshes)} mesh(es))")
    try:
        session.trees.use_disk(options.tree_folder, options.tree_cache_mib)
    except OSError as error:
        session.trees.use_disk(None, 0)
        host.report("WARNING", f"KD Trace: no kd-tree cache on disk: {error}")
    trees, sources, done = [], [], 0.0
    for mesh in meshes:
        share = mesh.triangle_count / max(stored, 1)     # of the progress bar

        def progress(fraction, message, done=done, share=share):
            if host.cancelled():
                raise FrameCancelled
            host.progress(0.5 * (done + share * fraction))
            host.status(f"Building kd-tree: {message}")
        tree, source = session.trees.get(mesh, options.tree_mode, options.tree_settings,
                                         progress, device=options.slave_device)
        trees.append(tree)
        sources.append(source)
        done += share
    if session.trees.disk_problem:
        host.report("WARNING", f"KD Trace: {session.trees.disk_problem}")
    return trees, sources


def find_slaves(session, options, host, identity, approved) -> list[tuple[str, int]]:
    """Listed hosts and every slave the LAN browser knows that this master may use (approved,
    or any with the farm secret: session.trusted_lan_endpoints); local slaves only when no
    other slave is known (or when asked to always use them). The browser runs in the
    background (the add-on starts it while KD Trace is the engine), so slaves seen before the
    frame are used at once: only a browser younger than the discovery time is waited for,
    until a slave answers."""
    endpoints = list(options.hosts)
    has_secret = options.secret is not None

    def lan():
        return session.trusted_lan_endpoints(approved, has_secret)
    if options.use_zeroconf:
        session.browser()
        settle_until = None
        while session.browsing_seconds() < options.discovery_seconds and not host.cancelled():
            if endpoints or lan():
                # Give the others that answer a moment too, then go.
                settle_until = settle_until or time.monotonic() + SETTLE_SECONDS
                if time.monotonic() >= settle_until:
                    break
            host.status("Looking for slaves on the LAN")
            time.sleep(POLL_SECONDS)
        endpoints += [e for e in lan() if e not in endpoints]
    session.local_reason = local_slaves_reason(options, endpoints, session.browsing_seconds())
    session.joined = []
    if session.local_reason:
        host.status(f"Starting {options.local_slaves} local slave(s): {session.local_reason}")
        endpoints += session.local_slaves.ensure(options.local_slaves, options.slave_python,
                                                 options.slave_device, identity.id,
                                                 cancelled=host.cancelled)
    if not endpoints:
        waiting = (f"; {len(session.unapproved)} slave(s) on the LAN wait for approval in the "
                   f"Slaves panel" if session.unapproved else "")
        raise FrameError("no slave is reachable: none answered on the LAN, no host is listed "
                         "and local slaves are off" + waiting)
    return endpoints


def local_slaves_reason(options, known: list, browsed_seconds: float) -> str:
    """Why this frame starts local slaves, for the panel and the report ("": it does not)."""
    if not options.local_slaves:
        return ""
    if options.local_slaves_always:
        return "Always Use Local Slaves is on"
    if known:
        return ""
    if options.use_zeroconf:
        return f"no slave answered on the LAN in {browsed_seconds:.1f} s and no host is listed"
    return "LAN discovery is off and no host is listed"


def join_new_lan_slaves(session, master) -> None:
    """A slave the LAN browser sees during a frame joins it if this master may use it
    (Master.join connects, checks its identity, uploads and hands it tiles on the master's
    threads)."""
    for endpoint in session.trusted_lan_endpoints(master.approved, master.secret is not None):
        if endpoint not in master.endpoints:
            session.joined.append(endpoint)
            master.join(*endpoint)


def local_takeover(session, options, host, master):
    """What to do when every slave is lost and none could be reconnected: once, local slaves
    (where enabled) join the frame. The returned function says False when nothing is left."""
    tried = []

    def take_over() -> bool:
        if tried or not options.local_slaves:
            return False
        tried.append(True)
        host.status(f"Every slave lost: starting {options.local_slaves} local slave(s)")
        try:
            endpoints = session.local_slaves.ensure(
                options.local_slaves, options.slave_python, options.slave_device,
                master.identity.id, cancelled=host.cancelled)
        except RuntimeError as error:
            host.report("WARNING", f"KD Trace: local slaves did not start: {error}")
            return False
        for local_id in session.local_slaves.ids():
            master.approved.add(local_id)       # started by this master: trusted
        for endpoint in endpoints:
            master.join(*endpoint)
        return True

    return take_over


def _receive_tiles(session, host, job, legend, master, take_over, steps):
    """Pass tiles to the host as they arrive; stop promptly on a cancel. `steps` marks the
    first tile."""
    done, total = 0, len(job.tiles)
    while not job.finished:
        if host.cancelled():
            job.cancel()
            return
        if job.stranded and not take_over():
            job.give_up()    # its error names every slave and why it was lost
        tiles = job.next_results(POLL_SECONDS)
        if not tiles:
            join_new_lan_slaves(session, master)
            continue
        for tile in tiles:
            host.tile(tile)
            legend.tile_done(tile)
        if done == 0:
            steps.mark("first tile")
        done += len(tiles)
        host.progress(0.5 + 0.5 * done / total)
        host.status(f"Tile {done}/{total} from {tile.slave_name}")


class Steps:
    """Wall seconds of a frame's steps, each from the previous mark (the report's breakdown:
    session.last_render["steps"], in order)."""

    def __init__(self, started: float):
        self.seconds: dict = {}
        self._last = started

    def mark(self, name: str) -> float:
        now = time.perf_counter()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - self._last
        self._last = now
        return now
