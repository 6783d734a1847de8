"""The Blender side of KD Trace: the only package that imports bpy."""
import atexit

import bpy

from . import engine, operators, properties, session, ui

_modules = (properties, operators, engine, ui)


def register():
    for module in _modules:
        for cls in module.classes:
            bpy.utils.register_class(cls)
    ui.register()
    atexit.register(session.close)


def unregister():
    atexit.unregister(session.close)
    session.close()
    ui.unregister()
    for module in reversed(_modules):
        for cls in reversed(module.classes):
            bpy.utils.unregister_class(cls)
