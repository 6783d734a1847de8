"""Shading against Cycles and the exporter's materials, through Tracer in-process.

A bpy subprocess builds each scene, exports it with the add-on's exporter (keeping the optional
arrays) and, for the light scene, renders it with Cycles, direct light only."""
from __future__ import annotations

import json

import numpy as np
import pytest

from kdtrace.core.scene.features import scene_features
from kdtrace.core.scene.model import Geometry, RenderSettings, View
from kdtrace.core.scene.scene import Scene
from tests.blender import build_extension, run_bpy_script

WIDTH, HEIGHT = 96, 72


def psnr(a, b) -> float:
    a, b = np.clip(a[..., :3], 0, 1), np.clip(b[..., :3], 0, 1)
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def load_exported(work):
    with np.load(work / "scene.npz") as arrays:
        geometry = Geometry(**{name: arrays[name] for name in arrays.files})
    view = View.from_dict(json.loads((work / "view.json").read_text()))
    return geometry, view


def render(geometry, view, **settings):
    from kdtrace.core.accel.kdtree import build_kdtree
    from kdtrace.slave.tracer import Tracer
    tracer = Tracer()
    tracer.load(Scene.from_parts(geometry, build_kdtree(geometry.vertices, geometry.triangles)))
    view.settings = RenderSettings(**settings)
    return tracer.render_tile(view, 0, 0, view.width, view.height), tracer


@pytest.fixture(scope="module")
def extension(tmp_path_factory):
    return build_extension(tmp_path_factory.mktemp("dist"))


@pytest.fixture(scope="module")
def lights_scene(extension, tmp_path_factory):
    work = tmp_path_factory.mktemp("lights")
    result = run_bpy_script("shading_scenes", work, zip=str(extension), out=str(work),
                            scene="lights", width=WIDTH, height=HEIGHT, cycles_samples=256)
    return work, result


@pytest.fixture(scope="module")
def materials_scene(extension, tmp_path_factory):
    work = tmp_path_factory.mktemp("materials")
    result = run_bpy_script("shading_scenes", work, zip=str(extension), out=str(work),
                            scene="materials", width=WIDTH, height=HEIGHT, world=[0.05, 0.05, 0.08])
    return work, result


def test_direct_light_matches_cycles(lights_scene):
    """Point, sun, spot and area lights (with radii and angles) on diffuse objects, direct
    light only: our render and Cycles' agree within PSNR 35 dB."""
    work, result = lights_scene
    geometry, view = load_exported(work)
    assert result["warnings"] == []
    assert {"POINT", "SUN", "SPOT", "AREA", "SOFT_LIGHTS", "SMOOTH"} <= scene_features(geometry, view)
    cycles = np.load(work / "cycles.npy")
    ours, _ = render(geometry, view, samples_per_axis=8, light_samples_per_axis=2, max_bounces=0)
    image = ours["combined"]
    assert np.isfinite(image).all()
    value = psnr(image, cycles)
    ratio = np.median(image[..., :3].mean(-1)[cycles[..., :3].mean(-1) > 0.05]
                      / cycles[..., :3].mean(-1)[cycles[..., :3].mean(-1) > 0.05])
    print(f"PSNR against Cycles {value:.2f} dB, median ratio ours/Cycles {ratio:.4f}")
    assert value >= 35.0


def test_materials_export_and_render(materials_scene):
    work, result = materials_scene
    geometry, view = load_exported(work)
    # One warning for the material KD Trace cannot map, naming it.
    assert len(result["warnings"]) == 1 and "'toon'" in result["warnings"][0], result["warnings"]
    features = scene_features(geometry, view)
    assert {"TEXTURES", "SMOOTH", "TRANSMISSION", "SPECULAR", "EMISSION", "ALPHA",
            "BOUNCES"} <= features
    assert geometry.normals is not None and geometry.uvs is not None
    assert geometry.texels.shape == (64, 4) and geometry.texture_sizes.tolist() == [[0, 8, 8]]
    passes, _ = render(geometry, view, samples_per_axis=2, max_bounces=6)
    image = passes["combined"]
    assert np.isfinite(image).all() and np.isfinite(passes["depth"]).all()
    # The emissive cube is brighter than any lit diffuse surface could be here.
    assert image[..., :3].max() > 3.0
    # The checker texture shows both of its colours (red-ish and blue-ish texels).
    rgb = image[..., :3].reshape(-1, 3)
    assert ((rgb[:, 0] > 2 * rgb[:, 2]) & (rgb[:, 0] > 0.1)).any()
    assert ((rgb[:, 2] > 2 * rgb[:, 0]) & (rgb[:, 2] > 0.1)).any()


def test_bad_input_is_named_and_cleaned(extension, tmp_path):
    """Empty meshes are skipped and zero-area faces dropped, each with a warning naming the
    object; an object with NaN vertices is skipped with a warning naming it (the render goes
    on: tests/test_degenerate_input.py)."""
    result = run_bpy_script("shading_scenes", tmp_path, zip=str(extension), out=str(tmp_path),
                            scene="bad", width=32, height=24)
    warnings = result["warnings"]
    assert any("'empty'" in w and "no faces" in w for w in warnings), warnings
    assert any("'degenerate'" in w and "2 zero-area" in w for w in warnings), warnings
    assert result["triangles"] == 2
    # The objects' triangles one after another, each indexing its own vertices; the flat
    # object's face normal at its corners beside the smooth one's kept corners.
    arrays = result["arrays"]
    assert len(arrays["vertices"]) == 8
    assert arrays["triangles"] == [[0, 1, 2], [3, 4, 5]], arrays["triangles"]
    assert np.allclose(arrays["normals"], [[0, 0, 1]] * 6, atol=1e-6), arrays["normals"]
    assert any("'good'" in w and "NaN or infinite" in w and "skipped" in w
               for w in result["nan_warnings"]), result["nan_warnings"]
    assert result["nan_triangles"] == 1      # the other object's good face


def test_tiles_match_the_full_image_with_supersampling():
    """Seeds come from the global pixel index: a tile equals the same pixels of the full image
    (uniform supersampling with soft lights), and renders repeat exactly."""
    from kdtrace.core.accel.kdtree import build_kdtree
    from kdtrace.core.scene.model import Camera, Light, Shading
    from kdtrace.slave.tracer import Tracer
    from tests.meshes import grid_plane, merge, uv_sphere
    vertices, triangles = merge(uv_sphere(16, 8, 1.0, (0, 0, 1)), grid_plane(6.0, 2, 0.0))
    tracer = Tracer()
    tracer.load(Scene.from_parts(Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16)),
                build_kdtree(vertices, triangles)))
    m = np.eye(4)
    m[:3, 3] = (0, 0, 8)
    lights = [Light("AREA", (1, 1, 1), 300.0, (1, -1, 4), shape="ELLIPSE", size_u=1.5, size_v=0.7),
              Light("POINT", (1, 1, 1), 200.0, (-2, 1, 3), radius=0.5)]
    view = View(Camera("PERSP", m, (0.5, 0.5), (0, 0), 0.1, 100), 40, 30,
                Shading(np.array([[0.8, 0.8, 0.8, 1]], np.float32), lights, (0, 0, 0)),
                settings=RenderSettings(samples_per_axis=3, light_samples_per_axis=2))
    full = tracer.render_tile(view, 0, 0, 40, 30)
    tile = tracer.render_tile(view, 13, 7, 11, 9)
    for name in full:
        np.testing.assert_array_equal(tile[name], full[name][7:16, 13:24])
    np.testing.assert_array_equal(tracer.render_tile(view, 0, 0, 40, 30)["combined"], full["combined"])
    view.settings.adaptive = True
    first = tracer.render_tile(view, 0, 0, 40, 30)["combined"]
    np.testing.assert_array_equal(tracer.render_tile(view, 0, 0, 40, 30)["combined"], first)
