// The path tracer (docs/shading.md, What is rendered): shadow rays, direct light from every
// light with multiple importance sampling, and trace_path, one path from the camera through
// its bounces under the Light Paths limits; render.cl runs it for a tile's pixels.

// Surfaces a shadow ray passes through (cut-outs, objects shadow rays do not see), at most.
#define MAX_SHADOW_SURFACES 16
// Surfaces a ray passes because its kind of ray does not see them (ray visibility).
#define MAX_UNSEEN_SURFACES 64

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
#if defined(HAS_ALPHA) && defined(HAS_CLOSURES)
            // A material of closures lets through its transparency (Transparent closures'
            // colour, Principled's 1 - alpha), as Cycles' transparent shadows.
            Surface at = surface_at(sc, &h, w);
            ShadeInfo info = shade_info(&at, w);
#ifdef HAS_LIGHT_PATH
            info.path = PATH_SHADOW;
            info.length = h.t;
#endif
            ClosureSum cs;
            closures_eval(sc, h.tri, h.u, h.v, 0, &info, 0.5f, &cs);
            T *= clamp(cs.transparency, 0.0f, 1.0f);
            if (all(T == 0.0f))
                return T;
#elif defined(HAS_ALPHA) && defined(HAS_NODES)
            Surface at = surface_at(sc, &h, w);
            ShadeInfo info = shade_info(&at, w);
#ifdef HAS_LIGHT_PATH
            info.path = PATH_SHADOW;
            info.length = h.t;
#endif
            Material m = material_eval(sc, h.tri, h.u, h.v, 0, &info);
            T *= 1.0f - clamp(m.alpha, 0.0f, 1.0f);
            if (all(T == 0.0f))
                return T;
#elif defined(HAS_ALPHA)
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

// ---------------------------------------------------------------------------------------------
// Paths

#ifdef HAS_EMISSION
// The weight of emission that a BSDF ray of density pdf_prev (0: a camera ray or a mirror)
// found at hit h against the emissive triangles' light samples.
inline float emission_mis(const Scene *sc, const Hit *h, float3 d, float pdf_prev, float n_light)
{
    float w = 1.0f;
    if (pdf_prev > 0.0f) {
        float3 n_l;
        triangle_area(sc, h->tri, &n_l);
        float len = kd_length(d), dist = h->t * len;
        w = mis_weight(pdf_prev, n_light * emitter_pdf(sc, h->tri, dist,
                                                       fabs(kd_dot(n_l, d)) / len));
    }
    return w;
}
#endif

// The ray goes on behind the surface it hit (a cut-out, an object it does not see), not a
// bounce; the camera ray keeps its clipping range and the distance it has travelled.
inline void go_behind(const Surface *s, const Hit *h, float3 d, bool primary, float3 *o,
                      uint *ignore, float *t_before, float *tmin, float *tmax)
{
    *o = spawn(s, d);
    *ignore = h->key;
    if (primary) {
        *t_before += h->t;
        *tmin = fmax(*tmin - h->t, 0.0f);
        *tmax -= h->t;
    }
}

// The bounce limits of a path (RenderSettings' Light Paths) and its clamping.
typedef struct {
    int max_bounces, diffuse, glossy, transmission, transparent;
    float clamp_direct, clamp_indirect;
    float filter_glossy;     // Cycles' Filter Glossy (0: off)
} PathLimits;

// One path from the camera. *depth and *normal get the first opaque surface (1e10 / 0 on a
// miss). At each surface: its emission and direct light from every light, the world and the
// emissive triangles (multiple importance sampling against the BSDF), then one BSDF sample to
// continue. A path that reaches a bounce limit still traces its last BSDF ray to collect the
// light it hits (as Cycles), so direct light is complete with any limit. `film` collects the
// frame's other passes (film.cl).
inline float3 trace_path(const Scene *sc, __global const float4 *cam, float3 o, float3 d,
                         Rng *rng, const PathLimits *limits, float *depth, float3 *normal,
                         float *alpha, Film *film)
{
    float3 radiance = (float3)(0.0f, 0.0f, 0.0f), beta = (float3)(1.0f, 1.0f, 1.0f);
    float along = kd_dot(d, CAMERA_VIEW_AXIS(cam));     // view-axis distance per unit of t
    float tmin = CAMERA_CLIP_START(cam) / along, tmax = CAMERA_CLIP_END(cam) / along;
    float t_before = 0.0f;
    uint ignore = NO_HIT;
    bool primary = true;     // still the camera ray (through cut-outs)
    bool last = false;       // a limit is reached: collect what the ray hits, then stop
    float pdf_prev = 0.0f;   // density of the BSDF sample that made this ray; 0: camera/mirror
    float min_pdf = INFINITY;    // the least density of the path's BSDF samples (Filter Glossy)
    int bounces = 0, diffuse = 0, glossy = 0, transmission = 0, transparent = 0;
    float n_light = (float)(sc->light_n * sc->light_n);
#ifdef HAS_VISIBILITY
    uint ray_kind = VISIBILITY_CAMERA;     // the kind of ray, as objects' ray visibility names it
    int unseen = 0;                        // surfaces passed because the ray does not see them
#endif
#ifdef HAS_LIGHT_PATH
    uint path_kind = PATH_CAMERA;          // the kind of ray, as the Light Path node names it
#endif
    *depth = 1e10f;
    *normal = (float3)(0.0f, 0.0f, 0.0f);
    *alpha = 1.0f;
    while (true) {
        // Clamping as Cycles: light that a ray finds counts for the surface that sent it
        // (direct light when that is the first surface), direct light of this surface for it.
        float limit_found = bounces <= 1 ? limits->clamp_direct : limits->clamp_indirect;
        float limit = bounces == 0 ? limits->clamp_direct : limits->clamp_indirect;
        Hit h;
        bool hit = trace(sc, o, d, tmin, tmax, false, ignore, &h);
#ifdef HAS_AREA
        // Area lights are seen by reflections and refractions, not by the camera (Cycles'
        // default ray visibility of lights).
        if (!primary) {
            float pdf_l;
            float3 Le = area_light_hit(sc, o, d, hit ? h.t : INFINITY, &pdf_l);
            if (any(Le != 0.0f)) {
                float w = pdf_prev > 0.0f ? mis_weight(pdf_prev, n_light * pdf_l) : 1.0f;
                float3 found = clamp_sample(beta * Le * w, limit_found);
                radiance += found;
                film_light(film, found, false);
                break;
            }
        }
#endif
        if (!hit) {
#ifdef HAS_TRANSPARENT_FILM
            if (primary) {          // Film > Transparent: the camera sees no world
#ifdef HAS_CLOSURES
                *alpha = fmax(*alpha - mean3(beta), 0.0f);  // what transparency let through
#else
                *alpha = 0.0f;
#endif
                break;
            }
#endif
            d = kd_normalize(d);
            float3 Le = world_radiance(sc, d);
#ifdef HAS_WORLD
            if (pdf_prev > 0.0f)
                Le *= mis_weight(pdf_prev, n_light * world_pdf(sc, d));
#endif
#if defined(HAS_SUN) && defined(HAS_SOFT_LIGHTS)
            if (!primary)
                Le += sun_disks(sc, d, pdf_prev, n_light);
#endif
            float3 found = clamp_sample(beta * Le, limit_found);
            radiance += found;
            film_light(film, found, false);
            break;
        }
        Surface s = surface_at(sc, &h, d);
#if defined(HAS_VISIBILITY) || defined(HAS_HOLDOUT)
        uint visibility = hit_visibility(sc, &h);
#endif
#ifdef HAS_VISIBILITY
        // An object this kind of ray does not see: the ray goes on behind it (not a bounce).
        if (!(visibility & ray_kind)) {
            if (++unseen > MAX_UNSEEN_SURFACES)
                break;
            go_behind(&s, &h, d, primary, &o, &ignore, &t_before, &tmin, &tmax);
            continue;
        }
#endif
#ifdef HAS_HOLDOUT
        // A holdout seen by the camera ray (through cut-outs too): black, and with Film >
        // Transparent a hole in alpha, as Cycles.
        if (primary && (visibility & VISIBILITY_HOLDOUT)) {
            *depth = (t_before + h.t) * along;
            *normal = s.ns;
#ifdef HAS_TRANSPARENT_FILM
#ifdef HAS_CLOSURES
            *alpha = fmax(*alpha - mean3(beta), 0.0f);
#else
            *alpha = 0.0f;
#endif
#endif
            break;
        }
#endif
        ShadeInfo info = shade_info(&s, d);
#ifdef HAS_LIGHT_PATH
        info.path = path_kind;
        info.length = h.t * kd_length(d);
        info.bounce = bounces;
        info.diffuse = diffuse;
        info.glossy = glossy;
        info.transmission = transmission;
        info.transparent = transparent;
#endif
        bool pass = false;      // the path goes on through the surface (not a bounce)
#ifdef HAS_CLOSURES
        // A material of closures (docs/shading.md, Closures): their emission, holdout and
        // transparency summed, one scattering closure chosen by its weight.
        ClosureSum cs;
        Material m = surface_closures(sc, &s, d, &info, rng_next(rng), &cs);
#if defined(HAS_HOLDOUT) && defined(HAS_TRANSPARENT_FILM)
        if (primary && cs.holdout > 0.0f)
            *alpha = fmax(*alpha - cs.holdout * mean3(beta), 0.0f);
#endif
#ifdef HAS_EMISSION
        if (any(cs.emission > 0.0f)) {
            float3 found = clamp_sample(beta * cs.emission * emission_mis(sc, &h, d, pdf_prev,
                                                                          n_light), limit_found);
            radiance += found;
            film_light(film, found, bounces == 0);
        }
#endif
        float p_pass = 0.0f;
#ifdef HAS_ALPHA
        // Through the transparency with probability mean(transparency) / (that + the
        // scattering weight), weighted by the transparency over it.
        float see_through = mean3(cs.transparency);
        if (see_through > 0.0f) {
            p_pass = see_through / (see_through + cs.scatter);
            pass = rng_next(rng) < p_pass;
            if (pass) {
                beta *= cs.transparency / p_pass;
                film_scale(film, cs.transparency / p_pass);
            }
        }
#endif
#else
        Material m = surface_material(sc, &s, d, &info);
#ifdef HAS_ALPHA
        // Cut-out: through with probability 1 - alpha (Cycles' stochastic transparency).
        pass = m.alpha < 1.0f && rng_next(rng) >= m.alpha;
#endif
#endif
        if (pass) {
            if (++transparent > limits->transparent)
                break;
            go_behind(&s, &h, d, primary, &o, &ignore, &t_before, &tmin, &tmax);
            continue;
        }
        if (primary) {
            *depth = (t_before + h.t) * along;
            *normal = s.ns;
        }
#ifdef HAS_CLOSURES
        // The chosen closure stands for all scattering ones: the path's weight times their
        // weight over the probability of scattering here (1 for a Mix Shader).
        if (!(cs.scatter > 0.0f))
            break;
        beta *= cs.scatter / (1.0f - p_pass);
        film_scale(film, (float3)(cs.scatter / (1.0f - p_pass)));
#elif defined(HAS_EMISSION)
        if (any(m.emission > 0.0f)) {
            float3 found = clamp_sample(beta * m.emission * emission_mis(sc, &h, d, pdf_prev,
                                                                         n_light), limit_found);
            radiance += found;
            film_light(film, found, bounces == 0);
        }
#endif
        if (last)
            break;
        primary = false;
        float3 wo = -kd_normalize(d);
        Frame fr = frame_of(s.ns);
        float3 wo_l = to_local(&fr, wo);
        // Filter Glossy (Cycles): after a wide BSDF sample, sharp lobes are blurred, which
        // trades the fireflies of caustics for a little blur.
        float alpha_min = 0.0f;
        if (limits->filter_glossy > 0.0f && min_pdf * (1.0f / limits->filter_glossy) < 1.0f)
            alpha_min = 0.5f * sqrt(1.0f - min_pdf * (1.0f / limits->filter_glossy));
        Lobes lobes = lobes_at(&m, wo_l.z, s.front, alpha_min);
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
        lobes.unbumped = to_local(&fr, m.unbumped);
#endif
        film_surface(film, cam, &m, &lobes, wo_l.z, s.ns, beta, bounces == 0,
                     (t_before + h.t) * kd_length(d));
        rng->depth = (uint)bounces;     // the point sequences of this scattering event
        radiance += direct_light(sc, &s, &m, &lobes, &fr, wo_l, beta, limit, rng);
#ifdef HAS_BOUNCES
        float3 wi_l, weight;
        int kind;
        float u_lobe = rng_next(rng), u3 = rng_next(rng);
        float2 u = rng_2d_at(rng, rng_dim(rng, RNG_BSDF, 0u), rng->sample);
        if (!bsdf_sample_local(&m, &lobes, wo_l, u_lobe, u.x, u.y, u3, &wi_l, &weight, &pdf_prev,
                               &kind))
            break;
        float3 wi = to_world(&fr, wi_l);
        // Reflections stay on the side they came from, refractions cross the surface.
        if ((kd_dot(wi, s.ng) > 0.0f) != (wi_l.z > 0.0f))
            break;
        ++bounces;
        if (pdf_prev > 0.0f)
            min_pdf = fmin(min_pdf, pdf_prev);
        last = bounces > limits->max_bounces;
        if (kind == LOBE_DIFFUSE)
            last = last || ++diffuse > limits->diffuse;
        else if (kind == LOBE_GLOSSY)
            last = last || ++glossy > limits->glossy;
        else
            last = last || ++transmission > limits->transmission;
#ifdef HAS_VISIBILITY
        ray_kind = kind == LOBE_DIFFUSE ? VISIBILITY_DIFFUSE
                   : kind == LOBE_GLOSSY ? VISIBILITY_GLOSSY : VISIBILITY_TRANSMISSION;
#endif
#ifdef HAS_LIGHT_PATH
        path_kind = (kind == LOBE_DIFFUSE || kind == LOBE_GLOSSY ? PATH_REFLECT : PATH_TRANSMIT)
                    | (kind == LOBE_DIFFUSE || kind == LOBE_TRANSLUCENT ? PATH_DIFFUSE : PATH_GLOSSY)
                    | (pdf_prev > 0.0f ? 0u : PATH_SINGULAR);
#endif
        beta *= weight;
        if (!all(isfinite(beta)) || all(beta == 0.0f))
            break;
        // Russian roulette after 3 bounces (Cycles' continuation probability).
        if (bounces > 3 && !last) {
            float q = fmin(sqrt(max3(beta)), 1.0f);
            if (rng_next(rng) >= q)
                break;
            beta /= q;
        }
        o = spawn(&s, wi);
        d = wi;
        tmin = 0.0f;
        tmax = INFINITY;
        ignore = h.key;
#else
        break;
#endif
    }
    return radiance;
}
