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
   launch pieces or KD_BIG_REFS / chunk sizes. Needs cl_khr_fp64. */

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

/* ----------------------------------------------------------------------------------------
   choose_nodes: one work-item per node of at most KD_BIG_REFS references. */

__kernel void choose_nodes(__global const LevelNode* restrict nodes,
                           __global const Ref* restrict refs,
                           __global Split* restrict splits,
                           uint n_nodes, uint level, uint depth_cap, float pow2)
{
    uint i = (uint)get_global_id(0);
    if (i >= n_nodes)
        return;
    LevelNode node = nodes[i];
    if (node.count > KD_BIG_REFS)
        return;                          /* choose_big's */
    __global const Ref* r = refs + node.first;
    Search s;
    uint n = 0u;
    if (node.count <= KD_EXACT_MAX) {
        float lo[3][KD_EXACT_MAX], hi[3][KD_EXACT_MAX];
        for (uint j = 0u; j < node.count; j++) {
            Ref x = r[j];
            if (ref_tri(x) == HOLE)
                continue;
            for (int a = 0; a < 3; a++) {
                lo[a][n] = lane(x.lo, a);
                hi[a][n] = lane(x.hi, a);
            }
            n++;
        }
        search_init(&s, node.lo, node.hi, n, pow2);
        if (level < depth_cap)
            for (int a = 0; a < 3; a++)
                exact_axis(&s, a, lo[a], hi[a], n, bin_count(node.count), pow2);
    } else {
        Planes pl;
        planes_of(&pl, node.lo, node.hi, node.count);
        uint h[HIST_WORDS];
        bin_refs(r, node.count, &pl, node.lo, h);
        n = h[HIST_VALID];
        search_init(&s, node.lo, node.hi, n, pow2);
        if (level < depth_cap)
            consider_bins(&s, h, &pl, n, pow2);
    }
    decide(splits + i, &s, n, node.bad, level, depth_cap);
}

/* ----------------------------------------------------------------------------------------
   Big nodes: histograms per chunk of references (bin_chunks), summed in chunk order per node
   (choose_big), which also gives each chunk its first places in the children. Chunk rows:
   BIN_CHUNK (node, first, count, and the places choose_big writes); big node rows:
   BIN_BIG (node, first chunk, chunks). */

__kernel void bin_chunks(__global const LevelNode* restrict nodes,
                         __global const Ref* restrict refs,
                         __global const uint* restrict chunks,
                         __global uint* restrict hist, uint n_chunks)
{
    uint c = (uint)get_global_id(0);
    if (c >= n_chunks)
        return;
    __global const uint* row = chunks + BIN_CHUNK_COLUMNS * c;
    LevelNode node = nodes[row[BIN_CHUNK_NODE]];
    Planes pl;
    planes_of(&pl, node.lo, node.hi, node.count);
    uint h[HIST_WORDS];
    bin_refs(refs + row[BIN_CHUNK_FIRST], row[BIN_CHUNK_COUNT], &pl, node.lo, h);
    __global uint* out = hist + (size_t)HIST_WORDS * c;
    for (uint k = 0u; k < HIST_WORDS; k++)
        out[k] = h[k];
}

/* A chunk's references below / above the chosen plane, from its histogram. */
inline void chunk_sides(__global const uint* h, const Split* d, const Planes* pl,
                        const LevelNode* node, uint* below, uint* above)
{
    uint n = h[HIST_VALID];
    if (d->flags & SPLIT_LEAF) {
        *below = *above = 0u;
        return;
    }
    int a = (int)SPLIT_AXIS(d->flags);
    float p = d->plane;
    /* The chosen plane is a bin plane (the last of equal ones) or a tight-bound cut. */
    uint k = 0u;
    for (uint j = 1u; j < pl->bins; j++)
        if (pl->p[a][j] == p)
            k = j;
    uint nb = 0u, na = 0u, np = 0u;
    if (k) {
        for (uint j = 0u; j < k; j++)
            nb += h[HIST_LO(a, j)];
        for (uint j = k; j < pl->bins; j++)
            na += h[HIST_HI(a, j)];
        np = h[HIST_FLAT(a, k)];
    } else {
        /* A tight-bound cut of the node: every reference of the chunk on one side. */
        int low_cut = d->below == 0u;
        nb = low_cut ? 0u : n;
        na = low_cut ? n : 0u;
    }
    if (d->flags & SPLIT_PLANAR_ABOVE)
        na += np;
    else
        nb += np;
    *below = nb;
    *above = na;
}

__kernel void choose_big(__global const LevelNode* restrict nodes,
                         __global const uint* restrict big,
                         __global uint* restrict chunks,
                         __global const uint* restrict hist,
                         __global Split* restrict splits,
                         uint n_big, uint level, uint depth_cap, float pow2)
{
    uint b = (uint)get_global_id(0);
    if (b >= n_big)
        return;
    __global const uint* row = big + BIN_BIG_COLUMNS * b;
    uint i = row[BIN_BIG_NODE], first = row[BIN_BIG_FIRST_CHUNK], count = row[BIN_BIG_CHUNKS];
    LevelNode node = nodes[i];
    Planes pl;
    planes_of(&pl, node.lo, node.hi, node.count);
    uint h[HIST_WORDS];
    for (uint k = 0u; k < HIST_WORDS; k++)
        h[k] = 0u;
    for (int a = 0; a < 3; a++) {
        h[HIST_TIGHT + a] = as_uint(INFINITY);
        h[HIST_TIGHT + 3 + a] = as_uint(-INFINITY);
    }
    for (uint c = first; c < first + count; c++) {
        __global const uint* hc = hist + (size_t)HIST_WORDS * c;
        for (uint k = 0u; k < 3u * HIST_AXIS; k++)
            h[k] += hc[k];
        h[HIST_VALID] += hc[HIST_VALID];
        for (int a = 0; a < 3; a++) {
            h[HIST_TIGHT + a] = as_uint(f_min(as_float(h[HIST_TIGHT + a]),
                                              as_float(hc[HIST_TIGHT + a])));
            h[HIST_TIGHT + 3 + a] = as_uint(f_max(as_float(h[HIST_TIGHT + 3 + a]),
                                                  as_float(hc[HIST_TIGHT + 3 + a])));
        }
    }
    uint n = h[HIST_VALID];
    Search s;
    search_init(&s, node.lo, node.hi, n, pow2);
    if (level < depth_cap)
        consider_bins(&s, h, &pl, n, pow2);
    decide(splits + i, &s, n, node.bad, level, depth_cap);
    Split d = splits[i];
    /* Each chunk's first places among its node's children's references (and leaf entries). */
    uint at_below = 0u, at_above = 0u, at_leaf = 0u;
    for (uint c = first; c < first + count; c++) {
        __global const uint* hc = hist + (size_t)HIST_WORDS * c;
        __global uint* cr = chunks + BIN_CHUNK_COLUMNS * c;
        uint nb, na;
        chunk_sides(hc, &d, &pl, &node, &nb, &na);
        cr[BIN_CHUNK_BELOW] = at_below;
        cr[BIN_CHUNK_ABOVE] = at_above;
        cr[BIN_CHUNK_LEAF] = at_leaf;
        at_below += nb;
        at_above += na;
        at_leaf += hc[HIST_VALID];
    }
}

/* ----------------------------------------------------------------------------------------
   The level's sums by blocks of KD_SUM_BLOCK nodes (BIN_SUMS rows): the host turns them into
   each block's first places (BIN_PLACES rows) for emit. */

inline void sah_term(const LevelNode* node, const Split* d, float pow2, float inv_root,
                     long* sah)
{
    float d0 = (node->hi[0] - node->lo[0]) * pow2, d1 = (node->hi[1] - node->lo[1]) * pow2,
          d2 = (node->hi[2] - node->lo[2]) * pow2;
    float share = (d0 * d1 + d1 * d2 + d2 * d0) * inv_root;
    float cost = (d->flags & SPLIT_LEAF) ? KD_KI * (float)d->valid * share : KD_KT * share;
    *sah += convert_long_rte(cost * 4294967296.0f);
}

__kernel void level_sums(__global const LevelNode* restrict nodes,
                         __global const Split* restrict splits,
                         __global uint* restrict sums, uint n_nodes, float pow2,
                         float inv_root)
{
    uint blk = (uint)get_global_id(0);
    uint first = blk * KD_SUM_BLOCK;
    if (first >= n_nodes)
        return;
    uint last = min(first + KD_SUM_BLOCK, n_nodes);
    uint inner = 0u, places = 0u, leaf_refs = 0u, leaves = 0u, empty = 0u, widest = 0u;
    long sah = 0;
    for (uint i = first; i < last; i++) {
        Split d = splits[i];
        LevelNode node = nodes[i];
        sah_term(&node, &d, pow2, inv_root, &sah);
        if (d.flags & SPLIT_LEAF) {
            leaves++;
            empty += d.valid == 0u;
            leaf_refs += d.valid;
        } else {
            inner++;
            places += d.below + d.above;
            widest = max(widest, max(d.below, d.above));
        }
    }
    __global uint* row = sums + BIN_SUMS_COLUMNS * blk;
    row[BIN_SUMS_INNER] = inner;
    row[BIN_SUMS_PLACES] = places;
    row[BIN_SUMS_LEAF_REFS] = leaf_refs;
    row[BIN_SUMS_LEAVES] = leaves;
    row[BIN_SUMS_EMPTY_LEAVES] = empty;
    row[BIN_SUMS_WIDEST] = widest;
    row[BIN_SUMS_SAH_LOW] = (uint)((ulong)sah & 0xFFFFFFFFUL);
    row[BIN_SUMS_SAH_HIGH] = (uint)((ulong)sah >> 32);
}

/* The level's node words, at level_base in the tree's nodes (final: child index and leaf
   offset absolute), and the next level's nodes; every split record learns its children's
   places and its leaf's place in the tree's lists. */
__kernel void emit(__global const LevelNode* restrict nodes,
                   __global Split* restrict splits,
                   __global const uint* restrict places,
                   __global uint2* restrict words,
                   __global LevelNode* restrict next,
                   uint n_nodes, uint level_base, uint next_base, uint leaf_base)
{
    uint blk = (uint)get_global_id(0);
    uint first = blk * KD_SUM_BLOCK;
    if (first >= n_nodes)
        return;
    uint last = min(first + KD_SUM_BLOCK, n_nodes);
    __global const uint* at = places + BIN_PLACES_COLUMNS * blk;
    uint inner = at[BIN_PLACES_INNER], place = at[BIN_PLACES_PLACES];
    uint leaf = at[BIN_PLACES_LEAF_REFS];
    for (uint i = first; i < last; i++) {
        Split d = splits[i];
        LevelNode node = nodes[i];
        if (d.flags & SPLIT_LEAF) {
            words[level_base + i] = (uint2)(KD_PLAIN_TAG_PUT(KD_LEAF_TAG)
                                            | KD_PLAIN_FIELD_PUT(d.valid), leaf_base + leaf);
            d.base = leaf_base + leaf;
            leaf += d.valid;
        } else {
            int a = (int)SPLIT_AXIS(d.flags);
            words[level_base + i] = (uint2)(KD_PLAIN_TAG_PUT(a)
                                            | KD_PLAIN_FIELD_PUT(next_base + 2u * inner),
                                            as_uint(d.plane));
            d.child = 2u * inner;
            d.base = place;
            LevelNode c = node;
            c.hi[a] = d.plane;
            c.first = place;
            c.count = d.below;
            c.bad = d.bad;
            c.unused = 0u;
            next[2u * inner] = c;
            c = node;
            c.lo[a] = d.plane;
            c.first = place + d.below;
            c.count = d.above;
            c.bad = d.bad;
            c.unused = 0u;
            next[2u * inner + 1u] = c;
            inner++;
            place += d.below + d.above;
        }
        splits[i] = d;
    }
}

/* ----------------------------------------------------------------------------------------
   The perfect split of a straddler: the triangle clipped to its reference's box (which is its
   piece of the cell: the piece's box, rounded outward and clamped to the cell), then cut by
   the plane; each half's box rounded outward to float32 and clamped to the half of the box.
   Returns bit 1: the below half kept, bit 2: the above half kept (a half of zero area - fewer
   than 3 vertices, or flat in an axis where the triangle is not - only touches that side). */

#define POLY_MAX 10

inline int clip_polygon(double (*in)[3], int n, double (*out)[3], int a, double v, int keep_below)
{
    int m = 0;
    for (int i = 0; i < n; i++) {
        int j = i + 1 == n ? 0 : i + 1;
        double di = keep_below ? v - in[i][a] : in[i][a] - v;
        double dj = keep_below ? v - in[j][a] : in[j][a] - v;
        if (di >= 0.0)
            for (int b = 0; b < 3; b++)
                out[m][b] = in[i][b];
        m += di >= 0.0;
        if ((di > 0.0 && dj < 0.0) || (di < 0.0 && dj > 0.0)) {
            double t = di / (di - dj);
            for (int b = 0; b < 3; b++)
                out[m][b] = in[i][b] + t * (in[j][b] - in[i][b]);
            out[m][a] = v;
            m++;
        }
    }
    return m;
}

inline int half_kept(const float* lo, const float* hi, const float* tlo, const float* thi,
                     int verts)
{
    if (verts < 3)
        return 0;
    for (int b = 0; b < 3; b++)
        if (lo[b] == hi[b] && tlo[b] < thi[b])
            return 0;
    return 1;
}

inline uint split_straddler(__global const float* restrict corners, Ref r, int axis, float plane,
                            Ref* below, Ref* above)
{
    uint tri = ref_tri(r);
    double poly[2][POLY_MAX][3];
    float tlo[3], thi[3], blo[3], bhi[3];
    __global const float* c = corners + (size_t)9 * tri;
    for (int k = 0; k < 3; k++)
        for (int b = 0; b < 3; b++)
            poly[0][k][b] = (double)c[3 * k + b];
    for (int b = 0; b < 3; b++) {
        tlo[b] = f_min(f_min(c[b], c[3 + b]), c[6 + b]);
        thi[b] = f_max(f_max(c[b], c[3 + b]), c[6 + b]);
        blo[b] = lane(r.lo, b);
        bhi[b] = lane(r.hi, b);
    }
    int n = 3, cur = 0;
    for (int b = 0; b < 3 && n >= 3; b++) {
        if (tlo[b] < blo[b]) {
            n = clip_polygon(poly[cur], n, poly[1 - cur], b, (double)blo[b], 0);
            cur = 1 - cur;
        }
        if (thi[b] > bhi[b] && n >= 3) {
            n = clip_polygon(poly[cur], n, poly[1 - cur], b, (double)bhi[b], 1);
            cur = 1 - cur;
        }
    }
    double lo2[2][3], hi2[2][3];
    int verts[2] = {0, 0};
    for (int s = 0; s < 2; s++)
        for (int b = 0; b < 3; b++) {
            lo2[s][b] = INFINITY;
            hi2[s][b] = -INFINITY;
        }
    double p = (double)plane;
    if (n >= 3)
        for (int i = 0; i < n; i++) {
            int j = i + 1 == n ? 0 : i + 1;
            double di = poly[cur][i][axis] - p, dj = poly[cur][j][axis] - p;
            for (int s = 0; s < 2; s++)
                if (s == 0 ? di <= 0.0 : di >= 0.0) {
                    verts[s]++;
                    for (int b = 0; b < 3; b++) {
                        lo2[s][b] = d_min(lo2[s][b], poly[cur][i][b]);
                        hi2[s][b] = d_max(hi2[s][b], poly[cur][i][b]);
                    }
                }
            if ((di > 0.0 && dj < 0.0) || (di < 0.0 && dj > 0.0)) {
                double t = di / (di - dj);
                double x[3];
                for (int b = 0; b < 3; b++)
                    x[b] = poly[cur][i][b] + t * (poly[cur][j][b] - poly[cur][i][b]);
                x[axis] = p;
                for (int s = 0; s < 2; s++) {
                    verts[s]++;
                    for (int b = 0; b < 3; b++) {
                        lo2[s][b] = d_min(lo2[s][b], x[b]);
                        hi2[s][b] = d_max(hi2[s][b], x[b]);
                    }
                }
            }
        }
    uint kept = 0u;
    for (int s = 0; s < 2; s++) {
        float lo[3], hi[3];
        for (int b = 0; b < 3; b++) {
            lo[b] = verts[s] ? f_max(convert_float_rtn(lo2[s][b]) + 0.0f, blo[b]) : 0.0f;
            hi[b] = verts[s] ? f_min(convert_float_rtp(hi2[s][b]) + 0.0f, bhi[b]) : 0.0f;
        }
        if (s == 0)
            hi[axis] = f_min(hi[axis], plane);
        else
            lo[axis] = f_max(lo[axis], plane);
        if (!half_kept(lo, hi, tlo, thi, verts[s]))
            continue;
        kept |= 1u << s;
        Ref h;
        h.lo = (float4)(lo[0], lo[1], lo[2], as_float(tri));
        h.hi = (float4)(hi[0], hi[1], hi[2], 0.0f);
        if (s == 0)
            *below = h;
        else
            *above = h;
    }
    return kept;
}

/* Move references [first, first + count) of a node with decision d: to its leaf list, or to
   its children in the next level (straddlers clipped; a half not kept leaves a hole). */
inline void move_refs(__global const Ref* restrict refs, uint first, uint count, const Split* d,
                      uint below_at, uint above_at, uint leaf_at,
                      __global const float* restrict corners, __global Ref* restrict next,
                      __global uint* restrict leaf_tris)
{
    if (d->flags & SPLIT_LEAF) {
        for (uint j = 0u; j < count; j++) {
            uint t = ref_tri(refs[first + j]);
            if (t != HOLE)
                leaf_tris[leaf_at++] = t;
        }
        return;
    }
    int a = (int)SPLIT_AXIS(d->flags);
    float p = d->plane;
    int planar_above = (d->flags & SPLIT_PLANAR_ABOVE) != 0u;
    Ref hole;
    hole.lo = (float4)(0.0f, 0.0f, 0.0f, as_float(HOLE));
    hole.hi = (float4)(0.0f);
    for (uint j = 0u; j < count; j++) {
        Ref r = refs[first + j];
        if (ref_tri(r) == HOLE)
            continue;
        float lo = lane(r.lo, a), hi = lane(r.hi, a);
        int goes_below = lo < p, goes_above = hi > p;
        if (lo == p && hi == p) {
            goes_below = !planar_above;
            goes_above = planar_above;
        }
        if (goes_below && goes_above) {
            Ref b = hole, c = hole;
            split_straddler(corners, r, a, p, &b, &c);
            next[below_at++] = b;
            next[above_at++] = c;
        } else if (goes_below) {
            next[below_at++] = r;
        } else {
            next[above_at++] = r;
        }
    }
}

__kernel void scatter_nodes(__global const LevelNode* restrict nodes,
                            __global const Ref* restrict refs,
                            __global const Split* restrict splits,
                            __global const float* restrict corners,
                            __global Ref* restrict next,
                            __global uint* restrict leaf_tris, uint n_nodes)
{
    uint i = (uint)get_global_id(0);
    if (i >= n_nodes)
        return;
    LevelNode node = nodes[i];
    if (node.count > KD_BIG_REFS)
        return;                          /* scatter_chunks' */
    Split d = splits[i];
    move_refs(refs, node.first, node.count, &d, d.base, d.base + d.below, d.base, corners, next,
              leaf_tris);
}

__kernel void scatter_chunks(__global const Ref* restrict refs,
                             __global const uint* restrict chunks,
                             __global const Split* restrict splits,
                             __global const float* restrict corners,
                             __global Ref* restrict next,
                             __global uint* restrict leaf_tris, uint n_chunks)
{
    uint c = (uint)get_global_id(0);
    if (c >= n_chunks)
        return;
    __global const uint* row = chunks + BIN_CHUNK_COLUMNS * c;
    Split d = splits[row[BIN_CHUNK_NODE]];
    move_refs(refs, row[BIN_CHUNK_FIRST], row[BIN_CHUNK_COUNT], &d, d.base + row[BIN_CHUNK_BELOW],
              d.base + d.below + row[BIN_CHUNK_ABOVE], d.base + row[BIN_CHUNK_LEAF], corners, next,
              leaf_tris);
}

/* ----------------------------------------------------------------------------------------
   The first references: each triangle's box and corners; a triangle of zero area (its cross
   product exactly zero in double) is a hole from the start. */

__kernel void first_refs(__global const float* restrict vertices,
                         __global const uint* restrict triangles,
                         __global float* restrict corners,
                         __global Ref* restrict refs, uint n)
{
    uint t = (uint)get_global_id(0);
    if (t >= n)
        return;
    float v[3][3];
    for (int k = 0; k < 3; k++) {
        uint at = triangles[3 * t + k];
        for (int b = 0; b < 3; b++) {
            v[k][b] = vertices[3 * at + b] + 0.0f;
            corners[(size_t)9 * t + 3 * k + b] = v[k][b];
        }
    }
    double e1[3], e2[3];
    for (int b = 0; b < 3; b++) {
        e1[b] = (double)v[1][b] - (double)v[0][b];
        e2[b] = (double)v[2][b] - (double)v[0][b];
    }
    double nx = e1[1] * e2[2] - e1[2] * e2[1];
    double ny = e1[2] * e2[0] - e1[0] * e2[2];
    double nz = e1[0] * e2[1] - e1[1] * e2[0];
    Ref r;
    float lo[3], hi[3];
    for (int b = 0; b < 3; b++) {
        lo[b] = f_min(f_min(v[0][b], v[1][b]), v[2][b]);
        hi[b] = f_max(f_max(v[0][b], v[1][b]), v[2][b]);
    }
    uint tri = (nx != 0.0 || ny != 0.0 || nz != 0.0) ? t : HOLE;
    r.lo = (float4)(lo[0], lo[1], lo[2], as_float(tri));
    r.hi = (float4)(hi[0], hi[1], hi[2], 0.0f);
    refs[t] = r;
}

/* The bounds and count of the kept triangles' boxes, per block of KD_SUM_BLOCK * 64 of them
   (BIN_BOUNDS rows). */
__kernel void ref_bounds(__global const Ref* restrict refs, __global float* restrict out, uint n)
{
    uint blk = (uint)get_global_id(0);
    uint first = blk * KD_SUM_BLOCK * 64u;
    if (first >= n)
        return;
    uint last = min(first + KD_SUM_BLOCK * 64u, n);
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    uint kept = 0u;
    for (uint i = first; i < last; i++) {
        Ref r = refs[i];
        if (ref_tri(r) == HOLE)
            continue;
        kept++;
        for (int a = 0; a < 3; a++) {
            lo[a] = f_min(lo[a], lane(r.lo, a));
            hi[a] = f_max(hi[a], lane(r.hi, a));
        }
    }
    __global float* row = out + BIN_BOUNDS_COLUMNS * blk;
    for (int a = 0; a < 3; a++) {
        row[BIN_BOUNDS_LO_X + a] = lo[a];
        row[BIN_BOUNDS_HI_X + a] = hi[a];
    }
    row[BIN_BOUNDS_KEPT] = as_float(kept);
}
