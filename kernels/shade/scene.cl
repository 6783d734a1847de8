// What the shading reads of a scene and a hit (docs/shading.md): the Scene (the kernel's
// buffers, filled in by render_samples in render.cl), the Material a hit's BSDF takes and the
// Surface point, a scene's one traversal call, the surface at a hit and the origin of a ray
// leaving it. Every optional part sits behind a HAS_<FEATURE> flag that
// core/scene/features.py derives from the scene, so a scene compiles only what it uses; the
// files after this one (slave/tracer.py KERNEL_FILES) build on these records.

// pbrt's gamma(7): relative error bound of a hit point from barycentrics (pbrt-v3 3.9.2), doubled.
#define HIT_ERROR (2.0f * 7.0f * 0x1.0p-24f / (1.0f - 7.0f * 0x1.0p-24f))

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
#ifdef HAS_CLOSURES
    float weight;                       // the closure's weight (MATERIAL_WEIGHT, or its program's)
#endif
#ifdef HAS_TRANSLUCENT
    float translucent;                  // the share of diffuse transmission
#endif
#ifdef HAS_COAT
    float coat_weight, coat_roughness, coat_ior;    // Principled's Coat
    float3 coat_tint;
#endif
} Material;

// What a node program knows of the ray beyond the hit's position and UVs (Cycles' ShaderData
// and path state): the unit direction back along the ray (Cycles' I), the shading normal its
// nodes read (Cycles' N: the smooth normal facing the ray), whether the ray hit the back.
// With LIGHT_PATH also the ray's PATH_<KIND> bits (Cycles' path flags), its length to the hit
// and the path's depths before it (Cycles' bounce counts).
typedef struct {
    float3 incoming, normal, ng;
    bool backfacing;
#ifdef HAS_LIGHT_PATH
    uint path;
    float length;
    int bounce, diffuse, glossy, transmission, transparent;
#endif
} ShadeInfo;

// A surface point: position, its error bound, the geometric normal facing the incoming ray,
// the shading normal on the same side, and whether the ray hit the front (winding) side.
typedef struct {
    float3 p, err, ng, ns;
    bool front;
    uint tri;
    uint key;                           // the hit's key (Hit.key): what a ray leaving it ignores
    float u, v;
} Surface;

// Fresnel reflectance of a dielectric interface (unpolarised); eta = n_transmitted / n_incident
// (the BSDF, bsdf.cl, and the coat's attenuation of what lies below it, material.cl).
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
