// Passes beside the image (docs/shading.md, "Passes"): the denoising guides as Cycles defines
// them (kernel/film/denoising_passes.h) and the data passes of the camera hit (Cycles'
// film_write_data_passes). Each is compiled only where the frame asks for it (HAS_GUIDES,
// HAS_PASS_<NAME>, all under HAS_FILM: core/scene/features.py pass_features); a pixel's sums
// are its FILM record (core/layout.py), which slave/film.py divides and finishes. Nothing here
// draws a random number or changes the path: the image is the same bits with or without it.

// One path's view of the film: the pixel's FILM record (a private copy that render_pixel
// keeps) and the guides' state along the path.
typedef struct {
#ifdef HAS_FILM
    float4 *sum;
#endif
#ifdef HAS_GUIDES
    float3 guide_weight;    // Cycles' denoising_feature_throughput: the tint on the way
    bool looking;           // no guide surface yet (Cycles' PATH_RAY_DENOISING_FEATURES)
#endif
    int unused;
} Film;

// A path starts: weight 1, still looking (`sum`: the pixel's FILM record).
inline Film film_path(float4 *sum)
{
    Film f;
#ifdef HAS_FILM
    f.sum = sum;
    FILM_SAMPLES(f.sum) += 1.0f;
#endif
#ifdef HAS_GUIDES
    f.guide_weight = (float3)(1.0f, 1.0f, 1.0f);
    f.looking = true;
#endif
    f.unused = 0;
    return f;
}

// Light the path found (`found`: what it added to the pixel: emission, the world, a lamp):
// while the guides still look, it adds to the albedo with their weight (Cycles' emission and
// background rule); a surface's emission seen by a camera ray (`camera_emission`) is the
// Emission pass.
inline void film_light(Film *f, float3 found, bool camera_emission)
{
#ifdef HAS_GUIDES
    if (f->looking)
        FILM_ALBEDO(f->sum) += f->guide_weight * found;
#endif
#ifdef HAS_PASS_EMISSION
    if (camera_emission)
        FILM_EMISSION(f->sum) += found;
#endif
}

// The path's weight was scaled at a surface (passing through its transparency, or the one
// closure chosen standing for all): the guides' weight is scaled alike.
inline void film_scale(Film *f, float3 factor)
{
#ifdef HAS_GUIDES
    f->guide_weight *= factor;
#endif
}

// The albedo of each kind of lobe of material m seen from cos_o (Cycles' bsdf_albedo of its
// Principled closures): the diffuse layer and diffuse transmission, the glossy reflections
// (the specular layer: what the diffuse below loses; metal: its Fresnel colour; glass: its
// reflection) and glass's refraction (tinted by sqrt(base) per refraction, as it renders).
inline void lobe_albedos(const Material *m, const Lobes *l, float cos_o, float3 *diffuse,
                         float3 *glossy, float3 *refraction)
{
    float3 zero = (float3)(0.0f, 0.0f, 0.0f);
    *diffuse = (l->w_dielectric * l->diffuse_weight) * m->base;
#ifdef HAS_TRANSLUCENT
    *diffuse += l->w_translucent * m->base;
#endif
    *glossy = zero;
    *refraction = zero;
#ifdef HAS_SPECULAR
    *glossy += (float3)(l->w_dielectric * (1.0f - l->diffuse_weight));
    if (l->w_metal > 0.0f)
        *glossy += l->w_metal * metal_fresnel(m->base, cos_o) * l->metal_scale;
#endif
#ifdef HAS_TRANSMISSION
    if (l->w_glass > 0.0f) {
        float F = fresnel_dielectric(cos_o, l->eta_glass);
        *glossy += (float3)(l->w_glass * F);
        *refraction = (l->w_glass * (1.0f - F)) * sqrt(m->base);   // as its refraction
    }
#endif
}

// A surface the path scatters at (m, its lobes seen from cos_o, shading normal ns; beta the
// path's weight; `camera`: the camera ray's surface, reached through transparency or not;
// `dist` its distance from the camera).
// Guides (Cycles' film_write_denoising_features_surface): when lobes of roughness alpha above
// 0.075 (diffuse-like; diffuse lobes always) carry more than a quarter of the weight, or none
// carries any, the albedo of the diffuse-like lobes times the guides' weight and the normal
// are written and the guides stop looking; else (a mirror, glass, sharp gloss) the weight is
// tinted by the sharp lobes' albedo and the guides look on along the path.
// Camera hit: Diffuse Color and Glossy Color (their lobes' albedo x beta) and Mist.
inline void film_surface(Film *f, __global const float4 *cam, const Material *m,
                         const Lobes *l, float cos_o, float3 ns, float3 beta, bool camera,
                         float dist)
{
#ifdef HAS_GUIDES
    bool looking = f->looking;
#else
    bool looking = false;
#endif
    if (!looking && !camera)        // past the camera hit and the guide surface: nothing to do
        return;
#if defined(HAS_GUIDES) || defined(HAS_PASS_DIFFUSE_COLOR) || defined(HAS_PASS_GLOSSY_COLOR)
    float3 diffuse, glossy, refraction;
    lobe_albedos(m, l, cos_o, &diffuse, &glossy, &refraction);
#endif
#ifdef HAS_GUIDES
    if (looking) {
        float3 sharp = glossy + refraction;
        bool rough = l->alpha > 0.075f;
        float total = mean3(diffuse + sharp);
        float diffuse_like = mean3(diffuse) + (rough ? mean3(sharp) : 0.0f);
        if (!(total > 0.0f) || 4.0f * diffuse_like > total) {
            float3 albedo = f->guide_weight * (rough ? diffuse + sharp : diffuse);
            if (all(isfinite(albedo)))
                FILM_ALBEDO(f->sum) += albedo;
            if (total > 0.0f)
                FILM_GUIDE_NORMAL(f->sum) += ns;
            f->looking = false;
        } else {
            f->guide_weight *= sharp;
        }
    }
#endif
    if (!camera)
        return;
#ifdef HAS_PASS_DIFFUSE_COLOR
    FILM_DIFFUSE_COLOR(f->sum) += beta * diffuse;
#endif
#ifdef HAS_PASS_GLOSSY_COLOR
    FILM_GLOSSY_COLOR(f->sum) += beta * glossy;
#endif
#ifdef HAS_PASS_MIST
    // Cycles: (distance - start) / depth in [0, 1], the falloff's power; 1 - mist summed
    // (1 - the sum over the samples is the pass: the world is mist 1).
    float mist = clamp((dist - CAMERA_MIST_START(cam)) * CAMERA_MIST_INV_DEPTH(cam), 0.0f, 1.0f);
    float falloff = CAMERA_MIST_FALLOFF(cam);
    mist = falloff == 1.0f ? mist : falloff == 2.0f ? mist * mist
           : falloff == 0.5f ? sqrt(mist) : pow(mist, falloff);
    FILM_MIST(f->sum) += (1.0f - mist) * mean3(beta);
#endif
}
