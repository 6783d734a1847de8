"""The KD Trace panel in Render Properties. draw() only reads state; it never touches the network."""
import bpy


def property_layout(panel, context):
    """A panel's layout with labels beside values (as Cycles' panels), and the scene settings."""
    layout = panel.layout
    layout.use_property_split = True
    return layout, context.scene.kdtrace


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
        layout, settings = property_layout(self, context)
        layout.prop(settings, "tile_partition")
        row = layout.row()
        row.active = settings.tile_partition == "SIZE"
        row.prop(settings, "tile_size")


class RENDER_PT_kdtrace_sampling(KDTracePanel, bpy.types.Panel):
    """As Cycles' Sampling panel: Noise Threshold (adaptive), Max and Min Samples; the
    viewport's Max Samples and Time Limit."""
    bl_label = "Sampling"
    bl_parent_id = "RENDER_PT_kdtrace"

    def draw(self, context):
        layout, settings = property_layout(self, context)
        heading = layout.column(align=True, heading="Noise Threshold")
        row = heading.row(align=True)
        row.prop(settings, "adaptive", text="")
        sub = row.row()
        sub.active = settings.adaptive
        sub.prop(settings, "adaptive_threshold", text="")
        col = layout.column(align=True)
        col.prop(settings, "samples_per_axis")
        sub = col.column(align=True)
        sub.active = settings.adaptive
        sub.prop(settings, "adaptive_min_samples")
        sub.prop(settings, "undersample")
        layout.label(text=f"{settings.samples_per_axis ** 2} samples at most")
        layout.prop(settings, "light_samples_per_axis")
        layout.prop(settings, "seed")
        col = layout.column(align=True, heading="Viewport")
        col.prop(settings, "viewport_samples_per_axis", text="Max Samples")
        col.prop(settings, "viewport_time_limit", text="Time Limit")
        col.prop(settings, "viewport_denoise", text="Denoise")


class RENDER_PT_kdtrace_denoise(KDTracePanel, bpy.types.Panel):
    """As Cycles' Sampling > Denoise: the master denoises the finished image (Open Image
    Denoise, Blender's own library)."""
    bl_label = "Denoise"
    bl_parent_id = "RENDER_PT_kdtrace_sampling"

    def draw_header(self, context):
        self.layout.prop(context.scene.kdtrace, "use_denoising", text="")

    def draw(self, context):
        layout, settings = property_layout(self, context)
        layout.active = settings.use_denoising
        layout.label(text="Open Image Denoise, albedo and normal")
        layout.prop(settings, "denoising_prefilter")
        layout.prop(settings, "denoising_quality")


class RENDER_PT_kdtrace_light_paths(KDTracePanel, bpy.types.Panel):
    """As Cycles' Light Paths panel: Max Bounces, Clamping, Caustics."""
    bl_label = "Light Paths"
    bl_parent_id = "RENDER_PT_kdtrace"

    def draw(self, context):
        layout, settings = property_layout(self, context)
        col = layout.column(align=True, heading="Max Bounces")
        col.prop(settings, "max_bounces")
        col.prop(settings, "diffuse_bounces")
        col.prop(settings, "glossy_bounces")
        col.prop(settings, "transmission_bounces")
        col.prop(settings, "transparent_bounces")
        col = layout.column(align=True, heading="Clamping")
        col.prop(settings, "clamp_direct")
        col.prop(settings, "clamp_indirect")
        layout.prop(settings, "filter_glossy")


class RENDER_PT_kdtrace_film(KDTracePanel, bpy.types.Panel):
    """As Cycles' Film panel: Pixel Filter and its width; Transparent (the world lights the
    scene but is not seen)."""
    bl_label = "Film"
    bl_parent_id = "RENDER_PT_kdtrace"

    def draw(self, context):
        layout, settings = property_layout(self, context)
        layout.prop(settings, "pixel_filter")
        layout.prop(settings, "filter_width")
        layout.prop(context.scene.render, "film_transparent", text="Transparent")


class RENDER_PT_kdtrace_motion_blur(KDTracePanel, bpy.types.Panel):
    """As Cycles' Motion Blur panel; KD Trace blurs the camera's motion (objects: issue 15)."""
    bl_label = "Motion Blur"
    bl_parent_id = "RENDER_PT_kdtrace"

    def draw_header(self, context):
        self.layout.prop(context.scene.render, "use_motion_blur", text="")

    def draw(self, context):
        layout, _ = property_layout(self, context)
        render = context.scene.render
        layout.active = render.use_motion_blur
        layout.prop(render, "motion_blur_position", text="Position")
        layout.prop(render, "motion_blur_shutter")


class OBJECT_PT_kdtrace_visibility(KDTracePanel, bpy.types.Panel):
    """As Cycles' Ray Visibility: which rays see the object, and Holdout."""
    bl_label = "KD Trace Ray Visibility"
    bl_context = "object"

    @classmethod
    def poll(cls, context):
        return super().poll(context) and context.object is not None

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        obj = context.object
        col = layout.column(heading="Ray Visibility", align=True)
        for ray in ("camera", "diffuse", "glossy", "transmission", "shadow"):
            col.prop(obj, f"visible_{ray}", text=ray.title())
        layout.prop(obj, "is_holdout")


class VIEWLAYER_PT_kdtrace_passes(KDTracePanel, bpy.types.Panel):
    """As Cycles' View Layer > Passes: the passes KD Trace fills (each computed and sent by the
    slaves only when switched on here)."""
    bl_label = "Passes"
    bl_context = "view_layer"

    def draw(self, context):
        pass


def draw_pass_switches(layout, view_layer, rows) -> None:
    """`rows` of (heading, switches) as Cycles draws its passes: each switch a property of the
    view layer ("kdtrace.<name>": of its KD Trace settings) and its label (None: its own)."""
    layout.use_property_split = True
    for heading, switches in rows:
        col = layout.column(heading=heading, align=True)
        for path, text in switches:
            owner, _, name = path.rpartition(".")
            data = getattr(view_layer, owner) if owner else view_layer
            col.prop(data, name, **({} if text is None else {"text": text}))


class VIEWLAYER_PT_kdtrace_passes_data(KDTracePanel, bpy.types.Panel):
    bl_label = "Data"
    bl_context = "view_layer"
    bl_parent_id = "VIEWLAYER_PT_kdtrace_passes"

    def draw(self, context):
        draw_pass_switches(self.layout, context.view_layer, (
            ("Include", (("use_pass_combined", None), ("use_pass_z", None),
                         ("use_pass_mist", None), ("use_pass_normal", None))),
            ("", (("kdtrace.denoising_store_passes", None),))))


class VIEWLAYER_PT_kdtrace_passes_light(KDTracePanel, bpy.types.Panel):
    bl_label = "Light"
    bl_context = "view_layer"
    bl_parent_id = "VIEWLAYER_PT_kdtrace_passes"

    def draw(self, context):
        draw_pass_switches(self.layout, context.view_layer, (
            ("Diffuse", (("use_pass_diffuse_color", "Color"),)),
            ("Glossy", (("use_pass_glossy_color", "Color"),)),
            ("Other", (("use_pass_emit", "Emission"),))))


class RENDER_PT_kdtrace_kdtree(KDTracePanel, bpy.types.Panel):
    bl_label = "kd-Tree"
    bl_parent_id = "RENDER_PT_kdtrace"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout, settings = property_layout(self, context)
        layout.prop(settings, "kdtree_mode")
        col = layout.column()
        col.active = settings.kdtree_mode != "standard"   # thresholds only matter when lifting
        col.prop(settings, "tau_occu")
        col.prop(settings, "tau_freq")
        row = col.row()
        row.active = settings.kdtree_mode == "compressed"        # choi: unlimited per path
        row.prop(settings, "refs_per_path")


class RENDER_PT_kdtrace_network(KDTracePanel, bpy.types.Panel):
    bl_label = "Network"
    bl_parent_id = "RENDER_PT_kdtrace"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        from .properties import preferences
        layout, settings = property_layout(self, context)
        layout.prop(settings, "tiles_in_flight")
        layout.prop(settings, "payload")
        layout.prop(settings, "interaction")
        layout.prop(preferences(context), "secret_file")


class KDTRACE_UL_hosts(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        row = layout.row(align=True)
        row.prop(item, "enabled", text="")
        row.prop(item, "host", text="", emboss=False, placeholder="host or IP address")
        row.prop(item, "port", text="")


class RENDER_PT_kdtrace_slaves(KDTracePanel, bpy.types.Panel):
    bl_label = "Slaves"
    bl_parent_id = "RENDER_PT_kdtrace"

    def draw(self, context):
        from ..core.frame.local_slaves import has_bundled_cpu_device
        from . import browsing, session
        from .properties import approved_ids, preferences
        layout = self.layout
        settings = context.scene.kdtrace
        state = session.current()
        browsing.browse_soon(context.scene)   # the panel shows what the LAN browser sees

        col = layout.column()
        col.use_property_split = True
        col.prop(settings, "use_zeroconf")
        sub = col.column()
        sub.active = settings.use_zeroconf
        sub.prop(settings, "discovery_seconds")
        col.prop(settings, "local_slaves")
        col.prop(settings, "use_local_slaves_always")
        if settings.local_slaves and not has_bundled_cpu_device():
            layout.label(text="No CPU OpenCL device is bundled here: local slaves need an "
                              "OpenCL driver (README)", icon="ERROR")

        prefs = preferences(context)
        approved = set(approved_ids(prefs))
        identity = state.identity_if_loaded()
        row = layout.row()
        row.label(text=f"This computer: ID {identity.short_id}" if identity is not None
                  else "This computer: ID made at the first render", icon="LOCKED")
        row.operator("kdtrace.copy_master_id", text="", icon="COPYDOWN")

        layout.label(text="Found on the LAN:")
        row = layout.row()
        box = row.box()
        found = state.discovered_slaves()
        if not found:
            box.label(text="None yet" if settings.use_zeroconf else "Discovery is off", icon="INFO")
        shown = set()
        for slave in found:
            slave_id = slave.properties.get("id", "")
            shown.add(slave.endpoint)
            draw_slave(box, slave.name, slave.host, slave.port, slave_id,
                            slave.properties.get("device", ""), slave_id in approved)
        for (host, port), slave_id in sorted(state.unapproved.items()):
            if (host, port) not in shown and slave_id not in approved:
                draw_slave(box, f"{host}:{port}", host, port, slave_id, "listed", False)
        local = state.local_slaves.pids()
        if local:
            box.label(text=f"{len(local)} local slave(s) running", icon="CONSOLE")
        row.operator("kdtrace.refresh_slaves", text="", icon="FILE_REFRESH")

        layout.label(text="Listed by address:")
        row = layout.row()
        row.template_list("KDTRACE_UL_hosts", "", settings, "hosts", settings, "active_host", rows=2)
        buttons = row.column(align=True)
        buttons.operator("kdtrace.host_add", text="", icon="ADD")
        buttons.operator("kdtrace.host_remove", text="", icon="REMOVE")


def draw_slave(layout, name, host, port, slave_id, device, approved) -> None:
    """One slave: name, address, short ID; Approve and Pair where it is not approved."""
    row = layout.row(align=True)
    short = "-".join(slave_id[i:i + 4] for i in range(0, 16, 4)) if slave_id else "no ID"
    row.label(text=f"{name}  {host}:{port}  ID {short}  {device}",
              icon="CHECKMARK" if approved else "NETWORK_DRIVE")
    if approved or len(slave_id) != 52:
        return
    approve = row.operator("kdtrace.slave_approve", text="Approve")
    approve.slave_id, approve.name = slave_id, name
    pair = row.operator("kdtrace.slave_pair", text="Pair")
    pair.host, pair.port, pair.slave_id, pair.name = host, port, slave_id, name


class RENDER_PT_kdtrace_legend(KDTracePanel, bpy.types.Panel):
    """Who rendered what in the last frame, in the colours of the tile frames and the Slave pass."""
    bl_label = "Last Render"
    bl_parent_id = "RENDER_PT_kdtrace"

    def draw(self, context):
        from . import session
        state = session.current()
        legend = state.legend
        if legend is None:
            self.layout.label(text="Nothing rendered yet")
            return
        grid = self.layout.grid_flow(columns=5, even_columns=False, align=True)
        for heading in ("Slave", "Device", "Tiles", "ms/tile", "State"):
            grid.label(text=heading)
        for status in legend.slaves.values():
            grid.label(text=status.name, icon=color_icon(status.color))
            grid.label(text=status.device)
            grid.label(text=str(status.tiles))
            grid.label(text=f"{status.ms_per_tile:.0f}")
            grid.label(text=status.state)
        if state.local_reason:
            self.layout.label(text=f"Local slaves started: {state.local_reason}", icon="CONSOLE")
        report = state.last_render
        if report.get("denoised"):
            self.layout.label(text=f"Denoised in {report['denoise_seconds']:.2f} s "
                                   f"({report['denoise_note']})")
        elif report.get("denoise_note", "off") not in ("off", "frame not finished"):
            self.layout.label(text=f"Not denoised: {report['denoise_note']}", icon="ERROR")


def color_icon(color) -> str:
    """The closest of Blender's eight coloured collection icons (labels cannot show any RGB)."""
    palette = {"COLLECTION_COLOR_01": (0.9, 0.3, 0.3), "COLLECTION_COLOR_02": (0.95, 0.6, 0.3),
               "COLLECTION_COLOR_03": (0.95, 0.9, 0.3), "COLLECTION_COLOR_04": (0.4, 0.8, 0.3),
               "COLLECTION_COLOR_05": (0.3, 0.55, 0.95), "COLLECTION_COLOR_06": (0.6, 0.35, 0.9),
               "COLLECTION_COLOR_07": (0.9, 0.4, 0.75), "COLLECTION_COLOR_08": (0.6, 0.45, 0.3)}
    return min(palette, key=lambda icon: sum((a - b) ** 2 for a, b in zip(palette[icon], color)))


classes = (KDTRACE_UL_hosts, RENDER_PT_kdtrace, RENDER_PT_kdtrace_sampling, RENDER_PT_kdtrace_denoise,
           RENDER_PT_kdtrace_light_paths, RENDER_PT_kdtrace_film, RENDER_PT_kdtrace_motion_blur,
           OBJECT_PT_kdtrace_visibility, VIEWLAYER_PT_kdtrace_passes,
           VIEWLAYER_PT_kdtrace_passes_data, VIEWLAYER_PT_kdtrace_passes_light,
           RENDER_PT_kdtrace_kdtree, RENDER_PT_kdtrace_slaves, RENDER_PT_kdtrace_network,
           RENDER_PT_kdtrace_legend)

# Blender's own panels that show what KD Trace renders (camera, lights, material base colour,
# world colour). Panels for Blender's generic engine list "BLENDER_RENDER"; the material and
# world surface panels are EEVEE's.
EXTRA_PANELS = ("EEVEE_MATERIAL_PT_context_material", "EEVEE_MATERIAL_PT_surface",
                "EEVEE_WORLD_PT_surface", "EEVEE_WORLD_PT_mist")
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
