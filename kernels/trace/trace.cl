// Ray queries against the kd-tree: the watertight ray/triangle test, the compact tree's node
// format decoded (load_node, inner_node, tref_slot, leaf_node: the one place that reads node
// words, for trace_ray here and trace_packet in packet.cl) and trace_ray, the one-ray
// traversal that intersect.cl and the shading (kernels/shade/) use. OpenCL C 1.2, single
// precision, no extensions. Node fields, buffer slots and codes are the names of the layout header that
// core/opencl.py kernel_source puts before the kernel files (generated from core/layout.py).
//
// Build options (slave/tracer.py kernel_options): KD_STACK_SIZE (>= tree depth + 1),
// KD_PACKET (packet.cl), KD_PREFETCH (CPU devices: prefetch_triangle), HAS_<FEATURE>
// (kernels/shade/), and KDTRACE_HASH (core/opencl.py: a hash of source and options, so no driver
// cache can serve a stale binary).

// Same rounding on every device: no silent a*b+c -> fma contraction.
#pragma OPENCL FP_CONTRACT OFF

#ifndef KD_STACK_SIZE
#error "KD_STACK_SIZE must be defined by the host"
#endif

#define NO_HIT 0xFFFFFFFFu
// pbrt's gamma(3): bound on the error of the slab distances, used to widen the root interval.
#define GAMMA3 (3.0f * 0x1.0p-24f / (1.0f - 3.0f * 0x1.0p-24f))

// Helpers of the hot paths are forced inline: PoCL (LLVM 14) otherwise calls even its own
// fmin/fmax/fabs/isfinite out of line, and every call spills all live float registers.
#define KD_INLINE inline __attribute__((always_inline))

// Component `axis` (0, 1, 2) of a vector; OpenCL C has no run-time indexing of vector lanes.
KD_INLINE float lane(float3 v, uint axis)
{
    return axis == 0 ? v.x : (axis == 1 ? v.y : v.z);
}

// fabs and isfinite as bit operations (exactly the builtins' results, inlined).
KD_INLINE float kd_fabs(float x)
{
    return as_float(as_uint(x) & 0x7FFFFFFFu);
}

KD_INLINE bool kd_isfinite(float x)
{
    return kd_fabs(x) < INFINITY;     // false for +-inf and NaN
}

// The geometric functions, each one formula and so the same bits on every device: OpenCL
// leaves the rounding of its dot, cross, length and normalize to the implementation (a GPU may
// fuse or reorder their sums), and PoCL 3.0 calls them out of line. Every kernel uses these.
KD_INLINE float kd_dot(float3 a, float3 b)
{
    return a.x * b.x + a.y * b.y + a.z * b.z;
}

KD_INLINE float kd_dot4(float4 a, float4 b)
{
    return a.x * b.x + a.y * b.y + a.z * b.z + a.w * b.w;
}

KD_INLINE float3 kd_cross(float3 a, float3 b)
{
    return (float3)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}

// The largest |component| of v, by comparisons (NaN components are passed over).
KD_INLINE float kd_max_abs(float3 v)
{
    float ax = kd_fabs(v.x), ay = kd_fabs(v.y), az = kd_fabs(v.z);
    float m = ax > ay ? ax : ay;
    return m > az ? m : az;
}

// |v|. Where the sum of squares leaves float's normal range (over- or underflow), v is first
// divided by its largest component.
KD_INLINE float kd_length(float3 v)
{
    float l2 = kd_dot(v, v);
    if (l2 >= FLT_MIN && l2 < INFINITY)
        return sqrt(l2);
    float m = kd_max_abs(v);
    if (l2 != l2 || m == 0.0f || m == INFINITY)
        return l2 != l2 ? l2 : m;       // NaN, 0, inf
    float3 s = v / m;
    return m * sqrt(kd_dot(s, s));
}

// v / |v|, scaled as kd_length; the zero vector stays zero (as OpenCL's normalize).
KD_INLINE float3 kd_normalize(float3 v)
{
    float l2 = kd_dot(v, v);
    if (l2 >= FLT_MIN && l2 < INFINITY)
        return v / sqrt(l2);
    float m = kd_max_abs(v);
    if (m == 0.0f)
        return v;
    float3 s = v / m;
    return s / sqrt(kd_dot(s, s));
}

// The float next to x towards +inf (up) or -inf: nextafter(x, +-INFINITY), as bit steps.
KD_INLINE float kd_next_float(float x, bool up)
{
    if (x != x || x == (up ? INFINITY : -INFINITY))
        return x;
    if (x == 0.0f)
        return up ? as_float(1u) : -as_float(1u);
    uint u = as_uint(x);
    return as_float((x > 0.0f) == up ? u + 1u : u - 1u);
}

typedef struct {
    float3 o, d, inv_d;
    uint kx, ky, kz;        // watertight test: kz = dominant axis of d
    float sx, sy, sz;       // shear constants
} Ray;

typedef struct {
    float t, u, v;
    uint tri;               // NO_HIT on a miss
    uint key;               // the hit's key: tri in a flat scene; with instances the key of
                            // (instance, triangle), as its realised scene's triangle index
    uint inst;              // with instances: the INSTANCE record hit
} Hit;

typedef struct {
    uint node;
    float t0, t1;
} StackEntry;

// p and v through the 3x4 transform of rows m (a point with the translation, a vector without):
// the camera's (render.cl) and instances'.
inline float3 transform_point(__global const float4 *m, float3 p)
{
    float4 q = (float4)(p, 1.0f);
    return (float3)(kd_dot4(m[0], q), kd_dot4(m[1], q), kd_dot4(m[2], q));
}

inline float3 transform_vector(__global const float4 *m, float3 v)
{
    float4 q = (float4)(v, 0.0f);
    return (float3)(kd_dot4(m[0], q), kd_dot4(m[1], q), kd_dot4(m[2], q));
}

KD_INLINE Ray make_ray(float3 o, float3 d)
{
    Ray r;
    r.o = o;
    r.d = d;
    // 1/0 = +-inf is wanted here: slab and plane distances then become +-inf (or NaN when the
    // origin lies on the plane), which the comparisons below treat conservatively.
    r.inv_d = (float3)(1.0f / d.x, 1.0f / d.y, 1.0f / d.z);
    float3 a = (float3)(kd_fabs(d.x), kd_fabs(d.y), kd_fabs(d.z));
    r.kz = (a.x > a.y) ? (a.x > a.z ? 0u : 2u) : (a.y > a.z ? 1u : 2u);
    r.kx = (r.kz + 1u) % 3u;
    r.ky = (r.kx + 1u) % 3u;
    float dz = lane(d, r.kz);
    if (dz < 0.0f) {        // swap to keep the winding, so the edge signs stay meaningful
        uint k = r.kx; r.kx = r.ky; r.ky = k;
    }
    r.sx = lane(d, r.kx) / dz;
    r.sy = lane(d, r.ky) / dz;
    r.sz = 1.0f / dz;
    return r;
}

// a*b - c*d with one rounding error (Kahan, via fma); used when an edge function is exactly 0,
// in place of the double-precision recomputation that OpenCL does not guarantee.
inline float diff_of_products(float a, float b, float c, float d)
{
    float cd = c * d;
    float err = fma(-c, d, cd);
    return fma(a, b, -cd) + err;
}

// Per-ray constants of the watertight test, unpacked from the Ray once per traversal.
typedef struct {
    uint kx, ky, kz;        // the permutation (kz = dominant axis of d)
    float okx, oky, okz;    // the origin's components in that order
    float sx, sy, sz;       // shear constants
} TriRay;

// The corners of a TRIANGLE record as float arrays, for component loads by axis.
typedef struct {
    __global const float *v0, *v1, *v2;
} Corners;

KD_INLINE Corners triangle_corners(__global const float4 *tri_verts, uint tri)
{
    __global const float4 *record = tri_verts + TRIANGLE_SIZE * tri;
    Corners c;
    c.v0 = (__global const float *)(record + TRIANGLE_V0_SLOT);
    c.v1 = (__global const float *)(record + TRIANGLE_V1_SLOT);
    c.v2 = (__global const float *)(record + TRIANGLE_V2_SLOT);
    return c;
}

// Watertight ray/triangle test (Woop, Benthin, Wald 2013) on the triangle with corners `c`. On
// a hit with t in [tmin, tmax] returns true and sets t, u (weight of v1), v (weight of v2). The
// permutation is applied by indexed loads: `v0[k] - o[k]` is lane(v0 - o, k) exactly, without
// a select per component.
KD_INLINE bool intersect_triangle(const TriRay *q, Corners c,
                                  float tmin, float tmax, float *t_out, float *u_out, float *v_out)
{
    uint kx = q->kx, ky = q->ky, kz = q->kz;
    float az = c.v0[kz] - q->okz, bz = c.v1[kz] - q->okz, cz = c.v2[kz] - q->okz;
    float ax = (c.v0[kx] - q->okx) - q->sx * az, ay = (c.v0[ky] - q->oky) - q->sy * az;
    float bx = (c.v1[kx] - q->okx) - q->sx * bz, by = (c.v1[ky] - q->oky) - q->sy * bz;
    float cx = (c.v2[kx] - q->okx) - q->sx * cz, cy = (c.v2[ky] - q->oky) - q->sy * cz;
    float e0 = cx * by - cy * bx;   // weight of v0
    float e1 = ax * cy - ay * cx;   // weight of v1
    float e2 = bx * ay - by * ax;   // weight of v2
    if (e0 == 0.0f || e1 == 0.0f || e2 == 0.0f) {
        e0 = diff_of_products(cx, by, cy, bx);
        e1 = diff_of_products(ax, cy, ay, cx);
        e2 = diff_of_products(bx, ay, by, ax);
    }
    if ((e0 < 0.0f || e1 < 0.0f || e2 < 0.0f) && (e0 > 0.0f || e1 > 0.0f || e2 > 0.0f))
        return false;
    float det = e0 + e1 + e2;
    if (det == 0.0f)
        return false;
    float tscaled = e0 * (q->sz * az) + e1 * (q->sz * bz) + e2 * (q->sz * cz);
    float t = tscaled / det;
    if (!(t >= tmin && t <= tmax))   // also rejects NaN
        return false;
    *t_out = t;
    *u_out = e1 / det;
    *v_out = e2 / det;
    return true;
}

// Where the host defines KD_PREFETCH (CPU devices): asks for both cache lines the TRIANGLE
// record of `tri` may span, so that a leaf's records are fetched together before its tests
// (an incoherent ray's are seldom in cache, and a test's data-dependent branches keep the CPU
// from running ahead to the next record's loads). Nothing elsewhere.
KD_INLINE void prefetch_triangle(__global const float4 *tri_verts, uint tri)
{
#ifdef KD_PREFETCH
    __global const float4 *record = tri_verts + TRIANGLE_SIZE * tri;
    __builtin_prefetch((__global const char *)record);
    __builtin_prefetch((__global const char *)(record + TRIANGLE_SIZE) - 1);
#endif
}

// Tolerance of the stopping test, relative to t and to the scene's size along the ray: a
// triangle coplanar with the best hit (a column on a floor) may sit in a cell whose computed
// entry rounds just past that hit; visiting it lets the tie go to the lower index.
#define KD_TIE_EPS 1e-6f

// The compact kd-tree (docs/kdtree_compression.md; one layout for the modes standard, choi and
// ours): nodes, the 32- and 16-bit leaf index lists, and the shift of 16-bit leaves' bases.
typedef struct {
    __global const uint2 *nodes;
    __global const uint *leaf32;
    __global const ushort *leaf16;
    uint leaf_shift;
    float3 bmin, bmax;
    float extent;           // max |bmin|, |bmax| over the axes (BOUNDS_EXTENT, from the host)
} KdTree;

// The kernels' tree arguments as a KdTree (`bounds`: a BOUNDS record).
KD_INLINE KdTree make_kdtree(__global const uint2 *nodes, __global const uint *leaf32,
                             __global const ushort *leaf16, uint leaf_shift,
                             __global const float4 *bounds)
{
    KdTree kd;
    kd.nodes = nodes;
    kd.leaf32 = leaf32;
    kd.leaf16 = leaf16;
    kd.leaf_shift = leaf_shift;
    kd.bmin = BOUNDS_MIN(bounds);
    kd.bmax = BOUNDS_MAX(bounds);
    kd.extent = BOUNDS_EXTENT(bounds);
    return kd;
}

// The node format, decoded here for every traversal (trace_ray, trace_packet): the KD_* fields
// of the layout header (core/layout.py COMPACT_NODE).

// The two words of node `index`, loaded as scalars: word 0 goes straight to the integer
// decoding (a uint2 load may land in a vector register first, a longer path to the branch).
KD_INLINE uint2 load_node(const KdTree *kd, uint index)
{
    __global const uint *words = (__global const uint *)(kd->nodes + index);
    uint2 n;
    n.x = words[0];
    n.y = words[1];
    return n;
}

KD_INLINE bool is_leaf(uint2 n)
{
    return KD_TAG(n.x) == KD_LEAF_TAG;
}

// An inner node: its split plane, its children (an elided child is an empty leaf: nothing to
// visit) and its T-reference slot, if any.
typedef struct {
    uint axis;
    float split;
    uint below, above;              // node indices of the children that are stored
    bool below_stored, above_stored;
    bool has_refs;
    uint refs;                      // node index of the T-reference slot (when has_refs)
} InnerNode;

KD_INLINE InnerNode inner_node(uint2 n)
{
    uint w = n.x;
    InnerNode in;
    in.axis = KD_TAG(w);
    in.split = as_float(n.y);
    // The group: the T-reference slot (if R), the below child (unless Eb), the above child.
    uint group = KD_GROUP(w), has_ref = KD_REF(w);
    in.has_refs = has_ref != 0u;
    in.refs = group;
    in.below = group + has_ref;
    in.above = in.below + 1u - KD_EMPTY_BELOW(w);
    in.below_stored = (w & KD_EMPTY_BELOW_BIT) == 0u;
    in.above_stored = (w & KD_EMPTY_ABOVE_BIT) == 0u;
    return in;
}

// The triangles of a T-reference slot: .x, and .y unless has_second_ref says it is empty.
KD_INLINE uint2 tref_slot(const KdTree *kd, const InnerNode *in)
{
    return kd->nodes[in->refs];
}

KD_INLINE bool has_second_ref(uint2 refs)
{
    return refs.y != KD_NO_TRIANGLE;
}

// A leaf's triangle list: count16 16-bit entries on a base, or count32 32-bit triangle indices
// (the other count is 0, so a traversal runs one loop of each kind without a test per entry).
typedef struct {
    uint count16, count32;
    uint base;                      // 16-bit lists: B << leaf_shift
    __global const ushort *entries16;
    __global const uint *entries32;
} LeafNode;

KD_INLINE LeafNode leaf_node(const KdTree *kd, uint2 n)
{
    uint w = n.x;
    bool list16 = (w & KD_LEAF16_BIT) != 0u;
    LeafNode leaf;
    leaf.count16 = list16 ? KD_LEAF16_COUNT(w) : 0u;
    leaf.count32 = list16 ? 0u : KD_LEAF32_COUNT(w);
    leaf.base = KD_LEAF16_BASE(w) << kd->leaf_shift;
    leaf.entries16 = kd->leaf16 + n.y;
    leaf.entries32 = kd->leaf32 + n.y;
    return leaf;
}

// Triangle i (< count16) of a 16-bit list, and i (< count32) of a 32-bit one.
KD_INLINE uint leaf16_triangle(const LeafNode *leaf, uint i)
{
    return leaf->base + (uint)leaf->entries16[i];
}

KD_INLINE uint leaf32_triangle(const LeafNode *leaf, uint i)
{
    return leaf->entries32[i];
}

// The best hit so far, in registers (written to the caller's Hit once, at the end).
typedef struct {
    float best;             // accepted hits satisfy t <= best (tmax at first)
    float limit;            // traversal stops at nodes starting beyond this (see below)
    float tie_abs;
    float t, u, v;
    uint tri;               // NO_HIT: none yet; any index is lower, so ties go to the lower one
} Best;

// Test triangle `tri` against [tmin, best]; keep it when it is nearer, or as near with a lower
// index (ties go to the lower triangle index, as brute force).
KD_INLINE bool consider(const TriRay *q, uint tri, uint ignore_tri,
                        __global const float4 *tri_verts, float tmin, Best *b)
{
    float t, u, v;
    if (tri != ignore_tri
        && intersect_triangle(q, triangle_corners(tri_verts, tri), tmin, b->best, &t, &u, &v)
        && (t < b->best || tri < b->tri)) {
        b->best = t;
        b->limit = t + (KD_TIE_EPS * t + b->tie_abs);
        b->t = t;
        b->u = u;
        b->v = v;
        b->tri = tri;
        return true;
    }
    return false;
}

KD_INLINE void store_hit(const Best *b, Hit *hit)
{
    hit->t = b->t;
    hit->u = b->u;
    hit->v = b->v;
    hit->tri = b->tri;
    hit->key = b->tri;
    hit->inst = 0u;
}

// Nearest hit with t in [tmin, tmax] (ties to the lower triangle index), or, when any_hit,
// the first hit found (shadow rays). Front-to-back stack traversal with t intervals (pbrt).
// Triangles referenced by an inner node are tested when it is visited (against [tmin, best]);
// such a hit is only a candidate, kept until a nearer one appears: traversal stops when the
// next node starts beyond the best hit (by more than the tie tolerance) or the stack is empty.
// `ignore_tri` (NO_HIT for none) is never reported: the triangle a secondary ray leaves from,
// which a ray leaving its plane cannot meet again (a guard beside the origin offset).
inline bool trace_ray(const Ray *r, float tmin, float tmax, bool any_hit, uint ignore_tri,
                      const KdTree *kd, __global const float4 *tri_verts, Hit *hit)
{
    hit->tri = NO_HIT;
    hit->t = INFINITY;
    hit->u = hit->v = 0.0f;
    __global const uint2 *nodes = kd->nodes;
    // The ray's components as arrays: the traversal indexes them by the split axis.
    float org[3] = {r->o.x, r->o.y, r->o.z};
    float inv[3] = {r->inv_d.x, r->inv_d.y, r->inv_d.z};
    float dir[3] = {r->d.x, r->d.y, r->d.z};
    float bmin[3] = {kd->bmin.x, kd->bmin.y, kd->bmin.z};
    float bmax[3] = {kd->bmax.x, kd->bmax.y, kd->bmax.z};

    // Clip to the root box. NaN slab distances (origin on a face, ray parallel to it) compare
    // false and are thereby ignored; the far distance is widened by pbrt's error bound.
    float t0 = tmin, t1 = tmax;
    for (uint axis = 0; axis < 3; ++axis) {
        float tn = (bmin[axis] - org[axis]) * inv[axis];
        float tf = (bmax[axis] - org[axis]) * inv[axis];
        if (tn > tf) { float s = tn; tn = tf; tf = s; }
        tf *= 1.0f + 2.0f * GAMMA3;
        if (tn > t0) t0 = tn;
        if (tf < t1) t1 = tf;
    }
    if (t0 > t1)
        return false;

    TriRay q;
    q.kx = r->kx; q.ky = r->ky; q.kz = r->kz;
    q.okx = org[r->kx]; q.oky = org[r->ky]; q.okz = org[r->kz];
    q.sx = r->sx; q.sy = r->sy; q.sz = r->sz;
    Best b;
    // The scene's size in units of t along this ray, for the tie tolerance.
    b.tie_abs = KD_TIE_EPS * kd->extent / kd_length(r->d);
    b.best = tmax;
    b.limit = tmax + (KD_TIE_EPS * tmax + b.tie_abs);
    b.t = INFINITY;
    b.u = b.v = 0.0f;
    b.tri = NO_HIT;
    StackEntry stack[KD_STACK_SIZE];
    int sp = 0;
    uint node = 0;

    while (true) {
        // Everything left starts at t0 or later (front to back). Not strict, and widened by
        // the tie tolerance (b.limit = best + 1e-6 (best + S)): a node starting at (or within
        // rounding of) the best t is still visited, so equal-t hits there can win the tie.
        if (t0 > b.limit)
            break;
        uint2 n = load_node(kd, node);
        if (!is_leaf(n)) {
            InnerNode in = inner_node(n);
            if (in.has_refs) {
                // T-reference slot: one or two triangles lifted from the leaves below.
                uint2 refs = tref_slot(kd, &in);
                if (consider(&q, refs.x, ignore_tri, tri_verts, tmin, &b) && any_hit)
                    break;
                if (has_second_ref(refs) && consider(&q, refs.y, ignore_tri, tri_verts, tmin, &b)
                    && any_hit)
                    break;
            }
            float o = org[in.axis];
            float tplane = (in.split - o) * inv[in.axis];
            // Bound on tplane's rounding error (one rounding in split - o, which is exact when
            // they are close, one in 1/d, one in the product). Cells that the ray meets within
            // it are visited too, so a ray through an edge or vertex lying in a split plane,
            // whose triangles sit in a cell it only touches there, still finds them (leaves
            // test [tmin, best], so an extra cell costs time, never a wrong answer). 0 when
            // tplane is +-inf (ray parallel to the plane) or NaN (origin on it as well).
            float abs_tplane = kd_fabs(tplane);
            float err = abs_tplane < INFINITY ? 2.0f * GAMMA3 * abs_tplane : 0.0f;
            float enter = tplane - err, leave = tplane + err;
            // The child holding the origin comes first; on the plane the direction decides.
            bool below_first = (o < in.split) || (o == in.split && dir[in.axis] <= 0.0f);
            uint first = below_first ? in.below : in.above;
            uint second = below_first ? in.above : in.below;
            bool first_ok = below_first ? in.below_stored : in.above_stored;
            bool second_ok = below_first ? in.above_stored : in.below_stored;
            // A NaN tplane fails every test and both children are visited: safe. Max/min are
            // comparisons that keep t0/t1 when tplane is NaN (as fmax/fmin would; t0 and t1
            // are never NaN, and the signs of their zeros are never read).
            if (enter > t1 || leave <= 0.0f) {
                if (first_ok) {
                    node = first;
                    continue;
                }
            } else if (leave < t0 && enter > 0.0f) {
                if (second_ok) {
                    node = second;
                    continue;
                }
            } else if (first_ok && second_ok) {
                stack[sp].node = second;
                stack[sp].t0 = enter > t0 ? enter : t0;
                stack[sp].t1 = t1;
                ++sp;
                node = first;
                t1 = leave < t1 ? leave : t1;
                continue;
            } else if (first_ok) {
                node = first;
                t1 = leave < t1 ? leave : t1;
                continue;
            } else {
                node = second;
                t0 = enter > t0 ? enter : t0;
                continue;
            }
            // The only child to visit is elided: nothing here, pop.
        } else {
            // A leaf. Its triangles are tested against [tmin, best] (not the cell interval: a
            // hit found here outside the cell is still a valid candidate, kept until a nearer
            // one appears).
            LeafNode leaf = leaf_node(kd, n);
            for (uint i = 0; i < leaf.count16; ++i)
                prefetch_triangle(tri_verts, leaf16_triangle(&leaf, i));
            for (uint i = 0; i < leaf.count32; ++i)
                prefetch_triangle(tri_verts, leaf32_triangle(&leaf, i));
            bool found = false;
            for (uint i = 0; i < leaf.count16 && !found; ++i)
                found = consider(&q, leaf16_triangle(&leaf, i), ignore_tri, tri_verts, tmin, &b)
                        && any_hit;
            for (uint i = 0; i < leaf.count32 && !found; ++i)
                found = consider(&q, leaf32_triangle(&leaf, i), ignore_tri, tri_verts, tmin, &b)
                        && any_hit;
            if (found)
                break;
        }
        if (sp == 0)
            break;
        --sp;
        node = stack[sp].node;
        t0 = stack[sp].t0;
        t1 = stack[sp].t1;
    }
    store_hit(&b, hit);
    return b.tri != NO_HIT;
}

#ifdef HAS_INSTANCES
// ---------------------------------------------------------------------------------------------
// Instanced scenes (docs/instances.md): a top-level BVH over the instances' world boxes
// (TOPLEVEL records), each instance a mesh's compact kd-tree in object space (its nodes, leaf
// lists and triangles from the mesh's bases: MESH columns), placed by its INSTANCE record.

typedef struct {
    __global const float4 *nodes;       // TOPLEVEL records, node 0 the root
    __global const float4 *instances;   // INSTANCE records in the top level's leaf order
    __global const uint *meshes;        // MESH rows
    __global const float4 *mesh_bounds; // one BOUNDS record per mesh (object space)
#ifdef HAS_OBJECT_MOTION
    float time;                         // the rays' moment in the shutter interval [0, 1]
#endif
} TopLevel;

// Where an instance is at the rays' time: its transforms (rows of 3x4 matrices).
typedef struct {
    float4 to_world[3];                 // object -> world
    float4 to_object[3];                // world -> object
    float orientation;                  // sign of det(to_world): -1 flips the geometric normal
} Placement;

// Instance record I's placement. With HAS_OBJECT_MOTION its transform blends linearly from
// to_world (shutter open) to to_world_end (close) and the blend's linear part is inverted
// here (the adjugate over the determinant; the scene's validation keeps the determinant away
// from zero over the shutter). A point then moves linearly in time, so the union of the open
// and close world boxes (the top level's) bounds it.
KD_INLINE Placement instance_placement(__global const float4 *I, const TopLevel *top)
{
    Placement p;
    __global const float4 *to_world = INSTANCE_TO_WORLD(I);
#ifdef HAS_OBJECT_MOTION
    __global const float4 *to_world_end = INSTANCE_TO_WORLD_END(I);
    float time = top->time;
    for (int k = 0; k < 3; ++k)
        p.to_world[k] = (1.0f - time) * to_world[k] + time * to_world_end[k];
    float3 r0 = p.to_world[0].xyz, r1 = p.to_world[1].xyz, r2 = p.to_world[2].xyz;
    float3 c0 = kd_cross(r1, r2), c1 = kd_cross(r2, r0), c2 = kd_cross(r0, r1);
    float det = kd_dot(r0, c0);
    float3 t = (float3)(p.to_world[0].w, p.to_world[1].w, p.to_world[2].w);
    float3 a0 = (float3)(c0.x, c1.x, c2.x) / det, a1 = (float3)(c0.y, c1.y, c2.y) / det;
    float3 a2 = (float3)(c0.z, c1.z, c2.z) / det;
    p.to_object[0] = (float4)(a0, -kd_dot(a0, t));
    p.to_object[1] = (float4)(a1, -kd_dot(a1, t));
    p.to_object[2] = (float4)(a2, -kd_dot(a2, t));
    p.orientation = det < 0.0f ? -1.0f : 1.0f;
#else
    __global const float4 *to_object = INSTANCE_TO_OBJECT(I);
    for (int k = 0; k < 3; ++k) {
        p.to_world[k] = to_world[k];
        p.to_object[k] = to_object[k];
    }
    p.orientation = INSTANCE_ORIENTATION(I);
#endif
    return p;
}

// p and v through the 3x4 transform of rows m (private rows: a placement's), as transform_point
// and transform_vector.
KD_INLINE float3 placed_vector(const float4 *m, float3 v)
{
    float4 q = (float4)(v, 0.0f);
    return (float3)(kd_dot4(m[0], q), kd_dot4(m[1], q), kd_dot4(m[2], q));
}

KD_INLINE float3 placed_point(const float4 *m, float3 p)
{
    float4 q = (float4)(p, 1.0f);
    return (float3)(kd_dot4(m[0], q), kd_dot4(m[1], q), kd_dot4(m[2], q));
}

// v through the transpose of the linear part of m: a normal of object space to world space
// when m is the world -> object transform (the inverse transpose of object -> world).
KD_INLINE float3 transform_normal(const float4 *m, float3 n)
{
    return (float3)(m[0].x * n.x + m[1].x * n.y + m[2].x * n.z,
                    m[0].y * n.x + m[1].y * n.y + m[2].y * n.z,
                    m[0].z * n.x + m[1].z * n.y + m[2].z * n.z);
}

// The entry distance of the ray into box [lo, hi] within [t0, t1], or INFINITY when it misses
// (slabs as trace_ray's root clip, the far distance widened by pbrt's error bound).
KD_INLINE float box_entry(const Ray *r, float3 lo, float3 hi, float t0, float t1)
{
    float3 tn = (lo - r->o) * r->inv_d, tf = (hi - r->o) * r->inv_d;
    float3 near = fmin(tn, tf), far = fmax(tn, tf);
    // fmin/fmax drop a NaN (origin on a face, ray parallel to it): that slab is ignored.
    float enter = fmax(t0, fmax(near.x, fmax(near.y, near.z)));
    float leave = fmin(t1, fmin(far.x, fmin(far.y, far.z)) * (1.0f + 2.0f * GAMMA3));
    return enter <= leave ? enter : INFINITY;
}

// The mesh's compact tree, from its bases in the scene's concatenated tree arrays.
KD_INLINE KdTree mesh_kdtree(const KdTree *all, const TopLevel *top, uint mesh)
{
    __global const uint *row = top->meshes + MESH_COLUMNS * mesh;
    return make_kdtree(all->nodes + row[MESH_NODE_BASE], all->leaf32 + row[MESH_LEAF32_BASE],
                       all->leaf16 + row[MESH_LEAF16_BASE], row[MESH_LEAF_SHIFT],
                       top->mesh_bounds + BOUNDS_SIZE * mesh);
}

// Instance `k` against the ray: its mesh's tree traversed with the ray in object space (the
// direction is not renormalised, so t stays the world t). Keeps a hit that is nearer than
// hit->t, or as near with a lower key (ties as in the realised scene). `ignore_key`: the key
// never reported (the surface a secondary ray leaves).
KD_INLINE bool consider_instance(const Ray *r, uint k, float tmin, bool any_hit, uint ignore_key,
                                 const KdTree *all, const TopLevel *top,
                                 __global const float4 *tri_verts, Hit *hit)
{
    __global const float4 *I = top->instances + INSTANCE_SIZE * k;
    uint mesh = as_uint(INSTANCE_MESH(I));
    __global const uint *row = top->meshes + MESH_COLUMNS * mesh;
    uint key_base = as_uint(INSTANCE_KEY_BASE(I));
    uint ignore = ignore_key - key_base;         // wraps past tri_count: not this instance's
    if (ignore >= row[MESH_TRI_COUNT])
        ignore = NO_HIT;
    // The origin relative to the instance's own origin first: A (o - T) rather than A o + b,
    // so the rounding scales with the ray's distance from the instance, not with where the
    // instance lies in the world (equal in exact arithmetic).
    Placement p = instance_placement(I, top);
    float3 from_origin = r->o - (float3)(p.to_world[0].w, p.to_world[1].w, p.to_world[2].w);
    Ray ro = make_ray(placed_vector(p.to_object, from_origin), placed_vector(p.to_object, r->d));
    KdTree kd = mesh_kdtree(all, top, mesh);
    Hit h;
    if (!trace_ray(&ro, tmin, hit->t, any_hit, ignore, &kd, tri_verts + TRIANGLE_SIZE * row[MESH_TRI_BASE], &h))
        return false;
    uint key = key_base + h.tri;
    if (!(h.t < hit->t || key < hit->key))
        return false;
    hit->t = h.t;
    hit->u = h.u;
    hit->v = h.v;
    hit->tri = row[MESH_TRI_BASE] + h.tri;
    hit->key = key;
    hit->inst = k;
    return true;
}

// trace_ray for an instanced scene: the nearest hit (ties to the lower key) over all
// instances, or with any_hit the first found. Front-to-back over the top level: the nearer
// child first, the other on a stack with its entry distance; nodes entered beyond the best
// hit (by more than the tie tolerance) are skipped.
inline bool trace_instances(const Ray *r, float tmin, float tmax, bool any_hit, uint ignore_key,
                            const KdTree *all, const TopLevel *top,
                            __global const float4 *tri_verts, Hit *hit)
{
    hit->tri = NO_HIT;
    hit->key = NO_HIT;
    hit->inst = 0u;
    hit->t = tmax;
    hit->u = hit->v = 0.0f;
    uint stack[TOPLEVEL_MAX_DEPTH];
    float stack_t[TOPLEVEL_MAX_DEPTH];
    int sp = 0;
    uint node = 0;
    float t_node = box_entry(r, TOPLEVEL_MIN(top->nodes), TOPLEVEL_MAX(top->nodes), tmin, tmax);
    bool found = false;
    while (true) {
        if (t_node < INFINITY && t_node <= hit->t + KD_TIE_EPS * hit->t) {
            __global const float4 *N = top->nodes + TOPLEVEL_SIZE * node;
            uint first = as_uint(TOPLEVEL_FIRST(N)), count = as_uint(TOPLEVEL_COUNT(N));
            if (count == 0u) {
                __global const float4 *A = top->nodes + TOPLEVEL_SIZE * first;
                __global const float4 *B = A + TOPLEVEL_SIZE;
                float limit = hit->t + KD_TIE_EPS * hit->t;
                float ta = box_entry(r, TOPLEVEL_MIN(A), TOPLEVEL_MAX(A), tmin, limit);
                float tb = box_entry(r, TOPLEVEL_MIN(B), TOPLEVEL_MAX(B), tmin, limit);
                bool a_first = ta <= tb;
                float t_far = a_first ? tb : ta;
                if (t_far < INFINITY) {
                    stack[sp] = a_first ? first + 1u : first;
                    stack_t[sp] = t_far;
                    ++sp;
                }
                node = a_first ? first : first + 1u;
                t_node = a_first ? ta : tb;
                continue;
            }
            for (uint k = first; k < first + count && !found; ++k)
                found = consider_instance(r, k, tmin, any_hit, ignore_key, all, top, tri_verts,
                                          hit) && any_hit;
            if (found)
                break;
        }
        if (sp == 0)
            break;
        --sp;
        node = stack[sp];
        t_node = stack_t[sp];
    }
    if (hit->tri == NO_HIT)
        hit->t = INFINITY;
    return hit->tri != NO_HIT;
}
#endif

// A kernel's top level, from its parameters of core/layout.py TOPLEVEL_PARAMS (shutter_time:
// the moment of the rays; the render kernel draws one per sample instead), and the one
// traversal call of a scene, flat or instanced.
#ifdef HAS_INSTANCES
#ifdef HAS_OBJECT_MOTION
#define TOPLEVEL_MAKE(name) TopLevel name = {toplevel, instances, meshes, mesh_bounds, shutter_time}
#else
#define TOPLEVEL_MAKE(name) TopLevel name = {toplevel, instances, meshes, mesh_bounds}
#endif
#define TOPLEVEL_ARG (&top)
#define trace_scene(r, tmin, tmax, any_hit, ignore, kd, top, tri_verts, hit) \
    trace_instances(r, tmin, tmax, any_hit, ignore, kd, top, tri_verts, hit)
#else
#define TOPLEVEL_MAKE(name)
#define TOPLEVEL_ARG 0
#define trace_scene(r, tmin, tmax, any_hit, ignore, kd, top, tri_verts, hit) \
    trace_ray(r, tmin, tmax, any_hit, ignore, kd, tri_verts, hit)
#endif
