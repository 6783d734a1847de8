"""Install the zip with its wheels and run the extension's `kdtrace_slave` command as
`blender --background --command kdtrace_slave ARGS` does: the callback the extension registered
with bpy.utils.register_cli_command, called with ARGS (the bpy module has no command line of its
own). The extension's wheels go first on sys.path, so the slave runs on them and not on this
Python's own packages (Blender's Python has none of them). Returns when the slave stops
(SIGTERM)."""
import sys

from blender_setup import arguments, install_extension, write_result

args, result_path = arguments()
addon = install_extension(args["zip"])
wheel_dirs = [p for p in sys.path if "extensions" in p and p.endswith("site-packages")]
sys.path[:0] = wheel_dirs
local_slaves = addon.addon.local_slaves
registered = local_slaves._command_handle is not None
status = local_slaves.run_command(args["argv"])
import zeroconf  # noqa: E402  (the slave imports it only when it advertises)
modules = {name: sys.modules[name].__file__ for name in ("pyopencl", "zeroconf", "slave", "core")}
write_result(result_path, {"status": status, "registered": registered, "modules": modules,
                           "wheel_dirs": wheel_dirs,
                           "extension_root": str(local_slaves.EXTENSION_ROOT)})
