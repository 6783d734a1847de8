"""Generates kernels/shade/ggx_albedo.cl: directional albedos of single-scattering GGX lobes
(height-correlated Smith masking), for the energy compensation of Cycles' Multiscatter GGX:
- GGX_E(mu, roughness), white Fresnel, and its cosine-weighted average GGX_E_AVG(roughness):
  metals (Turquin 2019);
- GLASS_E(mu, roughness, ior) of a rough dielectric boundary (reflection + transmission, as
  energy), entering (ior) and leaving (1 / ior): glass is scaled by 1 / E;
- SPECULAR_E(mu, roughness, ior), its reflection alone: what the specular layer of the
  Principled BSDF takes from the diffuse below it.
Run it after changing the tables' sizes:

    .venv/bin/python .ci/ggx_albedo.py

The tables are constants of the kernel source (identical bits on every device); tests/
test_materials.py checks a few entries against a fresh integration.
"""
from __future__ import annotations

import pathlib

import numpy as np

SIZE = 32               # mu and roughness both sampled at i / (SIZE - 1)
MIN_MU = 1e-3           # mu = 0 itself is the grazing limit
STRATA = 128            # STRATA^2 visible-normal samples per entry
DIELECTRIC_SIZE = 16    # mu, roughness and ior of the dielectric tables
IOR_RANGE = (1.0, 3.0)  # ior at i / (size - 1) of the range


def smith_lambda(alpha2, mu):
    mu2 = mu * mu
    return 0.5 * (-1.0 + np.sqrt(1.0 + alpha2 * (1.0 - mu2) / np.maximum(mu2, 1e-30)))


def fresnel_dielectric(cos_i, eta):
    sin2_t = (1 - cos_i * cos_i) / (eta * eta)
    cos_t = np.sqrt(np.maximum(1 - sin2_t, 0))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return np.where(sin2_t >= 1, 1.0, 0.5 * (rs * rs + rp * rp))


def visible_normals(mu, alpha, strata):
    """wo and stratified visible-normal samples m for it (Heitz 2018)."""
    wo = np.array([np.sqrt(1 - mu * mu), 0.0, mu])
    u1, u2 = np.meshgrid((np.arange(strata) + 0.5) / strata, (np.arange(strata) + 0.5) / strata)
    u1, u2 = u1.ravel(), u2.ravel()
    vh = np.array([alpha * wo[0], alpha * wo[1], wo[2]])
    vh /= np.linalg.norm(vh)
    t1 = np.array([1.0, 0.0, 0.0]) if vh[0] ** 2 + vh[1] ** 2 == 0 else \
        np.array([-vh[1], vh[0], 0.0]) / np.hypot(vh[0], vh[1])
    t2 = np.cross(vh, t1)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    p1, p2 = r * np.cos(phi), r * np.sin(phi)
    s = 0.5 * (1 + vh[2])
    p2 = (1 - s) * np.sqrt(1 - p1 * p1) + s * p2
    nh = (p1[:, None] * t1 + p2[:, None] * t2
          + np.sqrt(np.maximum(0, 1 - p1 * p1 - p2 * p2))[:, None] * vh)
    m = np.stack([alpha * nh[:, 0], alpha * nh[:, 1], np.maximum(nh[:, 2], 0)], axis=1)
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    return wo, m


def albedo(mu: float, roughness: float, strata: int = STRATA) -> float:
    """E(mu, roughness) by stratified sampling of visible normals (Heitz 2018): with that
    density the estimator of the albedo is G2 / G1(wo) wherever wi lies above the surface."""
    alpha = max(roughness * roughness, 1e-4)
    alpha2 = alpha * alpha
    mu = max(mu, MIN_MU)
    wo, m = visible_normals(mu, alpha, strata)
    wi = 2 * (m @ wo)[:, None] * m - wo
    mu_i = wi[:, 2]
    above = mu_i > 0
    g1 = 1 / (1 + smith_lambda(alpha2, mu))
    g2 = 1 / (1 + smith_lambda(alpha2, mu) + smith_lambda(alpha2, np.where(above, mu_i, 1)))
    return float(np.mean(np.where(above, g2 / g1, 0.0)))


def dielectric_albedo(mu: float, roughness: float, eta: float, strata: int = STRATA):
    """(reflection, reflection + transmission) albedo, as energy, of a rough dielectric
    boundary of relative IOR eta (n_t / n_i) seen at cos theta mu: Fresnel picks reflection
    or refraction at each visible normal, G2 / G1(wo) weighs the sample."""
    alpha = max(roughness * roughness, 1e-4)
    alpha2 = alpha * alpha
    mu = max(mu, MIN_MU)
    wo, m = visible_normals(mu, alpha, strata)
    cos_om = m @ wo
    F = fresnel_dielectric(cos_om, eta)
    g1 = 1 / (1 + smith_lambda(alpha2, mu))
    reflected = 2 * cos_om[:, None] * m - wo
    up = reflected[:, 2] > 0
    g2r = 1 / (1 + smith_lambda(alpha2, mu) + smith_lambda(alpha2, np.where(up, reflected[:, 2], 1)))
    sin2_t = (1 - cos_om * cos_om) / (eta * eta)
    cos_t = np.sqrt(np.maximum(1 - sin2_t, 0))
    refracted = -wo / eta + (cos_om / eta - cos_t)[:, None] * m
    down = (sin2_t < 1) & (refracted[:, 2] < 0)
    g2t = 1 / (1 + smith_lambda(alpha2, mu) + smith_lambda(alpha2, np.where(down, refracted[:, 2], -1)))
    reflection = np.mean(np.where(up, F * g2r / g1, 0.0))
    transmission = np.mean(np.where(down, (1 - F) * g2t / g1, 0.0))
    return float(reflection), float(reflection + transmission)


def dielectric_tables(size: int = DIELECTRIC_SIZE, strata: int = STRATA):
    """(SPECULAR_E, GLASS_E entering, GLASS_E leaving), each [ior][roughness][mu]."""
    grid = np.arange(size) / (size - 1)
    iors = IOR_RANGE[0] + grid * (IOR_RANGE[1] - IOR_RANGE[0])
    enter = np.array([[[dielectric_albedo(mu, r, ior, strata) for mu in grid] for r in grid]
                      for ior in iors])
    leave = np.array([[[dielectric_albedo(mu, r, 1 / ior, strata)[1] for mu in grid] for r in grid]
                      for ior in iors])
    return enter[..., 0], enter[..., 1], leave


def tables(size: int = SIZE, strata: int = STRATA):
    """(E (size x size, rows by roughness), E_avg (size,))."""
    grid = np.arange(size) / (size - 1)
    e = np.array([[albedo(mu, r, strata) for mu in grid] for r in grid])
    mus = (np.arange(4 * size) + 0.5) / (4 * size)
    e_avg = np.array([2 * np.mean([albedo(mu, r, strata) * mu for mu in mus]) for r in grid])
    return e, e_avg


def write(path: pathlib.Path) -> None:
    e, e_avg = tables()
    specular, enter, leave = dielectric_tables()

    def rows(values):
        return ",\n".join("    " + ", ".join(f"{v:.7f}f" for v in row) for row in values)
    path.write_text(
        "// Generated by .ci/ggx_albedo.py: do not edit.\n"
        "// GGX_E[r * GGX_TABLE_SIZE + m]: directional albedo of single-scattering GGX at\n"
        "// roughness r / (size - 1) and cos theta m / (size - 1); GGX_E_AVG[r]: its cosine-\n"
        "// weighted average over the hemisphere.\n"
        f"#define GGX_TABLE_SIZE {SIZE}\n"
        f"__constant float GGX_E[{SIZE * SIZE}] = {{\n{rows(e)}\n}};\n"
        f"__constant float GGX_E_AVG[{SIZE}] = {{\n{rows(e_avg.reshape(-1, 8))}\n}};\n"
        "// [(i * size + r) * size + m] at ior = 1 + 2 i / (size - 1), roughness r / (size - 1),\n"
        "// cos theta m / (size - 1): SPECULAR_E the reflection, GLASS_E_ENTER reflection +\n"
        "// transmission from outside, GLASS_E_LEAVE from inside (energy, without 1 / eta^2).\n"
        f"#define DIELECTRIC_TABLE_SIZE {DIELECTRIC_SIZE}\n"
        f"#define DIELECTRIC_IOR_MIN {IOR_RANGE[0]!r}f\n"
        f"#define DIELECTRIC_IOR_MAX {IOR_RANGE[1]!r}f\n"
        + "".join(f"__constant float {name}[{table.size}] = {{\n"
                  f"{rows(table.reshape(-1, DIELECTRIC_SIZE))}\n}};\n"
                  for name, table in (("SPECULAR_E", specular), ("GLASS_E_ENTER", enter),
                                      ("GLASS_E_LEAVE", leave))))


if __name__ == "__main__":
    write(pathlib.Path(__file__).resolve().parent.parent / "kernels" / "shade" / "ggx_albedo.cl")
