"""core/scene/sky.py: Blender 5.0's Sky Texture computed on the host. Each model is checked at a
few directions against its formulas written out once more in plain scalar Python (the
multiple scattering texel against a direct march whose transmittance is marched too, not read
from the table), the sun disc's energy against its integral, and the image against the
kernel's lookup; the last test renders Cycles' own sky as panoramas inside Blender."""
from __future__ import annotations

import math

import numpy as np
import pytest

from kdtrace.core.scene import sky
from kdtrace.core.scene.sky import SkyParams, sky_image, sky_radiance

ODD = dict(sun_elevation=0.7, sun_rotation=1.0, altitude=2000.0, air_density=2.0,
           aerosol_density=3.0, ozone_density=0.5, sun_size=0.05, sun_intensity=0.5)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def test_sun_direction_follows_elevation_and_rotation():
    """Sun Rotation turns the sun from +Y towards +X, Sun Elevation raises it; past the zenith
    it comes down on the other side (Cycles' simplify_settings)."""
    e, r = 0.3, 0.5
    expected = [math.cos(e) * math.sin(r), math.cos(e) * math.cos(r), math.sin(e)]
    assert np.allclose(SkyParams(sun_elevation=e, sun_rotation=r).sun_vector(), expected)
    over = SkyParams(sun_elevation=math.pi - e, sun_rotation=r).sun_vector()
    assert np.allclose(over, [-expected[0], -expected[1], expected[2]])


def perez(lam, theta, gamma):
    return ((1 + lam[0] * math.exp(lam[1] / math.cos(theta)))
            * (1 + lam[2] * math.exp(lam[3] * gamma) + lam[4] * math.cos(gamma) ** 2))


def test_preetham_is_the_perez_model():
    t = 3.0
    sun = unit([0.4, 0.5, 0.77])
    params = SkyParams(sky_type="PREETHAM", sun_direction=tuple(sun), turbidity=t)
    ts = math.acos(sun[2])
    coefficients = [
        [0.1787 * t - 1.4630, -0.3554 * t + 0.4275, -0.0227 * t + 5.3251, 0.1206 * t - 2.5771,
         -0.0670 * t + 0.3703],
        [-0.0193 * t - 0.2592, -0.0665 * t + 0.0008, -0.0004 * t + 0.2125, -0.0641 * t - 0.8989,
         -0.0033 * t + 0.0452],
        [-0.0167 * t - 0.2608, -0.0950 * t + 0.0092, -0.0079 * t + 0.2102, -0.0441 * t - 1.6537,
         -0.0109 * t + 0.0529]]
    chi = (4 / 9 - t / 120) * (math.pi - 2 * ts)
    zenith = [((4.0453 * t - 4.9710) * math.tan(chi) - 0.2155 * t + 2.4192) * 0.06,
              (0.00166 * ts ** 3 - 0.00375 * ts ** 2 + 0.00209 * ts) * t * t
              + (-0.02903 * ts ** 3 + 0.06377 * ts ** 2 - 0.03202 * ts + 0.00394) * t
              + (0.11693 * ts ** 3 - 0.21196 * ts ** 2 + 0.06052 * ts + 0.25886),
              (0.00275 * ts ** 3 - 0.00610 * ts ** 2 + 0.00317 * ts) * t * t
              + (-0.04214 * ts ** 3 + 0.08970 * ts ** 2 - 0.04153 * ts + 0.00516) * t
              + (0.15346 * ts ** 3 - 0.26756 * ts ** 2 + 0.06670 * ts + 0.26688)]
    directions = [unit(d) for d in ([0, 0, 1], [1, 0, 0.1], [-0.3, 0.8, 0.4], [0.4, 0.5, 0.77],
                                    [0.2, -1, -0.5])]
    for d in directions:
        theta = min(math.acos(d[2]), math.pi / 2 - 0.001)
        gamma = math.acos(min(1.0, float(d @ sun)))
        Y, x, y = (zenith[k] / perez(coefficients[k], 0.0, ts)
                   * perez(coefficients[k], theta, gamma) for k in range(3))
        xyz = np.array([x / y * Y, Y, (1 - x - y) / y * Y])
        expected = np.maximum(sky.XYZ_TO_REC709 @ xyz, 0)
        assert np.allclose(sky_radiance(params, [d])[0], expected, rtol=1e-9), d


SS_LAMBDA = np.arange(380, 781, 20)


def single_scattering_xyz(params, d):
    """One direction's single-scattered XYZ, written out loop by loop."""
    R, top = 6360e3, 6420e3
    e = params.sun_angles()[0]
    sun = np.array([math.cos(e), 0.0, math.sin(e)])
    camera = np.array([0.0, 0.0, R + min(max(params.altitude, 1.0), 59999.0)])
    scale = np.array([params.air_density, params.aerosol_density, params.ozone_density])

    def density(p):
        h = np.linalg.norm(p) - R
        return np.array([math.exp(-h / 8e3), math.exp(-h / 1.2e3),
                         max(0.0, 1 - abs(h - 25000) / 15000)])

    def to_top(p, v):
        b, c = 2 * (v @ p), p @ p - top * top
        return (-b + math.sqrt(b * b - 4 * c)) / 2

    def optical_depth(p, v):
        length = to_top(p, v)
        return sum(density(p + n * length * v) * w for n, w in
                   zip(sky._SS_QUADRATURE_NODES, sky._SS_QUADRATURE_WEIGHTS)) * length

    mu = d @ sun
    g = 0.76
    phase = np.array([3 / (16 * math.pi) * (1 + mu * mu),
                      3 * (1 - g * g) * (1 + mu * mu)
                      / (8 * math.pi * (2 + g * g) * (1 + g * g - 2 * g * mu) ** 1.5)])
    segment = to_top(camera, d) / 32
    depth, spectrum = np.zeros(3), np.zeros(21)
    for i in range(32):
        p = camera + (i + 0.5) * segment * d
        rho = scale * density(p)
        depth += segment * rho
        total = depth + scale * optical_depth(p, sun)
        for k in range(21):
            ext = total @ [sky._SS_RAYLEIGH_COEFF[k], 1.11 * 2e-5, sky._SS_OZONE_COEFF[k]]
            scattered = phase @ (rho[:2] * [sky._SS_RAYLEIGH_COEFF[k], 2e-5])
            spectrum[k] += math.exp(-ext) * scattered * sky._SS_IRRADIANCE[k] * segment
    return 20.0 * spectrum @ sky._SS_CMF


def test_single_scattering_table_is_the_marched_spectrum():
    """Texels of Cycles' single scattering table (Nishita's model, 21 wavelengths) against the
    march written out; the rows below the horizon are black, the table mirrored about the sun."""
    params = SkyParams(sky_type="SINGLE_SCATTERING", **ODD)
    table = sky.sky_table(params)
    assert table.shape == (256, 512, 3) and not table[:129].any()
    assert np.array_equal(table[:, :256], table[:, 256:][:, ::-1])
    for row, column in ((140, 10), (200, 128), (255, 250), (130, 255)):
        latitude = math.pi / 2 * (row / 128 - 1) ** 2
        longitude = 2 * math.pi * column / 512 - math.pi
        d = np.array([math.cos(latitude) * math.cos(longitude),
                      math.cos(latitude) * math.sin(longitude), math.sin(latitude)])
        assert np.allclose(table[row, column], single_scattering_xyz(params, d), rtol=1e-9)


def multiple_scattering_xyz(params, d):
    """One direction's radiance of the multiple scattering model, marched with the sun's
    transmittance marched at each step too (the model reads it from its 256 x 64 table)."""
    R, thickness = 6371.0, 100.0
    top = R + thickness
    e = params.sun_angles()[0]
    sun = np.array([-math.cos(e), 0.0, math.sin(e)])

    def coefficients(h):
        aerosol = 1.3681e20 * (math.exp(-h / 0.73) + 2e6 / 1.3681e20) * params.aerosol_density
        log_h = math.log(max(h, 1e-4))
        ozone = 3.78547397e20 * math.exp(-(log_h - 3.22261) ** 2 * 5.55555555 - log_h)
        molecular = (sky._MS_MOLECULAR_SCATTERING * math.exp(-0.07771971 * h ** 1.16364243)
                     * params.air_density)
        aerosol_scattering = sky._MS_AEROSOL_SCATTERING * aerosol
        extinction = (sky._MS_AEROSOL_ABSORPTION * aerosol + aerosol_scattering + molecular
                      + sky._MS_OZONE_CROSS_SECTION * 334.5 * ozone * params.ozone_density)
        return extinction, molecular, aerosol_scattering

    def hit(p, v, radius):
        b, c = p @ v, p @ p - radius * radius
        disc = b * b - c
        if (c > 0 and b > 0) or disc < 0:
            return -1.0
        return -b + math.sqrt(disc) if disc >= b * b else -b - math.sqrt(disc)

    def transmittance(cos_theta, h):
        v = np.array([-math.sqrt(max(1 - cos_theta ** 2, 0)), 0.0, cos_theta])
        p0 = np.array([0.0, 0.0, R + h])
        step = hit(p0, v, top) / 64
        depth = sum(coefficients(max(np.linalg.norm(p0 + (i + 0.5) * step * v) - R, 0))[0] * step
                    for i in range(64))
        return np.exp(-depth)

    camera = np.array([0.0, 0.0, R + min(max(params.altitude, 1.0), 99999.0) / 1000])
    ground = hit(camera, d, R)
    distance = ground if ground >= 0 else hit(camera, d, top)
    c = -(d @ sun)
    g = 0.8
    molecular_phase = 3 / (16 * math.pi) * (1 + c * c)
    den = 1 + g * g + 2 * g * c
    aerosol_phase = (1 - g * g) / (4 * math.pi * den * math.sqrt(den))
    dt = distance / 64
    radiance, through = np.zeros(4), np.ones(4)
    at_ground_zenith = transmittance(1.0, 0.0)
    for i in range(64):
        p = camera + (i + 0.5) * dt * d
        r = np.linalg.norm(p)
        h = max(r - R, 0.0)
        cos_sun = (p @ sun) / r
        extinction, molecular, aerosol = coefficients(h)
        to_sun = transmittance(cos_sun, h)
        omega = 2 * math.pi * (1 - math.sqrt(1 - (R / r) ** 2))
        ground_light = (omega / (4 * math.pi) * 0.3 / math.pi * transmittance(cos_sun, 0.0)
                        * at_ground_zenith / transmittance(1.0, h) * cos_sun)
        fit = 0.02 * np.array([0.217, 0.347, 0.594, 1.0]) / (1 + 5 * math.exp(-17.92 * cos_sun))
        ms = ground_light + fit
        source = sky._MS_SUN_IRRADIANCE * (molecular * (molecular_phase * to_sun + ms)
                                           + aerosol * (aerosol_phase * to_sun + ms))
        step = np.exp(-dt * extinction)
        radiance += through * (source - source * step) / np.maximum(extinction, 1e-7)
        through *= step
    return radiance @ sky._MS_SPECTRAL_XYZ


def test_multiple_scattering_table_is_the_marched_radiance():
    """Texels of Cycles' multiple scattering table against the march written out with its
    transmittance marched rather than read from the table: within 1 %, the table's
    interpolation; the table mirrored about the sun."""
    for params in (SkyParams(), SkyParams(**ODD)):
        table = sky.sky_table(params)
        assert np.array_equal(table[:, :256], table[:, 256:][:, ::-1])
        for row, column in ((250, 30), (180, 200), (140, 255), (129, 100), (60, 10)):
            l = 2 * (row + 0.5) / 256 - 1
            elevation = math.copysign(l * l, l) * math.pi / 2
            azimuth = 2 * math.pi * (column + 0.5) / 512
            d = np.array([math.cos(elevation) * math.cos(azimuth),
                          math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
            assert np.allclose(table[row, column], multiple_scattering_xyz(params, d),
                               rtol=0.01), (row, column)


@pytest.mark.parametrize("sky_type", ["SINGLE_SCATTERING", "MULTIPLE_SCATTERING"])
def test_sun_disc_in_the_image_holds_its_energy(sky_type):
    """The image's texels near the sun, times their solid angle, hold the sun disc's energy:
    its radiance between the disc's lowest and highest point times Cycles' limb darkening,
    whose mean over a disc is 1 - 0.6 / 3 = 0.8; and the brightest texel is the sun's."""
    for settings in ({}, {"sun_size": 0.002, "sun_elevation": 0.9, "sun_rotation": 2.0},
                     {"sun_size": 0.2, "sun_intensity": 3.0}):
        params = SkyParams(sky_type=sky_type, **settings)
        rgba, scale = sky_image(params)
        height, width = rgba.shape[:2]
        bottom, top = sky.sun_pixels(params)
        half = params.sun_size / 2
        disc = 2 * math.pi * (1 - math.cos(half))
        expected = sky.xyz_to_rgb((bottom + top) / 2) * 0.8 * disc * params.sun_intensity
        directions = sky.equirectangular_directions(width, height)
        near = directions @ params.sun_vector() > math.cos(half + 3 * math.pi / height)
        rows = np.nonzero(near)[0]
        solid = (2 * math.pi / width) * (np.sin(math.pi * ((rows + 1) / height - 0.5))
                                         - np.sin(math.pi * (rows / height - 0.5)))
        held = np.sum(rgba[near][:, :3].astype(np.float64) * scale * solid[:, None], 0)
        sky_only = sky._nishita_sky(params, sky.sky_table(params), directions[near])
        held -= np.sum(sky_only * solid[:, None], 0)
        assert np.allclose(held, expected, rtol=0.01), (settings, held, expected)
        brightest = np.unravel_index(np.argmax(rgba[..., 1]), rgba.shape[:2])
        assert directions[brightest] @ params.sun_vector() > math.cos(half + 2 * math.pi / height)
        assert rgba.max() <= sky.TEXEL_CEILING


def test_image_is_the_kernel_lookup_at_texel_centres():
    """Away from the sun each texel is the sky the kernel computes in its centre's direction,
    scaled; the image is read-only and kept by parameters."""
    for params in (SkyParams(**ODD), SkyParams(sky_type="SINGLE_SCATTERING"),
                   SkyParams(sky_type="PREETHAM", turbidity=5.0)):
        rgba, scale = sky_image(params)
        height, width = rgba.shape[:2]
        assert (height, width) == (sky.IMAGE_WIDTH // 2, sky.IMAGE_WIDTH)
        directions = sky.equirectangular_directions(width, height).reshape(-1, 3)
        pick = np.arange(0, len(directions), 7919)
        if params.sky_type != "PREETHAM":
            pick = pick[directions[pick] @ params.sun_vector() < math.cos(params.sun_size)]
        expected = sky_radiance(params, directions[pick])
        assert np.allclose(rgba.reshape(-1, 4)[pick, :3] * scale, expected, rtol=1e-5, atol=1e-9)
        assert not rgba.flags.writeable and sky_image(params)[0] is rgba


def test_hosek_wilkie_is_not_computed():
    assert "HOSEK_WILKIE" not in sky.SUPPORTED_TYPES
    with pytest.raises(ValueError):
        sky_image(SkyParams(sky_type="HOSEK_WILKIE"))


PANORAMAS = {"multiple": {}, "single": {"sky_type": "SINGLE_SCATTERING"},
             "preetham": {"sky_type": "PREETHAM"},
             "multiple_odd": ODD, "single_odd": dict(ODD, sky_type="SINGLE_SCATTERING"),
             "preetham_odd": {"sky_type": "PREETHAM", "sun_direction": (0.5, 0.3, 0.6),
                              "turbidity": 4.0}}


@pytest.mark.slow
def test_sky_matches_cycles_panoramas(tmp_path):
    """Cycles renders each model as an equirectangular panorama (tests/bpy_scripts/
    sky_panoramas.py); sky_radiance in each pixel centre's direction agrees, the sun disc
    aside: a median within 0.2 %, 99 % of the pixels above the horizon within 2 %."""
    from tests.blender import run_bpy_script
    width, height = 256, 128
    run_bpy_script("sky_panoramas", tmp_path, timeout=600, out=str(tmp_path), width=width,
                   height=height, cases=PANORAMAS)
    u, v = (np.arange(width) + 0.5) / width, (np.arange(height) + 0.5) / height
    a, e = np.meshgrid((u - 0.5) * 2 * np.pi, (v - 0.5) * np.pi)
    directions = np.stack([np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)], -1)
    directions = directions.reshape(-1, 3)
    for name, settings in PANORAMAS.items():
        params = SkyParams(**settings)
        cycles = np.load(tmp_path / f"{name}.npy").reshape(-1, 3)
        ours = sky_radiance(params, directions)
        keep = directions[:, 2] > 0.02
        if params.sky_type != "PREETHAM":
            keep &= directions @ params.sun_vector() < math.cos(math.radians(4))
        error = (np.abs(ours - cycles).max(-1) / np.maximum(cycles.max(-1), 1e-3))[keep]
        print(f"{name}: median {np.median(error):.5f}, "
              f"99th percentile {np.percentile(error, 99):.4f}")
        assert np.median(error) < 0.002 and np.percentile(error, 99) < 0.02, name
