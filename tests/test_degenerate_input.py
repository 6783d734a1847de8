"""F12 never fails on what Blender can hold (tests/bpy_scripts/render_degenerate.py): each odd
scene renders through the add-on with write_still, and the warnings name what was skipped; an
exception inside the frame ends the render with an error report and Blender renders again.
How such scenes look against Cycles: the "degenerate" scene of test_cycles_scenes.py."""
from __future__ import annotations

import math

import pytest

from tests.blender import build_extension, run_bpy_script

# case -> fragments of the warnings it must give (each found in one warning; no others)
CASES = {
    "flat_axis": ["object 'cube': 8 zero-area face(s) dropped"],
    "flat_all": ["object 'cube': 12 zero-area face(s) dropped"],
    "nan_transform": ["object 'cube' has a transform that is NaN or infinite; skipped"],
    "no_faces": ["object 'wire' has no faces; skipped", "object 'hollow' has no faces; skipped"],
    "text_curve_metaball": ["object 'words': 4 zero-area face(s) dropped"],
    "missing_image": ["material 'lost texture': image 'lost' could not be loaded",
                      "rendered magenta"],
    "odd_lights": ["light 'lost sun' has a transform that is NaN or infinite; skipped"],
    "missing_library": ["linked from a missing library, not rendered: object 'cube'"],
}


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    work = tmp_path_factory.mktemp("degenerate")
    return run_bpy_script("render_degenerate", work, zip=str(build_extension(work / "dist")),
                          out=str(work))


@pytest.mark.parametrize("case", list(CASES))
def test_odd_scene_renders_and_names_what_it_skipped(renders, case):
    result = renders[case]
    assert result["outcome"] == "finished"
    assert result["written"] and math.isfinite(result["mean"]) and result["mean"] > 0
    assert len(result["warnings"]) == len(CASES[case]) - (case == "missing_image"), result["warnings"]
    for fragment in CASES[case]:
        assert any(fragment in warning for warning in result["warnings"]), (fragment, result)


def test_skipped_objects_leave_the_floor_alone(renders):
    """A cube scaled to nothing, with a NaN transform, or linked from a missing library: the
    same picture (the floor); the cube flattened to a square on the floor shows."""
    floor_only = renders["flat_all"]["mean"]
    assert renders["nan_transform"]["mean"] == floor_only
    assert renders["missing_library"]["mean"] == floor_only
    assert renders["flat_axis"]["mean"] != floor_only


def test_an_exception_in_the_frame_is_reported_and_blender_renders_again(renders):
    failed, again = renders["exception_in_frame"], renders["after_the_exception"]
    assert "internal error, ValueError: a defect planted by the test" in failed["outcome"]
    assert again["outcome"] == "finished" and again["written"]
    # The scene of "no_faces" renders the same picture (its wire and empty meshes skipped).
    assert again["mean"] == renders["no_faces"]["mean"]
