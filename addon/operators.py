"""Buttons of the KD Trace panel."""
import bpy
from bpy.props import IntProperty, StringProperty

from ..core.npz_folder import NpzFolder
from . import session
from .properties import identity_folder, preferences, tree_folder

PAIR_TIMEOUT_S = 5.0     # the pairing connection, whole (a slave that does not answer)


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


def _approve(context, slave_id: str, name: str) -> bool:
    """Remember `slave_id` as approved in the preferences (saved with them); False if it was."""
    prefs = preferences(context)
    if any(slave.slave_id == slave_id for slave in prefs.approved_slaves):
        return False
    entry = prefs.approved_slaves.add()
    entry.slave_id, entry.name = slave_id, name
    session.current().unapproved = {endpoint: known for endpoint, known
                                    in session.current().unapproved.items() if known != slave_id}
    context.preferences.is_dirty = True
    return True


def _checked_id(operator, text: str) -> str | None:
    from ..core.net.identity import ID_LENGTH, normalize_id
    slave_id = normalize_id(text)
    if len(slave_id) != ID_LENGTH:
        operator.report({"ERROR"}, f"KD Trace: not a slave's full ID: {text[:60]!r}")
        return None
    return slave_id


class KDTRACE_OT_slave_approve(bpy.types.Operator):
    bl_idname = "kdtrace.slave_approve"
    bl_label = "Approve Slave"
    bl_description = ("Send scenes to this slave from now on. First check that the slave's "
                      "log (or kdtrace-slave --status) shows the same ID")
    bl_options = {"INTERNAL"}
    slave_id: StringProperty(options={"SKIP_SAVE"})
    name: StringProperty(options={"SKIP_SAVE"})

    def invoke(self, context, event):
        return context.window_manager.invoke_confirm(
            self, event, title=f"Approve {self.name}?",
            message=f"Its log must show ID {self.slave_id[:16]}", confirm_text="Approve")

    def execute(self, context):
        slave_id = _checked_id(self, self.slave_id)
        if slave_id is None:
            return {"CANCELLED"}
        if _approve(context, slave_id, self.name):
            self.report({"INFO"}, f"KD Trace: slave {self.name} approved")
        return {"FINISHED"}


class KDTRACE_OT_slave_forget(bpy.types.Operator):
    bl_idname = "kdtrace.slave_forget"
    bl_label = "Forget Slave"
    bl_description = "Send no more scenes to this slave (until it is approved again)"
    bl_options = {"INTERNAL"}
    index: IntProperty(default=-1, options={"SKIP_SAVE"})

    def execute(self, context):
        prefs = preferences(context)
        if not 0 <= self.index < len(prefs.approved_slaves):
            self.report({"ERROR"}, f"KD Trace: there is no approved slave number {self.index + 1}")
            return {"CANCELLED"}
        prefs.approved_slaves.remove(self.index)
        context.preferences.is_dirty = True
        return {"FINISHED"}


class KDTRACE_OT_slave_pair(bpy.types.Operator):
    """Pair with a slave in one step: this computer approves the slave (by the ID you picked)
    and proves the slave's pairing code, after which the slave serves this computer."""
    bl_idname = "kdtrace.slave_pair"
    bl_label = "Pair with Slave"
    bl_description = ("Approve this slave and let it serve this computer, with the pairing code "
                      "the slave shows when it starts")
    bl_options = {"INTERNAL"}
    host: StringProperty(options={"SKIP_SAVE"})
    port: IntProperty(options={"SKIP_SAVE"})
    slave_id: StringProperty(options={"SKIP_SAVE"})
    name: StringProperty(options={"SKIP_SAVE"})
    code: StringProperty(name="Pairing Code", description="The code the slave's log shows "
                         "(XXXX-XXXX)", options={"SKIP_SAVE"})

    def invoke(self, context, event):
        return context.window_manager.invoke_props_dialog(
            self, title=f"Pair with {self.name} (ID {self.slave_id[:16]})")

    def execute(self, context):
        from ..core.net.connection import MasterError, connect_slave
        slave_id = _checked_id(self, self.slave_id)
        if slave_id is None:
            return {"CANCELLED"}
        try:
            identity = session.current().master_identity(identity_folder())
            connection = connect_slave(self.host, self.port, PAIR_TIMEOUT_S, "blender",
                                       silence_s=PAIR_TIMEOUT_S, identity=identity,
                                       pairing={slave_id: self.code.strip()})
        except (MasterError, OSError) as error:
            self.report({"ERROR"}, f"KD Trace: pairing with {self.name} failed: {error}")
            return {"CANCELLED"}
        connection.close(say_bye=True)
        _approve(context, slave_id, self.name)
        self.report({"INFO"}, f"KD Trace: paired with slave {self.name}: it renders for this "
                              f"computer from now on")
        return {"FINISHED"}


class KDTRACE_OT_copy_master_id(bpy.types.Operator):
    bl_idname = "kdtrace.copy_master_id"
    bl_label = "Copy This Computer's ID"
    bl_description = ("Copy this computer's ID, for `kdtrace-slave --allow ID` on a slave "
                      "(instead of pairing)")

    def execute(self, context):
        try:
            identity = session.current().master_identity(identity_folder())
        except OSError as error:
            self.report({"ERROR"}, f"KD Trace: no identity: {error}")
            return {"CANCELLED"}
        context.window_manager.clipboard = identity.id
        self.report({"INFO"}, f"KD Trace: copied {identity.id}")
        return {"FINISHED"}


class KDTRACE_OT_new_farm_secret(bpy.types.Operator):
    bl_idname = "kdtrace.new_farm_secret"
    bl_label = "New Farm Secret"
    bl_description = ("Write a new farm secret to a file (readable by you only) and use it; "
                      "give the same file to each slave (--secret-file)")
    filepath: StringProperty(subtype="FILE_PATH", options={"SKIP_SAVE"})

    def invoke(self, context, event):
        self.filepath = "kdtrace-farm-secret.txt"
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        from ..core.net.trust import AuthError, write_new_secret
        try:
            write_new_secret(bpy.path.abspath(self.filepath))
        except (AuthError, OSError) as error:
            self.report({"ERROR"}, f"KD Trace: {error}")
            return {"CANCELLED"}
        preferences(context).secret_file = self.filepath
        context.preferences.is_dirty = True
        self.report({"INFO"}, f"KD Trace: farm secret written to {self.filepath}")
        return {"FINISHED"}


classes = (KDTRACE_OT_host_add, KDTRACE_OT_host_remove, KDTRACE_OT_refresh_slaves,
           KDTRACE_OT_clear_tree_cache, KDTRACE_OT_slave_approve, KDTRACE_OT_slave_forget,
           KDTRACE_OT_slave_pair, KDTRACE_OT_copy_master_id, KDTRACE_OT_new_farm_secret)
