// Materials (a Principled BSDF subset), textures, lights and shadow rays (docs/shading.md).
// Every optional part sits behind a HAS_<FEATURE> flag that core/scene/features.py derives from the
// scene, so a scene compiles only what it uses.
//
// The material and light buffers hold the MATERIAL and LIGHT records of the layout header
// (core/layout.py; packed by slave/buffers.py), read here through its names.

#define MAX_SHADOW_SURFACES 16
// pbrt's gamma(7): relative error bound of a hit point from barycentrics (pbrt-v3 3.9.2), doubled.
#define HIT_ERROR (2.0f * 7.0f * 0x1.0p-24f / (1.0f - 7.0f * 0x1.0p-24f))

#ifndef MIRROR_ROUGHNESS
#define MIRROR_ROUGHNESS 0.1f
#endif

typedef struct {
    KdTree kd;                          // the compact kd-tree (trace.cl)
    __global const float4 *tri_verts;
    __global const ushort *material_ids;
    __global const float4 *materials;
    __global const float4 *lights;
    __global const float *normals;      // (3T, 3) when HAS_SMOOTH
    __global const float *uvs;          // (3T, 2) when HAS_TEXTURES
    __global const half *texels;        // (N, 4) when HAS_TEXTURES
    __global const uint *tex_sizes;     // (K, 3) when HAS_TEXTURES
    uint light_count;
    int light_n;                        // light samples per axis
} Scene;

typedef struct {
    float3 base;
    float alpha;
    float metallic, roughness, transmission, ior;
    float3 emission;
    float specular;
} Material;

// A surface point: position, its error bound, the geometric normal facing the incoming ray,
// the shading normal on the same side, and whether the ray hit the front (winding) side.
typedef struct {
    float3 p, err, ng, ns;
    bool front;
    uint tri;
    float u, v;
} Surface;

inline bool trace(const Scene *sc, float3 o, float3 d, float tmin, float tmax, bool any_hit,
                  uint ignore, Hit *h)
{
    Ray r = make_ray(o, d);
    return trace_ray(&r, tmin, tmax, any_hit, ignore, &sc->kd, sc->tri_verts, h);
}

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
    float3 n = cross(v1 - v0, v2 - v0);
    float len = length(n);
    n = len > 0.0f && isfinite(len) ? n / len : -normalize(d);   // slivers: face the ray
    s.front = dot(n, d) < 0.0f;
    s.ng = s.front ? n : -n;
    s.ns = s.ng;
#ifdef HAS_SMOOTH
    float3 n0 = vload3(3 * tri, sc->normals), n1 = vload3(3 * tri + 1, sc->normals);
    float3 n2 = vload3(3 * tri + 2, sc->normals);
    float3 ns = b0 * n0 + h->u * n1 + h->v * n2;
    float ls = length(ns);
    if (ls > 0.0f && isfinite(ls)) {
        ns = ns / ls;
        if (!s.front)
            ns = -ns;
        // Interpolated normals may face away from the ray at grazing angles: keep them usable.
        if (dot(ns, -d) > 0.0f)
            s.ns = ns;
    }
#endif
    s.tri = tri;
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
    float d = dot(fabs(n), err) + HIT_ERROR * fmax(fmax(a.x, a.y), a.z) + 0x1.0p-100f;
    float3 off = d * n;
    float3 po = p + off;
    po.x = off.x > 0.0f ? nextafter(po.x, INFINITY) : (off.x < 0.0f ? nextafter(po.x, -INFINITY) : po.x);
    po.y = off.y > 0.0f ? nextafter(po.y, INFINITY) : (off.y < 0.0f ? nextafter(po.y, -INFINITY) : po.y);
    po.z = off.z > 0.0f ? nextafter(po.z, INFINITY) : (off.z < 0.0f ? nextafter(po.z, -INFINITY) : po.z);
    return po;
}

// Origin for a ray leaving `s` in direction w (to the side of ng that w goes to).
inline float3 spawn(const Surface *s, float3 w)
{
    return offset_origin(s->p, s->err, dot(w, s->ng) >= 0.0f ? s->ng : -s->ng);
}

#ifdef HAS_TEXTURES
inline float4 texel(const Scene *sc, uint offset, int w, int x, int y)
{
    return vload_half4(offset + (uint)(y * w + x), sc->texels);
}

// Bilinear lookup, repeat wrap; uv (0, 0) is the first texel (Blender's bottom-left).
inline float4 texture_lookup(const Scene *sc, int tex, float2 uv)
{
    __global const uint *size = sc->tex_sizes + TEXTURE_SIZE_COLUMNS * tex;
    uint offset = size[TEXTURE_SIZE_OFFSET];
    int w = (int)size[TEXTURE_SIZE_WIDTH], h = (int)size[TEXTURE_SIZE_HEIGHT];
    uv = uv - floor(uv);                               // [0, 1), also for huge uv
    float x = uv.x * (float)w - 0.5f, y = uv.y * (float)h - 0.5f;
    float fx = floor(x), fy = floor(y);
    float tx = x - fx, ty = y - fy;
    int x0 = (int)fx, y0 = (int)fy;
    int x1 = x0 + 1, y1 = y0 + 1;
    x0 = x0 < 0 ? w - 1 : (x0 >= w ? 0 : x0);
    y0 = y0 < 0 ? h - 1 : (y0 >= h ? 0 : y0);
    x1 = x1 >= w ? 0 : x1;
    y1 = y1 >= h ? 0 : y1;
    float4 c00 = texel(sc, offset, w, x0, y0), c10 = texel(sc, offset, w, x1, y0);
    float4 c01 = texel(sc, offset, w, x0, y1), c11 = texel(sc, offset, w, x1, y1);
    return (1.0f - ty) * ((1.0f - tx) * c00 + tx * c10) + ty * ((1.0f - tx) * c01 + tx * c11);
}
#endif

inline Material material_at(const Scene *sc, uint tri, float u, float v)
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
#ifdef HAS_TEXTURES
    int tex = (int)MATERIAL_TEXTURE(M);
    if (tex >= 0) {
        float2 uv = (1.0f - u - v) * vload2(3 * tri, sc->uvs) + u * vload2(3 * tri + 1, sc->uvs)
                    + v * vload2(3 * tri + 2, sc->uvs);
        float4 c = texture_lookup(sc, tex, uv);
        m.base *= c.xyz;
        if (MATERIAL_TEXTURE_ALPHA(M) > 0.0f)
            m.alpha *= c.w;
    }
#endif
    return m;
}

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

// F0 of the dielectric specular layer: ((ior - 1) / (ior + 1))^2 scaled by Blender's
// "Specular IOR Level" (0.5 = as the IOR says).
inline float dielectric_f0(const Material *m)
{
    float r = (m->ior - 1.0f) / (m->ior + 1.0f);
    return fmin(r * r * 2.0f * m->specular, 1.0f);
}

inline float pow5(float x)
{
    float x2 = x * x;
    return x2 * x2 * x;
}

// The non-delta part of the BSDF (times nothing: the caller multiplies by cos_in and light):
// Lambertian diffuse, and a GGX highlight for roughness >= MIRROR_ROUGHNESS.
inline float3 eval_bsdf(const Material *m, float3 ns, float3 wo, float3 wi)
{
    float f0 = dielectric_f0(m);
    float diffuse_w = (1.0f - m->metallic) * (1.0f - m->transmission) * (1.0f - f0);
    float3 f = m->base * (diffuse_w * M_1_PI_F);
#ifdef HAS_SPECULAR
    if (m->roughness >= MIRROR_ROUGHNESS) {
        float spec_w = m->metallic + (1.0f - m->metallic) * (1.0f - m->transmission)
                       * (m->specular > 0.0f ? 1.0f : 0.0f);
        if (spec_w > 0.0f) {
            float cos_o = dot(ns, wo), cos_i = dot(ns, wi);
            if (cos_o > 0.0f && cos_i > 0.0f) {
                float3 hv = normalize(wo + wi);
                float a = m->roughness * m->roughness;
                float a2 = a * a;
                float ch = fmax(dot(ns, hv), 0.0f);
                float den = ch * ch * (a2 - 1.0f) + 1.0f;
                float D = a2 / (M_PI_F * den * den);
                float g_o = 2.0f * cos_o / (cos_o + sqrt(a2 + (1.0f - a2) * cos_o * cos_o));
                float g_i = 2.0f * cos_i / (cos_i + sqrt(a2 + (1.0f - a2) * cos_i * cos_i));
                float3 F0 = m->metallic * m->base + (1.0f - m->metallic) * (1.0f - m->transmission) * f0;
                float3 F = F0 + (spec_w - F0) * pow5(1.0f - fmax(dot(wo, hv), 0.0f));
                f += F * (D * g_o * g_i / (4.0f * cos_o * cos_i));
            }
        }
    }
#endif
    return f;
}

inline float smoothstep01(float x)
{
    x = clamp(x, 0.0f, 1.0f);
    return x * x * (3.0f - 2.0f * x);
}

// Sample a point on light l as seen from p: returns the irradiance at normal incidence (before
// the cosine at the surface and before shadowing); *wi the unit direction to it, *target the
// point (for local lights) and *dist its distance (INFINITY for the sun).
inline float3 sample_light(const Scene *sc, uint l, float3 p, float u1, float u2, float3 *wi,
                           float3 *target, float *dist)
{
    __global const float4 *L = sc->lights + LIGHT_SIZE * l;
    int kind = (int)LIGHT_KIND(L);
    if (kind == LIGHT_SUN) {
#ifdef HAS_SUN
        float3 w = -LIGHT_DIRECTION(L);
#ifdef HAS_SOFT_LIGHTS
        if (LIGHT_SUN_COS_HALF_ANGLE(L) < 1.0f)
            w = normalize(uniform_cone(w, LIGHT_SUN_COS_HALF_ANGLE(L), u1, u2));
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
        float3 axis = normalize(p - LIGHT_POSITION(L));
        float3 t, b;
        basis(axis, &t, &b);
        float2 d = concentric_disk(u1, u2);
        pos += LIGHT_RADIUS(L) * (d.x * t + d.y * b);
    }
#endif
    float3 to = pos - p;
    float dist2 = dot(to, to);
    float dl = sqrt(dist2);
    if (!(dl > 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
    *wi = to / dl;
    *dist = dl;
    *target = pos;
    float cos_out = -dot(*wi, LIGHT_DIRECTION(L));
#ifdef HAS_SPOT
    if (kind == LIGHT_SPOT) {
        // The cone is measured from the light's centre (Cycles: smoothstep over the blend).
        float3 from_centre = normalize(p - LIGHT_POSITION(L));
        float c = dot(from_centre, LIGHT_DIRECTION(L));
        float cos_half = LIGHT_SPOT_COS_HALF(L), smooth = LIGHT_SPOT_SMOOTH(L);
        emit = smooth > 0.0f ? smoothstep01((c - cos_half) * smooth) : (c > cos_half ? 1.0f : 0.0f);
    }
#endif
#ifdef HAS_AREA
    if (kind == LIGHT_AREA)
        emit = fmax(cos_out, 0.0f);     // one-sided Lambertian emitter
#endif
    return LIGHT_INTENSITY(L) * (emit / dist2);
}

// How much light a surface lets through to a shadow ray: cut-out alpha and (for transmissive
// materials) the unrefracted transmission (1 - Fresnel) tinted by the base colour. Exact for
// IOR 1; for other IORs the shadow is lighter than a caustic-free one (docs/shading.md).
inline float3 surface_transmittance(const Scene *sc, const Hit *h, float3 w)
{
    Material m = material_at(sc, h->tri, h->u, h->v);
    float3 through = (float3)(0.0f, 0.0f, 0.0f);
#ifdef HAS_TRANSMISSION
    if (m.transmission > 0.0f) {
        __global const float4 *corners = sc->tri_verts + TRIANGLE_SIZE * h->tri;
        float3 v0 = TRIANGLE_V0(corners), v1 = TRIANGLE_V1(corners), v2 = TRIANGLE_V2(corners);
        float3 n = normalize(cross(v1 - v0, v2 - v0));
        float c = dot(n, w);
        bool front = c < 0.0f;
        float F = fresnel_dielectric(fabs(c), front ? m.ior : 1.0f / m.ior);
        through = m.base * ((1.0f - m.metallic) * m.transmission * (1.0f - F));
    }
#endif
    float alpha = clamp(m.alpha, 0.0f, 1.0f);
    return (1.0f - alpha) + alpha * through;
}

// Visibility (0..1 per channel) from o along unit w up to `target` (or forever for the sun).
inline float3 shadow(const Scene *sc, float3 o, float3 w, float dist, float3 target, uint ignore)
{
#if defined(HAS_TRANSMISSION) || defined(HAS_ALPHA)
    float3 T = (float3)(1.0f, 1.0f, 1.0f);
    for (int k = 0; k < MAX_SHADOW_SURFACES; ++k) {
        float tmax = isinf(dist) ? INFINITY : dist * (1.0f - 0x1.0p-12f);
        Hit h;
        if (!trace(sc, o, w, 0.0f, tmax, false, ignore, &h))
            return T;
        T *= surface_transmittance(sc, &h, w);
        if (all(T == 0.0f))
            return T;
        Surface s = surface_at(sc, &h, w);
        o = spawn(&s, w);
        ignore = h.tri;
        if (!isinf(dist))
            dist = length(target - o);
    }
    return (float3)(0.0f, 0.0f, 0.0f);
#else
    Hit h;
    float tmax = isinf(dist) ? INFINITY : dist * (1.0f - 0x1.0p-12f);
    return trace(sc, o, w, 0.0f, tmax, true, ignore, &h) ? (float3)(0.0f, 0.0f, 0.0f)
                                                         : (float3)(1.0f, 1.0f, 1.0f);
#endif
}

// Direct light at a surface from every light: L x L stratified samples for lights with an
// extent (area, soft point/spot/sun), one for the others.
inline float3 direct_light(const Scene *sc, const Surface *s, const Material *m, float3 wo,
                           Rng *rng)
{
    float3 total = (float3)(0.0f, 0.0f, 0.0f);
    for (uint l = 0; l < sc->light_count; ++l) {
        __global const float4 *L = sc->lights + LIGHT_SIZE * l;
        int kind = (int)LIGHT_KIND(L);
        bool extended = kind == LIGHT_AREA;
#ifdef HAS_SOFT_LIGHTS
        extended = extended || (kind == LIGHT_SUN ? LIGHT_SUN_COS_HALF_ANGLE(L) < 1.0f
                                                  : LIGHT_RADIUS(L) > 0.0f);
#endif
        int n = extended ? sc->light_n : 1;
        float3 sum = (float3)(0.0f, 0.0f, 0.0f);
        for (int j = 0; j < n * n; ++j) {
            float u1 = ((float)(j % n) + rng_next(rng)) / (float)n;
            float u2 = ((float)(j / n) + rng_next(rng)) / (float)n;
            float3 wi, target;
            float dist;
            float3 E = sample_light(sc, l, s->p, u1, u2, &wi, &target, &dist);
            if (all(E == 0.0f))
                continue;
            float cos_in = dot(s->ns, wi);
            if (!(cos_in > 0.0f) || !(dot(s->ng, wi) > 0.0f))
                continue;
            float3 f = eval_bsdf(m, s->ns, wo, wi);
            if (all(f == 0.0f))
                continue;
            float3 V = shadow(sc, spawn(s, wi), wi, dist, target, s->tri);
            sum += f * E * (cos_in * V);
        }
        total += sum / (float)(n * n);
    }
    return total;
}
