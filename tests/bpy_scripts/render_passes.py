"""Render the test scene with two local slaves and with one, to multilayer EXR; report which
passes the compositor's Render Layers node offers and what the add-on recorded."""
import bpy
import numpy as np

from blender_setup import arguments, build_test_scene, exr_passes, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
scene = build_test_scene(args["width"], args["height"])
scene.render.engine = "KDTRACE"
view_layer = bpy.context.view_layer
view_layer.use_pass_z = True
view_layer.use_pass_normal = True
scene.kdtrace.use_zeroconf = False
scene.kdtrace.tile_size = args["tile_size"]
settings = scene.render.image_settings
settings.media_type = "MULTI_LAYER_IMAGE"
settings.file_format = "OPEN_EXR_MULTILAYER"
settings.color_depth = "32"

reports = {}
for slaves in (2, 1):
    scene.kdtrace.local_slaves = slaves
    scene.render.filepath = f"{args['out']}/slaves{slaves}.exr"
    bpy.ops.render.render(write_still=True)
    state = addon.addon.session.current()
    reports[slaves] = dict(state.last_render)
    # Whether the scene's triangles were put in spatial order (ordering again moves nothing).
    spatial_order = addon.core.scene.spatial_order.spatial_order
    reports[slaves]["triangles_in_spatial_order"] = (
        spatial_order(state.last_scene[1].geometry)[1] is None
        and any(order is not None for order in state.mesh_orders))
    for name, channels in exr_passes(scene.render.filepath).items():
        np.save(f"{args['out']}/slaves{slaves}-{name}.npy", np.stack(list(channels.values()), -1))

tree = bpy.data.node_groups.new("compositor", "CompositorNodeTree")
scene.compositing_node_group = tree
node = tree.nodes.new("CompositorNodeRLayers")
write_result(result_path, {"reports": reports,
                           "compositor_outputs": [o.name for o in node.outputs if o.enabled]})
