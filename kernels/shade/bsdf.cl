// The BSDF (docs/shading.md, Materials): Fresnel, GGX microfacet lobes sampled by visible
// normals, the multiple-scattering compensation of ggx_albedo.cl's tables, Principled's
// layers as lobes, their evaluation and sampling, and the power heuristic that weighs a BSDF
// sample against a light sample.

// GGX lobes with alpha^2 below this are perfect mirrors (Cycles' singular threshold).
#define DELTA_ALPHA2 1e-7f

// ---------------------------------------------------------------------------------------------
// Fresnel and GGX

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
#define LOBE_TRANSLUCENT 3              // diffuse transmission: a transmission for the limits

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
#ifdef HAS_TRANSLUCENT
    float w_translucent, p_translucent;         // diffuse transmission (Translucent BSDF)
#endif
#ifdef HAS_COAT
    float w_coat, p_coat;                       // Principled's Coat: a GGX dielectric on top
    float coat_alpha, coat_alpha2, eta_coat;
    bool coat_delta;
    float3 below;                               // what it passes to the layers below (at wo)
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
#ifdef HAS_TRANSLUCENT
    // The Translucent BSDF's diffuse transmission takes its share from the other layers.
    l.w_translucent = clamp(m->translucent, 0.0f, 1.0f);
    l.w_metal *= 1.0f - l.w_translucent;
    l.w_glass *= 1.0f - l.w_translucent;
    l.w_dielectric *= 1.0f - l.w_translucent;
#endif
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
#ifdef HAS_TRANSLUCENT
    float a_translucent = l.w_translucent * mean3(m->base);
    total += a_translucent;
#endif
#ifdef HAS_COAT
    // The coat over everything (Cycles' layering: the layers below get 1 - its albedo, and
    // its tint); its own lobe a GGX of alpha = coat roughness^2 with the exact Fresnel of its
    // IOR, as Cycles' coat (no multiple-scattering compensation).
    l.w_coat = clamp(m->coat_weight, 0.0f, 1.0f);
    l.eta_coat = fmax(m->coat_ior, 1.0f);
    float coat_roughness = clamp(m->coat_roughness, 0.0f, 1.0f);
    l.coat_alpha = fmax(coat_roughness * coat_roughness, alpha_min);
    l.coat_alpha2 = l.coat_alpha * l.coat_alpha;
    l.coat_delta = l.coat_alpha2 <= DELTA_ALPHA2;
    l.coat_alpha = fmax(l.coat_alpha, 1e-4f);
    l.coat_alpha2 = fmax(l.coat_alpha2, 1e-8f);
    l.below = l.w_coat > 0.0f ? coat_below(m, cos_o) : (float3)(1.0f, 1.0f, 1.0f);
    float a_coat = l.w_coat * fresnel_dielectric(cos_o, l.eta_coat), below_mean = mean3(l.below);
    total = total * below_mean + a_coat;
#endif
    float inv = total > 0.0f ? 1.0f / total : 0.0f;
#ifdef HAS_COAT
    l.p_coat = a_coat * inv;
    inv *= below_mean;                          // the layers below, through the coat
#endif
#ifdef HAS_TRANSLUCENT
    l.p_translucent = a_translucent * inv;
#endif
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

// The non-delta part of the layers under a coat (all of the BSDF without one) for wo -> wi
// (local), without the cosine; *pdf: the density of bsdf_sample choosing wi (solid angle).
inline float3 bsdf_eval_layers(const Material *m, const Lobes *l, float3 wo, float3 wi, float *pdf)
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
#ifdef HAS_TRANSLUCENT
    if (cos_i < 0.0f && l->w_translucent > 0.0f) {      // Lambertian through the surface
        f += m->base * (l->w_translucent * M_1_PI_F);
        *pdf += l->p_translucent * -cos_i * M_1_PI_F;
    }
#endif
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

// The non-delta part of the BSDF for wo -> wi (local), without the cosine; *pdf: the
// density of bsdf_sample choosing wi (solid angle). With a coat: its lobe over the layers,
// which it passes l->below.
inline float3 bsdf_eval_local(const Material *m, const Lobes *l, float3 wo, float3 wi, float *pdf)
{
#ifdef HAS_COAT
    float3 f = bsdf_eval_layers(m, l, wo, wi, pdf) * l->below;
    float cos_o = wo.z, cos_i = wi.z;
#if defined(HAS_NORMAL_MAP) || defined(HAS_BUMP)
    if (kd_dot(l->unbumped, wi) * l->unbumped.z * cos_i < 0.0f)
        return f;
#endif
    if (l->w_coat > 0.0f && !l->coat_delta && cos_i > 0.0f) {
        float3 h = kd_normalize(wo + wi);
        float d = ggx_d(l->coat_alpha2, h.z), lambda_o = ggx_lambda(l->coat_alpha2, cos_o);
        float g2 = 1.0f / (1.0f + lambda_o + ggx_lambda(l->coat_alpha2, cos_i));
        f += l->w_coat * fresnel_dielectric(kd_dot(wo, h), l->eta_coat) * d * g2
             / (4.0f * cos_o * cos_i);
        *pdf += l->p_coat * d / ((1.0f + lambda_o) * 4.0f * cos_o);
    }
    return f;
#else
    return bsdf_eval_layers(m, l, wo, wi, pdf);
#endif
}

// A direction from the BSDF. Returns false when the sample is lost (below the surface,
// nothing to scatter). *weight = f cos / pdf; *pdf = 0 for a mirror (delta) direction;
// *kind: LOBE_DIFFUSE, LOBE_GLOSSY, LOBE_TRANSMISSION or LOBE_TRANSLUCENT (for the bounce
// limits).
inline bool bsdf_sample_local(const Material *m, const Lobes *l, float3 wo, float u_lobe,
                              float u1, float u2, float u3, float3 *wi, float3 *weight,
                              float *pdf, int *kind)
{
    float p_glass = l->p_glass;
    float p_any = l->p_diffuse + l->p_specular + l->p_metal + p_glass;
#ifdef HAS_TRANSLUCENT
    p_any += l->p_translucent;
#endif
#ifdef HAS_COAT
    p_any += l->p_coat;
#endif
    if (p_any <= 0.0f)
        return false;
#ifdef HAS_COAT
    if (u_lobe < l->p_coat) {               // the coat's reflection
        *kind = LOBE_GLOSSY;
        if (l->coat_delta) {
            *wi = (float3)(-wo.x, -wo.y, wo.z);
            *pdf = 0.0f;
            *weight = (float3)(l->w_coat * fresnel_dielectric(wo.z, l->eta_coat) / l->p_coat);
            return true;
        }
        float3 h = sample_vndf(wo, l->coat_alpha, u1, u2);
        *wi = 2.0f * kd_dot(wo, h) * h - wo;
        if (!(wi->z > 0.0f))
            return false;
    } else {
    u_lobe -= l->p_coat;                    // the layers below
#endif
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
#ifdef HAS_COAT
            *weight *= l->below;
#endif
            return true;
        }
        float3 h = sample_vndf(wo, l->alpha, u1, u2);
        *wi = 2.0f * kd_dot(wo, h) * h - wo;
        if (!(wi->z > 0.0f))
            return false;
    }
#ifdef HAS_TRANSLUCENT
    else if (u_lobe < l->p_diffuse + l->p_specular + l->p_metal + l->p_translucent) {
        *kind = LOBE_TRANSLUCENT;           // a cosine-distributed direction through
        float2 d = concentric_disk(u1, u2);
        *wi = (float3)(d.x, d.y, -sqrt(fmax(0.0f, 1.0f - d.x * d.x - d.y * d.y)));
    }
#endif
    else {
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
#ifdef HAS_COAT
            *weight *= l->below;
#endif
            return true;
        }
    }
#ifdef HAS_COAT
    }
#endif
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
