// Random numbers, sample warps and angles. No transcendental built-ins (their accuracy differs
// between devices): sin/cos are short polynomials on [-pi/4, pi/4], atan2 one on [0, 1],
// everything else is + * / sqrt.
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

// A sample's random numbers: a stream (rng_next) for the choices that are made once a sample
// (a lobe, a cut-out, Russian roulette), and stratified 2D points (rng_2d_at) for the light
// and BSDF samples, point `sample` of a sequence of the pixel's own for each use at each
// depth, so that a pixel's samples cover the square evenly rather than at random.
typedef struct {
    uint state;         // rng_next's stream
    uint pixel_seed;    // the scrambles of this pixel's sequences
    uint sample;        // the sample's index in them
    uint depth;         // scattering events so far on the path (trace_path sets it)
} Rng;

inline Rng rng_seed(uint pixel_index, uint sample, uint seed)
{
    Rng r;
    r.state = pcg_hash(pixel_index ^ pcg_hash(sample ^ pcg_hash(seed + 0x9E3779B9u)));
    r.pixel_seed = pcg_hash(pixel_index ^ pcg_hash(seed ^ 0x85EBCA6Bu));
    r.sample = sample;
    r.depth = 0u;
    return r;
}

// Uniform in [0, 1): 24 random bits.
inline float rng_next(Rng *r)
{
    r->state = pcg_hash(r->state);
    return (float)(r->state >> 8) * 0x1.0p-24f;
}

inline uint reverse_bits(uint x)
{
    x = ((x >> 1) & 0x55555555u) | ((x & 0x55555555u) << 1);
    x = ((x >> 2) & 0x33333333u) | ((x & 0x33333333u) << 2);
    x = ((x >> 4) & 0x0F0F0F0Fu) | ((x & 0x0F0F0F0Fu) << 4);
    x = ((x >> 8) & 0x00FF00FFu) | ((x & 0x00FF00FFu) << 8);
    return (x >> 16) | (x << 16);
}

// Owen scrambling in base 2 by a hash (Laine and Karras 2011, with Vegdahl's constants, as in
// Burley 2020): each bit is flipped by a function of the bits above it only, so the points of
// an aligned block of 2^k stay a stratified set.
inline uint owen_scramble(uint x, uint seed)
{
    x = reverse_bits(x);
    x ^= x * 0x3D20ADEAu;
    x += seed;
    x *= (seed >> 16) | 1u;
    x ^= x * 0x05526C56u;
    x ^= x * 0x53A22864u;
    return reverse_bits(x);
}

// The second dimension of the Sobol sequence (the first is reverse_bits): direction numbers
// v_0 = 2^31, v_k = v_(k-1) ^ (v_(k-1) >> 1).
inline uint sobol_second(uint index)
{
    uint x = 0u, v = 0x80000000u;
    for (; index != 0u; index >>= 1, v ^= v >> 1)
        if (index & 1u)
            x ^= v;
    return x;
}

// What a 2D point is for (rng_dim): its sequence is its own for each use, light and depth.
#define RNG_LIGHT 0u
#define RNG_WORLD 1u
#define RNG_EMISSION 2u
#define RNG_BSDF 3u
#define RNG_FILM_DIM 0xFFFFFFFFu    // where a camera sample goes in its pixel: beyond every depth

inline uint rng_dim(const Rng *r, uint use, uint which)
{
    return (r->depth * 4u + use) * 65536u + which;
}

// Point `index` in [0, 1)^2 of the pixel's Owen-scrambled Sobol sequence `dim` (Burley 2020,
// "Practical Hash-based Owen Scrambling"): the index shuffled and both coordinates scrambled
// by seeds of the pixel and the sequence, so sequences are independent of each other and of
// other pixels, and each 2^k points from an aligned start are stratified (a (0, k, 2)-net).
inline float2 rng_2d_at(const Rng *r, uint dim, uint index)
{
    uint seed = pcg_hash(r->pixel_seed ^ pcg_hash(dim));
    index = owen_scramble(index, seed);
    uint x = owen_scramble(reverse_bits(index), pcg_hash(seed ^ 0x68BC21EBu));
    uint y = owen_scramble(sobol_second(index), pcg_hash(seed ^ 0x02E5BE93u));
    return (float2)((float)(x >> 8) * 0x1.0p-24f, (float)(y >> 8) * 0x1.0p-24f);
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

// Angles without transcendental built-ins: atan2 and the sin and cos of any angle.

// atan of t in [-tan(pi/8), tan(pi/8)]: Taylor to t^15 (error below 2e-8).
inline float atan_small(float t)
{
    float t2 = t * t;
    float p = 1.0f / 15.0f;
    p = 1.0f / 13.0f - t2 * p;
    p = 1.0f / 11.0f - t2 * p;
    p = 1.0f / 9.0f - t2 * p;
    p = 1.0f / 7.0f - t2 * p;
    p = 1.0f / 5.0f - t2 * p;
    p = 1.0f / 3.0f - t2 * p;
    return t * (1.0f - t2 * p);
}

inline float atan_unit(float a)         // a in [0, 1]
{
    return a > 0.41421356f ? M_PI_4_F + atan_small((a - 1.0f) / (a + 1.0f)) : atan_small(a);
}

inline float atan2_poly(float y, float x)
{
    float ax = fabs(x), ay = fabs(y);
    if (ax == 0.0f && ay == 0.0f)
        return 0.0f;
    float a = ax >= ay ? atan_unit(ay / ax) : M_PI_2_F - atan_unit(ax / ay);
    if (x < 0.0f)
        a = M_PI_F - a;
    return y < 0.0f ? -a : a;
}

// sin and cos of any x in [-2 pi, 2 pi]: quarter turns, then the short polynomials.
inline float2 sincos_poly(float x)
{
    float q = floor(x * M_2_PI_F + 0.5f);
    float r = x - q * M_PI_2_F;
    float s = sin_small(r), c = cos_small(r);
    int k = ((int)q) & 3;
    if (k == 1)
        return (float2)(c, -s);
    if (k == 2)
        return (float2)(-s, -c);
    if (k == 3)
        return (float2)(-c, s);
    return (float2)(s, c);
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
