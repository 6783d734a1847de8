// Shader node programs (core/layout.py NODE_OP_CODES; compiled by addon/node_program.py): a few
// registers, one instruction per node, then OUT instructions that set the BSDF inputs.
// run_nodes interprets a program; the nodes it calls are above it (the Noise Texture in
// noise.cl, Image Texture lookups in textures.cl).

#ifdef HAS_NODES
// An operand: register ref / NODE_REF_REGISTER, one lane or (lane 4) the whole register. A
// CONST's operand words hold its value, not a reference: clamped, no value reads outside regs.
inline float4 node_operand(const float4 *regs, float ref)
{
    int r = (int)clamp(ref, 0.0f, (float)(NODE_REGISTERS * NODE_REF_REGISTER - 1));
    int lane = r % NODE_REF_REGISTER;
    float4 v = regs[r / NODE_REF_REGISTER];
    return lane == 0 ? v.xxxx : lane == 1 ? v.yyyy : lane == 2 ? v.zzzz : lane == 3 ? v.wwww : v;
}

inline float4 node_mix(int mode, float t, float4 a, float4 b)
{
    float4 c = b;
    if (mode == NODE_MIX_ADD)
        c = a + b;
    else if (mode == NODE_MIX_MULTIPLY)
        c = a * b;
    else if (mode == NODE_MIX_SUBTRACT)
        c = a - b;
    else if (mode == NODE_MIX_SCREEN)
        return 1.0f - ((1.0f - t) + t * (1.0f - b)) * (1.0f - a);
    else if (mode == NODE_MIX_DIFFERENCE)
        c = fabs(a - b);
    else if (mode == NODE_MIX_DARKEN)
        c = fmin(a, b);
    else if (mode == NODE_MIX_LIGHTEN)
        c = fmax(a, b);
    return (1.0f - t) * a + t * c;
}

// Cycles' wrapf and pingpongf (util/math_float.h).
inline float node_wrap(float value, float max_value, float min_value)
{
    float range = max_value - min_value;
    return range != 0.0f ? value - range * floor((value - min_value) / range) : min_value;
}

inline float node_pingpong(float a, float b)
{
    if (b == 0.0f)
        return 0.0f;
    float x = (a - b) / (b * 2.0f);
    return fabs((x - floor(x)) * b * 2.0f - b);
}

inline float node_smooth_min(float a, float b, float k)
{
    if (k == 0.0f)
        return fmin(a, b);
    float h = fmax(k - fabs(a - b), 0.0f) / k;
    return fmin(a, b) - h * h * h * k * (1.0f / 6.0f);
}

// Cycles' math node (svm_math), with its safe division, power, logarithm, square roots,
// modulo and inverse trigonometry.
inline float node_math(int op, float a, float b, float c)
{
    switch (op) {
    case NODE_MATH_ADD: return a + b;
    case NODE_MATH_SUBTRACT: return a - b;
    case NODE_MATH_MULTIPLY: return a * b;
    case NODE_MATH_DIVIDE: return b != 0.0f ? a / b : 0.0f;
    case NODE_MATH_MULTIPLY_ADD: return a * b + c;
    case NODE_MATH_POWER:
        if (a < 0.0f && b != floor(b))
            return 0.0f;
        return a < 0.0f ? ((int)b % 2 ? -1.0f : 1.0f) * pow(-a, b) : pow(a, b);
    case NODE_MATH_MINIMUM: return fmin(a, b);
    case NODE_MATH_MAXIMUM: return fmax(a, b);
    case NODE_MATH_LESS_THAN: return a < b ? 1.0f : 0.0f;
    case NODE_MATH_GREATER_THAN: return a > b ? 1.0f : 0.0f;
    case NODE_MATH_ABSOLUTE: return fabs(a);
    case NODE_MATH_SQRT: return sqrt(fmax(a, 0.0f));
    case NODE_MATH_INVERSE_SQRT: return a > 0.0f ? 1.0f / sqrt(a) : 0.0f;
    case NODE_MATH_LOGARITHM:
        if (a <= 0.0f || b <= 0.0f)
            return 0.0f;
        return log(b) != 0.0f ? log(a) / log(b) : 0.0f;
    case NODE_MATH_EXPONENT: return exp(a);
    case NODE_MATH_RADIANS: return a * (M_PI_F / 180.0f);
    case NODE_MATH_DEGREES: return a * (180.0f / M_PI_F);
    case NODE_MATH_SIGN: return a > 0.0f ? 1.0f : a < 0.0f ? -1.0f : 0.0f;
    case NODE_MATH_COMPARE: return a == b || fabs(a - b) <= fmax(c, FLT_EPSILON) ? 1.0f : 0.0f;
    case NODE_MATH_SMOOTH_MIN: return node_smooth_min(a, b, c);
    case NODE_MATH_SMOOTH_MAX: return -node_smooth_min(-a, -b, c);
    case NODE_MATH_ROUND: return floor(a + 0.5f);
    case NODE_MATH_FLOOR: return floor(a);
    case NODE_MATH_CEIL: return ceil(a);
    case NODE_MATH_TRUNC: return a >= 0.0f ? floor(a) : ceil(a);
    case NODE_MATH_FRACT: return a - floor(a);
    case NODE_MATH_MODULO: return b != 0.0f ? fmod(a, b) : 0.0f;
    case NODE_MATH_FLOORED_MODULO: return b != 0.0f ? a - floor(a / b) * b : 0.0f;
    case NODE_MATH_WRAP: return node_wrap(a, b, c);
    case NODE_MATH_SNAP: return b != 0.0f ? floor(a / b) * b : 0.0f;
    case NODE_MATH_PINGPONG: return node_pingpong(a, b);
    case NODE_MATH_SINE: return sin(a);
    case NODE_MATH_COSINE: return cos(a);
    case NODE_MATH_TANGENT: return tan(a);
    case NODE_MATH_SINH: return sinh(a);
    case NODE_MATH_COSH: return cosh(a);
    case NODE_MATH_TANH: return tanh(a);
    case NODE_MATH_ARCSINE: return a <= -1.0f ? -M_PI_2_F : a >= 1.0f ? M_PI_2_F : asin(a);
    case NODE_MATH_ARCCOSINE: return a >= 1.0f ? 0.0f : a <= -1.0f ? M_PI_F : acos(a);
    case NODE_MATH_ARCTANGENT: return atan(a);
    case NODE_MATH_ARCTAN2: return atan2(a, b);
    }
    return 0.0f;
}

// Cycles' checker: 1 where the parities of the cells' x, y and z say so.
inline float node_checker(float4 p)
{
    p = (p + 0.000001f) * 0.999999f;
    int x = abs((int)floor(p.x)), y = abs((int)floor(p.y)), z = abs((int)floor(p.z));
    return ((x % 2 == y % 2) == (z % 2)) ? 1.0f : 0.0f;
}

inline float3 node_safe_normalize(float3 v)
{
    float l = kd_length(v);
    return l != 0.0f ? v / l : (float3)(0.0f, 0.0f, 0.0f);
}

// Cycles' Vector Math (svm_vector_math): the vector in xyz, the value output (Dot Product,
// Length, Distance) in w. c: the third vector (Multiply Add, Face Forward, Wrap) or in c.x
// the Scale (Scale, Refract's IOR).
inline float4 node_vector_math(int op, float4 a, float4 b, float4 c)
{
    float3 x = a.xyz, y = b.xyz, z = c.xyz, r = (float3)(0.0f, 0.0f, 0.0f);
    float s = c.x, value = 0.0f;
    if (op == NODE_VECTOR_MATH_ADD) r = x + y;
    else if (op == NODE_VECTOR_MATH_SUBTRACT) r = x - y;
    else if (op == NODE_VECTOR_MATH_MULTIPLY) r = x * y;
    else if (op == NODE_VECTOR_MATH_DIVIDE)
        r = (float3)(y.x != 0.0f ? x.x / y.x : 0.0f, y.y != 0.0f ? x.y / y.y : 0.0f,
                     y.z != 0.0f ? x.z / y.z : 0.0f);
    else if (op == NODE_VECTOR_MATH_SCALE) r = x * s;
    else if (op == NODE_VECTOR_MATH_DOT_PRODUCT) value = kd_dot(x, y);
    else if (op == NODE_VECTOR_MATH_CROSS_PRODUCT) r = kd_cross(x, y);
    else if (op == NODE_VECTOR_MATH_LENGTH) value = kd_length(x);
    else if (op == NODE_VECTOR_MATH_NORMALIZE) r = node_safe_normalize(x);
    else if (op == NODE_VECTOR_MATH_ABSOLUTE) r = fabs(x);
    else if (op == NODE_VECTOR_MATH_MINIMUM) r = fmin(x, y);
    else if (op == NODE_VECTOR_MATH_MAXIMUM) r = fmax(x, y);
    else if (op == NODE_VECTOR_MATH_MULTIPLY_ADD) r = x * y + z;
    else if (op == NODE_VECTOR_MATH_DISTANCE) value = kd_length(x - y);
    else if (op == NODE_VECTOR_MATH_PROJECT) {
        float length_squared = kd_dot(y, y);
        r = length_squared != 0.0f ? (kd_dot(x, y) / length_squared) * y : r;
    }
    else if (op == NODE_VECTOR_MATH_REFLECT) {
        float3 n = node_safe_normalize(y);
        r = x - 2.0f * kd_dot(n, x) * n;
    }
    else if (op == NODE_VECTOR_MATH_REFRACT) {
        float3 n = node_safe_normalize(y);
        float cosine = kd_dot(n, x), k = 1.0f - s * s * (1.0f - cosine * cosine);
        r = k < 0.0f ? r : s * x - (s * cosine + sqrt(k)) * n;
    }
    else if (op == NODE_VECTOR_MATH_FACEFORWARD) r = kd_dot(z, y) < 0.0f ? x : -x;
    else if (op == NODE_VECTOR_MATH_SNAP)
        r = (float3)(y.x != 0.0f ? floor(x.x / y.x) * y.x : 0.0f,
                     y.y != 0.0f ? floor(x.y / y.y) * y.y : 0.0f,
                     y.z != 0.0f ? floor(x.z / y.z) * y.z : 0.0f);
    else if (op == NODE_VECTOR_MATH_FLOOR) r = floor(x);
    else if (op == NODE_VECTOR_MATH_CEIL) r = ceil(x);
    else if (op == NODE_VECTOR_MATH_MODULO)
        r = (float3)(y.x != 0.0f ? fmod(x.x, y.x) : 0.0f, y.y != 0.0f ? fmod(x.y, y.y) : 0.0f,
                     y.z != 0.0f ? fmod(x.z, y.z) : 0.0f);
    else if (op == NODE_VECTOR_MATH_FRACTION) r = x - floor(x);
    else if (op == NODE_VECTOR_MATH_WRAP)
        r = (float3)(node_wrap(x.x, y.x, z.x), node_wrap(x.y, y.y, z.y), node_wrap(x.z, y.z, z.z));
    else if (op == NODE_VECTOR_MATH_SINE) r = sin(x);
    else if (op == NODE_VECTOR_MATH_COSINE) r = cos(x);
    else if (op == NODE_VECTOR_MATH_TANGENT) r = tan(x);
    else if (op == NODE_VECTOR_MATH_POWER)
        r = (float3)(node_math(NODE_MATH_POWER, x.x, y.x, 0.0f),
                     node_math(NODE_MATH_POWER, x.y, y.y, 0.0f),
                     node_math(NODE_MATH_POWER, x.z, y.z, 0.0f));
    else if (op == NODE_VECTOR_MATH_SIGN)
        r = (float3)(node_math(NODE_MATH_SIGN, x.x, 0.0f, 0.0f),
                     node_math(NODE_MATH_SIGN, x.y, 0.0f, 0.0f),
                     node_math(NODE_MATH_SIGN, x.z, 0.0f, 0.0f));
    return (float4)(r, value);
}

// Cycles' rgb_to_hsv and hsv_to_rgb.
inline float3 rgb_to_hsv(float3 c)
{
    float cmax = fmax(c.x, fmax(c.y, c.z)), cmin = fmin(c.x, fmin(c.y, c.z));
    float delta = cmax - cmin, h = 0.0f, s = cmax != 0.0f ? delta / cmax : 0.0f;
    if (s != 0.0f) {
        float3 d = ((float3)(cmax, cmax, cmax) - c) / delta;
        h = c.x == cmax ? d.z - d.y : c.y == cmax ? 2.0f + d.x - d.z : 4.0f + d.y - d.x;
        h *= 1.0f / 6.0f;
        if (h < 0.0f)
            h += 1.0f;
    }
    return (float3)(h, s, cmax);
}

inline float3 hsv_to_rgb(float3 hsv)
{
    float h = hsv.x, s = hsv.y, v = hsv.z;
    if (s == 0.0f)
        return (float3)(v, v, v);
    if (h == 1.0f)
        h = 0.0f;
    h *= 6.0f;
    float i = floor(h), f = h - i;
    float p = v * (1.0f - s), q = v * (1.0f - s * f), t = v * (1.0f - s * (1.0f - f));
    if (i == 0.0f) return (float3)(v, t, p);
    if (i == 1.0f) return (float3)(q, v, p);
    if (i == 2.0f) return (float3)(p, v, t);
    if (i == 3.0f) return (float3)(p, q, v);
    if (i == 4.0f) return (float3)(t, p, v);
    return (float3)(v, p, q);
}

// Cycles' gradient texture value at p.
inline float node_gradient(int kind, float4 p)
{
    float r;
    if (kind == NODE_GRADIENT_QUADRATIC) {
        r = fmax(p.x, 0.0f);
        r = r * r;
    } else if (kind == NODE_GRADIENT_EASING) {
        r = fmin(fmax(p.x, 0.0f), 1.0f);
        float t = r * r;
        r = 3.0f * t - 2.0f * t * r;
    } else if (kind == NODE_GRADIENT_DIAGONAL) {
        r = (p.x + p.y) * 0.5f;
    } else if (kind == NODE_GRADIENT_RADIAL) {
        r = atan2_poly(p.y, p.x) * (0.5f * M_1_PI_F) + 0.5f;
    } else if (kind == NODE_GRADIENT_QUADRATIC_SPHERE || kind == NODE_GRADIENT_SPHERICAL) {
        r = fmax(0.999999f - sqrt(p.x * p.x + p.y * p.y + p.z * p.z), 0.0f);
        if (kind == NODE_GRADIENT_QUADRATIC_SPHERE)
            r = r * r;
    } else {
        r = p.x;
    }
    return clamp(r, 0.0f, 1.0f);
}

#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
inline float3 safe_normalize(float3 n)
{
    float len = kd_length(n);
    return len > 0.0f && isfinite(len) ? n / len : (float3)(0.0f, 0.0f, 0.0f);
}

// The triangle's first corner, its edges from it, and its UVs there and along the edges.
inline void triangle_edges_uv(const Scene *sc, uint tri, float3 *p0, float3 *e1, float3 *e2,
                             float2 *uv0, float2 *duv1, float2 *duv2)
{
    __global const float4 *T = sc->tri_verts + TRIANGLE_SIZE * tri;
    *p0 = TRIANGLE_V0(T);
    *e1 = TRIANGLE_V1(T) - *p0;
    *e2 = TRIANGLE_V2(T) - *p0;
    *uv0 = vload2(3 * tri, sc->uvs);
    *duv1 = vload2(3 * tri + 1, sc->uvs) - *uv0;
    *duv2 = vload2(3 * tri + 2, sc->uvs) - *uv0;
}
#endif

#ifdef HAS_NORMAL_MAP
// Cycles' Normal Map node (svm_node_normal_map). Tangent space: the UV map's tangent, here the
// triangle's dP/du made orthogonal to the normal (MikkTSpace's tangent where the UVs are
// affine over the faces around a vertex), the bitangent's sign from dP/dv, and the smooth
// normal unnormalised (the geometric one on flat faces); object space: through the object's
// normal matrix (the transpose of its world -> object rows). Then flipped on back faces and
// blended toward the shading normal by Strength.
inline float3 node_normal_map(const Scene *sc, const Surface *s, __global const float4 *rows,
                              int space, float3 colour, float strength)
{
    float3 c = 2.0f * (colour - 0.5f);
    float3 n;
    if (space == NODE_NORMAL_SPACE_TANGENT) {
        float3 p0, e1, e2;
        float2 uv0, duv1, duv2;
        triangle_edges_uv(sc, s->tri, &p0, &e1, &e2, &uv0, &duv1, &duv2);
        float3 normal = kd_normalize(kd_cross(e1, e2));
#ifdef HAS_SMOOTH
        float b0 = 1.0f - s->u - s->v;
        normal = b0 * vload3(3 * s->tri, sc->normals) + s->u * vload3(3 * s->tri + 1, sc->normals)
                 + s->v * vload3(3 * s->tri + 2, sc->normals);
#endif
        float det = duv1.x * duv2.y - duv2.x * duv1.y;
        if (det == 0.0f)
            return s->ns;                   // no UVs here: Cycles' unperturbed normal
        float3 dpdu = (e1 * duv2.y - e2 * duv1.y) / det, dpdv = (e2 * duv1.x - e1 * duv2.x) / det;
        float3 unit = safe_normalize(normal);
        float3 tangent = safe_normalize(dpdu - kd_dot(dpdu, unit) * unit);
        float sign = kd_dot(kd_cross(normal, tangent), dpdv) < 0.0f ? -1.0f : 1.0f;
        n = safe_normalize(c.x * tangent + c.y * sign * kd_cross(normal, tangent) + c.z * normal);
    } else {
        if (space == NODE_NORMAL_SPACE_BLENDER_OBJECT || space == NODE_NORMAL_SPACE_BLENDER_WORLD)
            c.yz = -c.yz;                   // Blender's convention
        if (space == NODE_NORMAL_SPACE_OBJECT || space == NODE_NORMAL_SPACE_BLENDER_OBJECT)
            c = c.x * rows[0].xyz + c.y * rows[1].xyz + c.z * rows[2].xyz;
        n = safe_normalize(c);
    }
    if (!s->front)
        n = -n;
    if (strength != 1.0f)
        n = safe_normalize(s->ns + (n - s->ns) * fmax(strength, 0.0f));
    return all(n == 0.0f) ? s->ns : n;
}
#endif

#ifdef HAS_BUMP
// Where a Bump node's height is evaluated: the hit (0) and two points a small step along the
// surface from it (1, 2; Cycles steps along the ray differentials, which for a height that
// is smooth at the scale of a pixel gives the same gradient), and the UVs there.
inline void bump_offsets(const Scene *sc, uint tri, float3 p, float3 *dp, float2 *duv)
{
    float3 p0, e1, e2;
    float2 uv0, duv1, duv2;
    triangle_edges_uv(sc, tri, &p0, &e1, &e2, &uv0, &duv1, &duv2);
    float3 n = safe_normalize(kd_cross(e1, e2)), t, b;
    basis(all(n == 0.0f) ? (float3)(0.0f, 0.0f, 1.0f) : n, &t, &b);
    float step = 1e-4f * (1.0f + fmax(fabs(p.x), fmax(fabs(p.y), fabs(p.z))));
    dp[0] = (float3)(0.0f, 0.0f, 0.0f);
    dp[1] = step * t;
    dp[2] = step * b;
    // The barycentric steps of dp (least squares in the triangle's plane) move the UVs.
    float a11 = kd_dot(e1, e1), a12 = kd_dot(e1, e2), a22 = kd_dot(e2, e2);
    float det = a11 * a22 - a12 * a12;
    for (int k = 0; k < 3; ++k) {
        float r1 = kd_dot(e1, dp[k]), r2 = kd_dot(e2, dp[k]);
        float s1 = det != 0.0f ? (a22 * r1 - a12 * r2) / det : 0.0f;
        float s2 = det != 0.0f ? (a11 * r2 - a12 * r1) / det : 0.0f;
        duv[k] = s1 * duv1 + s2 * duv2;
    }
}

// Cycles' Bump node (svm_node_set_bump): the surface gradient of the height from its values
// at the hit and at the two steps, the normal tilted against it by Distance (negative:
// inverted), blended with the input normal by Strength.
inline float3 node_bump(float3 dpx, float3 dpy, float3 normal_in, float4 heights,
                        float strength, float distance)
{
    float3 rx = kd_cross(dpy, normal_in), ry = kd_cross(normal_in, dpx);
    float det = kd_dot(dpx, rx);
    float3 gradient = (heights.y - heights.x) * rx + (heights.z - heights.x) * ry;
    float3 n = safe_normalize(fabs(det) * normal_in - distance * sign(det) * gradient);
    if (all(n == 0.0f))
        return normal_in;
    strength = fmax(strength, 0.0f);
    return kd_normalize(strength * n + (1.0f - strength) * normal_in);
}
#endif

#ifdef HAS_TEXTURES
// A Color Attribute / Attribute: the values at triangle tri's corners (texels 3 tri + k of
// texture `tex`, the exporter's corner array laid out in rows) blended by the barycentrics.
inline float4 corner_attribute(const Scene *sc, int tex, uint tri, float2 bary)
{
    __global const uint *size = sc->tex_sizes + TEXTURE_SIZE_COLUMNS * tex;
    uint offset = size[TEXTURE_SIZE_OFFSET];
    int w = max((int)size[TEXTURE_SIZE_WIDTH], 1), h = (int)size[TEXTURE_SIZE_HEIGHT];
    float4 c[3];
    for (int k = 0; k < 3; ++k) {
        uint i = 3u * tri + (uint)k;
        c[k] = texel(sc, offset, w, h, (int)(i % (uint)w), (int)(i / (uint)w));
    }
    return (1.0f - bary.x - bary.y) * c[0] + bary.x * c[1] + bary.y * c[2];
}
#endif

#ifdef HAS_LIGHT_PATH
// Cycles' Light Path node (svm_node_light_path): the ray's kind, length and depths.
inline float node_light_path(int what, const ShadeInfo *info)
{
    uint bit = what == NODE_LIGHT_PATH_IS_CAMERA_RAY ? PATH_CAMERA
             : what == NODE_LIGHT_PATH_IS_SHADOW_RAY ? PATH_SHADOW
             : what == NODE_LIGHT_PATH_IS_DIFFUSE_RAY ? PATH_DIFFUSE
             : what == NODE_LIGHT_PATH_IS_GLOSSY_RAY ? PATH_GLOSSY
             : what == NODE_LIGHT_PATH_IS_SINGULAR_RAY ? PATH_SINGULAR
             : what == NODE_LIGHT_PATH_IS_REFLECTION_RAY ? PATH_REFLECT
             : what == NODE_LIGHT_PATH_IS_TRANSMISSION_RAY ? PATH_TRANSMIT : 0u;
    if (bit)
        return (info->path & bit) ? 1.0f : 0.0f;
    if (what == NODE_LIGHT_PATH_RAY_LENGTH)
        return info->length;
    if (what == NODE_LIGHT_PATH_RAY_DEPTH)     // a shadow ray or light sample: one bounce further
        return (float)(info->bounce + ((info->path & PATH_SHADOW) || !info->path ? 1 : 0));
    return (float)(what == NODE_LIGHT_PATH_DIFFUSE_DEPTH ? info->diffuse
                 : what == NODE_LIGHT_PATH_GLOSSY_DEPTH ? info->glossy
                 : what == NODE_LIGHT_PATH_TRANSPARENT_DEPTH ? info->transparent
                 : what == NODE_LIGHT_PATH_TRANSMISSION_DEPTH ? info->transmission : 0);
}
#endif

// Cycles' fresnel_dielectric_cos (the Fresnel and Layer Weight nodes' reflectance).
inline float fresnel_dielectric_cos(float cosi, float eta)
{
    float c = fabs(cosi);
    float g = eta * eta - 1.0f + c * c;
    if (g > 0.0f) {
        g = sqrt(g);
        float A = (g - c) / (g + c);
        float B = (c * (g + c) - 1.0f) / (c * (g - c) + 1.0f);
        return 0.5f * A * A * (1.0f + B * B);
    }
    return 1.0f;
}

// Cycles' Fresnel node (svm_node_fresnel) and Layer Weight node (svm_node_layer_weight):
// `kind` -1 Fresnel of IOR `value`, else a NODE_LAYER_WEIGHT_<OUTPUT> of Blend `value`.
inline float node_fresnel(int kind, float value, float3 normal, const ShadeInfo *info)
{
    float3 wi = info ? info->incoming : (float3)(0.0f, 0.0f, 1.0f);
    bool back = info ? info->backfacing : false;
    float cos_i = kd_dot(wi, normal);
    if (kind < 0) {
        float eta = fmax(value, 1e-5f);
        return fresnel_dielectric_cos(cos_i, back ? 1.0f / eta : eta);
    }
    if (kind == NODE_LAYER_WEIGHT_FRESNEL) {
        float eta = fmax(1.0f - value, 1e-5f);
        return fresnel_dielectric_cos(cos_i, back ? eta : 1.0f / eta);
    }
    float f = fabs(cos_i);
    if (value != 0.5f) {
        float blend = clamp(value, 0.0f, 1.0f - 1e-5f);
        blend = blend < 0.5f ? 2.0f * blend : 0.5f / (1.0f - blend);
        f = pow(f, blend);
    }
    return 1.0f - f;
}

// Runs the program at row `at` of the materials buffer for the hit on triangle `tri` (bary:
// its barycentrics u, v; uv: its texture coordinates, p: its position; s: the surface point, or 0 where the shading normal
// does not matter; info: the ray's view of the hit, or 0) and sets the BSDF inputs it
// computes; a Normal output sets s->ns.
inline void run_nodes(const Scene *sc, int at, uint tri, float2 bary, float2 uv, float3 p,
                      Surface *s, const ShadeInfo *info, Material *m)
{
    float4 regs[NODE_REGISTERS];
    __global const float4 *code = sc->materials + at;
    for (int k = 0; k < NODE_REGISTERS; ++k)
        regs[k] = (float4)(0.0f, 0.0f, 0.0f, 0.0f);
#ifdef HAS_BUMP
    float3 dp[3];                       // UV and TRANSFORM p1 (bump step 0, 1, 2) move the hit
    float2 duv[3];
    bump_offsets(sc, tri, p, dp, duv);
#endif
    for (int pc = 0; pc < 2 * 1024; pc += 2) {
        float4 w0 = code[pc], w1 = code[pc + 1];
        int op = (int)w0.x, dst = clamp((int)w0.y, 0, NODE_REGISTERS - 1);
        if (op == NODE_OP_END)
            break;
        float4 a = node_operand(regs, w0.z), b = node_operand(regs, w0.w);
        float4 c = node_operand(regs, w1.x);
        float4 out = w1;
        if (op == NODE_OP_UV) {
            out = (float4)(uv, 0.0f, 0.0f);
#ifdef HAS_BUMP
            out.xy += duv[clamp((int)w1.y, 0, 2)];
#endif
        }
#ifdef HAS_TEXTURES
        else if (op == NODE_OP_IMAGE) {
            out = texture_lookup_ext(sc, (int)w1.y, a.xy, w1.z > 0.0f, (int)w1.w);
        }
#endif
        else if (op == NODE_OP_COMBINE) {
            out = (float4)(a.x, b.x, c.x, 1.0f);
        } else if (op == NODE_OP_MIX) {
            out = node_mix((int)w1.y, clamp(a.x, 0.0f, 1.0f), b, c);
            if (w1.z > 0.0f)
                out = clamp(out, 0.0f, 1.0f);
        } else if (op == NODE_OP_MATH) {
            float r = node_math((int)w1.y, a.x, b.x, c.x);
            out = (float4)(w1.z > 0.0f ? clamp(r, 0.0f, 1.0f) : r);
        } else if (op == NODE_OP_INVERT) {
            float t = a.x;
            out = (float4)((1.0f - t) * b.xyz + t * (1.0f - b.xyz), b.w);
        } else if (op == NODE_OP_CHECKER) {
            float f = node_checker(a * w1.y);
            out = f == 1.0f ? b : c;
            out.w = f;
        } else if (op == NODE_OP_RAMP) {
            // Cycles' ramp table lookup: linear between its rows unless constant.
            float f = clamp(a.x, 0.0f, 1.0f) * (float)(NODE_RAMP_SIZE - 1);
            int i = clamp((int)f, 0, NODE_RAMP_SIZE - 1);
            float t = f - (float)i;
            __global const float4 *table = code + pc + (int)w1.y;   // after the END
            out = table[i];
            if (w1.z > 0.0f && t > 0.0f)
                out = (1.0f - t) * out + t * table[i + 1];
        } else if (op == NODE_OP_MAP_RANGE) {  // a: value; b: from min, from max, to min; c: to max
            float span = b.y - b.x;
            float f = span != 0.0f ? (a.x - b.x) / span : 0.0f;
            float r = b.z + f * (c.x - b.z);
            if (w1.z > 0.0f)
                r = clamp(r, fmin(b.z, c.x), fmax(b.z, c.x));
            out = (float4)(r);
        } else if (op == NODE_OP_VECTOR_MATH) {   // c: the third vector, or the Scale
            out = node_vector_math((int)w1.y, a, b, c);
        } else if (op == NODE_OP_HSV) {        // a: fac; b: colour; c: hue, saturation, value
            float3 hsv = rgb_to_hsv(b.xyz);
            hsv.x = hsv.x + c.x + 0.5f;
            hsv.x -= floor(hsv.x);
            hsv.y = clamp(hsv.y * c.y, 0.0f, 1.0f);
            hsv.z *= c.z;
            float3 rgb = a.x * hsv_to_rgb(hsv) + (1.0f - a.x) * b.xyz;
            out = (float4)(fmax(rgb, 0.0f), b.w);
        } else if (op == NODE_OP_GRADIENT) {
            float f = node_gradient((int)w1.y, a);
            out = (float4)(f, f, f, f);
#ifdef HAS_NOISE
        } else if (op == NODE_OP_NOISE) {  // a: vector; b: detail, roughness, lacunarity; c: scale, offset, gain
            // p0: normalize + 2 colour + 4 dimensions + 32 type; p1: distortion; p2: W
            int flags = (int)w1.y;
            NoiseSettings n = {clamp((flags >> 2) & 7, 1, 4), flags >> 5, clamp(b.x, 0.0f, 15.0f),
                               fmax(b.y, 0.0f), b.z, c.y, c.z, (flags & 1) != 0};
            float4 q = n.dims == 1 ? (float4)(w1.w, 0.0f, 0.0f, 0.0f)
                     : n.dims == 2 ? (float4)(a.xy, 0.0f, 0.0f)
                                   : (float4)(a.xyz, n.dims == 4 ? w1.w : 0.0f);
            out = node_noise(&n, q * c.x, w1.z, (flags & 2) != 0);
        } else if (op == NODE_OP_WAVE) {   // a: vector; b: scale, distortion, detail; c: detail scale, roughness, phase
            float f = node_wave((int)w1.y, a * b.x, b.y, b.z, c.x, c.y, c.z);
            out = (float4)(f, f, f, f);
        } else if (op == NODE_OP_MAGIC) {  // a: vector; b: scale, distortion; p0: depth
            out = node_magic(a, b.x, (int)w1.y, b.y);
        } else if (op == NODE_OP_BRICK) {  // a: vector; b: scale, mortar size and smooth; c: bias, width, row height
            int frequency = (int)w1.y;     // p0: offset frequency + 256 squash frequency; p1, p2: offset, squash
            out = node_brick(a * b.x, b.y, b.z, c.x, c.y, c.z, w1.z, frequency & 255, w1.w,
                             frequency >> 8);
        } else if (op == NODE_OP_WHITE_NOISE) {    // a: vector; b: W; p0: dimensions + 8 colour
            int flags = (int)w1.y, dims = clamp(flags & 7, 1, 4);
            float4 q = dims == 1 ? (float4)(b.x, 0.0f, 0.0f, 0.0f) : dims == 2 ? (float4)(a.xy, 0.0f, 0.0f)
                     : (float4)(a.xyz, dims == 4 ? b.x : 0.0f);
            out = node_white_noise(dims, q, (flags & 8) != 0);
#endif
#ifdef HAS_VORONOI
        } else if (op == NODE_OP_VORONOI) {    // a: vector; b: scale, detail, roughness; c: lacunarity, smoothness, exponent
            int flags = (int)w1.y;             // p0: flags (VORONOI p0); p1: randomness; p2: W
            VoronoiParams v = {clamp(flags & 7, 1, 4), (flags >> 3) & 7, (flags >> 6) & 7, b.y, b.z,
                               c.x, c.y, c.z, w1.z, 0.0f, (flags & 512) != 0};
            float4 q = v.dims == 1 ? (float4)(w1.w, 0.0f, 0.0f, 0.0f)
                     : v.dims == 2 ? (float4)(a.xy, 0.0f, 0.0f) : (float4)(a.xyz, v.dims == 4 ? w1.w : 0.0f);
            out = node_voronoi(&v, q * b.x, b.x, flags >> 10);
#endif
        } else if (op == NODE_OP_TRANSFORM) {  // Generated / Object coordinates of the hit
            __global const float4 *rows = code + pc + (int)w1.y;
            float4 q = (float4)(p, 1.0f);
#ifdef HAS_BUMP
            q.xyz += dp[clamp((int)w1.z, 0, 2)];
#endif
            out = (float4)(kd_dot4(rows[0], q), kd_dot4(rows[1], q), kd_dot4(rows[2], q), 0.0f);
#ifdef HAS_NORMAL_MAP
        } else if (op == NODE_OP_NORMAL_MAP) { // a: colour; b: strength; p0: object rows; p1: space
            out = (float4)(s ? node_normal_map(sc, s, code + pc + (int)w1.y, (int)w1.z, a.xyz, b.x)
                             : (float3)(0.0f, 0.0f, 1.0f), 0.0f);
#endif
#ifdef HAS_BUMP
        } else if (op == NODE_OP_BUMP) {       // a: heights at the steps; b: normal; c: strength, distance
            float3 normal_in = s ? (w1.z > 0.0f ? b.xyz : s->ns) : (float3)(0.0f, 0.0f, 1.0f);
            out = (float4)(node_bump(dp[1], dp[2], normal_in, a, c.x, w1.y > 0.0f ? -c.y : c.y), 0.0f);
#endif
        } else if (op == NODE_OP_FRESNEL || op == NODE_OP_LAYER_WEIGHT) {
            // a: IOR or Blend; b: the normal where p1 says it is linked (else Cycles' N)
            float3 normal = w1.z > 0.0f ? b.xyz
                            : info ? info->normal : (float3)(0.0f, 0.0f, 1.0f);
            float f = node_fresnel(op == NODE_OP_FRESNEL ? -1 : (int)w1.y, a.x, normal, info);
            out = (float4)(f, f, f, f);
        } else if (op == NODE_OP_OBJECT_INFO) {    // p0: its table; p1: output
            __global const float4 *rows = code + pc + (int)w1.y;
            int what = (int)w1.z;
            out = what == NODE_OBJECT_INFO_LOCATION ? (float4)(rows[0].xyz, 0.0f)
                : what == NODE_OBJECT_INFO_COLOR ? rows[1] : what == NODE_OBJECT_INFO_ALPHA ? rows[1].wwww
                : what == NODE_OBJECT_INFO_OBJECT_INDEX ? rows[2].xxxx
                : what == NODE_OBJECT_INFO_MATERIAL_INDEX ? rows[2].yyyy : rows[0].wwww;
        } else if (op == NODE_OP_GEOMETRY) {   // p0: output; p1: bump step (Position)
            int what = (int)w1.y;
            float3 g = info ? info->incoming : (float3)(0.0f, 0.0f, 1.0f);
            if (what == NODE_GEOMETRY_POSITION) {
                g = p;
#ifdef HAS_BUMP
                g += dp[clamp((int)w1.z, 0, 2)];
#endif
            } else if (what == NODE_GEOMETRY_NORMAL || what == NODE_GEOMETRY_TRUE_NORMAL) {
                g = info ? (what == NODE_GEOMETRY_NORMAL ? info->normal : info->ng)
                         : (float3)(0.0f, 0.0f, 1.0f);
            } else if (what == NODE_GEOMETRY_BACKFACING) {
                g = (float3)(info && info->backfacing ? 1.0f : 0.0f);
            }
            out = (float4)(g, g.x);
#ifdef HAS_LIGHT_PATH
        } else if (op == NODE_OP_LIGHT_PATH) {     // p0: output
            out = (float4)(info ? node_light_path((int)w1.y, info) : 0.0f);
#endif
#ifdef HAS_TEXTURES
        } else if (op == NODE_OP_ATTRIBUTE) {      // p0: the texture of its corners' values; p1: output
            float4 c = corner_attribute(sc, (int)w1.y, tri, bary);
            int what = (int)w1.z;
            out = what == NODE_ATTRIBUTE_ALPHA ? c.wwww
                : what == NODE_ATTRIBUTE_FAC ? (float4)((c.x + c.y + c.z) * (1.0f / 3.0f)) : c;
#endif
        } else if (op == NODE_OP_DOT) {        // colour or vector to a value
            out = (float4)(kd_dot(a.xyz, w1.yzw));
        } else if (op == NODE_OP_OUT) {
            int field = (int)w1.y;
            if (field == NODE_OUT_BASE_COLOR)
                m->base = fmax(a.xyz, 0.0f);
            else if (field == NODE_OUT_ALPHA)
                m->alpha = clamp(a.x, 0.0f, 1.0f);
            else if (field == NODE_OUT_METALLIC)
                m->metallic = clamp(a.x, 0.0f, 1.0f);
            else if (field == NODE_OUT_ROUGHNESS)
                m->roughness = clamp(a.x, 0.0f, 1.0f);
            else if (field == NODE_OUT_TRANSMISSION)
                m->transmission = clamp(a.x, 0.0f, 1.0f);
            else if (field == NODE_OUT_IOR)
                m->ior = clamp(a.x, 0.01f, 100.0f);
            else if (field == NODE_OUT_SPECULAR)
                m->specular = fmax(a.x, 0.0f);
            else if (field == NODE_OUT_EMISSION)
                m->emission = fmax(a.xyz, 0.0f);
#ifdef HAS_CLOSURES
            else if (field == NODE_OUT_WEIGHT)
                m->weight = clamp(a.x, 0.0f, 1.0f);
#endif
#ifdef HAS_COAT
            else if (field == NODE_OUT_COAT_WEIGHT)
                m->coat_weight = clamp(a.x, 0.0f, 1.0f);
            else if (field == NODE_OUT_COAT_ROUGHNESS)
                m->coat_roughness = clamp(a.x, 0.0f, 1.0f);
            else if (field == NODE_OUT_COAT_IOR)
                m->coat_ior = clamp(a.x, 1.0f, 100.0f);
            else if (field == NODE_OUT_COAT_TINT)
                m->coat_tint = fmax(a.xyz, 0.0f);
#endif
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
            else if (field == NODE_OUT_NORMAL && s) {
                float3 n = safe_normalize(a.xyz);
                if (any(n != 0.0f))
                    s->ns = n;
            }
#endif
            continue;
        }
        regs[dst] = out;
    }
}
#endif
