"""Blender 5.0's Sky Texture, computed on the host as an equirectangular image for the world's
texture path (WorldTexture: importance sampled by the slaves like any Environment Texture).

What Cycles computes, reproduced here in numpy (the physics and constants of Blender's
intern/sky and Cycles' kernel/svm/sky.h; written anew, vectorised):
- SINGLE_SCATTERING (Nishita's model as Blender 2.90-4.x had it) and MULTIPLE_SCATTERING (Blender
  5.0's default: Fernando Garcia Linan's spectral model with four wavelengths, a transmittance
  table and a fitted multiple-scattering term) are precomputed by Cycles into a 512 x 256 XYZ
  table whose rows map elevation non-linearly (more rows near the horizon) and whose columns
  are azimuths from the sun, mirrored about it. `sky_table` computes that table the same way,
  and `sky_radiance` looks it up as the kernel does (bilinear, clamped at the edges; the single
  scattering sky fades to black below the horizon), then adds the sun disc: between the XYZ
  radiance at its lowest and highest point (attenuated by the atmosphere), times Cycles' limb
  darkening 1 - 0.6 (1 - sqrt(1 - (angle / radius)^2)) and Sun Intensity; hidden below the
  Earth's edge (single scattering: below the horizon).
- PREETHAM (Preetham, Shirley and Smits' Perez model in xyY) is analytic: evaluated per texel.
- HOSEK_WILKIE needs Hosek and Wilkie's fitted data set, which KD Trace does not carry:
  `SUPPORTED_TYPES` leaves it out; the exporter warns and renders Preetham's sky of the same
  sun direction and turbidity times `HOSEK_STAND_IN` (Cycles' Hosek / Wilkie sky holds about a
  sixth of its Preetham sky's energy at turbidity 2.2 and 4, measured on Cycles' panoramas).
XYZ becomes scene-linear Rec.709 through the matrix of Blender's OpenColorIO configuration
(`XYZ_TO_REC709`), negative components clamped to 0 as Cycles clamps them.

The image (`sky_image`): linear RGB in Cycles' equirectangular projection (u = 0.5 - atan2(y, x)
/ 2 pi, v = 0.5 + asin(z) / pi; rows bottom first, as Blender's images), the sky at each texel's
centre plus the sun disc integrated over each texel (its energy exact, spread over the texels it
covers: a disc of 0.545 degrees is a few texels wide at 2048 columns), divided by a common scale
so the brightest texel fits half floats; the world colour carries the scale. Computing it costs
about a second, so `sky_image` keeps the last few images by their parameters."""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

SKY_TYPES = ("SINGLE_SCATTERING", "MULTIPLE_SCATTERING", "PREETHAM", "HOSEK_WILKIE")
SUPPORTED_TYPES = ("SINGLE_SCATTERING", "MULTIPLE_SCATTERING", "PREETHAM")
NISHITA_TYPES = ("SINGLE_SCATTERING", "MULTIPLE_SCATTERING")

# Cycles' XYZ (D65 white) -> scene linear Rec.709 under Blender 5.0's OpenColorIO configuration:
# the configuration's "Linear CIE-XYZ D65" to "Linear Rec.709" matrix (Cycles' xyz_to_r/g/b;
# tests/test_sky.py's Cycles panoramas agree to 0.1 %; the textbook sRGB matrix is 2 % off).
XYZ_TO_REC709 = np.array([[3.2409699, -1.5373832, -0.4986108],
                          [-0.9692436, 1.8759675, 0.0415551],
                          [0.0556301, -0.2039770, 1.0569715]])

# Cycles' precomputed sky table (scene/image_sky.cpp SkyLoader).
TABLE_WIDTH, TABLE_HEIGHT = 512, 256
# The image handed to the world texture: 2048 x 1024 texels of 0.18 degrees.
IMAGE_WIDTH = 2048
HALF_MAX = 65504.0
# Texels are scaled so the brightest is this (a power of two below half floats' largest).
TEXEL_CEILING = 32768.0
HOSEK_STAND_IN = 1.0 / 6.0
SMALLEST_SUN = 0.0005       # Cycles' SkyTextureNode::get_sun_size clamp (radians)


@dataclass(frozen=True)
class SkyParams:
    """A Sky Texture node's settings (Blender's names and defaults; angles in radians)."""
    sky_type: str = "MULTIPLE_SCATTERING"
    sun_disc: bool = True
    sun_size: float = 0.009512044489383698
    sun_intensity: float = 1.0
    sun_elevation: float = math.radians(15.0)
    sun_rotation: float = 0.0
    altitude: float = 100.0
    air_density: float = 1.0
    aerosol_density: float = 1.0
    ozone_density: float = 1.0
    sun_direction: tuple = (0.0, 0.0, 1.0)
    turbidity: float = 2.2
    ground_albedo: float = 0.3

    def __post_init__(self):
        if self.sky_type not in SKY_TYPES:
            raise ValueError(f"sky type must be one of {SKY_TYPES}, got {self.sky_type!r}")
        object.__setattr__(self, "sun_direction", tuple(float(c) for c in self.sun_direction))

    def sun_angles(self) -> tuple:
        """(elevation, rotation) as Cycles' kernel uses them (SkyTextureNode::simplify_settings):
        the elevation wrapped into [-pi/2, pi/2] (past the zenith the sun turns round), the
        rotation wrapped and mirrored: the kernel's rotation is 2 pi - Blender's."""
        elevation, rotation = math.fmod(self.sun_elevation, 2 * math.pi), self.sun_rotation
        if abs(elevation) >= math.pi:
            elevation -= math.copysign(2.0, elevation) * math.pi
        if elevation >= math.pi / 2 or elevation <= -math.pi / 2:
            elevation = math.copysign(math.pi, elevation) - elevation
            rotation += math.pi
        rotation = math.fmod(rotation, 2 * math.pi)
        if rotation < 0.0:
            rotation += 2 * math.pi
        return elevation, 2 * math.pi - rotation

    def sun_vector(self) -> np.ndarray:
        """The unit direction of the sun disc's centre (Nishita types): elevation above the
        horizon, rotated from +Y towards +X by Sun Rotation."""
        elevation, rotation = self.sun_angles()
        return _spherical_to_direction(elevation - math.pi / 2, rotation - math.pi / 2)


def _spherical_to_direction(theta, phi) -> np.ndarray:
    return np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi),
                     math.cos(theta)])


def xyz_to_rgb(xyz: np.ndarray) -> np.ndarray:
    """Cycles' xyz_to_rgb_clamped: scene-linear Rec.709, negative components 0."""
    return np.maximum(np.asarray(xyz, np.float64) @ XYZ_TO_REC709.T, 0.0)


# ---------------------------------------------------------------- single scattering (Nishita)
_SS_RAYLEIGH_SCALE = 8e3           # m
_SS_MIE_SCALE = 1.2e3              # m
_SS_MIE_COEFF = 2e-5               # 1/m
_SS_MIE_G = 0.76
_SS_EARTH_RADIUS = 6360e3          # m
_SS_ATMOSPHERE_RADIUS = 6420e3     # m
_SS_STEPS = 32
_SS_STEP_LAMBDA = 20.0             # nm: 21 wavelengths from 380 to 780
# Sun irradiance at the top of the atmosphere (W m^-2 nm^-1), 380 to 780 nm by 20.
_SS_IRRADIANCE = np.array([
    1.45756829855592995315, 1.56596305559738380175, 1.65148449067670455293,
    1.71496242737209314555, 1.75797983805020541226, 1.78256407885924539336,
    1.79095108475838560302, 1.78541550133410664714, 1.76815554864306845317,
    1.74122069647250410362, 1.70647127164943679389, 1.66556087452739887134,
    1.61993437242451854274, 1.57083597368892080581, 1.51932335059305478886,
    1.46628494965214395407, 1.41245852740172450623, 1.35844961970384092709,
    1.30474913844739281998, 1.25174963272610817455, 1.19975998755420620867])
_SS_RAYLEIGH_COEFF = np.array([
    0.00005424820087636473, 0.00004418549866505454, 0.00003635151910165377,
    0.00003017929012024763, 0.00002526320226989157, 0.00002130859310621843,
    0.00001809838025320633, 0.00001547057129129042, 0.00001330284977336850,
    0.00001150184784075764, 0.00000999557429990163, 0.00000872799973630707,
    0.00000765513700977967, 0.00000674217203751443, 0.00000596134125832052,
    0.00000529034598065810, 0.00000471115687557433, 0.00000420910481110487,
    0.00000377218381260133, 0.00000339051255477280, 0.00000305591531679811])
_SS_OZONE_COEFF = np.array([
    0.00000000325126849861, 0.00000000585395365047, 0.00000001977191155085,
    0.00000007309568762914, 0.00000020084561514287, 0.00000040383958096161,
    0.00000063551335912363, 0.00000096707041180970, 0.00000154797400424410,
    0.00000209038647223331, 0.00000246128056164565, 0.00000273551299461512,
    0.00000215125863128643, 0.00000159051840791988, 0.00000112356197979857,
    0.00000073527551487574, 0.00000046450130357806, 0.00000033096079921048,
    0.00000022512612292678, 0.00000014879129266490, 0.00000016828623364192])
# CIE 1931 colour matching functions at the same wavelengths.
_SS_CMF = np.array([
    [0.00136800000, 0.00003900000, 0.00645000100], [0.01431000000, 0.00039600000, 0.06785001000],
    [0.13438000000, 0.00400000000, 0.64560000000], [0.34828000000, 0.02300000000, 1.74706000000],
    [0.29080000000, 0.06000000000, 1.66920000000], [0.09564000000, 0.13902000000, 0.81295010000],
    [0.00490000000, 0.32300000000, 0.27200000000], [0.06327000000, 0.71000000000, 0.07824999000],
    [0.29040000000, 0.95400000000, 0.02030000000], [0.59450000000, 0.99500000000, 0.00390000000],
    [0.91630000000, 0.87000000000, 0.00165000100], [1.06220000000, 0.63100000000, 0.00080000000],
    [0.85444990000, 0.38100000000, 0.00019000000], [0.44790000000, 0.17500000000, 0.00002000000],
    [0.16490000000, 0.06100000000, 0.00000000000], [0.04677000000, 0.01700000000, 0.00000000000],
    [0.01135916000, 0.00410200000, 0.00000000000], [0.00289932700, 0.00104700000, 0.00000000000],
    [0.00069007860, 0.00024920000, 0.00000000000], [0.00016615050, 0.00006000000, 0.00000000000],
    [0.00004150994, 0.00001499000, 0.00000000000]])
# Optical depth along a ray by 8-point Gauss-Laguerre quadrature, the ray scaled so that its
# last node lies inside the atmosphere (nodes / 25; weights x exp(node) / 25).
_SS_QUADRATURE_NODES = np.array([0.006811185292, 0.03614807107, 0.09004346519, 0.1706680068,
                                 0.2818362161, 0.4303406404, 0.6296271457, 0.9145252695])
_SS_QUADRATURE_WEIGHTS = np.array([0.01750893642, 0.04135477391, 0.06678839063, 0.09507698807,
                                   0.1283416365, 0.1707430204, 0.2327233347, 0.3562490486])


def _geographical(latitude, longitude) -> np.ndarray:
    latitude, longitude = np.broadcast_arrays(np.asarray(latitude, np.float64),
                                              np.asarray(longitude, np.float64))
    return np.stack([np.cos(latitude) * np.cos(longitude), np.cos(latitude) * np.sin(longitude),
                     np.sin(latitude)], -1)


def _ss_densities(height: np.ndarray) -> np.ndarray:
    """(Rayleigh, Mie, ozone) density factors at heights above sea level (m), (..., 3)."""
    return np.stack([np.exp(-height / _SS_RAYLEIGH_SCALE), np.exp(-height / _SS_MIE_SCALE),
                     np.maximum(0.0, 1.0 - np.abs(height - 25000.0) / 15000.0)], -1)


def _ss_atmosphere_distance(position: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Distance from `position` along `direction` to the top of the atmosphere."""
    b = 2.0 * np.sum(direction * position, -1)
    c = np.sum(position * position, -1) - _SS_ATMOSPHERE_RADIUS ** 2
    return (-b + np.sqrt(np.maximum(b * b - 4.0 * c, 0.0))) / 2.0


def _ss_optical_depth(origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(Rayleigh, Mie, ozone) optical depth factors from `origin` to the top, (..., 3)."""
    length = _ss_atmosphere_distance(origin, direction)
    depth = 0.0
    for node, weight in zip(_SS_QUADRATURE_NODES, _SS_QUADRATURE_WEIGHTS):
        point = origin + (node * length)[..., None] * direction
        depth = depth + _ss_densities(np.linalg.norm(point, axis=-1) - _SS_EARTH_RADIUS) * weight
    return depth * length[..., None]


def _ss_spectrum(directions: np.ndarray, sun: np.ndarray, altitude: float,
                 densities: np.ndarray) -> np.ndarray:
    """Single in-scattered spectrum (N, 21) along view directions (N, 3) from the camera at
    `altitude` (m): 32 segments, each evaluated at its middle, lit by the sun where the Earth
    does not block it."""
    origin = np.array([0.0, 0.0, _SS_EARTH_RADIUS + altitude])
    length = _ss_atmosphere_distance(origin[None], directions)
    segment = (length / _SS_STEPS)[:, None]
    mu = directions @ sun
    g2 = _SS_MIE_G * _SS_MIE_G
    phase = np.stack([(0.1875 / math.pi) * (1.0 + mu * mu),
                      3.0 * (1.0 - g2) * (1.0 + mu * mu)
                      / (8.0 * math.pi * (2.0 + g2)
                         * (1.0 + g2 - 2.0 * _SS_MIE_G * mu) ** 1.5)], -1)
    extinction = np.stack([_SS_RAYLEIGH_COEFF, np.full(21, 1.11 * _SS_MIE_COEFF), _SS_OZONE_COEFF])
    scattering = np.stack([_SS_RAYLEIGH_COEFF, np.full(21, _SS_MIE_COEFF)])
    spectrum = np.zeros((len(directions), 21))
    depth = np.zeros((len(directions), 3))
    # The sun as seen from a point: blocked by the Earth (Blender's test: the sun below the
    # local horizontal plane z and the line to it meeting the Earth's sphere).
    for i in range(_SS_STEPS):
        point = origin + (i + 0.5) * segment * directions
        density = densities * _ss_densities(np.linalg.norm(point, axis=-1) - _SS_EARTH_RADIUS)
        depth = depth + segment * density
        if sun[2] < 0:
            b = 2.0 * (point @ sun)
            c = np.sum(point * point, -1) - _SS_EARTH_RADIUS ** 2
            lit = b * b - 4.0 * c < 0.0
        else:
            lit = np.ones(len(directions), bool)
        light = densities * _ss_optical_depth(point, np.broadcast_to(sun, point.shape))
        attenuation = np.exp(-(depth + light) @ extinction)            # (N, 21)
        scattered = (phase * density[:, :2]) @ scattering              # (N, 21)
        spectrum += np.where(lit[:, None], attenuation * scattered * _SS_IRRADIANCE * segment, 0.0)
    return spectrum


def _spectrum_to_xyz_21(spectrum: np.ndarray) -> np.ndarray:
    return spectrum @ _SS_CMF * _SS_STEP_LAMBDA


def _single_scattering_table(params: SkyParams, width: int, height: int) -> np.ndarray:
    """Cycles' single scattering table (height, width, 3) of XYZ: row y > height / 2 at
    latitude pi/2 (y / (height/2) - 1)^2, column x < width / 2 at longitude 2 pi x / width - pi
    from the sun, mirrored; the rows below the horizon black."""
    elevation, _ = params.sun_angles()
    altitude = min(max(params.altitude, 1.0), 59999.0)
    half_width, half_height = width // 2, height // 2
    rows = np.arange(half_height + 1, height)
    latitude = math.pi / 2 * (rows / half_height - 1.0) ** 2
    longitude = 2 * math.pi / width * np.arange(half_width) - math.pi
    directions = _geographical(latitude[:, None], longitude[None, :]).reshape(-1, 3)
    sun = _geographical(elevation, 0.0)
    densities = np.array([params.air_density, params.aerosol_density, params.ozone_density])
    xyz = _spectrum_to_xyz_21(_ss_spectrum(directions, sun, altitude, densities))
    table = np.zeros((height, width, 3))
    table[half_height + 1:, :half_width] = xyz.reshape(len(rows), half_width, 3)
    table[:, half_width:] = table[:, :half_width][:, ::-1]
    return table


def _single_scattering_sun(params: SkyParams, diameter: float) -> tuple:
    """XYZ radiance of the sun disc at its lowest and highest point (clamped to the horizon;
    black when all of it is below), through the Rayleigh and Mie optical depth."""
    elevation, _ = params.sun_angles()
    altitude = min(max(params.altitude, 1.0), 59999.0)
    half = diameter / 2
    solid_angle = 2 * math.pi * (1 - math.cos(half))
    bottom, top = max(elevation - half, 0.0), max(elevation + half, 0.0)
    if not top > 0.0:
        return np.zeros(3), np.zeros(3)
    origin = np.array([[0.0, 0.0, _SS_EARTH_RADIUS + altitude]] * 2)
    depth = _ss_optical_depth(origin, _geographical(np.array([bottom, top]), 0.0))
    exponent = (np.outer(depth[:, 0], _SS_RAYLEIGH_COEFF) * params.air_density
                + np.outer(depth[:, 1], np.full(21, 1.11 * _SS_MIE_COEFF)) * params.aerosol_density)
    xyz = _spectrum_to_xyz_21(_SS_IRRADIANCE * np.exp(-exponent) / solid_angle)
    return xyz[0], xyz[1]


# ---------------------------------------------------------------- multiple scattering
_MS_EARTH_RADIUS = 6371.0          # km
_MS_ATMOSPHERE_THICKNESS = 100.0   # km
_MS_ATMOSPHERE_RADIUS = _MS_EARTH_RADIUS + _MS_ATMOSPHERE_THICKNESS
_MS_GROUND_ALBEDO = 0.3
_MS_G = 0.8                        # aerosols' anisotropy
_MS_TRANSMITTANCE_STEPS = 64
_MS_IN_SCATTERING_STEPS = 64
_MS_LUT_WIDTH, _MS_LUT_HEIGHT = 256, 64
# Four wavelengths: 630, 560, 490, 430 nm (urban aerosols).
_MS_SUN_IRRADIANCE = np.array([1.679, 1.828, 1.986, 1.307])
_MS_MOLECULAR_SCATTERING = np.array([6.605e-3, 1.067e-2, 1.842e-2, 3.156e-2])
_MS_OZONE_CROSS_SECTION = np.array([3.472e-25, 3.914e-25, 1.349e-25, 11.03e-27])
_MS_OZONE_MEAN_DOBSON = 334.5
_MS_AEROSOL_ABSORPTION = np.array([2.8722e-24, 4.6168e-24, 7.9706e-24, 1.3578e-23])
_MS_AEROSOL_SCATTERING = np.array([1.5908e-22, 1.7711e-22, 2.0942e-22, 2.4033e-22])
_MS_AEROSOL_BASE_DENSITY = 1.3681e20
_MS_AEROSOL_BACKGROUND_DENSITY = 2e6
_MS_AEROSOL_HEIGHT_SCALE = 0.73
# The four wavelengths' radiance -> XYZ.
_MS_SPECTRAL_XYZ = np.array([[53.386917738564668023, 22.981337506691024754, 0.0],
                             [43.904844466369358263, 71.347795700053393866, 0.102506867965741307],
                             [1.6137278251608962005, 18.422960591455485011, 31.742921188390805758],
                             [20.762668673810577145, 2.3614213523314368527, 110.48009643252140334]])


def _ray_sphere(position: np.ndarray, direction: np.ndarray, radius: float) -> np.ndarray:
    """Distance to a sphere around the origin along the ray; -1 where it misses (or lies
    behind an origin outside it); the far hit from inside, the near one from outside."""
    b = np.sum(position * direction, -1)
    c = np.sum(position * position, -1) - radius * radius
    d = b * b - c
    root = np.sqrt(np.maximum(d, 0.0))
    t = np.where(d >= b * b, -b + root, -b - root)
    return np.where(((c > 0) & (b > 0)) | (d < 0), -1.0, t)


class _MultipleScattering:
    """Blender 5.0's multiple scattering atmosphere (km): collision coefficients by altitude,
    a 256 x 64 transmittance table (cosine of the sun's zenith angle x normalised altitude)."""

    def __init__(self, air: float, aerosol: float, ozone: float):
        self.air, self.aerosol, self.ozone = air, aerosol, ozone
        u = np.arange(_MS_LUT_WIDTH) / (_MS_LUT_WIDTH - 1)
        v = np.arange(_MS_LUT_HEIGHT) / (_MS_LUT_HEIGHT - 1)
        cos_theta, altitude = np.meshgrid(u * 2 - 1, v)
        self.lut = self.transmittance(cos_theta.ravel(), altitude.ravel()).reshape(
            _MS_LUT_HEIGHT, _MS_LUT_WIDTH, 4)

    def coefficients(self, altitude: np.ndarray):
        """(extinction, molecular scattering, aerosol scattering), each (..., 4) per km."""
        altitude = np.asarray(altitude, np.float64)[..., None]
        aerosol = _MS_AEROSOL_BASE_DENSITY * (
            np.exp(-altitude / _MS_AEROSOL_HEIGHT_SCALE)
            + _MS_AEROSOL_BACKGROUND_DENSITY / _MS_AEROSOL_BASE_DENSITY) * self.aerosol
        log_h = np.log(np.maximum(altitude, 1e-4))
        ozone = 3.78547397e20 * np.exp(-(log_h - 3.22261) ** 2 * 5.55555555 - log_h)
        molecular_absorption = _MS_OZONE_CROSS_SECTION * _MS_OZONE_MEAN_DOBSON * ozone * self.ozone
        molecular = (_MS_MOLECULAR_SCATTERING * np.exp(-0.07771971 * altitude ** 1.16364243)
                     * self.air)
        aerosol_scattering = _MS_AEROSOL_SCATTERING * aerosol
        extinction = (_MS_AEROSOL_ABSORPTION * aerosol + aerosol_scattering
                      + molecular_absorption + molecular)
        return extinction, molecular, aerosol_scattering

    def transmittance(self, cos_theta: np.ndarray, normalized_altitude: np.ndarray) -> np.ndarray:
        """Transmittance (N, 4) towards a sun at zenith cosine `cos_theta`, from a normalised
        altitude, marched to the top of the atmosphere in 64 steps."""
        cos_theta = np.asarray(cos_theta, np.float64)
        sun = np.stack([-np.sqrt(np.maximum(1 - cos_theta ** 2, 0)), np.zeros_like(cos_theta),
                        cos_theta], -1)
        radius = _MS_EARTH_RADIUS + normalized_altitude * _MS_ATMOSPHERE_THICKNESS
        origin = np.stack([np.zeros_like(radius), np.zeros_like(radius), radius], -1)
        step = _ray_sphere(origin, sun, _MS_ATMOSPHERE_RADIUS) / _MS_TRANSMITTANCE_STEPS
        depth = 0.0
        for i in range(_MS_TRANSMITTANCE_STEPS):
            point = origin + ((i + 0.5) * step)[:, None] * sun
            altitude = np.maximum(np.linalg.norm(point, axis=-1) - _MS_EARTH_RADIUS, 0.0)
            depth = depth + self.coefficients(altitude)[0] * step[:, None]
        return np.exp(-depth)

    def lookup(self, cos_theta: np.ndarray, normalized_altitude: np.ndarray) -> np.ndarray:
        """The table bilinearly at (cos_theta, altitude), clamped to its range."""
        x = (_MS_LUT_WIDTH - 1) * np.clip(cos_theta * 0.5 + 0.5, 0.0, 1.0)
        y = (_MS_LUT_HEIGHT - 1) * np.clip(normalized_altitude, 0.0, 1.0)
        x1, y1 = x.astype(np.int64), y.astype(np.int64)
        x2, y2 = np.minimum(x1 + 1, _MS_LUT_WIDTH - 1), np.minimum(y1 + 1, _MS_LUT_HEIGHT - 1)
        fx, fy = (x - x1)[..., None], (y - y1)[..., None]
        flat = self.lut.reshape(-1, 4)
        y1, y2 = y1 * _MS_LUT_WIDTH, y2 * _MS_LUT_WIDTH
        a, b = np.take(flat, y1 + x1, 0), np.take(flat, y1 + x2, 0)
        c, d = np.take(flat, y2 + x1, 0), np.take(flat, y2 + x2, 0)
        bottom = a + fx * (b - a)
        return bottom + fy * (c + fx * (d - c) - bottom)

    def lookup_ground(self, cos_theta: np.ndarray) -> np.ndarray:
        """The table's ground row (altitude 0) at cos_theta."""
        x = (_MS_LUT_WIDTH - 1) * np.clip(cos_theta * 0.5 + 0.5, 0.0, 1.0)
        x1 = x.astype(np.int64)
        x2 = np.minimum(x1 + 1, _MS_LUT_WIDTH - 1)
        row = self.lut[0]
        a = np.take(row, x1, 0)
        return a + (x - x1)[..., None] * (np.take(row, x2, 0) - a)

    def multiple_scattering(self, cos_theta, normalized_altitude, distance) -> np.ndarray:
        """Light scattered more than once (N, 4): second order from the ground (albedo 0.3)
        plus the fit of Earth's multiple scattering."""
        omega = 2 * math.pi * (1 - np.sqrt(1 - (_MS_EARTH_RADIUS / distance) ** 2))
        to_ground = self.lookup_ground(cos_theta)
        column = self.lut[:, -1]                        # the sun at the zenith, by altitude
        y = (_MS_LUT_HEIGHT - 1) * np.clip(normalized_altitude, 0.0, 1.0)
        y1 = y.astype(np.int64)
        y2 = np.minimum(y1 + 1, _MS_LUT_HEIGHT - 1)
        at_sample = column[y1] + (y - y1)[..., None] * (column[y2] - column[y1])
        ground_to_sample = column[0] / at_sample
        ground = ((1 / (4 * math.pi)) * omega[..., None] * (_MS_GROUND_ALBEDO / math.pi)
                  * to_ground * ground_to_sample * cos_theta[..., None])
        fit = 0.02 * np.array([0.217, 0.347, 0.594, 1.0]) * (
            1.0 / (1.0 + 5.0 * np.exp(-17.92 * cos_theta)))[..., None]
        return fit + ground

    def inscattering(self, sun: np.ndarray, origin: np.ndarray, directions: np.ndarray,
                     distance: np.ndarray) -> np.ndarray:
        """In-scattered radiance (N, 4) along rays to `distance`, 64 steps, each integrated
        analytically against its extinction (Hillaire's energy-conserving step)."""
        cos_theta = -(directions @ sun)
        molecular_phase = (3.0 / 16.0) / math.pi * (1.0 + cos_theta ** 2)
        den = 1.0 + _MS_G * _MS_G + 2.0 * _MS_G * cos_theta
        aerosol_phase = (1 / (4 * math.pi)) * (1.0 - _MS_G * _MS_G) / (den * np.sqrt(den))
        dt = distance / _MS_IN_SCATTERING_STEPS
        radiance = np.zeros((len(directions), 4))
        transmittance = np.ones((len(directions), 4))
        for i in range(_MS_IN_SCATTERING_STEPS):
            point = origin + ((i + 0.5) * dt)[:, None] * directions
            centre_distance = np.linalg.norm(point, axis=-1)
            altitude = np.maximum(centre_distance - _MS_EARTH_RADIUS, 0.0)
            normalized = altitude / _MS_ATMOSPHERE_THICKNESS
            sample_cos = (point @ sun) / centre_distance
            extinction, molecular, aerosol = self.coefficients(altitude)
            to_sun = self.lookup(sample_cos, normalized)
            ms = self.multiple_scattering(sample_cos, normalized, centre_distance)
            source = _MS_SUN_IRRADIANCE * (molecular * (molecular_phase[:, None] * to_sun + ms)
                                           + aerosol * (aerosol_phase[:, None] * to_sun + ms))
            step = np.exp(-dt[:, None] * extinction)
            radiance += transmittance * (source - source * step) / np.maximum(extinction, 1e-7)
            transmittance *= step
        return radiance


def _multiple_scattering_table(params: SkyParams, width: int, height: int) -> np.ndarray:
    """Cycles' multiple scattering table (height, width, 3) of XYZ: texel (x, y) at azimuth
    2 pi (x + 0.5) / width from the sun's opposite, elevation l |l| pi / 2 with l = 2 (y + 0.5)
    / height - 1; mirrored about the sun; below the horizon the light scattered above the
    ground."""
    atmosphere = _MultipleScattering(params.air_density, params.aerosol_density,
                                     params.ozone_density)
    elevation, _ = params.sun_angles()
    altitude = min(max(params.altitude, 1.0), 99999.0) / 1000.0
    half_width = width // 2
    azimuth = 2 * math.pi * (np.arange(half_width) + 0.5) / width
    l = 2 * (np.arange(height) + 0.5) / height - 1
    view_elevation = np.sign(l) * l * l * math.pi / 2
    directions = _geographical(view_elevation[:, None], azimuth[None, :]).reshape(-1, 3)
    sun_cos = math.cos(math.pi / 2 - elevation)
    sun = np.array([-math.sqrt(max(1 - sun_cos * sun_cos, 0.0)), 0.0, sun_cos])
    origin = np.array([[0.0, 0.0, _MS_EARTH_RADIUS + altitude]])
    to_top = _ray_sphere(origin, directions, _MS_ATMOSPHERE_RADIUS)
    to_ground = _ray_sphere(origin, directions, _MS_EARTH_RADIUS)
    distance = np.where(to_ground < 0.0, to_top, to_ground)
    radiance = atmosphere.inscattering(sun, origin, directions, distance)
    table = np.zeros((height, width, 3))
    table[:, :half_width] = (radiance @ _MS_SPECTRAL_XYZ).reshape(height, half_width, 3)
    table[:, half_width:] = table[:, :half_width][:, ::-1]
    return table


def _multiple_scattering_sun(params: SkyParams, diameter: float) -> tuple:
    """XYZ radiance of the sun disc at its lowest and highest point: the sun's irradiance
    through the atmosphere's transmittance, over the disc's solid angle."""
    atmosphere = _MultipleScattering(params.air_density, params.aerosol_density,
                                     params.ozone_density)
    elevation, _ = params.sun_angles()
    altitude = min(max(params.altitude, 1.0), 99999.0) / 1000.0
    half = diameter / 2
    solid_angle = 2 * math.pi * (1 - math.cos(half))
    ends = np.array([elevation - half, elevation + half])
    transmittance = atmosphere.transmittance(np.cos(math.pi / 2 - ends),
                                             np.full(2, altitude / _MS_ATMOSPHERE_THICKNESS))
    xyz = (_MS_SUN_IRRADIANCE * transmittance / solid_angle) @ _MS_SPECTRAL_XYZ
    return xyz[0], xyz[1]


# ---------------------------------------------------------------- Preetham
def _perez(lam: np.ndarray, theta, gamma):
    return ((1.0 + lam[0] * np.exp(lam[1] / np.cos(theta)))
            * (1.0 + lam[2] * np.exp(lam[3] * gamma) + lam[4] * np.cos(gamma) ** 2))


def _preetham_state(params: SkyParams):
    """(sun theta, sun phi, zenith (Y, x, y), Perez coefficients of Y, x, y) as Cycles
    precomputes them from Sun Direction and Turbidity."""
    d = np.array(params.sun_direction, np.float64)
    norm = float(np.linalg.norm(d))
    d = d / norm if norm > 0 else np.array([0.0, 0.0, 1.0])
    theta, phi = math.acos(min(max(d[2], -1.0), 1.0)), math.atan2(d[0], d[1])
    t = params.turbidity
    chi = (4.0 / 9.0 - t / 120.0) * (math.pi - 2.0 * theta)
    zenith_Y = ((4.0453 * t - 4.9710) * math.tan(chi) - 0.2155 * t + 2.4192) * 0.06
    th2, th3 = theta * theta, theta ** 3
    zenith_x = ((0.00166 * th3 - 0.00375 * th2 + 0.00209 * theta) * t * t
                + (-0.02903 * th3 + 0.06377 * th2 - 0.03202 * theta + 0.00394) * t
                + (0.11693 * th3 - 0.21196 * th2 + 0.06052 * theta + 0.25886))
    zenith_y = ((0.00275 * th3 - 0.00610 * th2 + 0.00317 * theta) * t * t
                + (-0.04214 * th3 + 0.08970 * th2 - 0.04153 * theta + 0.00516) * t
                + (0.15346 * th3 - 0.26756 * th2 + 0.06670 * theta + 0.26688))
    coefficients = np.array([
        [0.1787 * t - 1.4630, -0.3554 * t + 0.4275, -0.0227 * t + 5.3251,
         0.1206 * t - 2.5771, -0.0670 * t + 0.3703],
        [-0.0193 * t - 0.2592, -0.0665 * t + 0.0008, -0.0004 * t + 0.2125,
         -0.0641 * t - 0.8989, -0.0033 * t + 0.0452],
        [-0.0167 * t - 0.2608, -0.0950 * t + 0.0092, -0.0079 * t + 0.2102,
         -0.0441 * t - 1.6537, -0.0109 * t + 0.0529]])
    zenith = np.array([zenith_Y, zenith_x, zenith_y])
    zenith = zenith / np.array([_perez(c, 0.0, theta) for c in coefficients])
    return theta, phi, zenith, coefficients


def _preetham_radiance(params: SkyParams, directions: np.ndarray) -> np.ndarray:
    """Preetham's sky (N, 3) linear RGB: the Perez function of the zenith angle (clamped just
    above the horizon: the ground repeats the horizon) and of the angle to the sun, in xyY."""
    sun_theta, sun_phi, zenith, coefficients = _preetham_state(params)
    theta = np.arccos(np.clip(directions[:, 2], -1.0, 1.0))
    phi = np.arctan2(directions[:, 0], directions[:, 1])
    cos_gamma = (np.sin(theta) * math.sin(sun_theta) * np.cos(phi - sun_phi)
                 + np.cos(theta) * math.cos(sun_theta))
    gamma = np.arccos(np.clip(cos_gamma, -1.0, 1.0))
    theta = np.minimum(theta, math.pi / 2 - 0.001)
    Y, x, y = (zenith[k] * _perez(coefficients[k], theta, gamma) for k in range(3))
    safe_y = np.where(y != 0, y, 1.0)
    X = np.where(y != 0, x / safe_y * Y, 0.0)
    Z = np.where((y != 0) & (Y != 0), (1.0 - x - y) / safe_y * Y, 0.0)
    return xyz_to_rgb(np.stack([X, Y, Z], -1))


# ---------------------------------------------------------------- the kernel's lookup
def sky_table(params: SkyParams) -> np.ndarray:
    """Cycles' precomputed 512 x 256 XYZ table of a Nishita type (rows bottom first; read-only,
    the last few kept by the settings it depends on: not the sun's rotation, size or
    intensity)."""
    if params.sky_type not in NISHITA_TYPES:
        raise ValueError(f"{params.sky_type} has no precomputed table")
    return _cached_table(params.sky_type, params.sun_angles()[0], params.altitude,
                         params.air_density, params.aerosol_density, params.ozone_density)


@functools.lru_cache(maxsize=4)
def _cached_table(sky_type, sun_elevation, altitude, air_density, aerosol_density, ozone_density):
    params = SkyParams(sky_type=sky_type, sun_elevation=sun_elevation, altitude=altitude,
                       air_density=air_density, aerosol_density=aerosol_density,
                       ozone_density=ozone_density)
    make = (_single_scattering_table if sky_type == "SINGLE_SCATTERING"
            else _multiple_scattering_table)
    table = make(params, TABLE_WIDTH, TABLE_HEIGHT)
    table.setflags(write=False)
    return table


def sun_pixels(params: SkyParams) -> tuple:
    """The sun disc's XYZ radiance at its lowest and highest point (Nishita types)."""
    diameter = max(params.sun_size, SMALLEST_SUN)
    if params.sky_type == "SINGLE_SCATTERING":
        return _single_scattering_sun(params, diameter)
    return _multiple_scattering_sun(params, diameter)


def _table_lookup(table: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup at (x, y) in [0, 1]^2 with texel centres at (i + 0.5) / size, clamped
    at the edges (Cycles' kernel_tex_image_interp, Linear, Extend)."""
    height, width = table.shape[:2]
    px, py = x * width - 0.5, y * height - 0.5
    ix, iy = np.floor(px), np.floor(py)
    fx, fy = (px - ix)[..., None], (py - iy)[..., None]
    ix, iy = ix.astype(np.int64), iy.astype(np.int64)
    x0, x1 = np.clip(ix, 0, width - 1), np.clip(ix + 1, 0, width - 1)
    y0, y1 = np.clip(iy, 0, height - 1), np.clip(iy + 1, 0, height - 1)
    return ((1 - fy) * ((1 - fx) * table[y0, x0] + fx * table[y0, x1])
            + fy * ((1 - fx) * table[y1, x0] + fx * table[y1, x1]))


def _earth_intersection_angle(altitude: float) -> float:
    """How far below the horizontal the Earth's edge lies, seen from `altitude` (m)."""
    return math.pi / 2 - math.asin(_MS_EARTH_RADIUS / (_MS_EARTH_RADIUS + altitude / 1000.0))


def _precise_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2.0 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


def _nishita_sky(params: SkyParams, table: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The sky without the sun (N, 3) linear RGB, as Cycles' kernel reads its table."""
    _, rotation = params.sun_angles()
    phi = np.arctan2(directions[:, 1], directions[:, 0])
    elevation = math.pi / 2 - np.arccos(np.clip(directions[:, 2], -1.0, 1.0))
    x = np.mod((-phi - math.pi / 2 + rotation) / (2 * math.pi), 1.0)
    y = np.sqrt(np.abs(elevation) / (math.pi / 2)) * np.where(elevation < 0, -1.0, 1.0) * 0.5 + 0.5
    rgb = xyz_to_rgb(_table_lookup(table, x, y))
    if params.sky_type == "SINGLE_SCATTERING":
        # Below the horizon: the horizon's colour fading to black at z = -0.4.
        z = directions[:, 2]
        fade = np.where(z < -0.4, 0.0, np.maximum(1.0 + z * 2.5, 0.0) ** 3)
        horizon = xyz_to_rgb(_table_lookup(table, x, np.full_like(x, 0.508)))
        rgb = np.where((z < 0.0)[:, None], horizon * fade[:, None], rgb)
    return rgb


def _nishita_sky_image(params: SkyParams, table: np.ndarray, width: int,
                       height: int) -> np.ndarray:
    """`_nishita_sky` at the texel centres of an equirectangular image (height, width, 3):
    the table's column depends on the azimuth alone and its row on the elevation alone, so
    the bilinear lookup is a blend of rows, then of columns."""
    _, rotation = params.sun_angles()
    table_height, table_width = table.shape[:2]

    def taps(coordinate, size):
        p = coordinate * size - 0.5
        i = np.floor(p)
        f = p - i
        i = i.astype(np.int64)
        return np.clip(i, 0, size - 1), np.clip(i + 1, 0, size - 1), f

    phi = 2 * math.pi * (0.5 - (np.arange(width) + 0.5) / width)
    elevation = math.pi * ((np.arange(height) + 0.5) / height - 0.5)
    x = np.mod((-phi - math.pi / 2 + rotation) / (2 * math.pi), 1.0)
    y = np.sqrt(np.abs(elevation) / (math.pi / 2)) * np.where(elevation < 0, -1.0, 1.0) * 0.5 + 0.5
    y0, y1, fy = taps(y, table_height)
    rows = table[y0] * (1 - fy)[:, None, None] + table[y1] * fy[:, None, None]
    x0, x1, fx = taps(x, table_width)
    xyz = rows[:, x0] * (1 - fx)[None, :, None] + rows[:, x1] * fx[None, :, None]
    rgb = xyz_to_rgb(xyz)
    if params.sky_type == "SINGLE_SCATTERING":
        z = np.sin(elevation)
        fade = np.where(z < -0.4, 0.0, np.maximum(1.0 + z * 2.5, 0.0) ** 3)
        h0, h1, fh = taps(np.array([0.508]), table_height)
        horizon_row = table[h0[0]] * (1 - fh[0]) + table[h1[0]] * fh[0]
        horizon = xyz_to_rgb(horizon_row[x0] * (1 - fx)[:, None] + horizon_row[x1] * fx[:, None])
        below = z < 0.0
        rgb[below] = horizon[None] * fade[below][:, None, None]
    return rgb


def _sun_disc(params: SkyParams, pixels: tuple, directions: np.ndarray) -> np.ndarray:
    """The sun disc's radiance (N, 3) linear RGB times Sun Intensity (0 outside the disc)."""
    if not params.sun_disc:
        return np.zeros((len(directions), 3))
    elevation, _ = params.sun_angles()
    diameter = max(params.sun_size, SMALLEST_SUN)
    half = diameter / 2
    angle = _precise_angle(directions, params.sun_vector()[None])
    view_elevation = math.pi / 2 - np.arccos(np.clip(directions[:, 2], -1.0, 1.0))
    inside = (angle < half) & (view_elevation > -_earth_intersection_angle(params.altitude))
    if params.sky_type == "SINGLE_SCATTERING":
        inside &= directions[:, 2] >= 0.0
    bottom, top = pixels
    y = (view_elevation - elevation) / diameter + 0.5
    xyz = bottom + y[:, None] * (top - bottom)
    limb = 1.0 - 0.6 * (1.0 - np.sqrt(np.maximum(1.0 - (angle / half) ** 2, 0.0)))
    rgb = xyz_to_rgb(xyz) * limb[:, None] * params.sun_intensity
    return np.where(inside[:, None], rgb, 0.0)


def sky_radiance(params: SkyParams, directions: np.ndarray, table: np.ndarray | None = None,
                 sun: tuple | None = None) -> np.ndarray:
    """The Sky Texture's colour (N, 3), linear Rec.709, in unit directions (N, 3), as Cycles'
    kernel evaluates it (svm_node_tex_sky) from its precomputed data."""
    directions = np.asarray(directions, np.float64).reshape(-1, 3)
    if params.sky_type == "PREETHAM":
        return _preetham_radiance(params, directions)
    if params.sky_type not in NISHITA_TYPES:
        raise ValueError(f"the {params.sky_type} sky is not computed by KD Trace")
    table = sky_table(params) if table is None else table
    sun = sun_pixels(params) if sun is None else sun
    return _nishita_sky(params, table, directions) + _sun_disc(params, sun, directions)


# ---------------------------------------------------------------- the world texture's image
def equirectangular_directions(width: int, height: int) -> np.ndarray:
    """Unit directions (height, width, 3) of the texel centres of an equirectangular image in
    Cycles' projection, rows bottom first."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    return _geographical(math.pi * (v - 0.5)[:, None], 2 * math.pi * (0.5 - u)[None, :])


def _disc_energy(params: SkyParams, pixels: tuple, rings: int = 256, spokes: int = 256):
    """Points over the sun disc (M, 3) and the energy each carries (M, 3): rings of equal
    solid angle times spokes, each point its cell's radiance x solid angle (midpoint rule)."""
    diameter = max(params.sun_size, SMALLEST_SUN)
    half = diameter / 2
    cap = 1.0 - math.cos(half)
    cos_r = 1.0 - cap * (np.arange(rings) + 0.5) / rings
    sin_r = np.sqrt(np.maximum(1 - cos_r ** 2, 0.0))
    spin = 2 * math.pi * (np.arange(spokes) + 0.5) / spokes
    centre = params.sun_vector()
    helper = np.array([0.0, 0.0, 1.0]) if abs(centre[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    t1 = np.cross(centre, helper)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(centre, t1)
    points = (cos_r[:, None, None] * centre
              + sin_r[:, None, None] * (np.cos(spin)[None, :, None] * t1
                                        + np.sin(spin)[None, :, None] * t2)).reshape(-1, 3)
    points /= np.linalg.norm(points, axis=-1, keepdims=True)
    solid_angle = 2 * math.pi * cap / (rings * spokes)
    return points, _sun_disc(params, pixels, points) * solid_angle


def _sun_texels(params: SkyParams, pixels: tuple, width: int, height: int) -> np.ndarray:
    """The sun disc integrated over each texel (height, width, 3): texels near the disc are
    supersampled (sub-texel steps at most 1/32 of the disc's diameter, at least 4 x 4 per
    texel), then scaled so the image holds exactly the disc's energy."""
    image = np.zeros((height, width, 3))
    if not params.sun_disc or params.sun_intensity <= 0.0:
        return image
    points, energy = _disc_energy(params, pixels)
    total = energy.sum(0)
    if not total.max() > 0.0:
        return image
    diameter = max(params.sun_size, SMALLEST_SUN)
    texel = math.pi / height
    reach = diameter / 2 + 1.5 * texel
    elevation, _ = params.sun_angles()
    band = np.nonzero(np.abs(math.pi * ((np.arange(height) + 0.5) / height - 0.5) - elevation)
                      < reach)[0]
    directions = equirectangular_directions(width, height)[band]
    near = _precise_angle(directions, params.sun_vector()[None, None]) < reach
    rows, columns = np.nonzero(near)
    rows = band[rows]
    k = int(min(max(math.ceil(texel / (diameter / 32)), 4), 256))
    offsets = (np.arange(k) + 0.5) / k
    sums = np.zeros((len(rows), 3))
    weights = np.zeros(len(rows))
    chunk = max(1, (1 << 20) // (k * k))
    for start in range(0, len(rows), chunk):
        r, c = rows[start:start + chunk], columns[start:start + chunk]
        u = (c[:, None, None] + offsets[None, None, :]) / width
        v = (r[:, None, None] + offsets[None, :, None]) / height
        shape = (len(r), k, k)
        elevation = np.broadcast_to(math.pi * (v - 0.5), shape)
        d = _geographical(elevation, np.broadcast_to(2 * math.pi * (0.5 - u), shape))
        cos_e = np.cos(elevation).reshape(len(r), -1)
        radiance = _sun_disc(params, pixels, d.reshape(-1, 3)).reshape(len(r), k * k, 3)
        sums[start:start + len(r)] = np.sum(radiance * cos_e[..., None], 1)
        weights[start:start + len(r)] = np.sum(cos_e, 1)
    image[rows, columns] = sums / np.maximum(weights, 1e-30)[:, None]
    # Exact energy: the texels' radiance x solid angle summed equals the disc's integral.
    v0, v1 = rows / height, (rows + 1) / height
    texel_solid = (2 * math.pi / width) * (np.sin(math.pi * (v1 - 0.5))
                                           - np.sin(math.pi * (v0 - 0.5)))
    held = np.sum(image[rows, columns] * texel_solid[:, None], 0)
    image *= np.where(held > 0, total / np.where(held > 0, held, 1.0), 0.0)
    return image


@functools.lru_cache(maxsize=4)
def _cached_image(params: SkyParams, width: int):
    height = width // 2
    if params.sky_type == "PREETHAM":
        directions = equirectangular_directions(width, height).reshape(-1, 3)
        rgb = _preetham_radiance(params, directions).reshape(height, width, 3)
    else:
        table, pixels = sky_table(params), sun_pixels(params)
        rgb = _nishita_sky_image(params, table, width, height)
        rgb += _sun_texels(params, pixels, width, height)
    peak = float(rgb.max())
    # A power of two: the texels keep their bits, the world colour carries the scale.
    scale = 2.0 ** math.ceil(math.log2(peak / TEXEL_CEILING)) if peak > TEXEL_CEILING else 1.0
    rgba = np.ones((height, width, 4), np.float32)
    rgba[..., :3] = rgb / scale
    rgba.setflags(write=False)
    return rgba, scale


def sky_image(params: SkyParams, width: int = IMAGE_WIDTH) -> tuple:
    """(RGBA float32 (width / 2, width, 4), scale): the sky as an equirectangular image in
    Cycles' projection (rows bottom first), its colour = texel x scale; the sun disc's energy
    integrated into the texels it covers. Read-only; the last few are kept by parameters."""
    if params.sky_type not in SUPPORTED_TYPES:
        raise ValueError(f"the {params.sky_type} sky is not computed by KD Trace")
    return _cached_image(params, int(width))
