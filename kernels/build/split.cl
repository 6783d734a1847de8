/* What every kd-tree build kernel shares: references, cells, the split choice, the leaf
   decision and the perfect split of straddling triangles (docs/kdtree_native.md).

   The big-node passes (big.cl) and the per-subtree builder (subtree.cl) make their decisions
   only through these functions, from integer counts and min/max values that do not depend on
   the order in which they were gathered, so the tree does not depend on where the build
   switches from one to the other, on work-group sizes or on thread counts.

   Build constants (from KDTreeParams, as -D options): KD_KT, KD_KI (traversal, intersection
   cost), KD_LAMBDA (empty bonus), KD_BPR (bins per reference), KD_MIN_BINS, KD_MAX_BINS,
   KD_MAX_BAD (bad refines), KD_SMALL_NODE, KD_EXACT_MAX (nodes up to this size: exact SAH).
   Node format constants: format.cl. Needs fp64.cl. */

#pragma OPENCL FP_CONTRACT OFF

/* A reference: box lo in lo.xyz, triangle id (uint bits) in lo.w; box hi in hi.xyz. */
typedef struct {
    float4 lo;
    float4 hi;
} Ref;

typedef struct {
    float lo[3];
    float hi[3];
} Cell;

/* A cell's dimensions and half surface area, scaled by a power of two of the scene (exact:
   keeps areas of tiny or huge scenes away from float32 denormals and overflow). */
typedef struct {
    float d[3];
    float half_area;
} Dims;

/* The best split found for a node: cost INFINITY when no plane lies strictly inside. */
typedef struct {
    float cost;
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

inline Dims cell_dims(const Cell* c, float pow2)
{
    Dims m;
    for (int a = 0; a < 3; a++)
        m.d[a] = c->hi[a] * pow2 - c->lo[a] * pow2;
    m.half_area = m.d[0] * m.d[1] + m.d[1] * m.d[2] + m.d[2] * m.d[0];
    return m;
}

/* What the SAH cost of a split on one axis needs of the cell. */
typedef struct {
    float width, perimeter, cap, kt_area, lo_scaled;
} AxisTerms;

inline AxisTerms axis_terms(const Dims* m, const Cell* c, int axis, float pow2)
{
    AxisTerms t;
    float s1 = m->d[axis == 0 ? 1 : 0], s2 = m->d[axis == 2 ? 1 : 2];
    t.width = m->d[axis];
    t.perimeter = s1 + s2;
    t.cap = s1 * s2;
    t.kt_area = KD_KT * m->half_area;
    t.lo_scaled = c->lo[axis] * pow2;
    return t;
}

/* SAH cost of a split at `plane` times the cell's half area (no division, so no rounding
   differences between devices): lambda (K_T A + K_I (A_below N_below + A_above N_above)),
   lambda = 1 unless a side is empty. */
inline float split_cost(const AxisTerms* t, float plane, float pow2, float nb, float na)
{
    float wb = plane * pow2 - t->lo_scaled;
    float area_below = wb * t->perimeter + t->cap;
    float area_above = (t->width - wb) * t->perimeter + t->cap;
    float cost = t->kt_area + KD_KI * (area_below * nb + area_above * na);
    return (nb == 0.0f || na == 0.0f) ? cost * KD_LAMBDA : cost;
}

inline int node_bins(uint n)
{
    int bins = (int)(KD_BPR * (float)n + 0.5f);
    return bins < KD_MIN_BINS ? KD_MIN_BINS : (bins > KD_MAX_BINS ? KD_MAX_BINS : bins);
}

/* ----------------------------------------------------------------------------------------
   Binned SAH with exact counts at the bin planes.

   Plane k (k < bins - 1) of an axis is lo + (k + 1) (width / bins) in float32 (width / bins as
   width * inv_bins[bins], a table from the host). A reference's low end goes into the bin
   "number of planes <= lo", its high end into "number of planes < hi", found from a seed
   (multiplying by an approximate bins / width) corrected against the planes themselves, so
   below(k) = #(lo < plane k) and above(k) = #(hi > plane k) exactly. */

typedef struct {
    float plane[3][KD_MAX_BINS + 1];   /* plane k at k + 1; -inf at 0 and +inf after the last */
    float seed_scale[3];
    float lo[3];
    int bins;
} BinPlanes;

inline void bin_planes(const Cell* c, uint n, __global const float* inv_bins, BinPlanes* bp)
{
    int bins = node_bins(n);
    bp->bins = bins;
    float inv = inv_bins[bins];
    for (int a = 0; a < 3; a++) {
        float width = c->hi[a] - c->lo[a];
        float step = width * inv;
        bp->plane[a][0] = -INFINITY;
        for (int k = 0; k < bins - 1; k++)
            bp->plane[a][k + 1] = c->lo[a] + (float)(k + 1) * step;
        bp->plane[a][bins] = INFINITY;
        bp->seed_scale[a] = (float)bins / width;
        bp->lo[a] = c->lo[a];
    }
}

inline float bin_plane(const BinPlanes* bp, int axis, int k)
{
    return bp->plane[axis][k + 1];
}

/* Bin of a low end (number of planes <= x) and of a high end (number of planes < x): the
   seed, then one step each way without branches (a seed is off by at most one bin unless
   the cell is tiny in float32 terms; the loops cover that). A reference lies inside its
   cell, so the seed is >= 0. */
inline int bin_of_low(const BinPlanes* bp, int axis, float x)
{
    const float* pl = bp->plane[axis];
    int b = (int)kd_min((x - bp->lo[axis]) * bp->seed_scale[axis], (float)(bp->bins - 1));
    b += pl[b + 1] <= x;
    b -= pl[b] > x;
    while (pl[b + 1] <= x)
        b++;
    while (pl[b] > x)
        b--;
    return b;
}

inline int bin_of_high(const BinPlanes* bp, int axis, float x)
{
    const float* pl = bp->plane[axis];
    int b = (int)kd_min((x - bp->lo[axis]) * bp->seed_scale[axis], (float)(bp->bins - 1));
    b += pl[b + 1] < x;
    b -= pl[b] >= x;
    while (pl[b + 1] < x)
        b++;
    while (pl[b] >= x)
        b--;
    return b;
}

/* Histogram words of one node or chunk: [axis][low ends, high ends][bin], then the tight
   bounds (min lo, max hi per axis, as float bits). */
#define HIST_WORDS (6 * KD_MAX_BINS + 6)
#define HIST_BOUNDS (6 * KD_MAX_BINS)

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

inline void consider(Choice* best, float cost, int axis, float plane)
{
    if (cost < best->cost) {
        best->cost = cost;
        best->axis = axis;
        best->plane = plane;
    }
}

/* Order of candidates: per axis the bin planes, then the cut at the tight low bound, then the
   one at the tight high bound; the first of equal costs wins. */
inline Choice choose_binned(const uint* h, const BinPlanes* bp, const Cell* c, uint n,
                            float pow2)
{
    Dims m = cell_dims(c, pow2);
    Choice best = {INFINITY, 0, 0.0f};
    float count = (float)n;
    for (int a = 0; a < 3; a++) {
        AxisTerms t = axis_terms(&m, c, a, pow2);
        uint below = 0u, not_above = 0u;
        for (int k = 0; k < bp->bins - 1; k++) {
            below += h[(2 * a) * KD_MAX_BINS + k];
            not_above += h[(2 * a + 1) * KD_MAX_BINS + k];
            float p = bin_plane(bp, a, k);
            if (p > c->lo[a] && p < c->hi[a])
                consider(&best, split_cost(&t, p, pow2, (float)below, (float)(n - not_above)),
                         a, p);
        }
        float tight_lo = as_float(h[HIST_BOUNDS + a]);
        float tight_hi = as_float(h[HIST_BOUNDS + 3 + a]);
        if (tight_lo > c->lo[a] && tight_lo < c->hi[a])
            consider(&best, split_cost(&t, tight_lo, pow2, 0.0f, count), a, tight_lo);
        if (tight_hi > c->lo[a] && tight_hi < c->hi[a])
            consider(&best, split_cost(&t, tight_hi, pow2, count, 0.0f), a, tight_hi);
    }
    return best;
}

/* ----------------------------------------------------------------------------------------
   Exact SAH for nodes of at most KD_EXACT_MAX references: every box bound is a candidate
   (per axis all low ends, then all high ends, in reference order); planar references at the
   plane go to the cheaper side.

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

inline void count_exact(ExactBoxes* x)
{
    int w = x->width;
    for (int a = 0; a < 3; a++) {
        const float* lo = x->cand[a].s;
        const float* hi = x->cand[a].s + w;
        for (int k = 0; k < w / 4; k++) {
            float8 p = x->cand[a].v[k];
            float8 nb = (float8)(0.0f), na = (float8)(0.0f), np = (float8)(0.0f);
            for (int j = 0; j < w; j++) {
                float8 l = (float8)(lo[j]), h = (float8)(hi[j]);
                nb += l < p ? (float8)(1.0f) : (float8)(0.0f);
                na += h > p ? (float8)(1.0f) : (float8)(0.0f);
                np += (l == p) & (h == p) ? (float8)(1.0f) : (float8)(0.0f);
            }
            x->below[a].v[k] = nb;
            x->above[a].v[k] = na;
            x->planar[a].v[k] = np;
        }
    }
}

/* split_cost() of 8 candidates, in the same float32 operations. */
inline float8 split_cost8(const AxisTerms* t, float8 p, float pow2, float8 nb, float8 na)
{
    float8 wb = p * pow2 - t->lo_scaled;
    float8 area_below = wb * t->perimeter + t->cap;
    float8 area_above = (t->width - wb) * t->perimeter + t->cap;
    float8 cost = t->kt_area + KD_KI * (area_below * nb + area_above * na);
    return (nb == 0.0f) | (na == 0.0f) ? cost * KD_LAMBDA : cost;
}

/* The cheapest candidate inside the cell (the first of equal costs), and its counts (what
   the exact recount gives). */
inline Choice rank_exact(const ExactBoxes* x, const Cell* c, float pow2, uint* counts)
{
    Dims m = cell_dims(c, pow2);
    Choice best = {INFINITY, 0, 0.0f};
    int w = x->width;
    for (int a = 0; a < 3; a++) {
        AxisTerms t = axis_terms(&m, c, a, pow2);
        Slots cost;
        for (int k = 0; k < w / 4; k++) {
            float8 p = x->cand[a].v[k];
            float8 nb = x->below[a].v[k], na = x->above[a].v[k], np = x->planar[a].v[k];
            float8 c1 = split_cost8(&t, p, pow2, nb + np, na);
            float8 c2 = split_cost8(&t, p, pow2, nb, na + np);
            float8 ck = (np > 0.0f) & (c2 < c1) ? c2 : c1;
            cost.v[k] = (p > c->lo[a]) & (p < c->hi[a]) ? ck : (float8)(INFINITY);
        }
        for (int e = 0; e < 2 * w; e++)
            if (cost.s[e] < best.cost) {
                best.cost = cost.s[e];
                best.axis = a;
                best.plane = x->cand[a].s[e];
                counts[0] = (uint)x->below[a].s[e];
                counts[1] = (uint)x->above[a].s[e];
                counts[2] = (uint)x->planar[a].s[e];
            }
    }
    return best;
}

/* ----------------------------------------------------------------------------------------
   Leaf or split, from the exact counts at the chosen plane (below: lo < plane, above:
   hi > plane, planar: flat at the plane). Automatic termination with pbrt's bad refines,
   which only nodes of at least KD_SMALL_NODE references may use. */

typedef struct {
    int leaf;
    int planar_below;     /* planar references go below (else above) */
    uint bad;             /* bad refines on the path, this node's included */
} Decision;

inline Decision decide(uint n, uint level, uint depth_cap, uint bad, Choice ch, uint nb,
                       uint na, uint np, const Cell* c, float pow2)
{
    Decision d = {1, 1, bad};
    if (n == 0u || level >= depth_cap || !(ch.cost < INFINITY))
        return d;
    Dims m = cell_dims(c, pow2);
    AxisTerms t = axis_terms(&m, c, ch.axis, pow2);
    float cost_below = split_cost(&t, ch.plane, pow2, (float)(nb + np), (float)na);
    float cost_above = split_cost(&t, ch.plane, pow2, (float)nb, (float)(na + np));
    d.planar_below = cost_below <= cost_above;
    float cost = kd_min(cost_below, cost_above);
    int is_bad = cost >= KD_KI * (float)n * m.half_area;
    d.bad = bad + (uint)is_bad;
    d.leaf = is_bad && (d.bad >= KD_MAX_BAD || n < KD_SMALL_NODE);
    return d;
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

/* SAH share of one node (area / root area times K_T or K_I N) in fixed point, 2^-32 units:
   integer sums do not depend on their order. */
inline long sah_fixed(const Cell* c, float pow2, float inv_root_half_area, float weight)
{
    Dims m = cell_dims(c, pow2);
    return (long)(weight * (m.half_area * inv_root_half_area) * 0x1p32f);
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

/* Clip the triangle of a straddling reference for both children. Returns bit 1 if the below
   half is kept (its box in *below), bit 2 for the above half. */
inline int clip_straddler(__global const float* vertices, __global const uint* triangles,
                          uint tri, const Cell* c, int axis, float plane, Ref* below,
                          Ref* above)
{
    float corner[3][3];
    for (int k = 0; k < 3; k++) {
        uint v = triangles[3 * tri + k];
        for (int a = 0; a < 3; a++)
            corner[k][a] = vertices[3 * v + a];
    }
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
