"""The `kdtrace_slave` command of Blender's command line:
`blender --background --command kdtrace_slave [slave options]` runs the standalone slave in the
foreground, on a machine where the extension is installed and enabled: the same slave as
`kdtrace-slave` (pyproject.toml), on Blender's own Python and the extension's wheels, run from
the extension's root folder as local slaves are (core/frame/local_slaves.py). (Blender's
command ids must be Python identifiers: no "-".)
"""
from __future__ import annotations

import signal
import subprocess
import sys

from ..core.frame.local_slaves import EXTENSION_ROOT, slave_environment

COMMAND = "kdtrace_slave"
_command_handle = None


def run_command(argv: list) -> int:
    """The `kdtrace_slave` command: the standalone slave with these arguments, as a child process
    (the add-on never imports the slave), until it ends; SIGTERM and Ctrl-C stop it."""
    env = slave_environment(KDTRACE_SLAVE_PROG=f"blender --background --command {COMMAND}")
    process = subprocess.Popen([sys.executable, "-m", "kdtrace.slave", *argv], cwd=EXTENSION_ROOT,
                               env=env)
    previous = {}
    for name in ("SIGTERM", "SIGINT"):
        number = getattr(signal, name)
        try:
            previous[number] = signal.signal(number, lambda *_: process.terminate())
        except ValueError:   # not Blender's main thread: nothing to pass on
            pass
    try:
        return process.wait()
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        if process.poll() is None:
            process.terminate()
            process.wait()


def register_command():
    global _command_handle
    import bpy
    _command_handle = bpy.utils.register_cli_command(COMMAND, run_command)


def unregister_command():
    global _command_handle
    if _command_handle is not None:
        import bpy
        bpy.utils.unregister_cli_command(_command_handle)
        _command_handle = None
