"""The render engine Blender lists as "KD Trace". A thin shell: F12 is render.py, the
viewport's Rendered mode viewport.py."""
import bpy

from . import render, viewport


class KDTraceRenderEngine(bpy.types.RenderEngine):
    bl_idname = "KDTRACE"
    bl_label = "KD Trace"
    bl_use_preview = False
    bl_use_postprocess = True

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.kdtrace_viewport = None    # viewport.ViewportState, from the first view_update

    def __del__(self):
        # Rendered mode left or the viewport closed.
        try:
            state = self.kdtrace_viewport
        except (ReferenceError, AttributeError):   # at exit: Blender freed the engine first
            return
        if state is not None:
            state.viewport.close()

    def render(self, depsgraph):
        render.render(self, depsgraph)

    def view_update(self, context, depsgraph):
        viewport.view_update(self, context, depsgraph)

    def view_draw(self, context, depsgraph):
        viewport.view_draw(self, context, depsgraph)

    def update_render_passes(self, scene=None, renderlayer=None):
        # Declared so the compositor sees the passes the slaves fill.
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        # Each tile filled with the colour of the slave that rendered it.
        self.register_pass(scene, renderlayer, "Slave", 4, "RGBA", "COLOR")
        for _, name, channels, ids, kind, _ in render.view_layer_passes(renderlayer):
            self.register_pass(scene, renderlayer, name, channels, ids, kind)
        if scene.kdtrace.use_denoising:     # as Cycles: the image before denoising
            self.register_pass(scene, renderlayer, *render.NOISY_IMAGE)


classes = (KDTraceRenderEngine,)
