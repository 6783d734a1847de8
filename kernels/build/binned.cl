/* The kd-tree builder (core/accel/binned.py; docs/kdtree_native.md): breadth first, one level
   of the tree per round of launches, every node of the level at once.

   Per level: each node chooses its split by the SAH (`choose_nodes`: one work-item per node;
   nodes of more than KD_BIG_REFS references are binned by chunks of their references instead,
   `bin_chunks` and `choose_big`), the host sums the level's counts by blocks of nodes
   (`level_sums`) into places, `emit` writes the level's final node words and the next level's
   nodes, and `scatter_nodes` / `scatter_chunks` move every reference to its children (clipping
   the straddlers) or into its leaf's list.

   The SAH: binned at every node of more than KD_EXACT_MAX references (bins = clamp(2 N,
   KD_MIN_BINS, KD_MAX_BINS) planes per axis, plus the cuts at the node's tight reference bounds),
   every reference bound a candidate below that. A reference's bin is the number of planes at or
   below its low end (strictly below its high end), found from a float estimate and corrected
   against the planes themselves, so the counts at each plane are exact: below = low end < plane,
   above = high end > plane, planar (flat at the plane) to the cheaper side; the children receive
   exactly these counts of references. Costs in float32 scaled by the cell's half area (no
   division), first minimum in the order axis, plane. Automatic termination with the bad-refine
   allowance and the depth cap (docs/kdtree.md).

   Straddlers are clipped exactly (Sutherland-Hodgman in double, against the faces of the
   reference's box that the triangle crosses, then cut by the plane), their halves' boxes rounded
   outward to float32 and clamped; a half of zero area is not kept. Its place in the child was
   counted before the clipping, so it is left as a hole (triangle HOLE), which the next level
   skips and never copies. So every count is known before any reference moves, and the build
   needs one pass over the references to choose and one to move them per level.

   Deterministic: integer counts, float32 and double operations in a fixed order in one
   work-item, sums over chunks and blocks in index order; no atomics, no float division that
   decides anything (only correctly rounded double division), FP_CONTRACT OFF. So the tree
   depends only on the geometry and the parameters, not on thread counts, work-group sizes,
   launch pieces or KD_BIG_REFS / chunk sizes. Needs cl_khr_fp64.

   The kernels, in the order core/accel/binned.py's KERNEL_FILES concatenates them (each file
   uses what the ones before it define): this file, the records and the SAH search (binning,
   the exact candidates); binned_level.cl, the level's kernels (the choice, big nodes' chunks,
   the level's sums, emit, the straddlers' clipping and the scatters, the first references). */

#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define HOLE 0xFFFFFFFFu
/* Helpers of the hot loops: PoCL otherwise calls some of them out of line. */
#define HOT inline __attribute__((always_inline))
#define NO_CHILD 0xFFFFFFFFu

/* A reference: its box's lo in lo.xyz and triangle in lo.w (uint bits), hi in hi.xyz. */
typedef struct {
    float4 lo;
    float4 hi;
} Ref;

/* A node of the level being split (BIN_NODE rows, core/layout.py). */
typedef struct {
    float lo[3];
    float hi[3];
    uint first, count, bad, unused;
} LevelNode;

/* A node's decision (choose_*) and, after emit, where its children and leaf list go. */
typedef struct {
    uint flags;          /* SPLIT_LEAF, the axis in bits 1-2, SPLIT_PLANAR_ABOVE */
    float plane;
    uint below, above;   /* places for the children's references (holes included) */
    uint valid;          /* references (holes left out) */
    uint bad;            /* bad refines on the path, this node's included */
    uint child;          /* emit: the first child's index in the next level */
    uint base;           /* emit: the below child's first reference in the next level, or the
                            leaf's first entry in the level's leaf list */
} Split;

#define SPLIT_LEAF 1u
#define SPLIT_AXIS(f) (((f) >> 1) & 3u)
#define SPLIT_PLANAR_ABOVE 8u

HOT uint ref_tri(Ref r)
{
    return as_uint(r.lo.w);
}

HOT float lane(float4 v, int a)
{
    return a == 0 ? v.x : (a == 1 ? v.y : v.z);
}

HOT float f_min(float a, float b)
{
    return b < a ? b : a;
}

HOT float f_max(float a, float b)
{
    return a < b ? b : a;
}

HOT double d_min(double a, double b)
{
    return b < a ? b : a;
}

HOT double d_max(double a, double b)
{
    return a < b ? b : a;
}

/* ----------------------------------------------------------------------------------------
   The SAH. A cell's dimensions are scaled by `pow2` (a power of two near 1 / the scene's
   size: exact, keeps products far from float32's limits). Costs are multiplied by the cell's
   half area A: a split costs KT A + KI (A_below n_below + A_above n_above), times KD_LAMBDA
   when a side receives nothing; a leaf KI n A. */

typedef struct {
    float lo[3], hi[3];
    float d[3];          /* scaled dimensions */
    float area;          /* scaled half area */
    float leaf;          /* scaled cost of a leaf of the node's valid references */
    float best;          /* the best split's scaled cost so far */
    int axis;
    float plane;
    uint planar_above, below, above;
    int found;
} Search;

inline void search_init(Search* s, const float* lo, const float* hi, uint n, float pow2)
{
    for (int a = 0; a < 3; a++) {
        s->lo[a] = lo[a];
        s->hi[a] = hi[a];
        s->d[a] = (hi[a] - lo[a]) * pow2;
    }
    s->area = s->d[0] * s->d[1] + s->d[1] * s->d[2] + s->d[2] * s->d[0];
    s->leaf = KD_KI * (float)n * s->area;
    s->best = INFINITY;
    s->found = 0;
    s->axis = 0;
    s->plane = 0.0f;
    s->planar_above = 0u;
    s->below = s->above = 0u;
}

/* Consider the plane p on axis a (strictly inside the cell) with nb references below it, na
   above it and the flat ones at p to the side `up` says (1: above). */
HOT void consider_side(Search* s, int a, float p, uint nb, uint na, uint up, float pow2)
{
    float side = s->d[(a + 1) % 3] + s->d[(a + 2) % 3];
    float face = s->d[(a + 1) % 3] * s->d[(a + 2) % 3];
    float ab = (p - s->lo[a]) * pow2 * side + face;
    float aa = (s->hi[a] - p) * pow2 * side + face;
    float cost = KD_KT * s->area + KD_KI * (ab * (float)nb + aa * (float)na);
    if (nb == 0u || na == 0u)
        cost *= KD_LAMBDA;
    if (cost < s->best) {
        s->best = cost;
        s->found = 1;
        s->axis = a;
        s->plane = p;
        s->planar_above = up;
        s->below = nb;
        s->above = na;
    }
}

/* The same with np references flat at p: on the cheaper side (below when equal). */
HOT void consider(Search* s, int a, float p, uint nb, uint na, uint np, float pow2)
{
    consider_side(s, a, p, nb + np, na, 0u, pow2);
    if (np)
        consider_side(s, a, p, nb, na + np, 1u, pow2);
}

/* The bin planes of one axis: p[1 .. bins-1] = lo + k ((hi - lo) / bins), in double, rounded
   to nearest float32 (correctly rounded operations: the same on every device). */
inline void bin_planes(float lo, float hi, uint bins, float* p)
{
    double step = ((double)hi - (double)lo) / (double)bins;
    for (uint k = 1u; k < bins; k++)
        p[k] = (float)((double)lo + step * (double)k) + 0.0f;
}

/* Planes at or below x (at_or_below) or strictly below it, from an estimate: exact. */
HOT uint bin_of(float x, float lo, float scale, uint bins, const float* p, int at_or_below)
{
    float e = (x - lo) * scale;
    int g = e > 0.0f ? (int)e : 0;
    if (g > (int)bins - 1 || !(e == e))
        g = (int)bins - 1;
    if (at_or_below) {
        while (g < (int)bins - 1 && p[g + 1] <= x)
            g++;
        while (g > 0 && p[g] > x)
            g--;
    } else {
        while (g < (int)bins - 1 && p[g + 1] < x)
            g++;
        while (g > 0 && p[g] >= x)
            g--;
    }
    return (uint)g;
}

inline uint bin_count(uint n)
{
    uint b = 2u * n;
    return b < KD_MIN_BINS ? KD_MIN_BINS : (b > KD_MAX_BINS ? KD_MAX_BINS : b);
}

/* A node's (or a chunk's) histogram: per axis, counts of low-end bins, high-end bins and flat
   references by plane; the tight bounds of the references and how many there are. */
#define HIST_AXIS (3u * KD_MAX_BINS)
#define HIST_WORDS (3u * HIST_AXIS + 7u)
#define HIST_LO(a, k) ((a) * HIST_AXIS + (k))
#define HIST_HI(a, k) ((a) * HIST_AXIS + KD_MAX_BINS + (k))
#define HIST_FLAT(a, k) ((a) * HIST_AXIS + 2u * KD_MAX_BINS + (k))
#define HIST_TIGHT (3u * HIST_AXIS)      /* 6 words: tight lo, tight hi (float bits) */
#define HIST_VALID (3u * HIST_AXIS + 6u)

typedef struct {
    float p[3][KD_MAX_BINS + 1];
    float scale[3];
    uint bins;
} Planes;

inline void planes_of(Planes* pl, const float* lo, const float* hi, uint n)
{
    pl->bins = bin_count(n);
    for (int a = 0; a < 3; a++) {
        bin_planes(lo[a], hi[a], pl->bins, pl->p[a]);
        pl->scale[a] = (float)pl->bins / (hi[a] - lo[a]);
    }
}

/* The histogram of references [0, count) of r (holes left out) in the node's planes, their
   tight bounds and how many there are (h[HIST_VALID]). */
inline void bin_refs(__global const Ref* r, uint count, const Planes* pl, const float* cell_lo,
                     uint* h)
{
    for (uint k = 0u; k < HIST_WORDS; k++)
        h[k] = 0u;
    float tlo[3] = {INFINITY, INFINITY, INFINITY}, thi[3] = {-INFINITY, -INFINITY, -INFINITY};
    uint n = 0u;
    for (uint j = 0u; j < count; j++) {
        Ref x = r[j];
        if (ref_tri(x) == HOLE)
            continue;
        n++;
        for (int a = 0; a < 3; a++) {
            float x0 = lane(x.lo, a), x1 = lane(x.hi, a);
            tlo[a] = f_min(tlo[a], x0);
            thi[a] = f_max(thi[a], x1);
            uint g0 = bin_of(x0, cell_lo[a], pl->scale[a], pl->bins, pl->p[a], 1);
            uint g1 = bin_of(x1, cell_lo[a], pl->scale[a], pl->bins, pl->p[a], 0);
            h[HIST_LO(a, g0)]++;
            h[HIST_HI(a, g1)]++;
            if (x0 == x1 && g0 > g1)
                h[HIST_FLAT(a, g0)]++;
        }
    }
    for (int a = 0; a < 3; a++) {
        h[HIST_TIGHT + a] = as_uint(tlo[a]);
        h[HIST_TIGHT + 3 + a] = as_uint(thi[a]);
    }
    h[HIST_VALID] = n;
}

/* Every plane of the histogram and the tight-bound cuts. */
inline void consider_bins(Search* s, const uint* h, const Planes* pl, uint n, float pow2)
{
    for (int a = 0; a < 3; a++) {
        float tlo = as_float(h[HIST_TIGHT + a]), thi = as_float(h[HIST_TIGHT + 3 + a]);
        uint below = 0u, above = n;
        for (uint k = 1u; k < pl->bins; k++) {
            below += h[HIST_LO(a, k - 1u)];
            above -= h[HIST_HI(a, k - 1u)];
            float p = pl->p[a][k];
            if (!(s->lo[a] < p && p < s->hi[a]))
                continue;
            if (k + 1u < pl->bins && pl->p[a][k + 1u] == p)
                continue;       /* equal planes: the last one holds the flat references */
            consider(s, a, p, below, above, h[HIST_FLAT(a, k)], pow2);
        }
        /* The tight-bound cuts: every reference on one side, the flat ones at the cut too. */
        if (s->lo[a] < tlo && tlo < s->hi[a])
            consider_side(s, a, tlo, 0u, n, 1u, pow2);
        if (s->lo[a] < thi && thi < s->hi[a])
            consider_side(s, a, thi, n, 0u, 0u, pow2);
    }
}

/* Leaf or split (automatic termination, bad refines as pbrt, never for small nodes). */
inline void decide(__global Split* out, const Search* s, uint n, uint bad, uint level,
                   uint depth_cap)
{
    Split r;
    r.valid = n;
    r.bad = bad;
    r.flags = SPLIT_LEAF;
    r.plane = 0.0f;
    r.below = r.above = 0u;
    r.child = NO_CHILD;
    r.base = 0u;
    if (n > 0u && level < depth_cap && s->found) {
        int good = s->best < s->leaf;
        if (good || (n >= KD_SMALL_NODE && bad + 1u < KD_MAX_BAD)) {
            r.flags = ((uint)s->axis << 1) | (s->planar_above ? SPLIT_PLANAR_ABOVE : 0u);
            r.plane = s->plane;
            r.below = s->below;
            r.above = s->above;
            r.bad = bad + (good ? 0u : 1u);
        }
    }
    *out = r;
}

/* ----------------------------------------------------------------------------------------
   Exact candidates of a node of at most KD_EXACT_MAX references on one axis: every reference
   bound, and the bin planes (only they can cut the empty space off references that lie in a
   face of the cell, a floor in its cell's floor), in this order; counted 8 candidates at a
   time against every reference. */

#define EXACT_GROUPS ((2u * KD_EXACT_MAX + KD_MAX_BINS + 7u) / 8u)

/* Whether any lane of m is set (PoCL calls any() out of line). */
HOT int any8(int8 m)
{
    int4 m4 = m.lo | m.hi;
    int2 m2 = m4.lo | m4.hi;
    return (m2.x | m2.y) != 0;
}

inline void exact_axis(Search* s, int a, const float* lo, const float* hi, uint n, uint bins,
                       float pow2)
{
    /* Vectors and their lanes through pointers: PoCL calls vload8 / vstore8 / select out of
       line. */
    float8 groups[EXACT_GROUPS];
    float* cand = (float*)groups;
    uint c = 0u;
    for (uint j = 0u; j < n; j++)
        cand[c++] = lo[j];
    for (uint j = 0u; j < n; j++)
        cand[c++] = hi[j];
    float planes[KD_MAX_BINS + 1];
    bin_planes(s->lo[a], s->hi[a], bins, planes);
    for (uint k = 1u; k < bins; k++)
        cand[c++] = planes[k];
    while (c & 7u)
        cand[c++] = NAN;            /* never strictly inside the cell */
    float side = s->d[(a + 1) % 3] + s->d[(a + 2) % 3];
    float face = s->d[(a + 1) % 3] * s->d[(a + 2) % 3];
    float base = KD_KT * s->area;
    /* The flat references (lo == hi), counted apart: most nodes have none. */
    float flat[KD_EXACT_MAX];
    uint m = 0u;
    for (uint j = 0u; j < n; j++)
        if (lo[j] == hi[j])
            flat[m++] = lo[j];
    for (uint g = 0u; g < c / 8u; g++) {
        float8 p = groups[g];
        int8 nb = 0, na = 0, np = 0;
        for (uint j = 0u; j < n; j++) {
            nb -= lo[j] < p;          /* a true comparison is -1 */
            na -= hi[j] > p;
        }
        for (uint j = 0u; j < m; j++)
            np -= flat[j] == p;
        float8 ab = (p - s->lo[a]) * pow2 * side + face;
        float8 aa = (s->hi[a] - p) * pow2 * side + face;
        float8 fb = convert_float8(nb), fa = convert_float8(na), fp = convert_float8(np);
        float8 cost0 = base + KD_KI * (ab * (fb + fp) + aa * fa);
        float8 cost1 = base + KD_KI * (ab * fb + aa * (fa + fp));
        cost0 = ((nb + np == 0) | (na == 0)) ? cost0 * KD_LAMBDA : cost0;
        cost1 = ((nb == 0) | (na + np == 0)) ? cost1 * KD_LAMBDA : cost1;
        int8 inside = (s->lo[a] < p) & (p < s->hi[a]);
        if (!any8(inside & ((cost0 < s->best) | ((np != 0) & (cost1 < s->best)))))
            continue;           /* nothing better in this group */
        const float *cp = (const float*)&p, *c0 = (const float*)&cost0,
                    *c1 = (const float*)&cost1;
        const int *bn = (const int*)&nb, *an = (const int*)&na, *pn = (const int*)&np,
                  *ok = (const int*)&inside;
        for (int k = 0; k < 8; k++) {
            if (!ok[k])
                continue;
            if (c0[k] < s->best) {
                s->best = c0[k];
                s->found = 1;
                s->axis = a;
                s->plane = cp[k];
                s->planar_above = 0u;
                s->below = (uint)(bn[k] + pn[k]);
                s->above = (uint)an[k];
            }
            if (pn[k] && c1[k] < s->best) {
                s->best = c1[k];
                s->found = 1;
                s->axis = a;
                s->plane = cp[k];
                s->planar_above = 1u;
                s->below = (uint)bn[k];
                s->above = (uint)(an[k] + pn[k]);
            }
        }
    }
}
