"""core/denoise.py: Open Image Denoise's RT filter through ctypes (here the library of the bpy
wheel, loaded without importing bpy), with Cycles' prefilter and quality choices."""
import numpy as np
import pytest

from kdtrace.core.denoise import PREFILTERS, QUALITIES, Denoiser, find_library


@pytest.fixture(scope="module")
def denoiser():
    assert find_library() is not None, "the bpy wheel ships libOpenImageDenoise"
    with Denoiser() as denoiser:
        yield denoiser


def noisy_gradient(seed=1, height=96, width=128):
    """A smooth image, its albedo and normal, and the image times exponential noise (mean 1)."""
    y, x = np.mgrid[0:height, 0:width]
    clean = np.stack([x / width, y / height, np.full(x.shape, 0.5)], -1).astype(np.float32)
    noise = np.random.default_rng(seed).exponential(1.0, (height, width, 1))
    normal = np.zeros_like(clean)
    normal[..., 2] = 1.0
    return clean, clean.copy(), normal, (clean * noise).astype(np.float32)


@pytest.mark.parametrize("prefilter", PREFILTERS)
@pytest.mark.parametrize("quality", list(QUALITIES))
def test_denoised_image_is_much_closer_to_the_clean_one(denoiser, prefilter, quality):
    clean, albedo, normal, noisy = noisy_gradient()
    out = denoiser.denoise(noisy, albedo, normal, prefilter=prefilter, quality=quality)
    assert out.shape == clean.shape and out.dtype == np.float32 and np.isfinite(out).all()
    assert np.abs(out - clean).mean() < np.abs(noisy - clean).mean() / 10


def test_alpha_is_kept_and_the_image_alone_denoises(denoiser):
    clean, _, _, noisy = noisy_gradient(seed=2)
    alpha = np.random.default_rng(3).random(noisy.shape[:2] + (1,)).astype(np.float32)
    out = denoiser.denoise(np.concatenate([noisy, alpha], -1))
    assert out.shape == clean.shape[:2] + (4,) and np.array_equal(out[..., 3:], alpha)
    assert np.abs(out[..., :3] - clean).mean() < np.abs(noisy - clean).mean() / 5


def test_bad_arguments_are_named(denoiser):
    _, albedo, normal, noisy = noisy_gradient()
    with pytest.raises(ValueError, match="prefilter"):
        denoiser.denoise(noisy, prefilter="SLOW")
    with pytest.raises(ValueError, match="quality"):
        denoiser.denoise(noisy, quality="BEST")
    with pytest.raises(ValueError, match="needs an albedo"):
        denoiser.denoise(noisy, normal=normal)
    with pytest.raises(ValueError, match="albedo must be"):
        denoiser.denoise(noisy, albedo[:10])
