"""State that lives from enabling the add-on to disabling it: local slaves, built kd-trees and the
LAN browser. Created in register(), closed in unregister() (and at Blender's exit)."""
from __future__ import annotations

import threading
from collections import OrderedDict

from ..core.kdtree import build_kdtree
from .local_slaves import LocalSlaves


class TreeCache:
    """Built kd-trees by geometry hash, so a re-render of unchanged geometry does not rebuild."""

    def __init__(self, capacity: int = 2):
        self.capacity = capacity
        self.builds = 0  # how many trees were built (tests count rebuilds with it)
        self._trees: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, geometry, progress=None):
        key = geometry.content_hash()
        with self._lock:
            if key in self._trees:
                self._trees.move_to_end(key)
                return self._trees[key], False
        tree = build_kdtree(geometry.vertices, geometry.triangles, progress=progress)
        with self._lock:
            self.builds += 1
            self._trees[key] = tree
            while len(self._trees) > self.capacity:
                self._trees.popitem(last=False)
        return tree, True


class Session:
    def __init__(self):
        self.local_slaves = LocalSlaves()
        self.trees = TreeCache()
        self._browser = None
        self.last_render: dict = {}  # timings and tiles per slave of the last render, for reports

    def browser(self):
        """The zeroconf browser on every interface, started on first use (it runs on zeroconf's
        own threads)."""
        if self._browser is None:
            from ..core.discovery import SlaveBrowser, all_ipv4_addresses
            self._browser = SlaveBrowser(interfaces=all_ipv4_addresses())
        return self._browser

    def discovered_slaves(self) -> list:
        return self._browser.slaves() if self._browser is not None else []

    def close(self):
        if self._browser is not None:
            self._browser.close()
            self._browser = None
        self.local_slaves.stop_all()


_session: Session | None = None


def current() -> Session:
    global _session
    if _session is None:
        _session = Session()
    return _session


def close():
    global _session
    if _session is not None:
        _session.close()
        _session = None

