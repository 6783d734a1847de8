"""Our Depth pass against Cycles' on the same scene, both rendered through Blender."""
import numpy as np
import pytest

from tests.blender import build_extension, run_bpy_script

MISS = 1e9  # Cycles writes 1e10 where nothing is hit; so do we
# Cycles cannot sample exactly at pixel centres: its box filter has a hard minimum width of
# 0.01 pixel, so its one sample lies up to 0.005 pixel off the centre.
CYCLES_JITTER_PIXELS = 0.005


def steepest_neighbour_slope(depth: np.ndarray) -> np.ndarray:
    """Per pixel, the largest relative depth change to a hit 4-neighbour (0 if none is a hit)."""
    padded = np.pad(depth, 1, constant_values=np.inf)
    slope = np.zeros_like(depth)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        neighbour = padded[dy:dy + depth.shape[0], dx:dx + depth.shape[1]]
        with np.errstate(invalid="ignore"):
            change = np.where(neighbour < MISS, np.abs(neighbour - depth) / depth, 0.0)
        slope = np.maximum(slope, change)
    return slope


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
    jitter = CYCLES_JITTER_PIXELS * steepest_neighbour_slope(np.where(our_hit, ours, np.inf))[both]
    within = relative <= np.maximum(1e-4, jitter)
    # Where a silhouette passes within that offset of a pixel centre, Cycles' one sample can
    # land on the other surface (checked once in float64: the ray through the exact centre of
    # such a pixel hits what we hit). Those pixels count with the hit/miss differences.
    silhouette = np.count_nonzero(~within) + np.count_nonzero(cycles_hit != our_hit)
    assert silhouette <= 0.001 * cycles.size, f"{silhouette} pixels disagree at silhouettes"
    assert np.mean(relative <= 1e-4) >= 0.999, f"only {np.mean(relative <= 1e-4):.4%} within 1e-4"


def test_normals_match_cycles_on_flat_surfaces(renders):
    # The ground plane is flat-shaded in both renderers: normals must agree there exactly.
    cycles, ours = renders["cycles_normal"], renders["kdtrace_normal"]
    plane = (np.abs(cycles[..., 2] - 1.0) < 1e-6) & (renders["kdtrace_depth"] < MISS)
    assert plane.sum() > 1000
    assert np.abs(ours[plane] - cycles[plane]).max() < 1e-5
