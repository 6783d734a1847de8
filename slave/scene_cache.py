"""Scenes a slave holds, by content hash: a small LRU in memory and, optionally, a folder on
disk with a size limit, so a restarted slave or a second master uploads nothing. The scenes in
memory and on disk are also found by their meshes' hash (`with_meshes`; on disk through a small
file `meshes-<meshes hash>.txt` naming the scene), so a frame whose instances alone changed
travels as instance arrays (docs/instances.md, "Scene deltas").

The disk copy is read back through the same validation as an upload (`Scene.from_wire`) and
its hash is recomputed: a damaged or tampered file is deleted, never trusted. The files are a
core.npz_folder.NpzFolder (numpy's .npz, no pickle, written under a temporary name + rename).
"""
from __future__ import annotations

import collections
import logging
import os
import threading

from ..core.net import protocol
from ..core.npz_folder import NpzFolder
from ..core.scene.scene import Scene

log = logging.getLogger("kdtrace.slave")


class SceneCache:
    def __init__(self, size: int = 2, disk_dir: str | os.PathLike | None = None,
                 disk_limit_bytes: int = 2 * 1024 ** 3):
        self.size = max(1, int(size))
        self.disk = NpzFolder(disk_dir, disk_limit_bytes) if disk_dir else None
        self._scenes = collections.OrderedDict()
        self._mesh_index = {}       # scene hash -> {mesh hash: mesh} of the scenes in memory
        self._lock = threading.Lock()

    def _meshes_path(self, meshes_hash: str):
        """The file naming the scene on disk that holds these meshes (its hash)."""
        return self.disk.folder / f"meshes-{protocol.check_scene_hash(meshes_hash)}.txt"

    def get(self, scene_hash: str):
        with self._lock:
            scene = self._scenes.get(scene_hash)
            if scene is not None:
                self._scenes.move_to_end(scene_hash)
                return scene
        scene = self._load_from_disk(scene_hash)
        if scene is not None:
            self._remember(scene_hash, scene)
        return scene

    def with_meshes(self, meshes_hash: str):
        """A scene whose meshes (geometry and trees) hash to `meshes_hash`, in memory or on
        disk: an instanced scene of other instances shares them (Scene.placed_from_wire)."""
        with self._lock:
            for scene in reversed(self._scenes.values()):
                if scene.meshes_hash == meshes_hash:
                    return scene
        if self.disk is None:
            return None
        pointer = self._meshes_path(meshes_hash)
        try:
            scene_hash = protocol.check_scene_hash(pointer.read_text()[:64])
        except (OSError, protocol.ProtocolError):
            return None
        scene = self.get(scene_hash)
        if scene is None or scene.meshes_hash != meshes_hash:
            pointer.unlink(missing_ok=True)     # its scene is gone (trimmed) or not that one
            return None
        return scene

    def held_mesh(self, mesh_hash: bytes):
        """(Geometry, CompactTree) of a mesh with this hash (Scene.mesh_hashes) in a scene in
        memory, or None: a scene whose other meshes changed takes it from there."""
        with self._lock:
            scenes = list(self._scenes.values())
        for scene in reversed(scenes):
            if scene.instances is None:
                continue
            index = self._mesh_index.get(scene.hash)
            if index is None:
                hashes = scene.mesh_hashes
                index = {} if hashes is None else {bytes(h): m for m, h in enumerate(hashes)}
                with self._lock:
                    if scene.hash in self._scenes:
                        self._mesh_index[scene.hash] = index
            if mesh_hash in index:
                return scene.mesh_parts[index[mesh_hash]]
        return None

    def put(self, scene: Scene, to_disk: bool = True) -> None:
        """Keep `scene`; on disk too unless `to_disk` is False (a scene placed from instances:
        its meshes went to disk with the scene that brought them)."""
        self._remember(scene.hash, scene)
        if self.disk is not None and to_disk:
            try:
                self._save_to_disk(scene)
            except OSError as exc:  # a full disk costs a future upload, nothing else
                log.warning("cannot write scene %s to the disk cache: %s", scene.hash, exc)

    def _remember(self, scene_hash: str, scene) -> None:
        with self._lock:
            self._scenes[scene_hash] = scene
            self._scenes.move_to_end(scene_hash)
            while len(self._scenes) > self.size:
                self._mesh_index.pop(self._scenes.popitem(last=False)[0], None)

    def _save_to_disk(self, scene: Scene) -> None:
        if not self.disk.write(protocol.check_scene_hash(scene.hash), scene.wire_arrays()):
            return          # bigger than the disk limit
        if scene.meshes_hash is not None:
            pointer = self._meshes_path(scene.meshes_hash)
            temporary = self.disk.temporary(pointer)
            temporary.write_text(scene.hash)
            os.replace(temporary, pointer)

    def _load_from_disk(self, scene_hash: str):
        if self.disk is None:
            return None

        def checked(arrays):
            scene = Scene.from_wire(arrays)
            if scene.hash != scene_hash:
                raise ValueError("content does not match its hash")
            return scene
        return self.disk.read(protocol.check_scene_hash(scene_hash), checked)
