"""The 3D viewport's Rendered mode with KD Trace (docs/viewport.md): the engine's view_update
and view_draw, as Blender's RenderEngine API documents them. A ViewportSession
(core/frame/viewport.py) renders through the same slaves and pipeline as F12 on its own thread;
here, on Blender's main thread, view_update exports the scene when it changed, view_draw hands
the session a new view when the user navigates, and draws the newest image: a float texture
through the display-space shader, and asks for another redraw while the session refines."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..core.frame.viewport import DENOISE as VIEWPORT_DENOISE, ViewportSession
from ..core.scene.model import Camera
from . import session
from .camera import projection_ndc
from .export import export_instanced_view
from .properties import preferences
from .render import frame_options


class ViewportState:
    """What an engine instance keeps across redraws: its session and the view it was given."""

    def __init__(self, viewport: ViewportSession):
        self.viewport = viewport
        self.view = None            # the View of the last update
        self.key = None             # what view_draw compares to see a navigation


def view_update(engine, context, depsgraph) -> None:
    """The scene changed (or Rendered mode began): export it with the viewport's camera."""
    import bpy
    state = getattr(engine, "kdtrace_viewport", None)
    settings = depsgraph.scene.kdtrace
    options = frame_options(settings, preferences(bpy.context), depsgraph.view_layer)
    if state is None:
        state = engine.kdtrace_viewport = ViewportState(ViewportSession(
            session.current(), options))
    # The panel's settings as they are now (a change of them is a change of the scene).
    viewport = state.viewport
    viewport.options = options
    viewport.samples_per_axis = settings.viewport_samples_per_axis
    viewport.time_limit = settings.viewport_time_limit
    viewport.denoise = dataclasses.replace(VIEWPORT_DENOISE, enabled=settings.viewport_denoise)
    camera, width, height, key = viewport_camera(context, depsgraph.scene)
    # Every object an instance: an object moved changes only the instances the slaves get.
    exported, view, info = export_instanced_view(depsgraph, every_object=True,
                                                 viewport=(camera, width, height))
    state.view, state.key = view, key
    state.viewport.update(view, exported, info["warnings"])


def view_draw(engine, context, depsgraph) -> None:
    """Draw the newest image; a navigated view starts a new frame (no export: the scene did
    not change)."""
    state = getattr(engine, "kdtrace_viewport", None)
    if state is None:
        return
    camera, width, height, key = viewport_camera(context, depsgraph.scene)
    if key != state.key and state.view is not None:
        state.view = dataclasses.replace(state.view, camera=camera, width=width, height=height,
                                         region=(0, 0, width, height))
        state.key = key
        state.viewport.update(state.view)
    shown = state.viewport.image()
    if shown is not None:
        draw_pixels(engine, depsgraph.scene, shown.pixels, width, height)
    if not state.viewport.done():
        engine.tag_redraw()         # called again until the session has refined the view


def viewport_camera(context, scene) -> tuple:
    """(Camera, width, height, key) of the 3D viewport being drawn: its view and projection
    matrices (through the scene camera in camera view), its clipping, its size in pixels; the
    key changes when any of them does."""
    region, region_data, space = context.region, context.region_data, context.space_data
    width, height = max(1, region.width), max(1, region.height)
    view_matrix = np.array(region_data.view_matrix, np.float64)
    projection = np.array(region_data.window_matrix, np.float64)
    kind = "PERSP" if region_data.is_perspective else "ORTHO"
    if region_data.view_perspective == "CAMERA" and scene.camera is not None:
        clip_start, clip_end = scene.camera.data.clip_start, scene.camera.data.clip_end
    else:
        clip_start, clip_end = space.clip_start, space.clip_end
    return (camera_from_matrices(kind, view_matrix, projection, clip_start, clip_end),
            width, height, (view_matrix.tobytes(), projection.tobytes(), width, height))


def camera_from_matrices(kind, view_matrix, projection, clip_start, clip_end) -> Camera:
    """The Camera of a view matrix (world -> view) and an OpenGL projection: perspective rays
    from the eye; orthographic ones start half the clip range behind the view plane (Blender's
    orthographic viewport clips at +-clip_end / 2 around it, as Cycles renders it)."""
    to_world = np.linalg.inv(view_matrix)
    scale, offset = projection_ndc(kind, projection)
    if kind == "ORTHO":
        to_world = to_world @ np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, clip_end / 2],
                                        [0, 0, 0, 1]], np.float64)
        clip_start = 0.0
    return Camera(kind, to_world, scale, offset, clip_start, clip_end)


def draw_pixels(engine, scene, pixels: np.ndarray, width: int, height: int) -> None:
    """Draw `pixels` ((h, w, 4) float32 RGBA, top row first, scene linear) over the region
    of `width` x `height` (stretched: the first image of a change has fewer pixels) through the
    display-space shader, which applies the scene's view transform (as the API's example
    engine draws)."""
    import gpu
    from gpu_extras.presets import draw_texture_2d
    h, w = pixels.shape[:2]
    # Half floats hold what a display shows; beyond their range a pixel would be inf.
    rows = np.clip(np.ascontiguousarray(pixels[::-1], np.float32), -65504.0, 65504.0)
    texture = gpu.types.GPUTexture((w, h), format="RGBA16F",
                                   data=gpu.types.Buffer("FLOAT", w * h * 4, rows.ravel()))
    gpu.state.blend_set("ALPHA_PREMULT")
    engine.bind_display_space_shader(scene)
    draw_texture_2d(texture, (0, 0), width, height)
    engine.unbind_display_space_shader()
    gpu.state.blend_set("NONE")
