"""The LAN browser runs in the background while KD Trace is the render engine, so that F12 uses
every slave already seen instead of waiting for answers.

It starts when KD Trace is selected (a message-bus subscription on the render engine), when a
file that uses it is loaded, when the Slaves panel is shown (draw() only schedules the start on
a timer: no network work in draw) and at F12 at the latest (core/frame/render.py find_slaves).
It stops when another engine is selected or LAN discovery is turned off, and with the session.
"""
import bpy
from bpy.app.handlers import persistent

from . import session

ENGINE = "KDTRACE"
_owner = object()   # the message-bus subscriptions of this module


def wanted(scene) -> bool:
    return scene.render.engine == ENGINE and scene.kdtrace.use_zeroconf


def update_browsing(scene=None) -> None:
    """Browse while the scene renders with KD Trace and discovery is on; otherwise stop."""
    scene = scene or getattr(bpy.context, "scene", None)
    if scene is None:
        return
    state = session.current()
    if wanted(scene):
        state.browser()
        _load_identity(state)
    else:
        state.stop_browser()


def _load_identity(state) -> None:
    """This computer's identity, for the Slaves panel (made on first use; a timer's work, not
    draw()'s)."""
    from .properties import identity_folder
    try:
        state.master_identity(identity_folder())
    except OSError as error:     # shown again at F12, as the frame's error
        print(f"KD Trace: no identity: {error}")


def browse_soon(scene) -> None:
    """For Panel.draw: bring the browser in line with the settings from a timer, soon."""
    if session.current().browsing != wanted(scene) and not bpy.app.timers.is_registered(_update_now):
        bpy.app.timers.register(_update_now, first_interval=0.0)


def _update_now(*_):
    """For the timer (once: returns None) and the message bus."""
    update_browsing()


def _subscribe():
    bpy.msgbus.clear_by_owner(_owner)
    bpy.msgbus.subscribe_rna(key=(bpy.types.RenderSettings, "engine"), owner=_owner, args=(),
                             notify=_update_now)


@persistent
def _file_loaded(*_):
    _subscribe()   # loading a file drops message-bus subscriptions
    update_browsing()


def register():
    _subscribe()
    bpy.app.handlers.load_post.append(_file_loaded)
    # The context has no scene while add-ons register at start-up: look once it has.
    bpy.app.timers.register(_update_now, first_interval=0.0)


def unregister():
    if bpy.app.timers.is_registered(_update_now):
        bpy.app.timers.unregister(_update_now)
    if _file_loaded in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_file_loaded)
    bpy.msgbus.clear_by_owner(_owner)
