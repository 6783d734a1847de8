"""A tile's passes beside the image (kernels/shade/film.cl): the FILM records the render kernel
sums into when the frame asks for such passes (core/scene/features.py pass_features), and the
passes finished from them as Cycles finishes its own (docs/shading.md, "Passes"):

    film = TileFilm(cl, context, flags, pixel_count)   # no buffer unless FILM is compiled
    values = {**values, **film.values}                 # the kernel's "film" argument
    film.read(queue)                                   # after the tile's samples
    film.passes(view, w, h, names)                     # name -> (h, w[, c]) float32

Every sum is divided by the samples the pixel traced into it (adaptive sampling: its own
count). Pixels that adaptive undersampling filled without tracing take the mean of their traced
neighbours, as their colour did.
"""
from __future__ import annotations

import numpy as np

from ..core.layout import FILM

# pass name -> (FILM slot, how it is finished)
FILM_PASSES = {"albedo": "albedo", "denoising_normal": "guide_normal", "mist": "mist",
               "emission": "emission", "diffuse_color": "diffuse_color",
               "glossy_color": "glossy_color"}
# Cycles' camera space: Blender's camera axes with z turned to look along +z (its
# blender_camera_matrix scales z by -1), so a normal facing the camera has z < 0.
CYCLES_CAMERA_AXES = np.array([1.0, 1.0, -1.0])


class TileFilm:
    """The FILM records of one tile on the device (none unless `flags` has FILM)."""

    def __init__(self, cl, context, flags, pixel_count: int):
        self._cl = cl
        self.records = None
        self.values = {}
        if "FILM" in flags:
            self.records = np.zeros((pixel_count, 4 * FILM.size), np.float32)
            self.buffer = cl.Buffer(context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR,
                                    hostbuf=self.records)
            self.values = {"film": self.buffer}

    def read(self, queue) -> None:
        if self.records is not None:
            self._cl.enqueue_copy(queue, self.records, self.buffer)

    def passes(self, view, w: int, h: int, names) -> dict:
        """The passes `names` asks for that the film holds, finished (after read())."""
        wanted = [name for name in names if name in FILM_PASSES]
        if not wanted:
            return {}
        if self.records is None:
            raise ValueError(f"passes {wanted} need the FILM feature in the render kernel")
        return finish_passes(self.records, view, w, h, wanted)


def finish_passes(records: np.ndarray, view, w: int, h: int, names) -> dict:
    """The passes `names` of a w x h tile's FILM records (n, 4 * FILM.size)."""
    rows = records.reshape(h, w, FILM.size, 4)
    samples = FILM.get(rows, "samples")
    traced = samples > 0
    out = {}
    count = np.maximum(samples, 1.0)
    for name in names:
        total = FILM.get(rows, FILM_PASSES[name])
        value = fill_untraced(total / (count if total.ndim == 2 else count[..., None]), traced)
        if name == "denoising_normal":
            value = camera_space(value, view.camera.to_world)
        elif name == "mist":            # the sums are of 1 - mist (the world: mist 1)
            value = 1.0 - value
        out[name] = np.ascontiguousarray(value, np.float32)
    return out


def camera_space(normals: np.ndarray, to_world: np.ndarray) -> np.ndarray:
    """World-space directions in Cycles' camera space (rotation only: Cycles clears the
    camera's scale)."""
    axes = np.asarray(to_world, np.float64)[:3, :3]
    axes = axes / np.maximum(np.linalg.norm(axes, axis=0, keepdims=True), 1e-30)
    return (normals @ axes) * CYCLES_CAMERA_AXES


def fill_untraced(value: np.ndarray, traced: np.ndarray) -> np.ndarray:
    """`value` (h, w[, c]) with each untraced pixel the mean of its traced 8 neighbours (none:
    left as it is, 0)."""
    if traced.all():
        return value
    h, w = traced.shape
    weight = traced.astype(np.float64)
    v = value if value.ndim == 3 else value[..., None]
    padded_v = np.pad(v * weight[..., None], ((1, 1), (1, 1), (0, 0)))
    padded_w = np.pad(weight, 1)
    total = np.zeros_like(v, dtype=np.float64)
    count = np.zeros((h, w))
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            total += padded_v[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
            count += padded_w[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
    filled = np.where((~traced & (count > 0))[..., None], total / np.maximum(count, 1)[..., None], v)
    return filled if value.ndim == 3 else filled[..., 0]
