// Materials, textures, lights and shadow rays (docs/shading.md): a Principled BSDF of GGX
// microfacet lobes at any roughness, the world and emissive triangles as importance-sampled
// lights, and Blender's lights, combined with the BSDF by multiple importance sampling.
// Every optional part sits behind a HAS_<FEATURE> flag that core/scene/features.py derives
// from the scene, so a scene compiles only what it uses.
//
// The material, light, world and emitter buffers hold the MATERIAL, LIGHT, WORLD and EMITTER
// records of the layout header (core/layout.py; packed by slave/buffers.py), read here through
// its names.

#define MAX_SHADOW_SURFACES 16
// Surfaces a ray passes because its kind of ray does not see them (ray visibility).
#define MAX_UNSEEN_SURFACES 64
// pbrt's gamma(7): relative error bound of a hit point from barycentrics (pbrt-v3 3.9.2), doubled.
#define HIT_ERROR (2.0f * 7.0f * 0x1.0p-24f / (1.0f - 7.0f * 0x1.0p-24f))
// GGX lobes with alpha^2 below this are perfect mirrors (Cycles' singular threshold).
#define DELTA_ALPHA2 1e-7f

typedef struct {
    KdTree kd;                          // the compact kd-tree (trace.cl)
#ifdef HAS_INSTANCES
    TopLevel top;                       // the instances and their BVH (trace.cl)
#endif
    __global const float4 *tri_verts;
    __global const ushort *material_ids;
    __global const float4 *materials;
    __global const float4 *lights;
    __global const float *normals;      // (3T, 3) when HAS_SMOOTH
    __global const float *uvs;          // (3T, 2) when HAS_TEXTURES
    __global const half *texels;        // (N, 4) when HAS_TEXTURES or HAS_WORLD_TEXTURE
    __global const uint *tex_sizes;     // (K, 3) likewise
    __global const float4 *world;       // one WORLD record
    __global const float *env_cdf;      // the world texture's importance map (HAS_WORLD_TEXTURE)
    __global const float4 *emitters;    // EMITTER records (HAS_EMISSION)
    float3 world_color;
    uint light_count, emitter_count;
    float emitter_power;                // sum over emitters of mean(emission) x area
    int light_n;                        // light samples per axis
} Scene;

// The BSDF inputs at a hit (per material now; a node evaluator may fill them per hit).
typedef struct {
    float3 base;
    float alpha;
    float metallic, roughness, transmission, ior;
    float3 emission;
    float specular;
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
    float3 unbumped;                    // the shading normal before Normal Map / Bump (world)
#endif
} Material;

// A surface point: position, its error bound, the geometric normal facing the incoming ray,
// the shading normal on the same side, and whether the ray hit the front (winding) side.
typedef struct {
    float3 p, err, ng, ns;
    bool front;
    uint tri;
    uint key;                           // the hit's key (Hit.key): what a ray leaving it ignores
    float u, v;
} Surface;

inline float mean3(float3 c)
{
    return (c.x + c.y + c.z) * (1.0f / 3.0f);
}

inline float max3(float3 c)
{
    return fmax(c.x, fmax(c.y, c.z));
}

inline bool trace(const Scene *sc, float3 o, float3 d, float tmin, float tmax, bool any_hit,
                  uint ignore, Hit *h)
{
    Ray r = make_ray(o, d);
#ifdef HAS_INSTANCES
    return trace_instances(&r, tmin, tmax, any_hit, ignore, &sc->kd, &sc->top, sc->tri_verts, h);
#else
    return trace_ray(&r, tmin, tmax, any_hit, ignore, &sc->kd, sc->tri_verts, h);
#endif
}

#ifdef HAS_INSTANCES
// |m| v: bounds what an error of at most v per component becomes through m's linear part.
inline float3 transform_abs(const float4 *m, float3 v)
{
    return (float3)(fabs(m[0].x) * v.x + fabs(m[0].y) * v.y + fabs(m[0].z) * v.z,
                    fabs(m[1].x) * v.x + fabs(m[1].y) * v.y + fabs(m[1].z) * v.z,
                    fabs(m[2].x) * v.x + fabs(m[2].y) * v.y + fabs(m[2].z) * v.z);
}

// A shading normal of the instance's mesh in world space (the inverse transpose), unit.
inline float3 instance_normal(const float4 *to_object, float3 n)
{
    float3 w = transform_normal(to_object, n);
    float len = kd_length(w);
    return len > 0.0f ? w / len : w;
}
#endif

inline Surface surface_at(const Scene *sc, const Hit *h, float3 d)
{
    Surface s;
    uint tri = h->tri;
    __global const float4 *corners = sc->tri_verts + TRIANGLE_SIZE * tri;
    float3 v0 = TRIANGLE_V0(corners), v1 = TRIANGLE_V1(corners), v2 = TRIANGLE_V2(corners);
    float b0 = 1.0f - h->u - h->v;
    // The barycentric point is more accurate than o + t d far from the origin; its error is
    // bounded relative to the coordinates' magnitude (pbrt), which scales the origin offset.
    s.p = b0 * v0 + h->u * v1 + h->v * v2;
    s.err = HIT_ERROR * (fabs(b0 * v0) + fabs(h->u * v1) + fabs(h->v * v2));
    float3 n = kd_cross(v1 - v0, v2 - v0);
#ifdef HAS_INSTANCES
    // The instance's mesh is in object space: the point to world space (its error through
    // |M|, plus the transform's own rounding), the normal by the inverse transpose, flipped
    // where the transform mirrors (as the realised triangle's winding is).
    __global const float4 *I = sc->top.instances + INSTANCE_SIZE * h->inst;
    Placement placement = instance_placement(I, &sc->top);
    const float4 *to_world = placement.to_world, *to_object = placement.to_object;
    s.err = transform_abs(to_world, s.err)
            + HIT_ERROR * (transform_abs(to_world, fabs(s.p)) + fabs((float3)(to_world[0].w,
                                                                          to_world[1].w,
                                                                          to_world[2].w)));
    s.p = placed_point(to_world, s.p);
    n = transform_normal(to_object, n) * placement.orientation;
#endif
    float len = kd_length(n);
    n = len > 0.0f && isfinite(len) ? n / len : -kd_normalize(d);   // slivers: face the ray
    s.front = kd_dot(n, d) < 0.0f;
    s.ng = s.front ? n : -n;
    s.ns = s.ng;
#ifdef HAS_SMOOTH
    float3 n0 = vload3(3 * tri, sc->normals), n1 = vload3(3 * tri + 1, sc->normals);
    float3 n2 = vload3(3 * tri + 2, sc->normals);
#ifdef HAS_INSTANCES
    n0 = instance_normal(to_object, n0);    // per corner, as the realised mesh's normals
    n1 = instance_normal(to_object, n1);
    n2 = instance_normal(to_object, n2);
#endif
    float3 ns = b0 * n0 + h->u * n1 + h->v * n2;
    float ls = kd_length(ns);
    if (ls > 0.0f && isfinite(ls)) {
        ns = ns / ls;
        if (!s.front)
            ns = -ns;
        // Interpolated normals may face away from the ray at grazing angles: keep them usable.
        if (kd_dot(ns, -d) > 0.0f)
            s.ns = ns;
    }
#endif
    s.tri = tri;
    s.key = h->key;
    s.u = h->u;
    s.v = h->v;
    return s;
}

// Offset a ray origin off the surface, to the side `n` points to, by the hit point's error
// bound projected on n, then one more float step away (pbrt-v3 OffsetRayOrigin). Scales with
// the coordinates' magnitude, unlike a fixed epsilon. pbrt also rejects hits with t below the
// t error bound, which our watertight test does not compute; instead the offset is at least
// the error bound of the largest coordinate, so a point on an axis plane (err 0 along it)
// still leaves the plane rather than starting on a coplanar neighbour (or in denormals, which
// some devices flush to zero).
inline float3 offset_origin(float3 p, float3 err, float3 n)
{
    float3 a = fabs(p);
    float d = kd_dot(fabs(n), err) + HIT_ERROR * fmax(fmax(a.x, a.y), a.z) + 0x1.0p-100f;
    float3 off = d * n;
    float3 po = p + off;
    po.x = off.x != 0.0f ? kd_next_float(po.x, off.x > 0.0f) : po.x;
    po.y = off.y != 0.0f ? kd_next_float(po.y, off.y > 0.0f) : po.y;
    po.z = off.z != 0.0f ? kd_next_float(po.z, off.z > 0.0f) : po.z;
    return po;
}

// Origin for a ray leaving `s` in direction w (to the side of ng that w goes to).
inline float3 spawn(const Surface *s, float3 w)
{
    return offset_origin(s->p, s->err, kd_dot(w, s->ng) >= 0.0f ? s->ng : -s->ng);
}

// ---------------------------------------------------------------------------------------------
// Angles without transcendental built-ins (their accuracy differs between devices).

// atan of t in [-tan(pi/8), tan(pi/8)]: Taylor to t^15 (error below 2e-8).
inline float atan_small(float t)
{
    float t2 = t * t;
    float p = 1.0f / 15.0f;
    p = 1.0f / 13.0f - t2 * p;
    p = 1.0f / 11.0f - t2 * p;
    p = 1.0f / 9.0f - t2 * p;
    p = 1.0f / 7.0f - t2 * p;
    p = 1.0f / 5.0f - t2 * p;
    p = 1.0f / 3.0f - t2 * p;
    return t * (1.0f - t2 * p);
}

inline float atan_unit(float a)         // a in [0, 1]
{
    return a > 0.41421356f ? M_PI_4_F + atan_small((a - 1.0f) / (a + 1.0f)) : atan_small(a);
}

inline float atan2_poly(float y, float x)
{
    float ax = fabs(x), ay = fabs(y);
    if (ax == 0.0f && ay == 0.0f)
        return 0.0f;
    float a = ax >= ay ? atan_unit(ay / ax) : M_PI_2_F - atan_unit(ax / ay);
    if (x < 0.0f)
        a = M_PI_F - a;
    return y < 0.0f ? -a : a;
}

// sin and cos of any x in [-2 pi, 2 pi]: quarter turns, then the short polynomials.
inline float2 sincos_poly(float x)
{
    float q = floor(x * M_2_PI_F + 0.5f);
    float r = x - q * M_PI_2_F;
    float s = sin_small(r), c = cos_small(r);
    int k = ((int)q) & 3;
    if (k == 1)
        return (float2)(c, -s);
    if (k == 2)
        return (float2)(-s, -c);
    if (k == 3)
        return (float2)(-c, s);
    return (float2)(s, c);
}

// ---------------------------------------------------------------------------------------------
// Textures

#if defined(HAS_TEXTURES) || defined(HAS_WORLD_TEXTURE)
// Texel (x, y) of the w x h texture at `offset`, the coordinates clamped into it (a NaN or
// infinite coordinate from a node program converts to any int) and the index taken in 64 bits:
// no read leaves the texture, which the host checked lies inside texels (Geometry.validate).
inline float4 texel(const Scene *sc, uint offset, int w, int h, int x, int y)
{
    x = clamp(x, 0, max(w - 1, 0));
    y = clamp(y, 0, max(h - 1, 0));
    return vload_half4((size_t)((ulong)offset + (ulong)y * (ulong)w + (ulong)x), sc->texels);
}

// Texel i of a row or column of n in an Image Texture extension mode (Cycles'); -1: outside
// the image (Clip: black and transparent).
inline int wrap_texel(int i, int n, int extension)
{
    if (extension == NODE_EXTENSION_EXTEND)
        return clamp(i, 0, n - 1);
    if (extension == NODE_EXTENSION_CLIP)
        return i < 0 || i >= n ? -1 : i;
    if (extension == NODE_EXTENSION_MIRROR) {
        int m = i % (2 * n);
        m = m < 0 ? m + 2 * n : m;
        return m < n ? m : 2 * n - 1 - m;
    }
    return i < 0 ? n - 1 : (i >= n ? 0 : i);           // repeat (i is in [-1, n])
}

inline float4 texel_or_clear(const Scene *sc, uint offset, int w, int h, int x, int y)
{
    return x < 0 || y < 0 ? (float4)(0.0f, 0.0f, 0.0f, 0.0f) : texel(sc, offset, w, h, x, y);
}

// Bilinear (or closest) lookup; uv (0, 0) is the first texel (Blender's bottom-left).
// `extension`: a NODE_EXTENSION code (material textures and the world repeat).
inline float4 texture_lookup_ext(const Scene *sc, int tex, float2 uv, bool closest,
                                 int extension)
{
    __global const uint *size = sc->tex_sizes + TEXTURE_SIZE_COLUMNS * tex;
    uint offset = size[TEXTURE_SIZE_OFFSET];
    int w = (int)size[TEXTURE_SIZE_WIDTH], h = (int)size[TEXTURE_SIZE_HEIGHT];
    if (extension == NODE_EXTENSION_REPEAT)
        uv = uv - floor(uv);                           // [0, 1), also for huge uv
    else
        uv = clamp(uv, -4.0f, 5.0f);                   // the same texels, no int overflow
    if (closest) {
        int x = (int)floor(uv.x * (float)w), y = (int)floor(uv.y * (float)h);
        if (extension == NODE_EXTENSION_REPEAT)
            return texel(sc, offset, w, h, x, y);
        return texel_or_clear(sc, offset, w, h, wrap_texel(x, w, extension),
                              wrap_texel(y, h, extension));
    }
    float x = uv.x * (float)w - 0.5f, y = uv.y * (float)h - 0.5f;
    float fx = floor(x), fy = floor(y);
    float tx = x - fx, ty = y - fy;
    int x0 = wrap_texel((int)fx, w, extension), y0 = wrap_texel((int)fy, h, extension);
    int x1 = wrap_texel((int)fx + 1, w, extension), y1 = wrap_texel((int)fy + 1, h, extension);
    float4 c00 = texel_or_clear(sc, offset, w, h, x0, y0), c10 = texel_or_clear(sc, offset, w, h, x1, y0);
    float4 c01 = texel_or_clear(sc, offset, w, h, x0, y1), c11 = texel_or_clear(sc, offset, w, h, x1, y1);
    return (1.0f - ty) * ((1.0f - tx) * c00 + tx * c10) + ty * ((1.0f - tx) * c01 + tx * c11);
}

inline float4 texture_lookup(const Scene *sc, int tex, float2 uv, bool closest)
{
    return texture_lookup_ext(sc, tex, uv, closest, NODE_EXTENSION_REPEAT);
}
#endif

#ifdef HAS_NODES
// ---------------------------------------------------------------------------------------------
// Shader node programs (core/layout.py NODE_OP_CODES; compiled by addon/nodes.py): a few
// registers, one instruction per node, then OUT instructions that set the BSDF inputs.

inline float4 node_operand(const float4 *regs, float ref)
{
    int r = (int)ref, lane = r % NODE_REF_REGISTER;
    float4 v = regs[min(r / NODE_REF_REGISTER, NODE_REGISTERS - 1)];
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

// Cycles' math node, with its safe division, power and square root.
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

// Cycles' Vector Math: the vector in xyz, the value output (Dot Product, Length) in w.
inline float4 node_vector_math(int op, float4 a, float4 b, float s)
{
    float3 x = a.xyz, y = b.xyz, r = (float3)(0.0f, 0.0f, 0.0f);
    float value = 0.0f;
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
    else if (op == NODE_VECTOR_MATH_NORMALIZE) {
        float l = kd_length(x);
        r = l != 0.0f ? x / l : (float3)(0.0f, 0.0f, 0.0f);
    }
    else if (op == NODE_VECTOR_MATH_ABSOLUTE) r = fabs(x);
    else if (op == NODE_VECTOR_MATH_MINIMUM) r = fmin(x, y);
    else if (op == NODE_VECTOR_MATH_MAXIMUM) r = fmax(x, y);
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

#ifdef HAS_NOISE
// Cycles' Noise Texture (every type, 1D to 4D): Perlin noise with Cycles' hash (Bob Jenkins' lookup3)
// and gradients, so that the pattern is Cycles' own, not merely alike. Points are float4 with
// the unused lanes 0.
inline uint lookup3_final(uint a, uint b, uint c)
{
    c ^= b; c -= rotate(b, 14u);
    a ^= c; a -= rotate(c, 11u);
    b ^= a; b -= rotate(a, 25u);
    c ^= b; c -= rotate(b, 16u);
    a ^= c; a -= rotate(c, 4u);
    b ^= a; b -= rotate(a, 14u);
    c ^= b; c -= rotate(b, 24u);
    return c;
}

// lookup3 of `n` words (Cycles' hash_uint, hash_uint2, hash_uint3, hash_uint4).
inline uint lookup3(int n, uint4 k)
{
    uint seed = 0xdeadbeefu + ((uint)n << 2) + 13u;
    uint a = seed + k.x, b = seed + (n > 1 ? k.y : 0u), c = seed + (n > 2 ? k.z : 0u);
    if (n == 4) {                       // lookup3's mix of the first three, then the fourth
        a -= c; a ^= rotate(c, 4u); c += b;
        b -= a; b ^= rotate(a, 6u); a += c;
        c -= b; c ^= rotate(b, 8u); b += a;
        a -= c; a ^= rotate(c, 16u); c += b;
        b -= a; b ^= rotate(a, 19u); a += c;
        c -= b; c ^= rotate(b, 4u); b += a;
        a += k.w;
    }
    return lookup3_final(a, b, c);
}

// Cycles' gradients (grad1 to grad4) of a lattice point's hash, dotted with the offset f.
inline float noise_gradient(int dims, uint hash, float4 f)
{
    if (dims == 1) {
        uint h = hash & 15u;
        float g = (float)(1u + (h & 7u));
        return ((h & 8u) ? -g : g) * f.x;
    }
    if (dims == 2) {
        uint h = hash & 7u;
        float u = h < 4u ? f.x : f.y, v = 2.0f * (h < 4u ? f.y : f.x);
        return ((h & 1u) ? -u : u) + ((h & 2u) ? -v : v);
    }
    if (dims == 3) {
        uint h = hash & 15u;
        float u = h < 8u ? f.x : f.y;
        float v = h < 4u ? f.y : (h == 12u || h == 14u) ? f.x : f.z;
        return ((h & 1u) ? -u : u) + ((h & 2u) ? -v : v);
    }
    uint h = hash & 31u;
    float u = h < 24u ? f.x : f.y, v = h < 16u ? f.y : f.z, t = h < 8u ? f.z : f.w;
    return ((h & 1u) ? -u : u) + ((h & 2u) ? -v : v) + ((h & 4u) ? -t : t);
}

// Signed Perlin noise in about [-1, 1] (Cycles' snoise_1d to snoise_4d and their OSL scales):
// the gradients at the cell's corners blended by the quintic fade; coordinates wrap every
// 100000 units, as Cycles' do, to keep float precision.
inline float signed_noise(int dims, float4 p)
{
    float4 big = (float4)(fabs(p.x) >= 1e6f ? 0.5f : 0.0f, fabs(p.y) >= 1e6f ? 0.5f : 0.0f,
                          fabs(p.z) >= 1e6f ? 0.5f : 0.0f, fabs(p.w) >= 1e6f ? 0.5f : 0.0f);
    p = fmod(p, 100000.0f) + big;
    float4 cell = floor(p), f = p - cell;
    int4 i = convert_int4(cell);
    float4 w = f * f * f * (f * (f * 6.0f - 15.0f) + 10.0f);
    float r = 0.0f;
    for (int k = 0; k < (1 << dims); ++k) {
        int4 d = (int4)(k & 1, (k >> 1) & 1, (k >> 2) & 1, (k >> 3) & 1);
        float4 t = select(1.0f - w, w, d != 0);
        float weight = t.x * (dims > 1 ? t.y : 1.0f) * (dims > 2 ? t.z : 1.0f) * (dims > 3 ? t.w : 1.0f);
        r += weight * noise_gradient(dims, lookup3(dims, as_uint4(i + d)), f - convert_float4(d));
    }
    return r * (dims == 1 ? 0.25f : dims == 2 ? 0.6616f : dims == 3 ? 0.9820f : 0.8344f);
}

// A Noise Texture's settings (detail clamped to [0, 15], roughness to >= 0, as Cycles').
typedef struct {
    int dims, type;
    float detail, roughness, lacunarity, offset, gain;
    bool normalize;
} NoiseSettings;

// Cycles' fractals of octaves at `lacunarity` times the frequency and `roughness` times the
// amplitude, the fraction of `detail` blending in the last octave: fBm (normalised to [0, 1]
// or not), multifractal, hybrid multifractal, ridged multifractal, heterogeneous terrain.
inline float noise_fractal(const NoiseSettings *n, float4 p)
{
    int octaves = (int)n->detail, dims = n->dims;
    float rest = n->detail - floor(n->detail), r = n->roughness, l = n->lacunarity;
    if (n->type == NODE_NOISE_TYPE_MULTIFRACTAL) {
        float value = 1.0f, pwr = 1.0f;
        for (int i = 0; i <= octaves; ++i, pwr *= r, p *= l)
            value *= pwr * signed_noise(dims, p) + 1.0f;
        return rest != 0.0f ? value * (rest * pwr * signed_noise(dims, p) + 1.0f) : value;
    }
    if (n->type == NODE_NOISE_TYPE_HETERO_TERRAIN) {
        float pwr = r, value = n->offset + signed_noise(dims, p);
        p *= l;
        for (int i = 1; i <= octaves; ++i, pwr *= r, p *= l)
            value += (signed_noise(dims, p) + n->offset) * pwr * value;
        if (rest != 0.0f)
            value += rest * (signed_noise(dims, p) + n->offset) * pwr * value;
        return value;
    }
    if (n->type == NODE_NOISE_TYPE_HYBRID_MULTIFRACTAL) {
        float pwr = 1.0f, value = 0.0f, weight = 1.0f;
        for (int i = 0; weight > 0.001f && i <= octaves; ++i, p *= l) {
            weight = fmin(weight, 1.0f);
            float signal = (signed_noise(dims, p) + n->offset) * pwr;
            pwr *= r;
            value += weight * signal;
            weight *= n->gain * signal;
        }
        if (rest != 0.0f && weight > 0.001f)
            value += rest * fmin(weight, 1.0f) * (signed_noise(dims, p) + n->offset) * pwr;
        return value;
    }
    if (n->type == NODE_NOISE_TYPE_RIDGED_MULTIFRACTAL) {
        float pwr = r, signal = n->offset - fabs(signed_noise(dims, p));
        signal *= signal;
        float value = signal;
        for (int i = 1; i <= octaves; ++i, pwr *= r) {
            p *= l;
            float weight = clamp(signal * n->gain, 0.0f, 1.0f);
            signal = n->offset - fabs(signed_noise(dims, p));
            signal *= signal * weight;
            value += signal * pwr;
        }
        return value;
    }
    float scale = 1.0f, amp = 1.0f, max_amp = 0.0f, sum = 0.0f;      // fBm
    for (int i = 0; i <= octaves; ++i, amp *= r, scale *= l) {
        sum += signed_noise(dims, scale * p) * amp;
        max_amp += amp;
    }
    if (rest != 0.0f) {
        float sum2 = sum + signed_noise(dims, scale * p) * amp;
        return n->normalize ? mix(0.5f * sum / max_amp + 0.5f, 0.5f * sum2 / (max_amp + amp) + 0.5f, rest)
                            : mix(sum, sum2, rest);
    }
    return n->normalize ? 0.5f * sum / max_amp + 0.5f : sum;
}

// Cycles' seed offsets for the distortion and colour channels: 100 + 100 x hash(seed, lane)
// per used lane, the hash of the two floats' bits (1D: of the seed alone).
inline float4 noise_offset(int dims, float seed)
{
    float r[4] = {0.0f, 0.0f, 0.0f, 0.0f};
    for (int k = 0; k < dims; ++k) {
        uint h = dims == 1 ? lookup3(1, (uint4)(as_uint(seed), 0u, 0u, 0u))
                           : lookup3(2, (uint4)(as_uint(seed), as_uint((float)k), 0u, 0u));
        r[k] = 100.0f + (float)h * (100.0f / (float)0xFFFFFFFFu);
    }
    return (float4)(r[0], r[1], r[2], r[3]);
}

// The Noise Texture at p (already times Scale; n->dims lanes used): (Fac, Fac, Fac) or, with
// `colour`, its Color (the seeds after the distortion's).
inline float4 node_noise(const NoiseSettings *n, float4 p, float distortion, bool colour)
{
    int dims = n->dims;
    if (distortion != 0.0f) {
        float shift[4] = {0.0f, 0.0f, 0.0f, 0.0f};
        for (int k = 0; k < dims; ++k)
            shift[k] = signed_noise(dims, p + noise_offset(dims, (float)k)) * distortion;
        p += (float4)(shift[0], shift[1], shift[2], shift[3]);
    }
    float f = noise_fractal(n, p);
    float4 out = (float4)(f, f, f, 1.0f);
    if (colour) {
        out.y = noise_fractal(n, p + noise_offset(dims, (float)dims));
        out.z = noise_fractal(n, p + noise_offset(dims, (float)(dims + 1)));
    }
    return out;
}
#endif

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

// Runs the program at row `at` of the materials buffer for the hit on triangle `tri` (uv: its
// texture coordinates, p: its position; s: the surface point, or 0 where the shading normal
// does not matter) and sets the BSDF inputs it computes; a Normal output sets s->ns.
inline void run_nodes(const Scene *sc, int at, uint tri, float2 uv, float3 p, Surface *s,
                      Material *m)
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
        int op = (int)w0.x, dst = min((int)w0.y, NODE_REGISTERS - 1);
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
        } else if (op == NODE_OP_VECTOR_MATH) {   // c: the Scale input
            out = node_vector_math((int)w1.y, a, b, c.x);
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

// The material of triangle `tri` at barycentrics (u, v); `s`: the surface point where the
// shading normal matters (a node program's Normal output sets s->ns), else 0.
inline Material material_eval(const Scene *sc, uint tri, float u, float v, Surface *s)
{
    uint id = sc->material_ids[tri];
    __global const float4 *M = sc->materials + MATERIAL_SIZE * id;
    Material m;
    m.base = MATERIAL_BASE_COLOR(M);
    m.alpha = MATERIAL_ALPHA(M);
    m.metallic = MATERIAL_METALLIC(M);
    m.roughness = MATERIAL_ROUGHNESS(M);
    m.transmission = MATERIAL_TRANSMISSION(M);
    m.ior = MATERIAL_IOR(M);
    m.emission = MATERIAL_EMISSION(M);
    m.specular = MATERIAL_SPECULAR(M);
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
    m.unbumped = s ? s->ns : (float3)(0.0f, 0.0f, 1.0f);
#endif
#ifdef HAS_TEXTURES
    int tex = (int)MATERIAL_TEXTURE(M);
    if (tex >= 0) {
        float2 uv = (1.0f - u - v) * vload2(3 * tri, sc->uvs) + u * vload2(3 * tri + 1, sc->uvs)
                    + v * vload2(3 * tri + 2, sc->uvs);
        float4 c = texture_lookup(sc, tex, uv, false);
        m.base *= c.xyz;
        if (MATERIAL_TEXTURE_ALPHA(M) > 0.0f)
            m.alpha *= c.w;
    }
#endif
#ifdef HAS_NODES
    int program = (int)MATERIAL_PROGRAM(M);
    if (program >= 0) {
        float2 uv = (1.0f - u - v) * vload2(3 * tri, sc->uvs) + u * vload2(3 * tri + 1, sc->uvs)
                    + v * vload2(3 * tri + 2, sc->uvs);
        __global const float4 *T = sc->tri_verts + TRIANGLE_SIZE * tri;
        float3 p = (1.0f - u - v) * TRIANGLE_V0(T) + u * TRIANGLE_V1(T) + v * TRIANGLE_V2(T);
        run_nodes(sc, program, tri, uv, p, s, &m);
    }
#endif
    return m;
}

// The material where the shading normal does not matter (emitters, shadow rays' alpha).
inline Material material_at(const Scene *sc, uint tri, float u, float v)
{
    return material_eval(sc, tri, u, v, 0);
}

#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
// Cycles' ensure_valid_specular_reflection: a shading normal n whose mirror reflection of wi
// (unit, toward the viewer) would go below the geometric normal ng is tilted toward ng just
// enough that the reflection stays above the surface.
inline float3 valid_reflection_normal(float3 ng, float3 wi, float3 n)
{
    float3 r = 2.0f * kd_dot(n, wi) * n - wi;
    float iz = kd_dot(wi, ng);
    float threshold = fmin(0.9f * iz, 0.01f);
    if (kd_dot(ng, r) >= threshold)
        return n;
    float3 x = safe_normalize(n - kd_dot(n, ng) * ng);
    if (all(x == 0.0f))
        x = n;
    float ix = kd_dot(wi, x);
    float a = ix * ix + iz * iz, b = 2.0f * (a + iz * threshold);
    float c = (threshold + iz) * (threshold + iz);
    float root = sqrt(fmax(b * b - 4.0f * a * c, 0.0f));
    float nz2 = 0.25f * (ix < 0.0f ? b + root : b - root) / a;
    return sqrt(fmax(1.0f - nz2, 0.0f)) * x + sqrt(fmax(nz2, 0.0f)) * ng;
}
#endif

// The material where a ray of direction d hit s. Normal Map and Bump nodes set s->ns, tilted
// as Cycles tilts it where it would reflect the ray below the surface.
inline Material surface_material(const Scene *sc, Surface *s, float3 d)
{
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
    float3 ns = s->ns;
    Material m = material_eval(sc, s->tri, s->u, s->v, s);
    if (any(s->ns != ns))
        s->ns = valid_reflection_normal(s->ng, -kd_normalize(d), s->ns);
    if (!(kd_dot(s->ns, d) < 0.0f))
        s->ns = ns;
    return m;
#else
    return material_eval(sc, s->tri, s->u, s->v, 0);
#endif
}

// The VISIBILITY_<RAY> bits of the rays that see the triangle, and VISIBILITY_HOLDOUT.
inline uint material_visibility(const Scene *sc, uint tri)
{
    return (uint)MATERIAL_VISIBILITY(sc->materials + MATERIAL_SIZE * sc->material_ids[tri]);
}

// The same for a hit: with instances, rays see it when both its material and its instance
// let them; either one makes it a holdout.
inline uint hit_visibility(const Scene *sc, const Hit *h)
{
    uint bits = material_visibility(sc, h->tri);
#ifdef HAS_INSTANCES
    uint own = (uint)INSTANCE_VISIBILITY(sc->top.instances + INSTANCE_SIZE * h->inst);
    bits = (bits & own & ~VISIBILITY_HOLDOUT) | ((bits | own) & VISIBILITY_HOLDOUT);
#endif
    return bits;
}

// ---------------------------------------------------------------------------------------------
// Fresnel and GGX

// Fresnel reflectance of a dielectric interface (unpolarised); eta = n_transmitted / n_incident.
inline float fresnel_dielectric(float cos_i, float eta)
{
    cos_i = clamp(cos_i, 0.0f, 1.0f);
    float sin2_t = (1.0f - cos_i * cos_i) / (eta * eta);
    if (sin2_t >= 1.0f)
        return 1.0f;                                    // total internal reflection
    float cos_t = sqrt(1.0f - sin2_t);
    float rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    float rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    return 0.5f * (rs * rs + rp * rp);
}

inline float pow5(float x)
{
    float x2 = x * x;
    return x2 * x2 * x;
}

inline float ggx_d(float alpha2, float cos_h)
{
    float den = cos_h * cos_h * (alpha2 - 1.0f) + 1.0f;
    return alpha2 / (M_PI_F * den * den);
}

// Smith's Lambda for GGX (masking G1 = 1 / (1 + Lambda); height-correlated G2 = 1 / (1 +
// Lambda_o + Lambda_i), as Cycles).
inline float ggx_lambda(float alpha2, float cos_t)
{
    float c2 = cos_t * cos_t;
    return 0.5f * (-1.0f + sqrt(1.0f + alpha2 * fmax(1.0f - c2, 0.0f) / fmax(c2, 1e-20f)));
}

// A microfacet normal from the visible normals seen from wo (local frame, wo.z > 0; Heitz
// 2018), with the concentric disk map (no trig).
inline float3 sample_vndf(float3 wo, float alpha, float u1, float u2)
{
    float3 vh = kd_normalize((float3)(alpha * wo.x, alpha * wo.y, wo.z));
    float lensq = vh.x * vh.x + vh.y * vh.y;
    float3 t1 = lensq > 0.0f ? (float3)(-vh.y, vh.x, 0.0f) / sqrt(lensq) : (float3)(1.0f, 0.0f, 0.0f);
    float3 t2 = kd_cross(vh, t1);
    float2 p = concentric_disk(u1, u2);
    float s = 0.5f * (1.0f + vh.z);
    p.y = (1.0f - s) * sqrt(fmax(0.0f, 1.0f - p.x * p.x)) + s * p.y;
    float3 nh = p.x * t1 + p.y * t2 + sqrt(fmax(0.0f, 1.0f - p.x * p.x - p.y * p.y)) * vh;
    return kd_normalize((float3)(alpha * nh.x, alpha * nh.y, fmax(nh.z, 1e-7f)));
}

// pbrt-v4's Refract: wo leaves the surface on the side of n; eta = n_t / n_i across it.
inline bool refract_local(float3 wo, float3 n, float eta, float3 *wt)
{
    float cos_i = kd_dot(n, wo);
    if (cos_i < 0.0f) {
        eta = 1.0f / eta;
        cos_i = -cos_i;
        n = -n;
    }
    float sin2_t = fmax(0.0f, 1.0f - cos_i * cos_i) / (eta * eta);
    if (sin2_t >= 1.0f)
        return false;
    float cos_t = sqrt(fmax(0.0f, 1.0f - sin2_t));
    *wt = -wo / eta + (cos_i / eta - cos_t) * n;
    return true;
}

// Bilinear lookup of the single-scattering GGX albedo table (ggx_albedo.cl).
inline float ggx_albedo(float cos_o, float roughness)
{
    float x = clamp(cos_o, 0.0f, 1.0f) * (float)(GGX_TABLE_SIZE - 1);
    float y = clamp(roughness, 0.0f, 1.0f) * (float)(GGX_TABLE_SIZE - 1);
    int x0 = min((int)x, GGX_TABLE_SIZE - 2), y0 = min((int)y, GGX_TABLE_SIZE - 2);
    float tx = x - (float)x0, ty = y - (float)y0;
    int i = y0 * GGX_TABLE_SIZE + x0;
    float a = GGX_E[i] + tx * (GGX_E[i + 1] - GGX_E[i]);
    float b = GGX_E[i + GGX_TABLE_SIZE] + tx * (GGX_E[i + GGX_TABLE_SIZE + 1] - GGX_E[i + GGX_TABLE_SIZE]);
    return a + ty * (b - a);
}

inline float ggx_albedo_avg(float roughness)
{
    float y = clamp(roughness, 0.0f, 1.0f) * (float)(GGX_TABLE_SIZE - 1);
    int y0 = min((int)y, GGX_TABLE_SIZE - 2);
    float ty = y - (float)y0;
    return GGX_E_AVG[y0] + ty * (GGX_E_AVG[y0 + 1] - GGX_E_AVG[y0]);
}

// Trilinear lookup of a dielectric albedo table (ggx_albedo.cl) at relative IOR eta >= 1.
inline float dielectric_albedo(__constant const float *table, float cos_o, float roughness,
                               float eta)
{
    const int n = DIELECTRIC_TABLE_SIZE;
    float x = clamp(cos_o, 0.0f, 1.0f) * (float)(n - 1);
    float y = clamp(roughness, 0.0f, 1.0f) * (float)(n - 1);
    float z = clamp((eta - DIELECTRIC_IOR_MIN) / (DIELECTRIC_IOR_MAX - DIELECTRIC_IOR_MIN),
                    0.0f, 1.0f) * (float)(n - 1);
    int x0 = min((int)x, n - 2), y0 = min((int)y, n - 2), z0 = min((int)z, n - 2);
    float tx = x - (float)x0, ty = y - (float)y0, tz = z - (float)z0;
    float c[2];
    for (int k = 0; k < 2; ++k) {
        __constant const float *t = table + ((z0 + k) * n + y0) * n + x0;
        float a = t[0] + tx * (t[1] - t[0]);
        float b = t[n] + tx * (t[n + 1] - t[n]);
        c[k] = a + ty * (b - a);
    }
    return c[0] + tz * (c[1] - c[0]);
}

// Single-scattering albedo of a glass boundary seen from wo (eta = n_t / n_i).
inline float glass_albedo(float cos_o, float roughness, float eta)
{
    return eta >= 1.0f ? dielectric_albedo(GLASS_E_ENTER, cos_o, roughness, eta)
                       : dielectric_albedo(GLASS_E_LEAVE, cos_o, roughness, 1.0f / eta);
}

// ---------------------------------------------------------------------------------------------
// The BSDF: Principled's layers (Cycles 4): metal (weight metallic), glass ((1 - metallic)
// transmission; each refraction tinted by sqrt(base), so that in and out of an object tint
// by the base colour, as Cycles) and a dielectric specular layer over Lambertian diffuse (the
// rest), GGX of alpha = roughness^2 for every specular lobe. Directions in the local frame of the shading
// normal (z up, wo.z > 0).

typedef struct {
    float3 t, b, n;
} Frame;

inline Frame frame_of(float3 n)
{
    Frame f;
    basis(n, &f.t, &f.b);
    f.n = n;
    return f;
}

inline float3 to_local(const Frame *f, float3 w)
{
    return (float3)(kd_dot(w, f->t), kd_dot(w, f->b), kd_dot(w, f->n));
}

inline float3 to_world(const Frame *f, float3 w)
{
    return w.x * f->t + w.y * f->b + w.z * f->n;
}

#define LOBE_DIFFUSE 0
#define LOBE_GLOSSY 1
#define LOBE_TRANSMISSION 2

typedef struct {
    float w_metal, w_glass, w_dielectric;       // layer weights
    float p_diffuse, p_specular, p_metal, p_glass;  // lobe sampling probabilities
    float alpha, alpha2;
    bool delta;                                 // the specular lobes are perfect mirrors
    float eta_specular;                         // IOR of the dielectric specular layer
    float eta_glass;                            // n_t / n_i for a ray leaving on wo's side
    float diffuse_weight;                       // 1 - the specular layer's albedo at wo
    float3 metal_scale;                         // multiple-scattering compensation of metal
    float glass_scale;                          // ... and of glass
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
    float3 unbumped;                            // Material.unbumped in the local frame
#endif
} Lobes;

inline float3 metal_fresnel(float3 f0, float cos_h)
{
    return f0 + (1.0f - f0) * pow5(1.0f - clamp(cos_h, 0.0f, 1.0f));
}

// `alpha_min`: Filter Glossy's blur (0: none), the least alpha of the specular lobes.
inline Lobes lobes_at(const Material *m, float cos_o, bool front, float alpha_min)
{
    Lobes l;
    float metallic = clamp(m->metallic, 0.0f, 1.0f);
    float transmission = clamp(m->transmission, 0.0f, 1.0f);
    l.w_metal = metallic;
    l.w_glass = (1.0f - metallic) * transmission;
    l.w_dielectric = (1.0f - metallic) * (1.0f - transmission);
    // The energy compensation is that of the material's own roughness; Filter Glossy then
    // widens the lobes without it (as Cycles blurs closures after their setup).
    float roughness = clamp(m->roughness, 0.0f, 1.0f);
    bool sharp = roughness * roughness * roughness * roughness <= DELTA_ALPHA2;
    l.alpha = fmax(roughness * roughness, alpha_min);
    l.alpha2 = l.alpha * l.alpha;
    l.delta = l.alpha2 <= DELTA_ALPHA2;
    l.alpha = fmax(l.alpha, 1e-4f);
    l.alpha2 = fmax(l.alpha2, 1e-8f);
    // "Specular IOR Level" scales F0 of the IOR (0.5 = as the IOR says); back to an IOR.
    float r = (m->ior - 1.0f) / (m->ior + 1.0f);
    float f0 = fmin(r * r * 2.0f * fmax(m->specular, 0.0f), 0.9999f);
    float sf = sqrt(f0);
    l.eta_specular = (1.0f + sf) / (1.0f - sf);
    l.eta_glass = front ? m->ior : 1.0f / m->ior;
    float f_spec = fresnel_dielectric(cos_o, l.eta_specular);
    // What the specular layer reflects (all directions) the diffuse below does not get.
    l.diffuse_weight = 1.0f - (sharp ? f_spec : dielectric_albedo(SPECULAR_E, cos_o, roughness,
                                                                   l.eta_specular));
    l.metal_scale = (float3)(1.0f, 1.0f, 1.0f);
    l.glass_scale = 1.0f;
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
    l.unbumped = (float3)(0.0f, 0.0f, 1.0f);
#endif
#ifdef HAS_TRANSMISSION
    if (l.w_glass > 0.0f && !sharp)
        l.glass_scale = 1.0f / fmax(glass_albedo(cos_o, roughness, l.eta_glass), 0.05f);
#endif
    float a_metal = 0.0f;
#ifdef HAS_SPECULAR
    if (l.w_metal > 0.0f) {
        if (!sharp) {
            float e = ggx_albedo(cos_o, roughness), e_avg = ggx_albedo_avg(roughness);
            float3 f_avg = m->base + (1.0f - m->base) * (1.0f / 21.0f);
            float3 f_ms = f_avg * e_avg / (1.0f - f_avg * (1.0f - e_avg));
            l.metal_scale = 1.0f + f_ms * ((1.0f - e) / e);
        }
        a_metal = l.w_metal * mean3(metal_fresnel(m->base, cos_o) * l.metal_scale);
    }
#endif
    float a_spec = 0.0f, a_glass = 0.0f;
#ifdef HAS_SPECULAR
    a_spec = l.w_dielectric * f_spec;
#endif
#ifdef HAS_TRANSMISSION
    a_glass = l.w_glass * fmax(mean3(m->base), 0.05f);
#endif
    float a_diff = l.w_dielectric * l.diffuse_weight * mean3(m->base);
    float total = a_metal + a_spec + a_glass + a_diff;
    float inv = total > 0.0f ? 1.0f / total : 0.0f;
    l.p_diffuse = a_diff * inv;
    l.p_specular = a_spec * inv;
    l.p_metal = a_metal * inv;
    l.p_glass = a_glass * inv;
    return l;
}

#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
// Cycles' bump shadowing of diffuse light (wi local; n: the unperturbed normal, local, where wi
// is on its side): the GGX shadowing of a roughness that grows with the normal's tilt, which
// softens the terminator (Conty Estevez et al., "A Microfacet-Based Shadowing Function to
// Solve the Bump Terminator Problem").
inline float bump_shadowing(float3 n, float3 wi)
{
    float cos_i = fabs(kd_dot(n, wi)), cos_d = fabs(n.z);
    if (cos_d >= 1.0f || cos_i >= 1.0f)
        return 1.0f;
    if (cos_i < 1e-6f)
        return 0.0f;
    float alpha2 = clamp(0.125f * (1.0f / (cos_d * cos_d) - 1.0f), 0.0f, 1.0f);
    return 2.0f / (1.0f + sqrt(1.0f + alpha2 * (1.0f / (cos_i * cos_i) - 1.0f)));
}
#endif

// The non-delta part of the BSDF for wo -> wi (local), without the cosine; *pdf: the
// density of bsdf_sample choosing wi (solid angle).
inline float3 bsdf_eval_local(const Material *m, const Lobes *l, float3 wo, float3 wi, float *pdf)
{
    float3 f = (float3)(0.0f, 0.0f, 0.0f);
    *pdf = 0.0f;
    float cos_o = wo.z, cos_i = wi.z;
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
    // Light on the other side of the unperturbed surface than the perturbed normal says (as
    // Cycles: no light leaks through bumps to the back of opaque geometry).
    if (kd_dot(l->unbumped, wi) * l->unbumped.z * cos_i < 0.0f)
        return f;
#endif
    if (cos_i > 0.0f) {
        float diffuse = l->w_dielectric * l->diffuse_weight * M_1_PI_F;
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
        diffuse *= bump_shadowing(l->unbumped, wi);
#endif
        f += m->base * diffuse;
        *pdf += l->p_diffuse * cos_i * M_1_PI_F;
    }
    if (l->delta)
        return f;
    float lambda_o = ggx_lambda(l->alpha2, cos_o);
#if defined(HAS_SPECULAR) || defined(HAS_TRANSMISSION)
    if (cos_i > 0.0f) {
        float3 h = kd_normalize(wo + wi);
        float d = ggx_d(l->alpha2, h.z);
        float g2 = 1.0f / (1.0f + lambda_o + ggx_lambda(l->alpha2, cos_i));
        float common = d * g2 / (4.0f * cos_o * cos_i);
        float pdf_reflect = d / ((1.0f + lambda_o) * 4.0f * cos_o);   // D G1(wo) / (4 cos_o)
        float cos_oh = kd_dot(wo, h);
#ifdef HAS_SPECULAR
        if (l->w_metal > 0.0f) {
            f += l->w_metal * metal_fresnel(m->base, cos_oh) * l->metal_scale * common;
            *pdf += l->p_metal * pdf_reflect;
        }
        if (l->w_dielectric > 0.0f && l->p_specular > 0.0f) {
            f += l->w_dielectric * fresnel_dielectric(cos_oh, l->eta_specular) * common;
            *pdf += l->p_specular * pdf_reflect;
        }
#endif
#ifdef HAS_TRANSMISSION
        if (l->w_glass > 0.0f) {
            float F = fresnel_dielectric(cos_oh, l->eta_glass);
            f += l->w_glass * l->glass_scale * F * common;
            *pdf += l->p_glass * pdf_reflect * F;
        }
#endif
    }
#endif
#ifdef HAS_TRANSMISSION
    if (cos_i < 0.0f && l->w_glass > 0.0f) {
        // pbrt-v4's rough dielectric transmission (generalised half vector), radiance mode.
        float etap = l->eta_glass;
        float3 h = wi * etap + wo;
        float hl = kd_length(h);
        if (hl > 0.0f) {
            h = h / hl;
            if (h.z < 0.0f)
                h = -h;
            float cos_oh = kd_dot(wo, h), cos_ih = kd_dot(wi, h);
            if (cos_oh > 0.0f && cos_ih < 0.0f) {
                float F = fresnel_dielectric(cos_oh, etap);
                float d = ggx_d(l->alpha2, h.z);
                float g2 = 1.0f / (1.0f + lambda_o + ggx_lambda(l->alpha2, cos_i));
                float denom = cos_ih + cos_oh / etap;
                denom = denom * denom;
                float ft = d * g2 * (1.0f - F) * fabs(cos_ih * cos_oh) / (fabs(cos_i) * cos_o * denom);
                f += sqrt(m->base) * (l->w_glass * l->glass_scale * ft / (etap * etap));
                float pdf_h = d * cos_oh / ((1.0f + lambda_o) * cos_o);     // D_wo(h)
                *pdf += l->p_glass * pdf_h * fabs(cos_ih) / denom * (1.0f - F);
            }
        }
    }
#endif
    return f;
}

// A direction from the BSDF. Returns false when the sample is lost (below the surface,
// nothing to scatter). *weight = f cos / pdf; *pdf = 0 for a mirror (delta) direction;
// *kind: LOBE_DIFFUSE, LOBE_GLOSSY or LOBE_TRANSMISSION (for the bounce limits).
inline bool bsdf_sample_local(const Material *m, const Lobes *l, float3 wo, float u_lobe,
                              float u1, float u2, float u3, float3 *wi, float3 *weight,
                              float *pdf, int *kind)
{
    float p_glass = l->p_glass;
    if (l->p_diffuse + l->p_specular + l->p_metal + p_glass <= 0.0f)
        return false;
    if (u_lobe < l->p_diffuse) {
        *kind = LOBE_DIFFUSE;
        float2 d = concentric_disk(u1, u2);
        *wi = (float3)(d.x, d.y, sqrt(fmax(0.0f, 1.0f - d.x * d.x - d.y * d.y)));
    } else if (u_lobe < l->p_diffuse + l->p_specular + l->p_metal) {
        *kind = LOBE_GLOSSY;
        bool metal = u_lobe >= l->p_diffuse + l->p_specular;
        if (l->delta) {
            *wi = (float3)(-wo.x, -wo.y, wo.z);
            *pdf = 0.0f;
            if (metal)
                *weight = l->w_metal * metal_fresnel(m->base, wo.z) * l->metal_scale / l->p_metal;
            else {
                float F = fresnel_dielectric(wo.z, l->eta_specular);
                *weight = (float3)(l->w_dielectric * F / l->p_specular);
            }
            return true;
        }
        float3 h = sample_vndf(wo, l->alpha, u1, u2);
        *wi = 2.0f * kd_dot(wo, h) * h - wo;
        if (!(wi->z > 0.0f))
            return false;
    } else {
        float etap = l->eta_glass;
        float3 h = l->delta ? (float3)(0.0f, 0.0f, 1.0f) : sample_vndf(wo, l->alpha, u1, u2);
        float cos_oh = kd_dot(wo, h);
        float F = fresnel_dielectric(cos_oh, etap);
        bool reflect = u3 < F;
        if (reflect) {
            *kind = LOBE_GLOSSY;
            *wi = 2.0f * cos_oh * h - wo;
            if (!(wi->z > 0.0f))
                return false;
        } else {
            *kind = LOBE_TRANSMISSION;
            if (!refract_local(wo, h, etap, wi) || !(wi->z < 0.0f))
                return false;
        }
        if (l->delta) {
            *pdf = 0.0f;
            *weight = reflect ? (float3)(l->w_glass / p_glass)
                              : sqrt(m->base) * (l->w_glass / (p_glass * etap * etap));
            return true;
        }
    }
    float3 f = bsdf_eval_local(m, l, wo, *wi, pdf);
    if (!(*pdf > 0.0f))
        return false;
    *weight = f * (fabs(wi->z) / *pdf);
    return true;
}

// Power heuristic for one sample of strategy a against n_b samples of strategy b.
inline float mis_weight(float pdf_a, float pdf_b)
{
    float a = pdf_a * pdf_a, b = pdf_b * pdf_b;
    return a > 0.0f ? a / (a + b) : 0.0f;
}

// ---------------------------------------------------------------------------------------------
// The world

#ifdef HAS_WORLD_TEXTURE
// A direction in the texture's space -> uv of the projection (Cycles' conventions).
inline float2 world_uv(int projection, float3 d)
{
    if (projection == PROJECTION_MIRROR_BALL) {
        float dy = d.y - 1.0f;
        float div = 2.0f * sqrt(fmax(-0.5f * dy, 0.0f));
        float x = div > 0.0f ? d.x / div : d.x, z = div > 0.0f ? d.z / div : d.z;
        return (float2)(0.5f * (x + 1.0f), 0.5f * (z + 1.0f));
    }
    float u = 0.5f - atan2_poly(d.y, d.x) * (0.5f * M_1_PI_F);
    float v = 0.5f + atan2_poly(d.z, sqrt(d.x * d.x + d.y * d.y)) * M_1_PI_F;
    return (float2)(u, v);
}

// uv -> a unit direction in the texture's space; false outside a mirror ball's disk.
inline bool world_direction(int projection, float2 uv, float3 *d)
{
    if (projection == PROJECTION_MIRROR_BALL) {
        float x = 2.0f * uv.x - 1.0f, z = 2.0f * uv.y - 1.0f;
        float r2 = x * x + z * z;
        if (r2 > 1.0f)
            return false;
        float s = 2.0f * sqrt(1.0f - r2);
        *d = (float3)(s * x, 2.0f * r2 - 1.0f, s * z);
        return true;
    }
    float2 phi = sincos_poly(M_PI_F * (1.0f - 2.0f * uv.x));
    float2 elevation = sincos_poly(M_PI_F * (uv.y - 0.5f));
    *d = (float3)(elevation.y * phi.y, elevation.y * phi.x, elevation.x);
    return true;
}

// Solid angle of the texture's space per unit of uv at d (unit).
inline float world_jacobian(int projection, float3 d)
{
    return projection == PROJECTION_MIRROR_BALL ? 16.0f
                                                : 2.0f * M_PI_F * M_PI_F * sqrt(d.x * d.x + d.y * d.y);
}

inline float3 rows_times(__global const float4 *m, float3 v)
{
    return (float3)(kd_dot(m[0].xyz, v), kd_dot(m[1].xyz, v), kd_dot(m[2].xyz, v));
}

// The importance map: marginal CDF of the rows (height + 1), then each row's CDF (width + 1).
inline float env_cell_probability(const Scene *sc, int i, int j)
{
    __global const float4 *W = sc->world;
    int w = (int)WORLD_CDF_WIDTH(W), h = (int)WORLD_CDF_HEIGHT(W);
    __global const float *row = sc->env_cdf + (h + 1) + j * (w + 1);
    return (sc->env_cdf[j + 1] - sc->env_cdf[j]) * (row[i + 1] - row[i]);
}

// Largest k in [0, n) with cdf[k] <= u (cdf[0] = 0, cdf[n] = 1).
inline int cdf_find(__global const float *cdf, int n, float u)
{
    int lo = 0, hi = n;
    while (hi - lo > 1) {
        int mid = (lo + hi) >> 1;
        if (cdf[mid] <= u)
            lo = mid;
        else
            hi = mid;
    }
    return lo;
}
#endif

// What a ray leaving the scene in unit direction d sees.
inline float3 world_radiance(const Scene *sc, float3 d)
{
    float3 c = sc->world_color;
#ifdef HAS_WORLD_TEXTURE
    __global const float4 *W = sc->world;
    int tex = (int)WORLD_TEXTURE(W);
    if (tex >= 0) {
        int projection = (int)WORLD_PROJECTION(W);
        float3 dt = kd_normalize(rows_times(WORLD_TO_TEXTURE(W), d));
        float2 uv = world_uv(projection, dt);
        c *= texture_lookup(sc, tex, uv, WORLD_INTERPOLATION(W) == INTERPOLATION_CLOSEST).xyz;
    }
#endif
    return c;
}

#ifdef HAS_WORLD
// Whether direct light samples the world: only a world that varies with direction (an
// Environment Texture). A constant world is left to the BSDF rays, as Cycles leaves it
// ("Background MIS has been disabled"): for a colour a BSDF sample is the better of the two
// (cosine-distributed on a diffuse surface, against uniform over the sphere), so the light
// samples' shadow rays would add time, not much else.
inline bool world_light_sampled(const Scene *sc)
{
#ifdef HAS_WORLD_TEXTURE
    return (int)WORLD_TEXTURE(sc->world) >= 0;
#else
    return false;
#endif
}

// Density (solid angle) of world_sample choosing unit direction d; 0 where direct light does
// not sample the world (a BSDF ray that finds it then counts in full).
inline float world_pdf(const Scene *sc, float3 d)
{
#ifdef HAS_WORLD_TEXTURE
    __global const float4 *W = sc->world;
    if (world_light_sampled(sc)) {
        int projection = (int)WORLD_PROJECTION(W);
        int w = (int)WORLD_CDF_WIDTH(W), h = (int)WORLD_CDF_HEIGHT(W);
        float3 a = rows_times(WORLD_TO_TEXTURE(W), d);
        float la = kd_length(a);
        float3 dt = a / la;
        float2 uv = world_uv(projection, dt);
        uv = uv - floor(uv);
        int i = min((int)(uv.x * (float)w), w - 1), j = min((int)(uv.y * (float)h), h - 1);
        float jac = world_jacobian(projection, dt);
        if (!(jac > 0.0f))
            return 0.0f;
        // Texture space -> world: |det A| / |A d|^3 (the solid-angle Jacobian of d -> Ad/|Ad|).
        return env_cell_probability(sc, i, j) * (float)(w * h) / jac
               * (WORLD_DET(W) / (la * la * la));
    }
#endif
    return 0.0f;
}

#ifdef HAS_WORLD_TEXTURE
// A direction towards the world, importance-sampled from its texture (only where
// world_light_sampled); returns its radiance, *pdf its density.
inline float3 world_sample(const Scene *sc, float u1, float u2, float3 *wi, float *pdf)
{
    __global const float4 *W = sc->world;
    int projection = (int)WORLD_PROJECTION(W);
    int w = (int)WORLD_CDF_WIDTH(W), h = (int)WORLD_CDF_HEIGHT(W);
    __global const float *marginal = sc->env_cdf;
    int j = cdf_find(marginal, h, u1);
    float pj = marginal[j + 1] - marginal[j];
    __global const float *row = sc->env_cdf + (h + 1) + j * (w + 1);
    int i = cdf_find(row, w, u2);
    float pi = row[i + 1] - row[i];
    if (!(pj > 0.0f) || !(pi > 0.0f)) {
        *pdf = 0.0f;
        return (float3)(0.0f, 0.0f, 0.0f);
    }
    float2 uv = (float2)(((float)i + clamp((u2 - row[i]) / pi, 0.0f, 1.0f)) / (float)w,
                         ((float)j + clamp((u1 - marginal[j]) / pj, 0.0f, 1.0f)) / (float)h);
    float3 dt;
    if (!world_direction(projection, uv, &dt)) {
        *pdf = 0.0f;
        return (float3)(0.0f, 0.0f, 0.0f);
    }
    float3 d = rows_times(WORLD_FROM_TEXTURE(W), dt);
    float ld = kd_length(d);
    *wi = d / ld;
    float jac = world_jacobian(projection, dt);
    // |A wi| = 1 / |A^-1 dt|.
    *pdf = jac > 0.0f ? pj * pi * (float)(w * h) / jac * (WORLD_DET(W) * ld * ld * ld) : 0.0f;
    return world_radiance(sc, *wi);
}
#endif
#endif

// ---------------------------------------------------------------------------------------------
// Emissive triangles

#ifdef HAS_EMISSION
inline float triangle_area(const Scene *sc, uint tri, float3 *n)
{
    __global const float4 *corners = sc->tri_verts + TRIANGLE_SIZE * tri;
    float3 c = kd_cross(TRIANGLE_V1(corners) - TRIANGLE_V0(corners),
                     TRIANGLE_V2(corners) - TRIANGLE_V0(corners));
    float len = kd_length(c);
    *n = len > 0.0f ? c / len : (float3)(0.0f, 0.0f, 1.0f);
    return 0.5f * len;
}

// Density (solid angle) of emitter_sample choosing the point at distance `dist` on triangle
// tri whose normal makes cosine cos_l with the ray.
inline float emitter_pdf(const Scene *sc, uint tri, float dist, float cos_l)
{
    float3 n;
    float area = triangle_area(sc, tri, &n);
    float power = mean3(MATERIAL_EMISSION(sc->materials + MATERIAL_SIZE * sc->material_ids[tri])) * area;
    if (!(area > 0.0f) || !(cos_l > 0.0f) || !(sc->emitter_power > 0.0f))
        return 0.0f;
    return power / sc->emitter_power / area * (dist * dist / cos_l);
}

// A point on an emissive triangle (chosen by power with the alias table) seen from p. Returns
// its emitted radiance (0 when nothing), *wi, *dist, *pdf (solid angle) and *tri.
inline float3 emitter_sample(const Scene *sc, float3 p, float u0, float u1, float u2,
                             float3 *wi, float *dist, float *pdf, uint *tri)
{
    float x = u0 * (float)sc->emitter_count;
    uint k = min((uint)x, sc->emitter_count - 1u);
    __global const float4 *E = sc->emitters + EMITTER_SIZE * k;
    if (x - (float)k >= EMITTER_THRESHOLD(E))
        E = sc->emitters + EMITTER_SIZE * as_uint(EMITTER_ALIAS(E));
    *tri = as_uint(EMITTER_TRIANGLE(E));
    float pmf = EMITTER_PMF(E);
    __global const float4 *corners = sc->tri_verts + TRIANGLE_SIZE * *tri;
    float s = sqrt(u1);
    float b0 = 1.0f - s, b1 = u2 * s;
    float3 q = b0 * TRIANGLE_V0(corners) + b1 * TRIANGLE_V1(corners)
               + (1.0f - b0 - b1) * TRIANGLE_V2(corners);
    float3 n;
    float area = triangle_area(sc, *tri, &n);
    float3 to = q - p;
    float d2 = kd_dot(to, to);
    float d = sqrt(d2);
    if (!(d > 0.0f) || !(area > 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
    *wi = to / d;
    *dist = d;
    float cos_l = fabs(kd_dot(n, *wi));                   // emission is two-sided, as Cycles'
    if (!(cos_l > 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
    *pdf = pmf / area * (d2 / cos_l);
    Material m = material_at(sc, *tri, b1, 1.0f - b0 - b1);
    return m.emission * clamp(m.alpha, 0.0f, 1.0f);
}
#endif

// ---------------------------------------------------------------------------------------------
// Blender's lights

inline float smoothstep01(float x)
{
    x = clamp(x, 0.0f, 1.0f);
    return x * x * (3.0f - 2.0f * x);
}

inline float area_light_area(__global const float4 *L)
{
    float a = kd_length(LIGHT_AREA_U(L)) * kd_length(LIGHT_AREA_V(L));
    return LIGHT_AREA_SHAPE(L) == LIGHT_SHAPE_ELLIPSE ? a * M_PI_4_F : a;
}

// Sample a point on light l as seen from p: returns the irradiance at normal incidence (before
// the cosine at the surface and before shadowing); *wi the unit direction to it, *target the
// point (for local lights), *dist its distance (INFINITY for the sun) and *pdf the sample's
// density in solid angle for lights a BSDF ray can also hit (area lights, a sun with an
// angle), else 0 (no multiple importance sampling).
inline float3 sample_light(const Scene *sc, uint l, float3 p, float u1, float u2, float3 *wi,
                           float3 *target, float *dist, float *pdf)
{
    __global const float4 *L = sc->lights + LIGHT_SIZE * l;
    int kind = (int)LIGHT_KIND(L);
    *pdf = 0.0f;
    if (kind == LIGHT_SUN) {
#ifdef HAS_SUN
        float3 w = -LIGHT_DIRECTION(L);
#ifdef HAS_SOFT_LIGHTS
        float cos_half = LIGHT_SUN_COS_HALF_ANGLE(L);
        if (cos_half < 1.0f) {
            w = kd_normalize(uniform_cone(w, cos_half, u1, u2));
            *pdf = 1.0f / (2.0f * M_PI_F * (1.0f - cos_half));
        }
#endif
        *wi = w;
        *dist = INFINITY;
        *target = p;
        return LIGHT_INTENSITY(L);
#else
        return (float3)(0.0f, 0.0f, 0.0f);
#endif
    }
    float3 pos = LIGHT_POSITION(L);
    float emit = 1.0f;
    if (kind == LIGHT_AREA) {
#ifdef HAS_AREA
        float3 area_u = LIGHT_AREA_U(L), area_v = LIGHT_AREA_V(L);
        if (LIGHT_AREA_SHAPE(L) == LIGHT_SHAPE_ELLIPSE) {
            float2 d = concentric_disk(u1, u2);
            pos += 0.5f * d.x * area_u + 0.5f * d.y * area_v;
        } else {
            pos += (u1 - 0.5f) * area_u + (u2 - 0.5f) * area_v;
        }
#else
        return (float3)(0.0f, 0.0f, 0.0f);
#endif
    }
#ifdef HAS_SOFT_LIGHTS
    else if (LIGHT_RADIUS(L) > 0.0f) {
        // A sphere light seen from p: a disk facing p (uniform radiance: same irradiance as
        // the point while unoccluded), which gives soft shadows.
        float3 axis = kd_normalize(p - LIGHT_POSITION(L));
        float3 t, b;
        basis(axis, &t, &b);
        float2 d = concentric_disk(u1, u2);
        pos += LIGHT_RADIUS(L) * (d.x * t + d.y * b);
    }
#endif
    float3 to = pos - p;
    float dist2 = kd_dot(to, to);
    float dl = sqrt(dist2);
    if (!(dl > 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
    *wi = to / dl;
    *dist = dl;
    *target = pos;
    float cos_out = -kd_dot(*wi, LIGHT_DIRECTION(L));
#ifdef HAS_SPOT
    if (kind == LIGHT_SPOT) {
        // The cone is measured from the light's centre (Cycles: smoothstep over the blend).
        float3 from_centre = kd_normalize(p - LIGHT_POSITION(L));
        float c = kd_dot(from_centre, LIGHT_DIRECTION(L));
        float cos_half = LIGHT_SPOT_COS_HALF(L), smooth = LIGHT_SPOT_SMOOTH(L);
        emit = smooth > 0.0f ? smoothstep01((c - cos_half) * smooth) : (c > cos_half ? 1.0f : 0.0f);
    }
#endif
#ifdef HAS_AREA
    if (kind == LIGHT_AREA) {
        emit = fmax(cos_out, 0.0f);     // one-sided Lambertian emitter
        float area = area_light_area(L);
        *pdf = cos_out > 0.0f && area > 0.0f ? dist2 / (area * cos_out) : 0.0f;
    }
#endif
    return LIGHT_INTENSITY(L) * (emit / dist2);
}

#ifdef HAS_AREA
// The nearest area light that the ray (o, unit d) reaches on its emitting side before t_max:
// returns its radiance (0 when none), *t_light and *pdf (solid angle, as sample_light).
inline float3 area_light_hit(const Scene *sc, float3 o, float3 d, float t_max, float *pdf)
{
    float3 found = (float3)(0.0f, 0.0f, 0.0f);
    float best = t_max;
    *pdf = 0.0f;
    for (uint l = 0; l < sc->light_count; ++l) {
        __global const float4 *L = sc->lights + LIGHT_SIZE * l;
        if ((int)LIGHT_KIND(L) != LIGHT_AREA)
            continue;
        float3 n = LIGHT_DIRECTION(L);
        float denom = kd_dot(d, n);
        if (!(denom < 0.0f))
            continue;
        float t = kd_dot(LIGHT_POSITION(L) - o, n) / denom;
        if (!(t > 0.0f) || !(t < best))
            continue;
        float3 q = o + t * d - LIGHT_POSITION(L);
        float3 au = LIGHT_AREA_U(L), av = LIGHT_AREA_V(L);
        float a = kd_dot(q, au) / kd_dot(au, au), b = kd_dot(q, av) / kd_dot(av, av);
        bool inside = LIGHT_AREA_SHAPE(L) == LIGHT_SHAPE_ELLIPSE ? 4.0f * (a * a + b * b) <= 1.0f
                                                                 : fabs(a) <= 0.5f && fabs(b) <= 0.5f;
        float area = area_light_area(L);
        if (!inside || !(area > 0.0f))
            continue;
        best = t;
        found = LIGHT_INTENSITY(L) / area;
        *pdf = t * t / (area * -denom);
    }
    return found;
}
#endif

#if defined(HAS_SUN) && defined(HAS_SOFT_LIGHTS)
// Suns with an angle that a ray leaving the scene in unit direction d looks into: their
// radiance, with the MIS weight against a BSDF density pdf_bsdf (0: a mirror, weight 1).
inline float3 sun_disks(const Scene *sc, float3 d, float pdf_bsdf, float n_light)
{
    float3 sum = (float3)(0.0f, 0.0f, 0.0f);
    for (uint l = 0; l < sc->light_count; ++l) {
        __global const float4 *L = sc->lights + LIGHT_SIZE * l;
        float cos_half = LIGHT_SUN_COS_HALF_ANGLE(L);
        if ((int)LIGHT_KIND(L) != LIGHT_SUN || !(cos_half < 1.0f)
            || kd_dot(d, -LIGHT_DIRECTION(L)) < cos_half)
            continue;
        float pdf_l = 1.0f / (2.0f * M_PI_F * (1.0f - cos_half));
        float w = pdf_bsdf > 0.0f ? mis_weight(pdf_bsdf, n_light * pdf_l) : 1.0f;
        sum += LIGHT_INTENSITY(L) * (pdf_l * w);
    }
    return sum;
}
#endif

// ---------------------------------------------------------------------------------------------
// Shadow rays and direct light

// Visibility (0..1 per channel) from o along unit w up to `target` (or forever): opaque
// surfaces (glass too, as in Cycles) block; alpha cut-outs let 1 - alpha through; objects
// with Shadow ray visibility off let everything through.
inline float3 shadow(const Scene *sc, float3 o, float3 w, float dist, float3 target, uint ignore)
{
#if defined(HAS_ALPHA) || defined(HAS_VISIBILITY)
    float3 T = (float3)(1.0f, 1.0f, 1.0f);
    for (int k = 0; k < MAX_SHADOW_SURFACES; ++k) {
        float tmax = isinf(dist) ? INFINITY : dist * (1.0f - 0x1.0p-12f);
        Hit h;
        if (!trace(sc, o, w, 0.0f, tmax, false, ignore, &h))
            return T;
#ifdef HAS_VISIBILITY
        if (hit_visibility(sc, &h) & VISIBILITY_SHADOW) {
#endif
#ifdef HAS_ALPHA
            Material m = material_at(sc, h.tri, h.u, h.v);
            T *= 1.0f - clamp(m.alpha, 0.0f, 1.0f);
            if (all(T == 0.0f))
                return T;
#else
            return (float3)(0.0f, 0.0f, 0.0f);
#endif
#ifdef HAS_VISIBILITY
        }
#endif
        Surface s = surface_at(sc, &h, w);
        o = spawn(&s, w);
        ignore = h.key;
        if (!isinf(dist))
            dist = kd_length(target - o);
    }
    return (float3)(0.0f, 0.0f, 0.0f);
#else
    Hit h;
    float tmax = isinf(dist) ? INFINITY : dist * (1.0f - 0x1.0p-12f);
    return trace(sc, o, w, 0.0f, tmax, true, ignore, &h) ? (float3)(0.0f, 0.0f, 0.0f)
                                                         : (float3)(1.0f, 1.0f, 1.0f);
#endif
}

// A contribution clamped as Cycles does: the mean of its channels at most `limit` (0: none).
inline float3 clamp_sample(float3 c, float limit)
{
    float mean = mean3(c);
    return limit > 0.0f && mean > limit ? c * (limit / mean) : c;
}

// One light sample's contribution: BSDF x radiance-over-pdf x cosine x visibility x MIS.
inline float3 light_contribution(const Scene *sc, const Surface *s, const Material *m,
                                 const Lobes *lobes, const Frame *fr, float3 wo_l, float3 wi,
                                 float3 L, float dist, float3 target, float pdf_light,
                                 float n_light)
{
    float cos_geo = kd_dot(s->ng, wi);
    float3 wi_l = to_local(fr, wi);
    // The shading and the geometric normal must agree on the side wi leaves to.
    if (wi_l.z == 0.0f || (wi_l.z > 0.0f) != (cos_geo > 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
    float pdf_bsdf;
    float3 f = bsdf_eval_local(m, lobes, wo_l, wi_l, &pdf_bsdf);
    if (all(f == 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
#ifdef HAS_BOUNCES
    float w = pdf_light > 0.0f ? mis_weight(n_light * pdf_light, pdf_bsdf) : 1.0f;
#else
    float w = 1.0f;     // no BSDF rays: light samples alone
#endif
    float3 V = shadow(sc, spawn(s, wi), wi, dist, target, s->key);
    return f * L * (fabs(wi_l.z) * w) * V;
}

// Direct light at a surface: every Blender light (L x L samples for lights with an extent, one
// for the others; a pixel's samples of a light at a depth are points of one sequence), a
// textured world (world_light_sampled) and the emissive triangles (L x L each), weighted
// against the BSDF by the power heuristic. `beta` the path's throughput and `limit` the
// clamp, applied per sample.
inline float3 direct_light(const Scene *sc, const Surface *s, const Material *m,
                           const Lobes *lobes, const Frame *fr, float3 wo_l, float3 beta,
                           float limit, Rng *rng)
{
    float3 total = (float3)(0.0f, 0.0f, 0.0f);
    int n = sc->light_n;
    float inv_nn = 1.0f / (float)(n * n);
    for (uint l = 0; l < sc->light_count; ++l) {
        __global const float4 *L = sc->lights + LIGHT_SIZE * l;
        int kind = (int)LIGHT_KIND(L);
        bool extended = kind == LIGHT_AREA;
#ifdef HAS_SOFT_LIGHTS
        extended = extended || (kind == LIGHT_SUN ? LIGHT_SUN_COS_HALF_ANGLE(L) < 1.0f
                                                  : LIGHT_RADIUS(L) > 0.0f);
#endif
        int k = extended ? n : 1;
        float share = extended ? inv_nn : 1.0f;
        uint dim = rng_dim(rng, RNG_LIGHT, l);
        for (int j = 0; j < k * k; ++j) {
            float2 u = rng_2d_at(rng, dim, rng->sample * (uint)(k * k) + (uint)j);
            float3 wi, target;
            float dist, pdf_light;
            float3 E = sample_light(sc, l, s->p, u.x, u.y, &wi, &target, &dist, &pdf_light);
            if (all(E == 0.0f))
                continue;
            // E is radiance over the sample's density already.
            total += clamp_sample(beta * light_contribution(sc, s, m, lobes, fr, wo_l, wi, E,
                                                            dist, target, pdf_light,
                                                            (float)(k * k)) * share, limit);
        }
    }
#ifdef HAS_WORLD_TEXTURE
    uint world_dim = rng_dim(rng, RNG_WORLD, 0u);
    for (int j = 0; j < n * n && world_light_sampled(sc); ++j) {
        float2 u = rng_2d_at(rng, world_dim, rng->sample * (uint)(n * n) + (uint)j);
        float3 wi;
        float pdf;
        float3 L = world_sample(sc, u.x, u.y, &wi, &pdf);
        if (!(pdf > 0.0f) || all(L == 0.0f))
            continue;
        total += clamp_sample(beta * light_contribution(sc, s, m, lobes, fr, wo_l, wi, L / pdf,
                                                        INFINITY, s->p, pdf, (float)(n * n))
                              * inv_nn, limit);
    }
#endif
#ifdef HAS_EMISSION
    if (sc->emitter_count > 0) {
        uint emission_dim = rng_dim(rng, RNG_EMISSION, 0u);
        for (int j = 0; j < n * n; ++j) {
            float u0 = rng_next(rng);
            float2 u = rng_2d_at(rng, emission_dim, rng->sample * (uint)(n * n) + (uint)j);
            float3 wi;
            float dist, pdf;
            uint tri;
            float3 L = emitter_sample(sc, s->p, u0, u.x, u.y, &wi, &dist, &pdf, &tri);
            if (tri == s->tri || !(pdf > 0.0f) || all(L == 0.0f))
                continue;
            // The MIS weight uses the density a BSDF ray hitting tri sees (emitter_pdf).
            float3 n_l;
            triangle_area(sc, tri, &n_l);
            float pdf_mis = emitter_pdf(sc, tri, dist, fabs(kd_dot(n_l, wi)));
            float3 c = light_contribution(sc, s, m, lobes, fr, wo_l, wi, L / pdf, dist,
                                          s->p + dist * wi, pdf_mis, (float)(n * n));
            total += clamp_sample(beta * c * inv_nn, limit);
        }
    }
#endif
    return total;
}
