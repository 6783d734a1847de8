"""Triangles in spatial order, where the add-on takes in an exported scene.

Blender hands over triangles in its face order, which may be anything (joined objects, boolean
results, a shuffle of "Sort Elements"). The kd-tree builder, the compaction and the tracer all
fetch triangles by index from arrays far bigger than the caches; in an order where neighbours
in space are neighbours in memory, a subtree's or a leaf's triangles share cache lines. The
add-on therefore puts each exported mesh's triangles in the Morton order of their first corners
before its hash and tree (addon/session.py `order_meshes`; docs/kdtree_native.md, "Triangle
order"). Only the triangles' indices change: the same
triangles, materials, normals and UVs, the same tree up to those indices, the same images (a hit
exactly as near as another goes to the lower index, so such rare ties may pick the other one).
"""
from __future__ import annotations

import numpy as np

from ..accel.morton import morton_order
from .model import Geometry


def spatial_order(geometry: Geometry, order: np.ndarray | None = None):
    """(`geometry` with its triangles, their material ids and corner rows in the Morton order of
    their first corners over the vertices' box, that order): the same geometry always gives
    the same order. `order`: a permutation to apply instead of computing one (the last
    render's, for a mesh that may not have changed). The order is None, and the geometry the
    same object, where nothing moves."""
    if order is None:
        if geometry.triangle_count < 2:
            return geometry, None
        vertices = geometry.vertices
        order = morton_order(vertices[geometry.triangles[:, 0]], vertices.min(0),
                             vertices.max(0))
        if np.all(order[1:] > order[:-1]):
            return geometry, None

    def corner_rows(array):         # 3 rows per triangle, moved as one row of 3 each
        return None if array is None else array.reshape(len(order), -1)[order]

    return Geometry(geometry.vertices, geometry.triangles[order], geometry.material_ids[order],
                    corner_rows(geometry.normals), corner_rows(geometry.uvs),
                    geometry.texels, geometry.texture_sizes), order
