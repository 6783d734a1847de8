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

#ifdef HAS_COAT
// What Cycles' Principled passes to the layers below its Coat seen at cosine cos_o: 1 - the
// coat's albedo (its weight x the dielectric Fresnel at cos_o: closure_layering_weight with
// Cycles' smooth-surface estimate of a dielectric's albedo), times the tint over the path
// through the coat (Beer's law: tint^(1 / cos of the refracted ray), blended by the weight).
inline float3 coat_below(const Material *m, float cos_o)
{
    float weight = clamp(m->coat_weight, 0.0f, 1.0f), eta = fmax(m->coat_ior, 1.0f);
    cos_o = clamp(cos_o, 0.0f, 1.0f);
    float3 below = (float3)(clamp(1.0f - weight * fresnel_dielectric(cos_o, eta), 0.0f, 1.0f));
    if (any(m->coat_tint != 1.0f)) {
        float cos_t = sqrt(1.0f - (1.0f - cos_o * cos_o) / (eta * eta));
        float3 tint = fmax(m->coat_tint, 0.0f);
        below *= 1.0f + weight * (pow(tint, 1.0f / cos_t) - 1.0f);
    }
    return below;
}
#endif

// The closure in MATERIAL record M of triangle `tri` at barycentrics (u, v); `s`: the surface
// point where the shading normal matters (a node program's Normal output sets s->ns), else 0;
// `info`: the ray's view of the hit for the nodes that read it (Fresnel, Layer Weight), or 0.
inline Material material_record(const Scene *sc, __global const float4 *M, uint tri, float u,
                                float v, Surface *s, const ShadeInfo *info)
{
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
#ifdef HAS_CLOSURES
    m.weight = MATERIAL_WEIGHT(M);
#endif
#ifdef HAS_TRANSLUCENT
    m.translucent = MATERIAL_TRANSLUCENT(M);
#endif
#ifdef HAS_COAT
    m.coat_weight = MATERIAL_COAT_WEIGHT(M);
    m.coat_roughness = MATERIAL_COAT_ROUGHNESS(M);
    m.coat_ior = MATERIAL_COAT_IOR(M);
    m.coat_tint = MATERIAL_COAT_TINT(M);
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
        run_nodes(sc, program, tri, (float2)(u, v), uv, p, s, info, &m);
    }
#endif
#ifdef HAS_COAT
    // Cycles attenuates the emission under the coat as the layers below (coat_below).
    if (info && m.coat_weight > 0.0f)
        m.emission *= coat_below(&m, kd_dot(info->incoming, info->normal));
#endif
    return m;
}

// The material of triangle `tri` (its first closure) at barycentrics (u, v); `s` as above.
inline Material material_eval(const Scene *sc, uint tri, float u, float v, Surface *s,
                              const ShadeInfo *info)
{
    uint id = sc->material_ids[tri];
    return material_record(sc, sc->materials + MATERIAL_SIZE * id, tri, u, v, s, info);
}

// The material where the shading normal does not matter (emitters, shadow rays' alpha).
inline Material material_at(const Scene *sc, uint tri, float u, float v)
{
    return material_eval(sc, tri, u, v, 0, 0);
}

#ifdef HAS_CLOSURES
// What a material's closures add up to at a hit (docs/shading.md, Closures).
typedef struct {
    float3 emission;        // the closures' emission x weight (x alpha)
    float3 transparency;    // Transparent closures' colour x weight, and 1 - alpha x weight
    float holdout;          // the Holdout closures' weight
    float scatter;          // the scattering closures' weight (x alpha)
} ClosureSum;

// Every closure of triangle `tri`'s material at (u, v) summed into *sum, and the one scattering
// closure chosen with probability weight / sum->scatter by u_pick in [0, 1) (one number for
// the whole choice: it is rescaled at each closure, as a weighted reservoir). The chosen
// closure's shading normal is left in s->ns. Without a scattering closure: the first closure.
inline Material closures_eval(const Scene *sc, uint tri, float u, float v, Surface *s,
                              const ShadeInfo *info, float u_pick, ClosureSum *sum)
{
    __global const float4 *M = sc->materials + MATERIAL_SIZE * sc->material_ids[tri];
    int n = clamp((int)MATERIAL_CLOSURES(M), 1, CLOSURES_MAX);
    float3 zero = (float3)(0.0f, 0.0f, 0.0f);
    sum->emission = zero;
    sum->transparency = zero;
    sum->holdout = 0.0f;
    sum->scatter = 0.0f;
    float3 ns = s ? s->ns : zero, chosen_ns = ns;
    Material chosen;
    for (int k = 0; k < n; ++k, M += MATERIAL_SIZE) {
        if (s)
            s->ns = ns;
        Material m = material_record(sc, M, tri, u, v, s, info);
        if (k == 0)
            chosen = m;
        int kind = (int)MATERIAL_KIND(M);
        float w = fmax(m.weight, 0.0f), a = clamp(m.alpha, 0.0f, 1.0f);
        if (kind == CLOSURE_TRANSPARENT) {
            sum->transparency += w * m.base;
            continue;
        }
        if (kind == CLOSURE_HOLDOUT) {
            sum->holdout += w;
            continue;
        }
        sum->emission += (w * a) * m.emission;
        if (kind != CLOSURE_PRINCIPLED)
            continue;
        sum->transparency += w * (1.0f - a);
        float ws = w * a;
        if (!(ws > 0.0f))
            continue;
        sum->scatter += ws;
        float p = ws / sum->scatter;
        if (u_pick < p) {
            chosen = m;
            chosen_ns = s ? s->ns : zero;
            u_pick = u_pick / p;
        } else {
            u_pick = (u_pick - p) / (1.0f - p);
        }
    }
    if (s)
        s->ns = chosen_ns;
    return chosen;
}
#endif

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

#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
// After a node program set s->ns (it was ns): tilted as Cycles tilts a normal that would
// reflect the ray of direction d below the surface, and ns again where it faces away.
inline void settle_normal(Surface *s, float3 d, float3 ns)
{
    if (any(s->ns != ns))
        s->ns = valid_reflection_normal(s->ng, -kd_normalize(d), s->ns);
    if (!(kd_dot(s->ns, d) < 0.0f))
        s->ns = ns;
}
#endif

// The material where a ray of direction d hit s (`info`: the ray's view of it). Normal Map
// and Bump nodes set s->ns (settle_normal).
inline Material surface_material(const Scene *sc, Surface *s, float3 d, const ShadeInfo *info)
{
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
    float3 ns = s->ns;
    Material m = material_eval(sc, s->tri, s->u, s->v, s, info);
    settle_normal(s, d, ns);
    return m;
#else
    return material_eval(sc, s->tri, s->u, s->v, 0, info);
#endif
}

#ifdef HAS_CLOSURES
// surface_material for a material of closures: their sum in *sum, the scattering closure
// u_pick chooses returned (closures_eval), its shading normal in s->ns.
inline Material surface_closures(const Scene *sc, Surface *s, float3 d, const ShadeInfo *info,
                                 float u_pick, ClosureSum *sum)
{
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
    float3 ns = s->ns;
    Material m = closures_eval(sc, s->tri, s->u, s->v, s, info, u_pick, sum);
    settle_normal(s, d, ns);
    return m;
#else
    return closures_eval(sc, s->tri, s->u, s->v, 0, info, u_pick, sum);
#endif
}
#endif

// What a node program sees of a ray of direction d that hit s.
inline ShadeInfo shade_info(const Surface *s, float3 d)
{
    ShadeInfo info;
    info.incoming = -kd_normalize(d);
    info.normal = s->ns;
    info.ng = s->ng;
    info.backfacing = !s->front;
#ifdef HAS_LIGHT_PATH
    info.path = 0u;         // (the caller says what kind of ray it is)
    info.length = 0.0f;
    info.bounce = info.diffuse = info.glossy = info.transmission = info.transparent = 0;
#endif
    return info;
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
