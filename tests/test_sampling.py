"""The kernels' 2D sample points (kernels/shade/sampling.cl rng_2d_at): Owen-scrambled Sobol
sequences, one per pixel and use. Each aligned block of 2^k points of a sequence must be a
(0, k, 2)-net (one point in every elementary interval of area 2^-k), and sequences of other
pixels and uses must be independent of it."""
import numpy as np
import pytest

from kdtrace.core.opencl import KERNEL_DIR, kernel_source
from tests.opencl_programs import programs_on

POINTS = r"""
__kernel void points(uint pixel, uint dim, uint first, __global float2 *out)
{
    uint i = get_global_id(0);
    Rng r = rng_seed(pixel, 0u, 7u);
    out[i] = rng_2d_at(&r, dim, first + i);
}
"""


@pytest.fixture(scope="module")
def points():
    cl, context, queue, programs = programs_on("cpu")
    source = (KERNEL_DIR / "shade" / "sampling.cl").read_text() + POINTS
    kernel = programs.kernels(kernel_source([]) + source, [])["points"]

    def run(pixel, dim, count, first=0):
        out = np.empty((count, 2), np.float32)
        buf = cl.Buffer(context, cl.mem_flags.WRITE_ONLY, out.nbytes)
        kernel(queue, (count,), None, np.uint32(pixel), np.uint32(dim), np.uint32(first), buf)
        cl.enqueue_copy(queue, out, buf)
        queue.finish()
        return out.astype(np.float64)
    return run


def is_net(p, k):
    """Every elementary interval of area 2^-k (2^a x 2^(k-a) cells) holds one of the 2^k points."""
    for a in range(k + 1):
        cells = np.floor(p[:, 0] * 2 ** a).astype(int) * 2 ** (k - a) + np.floor(p[:, 1] * 2 ** (k - a)).astype(int)
        if len(np.unique(cells)) != 2 ** k:
            return False
    return True


@pytest.mark.parametrize("pixel, dim", [(0, 0), (1, 3), (12345, 65536 * 7 + 2), (2 ** 31, 9)])
def test_aligned_blocks_are_stratified(points, pixel, dim):
    p = points(pixel, dim, 1024)
    assert ((p >= 0) & (p < 1)).all()
    for k in (2, 4, 6, 8, 10):
        for start in range(0, 1024, 2 ** k):
            assert is_net(p[start:start + 2 ** k], k), (k, start)
    # a later block too (adaptive sampling continues a pixel's sequence)
    assert is_net(points(pixel, dim, 256, first=4096), 8)


def test_random_points_are_not_a_net():
    """The check above can fail: 256 independent uniform points are almost never a net."""
    rng = np.random.default_rng(1)
    assert not any(is_net(rng.random((256, 2)), 8) for _ in range(20))


def test_sequences_of_other_pixels_and_uses_are_independent(points):
    """The first point of 4,096 pixels' sequences (and of 4,096 uses in one pixel) is uniform
    and uncorrelated: mean 1/2, variance 1/12, no correlation between the coordinates or
    between two uses of a pixel; no two sequences alike."""
    by_pixel = np.array([points(pixel, 5, 1)[0] for pixel in range(0, 4096 * 7, 7)])
    other_use = np.array([points(pixel, 6, 1)[0] for pixel in range(0, 4096 * 7, 7)])
    by_use = np.array([points(99, dim, 1)[0] for dim in range(4096)])
    for sample in (by_pixel, other_use, by_use):
        assert np.abs(sample.mean(0) - 0.5).max() < 0.02
        assert np.abs(sample.var(0) - 1 / 12).max() < 0.01
        assert abs(np.corrcoef(sample.T)[0, 1]) < 0.05
        assert len(np.unique(sample[:, 0])) > 4000
    assert abs(np.corrcoef(by_pixel[:, 0], other_use[:, 0])[0, 1]) < 0.05
