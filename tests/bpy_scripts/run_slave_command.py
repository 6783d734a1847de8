"""Install the zip with its wheels and run the extension's `kdtrace_slave` command as
`blender --background --command kdtrace_slave ARGS` does: the callback the extension registered
with bpy.utils.register_cli_command, called with ARGS (the bpy module has no command line of its
own). The extension's wheels go first on sys.path, as in Blender, whose Python has none of the
slave's packages (this one has). Returns when the slave stops (SIGTERM passed on)."""
import sys

from blender_setup import arguments, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
wheel_dirs = [p for p in sys.path if "extensions" in p and p.endswith("site-packages")]
sys.path[:0] = wheel_dirs
command = addon.addon.slave_command
registered = command._command_handle is not None
status = command.run_command(args["argv"])
write_result(result_path, {"status": status, "registered": registered, "wheel_dirs": wheel_dirs,
                           "extension_root": str(command.EXTENSION_ROOT)})
