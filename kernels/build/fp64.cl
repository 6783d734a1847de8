/* IEEE double arithmetic for the perfect-split clipping (kernels/build/split.cl).

   Devices with cl_khr_fp64 use native doubles (IEEE: correctly rounded +, -, *, /, denormals).
   Without it (KDTRACE_SOFT_FP64, chosen by the host) `dbl` is the double's bit pattern in a ulong
   and every operation is done in integer arithmetic with round-to-nearest-even, so that both
   paths give the same bits and the same tree on every device. The software path covers what
   the clipping produces: finite values whose magnitudes are zero or far above the double
   denormal range (they come from float32 inputs, their differences, products with a t in
   [0, 1] and quotients of such); a result below 2^-1022 is flushed to a signed zero (never
   reached from float32 input).

   Conversions to float32 round outward (down or up) into the float32 values without denormals:
   a magnitude below FLT_MIN goes to 0 or to +-FLT_MIN, whichever lies on the outward side, so a
   device that flushes float32 denormals sees the same boxes; or to the nearest float32 (bin
   planes), magnitudes below FLT_MIN to 0. */

#ifndef KDTRACE_SOFT_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

typedef double dbl;
#define D_FROM_F(f)   ((double)(f))
#define D_FROM_U(n)   ((double)(n))
#define D_BITS(u)     as_double((ulong)(u))
#define D_ADD(a, b)   ((a) + (b))
#define D_SUB(a, b)   ((a) - (b))
#define D_MUL(a, b)   ((a) * (b))
#define D_DIV(a, b)   ((a) / (b))
#define D_LT(a, b)    ((a) < (b))
#define D_LE(a, b)    ((a) <= (b))
#define D_EQ(a, b)    ((a) == (b))
#define D_ZERO        0.0

/* Outward float32 rounding of x (see above); up != 0: the smallest allowed float >= x. */
inline float d_to_float_outward(double x, int up)
{
    if ((x < 0.0 ? -x : x) < (double)FLT_MIN) {
        if (x == 0.0)
            return 0.0f;
        return up ? (x > 0.0 ? FLT_MIN : 0.0f) : (x > 0.0 ? 0.0f : -FLT_MIN);
    }
    return (up ? convert_float_rtp(x) : convert_float_rtn(x)) + 0.0f;
}

/* Nearest float32 (ties to even); magnitudes below FLT_MIN give 0. */
inline float d_to_float_nearest(double x)
{
    return (x < 0.0 ? -x : x) < (double)FLT_MIN ? 0.0f : (float)x + 0.0f;
}

/* Nearest integer, ties to even (numpy's round), of 0 <= x < 2^31. */
inline int d_round_to_int(double x)
{
    return (int)rint(x);
}

#else  /* software IEEE double */

typedef ulong dbl;
#define SD_SIGN 0x8000000000000000UL
#define SD_FRAC 0x000FFFFFFFFFFFFFUL
#define SD_HIDDEN 0x0010000000000000UL
#define D_ZERO 0UL

inline int sd_is_zero(ulong x) { return (x & ~SD_SIGN) == 0; }

/* Round a significand m (leading one at bit 55, then guard, round and sticky bits) with
   biased exponent e to nearest even and pack it. */
inline ulong sd_pack(ulong sign, int e, ulong m)
{
    ulong low = m & 7UL;
    m >>= 3;
    if (low > 4UL || (low == 4UL && (m & 1UL))) {
        m += 1UL;
        if (m >> 53) {
            m >>= 1;
            e += 1;
        }
    }
    if (e <= 0)
        return sign;                /* below the normal range: flushed (see above) */
    return sign | ((ulong)e << 52) | (m & SD_FRAC);
}

/* Shift right by d, keeping whether any one bit fell off in bit 0 ("jamming"). */
inline ulong sd_shift_jam(ulong m, int d)
{
    if (d <= 0)
        return m;
    if (d >= 63)
        return m != 0UL ? 1UL : 0UL;
    return (m >> d) | ((m & ((1UL << d) - 1UL)) != 0UL ? 1UL : 0UL);
}

inline ulong sd_add(ulong a, ulong b)
{
    if (sd_is_zero(a))
        return sd_is_zero(b) ? (a & b) : b;
    if (sd_is_zero(b))
        return a;
    if ((a & ~SD_SIGN) < (b & ~SD_SIGN)) {    /* |a| >= |b| from here on */
        ulong t = a;
        a = b;
        b = t;
    }
    ulong sign = a & SD_SIGN;
    int ea = (int)((a >> 52) & 0x7FF), eb = (int)((b >> 52) & 0x7FF);
    ulong ma = ((a & SD_FRAC) | SD_HIDDEN) << 3;
    ulong mb = sd_shift_jam(((b & SD_FRAC) | SD_HIDDEN) << 3, ea - eb);
    ulong m;
    if ((a ^ b) & SD_SIGN) {
        m = ma - mb;
        if (m == 0UL)
            return 0UL;               /* x - x is +0 when rounding to nearest */
        while (!(m >> 55)) {          /* exact when nothing was shifted off, else one step */
            m <<= 1;
            ea -= 1;
        }
    } else {
        m = ma + mb;
        if (m >> 56) {
            m = sd_shift_jam(m, 1);
            ea += 1;
        }
    }
    return sd_pack(sign, ea, m);
}

inline ulong sd_mul(ulong a, ulong b)
{
    ulong sign = (a ^ b) & SD_SIGN;
    if (sd_is_zero(a) || sd_is_zero(b))
        return sign;
    int ea = (int)((a >> 52) & 0x7FF), eb = (int)((b >> 52) & 0x7FF);
    ulong ma = (a & SD_FRAC) | SD_HIDDEN, mb = (b & SD_FRAC) | SD_HIDDEN;
    ulong hi = mul_hi(ma, mb), lo = ma * mb;           /* the 106-bit product */
    int s = (hi >> 41) ? 50 : 49;                      /* leading one to bit 55 */
    ulong m = (hi << (64 - s)) | (lo >> s);
    if (lo << (64 - s))
        m |= 1UL;
    return sd_pack(sign, ea + eb + s - 1072, m);
}

inline ulong sd_div(ulong a, ulong b)
{
    ulong sign = (a ^ b) & SD_SIGN;
    if (sd_is_zero(a))
        return sign;
    int ea = (int)((a >> 52) & 0x7FF), eb = (int)((b >> 52) & 0x7FF);
    ulong ma = (a & SD_FRAC) | SD_HIDDEN, mb = (b & SD_FRAC) | SD_HIDDEN;
    int s = ma >= mb ? 55 : 56;          /* floor(ma 2^s / mb) has its leading one at bit 55 */
    ulong r = ma, q = 0UL;
    for (int i = 0; i <= s; i++) {       /* restoring division, one quotient bit per step */
        q <<= 1;
        if (r >= mb) {
            r -= mb;
            q |= 1UL;
        }
        r <<= 1;
    }
    if (r)
        q |= 1UL;
    return sd_pack(sign, ea - eb + 1078 - s, q);
}

inline ulong sd_from_float(float f)
{
    uint u = as_uint(f);
    ulong sign = (ulong)(u >> 31) << 63;
    int e8 = (int)((u >> 23) & 0xFF);
    ulong m = (ulong)(u & 0x7FFFFF);
    if (e8 == 0) {
        if (m == 0UL)
            return sign;
        int p = 63 - (int)clz(m);        /* float32 denormal: leading one at bit p < 23 */
        return sign | ((ulong)(p - 149 + 1023) << 52) | ((m << (52 - p)) & SD_FRAC);
    }
    return sign | ((ulong)(e8 - 127 + 1023) << 52) | (m << 29);
}

/* Signed ordering key of a double's bits (both zeros give 0). */
inline long sd_key(ulong x)
{
    return (x & SD_SIGN) ? -(long)(x & ~SD_SIGN) : (long)x;
}

inline float d_to_float_outward(ulong x, int up)
{
    if (sd_is_zero(x))
        return 0.0f;
    int negative = (x & SD_SIGN) != 0UL;
    int e = (int)((x >> 52) & 0x7FF) - 1023;
    if (e < -126)
        return up ? (negative ? 0.0f : FLT_MIN) : (negative ? -FLT_MIN : 0.0f);
    ulong m = (x & SD_FRAC) | SD_HIDDEN;
    uint m24 = (uint)(m >> 29);
    if ((m & ((1UL << 29) - 1UL)) && (up != negative)) {   /* away from zero */
        m24 += 1u;
        if (m24 >> 24) {
            m24 >>= 1;
            e += 1;
        }
    }
    return as_float(((uint)negative << 31) | ((uint)(e + 127) << 23) | (m24 & 0x7FFFFFu)) + 0.0f;
}

inline float d_to_float_nearest(ulong x)
{
    int e = (int)((x >> 52) & 0x7FF) - 1023;
    if (sd_is_zero(x) || e < -126)
        return 0.0f;
    uint sign = (uint)(x >> 63);
    ulong m = (x & SD_FRAC) | SD_HIDDEN;
    uint m24 = (uint)(m >> 29);
    ulong rest = m & ((1UL << 29) - 1UL);
    if (rest > (1UL << 28) || (rest == (1UL << 28) && (m24 & 1u))) {
        m24 += 1u;
        if (m24 >> 24) {
            m24 >>= 1;
            e += 1;
        }
    }
    return as_float((sign << 31) | ((uint)(e + 127) << 23) | (m24 & 0x7FFFFFu)) + 0.0f;
}

inline ulong sd_from_uint(uint n)
{
    if (n == 0u)
        return 0UL;
    int p = 31 - (int)clz(n);
    return ((ulong)(p + 1023) << 52) | (((ulong)n << (52 - p)) & SD_FRAC);
}

inline int d_round_to_int(ulong x)
{
    int e = (int)((x >> 52) & 0x7FF) - 1023;
    if (sd_is_zero(x) || e < -1)
        return 0;
    ulong m = (x & SD_FRAC) | SD_HIDDEN;              /* value m 2^(e - 52), e <= 30 */
    int drop = 52 - e;                                /* fraction bits, 22..53 */
    ulong whole = m >> drop, rest = m & ((1UL << drop) - 1UL), midway = 1UL << (drop - 1);
    if (rest > midway || (rest == midway && (whole & 1UL)))
        whole += 1UL;
    return (int)whole;
}

#define D_FROM_F(f)   sd_from_float(f)
#define D_FROM_U(n)   sd_from_uint(n)
#define D_BITS(u)     ((ulong)(u))
#define D_ADD(a, b)   sd_add((a), (b))
#define D_SUB(a, b)   sd_add((a), (b) ^ SD_SIGN)
#define D_MUL(a, b)   sd_mul((a), (b))
#define D_DIV(a, b)   sd_div((a), (b))
#define D_LT(a, b)    (sd_key(a) < sd_key(b))
#define D_LE(a, b)    (sd_key(a) <= sd_key(b))
#define D_EQ(a, b)    (sd_key(a) == sd_key(b))

#endif

#define D_GT(a, b)    D_LT(b, a)
#define D_GE(a, b)    D_LE(b, a)
#define D_MIN(a, b)   (D_LT(b, a) ? (b) : (a))
#define D_MAX(a, b)   (D_LT(a, b) ? (b) : (a))
