"""THE checkpoint of a scene: geometry plus its compact kd-tree, validated once where it enters
(the exporter's side with `Scene.from_parts`, the wire and the slave's disk cache with
`Scene.from_wire`) and trusted by every later layer (master, slave, tracer).

A Scene carries what those layers would otherwise recompute: its content hash (the one key of
uploads and caches), the tree's depth (the traversal stack size) and which materials the
triangles use (what the kernel features depend on, core/scene/features.py).
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from ..accel.compact import CompactTree, compact_tree
from ..accel.kdtree import KDTree
from ..accel.validate import validate_compact
from .features import needed_arrays, program_textures, scene_features
from .model import (INDEX_DTYPE, MATERIAL_ID_DTYPE, MAX_LIGHTS, VERTEX_DTYPE, Geometry,
                    SceneError, View)

# The arrays of a scene as they travel and are stored: name -> (dtype, shape; -1 = any length).
SCENE_ARRAYS = {
    "vertices": (VERTEX_DTYPE, (-1, 3)),
    "triangles": (INDEX_DTYPE, (-1, 3)),
    "material_ids": (MATERIAL_ID_DTYPE, (-1,)),
    # The compact kd-tree (core/accel/compact.py, any mode; docs/kdtree_compression.md).
    "nodes": (np.dtype("<u4"), (-1, 2)),
    "leaf_index32": (np.dtype("<u4"), (-1,)),
    "leaf_index16": (np.dtype("<u2"), (-1,)),
    "bounds": (np.dtype("<f4"), (2, 3)),
    "leaf_shift": (np.dtype("<u4"), (1,)),
}
TREE_ARRAYS = ("nodes", "leaf_index32", "leaf_index16", "bounds", "leaf_shift")
# Geometry arrays that travel only when the scene needs them (smooth normals, textures).
OPTIONAL_SCENE_ARRAYS = {name: (dtype, (-1, width))
                         for name, (dtype, width) in Geometry.OPTIONAL.items()}


@dataclass(frozen=True, eq=False)
class Scene:
    geometry: Geometry
    tree: CompactTree
    hash: str                      # 32 hex digits over the geometry and the tree arrays
    depth: int                     # levels of the tree (root = 1)
    used_materials: np.ndarray     # sorted material ids that some triangle uses

    @classmethod
    def from_parts(cls, geometry: Geometry, tree) -> "Scene":
        """The scene of `geometry` and its kd-tree: a CompactTree as built for it, or a plain
        KDTree (core.accel.kdtree), which is laid out in mode "standard" (the same tree).
        SceneError names what does not fit together."""
        geometry.validate()
        if isinstance(tree, KDTree):
            tree = compact_tree(tree, geometry.triangle_count, mode="standard")
        elif not isinstance(tree, CompactTree):
            raise TypeError(f"a scene's tree is a KDTree or a CompactTree, not {type(tree).__name__}")
        return cls._checked(geometry, tree)

    @classmethod
    def from_wire(cls, arrays: dict) -> "Scene":
        """The scene of arrays received or read from disk (`wire_arrays` of a sender), after
        checking every name, dtype and shape, the geometry and the tree (so that no kernel ever
        indexes outside its buffers); SceneError names the problem."""
        if not set(SCENE_ARRAYS) <= set(arrays) <= set(SCENE_ARRAYS) | set(OPTIONAL_SCENE_ARRAYS):
            raise SceneError(f"a scene must carry the arrays {sorted(SCENE_ARRAYS)} and optionally "
                             f"{sorted(OPTIONAL_SCENE_ARRAYS)}, got {sorted(arrays)}")
        specs = {**SCENE_ARRAYS, **OPTIONAL_SCENE_ARRAYS}
        for name, array in arrays.items():
            dtype, pattern = specs[name]
            if array.dtype != dtype or array.ndim != len(pattern) or any(
                    p != -1 and p != n for p, n in zip(pattern, array.shape)):
                raise SceneError(f"scene array {name!r} must be {dtype.str} of shape {pattern}, "
                                 f"got {array.dtype.str} {array.shape}")
        geometry = Geometry(arrays["vertices"], arrays["triangles"], arrays["material_ids"],
                            **{name: arrays.get(name) for name in OPTIONAL_SCENE_ARRAYS})
        geometry.validate()
        tree = CompactTree(arrays["nodes"], arrays["leaf_index32"], arrays["leaf_index16"],
                           arrays["bounds"], int(arrays["leaf_shift"][0]))
        return cls._checked(geometry, tree)

    @classmethod
    def _checked(cls, geometry: Geometry, tree: CompactTree) -> "Scene":
        try:
            depth = validate_compact(tree.nodes, tree.leaf_index32, tree.leaf_index16,
                                     tree.bounds, tree.leaf_shift, geometry.triangle_count)
        except ValueError as exc:
            raise SceneError(f"invalid kd-tree: {exc}") from None
        used = np.unique(geometry.material_ids) if geometry.triangle_count else \
            np.zeros(0, geometry.material_ids.dtype)
        return cls(geometry, tree, _content_hash(geometry, tree), depth, used)

    @property
    def material_count(self) -> int:
        """Materials a view must provide: one more than the highest id a triangle uses."""
        return int(self.used_materials[-1]) + 1 if len(self.used_materials) else 0

    def wire_arrays(self) -> dict:
        """The arrays of a SCENE_UPLOAD (and of the slave's disk cache), in wire dtypes."""
        return _wire_arrays(self.geometry, self.tree)

    def check_view(self, view: View) -> None:
        """SceneError unless `view` can shade this scene, so that a frame is refused when it
        starts, never at its first tile: a material for every material id a triangle uses;
        every texture index (the world's too) an integer, -1 (none) or a texture of the
        geometry; the camera's view axis not degenerate; every geometry array the view's
        features need present."""
        if self.material_count > len(view.shading.materials):
            raise SceneError(f"the geometry uses {self.material_count} materials, the view's "
                             f"shading has {len(view.shading.materials)}")
        textures = view.shading.param("texture")
        if len(textures) and (textures != np.round(textures)).any():
            raise SceneError("a material's texture index is not a whole number")
        if len(textures) and (textures.min() < -1 or textures.max() >= self.geometry.texture_count):
            bad = textures.max() if textures.max() >= self.geometry.texture_count else textures.min()
            raise SceneError(f"a material uses texture {int(bad)}, the geometry has "
                             f"{self.geometry.texture_count}")
        images = program_textures(view.shading.node_program, view.shading.param("program"))
        if images and max(images) >= self.geometry.texture_count:
            raise SceneError(f"a node program reads texture {max(images)}, the geometry has "
                             f"{self.geometry.texture_count}")
        world = view.shading.world_texture
        if world is not None and world.texture >= self.geometry.texture_count:
            raise SceneError(f"the world uses texture {world.texture}, the geometry has "
                             f"{self.geometry.texture_count}")
        if len(view.shading.lights) > MAX_LIGHTS:
            raise SceneError(f"{len(view.shading.lights)} lights, at most {MAX_LIGHTS}")
        axis = view.camera.to_world[:3, :3] @ np.array([0.0, 0.0, -1.0])
        if not np.isfinite(axis).all() or not np.linalg.norm(axis) > 0:
            raise SceneError("the camera's to_world maps its view axis to zero")
        missing = sorted(name for name in needed_arrays(self.features(view))
                         if getattr(self.geometry, name) is None)
        if missing:
            raise SceneError(f"the view needs the geometry arrays {missing}, which the scene "
                             f"does not carry")

    def features(self, view: View) -> frozenset:
        """The kernel features this scene needs for `view` (core/scene/features.py)."""
        return scene_features(self.geometry, view, self.used_materials)


def _tree_arrays(tree: CompactTree) -> dict:
    arrays = {"nodes": tree.nodes, "leaf_index32": tree.leaf_index32,
              "leaf_index16": tree.leaf_index16, "bounds": tree.bounds,
              "leaf_shift": np.array([int(tree.leaf_shift)])}
    return {name: np.ascontiguousarray(array, dtype=SCENE_ARRAYS[name][0])
            for name, array in arrays.items()}


def _wire_arrays(geometry: Geometry, tree: CompactTree) -> dict:
    specs = {**SCENE_ARRAYS, **OPTIONAL_SCENE_ARRAYS}
    arrays = {name: np.ascontiguousarray(array, dtype=specs[name][0])
              for name, array in geometry.arrays().items()}
    return {**arrays, **_tree_arrays(tree)}


def _content_hash(geometry: Geometry, tree: CompactTree) -> str:
    """The geometry's hash plus the compact tree's arrays: another kd-tree mode or other
    thresholds, which give other arrays, give another hash."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(geometry.content_hash().encode())
    for name, array in _tree_arrays(tree).items():
        digest.update(f"{name}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()
