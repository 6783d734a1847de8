// Camera tiles: one work-item per pixel; primary ray, diffuse shading with one shadow ray per
// light, and the depth and normal passes.
//
// Camera buffer (float4 each), filled by slave/tracer.py _pack_camera:
//   cam[0..2]  rows of camera.to_world (3x4: rotation/scale and translation)
//   cam[3]     (ndc_scale.x, ndc_scale.y, ndc_offset.x, ndc_offset.y)
//   cam[4]     (unit view axis in world space, kind: 0 = PERSP, 1 = ORTHO)
//   cam[5]     (clip_start, clip_end, image width, image height)
//   cam[6]     (world colour, unused)
// Light buffer: 4 float4 per light, filled by slave/tracer.py _pack_lights:
//   [0] (position, kind: 0 POINT, 1 SUN, 2 SPOT, 3 AREA)
//   [1] (unit direction the light points, cos of the spot half angle)
//   [2] (intensity: colour times the unit factor of docs/tracer.md, spot smoothing factor)
//   [3] reserved (zeros)

#define LIGHT_POINT 0
#define LIGHT_SUN 1
#define LIGHT_SPOT 2
#define LIGHT_AREA 3

inline float3 transform_point(__global const float4 *m, float3 p)
{
    float4 q = (float4)(p, 1.0f);
    return (float3)(dot(m[0], q), dot(m[1], q), dot(m[2], q));
}

inline float3 transform_vector(__global const float4 *m, float3 v)
{
    float4 q = (float4)(v, 0.0f);
    return (float3)(dot(m[0], q), dot(m[1], q), dot(m[2], q));
}

// Start secondary rays just off the surface, on the side `n` points to (Waechter & Binder,
// Ray Tracing Gems ch. 6): a few ULPs away, which scales with the coordinate's magnitude.
inline float offset_lane(float p, float n)
{
    if (fabs(p) < 1.0f / 32.0f)
        return p + (1.0f / 65536.0f) * n;
    int of = convert_int(256.0f * n);
    return as_float(as_int(p) + (p < 0.0f ? -of : of));
}

inline float3 offset_ray_origin(float3 p, float3 n)
{
    return (float3)(offset_lane(p.x, n.x), offset_lane(p.y, n.y), offset_lane(p.z, n.z));
}

inline float smoothstep01(float x)
{
    x = clamp(x, 0.0f, 1.0f);
    return x * x * (3.0f - 2.0f * x);
}

__kernel void render_tile(__global const float4 *cam, int x0, int y0, int tile_w, int tile_h,
                          __global const uint2 *nodes, __global const uint *leaf_indices,
                          __global const float4 *tri_verts, __global const float4 *bounds,
                          __global const ushort *material_ids, __global const float4 *materials,
                          __global const float4 *lights, uint light_count,
                          __global float4 *out_combined, __global float *out_depth,
                          __global float *out_normal)
{
    int i = get_global_id(0);
    if (i >= tile_w * tile_h)
        return;
    int px = x0 + i % tile_w, py = y0 + i / tile_w;
    float width = cam[5].z, height = cam[5].w;

    // Camera ray (Camera docstring in core/scene.py). The direction is not normalised: t is
    // then proportional to the distance along the view axis, which both clipping and the
    // depth pass measure.
    float ndc_x = ((float)px + 0.5f) / width * 2.0f - 1.0f;
    float ndc_y = 1.0f - ((float)py + 0.5f) / height * 2.0f;
    float2 p = (float2)(ndc_x * cam[3].x + cam[3].z, ndc_y * cam[3].y + cam[3].w);
    float3 o, d;
    if (cam[4].w == 0.0f) {
        o = transform_point(cam, (float3)(0.0f, 0.0f, 0.0f));
        d = transform_vector(cam, (float3)(p, -1.0f));
    } else {
        o = transform_point(cam, (float3)(p, 0.0f));
        d = transform_vector(cam, (float3)(0.0f, 0.0f, -1.0f));
    }
    float along = dot(d, cam[4].xyz);     // view-axis distance per unit of t
    Ray r = make_ray(o, d);
    Hit h;
    trace_ray(&r, cam[5].x / along, cam[5].y / along, false, nodes, leaf_indices, tri_verts,
              bounds[0].xyz, bounds[1].xyz, &h);

    if (h.tri == NO_HIT) {
        out_combined[i] = (float4)(cam[6].xyz, 1.0f);
        out_depth[i] = 1e10f;
        vstore3((float3)(0.0f, 0.0f, 0.0f), i, out_normal);
        return;
    }

    float3 v0 = tri_verts[3 * h.tri].xyz, v1 = tri_verts[3 * h.tri + 1].xyz;
    float3 v2 = tri_verts[3 * h.tri + 2].xyz;
    float3 ng = normalize(cross(v1 - v0, v2 - v0));
    if (dot(ng, d) > 0.0f)
        ng = -ng;
    // The barycentric point is more accurate than o + t d far from the origin.
    float3 hit_p = (1.0f - h.u - h.v) * v0 + h.u * v1 + h.v * v2;
    float3 shadow_o = offset_ray_origin(hit_p, ng);
    float3 albedo = materials[material_ids[h.tri]].xyz;

    float3 radiance = (float3)(0.0f, 0.0f, 0.0f);
    for (uint l = 0; l < light_count; ++l) {
        float4 l0 = lights[4 * l], l1 = lights[4 * l + 1], l2 = lights[4 * l + 2];
        int kind = (int)l0.w;
        float3 to_light;        // shadow ray direction (unnormalised for local lights)
        float shadow_tmax;
        float3 irradiance;      // at normal incidence, before the cosine at the surface
        if (kind == LIGHT_SUN) {
#ifdef HAS_SUN
            to_light = -l1.xyz;
            shadow_tmax = INFINITY;
            irradiance = l2.xyz;
#else
            continue;
#endif
        } else {
            to_light = l0.xyz - shadow_o;
            shadow_tmax = 0.9999f;      // stop just short of the light itself
            float dist2 = dot(to_light, to_light);
            float emit = 1.0f;          // angular falloff of the emitter
            float cos_out = -dot(to_light, l1.xyz) / sqrt(dist2);
#ifdef HAS_SPOT
            if (kind == LIGHT_SPOT) {
                // Cycles: smoothstep((cos - cos_half_angle) * smooth), a hard edge when blend = 0
                emit = l2.w > 0.0f ? smoothstep01((cos_out - l1.w) * l2.w)
                                   : (cos_out > l1.w ? 1.0f : 0.0f);
            }
#endif
#ifdef HAS_AREA
            if (kind == LIGHT_AREA)
                emit = fmax(cos_out, 0.0f);     // one-sided emitter, Lambertian
#endif
            irradiance = l2.xyz * (emit / dist2);
        }
        float cos_in = dot(ng, to_light) / length(to_light);
        if (!(cos_in > 0.0f) || all(irradiance == 0.0f))
            continue;
        Ray s = make_ray(shadow_o, to_light);
        Hit sh;
        if (trace_ray(&s, 0.0f, shadow_tmax, true, nodes, leaf_indices, tri_verts,
                      bounds[0].xyz, bounds[1].xyz, &sh))
            continue;
        radiance += irradiance * cos_in;
    }
    // Lambertian BRDF: albedo / pi.
    out_combined[i] = (float4)(albedo * radiance * M_1_PI_F, 1.0f);
    out_depth[i] = h.t * along;
    vstore3(ng, i, out_normal);
}
