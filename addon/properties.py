"""Render settings stored in the .blend (Scene.kdtrace) and machine settings (add-on preferences)."""
import bpy
from bpy.props import (BoolProperty, CollectionProperty, FloatProperty, IntProperty,
                       PointerProperty, StringProperty)

from ..core.protocol import DEFAULT_PORT, MAX_TILE_SIZE


class KDTraceHost(bpy.types.PropertyGroup):
    """A slave given by address, for networks where multicast discovery does not work."""
    host: StringProperty(name="Host", description="Host name or IP address of the slave")
    port: IntProperty(name="Port", description="TCP port the slave listens on",
                      default=DEFAULT_PORT, min=1, max=65535)
    enabled: BoolProperty(name="Use", description="Use this slave", default=True)


class KDTraceRenderSettings(bpy.types.PropertyGroup):
    tile_size: IntProperty(
        name="Tile Size", description="Width and height of the image tiles handed to slaves, in pixels",
        default=64, min=8, max=MAX_TILE_SIZE)
    use_zeroconf: BoolProperty(
        name="Find Slaves on the LAN", description="Discover slaves with zeroconf (mDNS) before rendering",
        default=True)
    discovery_seconds: FloatProperty(
        name="Discovery Time", description="How long to wait for slaves to answer before rendering",
        default=1.0, min=0.1, max=30.0, subtype="TIME_ABSOLUTE", unit="TIME_ABSOLUTE")
    hosts: CollectionProperty(type=KDTraceHost, name="Hosts",
                              description="Slaves to use in any case, by address")
    active_host: IntProperty(name="Active Host", default=0)
    local_slaves: IntProperty(
        name="Local Slaves", description="Slaves to start on this machine when no other slave answers",
        default=2, min=0, max=64)
    use_local_slaves_always: BoolProperty(
        name="Always Use Local Slaves", description="Start local slaves even when slaves on the LAN answer",
        default=False)

    @classmethod
    def register(cls):
        bpy.types.Scene.kdtrace = PointerProperty(type=cls)

    @classmethod
    def unregister(cls):
        del bpy.types.Scene.kdtrace


class KDTracePreferences(bpy.types.AddonPreferences):
    bl_idname = __package__.rpartition(".")[0]  # the extension's package, not addon/

    slave_python: StringProperty(
        name="Python for Local Slaves",
        description="Python interpreter with pyopencl, numpy and zeroconf, used to start local "
        "slaves (empty: the Python running Blender)", default="", subtype="FILE_PATH")
    slave_device: StringProperty(
        name="Local Slave Device", description="OpenCL device of local slaves: auto, cpu, gpu or "
        "platform:device indices", default="auto")

    def draw(self, context):
        self.layout.prop(self, "slave_python")
        self.layout.prop(self, "slave_device")


def preferences(context):
    return context.preferences.addons[KDTracePreferences.bl_idname].preferences


classes = (KDTraceHost, KDTraceRenderSettings, KDTracePreferences)
