/* What every kd-tree build kernel shares: references, cells, the split choice, the leaf
   decision and the perfect split of straddling triangles (docs/kdtree_native.md).

   Every number that decides the tree is computed with the operations of the numpy builder
   (core/accel/kdtree.py: _binned_best_splits, _rank_exact, _step, _clip_straddlers) in the
   same precision and order: binned SAH and the leaf decision in IEEE double (fp64.cl),
   exact SAH ranking in float32. So the kernels build the numpy builder's tree, bit for bit.
   The big-node passes (big.cl) and the per-subtree builder (subtree.cl) decide only through
   these functions, from integer counts and min/max values that do not depend on the order
   in which they were gathered, so the tree does not depend on where the build switches from
   one to the other, on work-group sizes or on thread counts.

   Build constants (from KDTreeParams, as -D options): KD_KT_BITS, KD_KI_BITS, KD_2KI_BITS,
   KD_LAMBDA_BITS, KD_BPR_BITS (traversal and intersection cost, twice the latter, empty bonus,
   bins per reference: IEEE double bit patterns), KD_KT, KD_LAMBDA (the same as float32),
   KD_MIN_BINS, KD_MAX_BINS, KD_MAX_BAD (bad refines), KD_SMALL_NODE, KD_EXACT_MAX (nodes up to
   this size: exact SAH). Node format: core/layout.py's header (KD_PLAIN_*). Needs fp64.cl. */

#pragma OPENCL FP_CONTRACT OFF

#define D_KT D_BITS(KD_KT_BITS)
#define D_KI D_BITS(KD_KI_BITS)
#define D_2KI D_BITS(KD_2KI_BITS)
#define D_LAMBDA D_BITS(KD_LAMBDA_BITS)
#define D_BPR D_BITS(KD_BPR_BITS)
#define D_TWO D_BITS(0x4000000000000000UL)
#define D_ONE D_BITS(0x3FF0000000000000UL)

/* A reference: box lo in lo.xyz, triangle id (uint bits) in lo.w; box hi in hi.xyz. */
typedef struct {
    float4 lo;
    float4 hi;
} Ref;

typedef struct {
    float lo[3];
    float hi[3];
} Cell;

/* The chosen split of a node (none: no candidate lies strictly inside the cell). */
typedef struct {
    int valid;
    int axis;
    float plane;
} Choice;

inline float axis_of(float4 v, int axis)
{
    return axis == 0 ? v.x : (axis == 1 ? v.y : v.z);
}

inline uint ref_triangle(Ref r)
{
    return as_uint(r.lo.w);
}

/* min/max by comparison (PoCL calls fmin/fmax out of line). Box values never hold -0 (the
   host and the clipping canonicalise zeros), so equal values have equal bits and the result
   does not depend on the order. */
inline float kd_min(float a, float b)
{
    return b < a ? b : a;
}

inline float kd_max(float a, float b)
{
    return a < b ? b : a;
}

/* ----------------------------------------------------------------------------------------
   The SAH cost in double (kdtree.py _split_cost): a cell's dimensions and surface area, and
   the cost of a split at `width_below` from its low side with the given counts. */

typedef struct {
    dbl d[3];
    dbl area;
} CellD;

inline CellD cell_d(const Cell* c)
{
    CellD m;
    for (int a = 0; a < 3; a++)
        m.d[a] = D_SUB(D_FROM_F(c->hi[a]), D_FROM_F(c->lo[a]));
    dbl sum = D_ADD(D_ADD(D_MUL(m.d[0], m.d[1]), D_MUL(m.d[1], m.d[2])), D_MUL(m.d[2], m.d[0]));
    m.area = D_MUL(D_TWO, sum);
    return m;
}

inline dbl split_cost_d(const CellD* m, int axis, dbl width_below, uint nb, uint na)
{
    dbl side_a = m->d[axis == 2 ? 0 : axis + 1], side_b = m->d[axis == 0 ? 2 : axis - 1];
    dbl perimeter = D_ADD(side_a, side_b), cap = D_MUL(side_a, side_b);
    dbl width_above = D_SUB(m->d[axis], width_below);
    dbl area_below = D_MUL(D_TWO, D_ADD(D_MUL(width_below, perimeter), cap));
    dbl area_above = D_MUL(D_TWO, D_ADD(D_MUL(width_above, perimeter), cap));
    dbl sum = D_ADD(D_MUL(area_below, D_FROM_U(nb)), D_MUL(area_above, D_FROM_U(na)));
    dbl cost = D_ADD(D_KT, D_DIV(D_MUL(D_KI, sum), m->area));
    return (nb == 0u || na == 0u) ? D_MUL(cost, D_LAMBDA) : cost;
}

inline dbl width_below_d(const Cell* c, int axis, float plane)
{
    return D_SUB(D_FROM_F(plane), D_FROM_F(c->lo[axis]));
}

/* ----------------------------------------------------------------------------------------
   Binned SAH (kdtree.py _binned_best_splits): clip(round(bpr N), min, max) bins per axis;
   a low end goes into bin floor((lo - cell lo) scale), a high end into ceil(...) - 1, in
   float32, scale = float32(bins / width); plane k (k < bins - 1) is float32(cell lo +
   (k + 1) (width / bins)) from double; costs in double. */

typedef struct {
    float plane[3][KD_MAX_BINS];
    float scale[3];
    float lo[3];
    int bins;
} BinPlanes;

inline int node_bins(uint n)
{
    int bins = d_round_to_int(D_MUL(D_BPR, D_FROM_U(n)));
    return bins < KD_MIN_BINS ? KD_MIN_BINS : (bins > KD_MAX_BINS ? KD_MAX_BINS : bins);
}

inline void bin_planes(const Cell* c, uint n, BinPlanes* bp)
{
    int bins = node_bins(n);
    bp->bins = bins;
    dbl count = D_FROM_U((uint)bins);
    for (int a = 0; a < 3; a++) {
        dbl lo = D_FROM_F(c->lo[a]);
        dbl width = D_SUB(D_FROM_F(c->hi[a]), lo);
        dbl step = D_DIV(width, count);
        for (int k = 0; k < bins - 1; k++)
            bp->plane[a][k] = d_to_float_nearest(D_ADD(lo, D_MUL(D_FROM_U((uint)(k + 1)), step)));
        bp->scale[a] = d_to_float_nearest(D_DIV(count, width));
        bp->lo[a] = c->lo[a];
    }
}

/* floor / ceil of x >= 0 below 2^31 (PoCL calls floor and ceil out of line). */
inline float floor_pos(float x)
{
    return (float)(int)x;
}

inline float ceil_pos(float x)
{
    float f = (float)(int)x;
    return f < x ? f + 1.0f : f;
}

inline int bin_of_low(const BinPlanes* bp, int axis, float x)
{
    float b = floor_pos((x - bp->lo[axis]) * bp->scale[axis]);
    return (int)kd_min(b, (float)(bp->bins - 1));
}

inline int bin_of_high(const BinPlanes* bp, int axis, float x)
{
    float b = ceil_pos((x - bp->lo[axis]) * bp->scale[axis]) - 1.0f;
    return (int)kd_min(kd_max(b, 0.0f), (float)(bp->bins - 1));
}

/* Histogram words of one node or chunk: [axis][low ends, high ends][bin], then the tight
   bounds (min lo, max hi per axis, as float bits). */
#define HIST_WORDS (HISTOGRAM_WORDS_PER_BIN * KD_MAX_BINS + HISTOGRAM_BOUND_WORDS)
#define HIST_BOUNDS (HISTOGRAM_WORDS_PER_BIN * KD_MAX_BINS)

inline void hist_clear(uint* h)
{
    for (int i = 0; i < HIST_BOUNDS; i++)
        h[i] = 0u;
    for (int a = 0; a < 3; a++) {
        h[HIST_BOUNDS + a] = as_uint(INFINITY);
        h[HIST_BOUNDS + 3 + a] = as_uint(-INFINITY);
    }
}

inline void hist_add(uint* h, const BinPlanes* bp, Ref r)
{
    float lo[3] = {r.lo.x, r.lo.y, r.lo.z}, hi[3] = {r.hi.x, r.hi.y, r.hi.z};
    for (int a = 0; a < 3; a++) {
        h[(2 * a) * KD_MAX_BINS + bin_of_low(bp, a, lo[a])] += 1u;
        h[(2 * a + 1) * KD_MAX_BINS + bin_of_high(bp, a, hi[a])] += 1u;
        h[HIST_BOUNDS + a] = as_uint(kd_min(as_float(h[HIST_BOUNDS + a]), lo[a]));
        h[HIST_BOUNDS + 3 + a] = as_uint(kd_max(as_float(h[HIST_BOUNDS + 3 + a]), hi[a]));
    }
}

/* The binned candidates of one axis in order: the bin planes, then the cut at the tight low
   bound and the one at the tight high bound, each with its counts below and above; returns
   how many (bins + 1). */
#define BINNED_SLOTS (KD_MAX_BINS + 4)       /* bin planes, tight low, tight high, padding */

inline int binned_candidates(const uint* h, const BinPlanes* bp, int a, uint n,
                             float* planes, uint* below, uint* above)
{
    uint nb = 0u, not_above = 0u;
    for (int k = 0; k < bp->bins - 1; k++) {
        nb += h[(2 * a) * KD_MAX_BINS + k];
        not_above += h[(2 * a + 1) * KD_MAX_BINS + k];
        planes[k] = bp->plane[a][k];
        below[k] = nb;
        above[k] = n - not_above;
    }
    int slots = bp->bins + 1;
    planes[slots - 2] = as_float(h[HIST_BOUNDS + a]);
    planes[slots - 1] = as_float(h[HIST_BOUNDS + 3 + a]);
    below[slots - 2] = 0u;
    above[slots - 2] = n;
    below[slots - 1] = n;
    above[slots - 1] = 0u;
    return slots;
}

#ifndef KDTRACE_SOFT_FP64

/* split_cost_d() of 4 candidates of one axis (native doubles), the same operations per lane. */
inline double4 split_cost4(const CellD* m, int axis, double4 width_below, double4 nb, double4 na)
{
    double side_a = m->d[axis == 2 ? 0 : axis + 1], side_b = m->d[axis == 0 ? 2 : axis - 1];
    double perimeter = side_a + side_b, cap = side_a * side_b;
    double4 width_above = m->d[axis] - width_below;
    double4 area_below = 2.0 * (width_below * perimeter + cap);
    double4 area_above = 2.0 * (width_above * perimeter + cap);
    double4 cost = D_KT + (D_KI * (area_below * nb + area_above * na)) / m->area;
    return ((nb == 0.0) | (na == 0.0)) ? cost * D_LAMBDA : cost;
}

/* The first of equal costs wins (binned_candidates' order, axis after axis). All costs are
   formed four at a time, then the first minimum is looked up. */
inline Choice choose_binned(const uint* h, const BinPlanes* bp, const Cell* c, uint n)
{
    CellD m = cell_d(c);
    union {
        double4 v[BINNED_SLOTS / 4];
        double s[BINNED_SLOTS];
    } plane, nb, na, cost[3];
    float planes[3][BINNED_SLOTS];
    uint below[BINNED_SLOTS], above[BINNED_SLOTS];
    int slots = 0;
    double lowest = INFINITY;
    for (int a = 0; a < 3; a++) {
        slots = binned_candidates(h, bp, a, n, planes[a], below, above);
        int blocks = (slots + 3) / 4;
        for (int k = slots; k < 4 * blocks; k++) {
            planes[a][k] = c->lo[a];             /* never inside */
            below[k] = above[k] = 0u;
        }
        double lo = (double)c->lo[a];
        for (int k = 0; k < 4 * blocks; k++) {
            plane.s[k] = (double)planes[a][k] - lo;
            nb.s[k] = (double)below[k];
            na.s[k] = (double)above[k];
        }
        for (int k = 0; k < blocks; k++)
            cost[a].v[k] = split_cost4(&m, a, plane.v[k], nb.v[k], na.v[k]);
        for (int k = 0; k < 4 * blocks; k++) {
            float p = planes[a][k];
            if (!(p > c->lo[a] && p < c->hi[a]))
                cost[a].s[k] = INFINITY;
            lowest = cost[a].s[k] < lowest ? cost[a].s[k] : lowest;
        }
    }
    Choice best = {0, 0, 0.0f};
    if (!(lowest < INFINITY))
        return best;
    for (int a = 0; a < 3; a++)
        for (int k = 0; k < slots; k++)
            if (cost[a].s[k] == lowest) {
                best.valid = 1;
                best.axis = a;
                best.plane = planes[a][k];
                return best;
            }
    return best;
}

#else

/* The first of equal costs wins (binned_candidates' order, axis after axis). */
inline Choice choose_binned(const uint* h, const BinPlanes* bp, const Cell* c, uint n)
{
    CellD m = cell_d(c);
    Choice best = {0, 0, 0.0f};
    dbl best_cost = D_ZERO;
    float planes[BINNED_SLOTS];
    uint below[BINNED_SLOTS], above[BINNED_SLOTS];
    for (int a = 0; a < 3; a++) {
        int slots = binned_candidates(h, bp, a, n, planes, below, above);
        for (int k = 0; k < slots; k++) {
            float p = planes[k];
            if (!(p > c->lo[a] && p < c->hi[a]))
                continue;
            dbl cost = split_cost_d(&m, a, width_below_d(c, a, p), below[k], above[k]);
            if (!best.valid || D_LT(cost, best_cost)) {
                best.valid = 1;
                best_cost = cost;
                best.axis = a;
                best.plane = p;
            }
        }
    }
    return best;
}

#endif

/* ----------------------------------------------------------------------------------------
   Exact SAH for nodes of at most KD_EXACT_MAX references (kdtree.py _exact_best_splits,
   _rank_exact): every box bound is a candidate (per axis all low ends, then all high ends,
   in reference order); planar references at the plane go to the cheaper side; costs ranked
   in float32 as ((wP + Q) N_below + (R - wP) N_above + K_T) (lambda if a side is empty), with
   P, Q, R from the cell (scaled by 2 K_I / area).

   The boxes sit per axis in 2 `width` slots (width 4, 8 or KD_EXACT_MAX): low ends in slots
   0..width-1, high ends after them, unused slots +inf / -inf (they count on no side and are
   never inside a cell), so candidate e is simply slot e and both passes run 8 candidates at
   a time. Counting and ranking are separate: a child that an empty-space cut leaves with
   exactly its parent's references has the parent's counts at every candidate, so it is only
   ranked again for its own cell. */

/* 2 KD_EXACT_MAX floats, also as float8 blocks (no vload/vstore: PoCL calls builtins out of
   line). */
typedef union {
    float8 v[2 * KD_EXACT_MAX / 8];
    float s[2 * KD_EXACT_MAX];
} Slots;

typedef struct {
    Slots cand[3];
    Slots below[3];       /* per candidate: #(lo < p), #(hi > p), #flat at p */
    Slots above[3];
    Slots planar[3];
    int width;
} ExactBoxes;

inline int exact_width(uint n)
{
    return n <= 4u ? 4 : (n <= 8u ? 8 : KD_EXACT_MAX);
}

/* Counts at every candidate; the flat-at-the-plane count only on axes where some box is
   flat (rare, as kdtree.py does). */
inline void count_exact(ExactBoxes* x)
{
    int w = x->width;
    for (int a = 0; a < 3; a++) {
        const float* lo = x->cand[a].s;
        const float* hi = x->cand[a].s + w;
        int flat = 0;
        for (int j = 0; j < w; j++)
            flat |= lo[j] == hi[j];
        for (int k = 0; k < w / 4; k++) {
            float8 p = x->cand[a].v[k];
            float8 nb = (float8)(0.0f), na = (float8)(0.0f), np = (float8)(0.0f);
            for (int j = 0; j < w; j++) {
                float8 l = (float8)(lo[j]), h = (float8)(hi[j]);
                nb += (l < p) ? (float8)(1.0f) : (float8)(0.0f);
                na += (h > p) ? (float8)(1.0f) : (float8)(0.0f);
            }
            if (flat)
                for (int j = 0; j < w; j++) {
                    float8 l = (float8)(lo[j]), h = (float8)(hi[j]);
                    np += ((l == p) & (h == p)) ? (float8)(1.0f) : (float8)(0.0f);
                }
            x->below[a].v[k] = nb;
            x->above[a].v[k] = na;
            x->planar[a].v[k] = np;
        }
    }
}

/* kdtree.py _rank_exact's variant(): the same float32 operations in the same order. */
inline float8 exact_cost8(float8 wp, float q, float r, float8 nb, float8 na)
{
    float8 cost = wp + q;
    cost *= nb;
    cost += (r - wp) * na;
    cost += KD_KT;
    return ((nb == 0.0f) | (na == 0.0f)) ? cost * KD_LAMBDA : cost;
}

inline float hmin8(float8 v)
{
    float4 a = v.lo < v.hi ? v.lo : v.hi;
    float2 b = a.lo < a.hi ? a.lo : a.hi;
    return b.x < b.y ? b.x : b.y;
}

/* The cheapest candidate inside the cell (the first of equal costs, in the order axis, slot),
   and its counts (what the exact recount gives). */
inline Choice rank_exact(const ExactBoxes* x, const Cell* c, uint* counts)
{
    CellD m = cell_d(c);
    float scale = d_to_float_nearest(D_MUL(D_2KI, D_DIV(D_ONE, m.area)));
    float dims[3];
    for (int a = 0; a < 3; a++)
        dims[a] = d_to_float_nearest(m.d[a]);
    int blocks = x->width / 4;
    float8 cost[3][2 * KD_EXACT_MAX / 8];
    float8 least = (float8)(INFINITY);
    for (int a = 0; a < 3; a++) {
        float side_a = dims[a == 2 ? 0 : a + 1], side_b = dims[a == 0 ? 2 : a - 1];
        float p_ = (side_a + side_b) * scale;
        float q = side_a * side_b * scale;
        float r = dims[a] * p_ + q;
        for (int k = 0; k < blocks; k++) {
            float8 p = x->cand[a].v[k];
            int8 inside = (p > c->lo[a]) & (p < c->hi[a]);
            float8 wp = inside ? (p - c->lo[a]) : (float8)(0.0f);
            wp *= p_;
            float8 nb = x->below[a].v[k], na = x->above[a].v[k], np = x->planar[a].v[k];
            float8 c0 = exact_cost8(wp, q, r, nb + np, na);
            float8 c1 = exact_cost8(wp, q, r, nb, na + np);
            float8 ck = ((np > 0.0f) & (c1 < c0)) ? c1 : c0;
            ck = inside ? ck : (float8)(INFINITY);
            cost[a][k] = ck;
            least = ck < least ? ck : least;
        }
    }
    Choice best = {0, 0, 0.0f};
    float lowest = hmin8(least);
    if (!(lowest < INFINITY))
        return best;
    const float8 lane = (float8)(0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f);
    for (int a = 0; a < 3; a++)
        for (int k = 0; k < blocks; k++) {
            float first = hmin8(cost[a][k] == lowest ? lane : (float8)(8.0f));
            if (first < 8.0f) {
                int e = 8 * k + (int)first;
                best.valid = 1;
                best.axis = a;
                best.plane = x->cand[a].s[e];
                counts[0] = (uint)x->below[a].s[e];
                counts[1] = (uint)x->above[a].s[e];
                counts[2] = (uint)x->planar[a].s[e];
                return best;
            }
        }
    return best;
}

/* ----------------------------------------------------------------------------------------
   Leaf or split (kdtree.py _step), from the exact counts at the chosen plane (below:
   lo < plane, above: hi > plane, planar: flat at the plane), in double. Automatic
   termination with pbrt's bad refines, which only nodes of at least KD_SMALL_NODE references
   may use. */

typedef struct {
    int leaf;
    int planar_below;     /* planar references go below (else above) */
    uint bad;             /* bad refines on the path, this node's included */
} Decision;

inline Decision decide(uint n, uint level, uint depth_cap, uint bad, Choice ch, uint nb,
                       uint na, uint np, const Cell* c)
{
    Decision d = {1, 1, bad};
    if (n == 0u || level >= depth_cap || !ch.valid)
        return d;
    CellD m = cell_d(c);
    if (!D_LT(D_ZERO, m.area))
        m.area = D_ONE;                             /* as kdtree.py's safe_area */
    dbl wb = width_below_d(c, ch.axis, ch.plane);
    dbl cost_below = split_cost_d(&m, ch.axis, wb, nb + np, na);
    dbl cost_above = split_cost_d(&m, ch.axis, wb, nb, na + np);
    d.planar_below = D_LE(cost_below, cost_above);
    dbl cost = D_MIN(cost_below, cost_above);
    int is_bad = D_GE(cost, D_MUL(D_KI, D_FROM_U(n)));
    d.bad = bad + (uint)is_bad;
    d.leaf = is_bad && (d.bad >= KD_MAX_BAD || n < KD_SMALL_NODE);
    return d;
}

/* One reference counted below, above and planar at a plane (counts[0..2]). */
inline void count_at_plane(Ref r, int axis, float plane, uint* counts)
{
    float lo = axis_of(r.lo, axis), hi = axis_of(r.hi, axis);
    counts[0] += lo < plane;
    counts[1] += hi > plane;
    counts[2] += (lo == plane) & (hi == plane);
}

/* Bit 1: the reference goes below; bit 2: above (both: it straddles and is clipped). */
inline int ref_sides(Ref r, int axis, float plane, int planar_below)
{
    float lo = axis_of(r.lo, axis), hi = axis_of(r.hi, axis);
    if (lo == plane && hi == plane)
        return planar_below ? 1 : 2;
    return (lo < plane ? 1 : 0) | (hi > plane ? 2 : 0);
}

inline void child_cell(const Cell* parent, int axis, float plane, int above, Cell* child)
{
    *child = *parent;
    if (above)
        child->lo[axis] = plane;
    else
        child->hi[axis] = plane;
}

/* SAH share of one node (area / root area times K_T or K_I N, float32) in fixed point, 2^-32
   units: integer sums do not depend on their order. */
inline long sah_fixed(const Cell* c, float pow2, float inv_root_half_area, float weight)
{
    float d[3];
    for (int a = 0; a < 3; a++)
        d[a] = c->hi[a] * pow2 - c->lo[a] * pow2;
    float half_area = d[0] * d[1] + d[1] * d[2] + d[2] * d[0];
    return (long)(weight * (half_area * inv_root_half_area) * 0x1p32f);
}

/* ----------------------------------------------------------------------------------------
   Perfect splits: Sutherland-Hodgman in double (fp64.cl), exactly as core/accel/kdtree.py's
   _clip_straddlers: the triangle clipped to the faces of its cell that its own box crosses
   (axis 0..2, low face then high face), then cut by the plane; each half is its polygon's
   vertices on that side (a vertex on the plane belongs to both) plus the crossing points
   snapped onto the plane. A half of zero area (fewer than 3 vertices, or flat in an axis in
   which the triangle is not) is dropped; a kept half's box is rounded outward to float32 and
   clamped to the child cell. */

#define CLIP_VERTS 10        /* a triangle clipped by 6 planes has at most 9 vertices */

inline int clip_face(dbl p[3][CLIP_VERTS], int n, int axis, dbl value, int keep_below)
{
    dbl dist[CLIP_VERTS];
    int outside = 0;
    for (int i = 0; i < n; i++) {
        dist[i] = keep_below ? D_SUB(value, p[axis][i]) : D_SUB(p[axis][i], value);
        outside |= D_LT(dist[i], D_ZERO);
    }
    if (!outside)
        return n;
    dbl q[3][CLIP_VERTS];
    int m = 0;
    for (int i = 0; i < n; i++) {
        int j = i + 1 == n ? 0 : i + 1;
        if (D_GE(dist[i], D_ZERO)) {
            for (int a = 0; a < 3; a++)
                q[a][m] = p[a][i];
            m++;
        }
        if ((D_GT(dist[i], D_ZERO) && D_LT(dist[j], D_ZERO))
                || (D_LT(dist[i], D_ZERO) && D_GT(dist[j], D_ZERO))) {
            dbl t = D_DIV(dist[i], D_SUB(dist[i], dist[j]));
            for (int a = 0; a < 3; a++)
                q[a][m] = a == axis ? value : D_ADD(p[a][i], D_MUL(t, D_SUB(p[a][j], p[a][i])));
            m++;
        }
    }
    for (int i = 0; i < m; i++)
        for (int a = 0; a < 3; a++)
            p[a][i] = q[a][i];
    return m;
}

/* Clip the triangle of a straddling reference (its corners: a CORNERS row) for both
   children. Returns bit 1 if the below half is kept (its box in *below), bit 2 for the above
   half. */
inline int clip_straddler(__global const float* corners, uint tri, const Cell* c, int axis,
                          float plane, Ref* below, Ref* above)
{
    float corner[3][3];
    for (int k = 0; k < 3; k++)
        for (int a = 0; a < 3; a++)
            corner[k][a] = corners[CORNERS_COLUMNS * (size_t)tri + CORNERS_V0_X + 3 * k + a];
    dbl p[3][CLIP_VERTS];
    int flat[3];
    int n = 3;
    for (int a = 0; a < 3; a++) {
        float tlo = kd_min(kd_min(corner[0][a], corner[1][a]), corner[2][a]);
        float thi = kd_max(kd_max(corner[0][a], corner[1][a]), corner[2][a]);
        flat[a] = tlo == thi;
        for (int k = 0; k < 3; k++)
            p[a][k] = D_FROM_F(corner[k][a]);
    }
    for (int a = 0; a < 3; a++) {
        float tlo = kd_min(kd_min(corner[0][a], corner[1][a]), corner[2][a]);
        float thi = kd_max(kd_max(corner[0][a], corner[1][a]), corner[2][a]);
        if (tlo < c->lo[a])
            n = clip_face(p, n, a, D_FROM_F(c->lo[a]), 0);
        if (thi > c->hi[a])
            n = clip_face(p, n, a, D_FROM_F(c->hi[a]), 1);
    }
    /* The cut: d = x[axis] - plane; the crossing points belong to both halves. */
    dbl split = D_FROM_F(plane);
    dbl d[CLIP_VERTS];
    for (int i = 0; i < n; i++)
        d[i] = D_SUB(p[axis][i], split);
    dbl lo[2][3], hi[2][3];
    int count[2] = {0, 0};
    for (int i = 0; i < n; i++) {
        int j = i + 1 == n ? 0 : i + 1;
        for (int side = 0; side < 2; side++) {
            if (side == 0 ? D_LE(d[i], D_ZERO) : D_GE(d[i], D_ZERO)) {
                for (int a = 0; a < 3; a++) {
                    lo[side][a] = count[side] ? D_MIN(lo[side][a], p[a][i]) : p[a][i];
                    hi[side][a] = count[side] ? D_MAX(hi[side][a], p[a][i]) : p[a][i];
                }
                count[side]++;
            }
        }
        if ((D_GT(d[i], D_ZERO) && D_LT(d[j], D_ZERO)) || (D_LT(d[i], D_ZERO) && D_GT(d[j], D_ZERO))) {
            dbl t = D_DIV(d[i], D_SUB(d[i], d[j]));
            for (int a = 0; a < 3; a++) {
                dbl x = a == axis ? split : D_ADD(p[a][i], D_MUL(t, D_SUB(p[a][j], p[a][i])));
                for (int side = 0; side < 2; side++) {
                    lo[side][a] = count[side] ? D_MIN(lo[side][a], x) : x;
                    hi[side][a] = count[side] ? D_MAX(hi[side][a], x) : x;
                }
            }
            count[0]++;
            count[1]++;
        }
    }
    int kept = 0;
    for (int side = 0; side < 2; side++) {
        int positive = count[side] >= 3;
        for (int a = 0; a < 3 && positive; a++)
            if (D_EQ(hi[side][a], lo[side][a]) && !flat[a])
                positive = 0;
        if (!positive)
            continue;
        kept |= 1 << side;
        Cell child;
        child_cell(c, axis, plane, side, &child);
        float box[6];
        for (int a = 0; a < 3; a++) {
            box[a] = kd_max(d_to_float_outward(lo[side][a], 0), child.lo[a]);
            box[3 + a] = kd_min(d_to_float_outward(hi[side][a], 1), child.hi[a]);
        }
        Ref* out = side ? above : below;
        out->lo = (float4)(box[0], box[1], box[2], as_float(tri));
        out->hi = (float4)(box[3], box[4], box[5], 0.0f);
    }
    return kept;
}

/* The children a reference goes to (bit 1 below, bit 2 above) and its box in each: a
   straddler's clipped halves, otherwise the reference as it is. */
inline int ref_children(__global const float* corners, Ref r, const Cell* c, int axis,
                        float plane, int planar_below, Ref* below, Ref* above)
{
    *below = r;
    *above = r;
    int sides = ref_sides(r, axis, plane, planar_below);
    if (sides == 3)
        sides = clip_straddler(corners, ref_triangle(r), c, axis, plane, below, above);
    return sides;
}
