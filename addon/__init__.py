"""The Blender side of KD Trace: the only package that imports bpy."""
import atexit

import bpy

from . import browsing, engine, operators, properties, session, slave_command, ui

_modules = (properties, operators, engine, ui)


def register():
    for module in _modules:
        for cls in module.classes:
            bpy.utils.register_class(cls)
    ui.register()
    browsing.register()
    slave_command.register_command()
    atexit.register(session.close)


def unregister():
    atexit.unregister(session.close)
    slave_command.unregister_command()
    browsing.unregister()
    session.close()
    ui.unregister()
    for module in reversed(_modules):
        for cls in reversed(module.classes):
            bpy.utils.unregister_class(cls)
