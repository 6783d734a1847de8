"""THE one place that derives what a scene needs from the exported scene ("specialisation").

`scene_features(geometry, view)` returns the feature set; the tracer turns it into -D build
options (slave/tracer.py kernel_options, so the kernel is compiled with only these features and
its cache key includes them), and `strip_geometry` drops the optional geometry arrays the
features do not need, so the scene blob carries only those. docs/shading.md lists the features.
"""
from __future__ import annotations

import numpy as np

from .model import MATERIAL_PARAMS, Geometry, View

# Roughness below which a surface is a perfect mirror (reflection rays, no light highlight);
# at or above it, a GGX highlight from the lights and no reflection rays. Shared with the kernel.
MIRROR_ROUGHNESS = 0.1

# Every feature, and the geometry arrays each one needs (beyond vertices/triangles/material_ids).
FEATURES = {
    "POINT": (), "SUN": (), "SPOT": (), "AREA": (),  # light kinds present
    "SOFT_LIGHTS": (),        # a point/spot light with a radius or a sun with an angle
    "SMOOTH": ("normals",),   # interpolated (or custom split) corner normals
    "TEXTURES": ("uvs", "texels", "texture_sizes"),  # image-textured base colours
    "SPECULAR": (),           # metallic or specular > 0: highlights and mirror reflection
    "TRANSMISSION": (),       # refraction, Fresnel, total internal reflection; coloured shadows
    "ALPHA": (),              # alpha cut-out (< 1): rays and shadow rays pass through
    "EMISSION": (),           # emissive materials
    "BOUNCES": (),            # secondary rays at all (max_bounces > 0 and something to bounce)
    "DIFFUSE_BOUNCES": (),    # diffuse interreflection
}
ALL_FEATURES = frozenset(FEATURES)


def scene_features(geometry: Geometry, view: View, used_materials=None) -> frozenset:
    """The features the scene (geometry + the frame's view) needs. Only materials that some
    triangle uses count, so an unused glass material does not switch refraction on.
    `used_materials`: those material ids, when known (core.scene.scene.Scene keeps them)."""
    shading = view.shading
    features = {light.kind for light in shading.lights}
    if any((light.kind in ("POINT", "SPOT", "SUN") and light.radius > 0) for light in shading.lights):
        features.add("SOFT_LIGHTS")
    used = np.zeros(len(shading.materials), bool)
    if used_materials is None:
        used_materials = np.unique(geometry.material_ids)
    ids = np.asarray(used_materials)
    used[ids[ids < len(used)]] = True
    params = shading.material_params[used]
    colours = shading.materials[used]

    def column(name):
        return params[:, MATERIAL_PARAMS.index(name)]

    if geometry.normals is not None:
        features.add("SMOOTH")
    if geometry.texture_count and (column("texture") >= 0).any():
        features.add("TEXTURES")
    if ((column("metallic") > 0) | (column("specular") > 0)).any():
        features.add("SPECULAR")
    transmissive = (column("transmission") > 0) & (column("metallic") < 1)
    if transmissive.any():
        features.add("TRANSMISSION")
    if (colours[:, 3] < 1).any():
        features.add("ALPHA")
    if (params[:, 4:7] > 0).any():
        features.add("EMISSION")
    settings = view.settings
    mirrors = (((column("metallic") > 0) | (column("specular") > 0))
               & (column("roughness") < MIRROR_ROUGHNESS)).any()
    diffuse = settings.diffuse_bounces > 0 and len(colours) > 0
    if settings.max_bounces > 0 and (mirrors or transmissive.any() or diffuse):
        features.add("BOUNCES")
        if diffuse:
            features.add("DIFFUSE_BOUNCES")
    return frozenset(features)


def needed_arrays(features) -> set:
    """Names of the optional Geometry arrays that the features need."""
    return {name for feature in features for name in FEATURES.get(feature, ())}


def strip_geometry(geometry: Geometry, features) -> Geometry:
    """The geometry with only the optional arrays that `features` need (the others None)."""
    keep = needed_arrays(features)
    return Geometry(geometry.vertices, geometry.triangles, geometry.material_ids,
                    *(getattr(geometry, name) if name in keep else None
                      for name in ("normals", "uvs", "texels", "texture_sizes")))


def full_geometry(geometry: Geometry) -> Geometry:
    """The geometry with every optional array present (neutral values where the scene has
    none: flat corner normals, zero UVs, one white texel): what an unspecialised kernel that
    compiles every feature needs. Used to measure what specialisation saves."""
    corners = geometry.vertices[geometry.triangles].astype(np.float64)
    normals = geometry.normals
    if normals is None:
        n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        n = np.where(length > 0, n / np.where(length > 0, length, 1), 0.0)
        normals = np.repeat(n, 3, axis=0)
    uvs = geometry.uvs if geometry.uvs is not None else np.zeros((3 * geometry.triangle_count, 2))
    texels, sizes = geometry.texels, geometry.texture_sizes
    if texels is None:
        texels, sizes = np.ones((1, 4)), np.array([[0, 1, 1]])
    return Geometry(geometry.vertices, geometry.triangles, geometry.material_ids, normals, uvs,
                    texels, sizes)
