"""Run every KD Trace panel's draw() against a recording layout (there is no UI in background
mode): each property a panel shows must exist, and drawing must not raise. Also reports every
setting's default and range, which must be those of core/ (one home for each)."""
from types import SimpleNamespace

import bpy

from blender_setup import arguments, build_test_scene, install_extension, write_result


class RecordingLayout:
    """Stands in for UILayout: records prop() and label() calls, checks the properties exist."""

    def __init__(self, shown):
        self.shown = shown

    def prop(self, data, name, **_):
        if name not in data.bl_rna.properties:
            raise AttributeError(f"{type(data).__name__} has no property {name!r}")
        self.shown.append(name)

    def label(self, text="", **_):
        self.shown.append(f"label:{text}")

    def __getattr__(self, name):  # row(), column(), box(), operator(), template_list(), ...
        return lambda *args, **kwargs: self

    def __setattr__(self, name, value):  # use_property_split, active, ...
        object.__setattr__(self, name, value)


args, result_path = arguments()
addon = install_extension(args["zip"])
scene = build_test_scene(32, 24)
scene.render.engine = "KDTRACE"
scene.kdtrace.use_zeroconf = False
scene.kdtrace.local_slaves = 1
bpy.ops.render.render()  # so the Last Render legend has something to show
# A slave refused as not approved (a listed host), and one approved with the Approve button.
addon.addon.session.current().unapproved[("10.0.0.9", 47600)] = "A" * 52
bpy.ops.kdtrace.slave_approve("EXEC_DEFAULT", slave_id="B" * 52, name="approved-box")
context = SimpleNamespace(scene=scene, engine="KDTRACE", preferences=bpy.context.preferences,
                          object=scene.objects[0], view_layer=bpy.context.view_layer)
drawn = {}
for panel in addon.addon.ui.classes:
    if issubclass(panel, bpy.types.Panel):
        shown = []
        panel.draw(SimpleNamespace(layout=RecordingLayout(shown)), context)
        drawn[panel.__name__] = shown
# The add-on preferences, drawn through a stand-in that has their properties.
prefs = addon.addon.properties.preferences(bpy.context)
shown = []
stand_in = SimpleNamespace(layout=RecordingLayout(shown), bl_rna=prefs.bl_rna,
                           **{name: getattr(prefs, name) for name in prefs.bl_rna.properties.keys()
                              if name != "rna_type"})
type(prefs).draw(stand_in, context)
drawn["preferences"] = shown


def defaults_and_ranges(rna) -> dict:
    """Every setting's default and range as the panel offers it (the test compares them with
    core/)."""
    out = {}
    for name, prop in rna.properties.items():
        if name != "rna_type" and prop.type in ("INT", "FLOAT", "BOOLEAN", "ENUM"):
            out[name] = {"default": prop.default, "min": getattr(prop, "hard_min", None),
                         "max": getattr(prop, "hard_max", None)}
    return out


write_result(result_path, {"drawn": drawn, "settings": defaults_and_ranges(type(scene.kdtrace).bl_rna),
                           "preferences": defaults_and_ranges(prefs.bl_rna)})
