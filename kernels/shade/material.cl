// The material at a hit (docs/shading.md, Materials): its MATERIAL record (core/layout.py,
// packed by slave/buffers.py), its image texture and node program, the shading normal that
// Normal Map and Bump nodes set, and the rays that see it (ray visibility, holdouts).

#if defined(HAS_TEXTURES) || defined(HAS_NODES)
// The texture coordinates of triangle `tri` at barycentrics (u, v).
inline float2 hit_uv(const Scene *sc, uint tri, float u, float v)
{
    return (1.0f - u - v) * vload2(3 * tri, sc->uvs) + u * vload2(3 * tri + 1, sc->uvs)
           + v * vload2(3 * tri + 2, sc->uvs);
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
        float2 uv = hit_uv(sc, tri, u, v);
        float4 c = texture_lookup(sc, tex, uv, false);
        m.base *= c.xyz;
        if (MATERIAL_TEXTURE_ALPHA(M) > 0.0f)
            m.alpha *= c.w;
    }
#endif
#ifdef HAS_NODES
    int program = (int)MATERIAL_PROGRAM(M);
    if (program >= 0) {
        float2 uv = hit_uv(sc, tri, u, v);
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
