"""Every layout that the host and the kernels share, as tables: the kd-tree node words (the
builder's plain nodes and the tracer's compact nodes), the records of the tracer's buffers
(lights, materials, camera, world, emissive triangles, tree bounds, triangle corners, texture
sizes, accumulators), the builder's and compactor's rows and element sizes, the codes
stored in them, and the tracer's kernels' parameter lists.

The builder and the compactor (core/accel/), the validator and the packers (slave/buffers.py)
take their numbers from here, and `c_header()` writes the same tables as the C header that
core/opencl.py puts in front of every kernel source: a kernel names a field (`KD_GROUP(w)`,
`LIGHT_POSITION(L)`) and never spells its bits or slot itself. tests/test_layout.py checks
the header against these tables on the device.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

LANES = "xyzw"


@dataclass(frozen=True)
class BitField:
    """`bits` bits of a 32-bit node word, from bit `shift` on.

    C: NAME_SHIFT, NAME_BITS, NAME_MAX (the largest value), NAME(w) (the value in word w),
    NAME_PUT(v) (v in place), and NAME_BIT (the bit itself) for a one-bit field."""

    name: str
    shift: int
    bits: int
    doc: str

    @property
    def max(self) -> int:
        return (1 << self.bits) - 1

    @property
    def bit(self) -> int:
        assert self.bits == 1, f"{self.name} is not a one-bit field"
        return 1 << self.shift

    def get(self, word):
        """The field's value in `word` (an int or an integer numpy array)."""
        return (word >> self.shift) & self.max

    def put(self, value):
        """`value` in the field's place (to be or-ed into a word)."""
        return value << self.shift


@dataclass(frozen=True)
class Constant:
    name: str
    value: int
    doc: str


@dataclass(frozen=True)
class NodeFormat:
    """One kind of 8-byte node: two uint32 words. `fields` are bits of word 0; `words` says
    what each word holds."""

    title: str
    words: tuple
    fields: tuple
    constants: tuple = ()


@dataclass(frozen=True)
class Slot:
    """A value in a record of float4s (or float2s): `lanes` of element `index`, or `rows`
    whole elements from `index` on."""

    name: str
    index: int
    lanes: str
    doc: str
    rows: int = 1

    def indices(self):
        """numpy index of the value within one record (its last two axes)."""
        if self.rows > 1:
            return slice(self.index, self.index + self.rows), slice(None)
        first, last = LANES.index(self.lanes[0]), LANES.index(self.lanes[-1])
        assert self.lanes == LANES[first:last + 1], f"{self.name}: lanes must be contiguous"
        return self.index, (first if first == last else slice(first, last + 1))


@dataclass(frozen=True)
class Record:
    """One element of a buffer: `size` vectors of `width` floats (float4 or float2), holding
    the named slots; unnamed lanes are 0.

    C: PREFIX_SIZE, PREFIX_<SLOT>_SLOT (its first vector) and PREFIX_<SLOT>(r), the value in
    the record at pointer r (a pointer to its rows for a slot of several rows)."""

    prefix: str
    title: str
    size: int
    slots: tuple
    width: int = 4

    def slot(self, name: str) -> Slot:
        for slot in self.slots:
            if slot.name == name:
                return slot
        raise KeyError(f"{self.prefix} has no slot {name!r}")

    def put(self, records, name, value) -> None:
        """Write slot `name` of the record(s) `records` (numpy, last axes (size, width))."""
        records[(Ellipsis, *self.slot(name).indices())] = value

    def get(self, records, name):
        return records[(Ellipsis, *self.slot(name).indices())]


@dataclass(frozen=True)
class Columns:
    """A row of `columns` 32-bit words per item, integers unless the title says float32 (C:
    PREFIX_COLUMNS, PREFIX_<NAME> per column). A row that kernels load as one OpenCL vector
    (`vector`, such as "uint4", of as many lanes as columns) also has PREFIX_<NAME>_OF(v): that
    column's lane of v, to read or to assign."""

    prefix: str
    title: str
    columns: tuple
    vector: str = ""

    def index(self, name: str) -> int:
        return self.columns.index(name)

    @property
    def nbytes(self) -> int:
        """Bytes of one row."""
        return 4 * len(self.columns)


@dataclass(frozen=True)
class Element:
    """An element of a buffer whose fields only kernels read: its C type (an OpenCL vector
    type, or a struct a kernel file defines) and its size, by which the host allocates (C:
    PREFIX_BYTES; tests/test_layout.py checks sizeof(ctype) on the device)."""

    prefix: str
    title: str
    ctype: str
    nbytes: int


@dataclass(frozen=True)
class Codes:
    """Integer codes stored in a float slot (C: PREFIX_<NAME> per code)."""

    prefix: str
    title: str
    codes: dict


# ---------------------------------------------------------------------------------------------
# kd-tree nodes

LEAF_TAG = 3                    # word 0 bits 0-1 of a leaf (0/1/2 is an inner node's axis)
NO_TRIANGLE = 0xFFFFFFFF        # an empty second reference of a T-reference slot

# The builder's plain tree (core/accel/kdtree.py, Wald's 8-byte layout): siblings side by side.
PLAIN_TAG = BitField("KD_PLAIN_TAG", 0, 2, "split axis 0/1/2, or KD_LEAF_TAG for a leaf")
PLAIN_FIELD = BitField("KD_PLAIN_FIELD", 2, 30,
                       "inner: index of the below child (the above child follows it); "
                       "leaf: count of its triangle references")
PLAIN_NODE = NodeFormat(
    "Plain kd-tree node (core/accel/kdtree.py)",
    ("word 0: the fields below",
     "word 1: inner: split position (float32 bits); leaf: offset of its list in leaf_indices"),
    (PLAIN_TAG, PLAIN_FIELD),
    (Constant("KD_LEAF_TAG", LEAF_TAG, "word 0 tag of a leaf"),))

# The compact tree the tracer traverses (core/accel/compact.py, docs/kdtree_compression.md).
TAG = BitField("KD_TAG", 0, 2, "split axis 0/1/2, or KD_LEAF_TAG for a leaf")
INNER_REF = BitField("KD_REF", 2, 1, "R: a T-reference slot heads the node's group")
INNER_EMPTY_BELOW = BitField("KD_EMPTY_BELOW", 3, 1,
                             "Eb: the below child is an empty leaf and is not stored")
INNER_EMPTY_ABOVE = BitField("KD_EMPTY_ABOVE", 4, 1,
                             "Ea: the above child is an empty leaf and is not stored (never "
                             "together with Eb)")
INNER_GROUP = BitField("KD_GROUP", 5, 27,
                       "index of the node's group: the T-reference slot (if R), the below "
                       "child (unless Eb), the above child (unless Ea), in this order")
LEAF_WIDE = BitField("KD_LEAF16", 2, 1,
                     "W: 1 = 16-bit list in leaf_index16, 0 = 32-bit list in leaf_index32")
LEAF32_COUNT = BitField("KD_LEAF32_COUNT", 3, 29, "W = 0: triangle count")
LEAF16_COUNT = BitField("KD_LEAF16_COUNT", 3, 13, "W = 1: triangle count")
LEAF16_BASE = BitField("KD_LEAF16_BASE", 16, 16,
                       "W = 1: base B; triangle = (B << leaf_shift) + leaf_index16[offset + j]")
LEAF16_INDEX_BITS = 16          # an entry of leaf_index16
MAX_LEAF_SHIFT = 32 - LEAF16_BASE.bits     # B << leaf_shift spans every 32-bit index
COMPACT_NODE = NodeFormat(
    "Compact kd-tree node (core/accel/compact.py): inner node, T-reference slot or leaf",
    ("inner word 0: KD_TAG (axis), KD_REF, KD_EMPTY_BELOW, KD_EMPTY_ABOVE, KD_GROUP",
     "inner word 1: split position (float32 bits)",
     "T-reference slot: word 0 first triangle, word 1 second triangle or KD_NO_TRIANGLE "
     "(always in mode choi)",
     "leaf word 0: KD_TAG = KD_LEAF_TAG, KD_LEAF16, then KD_LEAF32_COUNT or KD_LEAF16_COUNT "
     "and KD_LEAF16_BASE",
     "leaf word 1: offset of its list in leaf_index32 (W = 0) or leaf_index16 (W = 1)"),
    (TAG, INNER_REF, INNER_EMPTY_BELOW, INNER_EMPTY_ABOVE, INNER_GROUP, LEAF_WIDE,
     LEAF32_COUNT, LEAF16_COUNT, LEAF16_BASE),
    (Constant("KD_NO_TRIANGLE", NO_TRIANGLE, "no second triangle in a T-reference slot"),
     Constant("KD_MAX_LEAF_SHIFT", MAX_LEAF_SHIFT, "the largest leaf_shift")))

NODE_FORMATS = (PLAIN_NODE, COMPACT_NODE)

# ---------------------------------------------------------------------------------------------
# The tracer's buffers (packed by slave/buffers.py)

LIGHT_CODES = {"POINT": 0, "SUN": 1, "SPOT": 2, "AREA": 3}
AREA_SHAPE_CODES = {"RECTANGLE": 0, "ELLIPSE": 1}     # Blender's SQUARE / DISK are the same shapes
CAMERA_CODES = {"PERSP": 0, "ORTHO": 1}
# Film > Pixel Filter (core/scene/model.py RenderSettings.pixel_filter): box samples uniformly
# over the filter width; the others through the inverse CDF tabulated after the CAMERA record.
PIXEL_FILTER_CODES = {"BOX": 0, "GAUSSIAN": 1, "BLACKMAN_HARRIS": 2}
FILTER_TABLE_SIZE = 257         # odd: its middle entry is the pixel centre exactly
PROJECTION_CODES = {"EQUIRECTANGULAR": 0, "MIRROR_BALL": 1}
INTERPOLATION_CODES = {"LINEAR": 0, "CLOSEST": 1}
# Ray visibility of an object (Blender's Object > Visibility > Ray Visibility) and its holdout,
# bits of MATERIAL_VISIBILITY: the exporter gives such objects records of their own.
VISIBILITY_CODES = {"CAMERA": 1, "DIFFUSE": 2, "GLOSSY": 4, "TRANSMISSION": 8, "SHADOW": 16,
                    "HOLDOUT": 32}
VISIBLE_TO_ALL = 31             # every ray sees it; no holdout
# A material is a set of closures (Mix Shader, Add Shader): 1 to MAX_CLOSURES consecutive
# MATERIAL records, the first saying how many (MATERIAL_CLOSURES), each a closure of one kind
# with its weight (docs/shading.md, Closures). PRINCIPLED scatters (every BSDF node maps onto
# its parameters); EMISSION only emits; TRANSPARENT lets the ray through, tinted by its base
# colour; HOLDOUT cuts the camera's view (alpha) and is black.
CLOSURE_CODES = {"PRINCIPLED": 0, "EMISSION": 1, "TRANSPARENT": 2, "HOLDOUT": 3}
MAX_CLOSURES = 4
# Shader node programs (addon/node_program.py NodeProgram; evaluated by shading.cl run_nodes):
# instructions of two float4 rows, (op, dst, a, b) and (c, p0, p1, p2); a, b, c are operand
# references register * NODE_REF_REGISTER + lane (0-3: that lane in all four, 4: the whole
# register). CONST loads its second row; OUT stores operand a into a BSDF input. Under a Bump
# node the height's coordinates are read three times: UV p0 and TRANSFORM p1 name the step
# (0: the hit, 1 and 2: a small step along the surface; shading.cl bump_offsets).
NODE_OP_CODES = {"END": 0, "CONST": 1, "UV": 2, "IMAGE": 3, "COMBINE": 4, "MIX": 5, "MATH": 6,
                 "INVERT": 7, "CHECKER": 8, "RAMP": 9, "OUT": 10, "DOT": 11, "MAP_RANGE": 12,
                 "VECTOR_MATH": 13, "HSV": 14, "GRADIENT": 15, "TRANSFORM": 16, "NOISE": 17,
                 "NORMAL_MAP": 18, "BUMP": 19, "FRESNEL": 20, "LAYER_WEIGHT": 21, "VORONOI": 22,
                 "WAVE": 23, "MAGIC": 24, "BRICK": 25, "WHITE_NOISE": 26, "ATTRIBUTE": 27,
                 "OBJECT_INFO": 28, "GEOMETRY": 29, "LIGHT_PATH": 30}
NODE_MIX_CODES = {"MIX": 0, "ADD": 1, "MULTIPLY": 2, "SUBTRACT": 3, "SCREEN": 4,
                  "DIFFERENCE": 5, "DARKEN": 6, "LIGHTEN": 7}
# Blender's Math and Vector Math operations, every one (Cycles' svm_math, svm_vector_math).
NODE_MATH_CODES = {"ADD": 0, "SUBTRACT": 1, "MULTIPLY": 2, "DIVIDE": 3, "MULTIPLY_ADD": 4,
                   "POWER": 5, "MINIMUM": 6, "MAXIMUM": 7, "LESS_THAN": 8, "GREATER_THAN": 9,
                   "ABSOLUTE": 10, "SQRT": 11, "INVERSE_SQRT": 12, "LOGARITHM": 13,
                   "EXPONENT": 14, "RADIANS": 15, "DEGREES": 16, "SIGN": 17, "COMPARE": 18,
                   "SMOOTH_MIN": 19, "SMOOTH_MAX": 20, "ROUND": 21, "FLOOR": 22, "CEIL": 23,
                   "TRUNC": 24, "FRACT": 25, "MODULO": 26, "FLOORED_MODULO": 27, "WRAP": 28,
                   "SNAP": 29, "PINGPONG": 30, "SINE": 31, "COSINE": 32, "TANGENT": 33,
                   "SINH": 34, "COSH": 35, "TANH": 36, "ARCSINE": 37, "ARCCOSINE": 38,
                   "ARCTANGENT": 39, "ARCTAN2": 40}
NODE_VECTOR_MATH_CODES = {"ADD": 0, "SUBTRACT": 1, "MULTIPLY": 2, "DIVIDE": 3, "SCALE": 4,
                          "DOT_PRODUCT": 5, "CROSS_PRODUCT": 6, "LENGTH": 7, "NORMALIZE": 8,
                          "ABSOLUTE": 9, "MINIMUM": 10, "MAXIMUM": 11, "MULTIPLY_ADD": 12,
                          "DISTANCE": 13, "PROJECT": 14, "REFLECT": 15, "REFRACT": 16,
                          "FACEFORWARD": 17, "SNAP": 18, "FLOOR": 19, "CEIL": 20, "MODULO": 21,
                          "FRACTION": 22, "WRAP": 23, "SINE": 24, "COSINE": 25, "TANGENT": 26,
                          "POWER": 27, "SIGN": 28}
NODE_GRADIENT_CODES = {"LINEAR": 0, "QUADRATIC": 1, "EASING": 2, "DIAGONAL": 3, "RADIAL": 4,
                       "QUADRATIC_SPHERE": 5, "SPHERICAL": 6}
NODE_EXTENSION_CODES = {"REPEAT": 0, "EXTEND": 1, "CLIP": 2, "MIRROR": 3}   # Image Texture
# Noise Texture types (NOISE p0 = normalize + 2 colour + 4 dimensions + 32 type)
NODE_NOISE_TYPE_CODES = {"FBM": 0, "MULTIFRACTAL": 1, "HYBRID_MULTIFRACTAL": 2,
                         "RIDGED_MULTIFRACTAL": 3, "HETERO_TERRAIN": 4}
NODE_OUT_CODES = {"BASE_COLOR": 0, "ALPHA": 1, "METALLIC": 2, "ROUGHNESS": 3,
                  "TRANSMISSION": 4, "IOR": 5, "SPECULAR": 6, "NORMAL": 7, "EMISSION": 8,
                  "WEIGHT": 9, "COAT_WEIGHT": 10, "COAT_ROUGHNESS": 11, "COAT_IOR": 12,
                  "COAT_TINT": 13}
# Layer Weight outputs (LAYER_WEIGHT p0): Cycles' NODE_LAYER_WEIGHT_FRESNEL and _FACING.
NODE_LAYER_WEIGHT_CODES = {"FRESNEL": 0, "FACING": 1}
# Voronoi Texture (VORONOI p0 = dimensions + 8 feature + 64 metric + 512 normalize + 1024
# output; p1 randomness, p2 W): Blender's features and metrics, and which output the
# instruction computes (DISTANCE: the Distance or the Radius; POSITION: the Position and W).
NODE_VORONOI_FEATURE_CODES = {"F1": 0, "F2": 1, "SMOOTH_F1": 2, "DISTANCE_TO_EDGE": 3,
                              "N_SPHERE_RADIUS": 4}
NODE_VORONOI_METRIC_CODES = {"EUCLIDEAN": 0, "MANHATTAN": 1, "CHEBYCHEV": 2, "MINKOWSKI": 3}
NODE_VORONOI_OUTPUT_CODES = {"DISTANCE": 0, "COLOR": 1, "POSITION": 2}
# Wave Texture (WAVE p0 = type + 2 bands direction + 8 rings direction + 32 profile).
NODE_WAVE_TYPE_CODES = {"BANDS": 0, "RINGS": 1}
NODE_WAVE_BANDS_CODES = {"X": 0, "Y": 1, "Z": 2, "DIAGONAL": 3}
NODE_WAVE_RINGS_CODES = {"X": 0, "Y": 1, "Z": 2, "SPHERICAL": 3}
NODE_WAVE_PROFILE_CODES = {"SIN": 0, "SAW": 1, "TRI": 2}
# Color Attribute / Attribute (ATTRIBUTE p0: the texture holding the value at each triangle
# corner, p1: output), Object Info (OBJECT_INFO p0: its table, p1: output: the table's rows are
# location and Random, colour and alpha, object and material pass index), Geometry (GEOMETRY
# p0: output, p1: bump step), Light Path (LIGHT_PATH p0: output, Cycles' NodeLightPath order).
NODE_ATTRIBUTE_CODES = {"COLOR": 0, "FAC": 1, "ALPHA": 2}
NODE_OBJECT_INFO_CODES = {"LOCATION": 0, "COLOR": 1, "ALPHA": 2, "OBJECT_INDEX": 3,
                          "MATERIAL_INDEX": 4, "RANDOM": 5}
NODE_GEOMETRY_CODES = {"POSITION": 0, "NORMAL": 1, "TRUE_NORMAL": 2, "INCOMING": 3,
                       "BACKFACING": 4}
NODE_LIGHT_PATH_CODES = {"IS_CAMERA_RAY": 0, "IS_SHADOW_RAY": 1, "IS_DIFFUSE_RAY": 2,
                         "IS_GLOSSY_RAY": 3, "IS_SINGULAR_RAY": 4, "IS_REFLECTION_RAY": 5,
                         "IS_TRANSMISSION_RAY": 6, "IS_VOLUME_SCATTER_RAY": 7, "RAY_LENGTH": 9,
                         "RAY_DEPTH": 10, "DIFFUSE_DEPTH": 11, "GLOSSY_DEPTH": 12,
                         "TRANSPARENT_DEPTH": 13, "TRANSMISSION_DEPTH": 14, "PORTAL_DEPTH": 15}
# The kind of a ray a node program sees (ShadeInfo.path): Cycles' PATH_RAY_* bits it reads.
PATH_CODES = {"CAMERA": 1, "SHADOW": 2, "DIFFUSE": 4, "GLOSSY": 8, "SINGULAR": 16, "REFLECT": 32,
              "TRANSMIT": 64}
NODE_NORMAL_SPACE_CODES = {"TANGENT": 0, "OBJECT": 1, "WORLD": 2, "BLENDER_OBJECT": 3,
                           "BLENDER_WORLD": 4}      # Normal Map (NORMAL_MAP p1)
NODE_OBJECT_NORMAL_SPACES = ("OBJECT", "BLENDER_OBJECT")    # these read the object's rows (p0)
NODE_REGISTERS = 16
NODE_REF_REGISTER = 8           # operand = register * 8 + lane
NODE_RAMP_SIZE = 256            # colour ramps as tables of this many RGBA rows (as Cycles)
NODE_TRANSFORM_SIZE = 4         # TRANSFORM: the hit point through a 3 x 4 matrix (Generated,
                                # Object coordinates): its 3 rows and one unused, after the END
# The top-level BVH of instanced scenes (core/accel/toplevel.py; TOPLEVEL_NODE below).
TOPLEVEL_LEAF_MAX = 4           # instances in a top-level leaf
TOPLEVEL_MAX_DEPTH = 48         # levels of the top-level BVH (its traversal stack)
# The compactor (compact_lifts.cl lift_candidates: per reference of a triangle, its nearest gaps
# on the left and right and a stack).
LIFT_SCRATCH_WORDS = 3
CODES = (Codes("LIGHT", "Light kinds (LIGHT_KIND)", LIGHT_CODES),
         Codes("LIGHT_SHAPE", "Area light shapes (LIGHT_AREA_SHAPE)", AREA_SHAPE_CODES),
         Codes("CAMERA", "Camera kinds (CAMERA_KIND)", CAMERA_CODES),
         Codes("PIXEL_FILTER", "Pixel filters (CAMERA_FILTER)", PIXEL_FILTER_CODES),
         Codes("FILTER_TABLE", "The pixel filter's inverse CDF after the CAMERA record",
               {"SIZE": FILTER_TABLE_SIZE}),
         Codes("PROJECTION", "World texture projections (WORLD_PROJECTION)", PROJECTION_CODES),
         Codes("INTERPOLATION", "World texture interpolation (WORLD_INTERPOLATION)",
               INTERPOLATION_CODES),
         Codes("VISIBILITY", "Ray visibility bits (MATERIAL_VISIBILITY)", VISIBILITY_CODES),
         Codes("CLOSURE", "Closure kinds (MATERIAL_KIND)", CLOSURE_CODES),
         Codes("CLOSURES", "Closures of a material", {"MAX": MAX_CLOSURES}),
         Codes("NODE_OP", "Shader node program operations", NODE_OP_CODES),
         Codes("NODE_MIX", "Mix node blend types (MIX p0)", NODE_MIX_CODES),
         Codes("NODE_MATH", "Math node operations (MATH p0)", NODE_MATH_CODES),
         Codes("NODE_OUT", "BSDF inputs a program sets (OUT p0)", NODE_OUT_CODES),
         Codes("NODE_VECTOR_MATH", "Vector Math operations (VECTOR_MATH p0)",
               NODE_VECTOR_MATH_CODES),
         Codes("NODE_GRADIENT", "Gradient Texture types (GRADIENT p0)", NODE_GRADIENT_CODES),
         Codes("NODE_EXTENSION", "Image Texture extensions (IMAGE p2)", NODE_EXTENSION_CODES),
         Codes("NODE_NORMAL_SPACE", "Normal Map spaces (NORMAL_MAP p1)", NODE_NORMAL_SPACE_CODES),
         Codes("NODE_NOISE_TYPE", "Noise Texture types (NOISE p0 / 32)", NODE_NOISE_TYPE_CODES),
         Codes("NODE_LAYER_WEIGHT", "Layer Weight outputs (LAYER_WEIGHT p0)",
               NODE_LAYER_WEIGHT_CODES),
         Codes("NODE_VORONOI", "Voronoi features (VORONOI p0 / 8 % 8)", NODE_VORONOI_FEATURE_CODES),
         Codes("NODE_VORONOI_METRIC", "Voronoi distance metrics (VORONOI p0 / 64 % 8)",
               NODE_VORONOI_METRIC_CODES),
         Codes("NODE_VORONOI_OUT", "Voronoi outputs (VORONOI p0 / 1024)",
               NODE_VORONOI_OUTPUT_CODES),
         Codes("NODE_WAVE", "Wave types (WAVE p0 % 2)", NODE_WAVE_TYPE_CODES),
         Codes("NODE_WAVE_BANDS", "Wave bands directions (WAVE p0 / 2 % 4)", NODE_WAVE_BANDS_CODES),
         Codes("NODE_WAVE_RINGS", "Wave rings directions (WAVE p0 / 8 % 4)", NODE_WAVE_RINGS_CODES),
         Codes("NODE_WAVE_PROFILE", "Wave profiles (WAVE p0 / 32)", NODE_WAVE_PROFILE_CODES),
         Codes("NODE_ATTRIBUTE", "Attribute outputs (ATTRIBUTE p1)", NODE_ATTRIBUTE_CODES),
         Codes("NODE_OBJECT_INFO", "Object Info outputs (OBJECT_INFO p1)", NODE_OBJECT_INFO_CODES),
         Codes("NODE_GEOMETRY", "Geometry outputs (GEOMETRY p0)", NODE_GEOMETRY_CODES),
         Codes("NODE_LIGHT_PATH", "Light Path outputs (LIGHT_PATH p0)", NODE_LIGHT_PATH_CODES),
         Codes("PATH", "The kind of ray a node program sees (ShadeInfo path bits)", PATH_CODES),
         Codes("TOPLEVEL", "Top-level BVH sizes",
               {"LEAF_MAX": TOPLEVEL_LEAF_MAX, "MAX_DEPTH": TOPLEVEL_MAX_DEPTH}),
         Codes("NODE", "Shader node program sizes",
               {"REGISTERS": NODE_REGISTERS, "REF_REGISTER": NODE_REF_REGISTER,
                "RAMP_SIZE": NODE_RAMP_SIZE, "TRANSFORM_SIZE": NODE_TRANSFORM_SIZE}),
         Codes("LIFT_SCRATCH", "lift_candidates' scratch", {"WORDS": LIFT_SCRATCH_WORDS}))

LIGHT = Record("LIGHT", "A light (lights buffer, light_count records)", 6, (
    Slot("position", 0, "xyz", "position"),
    Slot("kind", 0, "w", "a LIGHT_<KIND> code"),
    Slot("direction", 1, "xyz", "unit direction the light points"),
    Slot("spot_cos_half", 1, "w", "spot: cos of half the cone angle"),
    Slot("intensity", 2, "xyz", "colour times power times the kind's unit factor"),
    Slot("spot_smooth", 2, "w", "spot: 1 / ((1 - cos_half) blend), 0 = hard edge"),
    Slot("area_u", 3, "xyz", "area: axis_u times size_u"),
    Slot("radius", 3, "w", "point/spot: radius (0 = hard shadows)"),
    Slot("area_v", 4, "xyz", "area: axis_v times size_v"),
    Slot("area_shape", 4, "w", "area: a LIGHT_SHAPE_<SHAPE> code"),
    Slot("sun_cos_half_angle", 5, "x", "sun: cos of half the angular diameter (1 = sharp)"),
    Slot("sphere", 5, "y", "point/spot with a radius: 1 = a sphere of light (Soft Falloff off), "
         "0 = a disk facing the surface (on)"),
))

MATERIAL = Record("MATERIAL", "A closure of a material (materials buffer; a triangle's material "
                  "id names the first of its closures)", 7, (
    Slot("base_color", 0, "xyz", "base colour"),
    Slot("alpha", 0, "w", "alpha (< 1: cut-out)"),
    Slot("metallic", 1, "x", "metallic"),
    Slot("roughness", 1, "y", "roughness"),
    Slot("transmission", 1, "z", "transmission"),
    Slot("ior", 1, "w", "index of refraction"),
    Slot("emission", 2, "xyz", "emission colour times strength"),
    Slot("specular", 2, "w", "specular IOR level (0.5 = as the IOR says)"),
    Slot("texture", 3, "x", "base colour texture index, -1 = none"),
    Slot("texture_alpha", 3, "y", "1: the texture's alpha multiplies alpha, 0: it does not"),
    Slot("visibility", 3, "z", "VISIBILITY_<RAY> bits of the rays that see it, and HOLDOUT (as a "
         "float)"),
    Slot("program", 3, "w", "row of its shader node program in the materials buffer, -1 = none"),
    Slot("closures", 4, "x", "the first closure of a material: its closures, this one and the "
         "records after it (1 to CLOSURES_MAX)"),
    Slot("weight", 4, "y", "the closure's weight (the product of the Mix Shader factors on its "
         "path; its program may set it: then a stand-in)"),
    Slot("kind", 4, "z", "a CLOSURE_<KIND> code"),
    Slot("translucent", 4, "w", "the share of a diffuse transmission lobe (Translucent BSDF: 1)"),
    Slot("coat_weight", 5, "x", "Principled Coat Weight (0: no coat)"),
    Slot("coat_roughness", 5, "y", "Coat Roughness"),
    Slot("coat_ior", 5, "z", "Coat IOR"),
    Slot("coat_tint", 6, "xyz", "Coat Tint"),
))

CAMERA = Record("CAMERA", "The camera (one record; the pixel filter's table follows it)", 13, (
    Slot("to_world", 0, "xyzw", "rows of camera.to_world (3x4: rotation/scale, translation)",
         rows=3),
    Slot("ndc_scale", 3, "xy", "camera-space point = ndc * ndc_scale + ndc_offset"),
    Slot("ndc_offset", 3, "zw", "see ndc_scale"),
    Slot("view_axis", 4, "xyz", "unit view axis in world space"),
    Slot("kind", 4, "w", "a CAMERA_<KIND> code"),
    Slot("clip_start", 5, "x", "clip start (distance along the view axis)"),
    Slot("clip_end", 5, "y", "clip end"),
    Slot("width", 5, "z", "image width in pixels"),
    Slot("height", 5, "w", "image height in pixels"),
    Slot("world_color", 6, "xyz", "world colour (what a miss sees)"),
    Slot("aperture", 7, "x", "thin lens: aperture radius (0 = a pinhole)"),
    Slot("focus_distance", 7, "y", "thin lens: distance of the plane in focus along the view axis"),
    Slot("blades", 7, "z", "aperture blades (0 or fewer than 3: a disc)"),
    Slot("blade_rotation", 7, "w", "rotation of the blades in radians"),
    Slot("to_world_end", 8, "xyzw", "rows of camera.to_world at the shutter's close (motion "
         "blur; the same as to_world without it)", rows=3),
    Slot("filter", 11, "x", "the pixel filter, a PIXEL_FILTER_<KIND> code"),
    Slot("filter_width", 11, "y", "its width in pixels"),
    Slot("mist_start", 11, "z", "the Mist pass: distance from the camera where mist starts"),
    Slot("mist_inv_depth", 11, "w", "1 / the distance over which it reaches 1 (0: never)"),
    Slot("mist_falloff", 12, "x", "its falloff as a power (2 quadratic, 1 linear, 0.5)"),
))

BOUNDS = Record("BOUNDS", "The kd-tree's root box (bounds buffer, one record)", 2, (
    Slot("min", 0, "xyz", "lower corner"),
    Slot("extent", 0, "w", "max |coordinate| of the box: the scene's size for the tie tolerance"),
    Slot("max", 1, "xyz", "upper corner"),
))

TRIANGLE = Record("TRIANGLE", "A triangle (tri_verts buffer, by triangle index)", 3, (
    Slot("v0", 0, "xyz", "first corner"),
    Slot("v1", 1, "xyz", "second corner (weight u)"),
    Slot("v2", 2, "xyz", "third corner (weight v)"),
))

ACCUM = Record("ACCUM", "A pixel's colour accumulator (accum buffer, by tile pixel)", 2, (
    Slot("color", 0, "xyz", "sum of the samples' RGB"),
    Slot("samples", 0, "w", "number of samples"),
    Slot("alpha", 1, "x", "sum of the samples' alpha"),
    Slot("half", 1, "yzw", "sum of the RGB of Cycles' class A samples (its adaptive half buffer)"),
))

# The passes beside the image (kernels/shade/film.cl; finished by slave/film.py): a pixel's
# sums, kept only when the frame asks for a pass that needs them (the FILM feature). Its
# guides (GUIDES) are Cycles' denoising features; the others its data passes of the camera hit.
FILM = Record("FILM", "A pixel's pass sums (film buffer, by tile pixel)", 5, (
    Slot("albedo", 0, "xyz", "Denoising Albedo: the guide surface's albedo x the tint on the way"),
    Slot("samples", 0, "w", "samples traced into this record"),
    Slot("guide_normal", 1, "xyz", "Denoising Normal: the guide surface's shading normal (world)"),
    Slot("mist", 1, "w", "Mist: (1 - mist) x the path's weight at the camera hit, summed"),
    Slot("emission", 2, "xyz", "Emission: emission seen by camera rays"),
    Slot("diffuse_color", 3, "xyz", "Diffuse Color: the camera hit's diffuse albedo"),
    Slot("glossy_color", 4, "xyz", "Glossy Color: the camera hit's glossy albedo"),
))

# The world as a light (core/scene/model.py Shading.world_color and world_texture; packed by
# slave/buffers.py pack_world). The constant colour itself is CAMERA_WORLD_COLOR; with a texture
# it multiplies the texture. Directions go to the texture's own space through `to_texture`
# (the Mapping node's linear part); sampling maps back through `from_texture`.
WORLD = Record("WORLD", "The world (one record)", 8, (
    Slot("to_texture", 0, "xyzw", "rows of the 3x3 map from a world direction to the texture's "
         "direction (w unused)", rows=3),
    Slot("from_texture", 3, "xyzw", "rows of its inverse", rows=3),
    Slot("texture", 6, "x", "texture index into the texture table, -1 = a constant colour"),
    Slot("projection", 6, "y", "a PROJECTION_<NAME> code"),
    Slot("interpolation", 6, "z", "an INTERPOLATION_<NAME> code"),
    Slot("det", 6, "w", "|det| of to_texture (the solid-angle Jacobian of the mapping)"),
    Slot("cdf_width", 7, "x", "columns of the importance map (env_cdf)"),
    Slot("cdf_height", 7, "y", "rows of the importance map"),
))

# Emissive triangles as lights: an alias table over their power (slave/buffers.py
# pack_emitters). Sampling: pick record i uniformly, keep it if u < threshold, else take its
# alias; `pmf` is the probability of picking the record's own triangle.
EMITTER = Record("EMITTER", "An emissive triangle (emitters buffer, emitter_count records)", 1, (
    Slot("triangle", 0, "x", "triangle index (uint bits)"),
    Slot("alias", 0, "y", "the record taken when the threshold test fails (uint bits)"),
    Slot("threshold", 0, "z", "probability of keeping this record"),
    Slot("pmf", 0, "w", "probability of choosing this triangle: its power over all emitters'"),
))

# Instanced scenes (core/scene/instances.py; docs/instances.md): instances of meshes, each
# mesh a compact kd-tree in object space, and a top-level BVH over the instances' world boxes
# (core/accel/toplevel.py). Integers travel as uint bits of float slots.
INSTANCE = Record("INSTANCE", "An instance (instances buffer, in the top level's leaf order)", 10, (
    Slot("to_object", 0, "xyzw", "rows of the 3x4 world -> object transform", rows=3),
    Slot("to_world", 3, "xyzw", "rows of the 3x4 object -> world transform", rows=3),
    Slot("mesh", 6, "x", "its mesh: a row of the MESH table (uint bits)"),
    Slot("key_base", 6, "y", "hit key of its first triangle: the triangles of the instances "
         "before it (uint bits); key = key_base + triangle within the mesh"),
    Slot("visibility", 6, "z", "VISIBILITY_<RAY> bits of the rays that see it, and HOLDOUT"),
    Slot("orientation", 6, "w", "sign of det(to_world): -1 flips the geometric normal"),
    Slot("to_world_end", 7, "xyzw", "rows of the object -> world transform at shutter close "
         "(HAS_OBJECT_MOTION: blended with to_world at the ray's time)", rows=3),
))

TOPLEVEL_NODE = Record("TOPLEVEL", "A top-level BVH node (toplevel buffer; node 0 the root)", 2, (
    Slot("min", 0, "xyz", "lower corner of its world box"),
    Slot("first", 0, "w", "inner: the first child (the second follows it); leaf: its first "
         "instance record (uint bits)"),
    Slot("max", 1, "xyz", "upper corner"),
    Slot("count", 1, "w", "leaf: its instances (1 to TOPLEVEL_LEAF_MAX); inner: 0 (uint bits)"),
))

RECORDS = (LIGHT, MATERIAL, CAMERA, BOUNDS, TRIANGLE, ACCUM, FILM, WORLD, EMITTER, INSTANCE,
           TOPLEVEL_NODE)

# Geometry.texture_sizes (core/scene/model.py): one row per texture.
TEXTURE_SIZE = Columns("TEXTURE_SIZE", "A texture (texture_sizes, uint32 rows)",
                       ("offset", "width", "height"))
# An instanced scene's meshes: where each one's triangles and compact tree lie in the
# concatenated buffers (its tree's node, leaf-list and triangle indices count from these bases).
MESH = Columns("MESH", "A mesh of an instanced scene (meshes, uint32 rows)",
               ("tri_base", "tri_count", "node_base", "leaf32_base", "leaf16_base", "leaf_shift"))

# ---------------------------------------------------------------------------------------------
# The kd-tree builder's and compactor's buffers (core/accel/binned.py, compact_cl.py;
# kernels/build/): rows the host writes or reads by column, and the elements it only sizes.

CELL = Columns("CELL", "A box (float32 rows): a node's cell in the compaction's topology (by "
               "place in the level)", ("lo_x", "lo_y", "lo_z", "hi_x", "hi_y", "hi_z"))
# The compaction (compact_cl.py; compact*.cl).
CLIMB = Columns("CLIMB", "A node's climb record, by its preorder number (climb buffer): end of its "
                "preorder range, the parent's number, depth, the node",
                ("end", "parent", "depth", "node"), "uint4")
LIFT_GROUPED = Columns("LIFT_GROUPED", "A lift candidate grouped by node (grouped buffer; "
                       "cand_group)", ("triangle", "references", "first", "end"), "uint4")
LIFT_CANDIDATE = Columns("LIFT_CANDIDATE", "A lift candidate (lift_candidates' output, uint32 "
                         "rows): the run of a triangle's references first .. end - 1 below node",
                         ("depth", "node", "triangle", "references", "first", "end"))
LAYOUT_COUNTS = Columns("LAYOUT_COUNTS", "A block of nodes' counts for the compact tree's stats "
                        "(layout_stats, uint32 rows)",
                        ("leaves", "empty_leaves_stored", "empty_leaves_elided", "leaves_16bit",
                         "leaves_32bit", "inner", "largest_leaf", "collapsed_kept"))
# The binned builder (core/accel/binned.py; kernels/build/binned*.cl), one level at a time.
BIN_NODE = Columns("BIN_NODE", "A node of the level being split (nodes buffer; lo, hi float32 "
                   "bits): its cell, its references' places in the level, bad refines on its path",
                   ("lo_x", "lo_y", "lo_z", "hi_x", "hi_y", "hi_z", "first", "count",
                    "bad_refines", "unused"))
BIN_CHUNK = Columns("BIN_CHUNK", "A chunk of a big node's references (chunks buffer): the node, "
                    "its places, and (choose_big) its first places among the node's below and "
                    "above child's references and leaf entries",
                    ("node", "first", "count", "below", "above", "leaf"))
BIN_BIG = Columns("BIN_BIG", "A big node (big buffer): the node, its first chunk, its chunks",
                  ("node", "first_chunk", "chunks"))
BIN_SUMS = Columns("BIN_SUMS", "A block of a level's nodes (level_sums): inner nodes, places of "
                   "their children's references, leaf entries, leaves, empty leaves, the largest "
                   "child, SAH cost (int64 in 2^-32, low and high word)",
                   ("inner", "places", "leaf_refs", "leaves", "empty_leaves", "widest", "sah_low",
                    "sah_high"))
BIN_PLACES = Columns("BIN_PLACES", "A block's first inner node, reference place and leaf entry "
                     "(emit)", ("inner", "places", "leaf_refs"))
BIN_BOUNDS = Columns("BIN_BOUNDS", "A block of first references' bounds (ref_bounds, float32 "
                     "rows; kept: uint bits)", ("lo_x", "lo_y", "lo_z", "hi_x", "hi_y", "hi_z",
                                                "kept"))
COLUMNS = (TEXTURE_SIZE, MESH, CELL, CLIMB, LIFT_GROUPED, LIFT_CANDIDATE, LAYOUT_COUNTS,
           BIN_NODE, BIN_CHUNK, BIN_BIG, BIN_SUMS, BIN_PLACES, BIN_BOUNDS)

BUILD_REF = Element("BUILD_REF", "A triangle reference of the build (binned.cl): its box, the "
                    "triangle's uint bits in lo.w", "Ref", 32)
BUILD_SPLIT = Element("BUILD_SPLIT", "A node's decision and its children's places (binned.cl)",
                      "Split", 32)
WALK = Element("WALK", "A node's walk record by preorder number (compact.cl): area, the "
               "parent's number, non-empty leaves below and whether the area never shrinks up",
               "WalkRecord", 16)
ELEMENTS = (BUILD_REF, BUILD_SPLIT, WALK)


# ---------------------------------------------------------------------------------------------
# Kernel parameters: the argument list of each tracer kernel, written once. A kernel is
# declared `__kernel void render_samples(RENDER_SAMPLES_PARAMS)` (c_header writes the list)
# and slave/tracer.py passes its arguments by name through the same table
# (`KernelParams.present`), so that neither side can reorder, add or retype an argument alone
# (tests/test_kernel_sources.py checks both against the table).

# OpenCL scalar types and the numpy types the host passes them as.
SCALAR_DTYPES = {"int": "int32", "uint": "uint32", "float": "float32"}


@dataclass(frozen=True)
class Param:
    """A kernel parameter. `ctype` ending in "*": a buffer of that element type in global
    memory, read (`access` "in": `__global const T *`), written ("out": `__global T *`) or
    counted on atomically ("atomic": `volatile __global T *`); else a scalar passed by value.
    `when`: the features (HAS_<FLAG>) it exists under, all of them; none: always."""

    name: str
    ctype: str
    access: str = "in"
    when: tuple = ()

    @property
    def buffer(self) -> bool:
        return self.ctype.endswith("*")

    @property
    def dtype(self):
        """The numpy type name of a scalar parameter; None for a buffer."""
        return None if self.buffer else SCALAR_DTYPES[self.ctype]

    def c_declaration(self) -> str:
        if not self.buffer:
            return f"{self.ctype} {self.name}"
        space = {"in": "__global const", "out": "__global", "atomic": "volatile __global"}
        return f"{space[self.access]} {self.ctype[:-1]} *{self.name}"


@dataclass(frozen=True)
class KernelParams:
    """The parameters of kernel `kernel`, in order (C: KERNEL_PARAMS, the list)."""

    kernel: str
    title: str
    params: tuple

    @property
    def macro(self) -> str:
        return f"{self.kernel.upper()}_PARAMS"

    def present(self, flags) -> tuple:
        """The parameters of a program built with these features (HAS_<FLAG> names), in order."""
        flags = set(flags)
        return tuple(p for p in self.params if flags.issuperset(p.when))


# The kd-tree a ray query traverses (KdTree, kernels/trace/trace.cl make_kdtree).
TREE_PARAMS = (Param("nodes", "uint2*"), Param("leaf_index32", "uint*"),
               Param("leaf_index16", "ushort*"), Param("leaf_shift", "uint"),
               Param("tri_verts", "float4*"), Param("bounds", "float4*"))
# An instanced scene's top level (TopLevel, trace.cl TOPLEVEL_MAKE; slave/buffers.py
# pack_instances), and with object motion the rays' moment in the shutter.
TOPLEVEL_PARAMS = (Param("toplevel", "float4*", when=("INSTANCES",)),
                   Param("instances", "float4*", when=("INSTANCES",)),
                   Param("meshes", "uint*", when=("INSTANCES",)),
                   Param("mesh_bounds", "float4*", when=("INSTANCES",)),
                   Param("shutter_time", "float", when=("INSTANCES", "OBJECT_MOTION")))
RAY_PARAMS = (Param("origins", "float*"), Param("directions", "float*"), Param("tmin", "float"),
              Param("tmax", "float"), Param("ray_count", "uint"))

INTERSECT_RAYS = KernelParams("intersect_rays", "Nearest hits (kernels/trace/intersect.cl)",
                              RAY_PARAMS + TREE_PARAMS + TOPLEVEL_PARAMS + (
    Param("out_t", "float*", "out"), Param("out_tri", "int*", "out"),
    Param("out_u", "float*", "out"), Param("out_v", "float*", "out")))
OCCLUDED_RAYS = KernelParams("occluded_rays", "Any hits (kernels/trace/intersect.cl)",
                             RAY_PARAMS + TREE_PARAMS + TOPLEVEL_PARAMS + (
    Param("out_hit", "uchar*", "out"),))
RENDER_SAMPLES = KernelParams("render_samples", "Camera samples of a tile's pixels "
                              "(kernels/shade/render.cl)", (
    Param("cam", "float4*"),                    # one CAMERA record
    Param("x0", "int"), Param("y0", "int"), Param("tile_w", "int"),
    Param("pixels", "int*"), Param("pixel_count", "int"),
    Param("next_pixel", "int*", "atomic"),      # RENDER_PIXEL_QUEUE's counter
    Param("sample_start", "int"), Param("sample_count", "int"), Param("jitter", "int"),
    # RenderSettings' Light Paths and clamping (PathLimits)
    Param("max_bounces", "int"), Param("diffuse_bounces", "int"), Param("glossy_bounces", "int"),
    Param("transmission_bounces", "int"), Param("transparent_bounces", "int"),
    Param("clamp_direct", "float"), Param("clamp_indirect", "float"),
    Param("filter_glossy", "float"),
    Param("light_n", "int"), Param("seed", "uint"), Param("write_aux", "int"),
    *TREE_PARAMS, *TOPLEVEL_PARAMS,
    Param("material_ids", "ushort*"), Param("materials", "float4*"), Param("lights", "float4*"),
    Param("light_count", "uint"), Param("normals", "float*"), Param("uvs", "float*"),
    Param("texels", "half*"), Param("texture_sizes", "uint*"),
    Param("world", "float4*"), Param("env_cdf", "float*"), Param("emitters", "float4*"),
    Param("emitter_count", "uint"), Param("emitter_power", "float"),
    Param("accum", "float4*", "out"),
    Param("out_depth", "float*", "out"), Param("out_normal", "float*", "out"),
    Param("film", "float4*", "out", when=("FILM",))))
KERNEL_PARAMS = (INTERSECT_RAYS, OCCLUDED_RAYS, RENDER_SAMPLES)


# ---------------------------------------------------------------------------------------------
# The C header

def _c_int(value: int) -> str:
    return f"0x{value:X}u" if value > 0xFF else f"{value}u"


def _comment(text: str) -> str:
    return f"// {text}"


def _bit_field_lines(f: BitField) -> list:
    bits = f"bit {f.shift}" if f.bits == 1 else f"bits {f.shift}-{f.shift + f.bits - 1}"
    lines = [_comment(f"{f.name}: word 0 {bits}: {f.doc}"),
             f"#define {f.name}_SHIFT {f.shift}",
             f"#define {f.name}_BITS {f.bits}",
             f"#define {f.name}_MAX {_c_int(f.max)}",
             f"#define {f.name}(w) (((w) >> {f.name}_SHIFT) & {f.name}_MAX)",
             f"#define {f.name}_PUT(v) ((uint)(v) << {f.name}_SHIFT)"]
    if f.bits == 1:
        lines.append(f"#define {f.name}_BIT {_c_int(f.bit)}")
    return lines


def _record_lines(r: Record) -> list:
    vector = f"float{r.width}"
    lines = [_comment(f"{r.title}: {r.size} {vector} each"),
             f"#define {r.prefix}_SIZE {r.size}"]
    for s in r.slots:
        name = f"{r.prefix}_{s.name.upper()}"
        if s.rows > 1:
            where, value = f"[{s.index}..{s.index + s.rows - 1}]", f"((r) + {name}_SLOT)"
        else:
            where, value = f"[{s.index}].{s.lanes}", f"((r)[{name}_SLOT].{s.lanes})"
        lines += [_comment(f"  {where} {s.doc}"),
                  f"#define {name}_SLOT {s.index}",
                  f"#define {name}(r) {value}"]
    return lines


def _when_macro(when: tuple) -> str:
    return "KD_PARAMS_IF_" + "_".join(when)


def _kernel_params_lines() -> list:
    """KERNEL_PARAMS as C: a list macro per kernel; parameters that exist only under some
    features are wrapped in KD_PARAMS_IF_<FLAGS>(...), which keeps or drops them."""
    lines = ["", _comment("Kernel parameters (KERNEL_PARAMS): declare a kernel as "
                          "`__kernel void name(NAME_PARAMS)`")]
    for when in sorted({p.when for k in KERNEL_PARAMS for p in k.params if p.when}):
        test = " && ".join(f"defined(HAS_{flag})" for flag in when)
        lines += [f"#if {test}", f"#define {_when_macro(when)}(...) __VA_ARGS__", "#else",
                  f"#define {_when_macro(when)}(...)", "#endif"]
    for k in KERNEL_PARAMS:
        assert not k.params[0].when, f"{k.kernel}: the first parameter must always be there"
        groups = []             # runs of parameters under the same features
        for p in k.params:
            if groups and groups[-1][0] == p.when:
                groups[-1][1].append(p)
            else:
                groups.append((p.when, [p]))
        parts = []              # a line a parameter, a line a run under features
        for when, params in groups:
            if when:
                declarations = ", ".join(p.c_declaration() for p in params)
                parts.append(f"{_when_macro(when)}(, {declarations})")
            else:
                for p in params:
                    parts.append(f", {p.c_declaration()}" if parts else p.c_declaration())
        lines += ["", _comment(f"{k.kernel}: {k.title}"), f"#define {k.macro} \\"]
        lines += [f"    {part} \\" for part in parts[:-1]] + [f"    {parts[-1]}"]
    return lines


@functools.lru_cache(maxsize=None)
def c_header() -> str:
    """The tables as C: #defines only, valid OpenCL C 1.2 (core/opencl.py kernel_source puts
    it in front of every kernel source)."""
    lines = ["// Generated by core/layout.py c_header(): the host/kernel layouts. Do not edit;",
             "// change the tables there.", "#ifndef KDTRACE_LAYOUT", "#define KDTRACE_LAYOUT"]
    for node in NODE_FORMATS:
        lines += ["", _comment(node.title)] + [_comment(f"  {w}") for w in node.words]
        for c in node.constants:
            lines += [_comment(c.doc), f"#define {c.name} {_c_int(c.value)}"]
        for f in node.fields:
            lines += _bit_field_lines(f)
    for codes in CODES:
        lines += ["", _comment(codes.title)]
        lines += [f"#define {codes.prefix}_{name} {value}" for name, value in codes.codes.items()]
    for record in RECORDS:
        lines += [""] + _record_lines(record)
    for table in COLUMNS:
        lines += ["", _comment(f"{table.title}: {len(table.columns)} columns"),
                  f"#define {table.prefix}_COLUMNS {len(table.columns)}"]
        lines += [f"#define {table.prefix}_{name.upper()} {i}"
                  for i, name in enumerate(table.columns)]
        if table.vector:
            lines += [_comment(f"  read as a {table.vector}: {table.prefix}_<NAME>_OF(v) is that "
                               "column's lane")]
            lines += [f"#define {table.prefix}_{name.upper()}_OF(v) ((v).s{i:X})"
                      for i, name in enumerate(table.columns)]
    for element in ELEMENTS:
        lines += ["", _comment(f"{element.title}: {element.ctype}"),
                  f"#define {element.prefix}_BYTES {element.nbytes}"]
    lines += _kernel_params_lines()
    lines += ["", "#endif", ""]
    return "\n".join(lines)
