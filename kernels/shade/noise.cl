// The Noise Texture node of node programs (nodes.cl run_nodes calls node_noise).

#ifdef HAS_NOISE
// Cycles' Noise Texture (every type, 1D to 4D): Perlin noise with Cycles' hash (Bob Jenkins' lookup3)
// and gradients, so that the pattern is Cycles' own, not merely alike. Points are float4 with
// the unused lanes 0.
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
#endif
