"""The render engine Blender lists as "KD Trace". A thin shell: the work is in render.py."""
import bpy

from . import render


class KDTraceRenderEngine(bpy.types.RenderEngine):
    bl_idname = "KDTRACE"
    bl_label = "KD Trace"
    bl_use_preview = False
    bl_use_postprocess = True

    def render(self, depsgraph):
        render.render(self, depsgraph)

    def update_render_passes(self, scene=None, renderlayer=None):
        # Declared so the compositor sees the passes the slaves fill.
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        # Each tile filled with the colour of the slave that rendered it.
        self.register_pass(scene, renderlayer, "Slave", 4, "RGBA", "COLOR")
        if renderlayer.use_pass_z:
            self.register_pass(scene, renderlayer, "Depth", 1, "Z", "VALUE")
        if renderlayer.use_pass_normal:
            self.register_pass(scene, renderlayer, "Normal", 3, "XYZ", "VECTOR")


classes = (KDTraceRenderEngine,)
