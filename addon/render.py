"""One F12: export the evaluated scene, turn the panel's settings into core.frame's
FrameOptions and render the frame through the slaves (core/frame/render.py), with Blender's
engine as the host: each tile is shown as it arrives, framed in its slave's colour. Runs on
Blender's render thread; all socket work happens on the master's threads."""
from __future__ import annotations

import time
import traceback

import numpy as np

from ..core.accel.compact import user_settings
from ..core.frame.denoising import DenoiseSettings
from ..core.frame.options import FrameOptions
from ..core.frame.render import FRAME_ERRORS, FrameError, FrameHost, render_frame, summary
from ..core.net.slave_colors import slave_color
from ..core.net.trust import AuthError, load_secret
from . import session
from .export import export_instanced_view
from .properties import approved_ids, identity_folder, preferences, tree_folder

FRAME_PIXELS = 2     # width of the slave-coloured frame drawn around tiles while rendering


def render(engine, depsgraph):
    import bpy
    started = time.perf_counter()
    state = session.current()
    try:
        options = frame_options(depsgraph.scene.kdtrace, preferences(bpy.context),
                                depsgraph.view_layer)
        if options.use_zeroconf:
            state.browser()   # if not running yet: it looks while the scene exports and builds
        engine.update_stats("", "KD Trace | Exporting scene")
        exported, view, info = export_instanced_view(depsgraph,
                                                     every_object=bool(engine.is_animation))
        report = render_frame(state, exported, view, options, EngineHost(engine),
                              info["warnings"], started)
    except FRAME_ERRORS as error:
        _fail(engine, str(error))
        return
    except Exception as error:      # a defect: the render ends with a report, Blender lives on
        traceback.print_exc()
        _fail(engine, f"internal error, {type(error).__name__}: {error} (the traceback is in "
                      "the system console; please report it)")
        return
    if report is not None:
        line = summary(report)
        engine.update_stats("", f"KD Trace | Done: {line}")
        engine.report({"INFO"}, f"KD Trace: {line}")


def _fail(engine, message: str) -> None:
    engine.report({"ERROR"}, f"KD Trace: {message}")
    engine.error_set(f"KD Trace: {message}")


# The passes a view layer may show beyond Combined, as Cycles names them: (the slaves' pass,
# Blender's name, channels, channel ids, type, what switches it on: a property of the view layer,
# or of its KD Trace settings). Noisy Image is the master's (with denoising on).
VIEW_LAYER_PASSES = (
    ("depth", "Depth", 1, "Z", "VALUE", "use_pass_z"),
    ("mist", "Mist", 1, "Z", "VALUE", "use_pass_mist"),
    ("normal", "Normal", 3, "XYZ", "VECTOR", "use_pass_normal"),
    ("denoising_normal", "Denoising Normal", 3, "XYZ", "VECTOR", "kdtrace.denoising_store_passes"),
    ("albedo", "Denoising Albedo", 3, "RGB", "COLOR", "kdtrace.denoising_store_passes"),
    ("diffuse_color", "Diffuse Color", 3, "RGB", "COLOR", "use_pass_diffuse_color"),
    ("glossy_color", "Glossy Color", 3, "RGB", "COLOR", "use_pass_glossy_color"),
    ("emission", "Emission", 3, "RGB", "COLOR", "use_pass_emit"),
)
NOISY_IMAGE = ("Noisy Image", 4, "RGBA", "COLOR")


def _switched_on(view_layer, path: str) -> bool:
    owner, _, name = path.rpartition(".")
    owner = getattr(view_layer, owner, None) if owner else view_layer
    return bool(getattr(owner, name, False))


def view_layer_passes(view_layer) -> list:
    """The entries of VIEW_LAYER_PASSES the view layer shows."""
    return [entry for entry in VIEW_LAYER_PASSES if _switched_on(view_layer, entry[5])]


def frame_options(settings, prefs, view_layer) -> FrameOptions:
    """The panel's settings (scene.kdtrace), the add-on's preferences and the passes the view
    layer shows (Combined always, the others where enabled) as core.frame's options."""
    passes = ("combined",) + tuple(entry[0] for entry in view_layer_passes(view_layer))
    return FrameOptions(
        tree_mode=settings.kdtree_mode,
        tree_settings=user_settings(settings.kdtree_mode, settings.tau_occu, settings.tau_freq,
                                    settings.refs_per_path),
        tree_folder=tree_folder(prefs), tree_cache_mib=prefs.tree_cache_mib,
        hosts=listed_hosts(settings), use_zeroconf=settings.use_zeroconf,
        discovery_seconds=settings.discovery_seconds, local_slaves=settings.local_slaves,
        local_slaves_always=settings.use_local_slaves_always,
        slave_python=prefs.slave_python, slave_device=prefs.slave_device,
        secret=shared_secret(prefs), approved_slaves=approved_ids(prefs),
        identity_folder=identity_folder(),
        tile_size=settings.tile_size, tiles_in_flight=settings.tiles_in_flight,
        partition=None if settings.tile_partition == "SIZE" else int(settings.tile_partition),
        model=settings.interaction, payload=settings.payload.split("_")[0].lower(),
        compress=settings.payload.endswith("ZLIB"), passes=passes,
        denoise=DenoiseSettings(settings.use_denoising, settings.denoising_prefilter,
                                settings.denoising_quality))


def listed_hosts(settings) -> list[tuple[str, int]]:
    """The enabled entries of the panel's host list, with a message that names a bad one."""
    endpoints = []
    for number, entry in enumerate(settings.hosts, 1):
        if not entry.enabled:
            continue
        host = entry.host.strip().strip("[]")
        if not host or any(c.isspace() for c in host):
            raise FrameError(f"host {number} in the slave list has no valid address: {entry.host!r}")
        endpoints.append((host, entry.port))
    return endpoints


def shared_secret(prefs) -> bytes | None:
    """The farm secret from the preferences' file, else $KDTRACE_SECRET, else None."""
    try:
        return load_secret(bpy_path(prefs.secret_file) if prefs.secret_file else None)
    except AuthError as error:
        raise FrameError(str(error)) from None


def bpy_path(path: str) -> str:
    import bpy
    return bpy.path.abspath(path)


class EngineHost(FrameHost):
    """Blender's RenderEngine as the frame's host: Esc, the status line and progress bar,
    reports, and the render result filled tile by tile (TileCanvas)."""

    def __init__(self, engine):
        self.engine = engine
        self.canvas = None

    def cancelled(self) -> bool:
        return self.engine.test_break()

    def status(self, message: str) -> None:
        self.engine.update_stats("", f"KD Trace | {message}")

    def progress(self, fraction: float) -> None:
        self.engine.update_progress(fraction)

    def report(self, level: str, message: str) -> None:
        self.engine.report({level}, message)

    def begin(self, job) -> None:
        self.canvas = TileCanvas(self.engine, job)

    def tile(self, tile) -> None:
        self.canvas.add(tile)

    def denoised(self, job, noisy) -> None:
        self.canvas.denoised(noisy)

    def end(self, job) -> None:
        self.canvas.finish()


class TileCanvas:
    """The rendered region, filled tile by tile.

    The master writes each tile's passes straight into the job's frame (job.image); the canvas
    adds the Slave pass and, while rendering, shows each tile with a frame in its slave's
    colour. When the frame is over the clean image (and the Slave pass, each tile filled with
    its slave's colour) is written in one go, so the final Combined pass carries no frames.
    """

    BLENDER_PASSES = {"combined": "Combined",
                      **{entry[0]: entry[1] for entry in VIEW_LAYER_PASSES}}

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

    def denoised(self, noisy):
        """The master denoised Combined (in place, job.image); `noisy`: the image before, for
        the Noisy Image pass."""
        self.passes["Noisy Image"] = noisy

    def finish(self):
        """Write the clean region (what arrived; the rest stays empty on a cancel). Without
        denoising, Noisy Image (where the view layer has it) is the image itself."""
        self.passes.setdefault(NOISY_IMAGE[0], self.passes["Combined"])
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
