"""The viewport's Blender side (tests/bpy_scripts/viewport_draw.py): the camera made of a
viewport's matrices is the scene camera's where they agree, and the add-on's drawing code puts
a ViewportSession's image on the screen, read back from an RGBA32F offscreen. (Blender calls
view_update and view_draw only with a window: docs/viewport.md says how those were checked.)"""
import numpy as np
import pytest

from tests.blender import build_extension, run_bpy_script

WIDTH, HEIGHT = 48, 36


@pytest.fixture(scope="module")
def drawn(tmp_path_factory):
    work = tmp_path_factory.mktemp("viewport")
    result = run_bpy_script("viewport_draw", work, zip=str(build_extension(work / "dist")),
                            out=str(work), width=WIDTH, height=HEIGHT)
    return work, result


def test_the_viewport_camera_through_the_scene_camera_is_f12s(drawn):
    _, result = drawn
    assert result["camera_error"] < 1e-5     # Blender's matrices are float32


def test_the_session_image_is_drawn_as_it_is(drawn):
    """The drawing code puts the session's pixels on the region (through a half-float
    texture: to its precision); the display transform is Blender's, bound by
    bind_display_space_shader as the API's example engine does."""
    work, result = drawn
    session, screen = np.load(work / "session.npy"), np.load(work / "drawn.npy")
    assert result["final"] and session.shape == screen.shape == (HEIGHT, WIDTH, 4)
    assert session[..., :3].std() > 0.02, "the scene should show something"
    np.testing.assert_allclose(screen, session, rtol=1e-3, atol=1e-4)
