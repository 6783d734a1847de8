"""THE one place that derives what a scene needs from the exported scene ("specialisation").

`scene_features(geometry, view)` returns the feature set; the tracer turns it into -D build
options (slave/tracer.py kernel_options, so the kernel is compiled with only these features and
its cache key includes them), and `strip_geometry` drops the optional geometry arrays the
features do not need, so the scene blob carries only those. docs/shading.md lists the features.
"""
from __future__ import annotations

import numpy as np

from ..layout import CLOSURE_CODES, NODE_OP_CODES, VISIBILITY_CODES, VISIBLE_TO_ALL
from .model import MATERIAL_PARAMS, Geometry, View

# Every feature, and the geometry arrays each one needs (beyond vertices/triangles/material_ids).
FEATURES = {
    "POINT": (), "SUN": (), "SPOT": (), "AREA": (),  # light kinds present
    "SOFT_LIGHTS": (),        # a point/spot light with a radius or a sun with an angle
    "SPHERE_LIGHTS": (),      # a point/spot light with a radius and Soft Falloff off
    "SMOOTH": ("normals",),   # interpolated (or custom split) corner normals
    "TEXTURES": ("uvs", "texels", "texture_sizes"),  # image-textured base colours
    "SPECULAR": (),           # metallic or specular > 0: GGX reflection (any roughness)
    "TRANSMISSION": (),       # GGX refraction and reflection of glass, total internal reflection
    "TRANSLUCENT": (),        # diffuse transmission (Translucent BSDF)
    "COAT": (),               # Principled's Coat: a GGX dielectric layer over the others
    "ALPHA": (),              # alpha cut-out (< 1): rays and shadow rays pass through
    "EMISSION": (),           # emissive materials: seen, and their triangles sampled as lights
    "WORLD": (),              # the world lights the scene (a colour that is not black)
    "WORLD_TEXTURE": ("texels", "texture_sizes"),   # an Environment Texture, importance-sampled
    "BOUNCES": (),            # BSDF rays: bounces, or lights that a BSDF ray can hit (MIS)
    "TRANSPARENT_FILM": (),   # Film > Transparent: camera rays that miss give alpha 0
    "HOLDOUT": (),            # holdout objects: black (and alpha 0 with a transparent film)
    "VISIBILITY": (),         # objects that some kinds of rays do not see (ray visibility)
    "DOF": (),                # depth of field: a thin lens with an aperture
    "CAMERA_MOTION": (),      # camera motion blur: the camera moves while the shutter is open
    "NODES": ("uvs",),        # shader node programs compute BSDF inputs per hit
    "NOISE": (),              # a node program evaluates a Noise, Wave, Magic, Brick or White Noise
                              # Texture
    "VORONOI": (),            # a node program evaluates a Voronoi Texture
    "LIGHT_PATH": (),         # a node program reads the ray's kind or depths (Light Path)
    "NORMAL_MAP": (),         # a node program evaluates a Normal Map (sets the shading normal)
    "BUMP": (),               # a node program evaluates a Bump (heights at three points)
    "CLOSURES": (),           # materials of several closures (Mix / Add Shader) or of closures
                              # other than a BSDF (Transparent, Holdout, Emission in a mix)
    "INSTANCES": (),          # instanced meshes under a top-level BVH (docs/instances.md)
    "OBJECT_MOTION": (),      # object motion blur: instances move while the shutter is open
}
ALL_FEATURES = frozenset(FEATURES)

# The passes a frame may ask for beyond the image, depth and normal (core/net/protocol.py
# TILE_PASSES), and the kernel features that compute them: FILM (the film buffer of pass sums,
# core/layout.py FILM) with what fills it. Never part of a scene's features: a frame asks.
PASS_FEATURES = {
    "albedo": ("FILM", "GUIDES"),               # Denoising Albedo (Cycles' guides)
    "denoising_normal": ("FILM", "GUIDES"),     # Denoising Normal
    "mist": ("FILM", "PASS_MIST"),
    "emission": ("FILM", "PASS_EMISSION"),
    "diffuse_color": ("FILM", "PASS_DIFFUSE_COLOR"),
    "glossy_color": ("FILM", "PASS_GLOSSY_COLOR"),
}


def pass_features(passes) -> frozenset:
    """The kernel features that compute the passes `passes` (names of TILE_PASSES); the
    image, depth and normal need none."""
    return frozenset(feature for name in passes for feature in PASS_FEATURES.get(name, ()))


def scene_features(geometry: Geometry, view: View, used_materials=None,
                   instances=None) -> frozenset:
    """The features the scene (geometry + the frame's view) needs. Only materials that some
    triangle uses count, so an unused glass material does not switch refraction on.
    `used_materials`: those material ids, when known (core.scene.scene.Scene keeps them);
    `instances`: an instanced scene's InstanceSet (core/scene/instances.py)."""
    shading = view.shading
    features = {light.kind for light in shading.lights}
    if any((light.kind in ("POINT", "SPOT", "SUN") and light.radius > 0) for light in shading.lights):
        features.add("SOFT_LIGHTS")
    if any(light.kind in ("POINT", "SPOT") and light.radius > 0 and not light.soft_falloff
           for light in shading.lights):
        features.add("SPHERE_LIGHTS")
    used = np.zeros(len(shading.materials), bool)
    if used_materials is None:
        used_materials = geometry.used_material_ids()
    ids = np.asarray(used_materials)
    heads = ids[ids < len(used)]
    used[shading.closure_rows(heads)] = True     # every closure of the used materials
    params = shading.material_params[used]
    colours = shading.materials[used]

    def column(name):
        return params[:, MATERIAL_PARAMS.index(name)]

    kind = column("kind")
    bsdf = kind == CLOSURE_CODES["PRINCIPLED"]
    if (shading.param("closures")[heads] > 1).any() or (~bsdf).any():
        features.add("CLOSURES")

    if geometry.normals is not None:
        features.add("SMOOTH")
    programs = column("program")
    if (programs >= 0).any():
        features.add("NODES")
        ops = program_instructions(shading.node_program, programs[programs >= 0])[:, 0]
        for feature in ("NOISE", "NORMAL_MAP", "BUMP", "VORONOI", "LIGHT_PATH"):
            if (ops == NODE_OP_CODES[feature]).any():
                features.add(feature)
        if np.isin(ops, [NODE_OP_CODES[op] for op in ("WAVE", "MAGIC", "BRICK", "WHITE_NOISE")]).any():
            features.add("NOISE")
    if geometry.texture_count and ((column("texture") >= 0).any() or
                                   program_textures(shading.node_program, programs[programs >= 0])):
        features.add("TEXTURES")
    specular = bsdf & ((column("metallic") > 0) | (column("specular") > 0))
    if specular.any():
        features.add("SPECULAR")
    transmissive = bsdf & (column("transmission") > 0) & (column("metallic") < 1)
    if transmissive.any():
        features.add("TRANSMISSION")
    translucent = bsdf & (column("translucent") > 0)
    if translucent.any():
        features.add("TRANSLUCENT")
    coat = bsdf & (column("coat_weight") > 0)
    if coat.any():
        features.add("COAT")
    if (colours[:, 3] < 1).any() or (kind == CLOSURE_CODES["TRANSPARENT"]).any():
        features.add("ALPHA")
    if (kind == CLOSURE_CODES["HOLDOUT"]).any():
        features.add("HOLDOUT")
    emission = np.stack([column(f"emission_{c}") for c in "rgb"], axis=1) if len(params) else \
        np.zeros((0, 3))
    if (emission > 0).any():
        features.add("EMISSION")
    visibility = column("visibility").astype(np.int64)
    if (visibility & VISIBILITY_CODES["HOLDOUT"]).any():
        features.add("HOLDOUT")
    if ((visibility & VISIBLE_TO_ALL) != VISIBLE_TO_ALL).any():
        features.add("VISIBILITY")
    if instances is not None:
        features.add("INSTANCES")
        bits = instances.visibility.astype(np.int64)
        if (bits & VISIBILITY_CODES["HOLDOUT"]).any():
            features.add("HOLDOUT")
        if ((bits & VISIBLE_TO_ALL) != VISIBLE_TO_ALL).any():
            features.add("VISIBILITY")
        if instances.moving:
            features.add("OBJECT_MOTION")
    if view.film_transparent:
        features.add("TRANSPARENT_FILM")
    camera = view.camera
    if camera.kind == "PERSP" and camera.aperture > 0:
        features.add("DOF")
    if camera.to_world_end is not None and not np.array_equal(camera.to_world_end, camera.to_world):
        features.add("CAMERA_MOTION")
    if shading.world_lights:
        features.add("WORLD")
        if shading.world_texture is not None:
            features.add("WORLD_TEXTURE")
    settings = view.settings
    # Diffuse: every material but pure metal and pure glass has a diffuse part.
    diffuse = settings.diffuse_bounces > 0 and bool(
        (bsdf & ((1 - column("metallic")) * (1 - column("transmission")) > 0)).any())
    glossy = settings.glossy_bounces > 0 and bool(specular.any() or coat.any())
    refractive = settings.transmission_bounces > 0 and bool(transmissive.any() or
                                                            translucent.any())
    bounces = settings.max_bounces > 0 and (diffuse or glossy or refractive)
    # A BSDF ray can also find the area lights, suns with an angle, the world and emissive
    # triangles that direct light samples: the two are weighted against each other.
    hittable = bool({"AREA", "WORLD", "EMISSION"} & features) or any(
        light.kind == "SUN" and light.radius > 0 for light in shading.lights)
    if len(params) and (bounces or hittable):
        features.add("BOUNCES")
    return frozenset(features)


def program_instructions(program: np.ndarray, starts) -> np.ndarray:
    """The instructions (N, 8: both rows) of the node programs starting at `starts` (rows, -1
    none), each up to its END: every instruction that one of them runs, once, in program
    order. In time linear in the program and the starts (programs that share their ends,
    65535 materials starting at 65535 rows of one chain, took minutes walked one by one)."""
    starts = np.unique(np.asarray(starts, np.int64))
    starts = starts[(starts >= 0) & (starts < len(program))]
    pairs = program[:len(program) // 2 * 2].reshape(-1, 8)     # instructions start on even rows
    if (starts % 2).any():                                      # (check_node_program's starts)
        raise ValueError("a node program starts on an odd row")
    first = starts // 2
    ends = np.flatnonzero(pairs[:, 0] == NODE_OP_CODES["END"])
    stop = np.append(ends, len(pairs))[np.searchsorted(ends, first)]   # each start's END
    # Instructions in any [first, stop): +1 where a range begins, -1 after it ends.
    inside = np.zeros(len(pairs) + 1, np.int64)
    np.add.at(inside, first, 1)
    np.add.at(inside, stop, -1)
    return pairs[np.cumsum(inside[:-1]) > 0]


def program_textures(program: np.ndarray, starts) -> set:
    """The texture indices that the node programs starting at `starts` (rows, -1 none) read
    (Image Textures, and the corner arrays of Color Attributes)."""
    code = program_instructions(program, starts)
    reads = np.isin(code[:, 0], [NODE_OP_CODES["IMAGE"], NODE_OP_CODES["ATTRIBUTE"]])
    return {int(v) for v in code[reads, 5]}


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
