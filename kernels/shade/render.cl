// Camera tiles: one work-item per pixel of a list, a range of samples per call; each sample
// follows one path (camera ray, direct light at every surface, then BSDF bounces up to the
// bounce limits), and the results are summed into the tile's accumulators.
// slave/tracer.py decides which pixels get how many samples (uniform or adaptive).
// The camera buffer is one CAMERA record of the layout header (core/layout.py; packed by
// slave/buffers.py); the accumulators are ACCUM records, one per tile pixel.

#ifdef HAS_DOF
// A point of the aperture (radius 1) for u in [0, 1)^2, as Cycles samples it: a disc, or the
// regular polygon of `blades` corners turned by `rotation`.
inline float2 aperture_sample(__global const float4 *cam, float u1, float u2)
{
    int blades = (int)CAMERA_BLADES(cam);
    if (blades < 3)
        return concentric_disk(u1, u2);
    float corner = floor(u1 * (float)blades);
    float u = sqrt(u1 * (float)blades - corner);
    float v = u2 * u;
    u = 1.0f - u;
    float2 half_angle = sincos_poly(M_PI_F / (float)blades);
    float2 p = (float2)((u + v) * half_angle.y, (u - v) * half_angle.x);
    float turn = CAMERA_BLADE_ROTATION(cam) + corner * (2.0f * M_PI_F / (float)blades);
    turn -= 2.0f * M_PI_F * floor(turn * (0.5f * M_1_PI_F));
    float2 r = sincos_poly(turn);
    return (float2)(r.y * p.x - r.x * p.y, r.x * p.x + r.y * p.y);
}
#endif

// The camera ray through image position (fx, fy) in pixels of the full image (top-left
// origin; pixel centres at +0.5). The direction is not normalised: t is then proportional to
// the distance along the view axis, which both clipping and the depth pass measure.
// `lens`: the point of the aperture (radius 1; thin lens, perspective cameras with HAS_DOF);
// `time`: the moment in the shutter interval [0, 1) (HAS_CAMERA_MOTION).
inline void camera_ray(__global const float4 *cam, float fx, float fy, float2 lens, float time,
                       float3 *o, float3 *d)
{
    float width = CAMERA_WIDTH(cam), height = CAMERA_HEIGHT(cam);
    float ndc_x = fx / width * 2.0f - 1.0f;
    float ndc_y = 1.0f - fy / height * 2.0f;
    float2 scale = CAMERA_NDC_SCALE(cam), offset = CAMERA_NDC_OFFSET(cam);
    float2 p = (float2)(ndc_x * scale.x + offset.x, ndc_y * scale.y + offset.y);
    float3 origin = (float3)(0.0f, 0.0f, 0.0f), direction = (float3)(p, -1.0f);
    if (CAMERA_KIND(cam) != CAMERA_PERSP) {
        origin = (float3)(p, 0.0f);
        direction = (float3)(0.0f, 0.0f, -1.0f);
    }
#ifdef HAS_DOF
    else {
        // Thin lens: from a point of the aperture towards where the pinhole ray meets the
        // plane in focus (z = -focus distance); z stays -1, so t still measures the view axis.
        float2 l = lens * CAMERA_APERTURE(cam);
        origin = (float3)(l, 0.0f);
        direction = (float3)(p - l * (1.0f / CAMERA_FOCUS_DISTANCE(cam)), -1.0f);
    }
#endif
    __global const float4 *to_world = CAMERA_TO_WORLD(cam);
    *o = transform_point(to_world, origin);
    *d = transform_vector(to_world, direction);
#ifdef HAS_CAMERA_MOTION
    // The transform blends linearly from the shutter's open to its close.
    __global const float4 *to_world_end = CAMERA_TO_WORLD_END(cam);
    *o = (1.0f - time) * *o + time * transform_point(to_world_end, origin);
    *d = (1.0f - time) * *d + time * transform_vector(to_world_end, direction);
#endif
}

// A camera sample's offset from its pixel's centre, in pixels, for u in [0, 1) (Film > Pixel
// Filter): uniform over the width for a box; else the filter importance-sampled through the
// inverse CDF that slave/buffers.py filter_table put after the CAMERA record (Cycles'
// filter_table_sample). u = 1/2 is the centre exactly.
inline float filter_offset(__global const float4 *cam, float u)
{
    if ((int)CAMERA_FILTER(cam) == PIXEL_FILTER_BOX)
        return (u - 0.5f) * CAMERA_FILTER_WIDTH(cam);
    __global const float *table = (__global const float *)(cam + CAMERA_SIZE);
    float f = u * (float)(FILTER_TABLE_SIZE - 1);
    int i = clamp((int)f, 0, FILTER_TABLE_SIZE - 2);
    float t = f - (float)i;
    return (1.0f - t) * table[i] + t * table[i + 1];
}

// Samples sample_start .. + sample_count of pixel `here` (tile-local index) into its accum
// record and, with HAS_FILM, its FILM record in `film` (render_samples).
inline void render_pixel(Scene *sc, __global const float4 *cam, const PathLimits *limits,
                         int here, int x0, int y0, int tile_w, int sample_start,
                         int sample_count, int jitter, uint seed, int write_aux,
                         __global float4 *accum,
                         __global float *out_depth, __global float *out_normal,
                         __global float4 *film)
{
    int px = x0 + here % tile_w, py = y0 + here / tile_w;
    uint pixel_index = (uint)py * (uint)CAMERA_WIDTH(cam) + (uint)px;   // global: same on every slave

    float4 sum[ACCUM_SIZE];         // this pixel's ACCUM record, kept in registers
    for (int k = 0; k < ACCUM_SIZE; ++k)
        sum[k] = accum[ACCUM_SIZE * here + k];
#ifdef HAS_FILM
    float4 film_sum[FILM_SIZE];     // and its FILM record
    for (int k = 0; k < FILM_SIZE; ++k)
        film_sum[k] = film[FILM_SIZE * here + k];
#else
    float4 *film_sum = 0;
#endif
    float depth;
    float3 normal;
    for (int k = 0; k < sample_count; ++k) {
        uint s = (uint)(sample_start + k);
        Rng rng = rng_seed(pixel_index, s, seed);
        float jx = 0.5f, jy = 0.5f;
        if (jitter) {
            // Where the sample goes in its pixel (through the filter): point s of the pixel's
            // own Owen-scrambled Sobol sequence, so the first 2^k samples of the pixel are
            // stratified and placed at random within their strata, whatever the maximum.
            float2 u = rng_2d_at(&rng, RNG_FILM_DIM, s);
            jx = u.x;
            jy = u.y;
        }
        float2 lens = (float2)(0.0f, 0.0f);
        float time = 0.5f;
#ifdef HAS_DOF
        lens = aperture_sample(cam, rng_next(&rng), rng_next(&rng));
#endif
#if defined(HAS_CAMERA_MOTION) || defined(HAS_OBJECT_MOTION)
        time = rng_next(&rng);
#endif
#ifdef HAS_OBJECT_MOTION
        sc->top.time = time;         // the objects are where they are at the camera ray's moment
#endif
        float3 o, d;
        camera_ray(cam, (float)px + 0.5f + filter_offset(cam, jx),
                   (float)py + 0.5f + filter_offset(cam, jy), lens, time, &o, &d);
        float alpha;
        Film path_film = film_path(film_sum);
        float3 c = trace_path(sc, cam, o, d, &rng, limits, &depth, &normal, &alpha, &path_film);
        if (!all(isfinite(c)))
            c = (float3)(0.0f, 0.0f, 0.0f);                 // never let NaN/inf reach a pixel
        if (write_aux && !jitter && k == 0) {
            out_depth[here] = depth;
            vstore3(normal, here, out_normal);
        }
        ACCUM_COLOR(sum) += c;
        ACCUM_SAMPLES(sum) += 1.0f;
        ACCUM_ALPHA(sum) += alpha;
        // Half of the samples, for the adaptive noise estimate: Cycles' class A
        // (sample_is_class_A), the samples whose odd bits have an odd count: pairs of
        // consecutive samples, half of every aligned four, so each half of a pixel's
        // stratified sequence stays stratified (Christensen et al. 2018, 10.2.1) and a gradient
        // across the pixel cancels rather than reading as noise.
        if (popcount(s & 0xAAAAAAAAu) & 1u)
            ACCUM_HALF(sum) += c;
    }
    for (int k = 0; k < ACCUM_SIZE; ++k)
        accum[ACCUM_SIZE * here + k] = sum[k];
#ifdef HAS_FILM
    for (int k = 0; k < FILM_SIZE; ++k)
        film[FILM_SIZE * here + k] = film_sum[k];
#endif
    if (write_aux && jitter) {
        // Depth and normal from the pixel centre, as with one sample.
#ifdef HAS_OBJECT_MOTION
        sc->top.time = 0.5f;
#endif
        float3 o, d;
        camera_ray(cam, (float)px + 0.5f, (float)py + 0.5f, (float2)(0.0f, 0.0f), 0.5f, &o, &d);
        float along = kd_dot(d, CAMERA_VIEW_AXIS(cam));
        float tmin = CAMERA_CLIP_START(cam) / along, tmax = CAMERA_CLIP_END(cam) / along;
        float t_before = 0.0f;
        uint ignore = NO_HIT;
        Hit h;
        depth = 1e10f;
        normal = (float3)(0.0f, 0.0f, 0.0f);
        for (int k = 0; k <= MAX_UNSEEN_SURFACES; ++k) {
            if (!trace(sc, o, d, tmin, tmax, false, ignore, &h))
                break;
            Surface s = surface_at(sc, &h, d);
#ifdef HAS_VISIBILITY
            if (!(hit_visibility(sc, &h) & VISIBILITY_CAMERA)) {   // not seen: behind
                go_behind(&s, &h, d, true, &o, &ignore, &t_before, &tmin, &tmax);
                continue;
            }
#endif
            depth = (t_before + h.t) * along;
            normal = s.ns;
            break;
        }
        out_depth[here] = depth;
        vstore3(normal, here, out_normal);
    }
}

// Sample `sample_start + k` (k < sample_count) of each listed pixel. jitter: sample s goes to
// point s of the pixel's Sobol sequence RNG_FILM_DIM; 0: the pixel centre (one sample). pixels[i]: tile-local index (row * tile_w + column).
// accum: ACCUM records (sums of RGB and alpha, the sample count, the RGB of Cycles' class A samples).
// write_aux: also write the depth and normal passes (from the pixel-centre ray).
// film (HAS_FILM): FILM records, the sums of the other passes the frame asks for (film.cl).
// With RENDER_PIXEL_QUEUE (CPU devices) a few work-items take the pixels in turn from the
// counter next_pixel (0 at launch), one at a time as each finishes one: a tile's pixels differ
// in cost many times over, and PoCL shares work-groups out between its threads in halves, so
// one thread would wait for the other. Otherwise one work-item per pixel. The pixels do not
// depend on which work-item renders them. The parameters are core/layout.py's RENDER_SAMPLES
// table (the header's RENDER_SAMPLES_PARAMS), which slave/tracer.py passes its arguments by.
#ifdef HAS_FILM
#define FILM_BUFFER film
#else
#define FILM_BUFFER 0
#endif
__kernel void render_samples(RENDER_SAMPLES_PARAMS)
{
    Scene sc;
    sc.kd = make_kdtree(nodes, leaf_index32, leaf_index16, leaf_shift, bounds);
    sc.tri_verts = tri_verts;
#ifdef HAS_INSTANCES
    TOPLEVEL_MAKE(top);
    sc.top = top;
#endif
    sc.material_ids = material_ids;
    sc.materials = materials;
    sc.lights = lights;
    sc.normals = normals;
    sc.uvs = uvs;
    sc.texels = texels;
    sc.tex_sizes = texture_sizes;
    sc.light_count = light_count;
    sc.light_n = light_n;
    sc.world = world;
    sc.env_cdf = env_cdf;
    sc.emitters = emitters;
    sc.emitter_count = emitter_count;
    sc.emitter_power = emitter_power;
    sc.world_color = CAMERA_WORLD_COLOR(cam);
    PathLimits limits = {max_bounces, diffuse_bounces, glossy_bounces, transmission_bounces,
                         transparent_bounces, clamp_direct, clamp_indirect, filter_glossy};
#ifdef RENDER_PIXEL_QUEUE
    for (int i = atomic_inc(next_pixel); i < pixel_count; i = atomic_inc(next_pixel))
#else
    int i = get_global_id(0);
    if (i < pixel_count)
#endif
        render_pixel(&sc, cam, &limits, pixels[i], x0, y0, tile_w, sample_start, sample_count,
                     jitter, seed, write_aux, accum, out_depth, out_normal, FILM_BUFFER);
}
