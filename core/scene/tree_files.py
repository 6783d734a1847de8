"""The master's compact kd-trees on disk: after Blender restarts (or in each `blender -b -a` of
a render farm), F12 on an unchanged mesh reads its tree instead of building it again (the
dragon's 4 s, 12 dragons' 53 s on the 2-core machine of docs/kdtree_native.md).

A tree's file is named by its key: the mesh's content hash, the kd-tree mode and the settings
it uses, and a hash of every source that decides a tree (the builders and compactors, their
kernels, the layout, the treelet order: the kernels make the same tree bit for bit on every
device, docs/kdtree_native.md), so a new version of KD Trace builds anew instead of reading a
tree an older one made. The file holds the tree's arrays (those a scene sends), its parameters and
stats as JSON, the triangle count it was built for and a digest of all of it. Reading checks
the digest and validates the tree (checked_depth, as every scene does), so a damaged or
foreign file is deleted and the tree built again, never trusted.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pathlib

import numpy as np

from ..accel.compact import CompactParams, CompactTree
from ..npz_folder import NpzFolder
from .scene import checked_depth, tree_arrays, tree_digest

# The master keeps up to this much on disk unless the add-on's preferences say otherwise.
DEFAULT_LIMIT_MIB = 4096
LIMIT_MIB_RANGE = (0, 1 << 20)      # 0: no disk cache

EXTENSION_ROOT = pathlib.Path(__file__).resolve().parents[2]
# What decides a tree's bits, relative to the extension's root (files, or folders of them).
DECIDING_SOURCES = ("core/layout.py", "core/opencl.py", "core/accel/arrays.py",
                    "core/accel/kdtree.py", "core/accel/sah_splits.py", "core/accel/clipping.py",
                    "core/accel/ref_rows.py", "core/accel/device.py", "core/accel/binned.py",
                    "core/accel/compact.py", "core/accel/compact_topology.py",
                    "core/accel/compact_lifts.py", "core/accel/compact_layout.py",
                    "core/accel/compact_cl.py", "core/accel/reorder.py",
                    "kernels/build")


def builder_version(root: pathlib.Path = EXTENSION_ROOT) -> str:
    """32 hex digits over DECIDING_SOURCES' names and contents."""
    digest = hashlib.blake2b(digest_size=16)
    for name in DECIDING_SOURCES:
        path = root / name
        for file in sorted(path.rglob("*.*")) if path.is_dir() else [path]:
            digest.update(str(file.relative_to(root)).encode() + b"\0")
            digest.update(file.read_bytes())
    return digest.hexdigest()


class TreeFiles:
    """Compact trees in `folder`, at most `limit_bytes` of them (least recently used go)."""

    def __init__(self, folder: str | os.PathLike, limit_bytes: int):
        self.files = NpzFolder(folder, limit_bytes)
        self.version = builder_version()

    def key(self, content_hash: str, mode: str, settings: dict) -> str:
        """The file name of the tree of a mesh with `content_hash`, built in `mode` with the
        compact_tree `settings` (core.accel.compact.user_settings) by this version."""
        text = json.dumps([content_hash, mode, sorted(settings.items()), self.version])
        return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()

    def read(self, key: str, triangle_count: int, heartbeat=None) -> CompactTree | None:
        """The tree stored as `key` for a mesh of `triangle_count` triangles, validated, or
        None (no such file, or one that was damaged: it is deleted). heartbeat(), where given,
        is called between the arrays read and the digest's and the validation's pieces; its
        exception (Esc) goes up and the file stays."""
        def checked(arrays):
            return _tree_of(arrays, int(triangle_count), heartbeat)
        return self.files.read(key, checked, heartbeat)

    def write(self, key: str, tree: CompactTree, triangle_count: int) -> None:
        """Keep `tree` as `key`. OSError: the disk is full or read-only (the caller reports)."""
        arrays = dict(tree_arrays(tree))
        arrays["params"] = _json_bytes(dataclasses.asdict(tree.params))
        arrays["stats"] = _json_bytes(tree.stats)
        arrays["triangle_count"] = np.array([int(triangle_count)], np.int64)
        arrays["digest"] = np.frombuffer(_file_digest(tree, arrays).encode(), np.uint8)
        self.files.write(key, arrays)


def _tree_of(arrays: dict, triangle_count: int, heartbeat=None) -> CompactTree:
    stored = bytes(arrays.pop("digest")).decode("ascii")
    tree = CompactTree(arrays["nodes"], arrays["leaf_index32"], arrays["leaf_index16"],
                       arrays["bounds"].astype(np.float32), int(arrays["leaf_shift"][0]))
    if stored != _file_digest(tree, arrays, heartbeat):
        raise ValueError("its content does not match its digest")
    built_for = int(arrays["triangle_count"][0])
    if built_for != triangle_count:
        raise ValueError(f"built for {built_for} triangles, the mesh has {triangle_count}")
    tree.params = CompactParams(**json.loads(bytes(arrays["params"])))
    tree.stats = json.loads(bytes(arrays["stats"]))
    checked_depth(tree, triangle_count, heartbeat)     # ValueError names what is wrong
    return tree


def _file_digest(tree: CompactTree, arrays: dict, heartbeat=None) -> str:
    """The tree's digest (the one its scene's hash uses, kept on the tree) and the rest of the
    file's arrays."""
    digest = hashlib.blake2b(tree_digest(tree, heartbeat).encode(), digest_size=16)
    for name in ("params", "stats", "triangle_count"):
        digest.update(name.encode() + arrays[name].tobytes())
    return digest.hexdigest()


def _json_bytes(value) -> np.ndarray:
    def plain(x):       # numpy numbers in stats
        if isinstance(x, np.generic):
            return x.item()
        raise TypeError(f"{type(x).__name__} is not JSON")
    return np.frombuffer(json.dumps(value, default=plain).encode(), np.uint8)
