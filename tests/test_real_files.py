"""Real files that nobody on this project made (tests/real_files.md), opened as a user would
(glTF 2.0 and OBJ through Blender's importers, old .blend files through File > Open) and
rendered by Cycles and by KD Trace at matched settings (tests/bpy_scripts/real_files.py): each
is within 30 dB of Cycles, and what KD Trace does not render of it is named in a warning."""
from __future__ import annotations

import numpy as np
import pytest

from tests.blender import build_extension, run_bpy_script
from tests.real_files import REAL_FILES, real_files
from tests.test_cycles_scenes import MATCHED, psnr

WIDTH, HEIGHT, SAMPLES = 96, 72, 8
# Cycles' names of the Light Paths settings that MATCHED sets for KD Trace.
CYCLES_NAMES = {"max_bounces": "max_bounces", "diffuse_bounces": "diffuse_bounces",
                "glossy_bounces": "glossy_bounces", "transmission_bounces": "transmission_bounces",
                "transparent_max_bounces": "transparent_bounces",
                "sample_clamp_direct": "clamp_direct", "sample_clamp_indirect": "clamp_indirect",
                "blur_glossy": "filter_glossy"}
# What each file's export must warn of (every warning matches one of these, each is found);
# zero-area faces dropped are always allowed.
WARNED = {"clearcoat": ["'Coat Normal' is linked; the coat uses the BSDF's normal"],
          "two_uv_maps": ["reads UV map(s) 'UVMap.001'"]}


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    work = tmp_path_factory.mktemp("real_files")
    result = run_bpy_script(
        "real_files", work, timeout=1200, zip=str(build_extension(work / "dist")), out=str(work),
        files={name: str(path) for name, path in real_files().items()}, width=WIDTH,
        height=HEIGHT, samples_per_axis=SAMPLES, kdtrace=MATCHED,
        cycles={ours: MATCHED[theirs] for ours, theirs in CYCLES_NAMES.items()})
    return work, result


@pytest.mark.parametrize("name", list(REAL_FILES))
def test_real_file_renders_as_cycles_or_says_why(renders, name):
    work, result = renders
    cycles, ours = np.load(work / f"{name}-cycles.npy"), np.load(work / f"{name}-kdtrace.npy")
    assert cycles.shape == ours.shape == (HEIGHT, WIDTH, 4) and np.isfinite(ours).all()
    assert cycles[..., :3].std() > 0.01, "the view should show something"
    value = psnr(ours, cycles)
    print(f"{name}: PSNR {value:.2f} dB, mean ours / Cycles "
          f"{ours[..., :3].mean() / cycles[..., :3].mean():.4f}, "
          f"{result['timings'][name + '-kdtrace']:.1f} s / {result['timings'][name + '-cycles']:.1f} s")
    assert value >= 30.0
    warnings = [w for w in result["warnings"][name] if "zero-area face(s) dropped" not in w]
    expected = WARNED.get(name, [])
    for fragment in expected:
        assert any(fragment in w for w in warnings), (fragment, warnings)
    assert all(any(fragment in w for fragment in expected) for w in warnings), warnings
