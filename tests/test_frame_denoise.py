"""The master denoises an F12 frame (core/frame/denoising.py): through the frame pipeline with
local slaves, a noisy render comes back denoised as one whole image (the same as denoising the
assembled noisy image at once: no seams between tiles), much closer to a high-sample reference
than the noisy one; the guides travel only when the frame is denoised; without a library the
frame says so once and keeps the noisy image; the report says how long denoising took."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.denoise import Denoiser
from kdtrace.core.frame import denoising
from kdtrace.core.frame.denoising import DenoiseSettings
from kdtrace.core.frame.exported import InstancedExport
from kdtrace.core.frame.options import FrameOptions
from kdtrace.core.frame.render import FrameHost, render_frame, summary
from kdtrace.core.frame.session import FrameSession
from kdtrace.core.scene.model import Camera, Geometry, Light, RenderSettings, Shading, View
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import Tracer
from tests.meshes import grid_plane, look_at, merge, uv_sphere

WIDTH, HEIGHT = 96, 64
# Denoised, the 4-sample frame is at least this much closer to the reference than noisy
# (measured: 9.3 dB, from 30.8 to 40.2 dB against 1024 samples a pixel).
MIN_GAIN_DB = 6.0


class Host(FrameHost):
    def __init__(self):
        self.reports, self.noisy, self.image, self.job_passes = [], None, None, None

    def report(self, level, message):
        self.reports.append((level, message))

    def begin(self, job):
        self.job_passes = tuple(job.image)

    def denoised(self, job, noisy):
        self.noisy = noisy.copy()

    def end(self, job):
        self.image = {name: array.copy() for name, array in job.image.items()}


def scene_and_view(samples_per_axis: int):
    sphere = uv_sphere(48, 24, 1.0)
    sphere = (sphere[0] + np.float32([0.0, 0.0, 1.0]), sphere[1])
    vertices, triangles = merge(grid_plane(12.0, 4), sphere)
    ids = np.concatenate([np.zeros(len(grid_plane(12.0, 4)[1]), np.uint16),
                          np.ones(len(sphere[1]), np.uint16)])
    geometry = Geometry(vertices, triangles, ids)
    shading = Shading(np.array([[0.8, 0.8, 0.8, 1.0], [0.8, 0.3, 0.2, 1.0]], np.float32),
                      [Light("AREA", (1.0, 0.95, 0.9), 300.0, (2.0, -2.0, 5.0), size_u=2.0,
                             size_v=2.0)], (0.2, 0.25, 0.3))
    camera = Camera("PERSP", look_at((0.0, -6.0, 3.0), (0.0, 0.0, 0.8)), (0.5, 0.5 * HEIGHT / WIDTH))
    view = View(camera, WIDTH, HEIGHT, shading, settings=RenderSettings(
        samples_per_axis=samples_per_axis, adaptive=False))
    exported = InstancedExport([geometry], np.zeros(1, np.int64), np.eye(4)[None], None, None)
    return exported, view, geometry


@pytest.fixture(scope="module")
def reference():
    exported, view, geometry = scene_and_view(32)      # 1024 samples a pixel
    tracer = Tracer("cpu")
    tracer.load(Scene.from_parts(geometry, build_kdtree(geometry.vertices, geometry.triangles)))
    return tracer.render_tile(view, 0, 0, WIDTH, HEIGHT)["combined"][..., :3]


@pytest.fixture(scope="module")
def session():
    session = FrameSession()
    yield session
    session.close()


def options(**denoise) -> FrameOptions:
    return FrameOptions(use_zeroconf=False, local_slaves=2, tile_size=32,
                        denoise=DenoiseSettings(**denoise))


def psnr(image, reference) -> float:
    mse = float(np.mean((np.clip(image, 0, 1) - np.clip(reference, 0, 1)) ** 2))
    return 10 * np.log10(1.0 / mse)


def test_the_frame_comes_back_denoised_as_one_image_and_much_closer(session, reference):
    exported, view, _ = scene_and_view(2)
    host = Host()
    report = render_frame(session, exported, view, options(), host)
    assert set(host.job_passes) == {"combined", "albedo", "denoising_normal"}
    assert report["denoised"] and report["denoise_seconds"] > 0
    assert f"denoised in {report['denoise_seconds']:.2f} s" in summary(report)
    noisy, clean = host.noisy[..., :3], host.image["combined"][..., :3]
    assert np.array_equal(host.image["combined"][..., 3], host.noisy[..., 3])   # alpha kept
    # One whole image: exactly what denoising the assembled noisy frame at once gives.
    with Denoiser() as whole:
        at_once = whole.denoise(host.noisy, host.image["albedo"], host.image["denoising_normal"])
    assert np.array_equal(clean, at_once[..., :3])
    gain = psnr(clean, reference) - psnr(noisy, reference)
    assert gain >= MIN_GAIN_DB, (psnr(noisy, reference), psnr(clean, reference))


def test_off_the_guides_do_not_travel_and_the_image_stays_noisy(session):
    exported, view, _ = scene_and_view(2)
    host = Host()
    report = render_frame(session, exported, view, options(enabled=False), host)
    assert host.job_passes == ("combined",) and host.noisy is None
    assert not report["denoised"] and "denoised" not in summary(report)


def test_without_a_library_the_frame_says_so_once_and_stays_noisy(reference, monkeypatch):
    monkeypatch.setattr(denoising, "find_library", lambda: None)
    session = FrameSession()
    try:
        exported, view, _ = scene_and_view(2)
        hosts = [Host(), Host()]
        for host in hosts:
            report = render_frame(session, exported, view, options(), host)
            assert not report["denoised"] and host.noisy is None
        warnings = [m for h in hosts for level, m in h.reports if "Open Image Denoise" in m]
        assert len(warnings) == 1 and "not denoised" in warnings[0]
        assert np.array_equal(hosts[0].image["combined"], hosts[1].image["combined"])
    finally:
        session.close()


def test_settings_are_checked():
    with pytest.raises(ValueError, match="prefilter"):
        DenoiseSettings(prefilter="SLOW")
    with pytest.raises(ValueError, match="quality"):
        DenoiseSettings(quality="BEST")
    assert DenoiseSettings().passes() == ("albedo", "denoising_normal")
    assert (denoising.DENOISE, denoising.PREFILTER, denoising.QUALITY) == (True, "ACCURATE", "HIGH")
