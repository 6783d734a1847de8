"""Film > Pixel Filter: camera samples spread over the filter as Cycles importance-samples it.
A sharp edge (white left of x = 0, black right, under a sun straight down, seen by an
orthographic camera) rendered with many samples gives, across the edge, 1 minus the filter's
cumulative distribution at each pixel centre's distance from it: computed here by integrating
Cycles' filter functions, not from slave/buffers.py's table."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.scene.model import (MATERIAL_PARAMS, Camera, Geometry, Light, RenderSettings,
                                      Shading, View, default_material_params)
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.buffers import filter_table
from kdtrace.slave.tracer import Tracer

WIDTH = 24          # pixels across [-3, 3]: 4 pixels a unit; the edge at x = 0 lies between two


def cdf(kind: str, width: float, x: np.ndarray) -> np.ndarray:
    """The filter's mass left of x (pixels), by the trapezoidal rule on a fine grid."""
    if kind == "BOX":
        return np.clip(x / width + 0.5, 0.0, 1.0)
    span = {"GAUSSIAN": 3.0, "BLACKMAN_HARRIS": 2.0}[kind] * width
    v = np.linspace(-span / 2, span / 2, 200001)
    if kind == "GAUSSIAN":
        f = np.exp(-2.0 * (v * 6.0 / span) ** 2)
    else:
        a = 2 * np.pi * (v / span + 0.5)
        f = 0.35875 - 0.48829 * np.cos(a) + 0.14128 * np.cos(2 * a) - 0.01168 * np.cos(3 * a)
    c = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(v))])
    return np.interp(x, v, c / c[-1])


@pytest.fixture(scope="module")
def tracer():
    # Two quads: white left of x = 0, black right of it, wider than the view (+-3).
    v = np.array([[-9, -9, 0], [0, -9, 0], [0, 9, 0], [-9, 9, 0], [9, -9, 0], [9, 9, 0]], np.float32)
    t = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]], np.uint32)
    tracer = Tracer()
    tracer.load(Scene.from_parts(Geometry(v, t, np.array([0, 0, 1, 1], np.uint16)),
                                 build_kdtree(v, t)))
    return tracer


def edge_row(tracer, kind, width, samples_per_axis=32):
    params = default_material_params(2)
    params[:, MATERIAL_PARAMS.index("specular")] = 0.0
    shading = Shading(np.array([[1, 1, 1, 1], [0, 0, 0, 1]], np.float32),
                      [Light("SUN", (1, 1, 1), np.pi, direction=(0, 0, -1))], (0, 0, 0), params)
    m = np.eye(4)
    m[2, 3] = 1.0
    settings = RenderSettings(samples_per_axis=samples_per_axis, adaptive=False, max_bounces=0,
                              pixel_filter=kind, filter_width=width)
    view = View(Camera("ORTHO", m, (3.0, 3.0), (0, 0), 0.01, 10.0), WIDTH, WIDTH, shading,
                settings=settings)
    return tracer.render_tile(view, 0, WIDTH // 2, WIDTH, 1)["combined"][0, :, 0]


@pytest.mark.parametrize("kind,width", [("BLACKMAN_HARRIS", 1.5), ("BLACKMAN_HARRIS", 3.0),
                                        ("GAUSSIAN", 1.5), ("BOX", 1.0), ("BOX", 2.5)])
def test_an_edge_is_blurred_by_the_filter(tracer, kind, width):
    row = edge_row(tracer, kind, width)
    centres = np.arange(WIDTH) + 0.5 - WIDTH / 2          # pixel centres' distance from the edge
    expected = 1.0 - cdf(kind, width, centres)              # white (1) left of the edge
    np.testing.assert_allclose(row, expected, atol=0.01)
    assert 0.05 < row[WIDTH // 2 - 1] < 0.95 or width < 1.1  # the edge's neighbours are grey


def test_the_table_is_the_inverse_cdf_and_its_middle_the_centre():
    for kind, width in (("BLACKMAN_HARRIS", 1.5), ("GAUSSIAN", 2.0)):
        table = filter_table(kind, width)
        u = np.linspace(0, 1, len(table))
        assert table[len(table) // 2] == 0.0 and np.all(np.diff(table) > 0)
        np.testing.assert_allclose(cdf(kind, width, table[1:-1]), u[1:-1], atol=2e-3)


def test_one_sample_is_the_pixel_centre_whatever_the_filter(tracer):
    """One sample per pixel stays at its centre: a pixel left of the edge is white."""
    for kind in ("BOX", "GAUSSIAN", "BLACKMAN_HARRIS"):
        row = edge_row(tracer, kind, 1.5, samples_per_axis=1)
        np.testing.assert_allclose(row, (np.arange(WIDTH) < WIDTH // 2) * 1.0, atol=1e-5)
