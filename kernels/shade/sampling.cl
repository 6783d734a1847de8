// Random numbers and sample warps. No transcendental built-ins (their accuracy differs between
// devices): sin/cos are short polynomials on [-pi/4, pi/4], everything else is + * / sqrt.
//
// Seeds come from the GLOBAL pixel index (py * width + px), the sample number and the frame
// seed, never from the work-item or the slave, so a tile gives the same pixels wherever it runs.

// PCG hash (Jarzynski & Olano 2020): a good 32-bit permutation.
inline uint pcg_hash(uint v)
{
    uint state = v * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

typedef struct {
    uint state;
} Rng;

inline Rng rng_seed(uint pixel_index, uint sample, uint seed)
{
    Rng r;
    r.state = pcg_hash(pixel_index ^ pcg_hash(sample ^ pcg_hash(seed + 0x9E3779B9u)));
    return r;
}

// Uniform in [0, 1): 24 random bits.
inline float rng_next(Rng *r)
{
    r->state = pcg_hash(r->state);
    return (float)(r->state >> 8) * 0x1.0p-24f;
}

// sin and cos of x in [-pi/4, pi/4] (Taylor to x^9 / x^8: error below 4e-8).
inline float sin_small(float x)
{
    float x2 = x * x;
    return x * (1.0f - x2 / 6.0f * (1.0f - x2 / 20.0f * (1.0f - x2 / 42.0f * (1.0f - x2 / 72.0f))));
}

inline float cos_small(float x)
{
    float x2 = x * x;
    return 1.0f - x2 / 2.0f * (1.0f - x2 / 12.0f * (1.0f - x2 / 30.0f * (1.0f - x2 / 56.0f)));
}

// Shirley-Chiu concentric map of [0,1)^2 onto the unit disk (stratification is preserved).
inline float2 concentric_disk(float u1, float u2)
{
    float a = 2.0f * u1 - 1.0f, b = 2.0f * u2 - 1.0f;
    if (a == 0.0f && b == 0.0f)
        return (float2)(0.0f, 0.0f);
    float r, phi;           // phi in [-pi/4, pi/4] around the quadrant's axis
    if (fabs(a) > fabs(b)) {
        r = a;
        phi = M_PI_4_F * (b / a);
        return (float2)(r * cos_small(phi), r * sin_small(phi));
    }
    r = b;
    phi = M_PI_4_F * (a / b);
    // angle pi/2 - phi: (cos, sin) = (sin phi, cos phi)
    return (float2)(r * sin_small(phi), r * cos_small(phi));
}

// An orthonormal basis (t, b) around unit n (Duff et al. 2017).
inline void basis(float3 n, float3 *t, float3 *b)
{
    float sign = n.z >= 0.0f ? 1.0f : -1.0f;
    float a = -1.0f / (sign + n.z);
    float c = n.x * n.y * a;
    *t = (float3)(1.0f + sign * n.x * n.x * a, sign * c, -sign * n.x);
    *b = (float3)(c, sign + n.y * n.y * a, -n.y);
}

// Cosine-weighted direction around unit n (Malley's method).
inline float3 cosine_hemisphere(float3 n, float u1, float u2)
{
    float2 d = concentric_disk(u1, u2);
    float z = sqrt(fmax(0.0f, 1.0f - d.x * d.x - d.y * d.y));
    float3 t, b;
    basis(n, &t, &b);
    return d.x * t + d.y * b + z * n;
}

// Uniform direction in the cone of half angle acos(cos_max) around unit axis.
inline float3 uniform_cone(float3 axis, float cos_max, float u1, float u2)
{
    float cos_t = 1.0f - u1 * (1.0f - cos_max);
    float sin_t = sqrt(fmax(0.0f, 1.0f - cos_t * cos_t));
    // A point on the unit circle from u2 without trig of a full angle: the concentric map of a
    // point on the square's boundary (uniform in angle within each of the 8 octants).
    float s = 8.0f * u2;                              // which of the 8 octant edges
    int k = (int)s;
    float f = s - (float)k;
    float2 e;
    switch (k & 7) {
        case 0: e = (float2)(1.0f, f); break;
        case 1: e = (float2)(1.0f - f, 1.0f); break;
        case 2: e = (float2)(-f, 1.0f); break;
        case 3: e = (float2)(-1.0f, 1.0f - f); break;
        case 4: e = (float2)(-1.0f, -f); break;
        case 5: e = (float2)(-1.0f + f, -1.0f); break;
        case 6: e = (float2)(f, -1.0f); break;
        default: e = (float2)(1.0f, -1.0f + f); break;
    }
    float2 d = concentric_disk(0.5f * e.x + 0.5f, 0.5f * e.y + 0.5f);   // on the unit circle
    float3 t, b;
    basis(axis, &t, &b);
    return sin_t * (d.x * t + d.y * b) + cos_t * axis;
}

// Stratum `s` of an n x n grid in a progressive order: when n is a power of two, the first 4
// samples fall in the 4 quadrants, the first 16 in the 16 sub-blocks, ... (bit-reversed Morton
// order), so adaptive sampling that stops after any power of 4 is still stratified.
inline uint2 progressive_stratum(uint s, uint n)
{
    if (n & (n - 1u))
        return (uint2)(s % n, s / n);
    uint bits = 0;
    while ((1u << bits) < n)
        ++bits;
    uint total_bits = 2u * bits;
    uint rev = 0;
    for (uint i = 0; i < total_bits; ++i)
        rev |= ((s >> i) & 1u) << (total_bits - 1u - i);
    uint x = 0, y = 0;
    for (uint i = 0; i < bits; ++i) {
        x |= ((rev >> (2u * i)) & 1u) << i;
        y |= ((rev >> (2u * i + 1u)) & 1u) << i;
    }
    return (uint2)(x, y);
}
