"""Our Depth pass against Cycles' on the same scene, both rendered through Blender."""
import numpy as np
import pytest

from tests.blender import build_extension, run_bpy_script

MISS = 1e9  # Cycles writes 1e10 where nothing is hit; so do we
# Cycles cannot sample exactly at pixel centres: its box filter has a hard minimum width of
# 0.01 pixel, so its one sample lies up to 0.005 pixel off the centre.
CYCLES_JITTER_PIXELS = 0.005


def neighbour_change(values: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Per pixel, the largest change (max over channels) to a 4-neighbour that is a hit."""
    values = values.reshape(values.shape[0], values.shape[1], -1)
    padded = np.pad(values, ((1, 1), (1, 1), (0, 0)))
    padded_hit = np.pad(hit, 1)
    change = np.zeros(hit.shape)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        window = np.s_[dy:dy + hit.shape[0], dx:dx + hit.shape[1]]
        difference = np.abs(padded[window] - values).max(axis=-1)
        change = np.maximum(change, np.where(padded_hit[window], difference, 0.0))
    return change


CAMERAS = {
    "perspective, shifted, vertical sensor fit": dict(camera_type="PERSP", shift=[0.05, -0.03],
                                                      sensor_fit="VERTICAL"),
    "orthographic, shifted": dict(camera_type="ORTHO", shift=[-0.04, 0.02]),
}


@pytest.fixture(scope="module", params=sorted(CAMERAS))
def renders(request, tmp_path_factory):
    work = tmp_path_factory.mktemp("cycles")
    zip_path = build_extension(work / "dist")
    run_bpy_script("depth_vs_cycles", work, zip=str(zip_path), out=str(work),
                   width=160, height=120, **CAMERAS[request.param])
    return {name: np.load(work / f"{name}.npy") for name in
            ("cycles_depth", "kdtrace_depth", "cycles_normal", "kdtrace_normal")}


def test_depth_matches_cycles(renders):
    cycles, ours = renders["cycles_depth"], renders["kdtrace_depth"]
    assert cycles.shape == ours.shape == (120, 160)
    cycles_hit, our_hit = cycles < MISS, ours < MISS
    assert 0.2 < cycles_hit.mean() < 1.0, "the test scene should show both objects and background"
    both = cycles_hit & our_hit
    relative = np.abs(ours[both] - cycles[both]) / cycles[both]
    # Within 1e-4 wherever Cycles' own sub-pixel offset cannot move the depth by more.
    slope = neighbour_change(np.where(our_hit, ours, 0.0), our_hit) / np.where(our_hit, ours, 1.0)
    jitter = CYCLES_JITTER_PIXELS * slope[both]
    within = relative <= np.maximum(1e-4, jitter)
    # Where a silhouette passes within that offset of a pixel centre, Cycles' one sample can
    # land on the other surface (checked once in float64: the ray through the exact centre of
    # such a pixel hits what we hit). Those pixels count with the hit/miss differences.
    silhouette = np.count_nonzero(~within) + np.count_nonzero(cycles_hit != our_hit)
    assert silhouette <= 0.001 * cycles.size, f"{silhouette} pixels disagree at silhouettes"
    assert np.mean(relative <= 1e-4) >= 0.999, f"only {np.mean(relative <= 1e-4):.4%} within 1e-4"


def test_normals_match_cycles(renders):
    # The smooth-shaded sphere (interpolated normals) and the flat bunny and ground plane.
    cycles, ours = renders["cycles_normal"], renders["kdtrace_normal"]
    depth_ours, depth_cycles = renders["kdtrace_depth"], renders["cycles_depth"]
    same_surface = (depth_ours < MISS) & (np.abs(depth_ours - depth_cycles) <= 1e-3 * depth_cycles)
    assert same_surface.sum() > 0.2 * same_surface.size
    error = np.abs(ours - cycles).max(axis=-1)
    # As for depth: within 1e-4, or within what Cycles' sub-pixel offset explains on a curved
    # surface; at the edges between flat faces its sample may land on the neighbouring face.
    bound = np.maximum(1e-4, CYCLES_JITTER_PIXELS * neighbour_change(ours, depth_ours < MISS))
    off = np.count_nonzero(same_surface & (error > bound))
    assert off <= 0.005 * same_surface.sum(), f"{off} pixels off (of {same_surface.sum()})"
    assert np.median(error[same_surface]) < 1e-5
