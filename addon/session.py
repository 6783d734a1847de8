"""The add-on's frame session (core/frame/session.py: kd-trees, local slaves, the LAN browser,
the last frame's report), from first use to disabling the add-on; closed in unregister() (and
at Blender's exit)."""
from __future__ import annotations

from ..core.frame.session import FrameSession

_session: FrameSession | None = None


def current() -> FrameSession:
    global _session
    if _session is None:
        _session = FrameSession()
    return _session


def close():
    global _session
    if _session is not None:
        _session.close()
        _session = None
