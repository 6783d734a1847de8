"""An architecture-like test scene: a building of furnished rooms made of box primitives.

Big triangles straddle many kd-tree cells (walls, floors, ceilings, stair flights), small ones
cluster (furniture): the case where kd-trees duplicate references most and where lifting them
into inner nodes pays. Each box is 12 triangles; every room has walls with a door opening,
a floor slab, columns, a table with legs, chairs, shelves with boards and a few low-poly vases,
and one room per floor a staircase. `architecture_scene(rooms=(nx, ny), floors=f)` scales it:
about 1,000 triangles per room.
"""
from __future__ import annotations

import numpy as np

_BOX_FACES = np.array([
    [0, 2, 1], [1, 2, 3],      # -z
    [4, 5, 6], [5, 7, 6],      # +z
    [0, 1, 4], [1, 5, 4],      # -y
    [2, 6, 3], [3, 6, 7],      # +y
    [0, 4, 2], [2, 4, 6],      # -x
    [1, 3, 5], [3, 7, 5],      # +x
], np.int64)


def boxes(lo, hi):
    """Triangles of axis-aligned boxes (K, 3) lo/hi -> vertices (8K, 3), triangles (12K, 3)."""
    lo, hi = np.asarray(lo, np.float64).reshape(-1, 3), np.asarray(hi, np.float64).reshape(-1, 3)
    corner = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64)
    vertices = lo[:, None, :] + corner[None] * (hi - lo)[:, None, :]
    triangles = _BOX_FACES[None] + 8 * np.arange(len(lo))[:, None, None]
    return vertices.reshape(-1, 3), triangles.reshape(-1, 3)


def _vase(center, radius, height, segments=12, rings=6):
    """A closed low-poly surface of revolution (a vase) standing on `center`."""
    z = np.linspace(0, height, rings)
    r = radius * (0.6 + 0.4 * np.sin(np.linspace(0.3, 2.8, rings)))
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(phi), np.sin(phi)], 1)
    pts = np.concatenate([np.column_stack([ring * r[k], np.full(segments, z[k])])
                          for k in range(rings)])
    pts = np.vstack([pts, [[0, 0, 0], [0, 0, height]]]) + np.asarray(center)
    faces = []
    j = np.arange(segments)
    jn = (j + 1) % segments
    for k in range(rings - 1):
        a, b = k * segments + j, k * segments + jn
        faces += [np.stack([a, b, a + segments], 1), np.stack([b, b + segments, a + segments], 1)]
    bottom, top = len(pts) - 2, len(pts) - 1
    faces.append(np.stack([np.full(segments, bottom), jn, j], 1))
    last = (rings - 1) * segments
    faces.append(np.stack([np.full(segments, top), last + j, last + jn], 1))
    return pts, np.vstack(faces)


def _room(rng, x0, y0, z0, size, wall, stairs):
    """Box lists (lo, hi) and extra meshes of one room whose floor corner is (x0, y0, z0)."""
    sx, sy, sz = size
    lo, hi = [], []

    def box(a, b):
        lo.append(a)
        hi.append(b)

    t = wall
    box((x0, y0, z0 - t), (x0 + sx, y0 + sy, z0))                        # floor slab
    # Walls on the -x and -y sides (the neighbours' walls close the room), each with a door.
    for axis in (0, 1):
        length = sx if axis == 0 else sy
        door = rng.uniform(0.2, 0.6) * length
        width = min(1.0, 0.25 * length)
        pieces = [(0.0, door, 0.0, sz), (door + width, length, 0.0, sz),
                  (door, door + width, 2.1, sz)]
        for a, b, za, zb in pieces:
            if axis == 0:   # wall along x at y = y0
                box((x0 + a, y0, z0 + za), (x0 + b, y0 + t, z0 + zb))
            else:           # wall along y at x = x0
                box((x0, y0 + a, z0 + za), (x0 + t, y0 + b, z0 + zb))
    # Columns in the corners.
    for cx, cy in ((0.3, 0.3), (sx - 0.6, 0.3), (0.3, sy - 0.6), (sx - 0.6, sy - 0.6)):
        box((x0 + cx, y0 + cy, z0), (x0 + cx + 0.3, y0 + cy + 0.3, z0 + sz))
    # A table with four legs, and chairs.
    tx, ty = x0 + rng.uniform(1.2, sx - 2.8), y0 + rng.uniform(1.2, sy - 2.2)
    box((tx, ty, z0 + 0.72), (tx + 1.6, ty + 0.9, z0 + 0.76))
    for lx, ly in ((0.05, 0.05), (1.5, 0.05), (0.05, 0.8), (1.5, 0.8)):
        box((tx + lx, ty + ly, z0), (tx + lx + 0.05, ty + ly + 0.05, z0 + 0.72))
    for k in range(4):
        cx = tx + 0.2 + 0.7 * (k % 2)
        cy = ty - 0.55 if k < 2 else ty + 1.0
        box((cx, cy, z0 + 0.42), (cx + 0.45, cy + 0.45, z0 + 0.46))         # seat
        box((cx, cy + (0.4 if k < 2 else 0.0), z0 + 0.46),
            (cx + 0.45, cy + (0.45 if k < 2 else 0.05), z0 + 0.95))        # back
        for lx, ly in ((0, 0), (0.4, 0), (0, 0.4), (0.4, 0.4)):
            box((cx + lx, cy + ly, z0), (cx + lx + 0.04, cy + ly + 0.04, z0 + 0.42))
    # A shelf against the +x side: two sides, a back and five boards.
    shx, shy = x0 + sx - 0.45, y0 + rng.uniform(0.8, sy - 2.2)
    box((shx, shy, z0), (shx + 0.4, shy + 0.03, z0 + 2.0))
    box((shx, shy + 1.2, z0), (shx + 0.4, shy + 1.23, z0 + 2.0))
    box((shx + 0.37, shy, z0), (shx + 0.4, shy + 1.23, z0 + 2.0))
    for k in range(5):
        box((shx, shy, z0 + 0.05 + 0.45 * k), (shx + 0.37, shy + 1.23, z0 + 0.08 + 0.45 * k))
    # Stairs: a flight of 14 steps rising to the ceiling along y.
    if stairs:
        run = min(0.28, (sy - 1.5) / 14)
        for k in range(14):
            box((x0 + 1.0, y0 + 0.6 + k * run, z0),
                (x0 + 2.2, y0 + 0.6 + (k + 1) * run, z0 + (k + 1) * sz / 14))
    meshes = [_vase((tx + rng.uniform(0.3, 1.3), ty + rng.uniform(0.2, 0.7), z0 + 0.76),
                    0.08, 0.3)]
    for k in range(3):
        meshes.append(_vase((shx + 0.2, shy + 0.3 + 0.3 * k, z0 + 0.53), 0.05, 0.25, 10, 5))
    return lo, hi, meshes


def architecture_scene(rooms=(4, 3), floors=2, room_size=(6.0, 5.0, 3.0), wall=0.2, seed=0):
    """A building of rooms[0] x rooms[1] rooms on `floors` storeys with outer walls and a roof.

    Returns (vertices float32 (V, 3), triangles uint32 (T, 3)); ~1,000 triangles per room.
    """
    rng = np.random.default_rng(seed)
    nx, ny = rooms
    sx, sy, sz = room_size
    lo, hi, meshes = [], [], []
    for f in range(floors):
        for i in range(nx):
            for j in range(ny):
                l, h, m = _room(rng, i * sx, j * sy, f * sz, room_size, wall,
                                stairs=(i, j) == (f % nx, 0))
                lo += l
                hi += h
                meshes += m
    width, depth, height = nx * sx, ny * sy, floors * sz
    # Outer walls on the +x and +y sides and the roof.
    lo += [(width, 0, 0), (0, depth, 0), (0, 0, height)]
    hi += [(width + wall, depth + wall, height), (width + wall, depth + wall, height),
           (width + wall, depth + wall, height + wall)]
    vertices, triangles = boxes(np.array(lo), np.array(hi))
    parts_v, parts_t, offset = [vertices], [triangles], len(vertices)
    for v, t in meshes:
        parts_v.append(v)
        parts_t.append(t + offset)
        offset += len(v)
    return np.vstack(parts_v).astype(np.float32), np.vstack(parts_t).astype(np.uint32)
