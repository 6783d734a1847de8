// Camera tiles: one work-item per pixel of a list, a range of samples per call; each sample
// follows one path (camera ray, direct light at every surface, then mirror / glass / diffuse
// bounces up to the bounce limits), and the results are summed into the tile's accumulators.
// slave/tracer.py decides which pixels get how many samples (uniform or adaptive).
// The camera buffer is one CAMERA record of the layout header (core/layout.py; packed by
// slave/buffers.py); the accumulators are ACCUM and STATS records, one per tile pixel.

inline float3 transform_point(__global const float4 *m, float3 p)
{
    float4 q = (float4)(p, 1.0f);
    return (float3)(dot(m[0], q), dot(m[1], q), dot(m[2], q));
}

inline float3 transform_vector(__global const float4 *m, float3 v)
{
    float4 q = (float4)(v, 0.0f);
    return (float3)(dot(m[0], q), dot(m[1], q), dot(m[2], q));
}

// The camera ray through image position (fx, fy) in pixels of the full image (top-left
// origin; pixel centres at +0.5). The direction is not normalised: t is then proportional to
// the distance along the view axis, which both clipping and the depth pass measure.
inline void camera_ray(__global const float4 *cam, float fx, float fy, float3 *o, float3 *d)
{
    float width = CAMERA_WIDTH(cam), height = CAMERA_HEIGHT(cam);
    float ndc_x = fx / width * 2.0f - 1.0f;
    float ndc_y = 1.0f - fy / height * 2.0f;
    float2 scale = CAMERA_NDC_SCALE(cam), offset = CAMERA_NDC_OFFSET(cam);
    float2 p = (float2)(ndc_x * scale.x + offset.x, ndc_y * scale.y + offset.y);
    __global const float4 *to_world = CAMERA_TO_WORLD(cam);
    if (CAMERA_KIND(cam) == CAMERA_PERSP) {
        *o = transform_point(to_world, (float3)(0.0f, 0.0f, 0.0f));
        *d = transform_vector(to_world, (float3)(p, -1.0f));
    } else {
        *o = transform_point(to_world, (float3)(p, 0.0f));
        *d = transform_vector(to_world, (float3)(0.0f, 0.0f, -1.0f));
    }
}

inline float3 refract_dir(float3 w, float3 n, float eta_ratio, bool *ok)
{
    // w: unit incident direction, n: unit normal facing against w, eta_ratio = n_i / n_t.
    float cos_i = -dot(n, w);
    float sin2_t = eta_ratio * eta_ratio * fmax(0.0f, 1.0f - cos_i * cos_i);
    *ok = sin2_t < 1.0f;
    float cos_t = sqrt(fmax(0.0f, 1.0f - sin2_t));
    return eta_ratio * w + (eta_ratio * cos_i - cos_t) * n;
}

inline float3 reflect_dir(float3 w, float3 n)
{
    return w - 2.0f * dot(w, n) * n;
}

// One path from the camera. *depth and *normal get the first opaque surface (1e10 / 0 on a
// miss). max_bounces: surfaces after the first that may scatter the path further.
inline float3 trace_path(const Scene *sc, __global const float4 *cam, float3 o, float3 d,
                         Rng *rng, int max_bounces, int diffuse_bounces, float *depth,
                         float3 *normal)
{
    float3 radiance = (float3)(0.0f, 0.0f, 0.0f), beta = (float3)(1.0f, 1.0f, 1.0f);
    float along = dot(d, CAMERA_VIEW_AXIS(cam));     // view-axis distance per unit of t
    float tmin = CAMERA_CLIP_START(cam) / along, tmax = CAMERA_CLIP_END(cam) / along;
    float t_before = 0.0f;
    uint ignore = NO_HIT;
    bool primary = true;
    int bounces = 0, diffuse = 0, passes = 0;
    *depth = 1e10f;
    *normal = (float3)(0.0f, 0.0f, 0.0f);
    while (true) {
        Hit h;
        if (!trace(sc, o, d, tmin, tmax, false, ignore, &h)) {
            radiance += beta * CAMERA_WORLD_COLOR(cam);
            break;
        }
        Surface s = surface_at(sc, &h, d);
        Material m = material_at(sc, h.tri, h.u, h.v);
#ifdef HAS_ALPHA
        // Cut-out: the path goes on through with probability 1 - alpha (Cycles' stochastic
        // transparency); not a bounce.
        if (m.alpha < 1.0f && rng_next(rng) >= m.alpha) {
            if (++passes > 64)
                break;
            o = spawn(&s, d);
            ignore = h.tri;
            if (primary) {
                t_before += h.t;
                tmin = fmax(tmin - h.t, 0.0f);
                tmax = tmax - h.t;
            }
            continue;
        }
#endif
        if (primary) {
            *depth = (t_before + h.t) * along;
            *normal = s.ns;
            primary = false;
        }
        float3 wo = -normalize(d);
#ifdef HAS_EMISSION
        radiance += beta * m.emission;
#endif
        radiance += beta * direct_light(sc, &s, &m, wo, rng);
#ifdef HAS_BOUNCES
        if (bounces >= max_bounces)
            break;
        ++bounces;
        // Pick one lobe to continue with, with probability equal to its weight.
        float pick = rng_next(rng);
        float w_metal = m.metallic, w_glass = (1.0f - m.metallic) * m.transmission;
        bool mirror = m.roughness < MIRROR_ROUGHNESS;
        float cos_o = fmax(dot(s.ns, wo), 0.0f);
        float3 nd = (float3)(0.0f, 0.0f, 0.0f);
        bool go = false;
        if (pick < w_metal) {
#ifdef HAS_SPECULAR
            if (mirror) {
                nd = reflect_dir(-wo, s.ns);
                beta *= m.base + (1.0f - m.base) * pow5(1.0f - cos_o);
                go = true;
            }
#endif
        } else if (pick < w_metal + w_glass) {
#ifdef HAS_TRANSMISSION
            float eta = s.front ? m.ior : 1.0f / m.ior;       // n_t / n_i
            float F = fresnel_dielectric(cos_o, eta);
            bool ok = false;
            if (rng_next(rng) >= F)
                nd = refract_dir(-wo, s.ns, 1.0f / eta, &ok);
            if (ok) {
                beta *= m.base;
            } else {
                nd = reflect_dir(-wo, s.ns);                   // Fresnel or total reflection
            }
            go = true;
#endif
        } else {
            bool specular = false;
#ifdef HAS_SPECULAR
            float f0 = dielectric_f0(&m);
            if (mirror && m.specular > 0.0f
                    && rng_next(rng) < f0 + (1.0f - f0) * pow5(1.0f - cos_o)) {
                nd = reflect_dir(-wo, s.ns);
                specular = go = true;
            }
#endif
#ifdef HAS_DIFFUSE_BOUNCES
            if (!specular && diffuse < diffuse_bounces) {
                ++diffuse;
                nd = cosine_hemisphere(s.ns, rng_next(rng), rng_next(rng));
                beta *= m.base;                                // albedo; pdf cancels cos / pi
                go = true;
            }
#endif
        }
        if (!go || all(beta == 0.0f))
            break;
        o = spawn(&s, nd);
        d = nd;
        tmin = 0.0f;
        tmax = INFINITY;
        ignore = h.tri;
#else
        break;
#endif
    }
    return radiance;
}

// Sample `sample_start + k` (k < sample_count) of each listed pixel. strata n > 0: sample s
// lies in stratum progressive_stratum(s, n) of an n x n grid, jittered; n == 0: the pixel
// centre (one sample). pixels[i]: tile-local index (row * tile_w + column).
// accum: (sum of RGB, sample count); stats: (sum, sum of squares) of min(luminance, 1).
// write_aux: also write the depth and normal passes (from the pixel-centre ray).
__kernel void render_samples(__global const float4 *cam, int x0, int y0, int tile_w,
                             __global const int *pixels, int pixel_count, int sample_start,
                             int sample_count, int strata, int max_bounces, int diffuse_bounces,
                             int light_n, uint seed, int write_aux,
                             __global const uint2 *nodes, __global const uint *leaf_index32,
                             __global const ushort *leaf_index16, uint leaf_shift,
                             __global const float4 *tri_verts, __global const float4 *bounds,
                             __global const ushort *material_ids,
                             __global const float4 *materials, __global const float4 *lights,
                             uint light_count, __global const float *normals,
                             __global const float *uvs, __global const half *texels,
                             __global const uint *tex_sizes,
                             __global float4 *accum, __global float2 *stats,
                             __global float *out_depth, __global float *out_normal)
{
    int i = get_global_id(0);
    if (i >= pixel_count)
        return;
    int here = pixels[i];
    int px = x0 + here % tile_w, py = y0 + here / tile_w;
    uint pixel_index = (uint)py * (uint)CAMERA_WIDTH(cam) + (uint)px;   // global: same on every slave

    Scene sc;
    sc.kd = make_kdtree(nodes, leaf_index32, leaf_index16, leaf_shift, bounds);
    sc.tri_verts = tri_verts;
    sc.material_ids = material_ids;
    sc.materials = materials;
    sc.lights = lights;
    sc.normals = normals;
    sc.uvs = uvs;
    sc.texels = texels;
    sc.tex_sizes = tex_sizes;
    sc.light_count = light_count;
    sc.light_n = light_n;

    float4 sum = accum[here];       // this pixel's ACCUM and STATS records, kept in registers
    float2 st = stats[here];
    float depth;
    float3 normal;
    for (int k = 0; k < sample_count; ++k) {
        uint s = (uint)(sample_start + k);
        Rng rng = rng_seed(pixel_index, s, seed);
        float jx = 0.5f, jy = 0.5f;
        if (strata > 0) {
            uint2 cell = progressive_stratum(s % (uint)(strata * strata), (uint)strata);
            jx = ((float)cell.x + rng_next(&rng)) / (float)strata;
            jy = ((float)cell.y + rng_next(&rng)) / (float)strata;
        }
        float3 o, d;
        camera_ray(cam, (float)px + jx, (float)py + jy, &o, &d);
        float3 c = trace_path(&sc, cam, o, d, &rng, max_bounces, diffuse_bounces, &depth, &normal);
        if (!all(isfinite(c)))
            c = (float3)(0.0f, 0.0f, 0.0f);                 // never let NaN/inf reach a pixel
        if (write_aux && strata == 0 && k == 0) {
            out_depth[here] = depth;
            vstore3(normal, here, out_normal);
        }
        float lum = fmin(0.2126f * c.x + 0.7152f * c.y + 0.0722f * c.z, 1.0f);
        ACCUM_COLOR(&sum) += c;
        ACCUM_SAMPLES(&sum) += 1.0f;
        STATS_SUM(&st) += lum;
        STATS_SUM_SQUARES(&st) += lum * lum;
    }
    accum[here] = sum;
    stats[here] = st;
    if (write_aux && strata > 0) {
        // Depth and normal from the pixel centre, as with one sample.
        float3 o, d;
        camera_ray(cam, (float)px + 0.5f, (float)py + 0.5f, &o, &d);
        float along = dot(d, CAMERA_VIEW_AXIS(cam));
        Hit h;
        depth = 1e10f;
        normal = (float3)(0.0f, 0.0f, 0.0f);
        if (trace(&sc, o, d, CAMERA_CLIP_START(cam) / along, CAMERA_CLIP_END(cam) / along, false,
                  NO_HIT, &h)) {
            Surface s = surface_at(&sc, &h, d);
            depth = h.t * along;
            normal = s.ns;
        }
        out_depth[here] = depth;
        vstore3(normal, here, out_normal);
    }
}
