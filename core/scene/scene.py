"""THE checkpoint of a scene: geometry plus its compact kd-tree, validated once where it enters
(the exporter's side with `Scene.from_parts`, the wire and the slave's disk cache with
`Scene.from_wire`) and trusted by every later layer (master, slave, tracer).

A Scene carries what those layers would otherwise recompute: its content hash (the one key of
uploads and caches), the tree's depth (the traversal stack size) and which materials the
triangles use (what the kernel features depend on, core/scene/features.py).

An instanced scene (`Scene.from_instances`, docs/instances.md) also carries `instances`
(core/scene/instances.py): its geometry is then its meshes' object-space triangles one after
another, its tree their compact kd-trees one after another (each counting from its bases in
the MESH table) with the world box of all instances as bounds, and its depth the deepest
mesh tree's. A scene of one identity instance is made flat: the same scene as from_parts.
"""
from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass

import numpy as np

from ..accel.compact import CompactTree, compact_tree
from ..accel.kdtree import KDTree
from ..accel.validate import validate_compact
from ..layout import INSTANCE, MESH, VISIBLE_TO_ALL
from .features import full_geometry, needed_arrays, program_textures, scene_features
from .instances import MAX_MESH_BASE, MAX_MESHES, VISIBILITY_BITS, InstanceSet, as_3x4
from .model import (INDEX_DTYPE, MATERIAL_ID_DTYPE, MATERIAL_PARAMS, MAX_LIGHTS, VERTEX_DTYPE,
                    Geometry, SceneError, View)

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
# An instanced scene's arrays in place of "bounds" and "leaf_shift" (core/scene/instances.py).
# mesh_counts: per mesh its triangles, nodes, 32-bit and 16-bit leaf entries and leaf_shift
# (the bases follow as their running sums); mesh_bounds: its object-space root box.
MESH_COUNTS = ("triangles", "nodes", "leaf32", "leaf16", "leaf_shift")
INSTANCE_ARRAYS = {
    "mesh_counts": (np.dtype("<u4"), (-1, len(MESH_COUNTS))),
    "mesh_bounds": (np.dtype("<f4"), (-1, 2, 3)),
    "instance_mesh": (np.dtype("<u4"), (-1,)),
    "instance_to_world": (np.dtype("<f4"), (-1, 3, 4)),
    "instance_visibility": (np.dtype("u1"), (-1,)),
}
# The instances' transforms at shutter close, carried only where some object moves (motion blur).
MOTION_ARRAYS = {"instance_to_world_end": (np.dtype("<f4"), (-1, 3, 4))}
# What a SCENE_INSTANCES message carries: the instances alone, for meshes the slave holds
# (and MOTION_ARRAYS where they move).
PLACEMENT_ARRAYS = ("instance_mesh", "instance_to_world", "instance_visibility")
INSTANCED_SCENE_ARRAYS = {**{name: SCENE_ARRAYS[name] for name in ("vertices", "triangles",
                                                                  "material_ids", "nodes",
                                                                  "leaf_index32", "leaf_index16")},
                          **INSTANCE_ARRAYS}


@dataclass(frozen=True, eq=False)
class Scene:
    geometry: Geometry
    tree: CompactTree
    hash: str                      # 32 hex digits over the geometry and the tree arrays
    depth: int                     # levels of the tree (root = 1)
    used_materials: np.ndarray     # sorted material ids that some triangle uses
    instances: InstanceSet | None = None    # None: a flat scene (world-space geometry)
    meshes_hash: str | None = None  # instanced: the hash of the meshes and their trees alone

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
        instanced = "instance_mesh" in arrays
        required = INSTANCED_SCENE_ARRAYS if instanced else SCENE_ARRAYS
        optional = {**OPTIONAL_SCENE_ARRAYS, **(MOTION_ARRAYS if instanced else {})}
        if not set(required) <= set(arrays) <= set(required) | set(optional):
            raise SceneError(f"a scene must carry the arrays {sorted(required)} and optionally "
                             f"{sorted(optional)}, got {sorted(arrays)}")
        _check_array_specs(arrays, {**required, **optional})
        geometry = Geometry(arrays["vertices"], arrays["triangles"], arrays["material_ids"],
                            **{name: arrays.get(name) for name in OPTIONAL_SCENE_ARRAYS})
        geometry.validate()
        if "instance_mesh" in arrays:
            return cls._checked_instances(geometry, arrays)
        tree = CompactTree(arrays["nodes"], arrays["leaf_index32"], arrays["leaf_index16"],
                           arrays["bounds"], int(arrays["leaf_shift"][0]))
        return cls._checked(geometry, tree)

    @classmethod
    def from_instances(cls, meshes, instance_mesh, to_world, visibility=None, texels=None,
                       texture_sizes=None, to_world_end=None) -> "Scene":
        """The scene of meshes (a list of (Geometry in object space, its KDTree or CompactTree);
        their optional arrays normals/uvs, where some mesh has them) placed by instances:
        instance_mesh (I,) mesh indices, to_world (I, 4, 4) or (I, 3, 4) object-to-world
        transforms, visibility (I,) VISIBILITY bits (default: every ray), to_world_end: the
        transforms at shutter close (motion blur; None, or all equal to to_world: still). The
        textures are the scene's. One identity instance of one mesh gives the flat scene."""
        instance_mesh = np.asarray(instance_mesh, np.int64).reshape(-1)
        matrices = as_3x4(to_world)
        motion = _motion_arrays(matrices, to_world_end)
        visibility = _visibility_bits(visibility, len(instance_mesh))
        if len(instance_mesh) and (instance_mesh.min() < 0 or instance_mesh.max() >= len(meshes)):
            raise SceneError(f"an instance uses a mesh outside 0..{len(meshes) - 1}")
        parts, depths = [], []
        for m, (geometry, tree) in enumerate(meshes):
            geometry.validate()
            if isinstance(tree, KDTree):
                tree = compact_tree(tree, geometry.triangle_count, mode="standard")
            try:
                depths.append(checked_depth(tree, geometry.triangle_count))
            except ValueError as exc:
                raise SceneError(f"invalid kd-tree of mesh {m}: {exc}") from None
            parts.append((geometry, tree))
        if _flat(len(parts), instance_mesh, matrices, visibility, motion):
            geometry, tree = parts[0]
            if texels is not None or texture_sizes is not None or geometry.texels is not None:
                geometry = Geometry(geometry.vertices, geometry.triangles, geometry.material_ids,
                                    geometry.normals, geometry.uvs, texels, texture_sizes)
            return cls.from_parts(geometry, tree)   # (untextured: its hash is computed once)
        arrays = _concatenated_meshes(parts)
        geometry = Geometry(arrays.pop("vertices"), arrays.pop("triangles"),
                            arrays.pop("material_ids"), arrays.pop("normals", None),
                            arrays.pop("uvs", None), texels, texture_sizes)
        geometry.validate()
        arrays.update(instance_mesh=instance_mesh.astype(np.uint32),
                      instance_to_world=matrices.astype(np.float32),
                      instance_visibility=visibility, **motion)
        return cls._checked_instances(geometry, arrays, depths)

    @staticmethod
    def places_flat(mesh_count: int, instance_mesh, to_world, to_world_end=None) -> bool:
        """Whether from_instances makes these meshes (visible to every ray) placed so the flat
        scene of mesh 0: one mesh, one identity instance, nothing moving."""
        matrices = as_3x4(to_world)
        return _flat(mesh_count, np.asarray(instance_mesh).reshape(-1), matrices,
                     (VISIBLE_TO_ALL,), _motion_arrays(matrices, to_world_end))

    @classmethod
    def _checked_instances(cls, geometry: Geometry, arrays: dict, depths=None) -> "Scene":
        """`depths`: the mesh trees' depths where from_instances has validated the trees these
        arrays concatenate (else each mesh's slice of the arrays is validated here)."""
        counts = arrays["mesh_counts"].astype(np.int64)
        if not 1 <= len(counts) <= MAX_MESHES:      # before any work per mesh
            raise SceneError(f"an instanced scene has 1 to {MAX_MESHES} meshes, got {len(counts)}")
        totals = _column_totals(counts[:, :4])
        sizes = (geometry.triangle_count, len(arrays["nodes"]), len(arrays["leaf_index32"]),
                 len(arrays["leaf_index16"]))
        if totals != sizes:
            raise SceneError(f"the meshes' triangles, nodes and leaf entries add up to "
                             f"{totals}, the scene has {sizes}")
        if max(totals) > MAX_MESH_BASE:
            raise SceneError(f"the meshes' triangles, nodes and leaf entries {totals} do not "
                             f"fit the 32-bit bases of the mesh table (at most {MAX_MESH_BASE})")
        bases = np.concatenate([np.zeros((1, 4), np.int64), np.cumsum(counts[:, :4], axis=0)])
        table = np.zeros((len(counts), len(MESH.columns)), np.uint32)
        for column, k in (("tri_base", 0), ("node_base", 1), ("leaf32_base", 2),
                          ("leaf16_base", 3)):
            table[:, MESH.index(column)] = bases[:-1, k]
        table[:, MESH.index("tri_count")] = counts[:, 0]
        table[:, MESH.index("leaf_shift")] = counts[:, 4]
        mesh_bounds = arrays["mesh_bounds"]
        if len(mesh_bounds) != len(counts):
            raise SceneError(f"{len(mesh_bounds)} mesh boxes for {len(counts)} meshes")
        if depths is None:
            depths = []
            for m in range(len(counts)):
                lo, hi = bases[m], bases[m + 1]
                try:
                    depths.append(validate_compact(
                        arrays["nodes"][lo[1]:hi[1]], arrays["leaf_index32"][lo[2]:hi[2]],
                        arrays["leaf_index16"][lo[3]:hi[3]], mesh_bounds[m], int(counts[m, 4]),
                        int(hi[0] - lo[0])))
                except ValueError as exc:
                    raise SceneError(f"invalid kd-tree of mesh {m}: {exc}") from None
        depth = max([1, *depths])
        instances = InstanceSet.checked(arrays["instance_mesh"], arrays["instance_to_world"],
                                        arrays["instance_visibility"], table, mesh_bounds,
                                        arrays.get("instance_to_world_end"))
        tree = CompactTree(arrays["nodes"], arrays["leaf_index32"], arrays["leaf_index16"],
                           instances.bounds(), 0)
        used = geometry.used_material_ids()
        meshes = {name: np.ascontiguousarray(arrays[name], dtype=INSTANCED_SCENE_ARRAYS[name][0])
                  for name in ("nodes", "leaf_index32", "leaf_index16", "mesh_counts",
                               "mesh_bounds")}
        meshes_hash = _digest(b"meshes" + geometry.content_hash().encode(), meshes)
        return cls(geometry, tree, _instanced_hash(meshes_hash, instances), depth, used,
                   instances, meshes_hash)

    def moved(self, to_world, visibility=None) -> "Scene":
        """This instanced scene with its instances placed by `to_world` ((I, 4, 4) or
        (I, 3, 4), one per instance, each keeping its mesh) and `visibility` (default: as
        now): only the instances are checked again and the top level rebuilt; the meshes and
        their trees are shared. The same scene as from_instances with these transforms."""
        if self.instances is None:
            raise SceneError("only an instanced scene has instances to move")
        old = self.instances
        if len(as_3x4(to_world)) != old.count:
            raise SceneError(f"{len(as_3x4(to_world))} transforms for {old.count} instances")
        return self.placed(old.mesh, to_world, old.visibility if visibility is None else visibility)

    def placed(self, instance_mesh, to_world, visibility=None, to_world_end=None) -> "Scene":
        """This instanced scene's meshes placed by other instances (any number: instance_mesh
        (I,) mesh indices, to_world (I, 4, 4) or (I, 3, 4), visibility (I,), default: every
        ray), to_world_end (motion blur, as from_instances): only the instances are checked
        and the top level built; the meshes and their
        trees are shared (same meshes_hash). The same scene as from_instances with these
        instances (but never flattened)."""
        if self.instances is None:
            raise SceneError("only an instanced scene has instances to place")
        old = self.instances
        mesh = np.asarray(instance_mesh, np.int64).reshape(-1)
        matrices = as_3x4(to_world).astype(np.float32)
        meshes = len(old.mesh_table)
        if len(mesh) and (mesh.min() < 0 or mesh.max() >= meshes):   # before the uint32 cast
            raise SceneError(f"an instance uses a mesh outside 0..{meshes - 1}")
        return self._placed(mesh.astype(np.uint32), matrices,
                            _visibility_bits(visibility, len(mesh)),
                            **_motion_arrays(matrices, to_world_end))

    def placed_from_wire(self, arrays: dict) -> "Scene":
        """This scene's meshes placed by the instance arrays of a SCENE_INSTANCES message
        (`instance_arrays` of a sender), after checking their names, dtypes and shapes and
        then the instances (InstanceSet.checked); SceneError names the problem."""
        if self.instances is None:
            raise SceneError("only an instanced scene has instances to place")
        if not set(PLACEMENT_ARRAYS) <= set(arrays) <= set(PLACEMENT_ARRAYS) | set(MOTION_ARRAYS):
            raise SceneError(f"instance arrays must be {sorted(PLACEMENT_ARRAYS)} and optionally "
                             f"{sorted(MOTION_ARRAYS)}, got {sorted(arrays)}")
        _check_array_specs(arrays, {**INSTANCE_ARRAYS, **MOTION_ARRAYS})
        return self._placed(arrays["instance_mesh"], arrays["instance_to_world"],
                            arrays["instance_visibility"], arrays.get("instance_to_world_end"))

    def _placed(self, mesh, to_world, visibility, instance_to_world_end=None) -> "Scene":
        old = self.instances
        instances = InstanceSet.checked(mesh, to_world, visibility, old.mesh_table,
                                        old.mesh_bounds, instance_to_world_end)
        tree = CompactTree(self.tree.nodes, self.tree.leaf_index32, self.tree.leaf_index16,
                           instances.bounds(), 0)
        scene = Scene(self.geometry, tree, _instanced_hash(self.meshes_hash, instances),
                      self.depth, self.used_materials, instances, self.meshes_hash)
        for name in ("mesh_parts", "mesh_hashes"):    # the same meshes: computed once
            if name in self.__dict__:
                scene.__dict__[name] = self.__dict__[name]
        return scene

    def instance_arrays(self) -> dict:
        """An instanced scene's instance arrays as they travel (SCENE_INSTANCES, SCENE_UPLOAD)."""
        return _placement_arrays(self.instances)

    @functools.cached_property
    def mesh_parts(self) -> list | None:
        """An instanced scene's meshes as from_instances takes them, (object-space Geometry,
        CompactTree) sliced from the scene's arrays (textures stay the scene's); None where
        the meshes' vertices are not one block per mesh in mesh order (a scene from_instances
        made always has them so), as they could not travel one by one."""
        table = self.instances.mesh_table
        counts = table[:, MESH.index("tri_count")].astype(np.int64)
        return _split_meshes(self.geometry, counts, self.mesh_trees())

    @functools.cached_property
    def mesh_hashes(self) -> np.ndarray | None:
        """(M, 16) uint8: each mesh's hash (its geometry and tree, as `mesh_parts`); None
        where the meshes cannot travel one by one."""
        parts = self.mesh_parts
        if parts is None:
            return None
        return np.array([list(bytes.fromhex(_content_hash(g, t))) for g, t in parts], np.uint8)

    @property
    def meshes_travel_alone(self) -> bool:
        """Whether SCENE_MESHES can carry this scene (some meshes only): instanced, its meshes
        one block each, and not the one identity instance that from_instances makes flat."""
        inst = self.instances
        if inst is None or self.mesh_hashes is None:
            return False
        return not (inst.count == 1 and len(inst.mesh_table) == 1 and
                    np.array_equal(inst.to_world[0], np.eye(3, 4)) and
                    inst.visibility[0] == VISIBLE_TO_ALL)

    def mesh_wire_arrays(self, new) -> dict:
        """The arrays of a SCENE_MESHES message: every mesh's hash, which meshes travel (`new`,
        (M,) bool) and their arrays (as an upload's, concatenated), the textures and the
        instances. The receiver takes the other meshes from the scenes it holds."""
        new = np.asarray(new, bool)
        parts = [part for part, sent in zip(self.mesh_parts, new) if sent]
        arrays = _concatenated_meshes(parts) if parts else {}
        specs = {**SCENE_ARRAYS, **OPTIONAL_SCENE_ARRAYS, **INSTANCE_ARRAYS}
        arrays = {name: np.ascontiguousarray(a, specs[name][0]) for name, a in arrays.items()}
        for name in ("texels", "texture_sizes"):
            if getattr(self.geometry, name) is not None:
                arrays[name] = np.ascontiguousarray(getattr(self.geometry, name), specs[name][0])
        return {"mesh_hashes": self.mesh_hashes, "mesh_new": new.astype(np.uint8), **arrays,
                **self.instance_arrays()}

    @classmethod
    def from_mesh_wire(cls, arrays: dict, held) -> "Scene":
        """The scene of a SCENE_MESHES message (`mesh_wire_arrays` of a sender): the meshes it
        carries, checked as an upload's, and the others from `held` (mesh hash bytes -> the
        (Geometry, CompactTree) of a scene this side holds, or None); SceneError names the
        problem (a mesh not held among them)."""
        hashes, new = arrays.get("mesh_hashes"), arrays.get("mesh_new")
        if hashes is None or new is None or hashes.dtype != np.uint8 or new.dtype != np.uint8 \
                or hashes.ndim != 2 or hashes.shape[1] != 16 or new.shape != hashes.shape[:1] \
                or not 1 <= len(new) <= MAX_MESHES or (new > 1).any():
            raise SceneError("SCENE_MESHES needs mesh_hashes u1 (M, 16) and mesh_new u1 (M,) of "
                             f"0/1, 1 <= M <= {MAX_MESHES}")
        carried = {name: a for name, a in arrays.items() if name not in ("mesh_hashes", "mesh_new")}
        mesh_arrays = ("vertices", "triangles", "material_ids", "nodes", "leaf_index32",
                       "leaf_index16", "mesh_counts", "mesh_bounds")
        required = set(PLACEMENT_ARRAYS) | (set(mesh_arrays) if new.any() else set())
        allowed = required | set(OPTIONAL_SCENE_ARRAYS) | set(MOTION_ARRAYS)
        if not required <= set(carried) <= allowed:
            raise SceneError(f"SCENE_MESHES must carry {sorted(required)} and optionally "
                             f"{sorted(OPTIONAL_SCENE_ARRAYS)}, got {sorted(carried)}")
        _check_array_specs(carried, {**SCENE_ARRAYS, **OPTIONAL_SCENE_ARRAYS, **INSTANCE_ARRAYS,
                                     **MOTION_ARRAYS})
        sent = []
        if new.any():
            geometry = Geometry(*(carried[n] for n in ("vertices", "triangles", "material_ids")),
                                carried.get("normals"), carried.get("uvs"))
            geometry.validate()
            counts = carried["mesh_counts"].astype(np.int64)
            sizes = (geometry.triangle_count, len(carried["nodes"]), len(carried["leaf_index32"]),
                     len(carried["leaf_index16"]))
            if len(counts) != int(new.sum()) or len(carried["mesh_bounds"]) != len(counts) or \
                    _column_totals(counts[:, :4]) != sizes:
                raise SceneError(f"the carried meshes' counts do not add up to their arrays "
                                 f"({int(new.sum())} meshes marked new)")
            ends = np.cumsum(counts[:, 1:4], axis=0)
            starts = ends - counts[:, 1:4]
            trees = [CompactTree(carried["nodes"][a[0]:b[0]], carried["leaf_index32"][a[1]:b[1]],
                                 carried["leaf_index16"][a[2]:b[2]], carried["mesh_bounds"][m],
                                 int(counts[m, 4])) for m, (a, b) in enumerate(zip(starts, ends))]
            sent = _split_meshes(geometry, counts[:, 0], trees)
            if sent is None:
                raise SceneError("the carried meshes' vertices are not one block per mesh")
        parts, sent = [], iter(sent)
        for m, (digest, is_new) in enumerate(zip(hashes, new)):
            part = next(sent) if is_new else held(bytes(digest))
            if part is None:
                raise SceneError(f"mesh {m} is neither carried nor held here")
            parts.append(part)
        return cls.from_instances(parts, carried["instance_mesh"], carried["instance_to_world"],
                                  carried["instance_visibility"], carried.get("texels"),
                                  carried.get("texture_sizes"),
                                  carried.get("instance_to_world_end"))

    def mesh_trees(self) -> list:
        """An instanced scene's mesh trees (CompactTree views into the scene's tree arrays)."""
        table = self.instances.mesh_table
        ends = [len(self.tree.nodes), len(self.tree.leaf_index32), len(self.tree.leaf_index16)]
        columns = [MESH.index(c) for c in ("node_base", "leaf32_base", "leaf16_base")]
        out = []
        for m in range(len(table)):
            lo = [int(table[m, c]) for c in columns]
            hi = [int(table[m + 1, c]) for c in columns] if m + 1 < len(table) else ends
            out.append(CompactTree(self.tree.nodes[lo[0]:hi[0]],
                                   self.tree.leaf_index32[lo[1]:hi[1]],
                                   self.tree.leaf_index16[lo[2]:hi[2]],
                                   self.instances.mesh_bounds[m],
                                   int(table[m, MESH.index("leaf_shift")])))
        return out

    @classmethod
    def _checked(cls, geometry: Geometry, tree: CompactTree) -> "Scene":
        try:
            depth = checked_depth(tree, geometry.triangle_count)
        except ValueError as exc:
            raise SceneError(f"invalid kd-tree: {exc}") from None
        used = geometry.used_material_ids()
        return cls(geometry, tree, _content_hash(geometry, tree), depth, used)

    @property
    def material_count(self) -> int:
        """Materials a view must provide: one more than the highest id a triangle uses."""
        return int(self.used_materials[-1]) + 1 if len(self.used_materials) else 0

    def wire_arrays(self) -> dict:
        """The arrays of a SCENE_UPLOAD (and of the slave's disk cache), in wire dtypes."""
        if self.instances is None:
            return _wire_arrays(self.geometry, self.tree)
        inst = self.instances
        trees = self.mesh_trees()
        table = inst.mesh_table
        counts = np.stack([table[:, MESH.index("tri_count")],
                           [len(t.nodes) for t in trees], [len(t.leaf_index32) for t in trees],
                           [len(t.leaf_index16) for t in trees],
                           table[:, MESH.index("leaf_shift")]], axis=1).astype(np.uint32)
        arrays = _wire_arrays(self.geometry, self.tree)
        for name in ("bounds", "leaf_shift"):
            del arrays[name]
        arrays.update(mesh_counts=counts, mesh_bounds=np.ascontiguousarray(inst.mesh_bounds, "<f4"),
                      **self.instance_arrays())
        return arrays

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
        if self.instances is not None:
            self._check_world_space(view)
        missing = sorted(name for name in needed_arrays(self.features(view))
                         if getattr(self.geometry, name) is None)
        if missing:
            raise SceneError(f"the view needs the geometry arrays {missing}, which the scene "
                             f"does not carry")

    def _check_world_space(self, view: View) -> None:
        """Emissive triangles are sampled as lights in world space, and node programs read
        the hit's position and the triangle's frame from the triangle buffer: in an instanced
        scene, triangles with such materials must lie in meshes placed once, by the identity
        (the exporter realises them)."""
        params = view.shading.material_params
        emission = params[:, [MATERIAL_PARAMS.index(f"emission_{c}") for c in "rgb"]]
        world_space = view.shading.per_material(
            (emission > 0).any(axis=1) | (params[:, MATERIAL_PARAMS.index("program")] >= 0))
        if not world_space[self.used_materials].any():
            return
        inst = self.instances
        table = inst.mesh_table
        tri_mesh = np.repeat(np.arange(len(table)), table[:, MESH.index("tri_count")])
        needs = np.zeros(len(table), bool)
        needs[tri_mesh[world_space[self.geometry.material_ids]]] = True
        uses = np.bincount(inst.mesh, minlength=len(table))
        identity = (inst.to_world == np.eye(3, 4, dtype=np.float32)).all(axis=(1, 2))
        placed_once = (uses == 1) & np.bincount(inst.mesh, identity, len(table)).astype(bool)
        bad = needs & ~placed_once
        if bad.any():
            raise SceneError(f"mesh {int(np.flatnonzero(bad)[0])} has emissive or node-program "
                             f"materials and is not placed once by the identity: such "
                             f"triangles must be realised")

    def features(self, view: View) -> frozenset:
        """The kernel features this scene needs for `view` (core/scene/features.py)."""
        return scene_features(self.geometry, view, self.used_materials, self.instances)


def _split_meshes(geometry: Geometry, tri_counts, trees) -> list | None:
    """(Geometry, tree) per mesh of concatenated meshes (tri_counts triangles each, in order),
    each mesh's vertices the block its triangles use; None where those blocks do not follow
    one another through the whole vertex array."""
    tri_ends = np.cumsum(tri_counts)
    parts, vertex_end = [], 0
    for tree, hi, count in zip(trees, tri_ends, tri_counts):
        lo = hi - count
        triangles = geometry.triangles[lo:hi]
        if count == 0 or int(triangles.min()) != vertex_end:
            return None
        start, vertex_end = vertex_end, int(triangles.max()) + 1
        corner = {name: None if getattr(geometry, name) is None else
                  getattr(geometry, name)[3 * lo:3 * hi] for name in ("normals", "uvs")}
        parts.append((Geometry(geometry.vertices[start:vertex_end], triangles - np.uint32(start),
                               geometry.material_ids[lo:hi], **corner), tree))
    return parts if vertex_end == len(geometry.vertices) else None


def _column_totals(counts: np.ndarray) -> tuple:
    """Each column's sum of a peer's (M, k) counts, in Python integers (numpy's sums wrap)."""
    return tuple(sum(column) for column in counts.T.tolist())


def _visibility_bits(visibility, count: int) -> np.ndarray:
    """(count,) uint8 VISIBILITY bits of the instances (None: every ray): integers that fit
    uint8, refused before the cast would wrap them (256 to 0); InstanceSet.checked checks the
    bits."""
    if visibility is None:
        return np.full(count, VISIBLE_TO_ALL, np.uint8)
    values = np.asarray(visibility).reshape(-1)
    if values.dtype.kind not in "iub" or (len(values) and not (
            0 <= int(values.min()) and int(values.max()) <= np.iinfo(np.uint8).max)):
        raise SceneError(f"instance visibility must be integers of VISIBILITY bits "
                         f"(0..{VISIBILITY_BITS})")
    return values.astype(np.uint8)


def _check_array_specs(arrays: dict, specs: dict) -> None:
    for name, array in arrays.items():
        dtype, pattern = specs[name]
        if array.dtype != dtype or array.ndim != len(pattern) or any(
                p != -1 and p != n for p, n in zip(pattern, array.shape)):
            raise SceneError(f"scene array {name!r} must be {dtype.str} of shape {pattern}, "
                             f"got {array.dtype.str} {array.shape}")


def tree_arrays(tree: CompactTree) -> dict:
    arrays = {"nodes": tree.nodes, "leaf_index32": tree.leaf_index32,
              "leaf_index16": tree.leaf_index16, "bounds": tree.bounds,
              "leaf_shift": np.array([int(tree.leaf_shift)])}
    return {name: np.ascontiguousarray(array, dtype=SCENE_ARRAYS[name][0])
            for name, array in arrays.items()}


def _wire_arrays(geometry: Geometry, tree: CompactTree) -> dict:
    specs = {**SCENE_ARRAYS, **OPTIONAL_SCENE_ARRAYS}
    arrays = {name: np.ascontiguousarray(array, dtype=specs[name][0])
              for name, array in geometry.arrays().items()}
    return {**arrays, **tree_arrays(tree)}


def _content_hash(geometry: Geometry, tree: CompactTree) -> str:
    """The geometry's hash plus the compact tree's (another kd-tree mode or other thresholds,
    which give other arrays, give another hash)."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(geometry.content_hash().encode())
    digest.update(tree_digest(tree).encode())
    return digest.hexdigest()


DIGEST_PIECE = 64 << 20     # tree_digest hashes this many bytes between two heartbeats


def tree_digest(tree: CompactTree, heartbeat=None) -> str:
    """32 hex digits over the compact tree's arrays, computed once per tree object (its arrays
    are not changed after it is made, so the master's cached tree is hashed once, not at every
    render): CompactTree.digest. heartbeat(), where given, is called after each 64 MB."""
    if tree.digest is None:
        digest = hashlib.blake2b(digest_size=16)
        for name, array in tree_arrays(tree).items():
            digest.update(f"{name}{array.shape}".encode())
            data = memoryview(array.reshape(-1)).cast("B")
            for start in range(0, len(data), DIGEST_PIECE):   # the same digest as in one go
                digest.update(data[start:start + DIGEST_PIECE])
                if heartbeat is not None:
                    heartbeat()
        tree.digest = digest.hexdigest()
    return tree.digest


def checked_depth(tree: CompactTree, triangle_count: int, heartbeat=None) -> int:
    """validate_compact's depth of `tree` for `triangle_count` triangles, computed once per
    tree object (CompactTree.checked); ValueError names what is wrong. heartbeat: as
    validate_compact's."""
    if tree.checked is None or tree.checked[0] != triangle_count:
        tree.checked = (triangle_count, validate_compact(
            tree.nodes, tree.leaf_index32, tree.leaf_index16, tree.bounds, tree.leaf_shift,
            triangle_count, heartbeat))
    return tree.checked[1]


def _concatenated_meshes(parts) -> dict:
    """The meshes' geometry and tree arrays one after another (triangles index the joined
    vertices; each tree stays local to its mesh), with the mesh_counts and mesh_bounds of the
    wire. Normals and UVs are joined when some mesh has them: flat corner normals and zero
    UVs stand in for a mesh without."""
    vertex_bases = np.cumsum([0] + [len(g.vertices) for g, _ in parts])
    out = {"vertices": np.concatenate([g.vertices for g, _ in parts]),
           "triangles": np.concatenate([g.triangles + np.uint32(base)
                                        for (g, _), base in zip(parts, vertex_bases)]),
           "material_ids": np.concatenate([g.material_ids for g, _ in parts])}
    if any(g.normals is not None for g, _ in parts):
        out["normals"] = np.concatenate([g.normals if g.normals is not None
                                         else full_geometry(g).normals for g, _ in parts])
    if any(g.uvs is not None for g, _ in parts):
        out["uvs"] = np.concatenate([g.uvs if g.uvs is not None
                                     else np.zeros((3 * g.triangle_count, 2)) for g, _ in parts])
    for name in ("nodes", "leaf_index32", "leaf_index16"):
        out[name] = np.ascontiguousarray(np.concatenate([getattr(t, name) for _, t in parts]),
                                         SCENE_ARRAYS[name][0])
    out["mesh_counts"] = np.array([(g.triangle_count, len(t.nodes), len(t.leaf_index32),
                                    len(t.leaf_index16), int(t.leaf_shift))
                                   for g, t in parts], np.uint32)
    out["mesh_bounds"] = np.array([t.bounds for _, t in parts], np.float32)
    return out


def memory_report(scene: Scene) -> dict:
    """What the scene costs each slave against its realised version (docs/instances.md):
    triangles stored and referenced, bytes of the meshes (geometry and kd-trees) and of the top
    level (BVH nodes and instance records), and the realised scene's bytes estimated at the
    meshes' bytes per triangle."""
    inst = scene.instances
    stored = scene.geometry.triangle_count
    referenced = stored if inst is None else inst.referenced_triangles
    mesh_bytes = scene.geometry.nbytes + scene.tree.nbytes
    top_bytes = 0 if inst is None else int(inst.toplevel.nodes.nbytes) + \
        inst.count * INSTANCE.size * 16
    return {"instances": 1 if inst is None else inst.count,
            "meshes": 1 if inst is None else len(inst.mesh_table),
            "triangles_stored": stored, "triangles_referenced": referenced,
            "bytes_meshes": mesh_bytes, "bytes_top_level": top_bytes,
            "bytes_realised_estimate": int(mesh_bytes * referenced / max(stored, 1))}


def memory_summary(report: dict) -> str:
    """One line of the render's report."""
    if report["instances"] == 1:
        return f"{report['triangles_stored']:,} triangles"
    return (f"{report['instances']:,} instances of {report['meshes']} mesh(es): "
            f"{report['triangles_referenced']:,} triangles referenced, "
            f"{report['triangles_stored']:,} stored; {report['bytes_meshes'] / 1e6:.1f} MB meshes "
            f"+ {report['bytes_top_level'] / 1e6:.2f} MB top level (realised: about "
            f"{report['bytes_realised_estimate'] / 1e6:.0f} MB)")


def _digest(prefix: bytes, arrays: dict) -> str:
    digest = hashlib.blake2b(prefix, digest_size=16)
    for name, array in arrays.items():
        digest.update(f"{name}{array.shape}".encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def _instanced_hash(meshes_hash: str, instances: InstanceSet) -> str:
    """An instanced scene's hash: its meshes' (which stay when only instances change) and
    the instance arrays."""
    return _digest(b"instanced" + meshes_hash.encode(), _placement_arrays(instances))


def _placement_arrays(instances: InstanceSet) -> dict:
    """The instance arrays as they travel and are hashed (the shutter-close transforms only
    where the instances move)."""
    arrays = {"instance_mesh": instances.mesh, "instance_to_world": instances.to_world,
              "instance_visibility": instances.visibility}
    if instances.to_world_end is not None:
        arrays["instance_to_world_end"] = instances.to_world_end
    return arrays


def _flat(mesh_count: int, instance_mesh, matrices, visibility, motion: dict) -> bool:
    return mesh_count == 1 and len(instance_mesh) == 1 and \
        np.array_equal(matrices[0], np.eye(3, 4)) and visibility[0] == VISIBLE_TO_ALL and not motion


def _motion_arrays(matrices: np.ndarray, to_world_end) -> dict:
    """{"instance_to_world_end": (I, 3, 4) float32} where the transforms at shutter close
    differ from `matrices` (I, 3, 4), else {} (a still scene)."""
    if to_world_end is None:
        return {}
    end = as_3x4(to_world_end).astype(np.float32)
    if end.shape == matrices.shape and np.array_equal(end, matrices.astype(np.float32)):
        return {}
    return {"instance_to_world_end": end}
