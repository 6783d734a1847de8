// The ray queries of Tracer.intersect and Tracer.occluded: for each of ray_count rays, the
// nearest hit in [tmin, tmax] (intersect_rays), or whether there is any (occluded_rays: what
// trace_ray's any_hit answers, stopping at the first hit found). One ray per work-item, or,
// where the host defines KD_PACKET (CPU devices), KD_PACKET neighbouring rays per work-item:
// traced together by trace_packet (packet.cl) when they go the same way, else one after
// another by trace_ray; the same results either way.
// origins/directions: n packed float3 (the (n, 3) float32 arrays of the host).

// Ray i of the packed float3 arrays (component loads rather than vload3, which PoCL calls out
// of line).
KD_INLINE Ray load_ray(__global const float *origins, __global const float *directions, uint i)
{
    return make_ray((float3)(origins[3 * i], origins[3 * i + 1], origins[3 * i + 2]),
                    (float3)(directions[3 * i], directions[3 * i + 1], directions[3 * i + 2]));
}

// With instances the host is given the hit's key (core/scene/instances.py hit_instance).
KD_INLINE void write_hit(const Hit *h, uint i, __global float *out_t, __global int *out_tri,
                         __global float *out_u, __global float *out_v)
{
    out_t[i] = h->t;
#ifdef HAS_INSTANCES
    out_tri[i] = h->tri == NO_HIT ? -1 : (int)h->key;
#else
    out_tri[i] = h->tri == NO_HIT ? -1 : (int)h->tri;
#endif
    out_u[i] = h->u;
    out_v[i] = h->v;
}

// Instanced scenes trace one ray per work-item (packets are for flat scenes so far).
#if defined(KD_PACKET) && defined(HAS_INSTANCES)
#undef KD_PACKET
#endif

#ifdef KD_PACKET
// Whether the live rays of a packet go the same way: their directions share the octant (the
// signs of all three components). Such rays (a camera's, shadow rays to one light from
// neighbouring points) share most of their path through the tree, and a packet traverses it
// once for all; rays in different octants (bounces off a surface, rays in random order) part
// at the first nodes, where a packet would visit the union of their paths.
KD_INLINE bool packet_coherent(const PacketRays *pr, int8 live)
{
    int8 differ = (int8)(0);
    for (uint a = 0; a < 3; ++a) {
        int8 negative = pr->d[a].v < 0.0f;
        differ |= negative ^ (int8)(negative.s0);
    }
    return !any_lane(live & differ);
}

// Rays that part at once, one after another (out of line: inlined, trace_ray's registers made
// the packet path slower).
__attribute__((noinline)) void trace_one_by_one(const PacketRays *pr, uint count, float tmin,
                                                float tmax, bool any_hit, const KdTree *kd,
                                                __global const float4 *tri_verts, Hit *h)
{
    for (uint k = 0; k < count; ++k) {
        Ray r = lane_ray(pr, k);
        trace_ray(&r, tmin, tmax, any_hit, NO_HIT, kd, tri_verts, &h[k]);
    }
}

// Component a of ray i of the packed float3 arrays p, for the 8 rays i[0..7].
#define LOAD_LANES(p, i, a) (float8)((p)[3 * (i).s0 + (a)], (p)[3 * (i).s1 + (a)], \
    (p)[3 * (i).s2 + (a)], (p)[3 * (i).s3 + (a)], (p)[3 * (i).s4 + (a)], \
    (p)[3 * (i).s5 + (a)], (p)[3 * (i).s6 + (a)], (p)[3 * (i).s7 + (a)])

// The rays of work-item `item` (KD_PACKET consecutive ones, fewer at the end): their hits (or,
// when any_hit, whether each has one) in h.
KD_INLINE uint trace_rays_of_item(uint item, __global const float *origins,
                                  __global const float *directions, float tmin, float tmax,
                                  uint ray_count, bool any_hit, const KdTree *kd,
                                  __global const float4 *tri_verts, Hit *h)
{
    uint first = item * KD_PACKET;
    uint count = min((uint)KD_PACKET, ray_count - first);
    // Past the end: copies of the last ray, switched off.
    uint8 lane = (uint8)(0, 1, 2, 3, 4, 5, 6, 7);
    uint8 index = (uint8)(first) + min(lane, (uint8)(count - 1u));
    int8 live = as_int8(lane) < (int8)((int)count);
    PacketRays pr;
    for (uint a = 0; a < 3; ++a) {
        pr.o[a].v = LOAD_LANES(origins, index, a);
        pr.d[a].v = LOAD_LANES(directions, index, a);
    }
    if (packet_coherent(&pr, live))
        trace_packet(&pr, live, tmin, tmax, any_hit, kd, tri_verts, h);
    else
        trace_one_by_one(&pr, count, tmin, tmax, any_hit, kd, tri_verts, h);
    return count;
}
#endif

// The nearest hit of each ray in [tmin, tmax] (out_t, out_tri, out_u, out_v). The kernels'
// parameters are the tables INTERSECT_RAYS and OCCLUDED_RAYS of core/layout.py (the header's
// *_PARAMS lists), which slave/tracer.py passes its arguments by.
__kernel void intersect_rays(INTERSECT_RAYS_PARAMS)
{
    KdTree kd = make_kdtree(nodes, leaf_index32, leaf_index16, leaf_shift, bounds);
    TOPLEVEL_MAKE(top);
#ifdef KD_PACKET
    uint item = get_global_id(0);
    if (item * KD_PACKET >= ray_count)
        return;
    Hit h[KD_PACKET];
    uint count = trace_rays_of_item(item, origins, directions, tmin, tmax, ray_count, false, &kd,
                                    tri_verts, h);
    for (uint k = 0; k < count; ++k)
        write_hit(&h[k], item * KD_PACKET + k, out_t, out_tri, out_u, out_v);
#else
    uint i = get_global_id(0);
    if (i >= ray_count)
        return;
    Ray r = load_ray(origins, directions, i);
    Hit h;
    trace_scene(&r, tmin, tmax, false, NO_HIT, &kd, TOPLEVEL_ARG, tri_verts, &h);
    write_hit(&h, i, out_t, out_tri, out_u, out_v);
#endif
}

// out_hit[i] = 1 where ray i has a hit in [tmin, tmax], else 0.
__kernel void occluded_rays(OCCLUDED_RAYS_PARAMS)
{
    KdTree kd = make_kdtree(nodes, leaf_index32, leaf_index16, leaf_shift, bounds);
    TOPLEVEL_MAKE(top);
#ifdef KD_PACKET
    uint item = get_global_id(0);
    if (item * KD_PACKET >= ray_count)
        return;
    Hit h[KD_PACKET];
    uint count = trace_rays_of_item(item, origins, directions, tmin, tmax, ray_count, true, &kd,
                                    tri_verts, h);
    for (uint k = 0; k < count; ++k)
        out_hit[item * KD_PACKET + k] = h[k].tri != NO_HIT;
#else
    uint i = get_global_id(0);
    if (i >= ray_count)
        return;
    Ray r = load_ray(origins, directions, i);
    Hit h;
    out_hit[i] = trace_scene(&r, tmin, tmax, true, NO_HIT, &kd, TOPLEVEL_ARG, tri_verts, &h);
#endif
}
