"""The viewport's Blender side where it can run without a window (docs/viewport.md): the
camera the add-on makes of a viewport's matrices against the scene camera's export; and the
add-on's drawing code (addon/viewport.py draw_pixels) drawing a ViewportSession's image of the
scene into an RGBA32F offscreen, read back. Blender never calls view_update/view_draw in
background mode, and drawing needs the GPU backend that a first Workbench render starts (Mesa's
llvmpipe through EGL) and a RenderEngine's render() for the display-space shader: the draw runs
inside KD Trace's render()."""
import time

import bpy
import gpu
import numpy as np
from mathutils import Matrix

from blender_setup import arguments, build_test_scene, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
package = addon.addon
from importlib import import_module
core = import_module(addon.__name__ + ".core.frame.viewport")
options_module = import_module(addon.__name__ + ".core.frame.options")
width, height = args["width"], args["height"]
scene = build_test_scene(width, height)
scene.view_settings.view_transform = "Standard"
scene.view_settings.look = "None"
depsgraph = bpy.context.evaluated_depsgraph_get()

# 1. The viewport camera from matrices, seen through the scene camera, is the F12 camera.
camera = scene.camera.evaluated_get(depsgraph)
view_matrix = np.array(camera.matrix_world.normalized().inverted(), np.float64)
projection = np.array(camera.calc_matrix_camera(depsgraph, x=width, y=height), np.float64)
ours = package.viewport.camera_from_matrices("PERSP", view_matrix, projection,
                                             camera.data.clip_start, camera.data.clip_end)
_, f12_view, _ = package.export.export_instanced_view(depsgraph)
camera_error = float(max(np.abs(ours.to_world - f12_view.camera.to_world).max(),
                         np.abs(np.subtract(ours.ndc_scale, f12_view.camera.ndc_scale)).max(),
                         np.abs(np.subtract(ours.ndc_offset, f12_view.camera.ndc_offset)).max()))

# 2. A session's image of the scene, as view_update would start it.
exported, view, info = package.export.export_instanced_view(
    depsgraph, viewport=(ours, width, height))
session = core.ViewportSession(package.session.current(), options_module.FrameOptions(
    use_zeroconf=False, local_slaves=1, tile_size=16), samples_per_axis=1)
session.update(view, exported, info["warnings"])
deadline = time.monotonic() + 120
while not session.done() and time.monotonic() < deadline:
    time.sleep(0.02)
shown = session.image()
session.close()
np.save(args["out"] + "/session.npy", shown.pixels)

# 3. The GPU backend up (a Workbench render), then the drawing code inside KD Trace's render().
scene.render.engine = "BLENDER_WORKBENCH"
scene.render.resolution_x = scene.render.resolution_y = 4
bpy.ops.render.render()
scene.render.resolution_x, scene.render.resolution_y = width, height
drawn = {}


def draw_in_render(engine, depsgraph):
    offscreen = gpu.types.GPUOffScreen(width, height, format="RGBA32F")
    with offscreen.bind():
        framebuffer = gpu.state.active_framebuffer_get()
        framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0))
        with gpu.matrix.push_pop():
            gpu.matrix.load_matrix(Matrix.Identity(4))
            gpu.matrix.load_projection_matrix(Matrix(((2 / width, 0, 0, -1), (0, 2 / height, 0, -1),
                                                      (0, 0, 1, 0), (0, 0, 0, 1))))
            package.viewport.draw_pixels(engine, depsgraph.scene, shown.pixels, width, height)
        buffer = framebuffer.read_color(0, 0, width, height, 4, 0, "FLOAT")
    buffer.dimensions = width * height * 4
    drawn["pixels"] = np.array(buffer, np.float32).reshape(height, width, 4)[::-1]
    offscreen.free()


package.render.render = draw_in_render          # KD Trace's render() draws, nothing else
scene.render.engine = "KDTRACE"
bpy.ops.render.render()
np.save(args["out"] + "/drawn.npy", drawn["pixels"])
write_result(result_path, {"camera_error": camera_error, "epoch": shown.epoch,
                           "final": shown.final, "warnings": info["warnings"]})
