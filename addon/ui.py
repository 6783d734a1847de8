"""The KD Trace panel in Render Properties. draw() only reads state; it never touches the network."""
import bpy


class KDTracePanel:
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    COMPAT_ENGINES = {"KDTRACE"}

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES


class RENDER_PT_kdtrace(KDTracePanel, bpy.types.Panel):
    bl_label = "KD Trace"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        settings = context.scene.kdtrace
        layout.prop(settings, "tile_size")


class RENDER_PT_kdtrace_slaves(KDTracePanel, bpy.types.Panel):
    bl_label = "Slaves"
    bl_parent_id = "RENDER_PT_kdtrace"

    def draw(self, context):
        from . import session
        layout = self.layout
        settings = context.scene.kdtrace
        col = layout.column()
        col.use_property_split = True
        col.prop(settings, "use_zeroconf")
        sub = col.column()
        sub.active = settings.use_zeroconf
        sub.prop(settings, "discovery_seconds")
        col.prop(settings, "manual_hosts")
        col.prop(settings, "local_slaves")
        col.prop(settings, "use_local_slaves_always")
        box = layout.box()
        found = session.current().discovered_slaves()
        if not found:
            box.label(text="No slave found on the LAN yet", icon="INFO")
        for slave in found:
            box.label(text=f"{slave.name}  {slave.host}:{slave.port}  {slave.properties.get('device', '')}",
                      icon="NETWORK_DRIVE")
        local = session.current().local_slaves.pids()
        if local:
            box.label(text=f"{len(local)} local slave(s) running", icon="CONSOLE")


classes = (RENDER_PT_kdtrace, RENDER_PT_kdtrace_slaves)

# Blender's own panels that show what KD Trace renders (camera, lights, material base colour,
# world colour). Panels for Blender's generic engine list "BLENDER_RENDER"; the material and
# world surface panels are EEVEE's.
EXTRA_PANELS = ("EEVEE_MATERIAL_PT_context_material", "EEVEE_MATERIAL_PT_surface",
                "EEVEE_WORLD_PT_surface")
SKIPPED_PANELS = ("VIEWLAYER_PT_filter", "VIEWLAYER_PT_layer_passes")


def blender_panels():
    for panel in bpy.types.Panel.__subclasses__():
        engines = getattr(panel, "COMPAT_ENGINES", None)
        if engines is None or panel.__name__ in SKIPPED_PANELS:
            continue
        if "BLENDER_RENDER" in engines or panel.__name__ in EXTRA_PANELS:
            yield panel


def register():
    for panel in blender_panels():
        panel.COMPAT_ENGINES.add("KDTRACE")


def unregister():
    for panel in blender_panels():
        panel.COMPAT_ENGINES.discard("KDTRACE")
