"""Instances of meshes: the second level of an instanced scene (docs/instances.md).

An instanced Scene (core/scene/scene.py) holds meshes, each object-space triangles with their
own compact kd-tree, concatenated into the scene's geometry and tree arrays (a mesh's tree
counts its nodes, leaf lists and triangles from its bases in the MESH table, core/layout.py),
and instances: a mesh, a 3x4 object-to-world transform (float32, as it travels) and the rays
that see it. `InstanceSet.checked` validates them once, where the scene enters, and derives
what the kernels need: the inverse transforms (float64, stored float32), the instances' world
boxes, their hit keys and the top-level BVH (core/accel/toplevel.py).

Object motion blur: an instance may also carry its transform at shutter close (to_world_end);
the kernels blend the two linearly at the ray's time and invert the blend. A point under
linearly blended transforms moves linearly in time, so the union of the open and close world
boxes bounds the instance over the whole shutter.

Hit keys: an instance's triangles are numbered after those of the instances before it, as the
triangles of the realised scene (every instance's triangles in world space, in instance order)
would be; kernels report and break ties by this key, so an instanced scene gives the same
hits as its realised one.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np

from ..accel.toplevel import TopLevel, build_toplevel
from ..layout import MESH, VISIBLE_TO_ALL
from .model import SceneError

# The limits of an instanced scene, checked where it enters (export and wire).
MAX_INSTANCES = 1 << 20
MAX_MESHES = 1 << 16
MAX_REFERENCED_TRIANGLES = (1 << 32) - 2     # hit keys are uint32; 0xFFFFFFFF is no hit
MAX_MESH_BASE = (1 << 32) - 1                # the MESH table's bases are uint32
VISIBILITY_BITS = 63                         # VISIBILITY_<RAY> bits and HOLDOUT
# A transform whose linear part has |det| at most this fraction of its largest entry cubed
# is singular (a scale of zero): its inverse would not be finite.
MIN_RELATIVE_DET = 1e-12
# World boxes are widened by this fraction of their size (and of their coordinates'
# magnitude): the kernels transform rays into object space in float32, so a hit on a mesh's
# box face may lie a few ulps outside the box transformed in float64.
BOX_MARGIN = 1e-5


@dataclass(frozen=True, eq=False)
class InstanceSet:
    mesh: np.ndarray            # (I,) uint32: the mesh of each instance
    to_world: np.ndarray        # (I, 3, 4) float32
    to_object: np.ndarray       # (I, 3, 4) float32, the inverse (computed in float64)
    visibility: np.ndarray      # (I,) uint8 VISIBILITY bits
    key_base: np.ndarray        # (I,) uint32 hit key of each instance's first triangle
    mesh_table: np.ndarray      # (M, MESH columns) uint32 (core/layout.py MESH)
    mesh_bounds: np.ndarray     # (M, 2, 3) float32 object-space root boxes
    world_bounds: np.ndarray    # (I, 2, 3) float32 world boxes (rounded outward, widened)
    toplevel: TopLevel
    to_world_end: np.ndarray | None = None  # (I, 3, 4) float32 at shutter close; None: still

    @property
    def moving(self) -> bool:
        """Whether some instance's transform differs at shutter close (object motion blur)."""
        return self.to_world_end is not None and \
            not np.array_equal(self.to_world_end, self.to_world)

    @property
    def count(self) -> int:
        return len(self.mesh)

    @property
    def referenced_triangles(self) -> int:
        """Triangles of the realised scene: every instance's mesh counted once per instance."""
        return int(self.mesh_table[self.mesh, MESH.index("tri_count")].astype(np.int64).sum())

    @classmethod
    def checked(cls, mesh, to_world, visibility, mesh_table, mesh_bounds,
                to_world_end=None) -> "InstanceSet":
        """Validate instance arrays (as from the wire: mesh (I,) uint32, to_world (I, 3, 4)
        float32, visibility (I,) uint8, to_world_end None or as to_world: the transforms at
        shutter close) against the mesh table; SceneError names the problem."""
        count, meshes = len(mesh), len(mesh_table)
        if not 1 <= count <= MAX_INSTANCES:
            raise SceneError(f"an instanced scene has 1 to {MAX_INSTANCES} instances, got {count}")
        if not 1 <= meshes <= MAX_MESHES:
            raise SceneError(f"an instanced scene has 1 to {MAX_MESHES} meshes, got {meshes}")
        if len(to_world) != count or len(visibility) != count:
            raise SceneError(f"{count} instance meshes, {len(to_world)} transforms and "
                             f"{len(visibility)} visibilities: one each per instance")
        if int(mesh.max()) >= meshes:
            raise SceneError(f"instance {int(np.argmax(mesh >= meshes))} uses mesh "
                             f"{int(mesh.max())}, the scene has {meshes}")
        if (visibility & ~np.uint8(VISIBILITY_BITS)).any():
            raise SceneError(f"an instance's visibility has bits outside {VISIBILITY_BITS}")
        if not np.isfinite(to_world).all():
            raise SceneError(f"instance {_first(~np.isfinite(to_world).all(axis=(1, 2)))}'s "
                             f"transform has NaN or infinite entries")
        matrix = to_world.astype(np.float64)
        linear = matrix[:, :, :3]
        det = np.linalg.det(linear)
        scale = np.abs(linear).max(axis=(1, 2))
        singular = ~(np.abs(det) > MIN_RELATIVE_DET * scale ** 3)
        if singular.any():
            raise SceneError(f"instance {_first(singular)}'s transform is singular (a scale of "
                             f"zero): it has no inverse")
        inverse = np.linalg.inv(linear)
        to_object = np.concatenate(
            [inverse, -np.einsum("ijk,ik->ij", inverse, matrix[:, :, 3])[:, :, None]], axis=2)
        if not (np.isfinite(to_object).all() and np.abs(to_object).max() < 1e30):
            raise SceneError("an instance's inverse transform does not fit in float32")
        tri_counts = mesh_table[:, MESH.index("tri_count")].astype(np.int64)
        # Exact in int64: at most MAX_INSTANCES (2^20, checked above) counts below 2^32.
        key_base = np.concatenate([[0], np.cumsum(tri_counts[mesh])])
        if int(key_base[-1]) > MAX_REFERENCED_TRIANGLES:
            raise SceneError(f"the instances reference {int(key_base[-1])} triangles, at most "
                             f"{MAX_REFERENCED_TRIANGLES}")
        world = world_boxes(matrix, mesh_bounds[mesh].astype(np.float64))
        if to_world_end is not None:
            end = _checked_motion(matrix, to_world_end, count)
            end_world = world_boxes(end, mesh_bounds[mesh].astype(np.float64))
            world = np.stack([np.minimum(world[:, 0], end_world[:, 0]),
                              np.maximum(world[:, 1], end_world[:, 1])], axis=1)
            to_world_end = to_world_end.astype(np.float32)
        if not np.isfinite(world).all() or np.abs(world).max() >= np.finfo(np.float32).max:
            raise SceneError("an instance's world box does not fit in float32")
        world32 = _outward(world)
        return cls(mesh.astype(np.uint32), to_world.astype(np.float32),
                   to_object.astype(np.float32), visibility.astype(np.uint8),
                   key_base[:-1].astype(np.uint32), mesh_table, mesh_bounds, world32,
                   build_toplevel(world32[:, 0], world32[:, 1]), to_world_end)

    def bounds(self) -> np.ndarray:
        """(2, 3) float32: the world box of all instances."""
        return np.stack([self.world_bounds[:, 0].min(axis=0), self.world_bounds[:, 1].max(axis=0)])

    def hit_instance(self, key: np.ndarray):
        """(instance, triangle within its mesh) of hit keys (int64 arrays; key < 0: none)."""
        inst = np.searchsorted(self.key_base, key, side="right") - 1
        inst = np.where(key < 0, -1, inst)
        local = np.where(key < 0, -1, key - self.key_base[np.maximum(inst, 0)].astype(np.int64))
        return inst, local


def _checked_motion(start: np.ndarray, to_world_end, count: int) -> np.ndarray:
    """The (I, 3, 4) float64 transforms at shutter close, checked: finite, and every blend
    (1 - t) start + t end for t in [0, 1] invertible. det of the blend is a cubic in t; it
    keeps away from zero where its four Bernstein coefficients (from its values at t = 0,
    1/3, 2/3, 1) have one sign and exceed MIN_RELATIVE_DET of the largest entry cubed (a
    sufficient test: a blend through a half turn is refused)."""
    if to_world_end.shape != (count, 3, 4):
        raise SceneError(f"{len(to_world_end)} shutter-close transforms for {count} instances")
    if not np.isfinite(to_world_end).all():
        raise SceneError(f"instance {_first(~np.isfinite(to_world_end).all(axis=(1, 2)))}'s "
                         f"shutter-close transform has NaN or infinite entries")
    end = to_world_end.astype(np.float64)
    kept = blend_stays_invertible(start, end)
    if not kept.all():
        raise SceneError(f"instance {_first(~kept)}'s transform may become singular between "
                         f"shutter open and close (it turns or scales through zero)")
    return end


def blend_stays_invertible(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(I,) bool: whether every blend (1 - t) start + t end, t in [0, 1], of the (I, 3, 4)
    (or 4x4) transforms is invertible, by the Bernstein test of _checked_motion."""
    a, b = np.asarray(start, np.float64)[:, :3, :3], np.asarray(end, np.float64)[:, :3, :3]
    values = np.stack([np.linalg.det((1 - t) * a + t * b) for t in (0, 1 / 3, 2 / 3, 1)], axis=1)
    bernstein = values @ _VALUES_TO_BERNSTEIN.T
    scale = np.maximum(np.abs(a).max(axis=(1, 2)), np.abs(b).max(axis=(1, 2)))
    limit = (MIN_RELATIVE_DET * scale ** 3)[:, None]
    return (bernstein > limit).all(axis=1) | (bernstein < -limit).all(axis=1)


def _values_to_bernstein() -> np.ndarray:
    """The matrix that takes a cubic's values at t = 0, 1/3, 2/3, 1 to its Bernstein
    coefficients."""
    t = np.array([0, 1 / 3, 2 / 3, 1])
    basis = np.stack([comb(3, k) * t ** k * (1 - t) ** (3 - k) for k in range(4)], axis=1)
    return np.linalg.inv(basis)


_VALUES_TO_BERNSTEIN = _values_to_bernstein()


def _first(mask) -> int:
    return int(np.flatnonzero(mask)[0])


def world_boxes(to_world: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(I, 2, 3) float64 world boxes of the object-space boxes (I, 2, 3) under the 3x4
    transforms (I, 3, 4), widened by BOX_MARGIN."""
    centre = 0.5 * (boxes[:, 0] + boxes[:, 1])
    half = 0.5 * (boxes[:, 1] - boxes[:, 0])
    c = np.einsum("ijk,ik->ij", to_world[:, :, :3], centre) + to_world[:, :, 3]
    h = np.einsum("ijk,ik->ij", np.abs(to_world[:, :, :3]), half)
    pad = BOX_MARGIN * (h.max(axis=1, keepdims=True) + np.abs(c).max(axis=1, keepdims=True))
    return np.stack([c - h - pad, c + h + pad], axis=1)


def _outward(boxes: np.ndarray) -> np.ndarray:
    """float64 boxes rounded outward to float32."""
    out = boxes.astype(np.float32)
    lo, hi = out[:, 0], out[:, 1]
    lo[:] = np.where(lo > boxes[:, 0], np.nextafter(lo, np.float32(-np.inf)), lo)
    hi[:] = np.where(hi < boxes[:, 1], np.nextafter(hi, np.float32(np.inf)), hi)
    return out


def as_3x4(matrices) -> np.ndarray:
    """(I, 3, 4) float64 from 4x4 or 3x4 matrices."""
    m = np.asarray(matrices, np.float64)
    if m.ndim == 2:
        m = m[None]
    return m[:, :3, :4]
