"""Issue 14's scenes rendered with Cycles and with KD Trace inside Blender (the installed
add-on, local slaves) at matched settings (tests/bpy_scripts/cycles_scenes.py): the world as
a colour (sky fill) and as an HDRI (equirectangular and mirror ball, through a Mapping node),
a room lit only by an emissive mesh, the BSDF nodes and Principled inputs, glass under an area
light, Film > Transparent with a holdout, ray visibility, depth of field, camera and
object motion blur, shader node programs and procedural textures, texture coordinates through
Mapping nodes (as Blender's glTF importer makes them), the Material and World Output Cycles
uses where there are several, Mix and Add Shaders (closures), Translucent and Transparent
BSDFs, the Voronoi, Wave, Magic, Brick and White Noise textures, Color Attribute, Attribute,
Object Info, Geometry and Light Path, the Sky Texture (Multiple and Single Scattering with
their sun discs, Preetham through a Mapping node), Principled Coat, point and spot lights
with Soft Falloff off, and odd input (an object
scaled to 0 on an axis and on all, text, curve and metaball objects, an image that cannot be
loaded, an area light flattened to a line). Compared by PSNR on Combined (and alpha); each scene's kernel compiles exactly the features it
uses; what is not supported is named in warnings. docs/cycles_features.md lists the rows."""
from __future__ import annotations

import json

import numpy as np
import pytest

from kdtrace.core.scene.model import RenderSettings
from tests.blender import build_extension, run_bpy_script

WIDTH, HEIGHT = 64, 48
# scene -> (samples per pixel: N x N for both, the features its kernel compiles, exactly)
SCENES = {
    "world_color": (8, {"BOUNCES", "SMOOTH", "SOFT_LIGHTS", "SPECULAR", "SUN", "WORLD"}),
    "world_hdri": (12, {"BOUNCES", "SMOOTH", "SPECULAR", "WORLD", "WORLD_TEXTURE"}),
    "world_mirror_ball": (12, {"BOUNCES", "SMOOTH", "SPECULAR", "WORLD", "WORLD_TEXTURE"}),
    "emission_room": (12, {"BOUNCES", "EMISSION", "SMOOTH", "SPECULAR"}),
    "materials": (16, {"AREA", "BOUNCES", "EMISSION", "SMOOTH", "SPECULAR", "TRANSMISSION",
                       "WORLD"}),
    "glass": (20, {"AREA", "BOUNCES", "SMOOTH", "SPECULAR", "TRANSMISSION", "WORLD"}),
    "film_holdout": (12, {"ALPHA", "AREA", "BOUNCES", "HOLDOUT", "SMOOTH", "SPECULAR",
                          "TRANSPARENT_FILM", "WORLD"}),
    "ray_visibility": (16, {"BOUNCES", "SMOOTH", "SOFT_LIGHTS", "SPECULAR", "SUN", "VISIBILITY",
                            "WORLD"}),
    "depth_of_field": (12, {"AREA", "BOUNCES", "DOF", "SMOOTH", "WORLD"}),
    "camera_motion": (12, {"BOUNCES", "CAMERA_MOTION", "SMOOTH", "SOFT_LIGHTS", "SUN", "WORLD"}),
    "object_motion": (12, {"BOUNCES", "INSTANCES", "OBJECT_MOTION", "SMOOTH", "SOFT_LIGHTS",
                           "SUN", "WORLD"}),
    "nodes": (12, {"AREA", "BOUNCES", "NODES", "SMOOTH", "SPECULAR", "TEXTURES", "WORLD"}),
    "nodes_more": (12, {"AREA", "BOUNCES", "NODES", "SMOOTH", "SPECULAR", "TEXTURES", "WORLD"}),
    "generated": (12, {"AREA", "BOUNCES", "NODES", "SMOOTH", "SPECULAR", "WORLD"}),
    "mapping": (12, {"AREA", "BOUNCES", "NODES", "SMOOTH", "SPECULAR", "TEXTURES", "WORLD"}),
    "outputs": (12, {"AREA", "BOUNCES", "SMOOTH", "SPECULAR", "WORLD"}),
    "degenerate": (12, {"AREA", "BOUNCES", "NODES", "SMOOTH", "SPECULAR", "TEXTURES", "WORLD"}),
    "procedural": (12, {"AREA", "BOUNCES", "BUMP", "EMISSION", "NODES", "NOISE", "NORMAL_MAP",
                        "SMOOTH", "SPECULAR", "TEXTURES", "WORLD"}),
    "closures": (12, {"ALPHA", "AREA", "BOUNCES", "CLOSURES", "EMISSION", "HOLDOUT", "NODES",
                      "SMOOTH", "SPECULAR", "TRANSPARENT_FILM", "VISIBILITY", "WORLD"}),
    "translucent": (12, {"ALPHA", "AREA", "BOUNCES", "CLOSURES", "SMOOTH", "TRANSLUCENT", "WORLD"}),
    "textures": (12, {"AREA", "BOUNCES", "NODES", "NOISE", "SMOOTH", "SPECULAR", "VORONOI", "WORLD"}),
    "sky_multiple": (12, {"BOUNCES", "SMOOTH", "SPECULAR", "WORLD", "WORLD_TEXTURE"}),
    "sky_single": (12, {"BOUNCES", "SMOOTH", "SPECULAR", "WORLD", "WORLD_TEXTURE"}),
    "sky_preetham": (12, {"BOUNCES", "SMOOTH", "SPECULAR", "WORLD", "WORLD_TEXTURE"}),
    "coat": (12, {"AREA", "BOUNCES", "COAT", "NODES", "SMOOTH", "SPECULAR", "WORLD"}),
    "soft_falloff": (12, {"BOUNCES", "POINT", "SMOOTH", "SOFT_LIGHTS", "SPHERE_LIGHTS", "SPOT",
                          "WORLD"}),
    "attributes": (12, {"ALPHA", "AREA", "BOUNCES", "CLOSURES", "EMISSION", "LIGHT_PATH", "NODES",
                        "SMOOTH", "SPECULAR", "TEXTURES", "WORLD"}),
}
# What a scene's export may warn of (each warning names the object or material, and each
# expected fragment is found): the rest must export without a warning.
WARNED = {"degenerate": ["material 'lost texture': image 'lost' could not be loaded",
                         "object 'Sphere': 2208 zero-area face(s) dropped",
                         "object 'Text': 4 zero-area face(s) dropped"]}
# Cycles' Light Paths defaults (also ours), uniform sampling, the samples of each scene.
MATCHED = {name: value for name, value in RenderSettings().to_dict().items()
           if name not in ("samples_per_axis", "adaptive", "adaptive_threshold",
                           "adaptive_min_samples", "seed")}
MATCHED.update(adaptive=False, light_samples_per_axis=1)


def psnr(image, reference, channels=slice(0, 3)) -> float:
    a, b = np.clip(image[..., channels], 0, 1), np.clip(reference[..., channels], 0, 1)
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    work = tmp_path_factory.mktemp("cycles_scenes")
    result = run_bpy_script(
        "cycles_scenes", work, timeout=900, zip=str(build_extension(work / "dist")),
        out=str(work), scenes=[*SCENES, "warned"], width=WIDTH, height=HEIGHT, kdtrace=MATCHED,
        per_scene={name: {"samples_per_axis": n} for name, (n, _) in SCENES.items()})
    return work, result


@pytest.mark.parametrize("name", list(SCENES))
def test_scene_matches_cycles(renders, name):
    work, result = renders
    cycles, ours = np.load(work / f"{name}-cycles.npy"), np.load(work / f"{name}-kdtrace.npy")
    assert cycles.shape == ours.shape == (HEIGHT, WIDTH, 4) and np.isfinite(ours).all()
    value = psnr(ours, cycles)
    # The brightness a viewer sees, clipped to the display range as psnr is: a sample on a
    # pixel-sized glint (ray_visibility's sun in the mirror, radiance ~3,000) would move the
    # whole image's mean by 1 % on its own, in either engine.
    ratio = np.clip(ours[..., :3], 0, 1).mean() / np.clip(cycles[..., :3], 0, 1).mean()
    print(f"{name}: PSNR {value:.2f} dB, mean ours / Cycles {ratio:.4f}, "
          f"{result['timings'][name + '-kdtrace']:.1f} s / {result['timings'][name + '-cycles']:.1f} s")
    assert value >= 30.0
    assert abs(ratio - 1) < 0.02
    expected = WARNED.get(name, [])
    assert len(result["warnings"][name]) == len(expected)
    for fragment in expected:
        assert any(fragment in warning for warning in result["warnings"][name]), fragment


@pytest.mark.parametrize("name", list(SCENES))
def test_features_a_scene_does_not_use_are_off(renders, name):
    work, _ = renders
    assert set(json.loads((work / f"{name}-features.json").read_text())) == SCENES[name][1]


def test_transparent_film_and_holdout_alpha_match_cycles(renders):
    """Film > Transparent and a holdout cube (behind a cut-out leaf, and in a mirror ball):
    alpha as Cycles' (the colours: test_scene_matches_cycles)."""
    work, _ = renders
    cycles, ours = (np.load(work / f"film_holdout-{who}.npy") for who in ("cycles", "kdtrace"))
    assert (cycles[..., 3] < 0.01).mean() > 0.1 and ((cycles[..., 3] > 0.2) & (cycles[..., 3] < 0.8)).any()
    value = psnr(ours, cycles, 3)
    print(f"film_holdout alpha: PSNR {value:.2f} dB")
    assert value >= 30.0


def test_closures_alpha_matches_cycles(renders):
    """Mixed closures on a transparent film: a Holdout mixed in by half, Transparent closures
    by a checker and added to a diffuse pane; alpha as Cycles' (its holdout and transparency)."""
    work, _ = renders
    cycles, ours = (np.load(work / f"closures-{who}.npy") for who in ("cycles", "kdtrace"))
    assert ((cycles[..., 3] > 0.2) & (cycles[..., 3] < 0.8)).any()
    value = psnr(ours, cycles, 3)
    print(f"closures alpha: PSNR {value:.2f} dB")
    assert value >= 30.0


def test_glass_shows_the_area_lights_highlight(renders):
    """The area light's reflection in the glass spheres: the brightest pixels of both renders
    (beyond the display range) lie at the same place, and are as bright."""
    work, _ = renders
    cycles, ours = (np.load(work / f"glass-{who}.npy")[..., :3].mean(-1) for who in ("cycles", "kdtrace"))
    peak = np.unravel_index(np.argmax(cycles), cycles.shape)
    assert cycles[peak] > 2.0, "the scene should show the highlight"
    near = ours[max(peak[0] - 1, 0):peak[0] + 2, max(peak[1] - 1, 0):peak[1] + 2]
    assert near.max() == ours.max()
    assert 0.75 < ours.max() / cycles.max() < 1.33


def test_unsupported_things_are_named(renders):
    """One warning per material, world and light, naming it (and the object) and what is not
    rendered."""
    _, result = renders
    warnings = result["warnings"]["warned"]
    def one(*words):
        found = [w for w in warnings if all(word in w for word in words)]
        assert len(found) == 1, (words, warnings)
    one("world 'sky world'", "HOSEK_WILKIE sky model is not computed")
    one("material 'brushed'", "object 'brushed ball'", "Anisotropic", "Normal",
        "'Sheen Weight'", "'Subsurface Weight' (0.3) is rendered as diffuse", "Subsurface Radius")
    one("material 'toon'", "object 'toon floor'", "Toon")
    one("light 'narrow area'", "spread")
    one("object 'moving box'", "motion blur", "parents")
    one("object 'spinning box'", "motion blur", "turns or scales through zero")
    one("object 'two maps'", "material 'second uvs'", "'second'", "one UV map per mesh")
    one("material 'noisy'", "object 'noisy cube'", "Gabor Texture", "Volume shader is not rendered",
        "Displacement is not rendered")
    assert len(warnings) == 8, warnings
