"""Built kd-trees kept across frames, in memory and on disk (docs/kdtree_native.md)."""
from __future__ import annotations

import pathlib
import threading
from collections import OrderedDict

from ..accel.binned import build_standard, opencl_builder
from ..accel.compact import compact_tree
from ..accel.reorder import treelet_order
from ..scene.model import SceneError
from ..scene.scene import checked_depth, tree_digest
from ..scene.tree_files import TreeFiles


class TreeCache:
    """Built kd-trees in the compact layout, by (geometry hash, mode, the settings the mode uses),
    so a re-render of unchanged geometry with unchanged kd-tree settings does not rebuild. The
    standard SAH tree of a geometry is kept too, so another mode or threshold only redoes the
    compaction. An instanced scene keeps a tree per mesh (docs/instances.md): the capacity
    counts trees. With a folder (`use_disk`), compact trees are also kept on disk
    (core/scene/tree_files.py), so they outlive Blender."""

    def __init__(self, capacity: int = 8):
        self.capacity = capacity
        self.builds = 0        # how many standard trees were built (tests count rebuilds with it)
        self.compactions = 0   # how many compact trees were made from them
        self.disk: TreeFiles | None = None
        self.disk_problem = ""  # why a tree of this render could not be written to disk
        self._trees: OrderedDict = OrderedDict()      # key -> CompactTree
        self._standard: OrderedDict = OrderedDict()   # geometry hash -> KDTree
        self._lock = threading.Lock()

    def use_disk(self, folder, limit_mib: int):
        """Keep trees in `folder` too, up to limit_mib MiB; None or a limit of 0: memory only.
        OSError when the folder cannot be made. Called at each render: the last render's
        disk problem is forgotten here."""
        self.disk_problem = ""
        if not folder or limit_mib <= 0:
            self.disk = None
        elif (self.disk is None or self.disk.files.folder != pathlib.Path(folder)
              or self.disk.files.limit_bytes != limit_mib << 20):
            self.disk = TreeFiles(folder, limit_mib << 20)

    def get(self, geometry, mode: str, settings: dict, progress=None, device="auto"):
        """(compact tree, where from): "memory", "disk" or "built" (anything had to be built
        or compacted). `settings`: compact_tree's keyword arguments
        (core.accel.compact.user_settings). progress(fraction, message) covers both steps:
        the SAH build 0-0.8, compaction 0.8-1. Both run on the OpenCL device `device` (the
        preferences' local slave device) when there is one, else with numpy; the tree's stats
        say which builder ran where. The tree comes in its final node order (treelets,
        core/accel/reorder.py), which slaves upload as it is."""
        report = progress or (lambda fraction, message: None)
        key = (geometry.content_hash(), mode, tuple(sorted(settings.items())))
        with self._lock:
            if key in self._trees:
                self._trees.move_to_end(key)
                return self._trees[key], "memory"
            standard = self._standard.get(key[0])
        disk, name = self.disk, None
        if disk is not None:
            name = disk.key(key[0], mode, settings)
            report(0.0, "reading the kd-tree from disk")
            compact = disk.read(name, geometry.triangle_count,
                                lambda: report(0.0, "checking the kd-tree read from disk"))
            if compact is not None:
                with self._lock:
                    self._remember(self._trees, key, compact)
                return compact, "disk"
        if standard is None:
            standard, builder = build_standard(geometry.vertices, geometry.triangles, device,
                                               progress=lambda f, m: report(0.8 * f, m))
            with self._lock:
                self.builds += 1
                self._remember(self._standard, key[0], standard)
        else:
            builder = opencl_builder(device)[0]
        compact = compact_tree(standard, geometry.triangle_count, mode, **settings,
                               progress=lambda f, m: report(0.8 + 0.2 * f, m), device=builder)
        laying_out = lambda: report(1.0, "laying the kd-tree out in treelets")     # noqa: E731
        compact = treelet_order(compact, heartbeat=laying_out)
        compact.stats.update({k: standard.stats[k] for k in ("builder", "device", "build_seconds")})
        # The scene's checks of the tree and its digest, done here where Esc is heard (12
        # dragons': 3-4 s); the scene finds them done.
        checking = lambda: report(1.0, "checking the kd-tree")      # noqa: E731
        try:
            checked_depth(compact, geometry.triangle_count, checking)
        except ValueError as error:
            raise SceneError(f"invalid kd-tree: {error}") from None
        tree_digest(compact, checking)
        with self._lock:
            self.compactions += 1
            self._remember(self._trees, key, compact)
        if disk is not None:
            try:
                disk.write(name, compact, geometry.triangle_count)
            except OSError as error:    # a full disk costs a build after a restart, no more
                self.disk_problem = f"cannot keep the kd-tree in {disk.files.folder}: {error}"
        return compact, "built"

    def clear(self):
        """Forget every tree held in memory (the disk's are the caller's to delete)."""
        with self._lock:
            self._trees.clear()
            self._standard.clear()

    def _remember(self, store, key, value):
        store[key] = value
        store.move_to_end(key)
        while len(store) > self.capacity:
            store.popitem(last=False)
