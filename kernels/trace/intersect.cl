// Arbitrary rays: the nearest hit in [tmin, tmax] of each of ray_count rays, one ray per
// work-item, or KD_PACKET neighbouring rays per work-item where the host defines KD_PACKET
// (CPU devices: trace_packet of packet.cl; the same results).
// origins/directions: n packed float3 (the (n, 3) float32 arrays of the host).

// Ray i of the packed float3 arrays (component loads rather than vload3, which PoCL calls out
// of line).
KD_INLINE Ray load_ray(__global const float *origins, __global const float *directions, uint i)
{
    return make_ray((float3)(origins[3 * i], origins[3 * i + 1], origins[3 * i + 2]),
                    (float3)(directions[3 * i], directions[3 * i + 1], directions[3 * i + 2]));
}

KD_INLINE void write_hit(const Hit *h, uint i, __global float *out_t, __global int *out_tri,
                         __global float *out_u, __global float *out_v)
{
    out_t[i] = h->t;
    out_tri[i] = h->tri == NO_HIT ? -1 : (int)h->tri;
    out_u[i] = h->u;
    out_v[i] = h->v;
}

__kernel void intersect_rays(__global const float *origins, __global const float *directions,
                             float tmin, float tmax, uint ray_count,
                             __global const uint2 *nodes, __global const uint *leaf_index32,
                             __global const ushort *leaf_index16, uint leaf_shift,
                             __global const float4 *tri_verts, __global const float4 *bounds,
                             __global float *out_t, __global int *out_tri,
                             __global float *out_u, __global float *out_v)
{
    KdTree kd = make_kdtree(nodes, leaf_index32, leaf_index16, leaf_shift, bounds);
#ifdef KD_PACKET
    // Work-item i traces rays KD_PACKET i .. KD_PACKET i + KD_PACKET - 1.
    uint first = get_global_id(0) * KD_PACKET;
    if (first >= ray_count)
        return;
    Ray r[KD_PACKET];
    LaneMask live;
    for (uint k = 0; k < KD_PACKET; ++k) {
        // Past the end: a copy of the last ray, switched off.
        r[k] = load_ray(origins, directions, min(first + k, ray_count - 1u));
        live.s[k] = first + k < ray_count ? -1 : 0;
    }
    Hit h[KD_PACKET];
    trace_packet(r, live.v, tmin, tmax, &kd, tri_verts, h);
    for (uint k = 0; k < KD_PACKET && first + k < ray_count; ++k)
        write_hit(&h[k], first + k, out_t, out_tri, out_u, out_v);
#else
    uint i = get_global_id(0);
    if (i >= ray_count)
        return;
    Ray r = load_ray(origins, directions, i);
    Hit h;
    trace_ray(&r, tmin, tmax, false, NO_HIT, &kd, tri_verts, &h);
    write_hit(&h, i, out_t, out_tri, out_u, out_v);
#endif
}
