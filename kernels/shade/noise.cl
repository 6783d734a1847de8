// The procedural textures of node programs (nodes.cl run_nodes calls them): Noise, Wave, Magic,
// Brick and White Noise (NOISE), Voronoi (VORONOI), each Cycles' formulas and hashes
// (kernel/svm/noise.h, wave.h, magic.h, brick.h, white_noise.h, voronoi.h; util/hash.h), so
// that the patterns are Cycles' own, not merely alike. Points are float4, unused lanes 0.

#if defined(HAS_NOISE) || defined(HAS_VORONOI)
// Cycles' hashes: Bob Jenkins' lookup3 of 1 to 4 words (hash_uint to hash_uint4) and PCG of
// 2 to 4 ints (hash_pcg2d_i to hash_pcg4d_i: signed, shifted arithmetically).
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

// Cycles' hash_float<n>_to_float: lookup3 of the floats' bits as a float in [0, 1].
inline float hash_floats(int n, float4 k)
{
    return (float)lookup3(n, as_uint4(k)) * (1.0f / (float)0xFFFFFFFFu);
}

// hash_float_to_float3 ... hash_float4_to_float3 (n: the floats k holds).
inline float3 hash_floats_to_float3(int n, float4 k)
{
    if (n == 1)
        return (float3)(hash_floats(1, k), hash_floats(2, (float4)(k.x, 1.0f, 0.0f, 0.0f)),
                        hash_floats(2, (float4)(k.x, 2.0f, 0.0f, 0.0f)));
    if (n == 2)
        return (float3)(hash_floats(2, k), hash_floats(3, (float4)(k.xy, 1.0f, 0.0f)),
                        hash_floats(3, (float4)(k.xy, 2.0f, 0.0f)));
    if (n == 3)
        return (float3)(hash_floats(3, k), hash_floats(4, (float4)(k.xyz, 1.0f)),
                        hash_floats(4, (float4)(k.xyz, 2.0f)));
    return (float3)(hash_floats(4, k), hash_floats(4, k.zxwy), hash_floats(4, k.wzyx));
}
#endif

#ifdef HAS_NOISE

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

// Cycles' Wave Texture (svm_wave) at p (already times Scale). flags: WAVE p0; b: distortion,
// detail, detail scale; c: detail roughness, phase.
inline float node_wave(int flags, float4 p, float distortion, float detail, float dscale,
                       float droughness, float phase)
{
    int type = flags & 1, bands = (flags >> 1) & 3, rings = (flags >> 3) & 3, profile = flags >> 5;
    p = (float4)((p.xyz + 0.000001f) * 0.999999f, 0.0f);
    float n;
    if (type == NODE_WAVE_BANDS) {
        n = bands == NODE_WAVE_BANDS_X ? p.x * 20.0f : bands == NODE_WAVE_BANDS_Y ? p.y * 20.0f
            : bands == NODE_WAVE_BANDS_Z ? p.z * 20.0f : (p.x + p.y + p.z) * 10.0f;
    } else {
        float3 rp = p.xyz;
        if (rings == NODE_WAVE_RINGS_X)
            rp *= (float3)(0.0f, 1.0f, 1.0f);
        else if (rings == NODE_WAVE_RINGS_Y)
            rp *= (float3)(1.0f, 0.0f, 1.0f);
        else if (rings == NODE_WAVE_RINGS_Z)
            rp *= (float3)(1.0f, 1.0f, 0.0f);
        n = sqrt(kd_dot(rp, rp)) * 20.0f;
    }
    n += phase;
    if (distortion != 0.0f) {
        NoiseSettings fbm = {3, NODE_NOISE_TYPE_FBM, clamp(detail, 0.0f, 15.0f), fmax(droughness, 0.0f),
                             2.0f, 0.0f, 1.0f, true};
        n += distortion * (noise_fractal(&fbm, p * dscale) * 2.0f - 1.0f);
    }
    if (profile == NODE_WAVE_PROFILE_SIN)
        return 0.5f + 0.5f * sin(n - M_PI_2_F);
    n /= 2.0f * M_PI_F;
    return profile == NODE_WAVE_PROFILE_SAW ? n - floor(n) : fabs(n - floor(n + 0.5f)) * 2.0f;
}

// Cycles' Magic Texture (svm_magic): (colour, its average) at p for `depth` turns.
inline float4 node_magic(float4 p, float scale, int depth, float distortion)
{
    float px = fmod(p.x, 2.0f * M_PI_F), py = fmod(p.y, 2.0f * M_PI_F), pz = fmod(p.z, 2.0f * M_PI_F);
    float x = sin((px + py + pz) * 5.0f * scale);
    float y = cos((-px + py - pz) * 5.0f * scale);
    float z = -cos((-px - py + pz) * 5.0f * scale);
    if (depth > 0) {
        x *= distortion; y *= distortion; z *= distortion;
        y = -cos(x - y + z); y *= distortion;
        if (depth > 1) { x = cos(x - y - z); x *= distortion; }
        if (depth > 2) { z = sin(-x - y - z); z *= distortion; }
        if (depth > 3) { x = -cos(-x + y - z); x *= distortion; }
        if (depth > 4) { y = -sin(-x + y + z); y *= distortion; }
        if (depth > 5) { y = -cos(-x + y + z); y *= distortion; }
        if (depth > 6) { x = cos(x + y + z); x *= distortion; }
        if (depth > 7) { z = sin(x + y - z); z *= distortion; }
        if (depth > 8) { x = -cos(-x - y + z); x *= distortion; }
        if (depth > 9) { y = -sin(x - y + z); y *= distortion; }
    }
    if (distortion != 0.0f) {
        distortion *= 2.0f;
        x /= distortion; y /= distortion; z /= distortion;
    }
    float3 c = (float3)(0.5f - x, 0.5f - y, 0.5f - z);
    return (float4)(c, (c.x + c.y + c.z) * (1.0f / 3.0f));
}

// Cycles' brick_noise (its integer noise for each brick's tint).
inline float brick_noise(uint n)
{
    n = (n + 1013u) & 0x7fffffffu;
    n = (n >> 13) ^ n;
    uint nn = (n * (n * n * 60493u + 19990303u) + 1376312589u) & 0x7fffffffu;
    return 0.5f * ((float)nn / 1073741824.0f);
}

// Cycles' Brick Texture (svm_brick): (tint, mortar) at p (times Scale). b: mortar size and
// smooth, bias; c: brick width, row height; the offset and squash amounts and frequencies.
inline float4 node_brick(float4 p, float mortar_size, float mortar_smooth, float bias,
                         float brick_width, float row_height, float offset_amount,
                         int offset_frequency, float squash_amount, int squash_frequency)
{
    int rownum = (int)floor(p.y / row_height);
    float offset = 0.0f;
    if (offset_frequency && squash_frequency) {
        brick_width *= (rownum % squash_frequency) ? 1.0f : squash_amount;
        offset = (rownum % offset_frequency) ? 0.0f : brick_width * offset_amount;
    }
    int bricknum = (int)floor((p.x + offset) / brick_width);
    float x = (p.x + offset) - brick_width * (float)bricknum;
    float y = p.y - row_height * (float)rownum;
    float tint = clamp(brick_noise((uint)((rownum << 16) + (bricknum & 0xFFFF))) + bias, 0.0f, 1.0f);
    float min_dist = fmin(fmin(x, y), fmin(brick_width - x, row_height - y));
    float mortar;
    if (min_dist >= mortar_size)
        mortar = 0.0f;
    else if (mortar_smooth == 0.0f)
        mortar = 1.0f;
    else {
        float f = (1.0f - min_dist / mortar_size) / mortar_smooth;
        float ff = f * f;
        mortar = f <= 0.0f ? 0.0f : f >= 1.0f ? 1.0f : 3.0f * ff - 2.0f * ff * f;
    }
    return (float4)(tint, mortar, 0.0f, 0.0f);
}

// Cycles' White Noise Texture (svm_node_tex_white_noise) of `dims` dimensions (the vector's
// lanes, W last): (value, value, value, value) or (colour, 1).
inline float4 node_white_noise(int dims, float4 p, bool colour)
{
    if (colour)
        return (float4)(hash_floats_to_float3(dims, p), 1.0f);
    float v = hash_floats(dims, p);
    return (float4)(v, v, v, v);
}
#endif

#ifdef HAS_VORONOI
// PCG hashes of integer cells as Cycles' Voronoi takes them (hash_int2_to_float2,
// hash_int3_to_float3, hash_int4_to_float4: components in [0, 1]).
inline float4 hash_pcg(int dims, int4 k)
{
    uint4 v = as_uint4(k) * 1664525u + 1013904223u;
    if (dims == 2) {
        v.x += v.y * 1664525u; v.y += v.x * 1664525u;
        v ^= as_uint4(as_int4(v) >> 16);
        v.x += v.y * 1664525u; v.y += v.x * 1664525u;
    } else if (dims == 3) {
        v.x += v.y * v.z; v.y += v.z * v.x; v.z += v.x * v.y;
        v ^= as_uint4(as_int4(v) >> 16);
        v.x += v.y * v.z; v.y += v.z * v.x; v.z += v.x * v.y;
    } else {
        v.x += v.y * v.w; v.y += v.z * v.x; v.z += v.x * v.y; v.w += v.y * v.z;
        v ^= as_uint4(as_int4(v) >> 16);
        v.x += v.y * v.w; v.y += v.z * v.x; v.z += v.x * v.y; v.w += v.y * v.z;
    }
    float4 f = convert_float4(as_int4(v & 0x7FFFFFFFu)) * (1.0f / (float)0x7FFFFFFFu);
    return dims == 2 ? (float4)(f.xy, 0.0f, 0.0f) : dims == 3 ? (float4)(f.xyz, 0.0f) : f;
}

typedef struct {
    int dims, feature, metric;
    float detail, roughness, lacunarity, smoothness, exponent, randomness, max_distance;
    bool normalize;
} VoronoiParams;

// A cell's point (its offset in [0, 1) per lane) and colour: 1D hashes the cell's float
// (lookup3), 2D to 4D its integers (PCG; 2D colours of (x, y, 0)).
inline float4 voronoi_point(int dims, int4 cell, float cellf)
{
    return dims == 1 ? (float4)(hash_floats(1, (float4)(cellf, 0.0f, 0.0f, 0.0f)), 0.0f, 0.0f, 0.0f)
                     : hash_pcg(dims, cell);
}

inline float3 voronoi_colour(int dims, int4 cell, float cellf)
{
    return dims == 1 ? hash_floats_to_float3(1, (float4)(cellf, 0.0f, 0.0f, 0.0f))
                     : hash_pcg(dims == 2 ? 3 : dims, cell).xyz;
}

// The point of the cell at offset o from `cell` (cellf: its float, which 1D hashes).
inline float4 voronoi_cell_point(const VoronoiParams *v, int4 cell, float cellf, int4 o)
{
    return convert_float4(o) + voronoi_point(v->dims, cell + o, cellf + (float)o.x) * v->randomness;
}

// The squared length of d (1D: its length) that orders N-Sphere Radius' points.
inline float voronoi_radius_order(int dims, float4 d)
{
    return dims == 1 ? fabs(d.x) : kd_dot4(d, d);
}

// Cycles' voronoi_distance (bound: voronoi_distance_bound, which orders points alike) over
// the used lanes; 1D: |a - b|.
inline float voronoi_distance(const VoronoiParams *v, float4 a, float4 b, bool bound)
{
    float4 d = fabs(a - b);
    if (v->dims == 1)
        return d.x;
    if (v->metric == NODE_VORONOI_METRIC_MANHATTAN)
        return d.x + d.y + d.z + d.w;
    if (v->metric == NODE_VORONOI_METRIC_CHEBYCHEV)
        return fmax(fmax(d.x, d.y), fmax(d.z, d.w));
    if (v->metric == NODE_VORONOI_METRIC_MINKOWSKI) {
        float sum = 0.0f;
        for (int k = 0; k < v->dims; ++k)
            sum += pow(k == 0 ? d.x : k == 1 ? d.y : k == 2 ? d.z : d.w, v->exponent);
        return bound ? sum : pow(sum, 1.0f / v->exponent);
    }
    float sq = d.x * d.x + d.y * d.y + d.z * d.z + d.w * d.w;
    return bound ? sq : sqrt(sq);
}

// The k-th cell offset of a (2 r + 1)^dims neighbourhood, x fastest (Cycles' loop order).
inline int4 voronoi_offset(int dims, int k, int r)
{
    int side = 2 * r + 1;
    int4 o = (int4)(k % side, (k / side) % side, (k / (side * side)) % side,
                    k / (side * side * side)) - r;
    return (int4)(o.x, dims > 1 ? o.y : 0, dims > 2 ? o.z : 0, dims > 3 ? o.w : 0);
}

// One octave of F1, F2 or Smooth F1 at coord: *distance, *colour, *position (cell space).
inline void voronoi_octave(const VoronoiParams *v, float4 coord, float *distance, float3 *colour,
                           float4 *position)
{
    int dims = v->dims;
    float4 cellf = floor(coord), inside = coord - cellf;
    int4 cell = convert_int4(cellf);
    bool smooth = v->feature == NODE_VORONOI_SMOOTH_F1 && v->smoothness != 0.0f;
    int r = smooth ? 2 : 1, side = 2 * r + 1, count = side;
    for (int k = 1; k < dims; ++k)
        count *= side;
    float d1 = FLT_MAX, d2 = FLT_MAX, h = -1.0f;
    int4 o1 = (int4)(0), o2 = (int4)(0);
    float4 p1 = (float4)(0.0f), p2 = (float4)(0.0f);
    float sd = 0.0f;
    float3 sc = (float3)(0.0f);
    float4 sp = (float4)(0.0f);
    for (int k = 0; k < count; ++k) {
        int4 o = voronoi_offset(dims, k, r);
        float4 point = voronoi_cell_point(v, cell, cellf.x, o);
        if (smooth) {
            float d = voronoi_distance(v, point, inside, false);
            if (h == -1.0f) {
                h = 1.0f;
            } else {
                float x = 0.5f + 0.5f * (sd - d) / v->smoothness;
                h = x < 0.0f ? 0.0f : x >= 1.0f ? 1.0f : (3.0f - 2.0f * x) * (x * x);
            }
            float correction = v->smoothness * h * (1.0f - h);
            sd = sd + h * (d - sd) - correction;
            correction /= 1.0f + 3.0f * v->smoothness;
            float3 c = voronoi_colour(dims, cell + o, cellf.x + (float)o.x);
            sc = sc + h * (c - sc) - correction;
            sp = sp + h * (point - sp) - correction;
            continue;
        }
        bool f2 = v->feature == NODE_VORONOI_F2;
        float d = voronoi_distance(v, point, inside, !f2);
        if (d < d1) {
            d2 = d1; o2 = o1; p2 = p1;
            d1 = d; o1 = o; p1 = point;
        } else if (f2 && d < d2) {
            d2 = d; o2 = o; p2 = point;
        }
    }
    float4 used = (float4)(1.0f, dims > 1 ? 1.0f : 0.0f, dims > 2 ? 1.0f : 0.0f, dims > 3 ? 1.0f : 0.0f);
    if (smooth) {
        *distance = sd;
        *colour = sc;
        *position = (cellf + sp) * used;
    } else if (v->feature == NODE_VORONOI_F2) {
        *distance = d2;
        *colour = voronoi_colour(dims, cell + o2, cellf.x + (float)o2.x);
        *position = p2 + cellf;
    } else {
        *distance = dims == 1 ? d1 : voronoi_distance(v, p1, inside, false);
        *colour = voronoi_colour(dims, cell + o1, cellf.x + (float)o1.x);
        *position = p1 + cellf;
    }
}

// Distance to Edge (1 octave; Euclidean as Cycles).
inline float voronoi_edge(const VoronoiParams *v, float4 coord)
{
    int dims = v->dims;
    float4 cellf = floor(coord), inside = coord - cellf;
    int4 cell = convert_int4(cellf);
    if (dims == 1) {
        float mid = voronoi_point(1, cell, cellf.x).x * v->randomness;
        float left = -1.0f + voronoi_point(1, cell, cellf.x - 1.0f).x * v->randomness;
        float right = 1.0f + voronoi_point(1, cell, cellf.x + 1.0f).x * v->randomness;
        return fmin(fabs((mid + left) / 2.0f - inside.x), fabs((mid + right) / 2.0f - inside.x));
    }
    int count = dims == 2 ? 9 : dims == 3 ? 27 : 81;
    float4 closest = (float4)(0.0f);
    float best = FLT_MAX;
    for (int k = 0; k < count; ++k) {
        int4 o = voronoi_offset(dims, k, 1);
        float4 to = voronoi_cell_point(v, cell, 0.0f, o) - inside;
        float d = kd_dot4(to, to);
        if (d < best) {
            best = d;
            closest = to;
        }
    }
    best = FLT_MAX;
    for (int k = 0; k < count; ++k) {
        int4 o = voronoi_offset(dims, k, 1);
        float4 to = voronoi_cell_point(v, cell, 0.0f, o) - inside;
        float4 perpendicular = to - closest;
        float lsq = kd_dot4(perpendicular, perpendicular);
        if (lsq > 0.0001f)
            best = fmin(best, kd_dot4((closest + to) / 2.0f, perpendicular / sqrt(lsq)));
    }
    return best;
}

// N-Sphere Radius (1 octave): half the distance from the closest point to its closest point.
inline float voronoi_radius(const VoronoiParams *v, float4 coord)
{
    int dims = v->dims, count = dims == 1 ? 3 : dims == 2 ? 9 : dims == 3 ? 27 : 81;
    float4 cellf = floor(coord), inside = coord - cellf;
    int4 cell = convert_int4(cellf);
    float4 closest = (float4)(0.0f);
    int4 closest_offset = (int4)(0);
    float best = FLT_MAX;
    for (int k = 0; k < count; ++k) {
        int4 o = voronoi_offset(dims, k, 1);
        float4 point = voronoi_cell_point(v, cell, cellf.x, o);
        float d = voronoi_radius_order(dims, point - inside);
        if (d < best) {
            best = d;
            closest = point;
            closest_offset = o;
        }
    }
    best = FLT_MAX;
    float4 second = (float4)(0.0f);
    for (int k = 0; k < count; ++k) {
        int4 o = voronoi_offset(dims, k, 1);
        if (all(o == 0))
            continue;
        float4 point = voronoi_cell_point(v, cell, cellf.x, o + closest_offset);
        float d = voronoi_radius_order(dims, closest - point);
        if (d < best) {
            best = d;
            second = point;
        }
    }
    float4 gap = second - closest;
    return (dims == 1 ? fabs(gap.x) : sqrt(kd_dot4(gap, gap))) / 2.0f;
}

// Cycles' Voronoi Texture (svm_node_tex_voronoi with its fractal octaves): coord already
// times Scale (1D: W in lane x). Returns the output `out` asks for: (distance or radius),
// (colour, 1) or (position xyz, W).
inline float4 node_voronoi(VoronoiParams *v, float4 coord, float scale, int out)
{
    v->detail = clamp(v->detail, 0.0f, 15.0f);
    v->roughness = clamp(v->roughness, 0.0f, 1.0f);
    v->randomness = clamp(v->randomness, 0.0f, 1.0f);
    v->smoothness = clamp(v->smoothness / 2.0f, 0.0f, 0.5f);
    bool zero_input = v->detail == 0.0f || v->roughness == 0.0f;
    float amplitude = 1.0f, octave_scale = 1.0f, rest = v->detail - floor(v->detail);
    if (v->feature == NODE_VORONOI_N_SPHERE_RADIUS) {
        float radius = voronoi_radius(v, coord);
        return (float4)(radius, radius, radius, radius);
    }
    float reach = 0.5f + 0.5f * v->randomness;
    if (v->feature == NODE_VORONOI_DISTANCE_TO_EDGE) {
        v->max_distance = reach;
        float max_amplitude = v->max_distance, distance = 8.0f;
        for (int i = 0; (float)i <= ceil(v->detail); ++i) {
            float d = voronoi_edge(v, coord * octave_scale);
            if (zero_input) {
                distance = d;
                break;
            }
            if ((float)i <= v->detail) {
                max_amplitude = mix(max_amplitude, v->max_distance / octave_scale, amplitude);
                distance = mix(distance, fmin(distance, d / octave_scale), amplitude);
                octave_scale *= v->lacunarity;
                amplitude *= v->roughness;
            } else if (rest != 0.0f) {
                float lerp_amplitude = mix(max_amplitude, v->max_distance / octave_scale, amplitude);
                max_amplitude = mix(max_amplitude, lerp_amplitude, rest);
                float lerp_distance = mix(distance, fmin(distance, d / octave_scale), amplitude);
                distance = mix(distance, fmin(distance, lerp_distance), rest);
            }
        }
        if (v->normalize)
            distance /= max_amplitude;
        return (float4)(distance, distance, distance, distance);
    }
    float4 corner = (float4)(reach, v->dims > 1 ? reach : 0.0f, v->dims > 2 ? reach : 0.0f,
                             v->dims > 3 ? reach : 0.0f);
    v->max_distance = voronoi_distance(v, (float4)(0.0f), corner, false)
                      * (v->feature == NODE_VORONOI_F2 ? 2.0f : 1.0f);
    float max_amplitude = 0.0f, distance = 0.0f;
    float3 colour = (float3)(0.0f);
    float4 position = (float4)(0.0f);
    for (int i = 0; (float)i <= ceil(v->detail); ++i) {
        float d;
        float3 c;
        float4 p;
        voronoi_octave(v, coord * octave_scale, &d, &c, &p);
        if (zero_input) {
            max_amplitude = 1.0f;
            distance = d;
            colour = c;
            position = p;
            break;
        }
        if ((float)i <= v->detail) {
            max_amplitude += amplitude;
            distance += d * amplitude;
            colour += c * amplitude;
            position = mix(position, p / octave_scale, amplitude);
            octave_scale *= v->lacunarity;
            amplitude *= v->roughness;
        } else if (rest != 0.0f) {
            max_amplitude = mix(max_amplitude, max_amplitude + amplitude, rest);
            distance = mix(distance, distance + d * amplitude, rest);
            colour = mix(colour, colour + c * amplitude, rest);
            position = mix(position, mix(position, p / octave_scale, amplitude), rest);
        }
    }
    if (v->normalize) {
        distance /= max_amplitude * v->max_distance;
        colour /= max_amplitude;
    }
    position = scale != 0.0f ? position / scale : (float4)(0.0f);
    if (out == NODE_VORONOI_OUT_COLOR)
        return (float4)(colour, 1.0f);
    if (out == NODE_VORONOI_OUT_POSITION)       // 1D: the position is W
        return v->dims == 1 ? (float4)(0.0f, 0.0f, 0.0f, position.x) : position;
    return (float4)(distance, distance, distance, distance);
}
#endif
