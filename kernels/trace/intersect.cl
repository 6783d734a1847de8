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
KD_INLINE bool packet_coherent(const Ray *r, int8 live)
{
    LaneMask m;
    m.v = live;
    bool nx = r[0].d.x < 0.0f, ny = r[0].d.y < 0.0f, nz = r[0].d.z < 0.0f;
    bool differ = false;
    for (uint k = 1; k < KD_PACKET; ++k)
        differ |= m.s[k] && ((r[k].d.x < 0.0f) != nx || (r[k].d.y < 0.0f) != ny
                             || (r[k].d.z < 0.0f) != nz);
    return !differ;
}

// Rays that part at once, one after another (out of line: inlined, trace_ray's registers made
// the packet path slower).
__attribute__((noinline)) void trace_one_by_one(const Ray *r, uint count, float tmin, float tmax,
                                                bool any_hit, const KdTree *kd,
                                                __global const float4 *tri_verts, Hit *h)
{
    for (uint k = 0; k < count; ++k)
        trace_ray(&r[k], tmin, tmax, any_hit, NO_HIT, kd, tri_verts, &h[k]);
}

// The rays of work-item `item` (KD_PACKET consecutive ones, fewer at the end): their hits (or,
// when any_hit, whether each has one) in h.
KD_INLINE uint trace_rays_of_item(uint item, __global const float *origins,
                                  __global const float *directions, float tmin, float tmax,
                                  uint ray_count, bool any_hit, const KdTree *kd,
                                  __global const float4 *tri_verts, Hit *h)
{
    uint first = item * KD_PACKET;
    uint count = min((uint)KD_PACKET, ray_count - first);
    Ray r[KD_PACKET];
    LaneMask live;
    for (uint k = 0; k < KD_PACKET; ++k) {
        // Past the end: a copy of the last ray, switched off.
        r[k] = load_ray(origins, directions, first + min(k, count - 1u));
        live.s[k] = k < count ? -1 : 0;
    }
    if (packet_coherent(r, live.v))
        trace_packet(r, live.v, tmin, tmax, any_hit, kd, tri_verts, h);
    else
        trace_one_by_one(r, count, tmin, tmax, any_hit, kd, tri_verts, h);
    return count;
}
#endif

__kernel void intersect_rays(__global const float *origins, __global const float *directions,
                             float tmin, float tmax, uint ray_count,
                             __global const uint2 *nodes, __global const uint *leaf_index32,
                             __global const ushort *leaf_index16, uint leaf_shift,
                             __global const float4 *tri_verts, __global const float4 *bounds
                             TOPLEVEL_PARAMS,
                             __global float *out_t, __global int *out_tri,
                             __global float *out_u, __global float *out_v)
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
__kernel void occluded_rays(__global const float *origins, __global const float *directions,
                            float tmin, float tmax, uint ray_count,
                            __global const uint2 *nodes, __global const uint *leaf_index32,
                            __global const ushort *leaf_index16, uint leaf_shift,
                            __global const float4 *tri_verts, __global const float4 *bounds
                            TOPLEVEL_PARAMS,
                            __global uchar *out_hit)
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
