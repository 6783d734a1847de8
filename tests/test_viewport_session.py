"""The viewport's session without Blender (core/frame/viewport.py): a scripted host changes the
view and edits the scene (an object moved, a material, the world, a light, a mesh) at random
moments while local slaves render; after the last change the image is an F12 frame of that
view at the same samples, bit for bit; an image of a cancelled change never replaces a newer
one; cancelled frames are confirmed by the slaves."""
from __future__ import annotations

import dataclasses
import random
import time

import numpy as np
import pytest

from kdtrace.core.frame.exported import load_export
from kdtrace.core.frame.options import FrameOptions
from kdtrace.core.frame.render import render_frame
from kdtrace.core.frame.session import FrameSession
from kdtrace.core.frame.viewport import PREVIEW_PIXELS, ViewportSession, passes
from kdtrace.core.scene.model import Geometry
from tests.test_frame_session import ScriptedHost, f12  # noqa: F401 (the F12 fixture)

SAMPLES = 2         # the viewport's N: passes at 1 and 2 x 2 samples


@pytest.fixture(scope="module")
def session():
    session = FrameSession()
    yield session
    session.close()


def options(denoise=None) -> FrameOptions:
    """Two local slaves; F12's denoising as given (off: the viewport's default)."""
    from kdtrace.core.frame.denoising import DenoiseSettings
    return FrameOptions(use_zeroconf=False, local_slaves=2, tile_size=16,
                        denoise=denoise or DenoiseSettings(enabled=False))


def wait_done(viewport, seconds=120):
    deadline = time.monotonic() + seconds
    while not viewport.done():
        assert time.monotonic() < deadline, "the viewport did not finish"
        time.sleep(0.01)


def f12_image(session, exported, view):
    """What F12 renders of `view` at the viewport's samples (render_frame, uniform)."""
    settings = dataclasses.replace(view.settings, samples_per_axis=SAMPLES, adaptive=False)
    host = ScriptedHost()
    render_frame(session, exported, dataclasses.replace(view, settings=settings), options(), host)
    return host.image["combined"]


def edits(exported, view):
    """(what changed, export or None, view) for each kind of change the viewport sees."""
    camera = view.camera
    moved_camera = dataclasses.replace(camera, to_world=camera.to_world.copy())
    moved_camera.to_world[:3, 3] += (0.3, 0.2, 0.0)
    shading = view.shading
    materials = shading.materials.copy()
    materials[:, :3] = materials[:, :3][:, ::-1]
    lights = [dataclasses.replace(light, power=light.power * 2) for light in shading.lights]
    to_world = exported.to_world.copy()
    to_world[-1, :3, 3] += (0.4, 0.0, 0.0)
    mesh = exported.meshes[-1]
    edited = Geometry(**dict(mesh.arrays(), vertices=mesh.vertices * np.float32(1.1)))
    return [
        ("camera", None, dataclasses.replace(view, camera=moved_camera)),
        ("material", None, dataclasses.replace(view, shading=dataclasses.replace(
            shading, materials=materials))),
        ("world", None, dataclasses.replace(view, shading=dataclasses.replace(
            shading, world_color=(0.2, 0.3, 0.5)))),
        ("light", None, dataclasses.replace(view, shading=dataclasses.replace(
            shading, lights=lights))),
        ("object moved", exported._replace(to_world=to_world), view),
        ("mesh edited", exported._replace(meshes=[*exported.meshes[:-1], edited]), view),
    ]


def test_passes_preview_then_doubling_samples():
    from kdtrace.core.scene.model import Camera, RenderSettings, Shading, View
    view = View(Camera("PERSP", np.eye(4), (1, 1), (0, 0), 0.1, 100), 960, 540,
                Shading(np.array([[1, 1, 1, 1]], np.float32), [], (0, 0, 0)),
                settings=RenderSettings(adaptive=True))
    views = passes(view, 16)
    assert (views[0].width, views[0].height) == (PREVIEW_PIXELS, 90)
    assert views[0].region == (0, 0, PREVIEW_PIXELS, 90)
    assert [v.settings.samples_per_axis for v in views] == [1, 1, 2, 4, 8, 16]
    assert all(v.width == 960 and not v.settings.adaptive for v in views[1:])
    assert [v.settings.samples_per_axis for v in passes(view, 6)] == [1, 1, 2, 4, 6]


def test_the_last_pass_is_f12_bit_for_bit(f12, session):  # noqa: F811
    """The viewport's last pass is render_frame's image of the view at the viewport's samples
    (which tests/test_frame_session.py shows is F12's in Blender)."""
    exported, view = load_export(f12 / "export.npz")
    viewport = ViewportSession(session, options(), samples_per_axis=SAMPLES)
    try:
        viewport.update(view, exported)
        wait_done(viewport)
        assert not viewport.error
        shown = viewport.image()
        assert shown.final and shown.samples == SAMPLES ** 2
        assert np.array_equal(shown.pixels, f12_image(session, exported, view))
    finally:
        viewport.close()


def test_changes_at_random_moments_end_in_the_last_views_f12_image(f12, session):  # noqa: F811
    exported, view = load_export(f12 / "export.npz")
    rng = random.Random(3)
    viewport = ViewportSession(session, options(), samples_per_axis=SAMPLES)
    seen = []           # every image drawn: (epoch it claims, pixels)
    try:
        epochs = {viewport.update(view, exported): (exported, view)}
        for name, changed_export, changed_view in edits(exported, view) * 2:
            deadline = time.monotonic() + rng.uniform(0.0, 0.8)
            while time.monotonic() < deadline:
                shown = viewport.image()
                if shown is not None and (not seen or seen[-1][0] is not shown):
                    seen.append((shown, shown.pixels.copy()))
                time.sleep(0.005)
            exported = changed_export or exported
            view = changed_view
            epochs[viewport.update(view, changed_export)] = (exported, view)
        wait_done(viewport)
        assert not viewport.error, viewport.error
        last = viewport.image()
        assert last.epoch == max(epochs) and last.final
        assert np.array_equal(last.pixels, f12_image(session, exported, view))
        # Images only ever move to newer changes, and a change's final image is F12's of
        # that change (up to three checked).
        assert [s.epoch for s, _ in seen] == sorted(s.epoch for s, _ in seen)
        finals = [(s, pixels) for s, pixels in seen if s.final][:3]
        for shown, pixels in finals:
            assert np.array_equal(pixels, f12_image(session, *epochs[shown.epoch]))
        assert viewport.cancels >= 1
        assert all(seconds < 30 for seconds in viewport.cancel_seconds)
    finally:
        viewport.close()


def test_a_cancelled_change_never_replaces_a_newer_one(f12, session):  # noqa: F811
    """Two changes in quick succession: the first's frame is cancelled before it ends, and no
    image of it is ever drawn after the second change."""
    exported, view = load_export(f12 / "export.npz")
    viewport = ViewportSession(session, options(), samples_per_axis=8)
    try:
        first = viewport.update(view, exported)
        time.sleep(0.3)
        second = viewport.update(edits(exported, view)[2][2])     # the world changed
        drawn = []
        deadline = time.monotonic() + 120
        while not viewport.done() and time.monotonic() < deadline:
            shown = viewport.image()
            if shown is not None:
                drawn.append(shown.epoch)
            time.sleep(0.005)
        assert drawn and drawn[-1] == second
        after = drawn[drawn.index(second):] if second in drawn else []
        assert first not in after
    finally:
        viewport.close()


def test_a_denoised_viewport_ends_in_f12s_denoised_image(f12, session):  # noqa: F811
    """With viewport denoising on, the last pass is denoised as F12 denoises its frame (the
    same noisy pixels and guides through the same filter)."""
    from kdtrace.core.frame.denoising import DenoiseSettings
    exported, view = load_export(f12 / "export.npz")
    denoise = DenoiseSettings(enabled=True, prefilter="FAST", quality="BALANCED")
    viewport = ViewportSession(session, options(), samples_per_axis=SAMPLES, denoise=denoise)
    try:
        viewport.update(view, exported)
        wait_done(viewport)
        assert not viewport.error
        shown = viewport.image()
    finally:
        viewport.close()
    settings = dataclasses.replace(view.settings, samples_per_axis=SAMPLES, adaptive=False)
    host = ScriptedHost()
    render_frame(session, exported, dataclasses.replace(view, settings=settings),
                 options(denoise), host)
    noisy = f12_image(session, exported, view)
    assert not np.array_equal(shown.pixels, noisy)
    np.testing.assert_allclose(shown.pixels, host.image["combined"], atol=1e-3)

