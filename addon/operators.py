"""Buttons of the KD Trace panel."""
import bpy
from bpy.props import IntProperty

from ..core.npz_folder import NpzFolder
from . import session
from .properties import preferences, tree_folder


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


class KDTRACE_OT_clear_tree_cache(bpy.types.Operator):
    bl_idname = "kdtrace.clear_tree_cache"
    bl_label = "Clear kd-Tree Cache"
    bl_description = "Delete the kd-trees kept on disk and in memory (the next render builds anew)"

    def execute(self, context):
        session.current().trees.clear()
        try:
            files, size = NpzFolder(tree_folder(preferences(context)), 0).clear()
        except OSError as error:
            self.report({"ERROR"}, f"KD Trace: cannot clear the kd-tree cache: {error}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"KD Trace: {files} kd-tree(s) deleted, {size / 2 ** 20:.1f} MiB")
        return {"FINISHED"}


classes = (KDTRACE_OT_host_add, KDTRACE_OT_host_remove, KDTRACE_OT_refresh_slaves,
           KDTRACE_OT_clear_tree_cache)
