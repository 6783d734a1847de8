// Ray packets for CPU devices: KD_PACKET (8) rays per work-item, traversed together.
// PoCL runs work-items one after another and cannot vectorise the data-dependent node loop,
// so one work-item takes 8 neighbouring rays and does each node's plane test for all of them
// in one float8 operation: neighbouring rays share most of their path through the tree.
// Compiled only where the host defines KD_PACKET (CPU devices; a GPU already runs neighbouring
// work-items in lock step and keeps one ray per work-item): intersect_rays (intersect.cl) then
// traces KD_PACKET rays per work-item with trace_packet.
//
// Each lane does exactly what trace_ray does for its ray: the same child cases, intervals and
// tie tolerance, the same triangles in the same order (a lane is masked off where its ray
// would not go), and it stops for good where trace_ray would stop. Where the lanes disagree
// on which child comes first, the packet visits the first child for the lanes that want it
// first, then the second for all, then the first again for the others; so the results are
// bit-identical to trace_ray's. Nodes are read with trace.cl's node routines, as in trace_ray.
#ifdef KD_PACKET

#if KD_PACKET != 8
#error "KD_PACKET must be 8 (the float8 lanes below)"
#endif

typedef union { float8 v; float s[8]; } Lanes;    // per-lane floats, read as a vector or by lane
typedef union { int8 v; int s[8]; } LaneMask;     // -1: the lane takes part, 0: it does not

KD_INLINE bool any_lane(int8 m)
{
    int4 a = m.lo | m.hi;
    int2 b = a.lo | a.hi;
    return (b.x | b.y) != 0;
}

// select() by bit operations on the all-ones/zero masks: PoCL calls its select out of line.
KD_INLINE float8 pick8(float8 if_clear, float8 if_set, int8 m)
{
    return as_float8((as_int8(if_clear) & ~m) | (as_int8(if_set) & m));
}

KD_INLINE int8 pick_mask8(int8 if_clear, int8 if_set, int8 m)
{
    return (if_clear & ~m) | (if_set & m);
}

KD_INLINE float8 fabs8(float8 x)
{
    return as_float8(as_uint8(x) & 0x7FFFFFFFu);
}

typedef union { uint8 v; uint s[8]; } LaneUints;

// The lanes' ray constants of the watertight test, as vectors (kx, ky, kz: when all lanes
// share the permutation, `same_axes`).
typedef struct {
    Lanes okx, oky, okz, sx, sy, sz;
    uint kx, ky, kz;
    bool same_axes;
} PacketRay;

// The lanes' best hits (Best of trace_ray, one lane each).
typedef struct {
    Lanes best, limit, tie_abs, t, u, v;
    LaneUints tri;
} PacketBest;

// The rays of a packet as lanes: origins and directions by axis.
typedef struct {
    Lanes o[3], d[3];
} PacketRays;

// Lane k's ray (make_ray: what trace_ray is given for it).
KD_INLINE Ray lane_ray(const PacketRays *pr, uint k)
{
    return make_ray((float3)(pr->o[0].s[k], pr->o[1].s[k], pr->o[2].s[k]),
                    (float3)(pr->d[0].s[k], pr->d[1].s[k], pr->d[2].s[k]));
}

// Lane k's constants of the watertight test when the lanes share the permutation.
KD_INLINE TriRay shared_axes_tri_ray(const PacketRay *p, uint k)
{
    TriRay q;
    q.kx = p->kx; q.ky = p->ky; q.kz = p->kz;
    q.okx = p->okx.s[k]; q.oky = p->oky.s[k]; q.okz = p->okz.s[k];
    q.sx = p->sx.s[k]; q.sy = p->sy.s[k]; q.sz = p->sz.s[k];
    return q;
}

// consider() for lane k.
KD_INLINE void consider_lane(uint k, uint tri, const TriRay *q, __global const float4 *tri_verts,
                             float tmin, PacketBest *b)
{
    float t, u, v;
    if (intersect_triangle(q, triangle_corners(tri_verts, tri), tmin, b->best.s[k], &t, &u, &v)
        && (t < b->best.s[k] || tri < b->tri.s[k])) {
        b->best.s[k] = t;
        b->limit.s[k] = t + (KD_TIE_EPS * t + b->tie_abs.s[k]);
        b->t.s[k] = t;
        b->u.s[k] = u;
        b->v.s[k] = v;
        b->tri.s[k] = tri;
    }
}

// consider() for every lane in `m`. When the lanes share the permutation, intersect_triangle's
// arithmetic runs on all lanes at once (the same operations, so the same bits); a lane whose
// edge function is exactly 0, or all lanes otherwise (with their own constants q[k]), take the
// scalar path.
KD_INLINE void consider_lanes(int8 m, uint tri, const PacketRay *p, const TriRay *q,
                              __global const float4 *tri_verts, float tmin, PacketBest *b)
{
    LaneMask one;
    if (p->same_axes) {
        Corners c = triangle_corners(tri_verts, tri);
        uint kx = p->kx, ky = p->ky, kz = p->kz;
        float8 okx = p->okx.v, oky = p->oky.v, okz = p->okz.v, sx = p->sx.v, sy = p->sy.v;
        float8 az = c.v0[kz] - okz, bz = c.v1[kz] - okz, cz = c.v2[kz] - okz;
        float8 ax = (c.v0[kx] - okx) - sx * az, ay = (c.v0[ky] - oky) - sy * az;
        float8 bx = (c.v1[kx] - okx) - sx * bz, by = (c.v1[ky] - oky) - sy * bz;
        float8 cx = (c.v2[kx] - okx) - sx * cz, cy = (c.v2[ky] - oky) - sy * cz;
        float8 e0 = cx * by - cy * bx;
        float8 e1 = ax * cy - ay * cx;
        float8 e2 = bx * ay - by * ax;
        one.v = m & ((e0 == 0.0f) | (e1 == 0.0f) | (e2 == 0.0f));
        if (any_lane(one.v)) {
            for (uint k = 0; k < KD_PACKET; ++k)
                if (one.s[k]) {
                    TriRay qk = shared_axes_tri_ray(p, k);
                    consider_lane(k, tri, &qk, tri_verts, tmin, b);
                }
            m &= ~one.v;
        }
        int8 outside = ((e0 < 0.0f) | (e1 < 0.0f) | (e2 < 0.0f))
                       & ((e0 > 0.0f) | (e1 > 0.0f) | (e2 > 0.0f));
        float8 det = e0 + e1 + e2;
        m &= ~outside & (det != 0.0f);
        if (!any_lane(m))
            return;
        float8 sz = p->sz.v;
        float8 tscaled = e0 * (sz * az) + e1 * (sz * bz) + e2 * (sz * cz);
        float8 t = tscaled / det;
        float8 best = b->best.v;
        m &= (t >= tmin) & (t <= best) & ((t < best) | ((uint8)(tri) < b->tri.v));
        if (!any_lane(m))
            return;
        b->best.v = pick8(best, t, m);
        b->limit.v = pick8(b->limit.v, t + (KD_TIE_EPS * t + b->tie_abs.v), m);
        b->t.v = pick8(b->t.v, t, m);
        b->u.v = pick8(b->u.v, e1 / det, m);
        b->v.v = pick8(b->v.v, e2 / det, m);
        b->tri.v = as_uint8(pick_mask8(as_int8(b->tri.v), (int8)(tri), m));
        return;
    }
    one.v = m;
    for (uint k = 0; k < KD_PACKET; ++k)
        if (one.s[k])
            consider_lane(k, tri, &q[k], tri_verts, tmin, b);
}

// The lanes' component of the axes in `axis` (0, 1, 2 per lane).
KD_INLINE float8 lane_axis8(const Lanes *v, int8 axis)
{
    return pick8(pick8(v[0].v, v[1].v, axis == 1), v[2].v, axis == 2);
}

// Nearest hits of the rays of `pr` for the lanes in `live` (the others are left as misses),
// or, when any_hit, a hit for each lane that has one (a lane stops at its first hit, as
// trace_ray's any_hit: shadow rays).
void trace_packet(const PacketRays *pr, int8 live, float tmin, float tmax, bool any_hit,
                  const KdTree *kd, __global const float4 *tri_verts, Hit *hits)
{
    __global const uint2 *nodes = kd->nodes;
    Lanes org[3], inv[3], dir[3];
    TriRay q[KD_PACKET];
    PacketRay p;
    PacketBest b;
    // make_ray on all lanes at once: the same operations, so the same bits (division and sqrt
    // round correctly in vectors as in scalars). Built as whole vectors: lanes written one by
    // one and then read as vectors stall on store forwarding, which was most of the set-up.
    for (uint a = 0; a < 3; ++a) {
        org[a].v = pr->o[a].v;
        dir[a].v = pr->d[a].v;
        inv[a].v = 1.0f / pr->d[a].v;
    }
    float8 adx = fabs8(dir[0].v), ady = fabs8(dir[1].v), adz = fabs8(dir[2].v);
    int8 kz = pick_mask8(pick_mask8((int8)(2), (int8)(1), ady > adz),
                         pick_mask8((int8)(2), (int8)(0), adx > adz), adx > ady);
    int8 kx = pick_mask8(kz + 1, (int8)(0), kz == 2);
    int8 ky = pick_mask8(kx + 1, (int8)(0), kx == 2);
    float8 dz = lane_axis8(dir, kz);
    int8 flip = dz < 0.0f;          // swap kx and ky to keep the winding (make_ray)
    int8 kx2 = pick_mask8(kx, ky, flip), ky2 = pick_mask8(ky, kx, flip);
    kx = kx2;
    ky = ky2;
    LaneMask differ;
    differ.v = live & ((kx != (int8)(kx.s0)) | (ky != (int8)(ky.s0)) | (kz != (int8)(kz.s0)));
    p.same_axes = !any_lane(differ.v);
    if (p.same_axes) {
        p.kx = (uint)kx.s0; p.ky = (uint)ky.s0; p.kz = (uint)kz.s0;
        p.okx.v = org[p.kx].v; p.oky.v = org[p.ky].v; p.okz.v = org[p.kz].v;
        p.sx.v = dir[p.kx].v / dz;
        p.sy.v = dir[p.ky].v / dz;
        p.sz.v = 1.0f / dz;
    } else {
        for (uint k = 0; k < KD_PACKET; ++k) {
            Ray r = lane_ray(pr, k);
            float o3[3] = {r.o.x, r.o.y, r.o.z};
            q[k].kx = r.kx; q[k].ky = r.ky; q[k].kz = r.kz;
            q[k].okx = o3[r.kx]; q[k].oky = o3[r.ky]; q[k].okz = o3[r.kz];
            q[k].sx = r.sx; q[k].sy = r.sy; q[k].sz = r.sz;
        }
    }
    // kd_length of every lane's direction: one vector sqrt where every sum of squares is in
    // float's normal range, kd_length lane by lane else.
    float8 l2 = dir[0].v * dir[0].v + dir[1].v * dir[1].v + dir[2].v * dir[2].v;
    Lanes len;
    if (!any_lane(~((l2 >= FLT_MIN) & (l2 < INFINITY)))) {
        len.v = sqrt(l2);
    } else {
        for (uint k = 0; k < KD_PACKET; ++k)
            len.s[k] = kd_length((float3)(dir[0].s[k], dir[1].s[k], dir[2].s[k]));
    }
    b.tie_abs.v = KD_TIE_EPS * kd->extent / len.v;
    b.best.v = (float8)(tmax);
    b.limit.v = tmax + (KD_TIE_EPS * tmax + b.tie_abs.v);
    b.t.v = (float8)(INFINITY);
    b.u.v = b.v.v = (float8)(0.0f);
    b.tri.v = (uint8)(NO_HIT);

    // Clip to the root box, as trace_ray (comparisons that keep t0/t1 on NaN).
    float bmin[3] = {kd->bmin.x, kd->bmin.y, kd->bmin.z};
    float bmax[3] = {kd->bmax.x, kd->bmax.y, kd->bmax.z};
    float8 t0 = (float8)(tmin), t1 = (float8)(tmax);
    for (uint axis = 0; axis < 3; ++axis) {
        float8 tn = (bmin[axis] - org[axis].v) * inv[axis].v;
        float8 tf = (bmax[axis] - org[axis].v) * inv[axis].v;
        int8 swap = tn > tf;
        float8 near = pick8(tn, tf, swap), far = pick8(tf, tn, swap);
        far *= 1.0f + 2.0f * GAMMA3;
        t0 = pick8(t0, near, near > t0);
        t1 = pick8(t1, far, far < t1);
    }
    int8 alive = live & (t0 <= t1);     // lanes that have not stopped
    int8 m = alive;                     // lanes that visit the current node

    uint stack_node[2 * KD_STACK_SIZE];   // a node pushes at most two entries
    int8 stack_mask[2 * KD_STACK_SIZE];
    float8 stack_t0[2 * KD_STACK_SIZE], stack_t1[2 * KD_STACK_SIZE];
    int sp = 0;
    uint node = 0;

    while (true) {
        // trace_ray stops a ray for good at a node that starts beyond its best hit.
        int8 stop = m & (t0 > b.limit.v);
        alive &= ~stop;
        m &= ~stop;
        if (any_lane(m)) {
            uint2 n = load_node(kd, node);
            if (!is_leaf(n)) {
                InnerNode in = inner_node(n);
                if (in.has_refs) {
                    // Each lane tests refs.x, then refs.y, as trace_ray does.
                    uint2 refs = tref_slot(kd, &in);
                    consider_lanes(m, refs.x, &p, q, tri_verts, tmin, &b);
                    if (has_second_ref(refs))
                        consider_lanes(m, refs.y, &p, q, tri_verts, tmin, &b);
                    if (any_hit) {
                        // A lane with a hit is done (the second reference makes no difference
                        // to whether it has one).
                        alive &= ~as_int8(b.tri.v != (uint8)(NO_HIT));
                        m &= alive;
                    }
                }
                float split = in.split;
                float8 o = org[in.axis].v, d = dir[in.axis].v;
                float8 tplane = (split - o) * inv[in.axis].v;
                float8 abs_tplane = fabs8(tplane);
                float8 err = as_float8(as_int8((2.0f * GAMMA3) * abs_tplane)
                                       & (abs_tplane < INFINITY));
                float8 enter = tplane - err, leave = tplane + err;
                int8 below_first = (o < split) | ((o == split) & (d <= 0.0f));
                uint below = in.below, above = in.above;
                int8 below_ok = in.below_stored ? (int8)(-1) : (int8)(0);
                int8 above_ok = in.above_stored ? (int8)(-1) : (int8)(0);
                int8 first_ok = pick_mask8(above_ok, below_ok, below_first);
                int8 second_ok = pick_mask8(below_ok, above_ok, below_first);
                // trace_ray's three cases: first child only, second only, both.
                int8 only_first = (enter > t1) | (leave <= 0.0f);
                int8 only_second = ~only_first & (leave < t0) & (enter > 0.0f);
                int8 both = ~(only_first | only_second);
                int8 go_first = m & first_ok & (only_first | both);
                int8 go_second = m & second_ok & (only_second | both);
                float8 first_t1 = pick8(t1, leave, both & (leave < t1));
                float8 second_t0 = pick8(t0, enter, both & (enter > t0));
                int8 go_below = pick_mask8(go_second, go_first, below_first);
                int8 go_above = pick_mask8(go_first, go_second, below_first);
                float8 below_t0 = pick8(second_t0, t0, below_first);
                float8 below_t1 = pick8(t1, first_t1, below_first);
                float8 above_t0 = pick8(t0, second_t0, below_first);
                float8 above_t1 = pick8(first_t1, t1, below_first);
                // Visit order: below for the lanes that want it first, above, below for the rest.
                int8 m1 = go_below & below_first, m2 = go_above, m3 = go_below & ~below_first;
                bool v1 = any_lane(m1), v2 = any_lane(m2), v3 = any_lane(m3);
                if (v3 && (v1 || v2)) {
                    stack_node[sp] = below;
                    stack_mask[sp] = m3;
                    stack_t0[sp] = below_t0;
                    stack_t1[sp] = below_t1;
                    ++sp;
                }
                if (v1) {
                    if (v2) {
                        stack_node[sp] = above;
                        stack_mask[sp] = m2;
                        stack_t0[sp] = above_t0;
                        stack_t1[sp] = above_t1;
                        ++sp;
                    }
                    node = below; m = m1; t0 = below_t0; t1 = below_t1;
                    continue;
                }
                if (v2) {
                    node = above; m = m2; t0 = above_t0; t1 = above_t1;
                    continue;
                }
                if (v3) {
                    node = below; m = m3; t0 = below_t0; t1 = below_t1;
                    continue;
                }
                // No lane goes on from here: pop.
            } else {
                // A leaf: each triangle for every lane here, against the lane's [tmin, best].
                LeafNode leaf = leaf_node(kd, n);
                for (uint i = 0; i < leaf.count16; ++i)
                    consider_lanes(m, leaf16_triangle(&leaf, i), &p, q, tri_verts, tmin, &b);
                for (uint i = 0; i < leaf.count32; ++i)
                    consider_lanes(m, leaf32_triangle(&leaf, i), &p, q, tri_verts, tmin, &b);
                if (any_hit)
                    alive &= ~as_int8(b.tri.v != (uint8)(NO_HIT));
            }
        }
        // Pop the next entry that still has a lane going on.
        do {
            if (sp == 0) {
                for (uint k = 0; k < KD_PACKET; ++k) {
                    hits[k].t = b.t.s[k];
                    hits[k].u = b.u.s[k];
                    hits[k].v = b.v.s[k];
                    hits[k].tri = b.tri.s[k];
                }
                return;
            }
            --sp;
            m = stack_mask[sp] & alive;
        } while (!any_lane(m));
        node = stack_node[sp];
        t0 = stack_t0[sp];
        t1 = stack_t1[sp];
    }
}

#endif
