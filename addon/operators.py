"""Buttons of the KD Trace panel."""
import bpy
from bpy.props import IntProperty

from . import session


class KDTRACE_OT_host_add(bpy.types.Operator):
    bl_idname = "kdtrace.host_add"
    bl_label = "Add Slave Host"
    bl_description = "Add a slave by address (for networks where discovery does not work)"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        settings = context.scene.kdtrace
        settings.hosts.add()
        settings.active_host = len(settings.hosts) - 1
        return {"FINISHED"}


class KDTRACE_OT_host_remove(bpy.types.Operator):
    bl_idname = "kdtrace.host_remove"
    bl_label = "Remove Slave Host"
    bl_description = "Remove the selected slave address"
    bl_options = {"REGISTER", "UNDO"}
    index: IntProperty(default=-1, options={"SKIP_SAVE"})

    @classmethod
    def poll(cls, context):
        return len(context.scene.kdtrace.hosts) > 0

    def execute(self, context):
        settings = context.scene.kdtrace
        index = self.index if self.index >= 0 else settings.active_host
        if not 0 <= index < len(settings.hosts):
            self.report({"ERROR"}, f"there is no host number {index + 1}")
            return {"CANCELLED"}
        settings.hosts.remove(index)
        settings.active_host = min(settings.active_host, len(settings.hosts) - 1)
        return {"FINISHED"}


class KDTRACE_OT_refresh_slaves(bpy.types.Operator):
    bl_idname = "kdtrace.refresh_slaves"
    bl_label = "Refresh Slaves"
    bl_description = "Forget the slaves found so far and look for slaves on the LAN again"

    def execute(self, context):
        session.current().restart_browser()
        return {"FINISHED"}


classes = (KDTRACE_OT_host_add, KDTRACE_OT_host_remove, KDTRACE_OT_refresh_slaves)
