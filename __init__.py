"""KD Trace: a distributed kd-tree ray tracer for Blender (the extension's entry point).

The add-on lives in addon/; core/ and slave/ never import bpy and also run outside Blender.
"""


def register():
    from .addon import register as register_addon
    register_addon()


def unregister():
    from .addon import unregister as unregister_addon
    unregister_addon()
