// Lights (docs/shading.md, World, Emissive meshes as lights, Blender's lights): the world
// (colour or Environment Texture, importance-sampled by its map), emissive triangles (chosen
// by power with the alias table of EMITTER records) and Blender's lights (LIGHT records),
// each with the density a BSDF ray that finds it is weighed against.

// ---------------------------------------------------------------------------------------------
// The world

#ifdef HAS_WORLD_TEXTURE
// A direction in the texture's space -> uv of the projection (Cycles' conventions).
inline float2 world_uv(int projection, float3 d)
{
    if (projection == PROJECTION_MIRROR_BALL) {
        float dy = d.y - 1.0f;
        float div = 2.0f * sqrt(fmax(-0.5f * dy, 0.0f));
        float x = div > 0.0f ? d.x / div : d.x, z = div > 0.0f ? d.z / div : d.z;
        return (float2)(0.5f * (x + 1.0f), 0.5f * (z + 1.0f));
    }
    float u = 0.5f - atan2_poly(d.y, d.x) * (0.5f * M_1_PI_F);
    float v = 0.5f + atan2_poly(d.z, sqrt(d.x * d.x + d.y * d.y)) * M_1_PI_F;
    return (float2)(u, v);
}

// uv -> a unit direction in the texture's space; false outside a mirror ball's disk.
inline bool world_direction(int projection, float2 uv, float3 *d)
{
    if (projection == PROJECTION_MIRROR_BALL) {
        float x = 2.0f * uv.x - 1.0f, z = 2.0f * uv.y - 1.0f;
        float r2 = x * x + z * z;
        if (r2 > 1.0f)
            return false;
        float s = 2.0f * sqrt(1.0f - r2);
        *d = (float3)(s * x, 2.0f * r2 - 1.0f, s * z);
        return true;
    }
    float2 phi = sincos_poly(M_PI_F * (1.0f - 2.0f * uv.x));
    float2 elevation = sincos_poly(M_PI_F * (uv.y - 0.5f));
    *d = (float3)(elevation.y * phi.y, elevation.y * phi.x, elevation.x);
    return true;
}

// Solid angle of the texture's space per unit of uv at d (unit).
inline float world_jacobian(int projection, float3 d)
{
    return projection == PROJECTION_MIRROR_BALL ? 16.0f
                                                : 2.0f * M_PI_F * M_PI_F * sqrt(d.x * d.x + d.y * d.y);
}

inline float3 rows_times(__global const float4 *m, float3 v)
{
    return (float3)(kd_dot(m[0].xyz, v), kd_dot(m[1].xyz, v), kd_dot(m[2].xyz, v));
}

// The importance map: marginal CDF of the rows (height + 1), then each row's CDF (width + 1).
inline float env_cell_probability(const Scene *sc, int i, int j)
{
    __global const float4 *W = sc->world;
    int w = (int)WORLD_CDF_WIDTH(W), h = (int)WORLD_CDF_HEIGHT(W);
    __global const float *row = sc->env_cdf + (h + 1) + j * (w + 1);
    return (sc->env_cdf[j + 1] - sc->env_cdf[j]) * (row[i + 1] - row[i]);
}

// Largest k in [0, n) with cdf[k] <= u (cdf[0] = 0, cdf[n] = 1).
inline int cdf_find(__global const float *cdf, int n, float u)
{
    int lo = 0, hi = n;
    while (hi - lo > 1) {
        int mid = (lo + hi) >> 1;
        if (cdf[mid] <= u)
            lo = mid;
        else
            hi = mid;
    }
    return lo;
}
#endif

// What a ray leaving the scene in unit direction d sees.
inline float3 world_radiance(const Scene *sc, float3 d)
{
    float3 c = sc->world_color;
#ifdef HAS_WORLD_TEXTURE
    __global const float4 *W = sc->world;
    int tex = (int)WORLD_TEXTURE(W);
    if (tex >= 0) {
        int projection = (int)WORLD_PROJECTION(W);
        float3 dt = kd_normalize(rows_times(WORLD_TO_TEXTURE(W), d));
        float2 uv = world_uv(projection, dt);
        c *= texture_lookup(sc, tex, uv, WORLD_INTERPOLATION(W) == INTERPOLATION_CLOSEST).xyz;
    }
#endif
    return c;
}

#ifdef HAS_WORLD
// Whether direct light samples the world: only a world that varies with direction (an
// Environment Texture). A constant world is left to the BSDF rays, as Cycles leaves it
// ("Background MIS has been disabled"): for a colour a BSDF sample is the better of the two
// (cosine-distributed on a diffuse surface, against uniform over the sphere), so the light
// samples' shadow rays would add time, not much else.
inline bool world_light_sampled(const Scene *sc)
{
#ifdef HAS_WORLD_TEXTURE
    return (int)WORLD_TEXTURE(sc->world) >= 0;
#else
    return false;
#endif
}

// Density (solid angle) of world_sample choosing unit direction d; 0 where direct light does
// not sample the world (a BSDF ray that finds it then counts in full).
inline float world_pdf(const Scene *sc, float3 d)
{
#ifdef HAS_WORLD_TEXTURE
    __global const float4 *W = sc->world;
    if (world_light_sampled(sc)) {
        int projection = (int)WORLD_PROJECTION(W);
        int w = (int)WORLD_CDF_WIDTH(W), h = (int)WORLD_CDF_HEIGHT(W);
        float3 a = rows_times(WORLD_TO_TEXTURE(W), d);
        float la = kd_length(a);
        float3 dt = a / la;
        float2 uv = world_uv(projection, dt);
        uv = uv - floor(uv);
        int i = min((int)(uv.x * (float)w), w - 1), j = min((int)(uv.y * (float)h), h - 1);
        float jac = world_jacobian(projection, dt);
        if (!(jac > 0.0f))
            return 0.0f;
        // Texture space -> world: |det A| / |A d|^3 (the solid-angle Jacobian of d -> Ad/|Ad|).
        return env_cell_probability(sc, i, j) * (float)(w * h) / jac
               * (WORLD_DET(W) / (la * la * la));
    }
#endif
    return 0.0f;
}

#ifdef HAS_WORLD_TEXTURE
// A direction towards the world, importance-sampled from its texture (only where
// world_light_sampled); returns its radiance, *pdf its density.
inline float3 world_sample(const Scene *sc, float u1, float u2, float3 *wi, float *pdf)
{
    __global const float4 *W = sc->world;
    int projection = (int)WORLD_PROJECTION(W);
    int w = (int)WORLD_CDF_WIDTH(W), h = (int)WORLD_CDF_HEIGHT(W);
    __global const float *marginal = sc->env_cdf;
    int j = cdf_find(marginal, h, u1);
    float pj = marginal[j + 1] - marginal[j];
    __global const float *row = sc->env_cdf + (h + 1) + j * (w + 1);
    int i = cdf_find(row, w, u2);
    float pi = row[i + 1] - row[i];
    if (!(pj > 0.0f) || !(pi > 0.0f)) {
        *pdf = 0.0f;
        return (float3)(0.0f, 0.0f, 0.0f);
    }
    float2 uv = (float2)(((float)i + clamp((u2 - row[i]) / pi, 0.0f, 1.0f)) / (float)w,
                         ((float)j + clamp((u1 - marginal[j]) / pj, 0.0f, 1.0f)) / (float)h);
    float3 dt;
    if (!world_direction(projection, uv, &dt)) {
        *pdf = 0.0f;
        return (float3)(0.0f, 0.0f, 0.0f);
    }
    float3 d = rows_times(WORLD_FROM_TEXTURE(W), dt);
    float ld = kd_length(d);
    *wi = d / ld;
    float jac = world_jacobian(projection, dt);
    // |A wi| = 1 / |A^-1 dt|.
    *pdf = jac > 0.0f ? pj * pi * (float)(w * h) / jac * (WORLD_DET(W) * ld * ld * ld) : 0.0f;
    return world_radiance(sc, *wi);
}
#endif
#endif

// ---------------------------------------------------------------------------------------------
// Emissive triangles

#ifdef HAS_EMISSION
inline float triangle_area(const Scene *sc, uint tri, float3 *n)
{
    __global const float4 *corners = sc->tri_verts + TRIANGLE_SIZE * tri;
    float3 c = kd_cross(TRIANGLE_V1(corners) - TRIANGLE_V0(corners),
                     TRIANGLE_V2(corners) - TRIANGLE_V0(corners));
    float len = kd_length(c);
    *n = len > 0.0f ? c / len : (float3)(0.0f, 0.0f, 1.0f);
    return 0.5f * len;
}

// Density (solid angle) of emitter_sample choosing the point at distance `dist` on triangle
// tri whose normal makes cosine cos_l with the ray.
inline float emitter_pdf(const Scene *sc, uint tri, float dist, float cos_l)
{
    float3 n;
    float area = triangle_area(sc, tri, &n);
    __global const float4 *M = sc->materials + MATERIAL_SIZE * sc->material_ids[tri];
#ifdef HAS_CLOSURES
    // As slave/buffers.py material_emission: each closure's mean emission times its weight.
    float strength = 0.0f;
    int closures = clamp((int)MATERIAL_CLOSURES(M), 1, CLOSURES_MAX);
    for (int k = 0; k < closures; ++k, M += MATERIAL_SIZE)
        strength += mean3(MATERIAL_EMISSION(M)) * MATERIAL_WEIGHT(M);
    float power = strength * area;
#else
    float power = mean3(MATERIAL_EMISSION(M)) * area;
#endif
    if (!(area > 0.0f) || !(cos_l > 0.0f) || !(sc->emitter_power > 0.0f))
        return 0.0f;
    return power / sc->emitter_power / area * (dist * dist / cos_l);
}

// A point on an emissive triangle (chosen by power with the alias table) seen from p. Returns
// its emitted radiance (0 when nothing), *wi, *dist, *pdf (solid angle) and *tri.
inline float3 emitter_sample(const Scene *sc, float3 p, float u0, float u1, float u2,
                             float3 *wi, float *dist, float *pdf, uint *tri)
{
    float x = u0 * (float)sc->emitter_count;
    uint k = min((uint)x, sc->emitter_count - 1u);
    __global const float4 *E = sc->emitters + EMITTER_SIZE * k;
    if (x - (float)k >= EMITTER_THRESHOLD(E))
        E = sc->emitters + EMITTER_SIZE * as_uint(EMITTER_ALIAS(E));
    *tri = as_uint(EMITTER_TRIANGLE(E));
    float pmf = EMITTER_PMF(E);
    __global const float4 *corners = sc->tri_verts + TRIANGLE_SIZE * *tri;
    float s = sqrt(u1);
    float b0 = 1.0f - s, b1 = u2 * s;
    float3 q = b0 * TRIANGLE_V0(corners) + b1 * TRIANGLE_V1(corners)
               + (1.0f - b0 - b1) * TRIANGLE_V2(corners);
    float3 n;
    float area = triangle_area(sc, *tri, &n);
    float3 to = q - p;
    float d2 = kd_dot(to, to);
    float d = sqrt(d2);
    if (!(d > 0.0f) || !(area > 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
    *wi = to / d;
    *dist = d;
    float cos_l = fabs(kd_dot(n, *wi));                   // emission is two-sided, as Cycles'
    if (!(cos_l > 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
    *pdf = pmf / area * (d2 / cos_l);
    // The emission as a BSDF ray along wi would find it (the nodes' N: the face's normal).
    ShadeInfo info;
    info.incoming = -*wi;
    info.backfacing = kd_dot(n, *wi) > 0.0f;
    info.normal = info.backfacing ? -n : n;
    info.ng = info.normal;
#ifdef HAS_LIGHT_PATH
    info.path = 0u;         // Cycles evaluates light samples' emission as PATH_RAY_EMISSION
    info.length = *dist;
    info.bounce = info.diffuse = info.glossy = info.transmission = info.transparent = 0;
#endif
#ifdef HAS_CLOSURES
    ClosureSum cs;
    closures_eval(sc, *tri, b1, 1.0f - b0 - b1, 0, &info, 0.5f, &cs);
    return cs.emission;
#else
    Material m = material_eval(sc, *tri, b1, 1.0f - b0 - b1, 0, &info);
    return m.emission * clamp(m.alpha, 0.0f, 1.0f);
#endif
}
#endif

// ---------------------------------------------------------------------------------------------
// Blender's lights

inline float smoothstep01(float x)
{
    x = clamp(x, 0.0f, 1.0f);
    return x * x * (3.0f - 2.0f * x);
}

inline float area_light_area(__global const float4 *L)
{
    float a = kd_length(LIGHT_AREA_U(L)) * kd_length(LIGHT_AREA_V(L));
    return LIGHT_AREA_SHAPE(L) == LIGHT_SHAPE_ELLIPSE ? a * M_PI_4_F : a;
}

#ifdef HAS_SPHERE_LIGHTS
// A point or spot light with Soft Falloff off: Cycles' sphere of light (point.h, spot.h; its
// radiance the power over 4 pi^2 r^2, colour x LIGHT_INTENSITY / (pi r^2)), its visible cap
// sampled uniformly in solid angle from outside, every direction from inside; a spot's cone
// is measured along each sampled ray, as Cycles measures it. Returns radiance over density.
inline float3 sample_sphere_light(__global const float4 *L, int kind, float3 p, float u1,
                                  float u2, float3 *wi, float3 *target, float *dist)
{
    float r = LIGHT_RADIUS(L), r2 = r * r;
    float3 to = LIGHT_POSITION(L) - p;
    float d2 = kd_dot(to, to), d = sqrt(d2);
    float3 radiance = LIGHT_INTENSITY(L) * (1.0f / (M_PI_F * r2));
    float3 w;
    float over_pdf, t;
    if (d2 > r2) {
        float s2 = r2 / d2, one_minus_cos = s2 / (1.0f + sqrt(1.0f - s2));
        w = kd_normalize(uniform_cone(to / d, 1.0f - one_minus_cos, u1, u2));
        over_pdf = 2.0f * M_PI_F * one_minus_cos;
        float c = kd_dot(w, to) / d;        // law of cosines: the nearer intersection
        t = d * c - sqrt(fmax(r2 - d2 + d2 * c * c, 0.0f));
#ifdef HAS_SPOT
        if (kind == LIGHT_SPOT) {
            float cos_half = LIGHT_SPOT_COS_HALF(L), smooth = LIGHT_SPOT_SMOOTH(L);
            float cz = -kd_dot(w, LIGHT_DIRECTION(L));
            radiance *= smooth > 0.0f ? smoothstep01((cz - cos_half) * smooth)
                                      : (cz > cos_half ? 1.0f : 0.0f);
        }
#endif
    } else {
        float z = 1.0f - 2.0f * u1, sz = sqrt(fmax(0.0f, 1.0f - z * z));
        float2 e = sincos_poly(2.0f * M_PI_F * u2);
        w = (float3)(sz * e.y, sz * e.x, z);
        over_pdf = 4.0f * M_PI_F;
        float c = d > 0.0f ? kd_dot(w, to) / d : 0.0f;
        t = d * c + sqrt(fmax(r2 - d2 + d2 * c * c, 0.0f));
    }
    if (!(t > 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
    *wi = w;
    *dist = t;
    *target = p + t * w;
    return radiance * over_pdf;
}
#endif

// Sample a point on light l as seen from p: returns the irradiance at normal incidence (before
// the cosine at the surface and before shadowing); *wi the unit direction to it, *target the
// point (for local lights), *dist its distance (INFINITY for the sun) and *pdf the sample's
// density in solid angle for lights a BSDF ray can also hit (area lights, a sun with an
// angle), else 0 (no multiple importance sampling).
inline float3 sample_light(const Scene *sc, uint l, float3 p, float u1, float u2, float3 *wi,
                           float3 *target, float *dist, float *pdf)
{
    __global const float4 *L = sc->lights + LIGHT_SIZE * l;
    int kind = (int)LIGHT_KIND(L);
    *pdf = 0.0f;
    if (kind == LIGHT_SUN) {
#ifdef HAS_SUN
        float3 w = -LIGHT_DIRECTION(L);
#ifdef HAS_SOFT_LIGHTS
        float cos_half = LIGHT_SUN_COS_HALF_ANGLE(L);
        if (cos_half < 1.0f) {
            w = kd_normalize(uniform_cone(w, cos_half, u1, u2));
            *pdf = 1.0f / (2.0f * M_PI_F * (1.0f - cos_half));
        }
#endif
        *wi = w;
        *dist = INFINITY;
        *target = p;
        return LIGHT_INTENSITY(L);
#else
        return (float3)(0.0f, 0.0f, 0.0f);
#endif
    }
    float3 pos = LIGHT_POSITION(L);
    float emit = 1.0f;
    if (kind == LIGHT_AREA) {
#ifdef HAS_AREA
        float3 area_u = LIGHT_AREA_U(L), area_v = LIGHT_AREA_V(L);
        if (LIGHT_AREA_SHAPE(L) == LIGHT_SHAPE_ELLIPSE) {
            float2 d = concentric_disk(u1, u2);
            pos += 0.5f * d.x * area_u + 0.5f * d.y * area_v;
        } else {
            pos += (u1 - 0.5f) * area_u + (u2 - 0.5f) * area_v;
        }
#else
        return (float3)(0.0f, 0.0f, 0.0f);
#endif
    }
#ifdef HAS_SPHERE_LIGHTS
    else if (LIGHT_RADIUS(L) > 0.0f && LIGHT_SPHERE(L) > 0.0f)
        return sample_sphere_light(L, kind, p, u1, u2, wi, target, dist);
#endif
#ifdef HAS_SOFT_LIGHTS
    else if (LIGHT_RADIUS(L) > 0.0f) {
        // A sphere light seen from p: a disk facing p (uniform radiance: same irradiance as
        // the point while unoccluded), which gives soft shadows.
        float3 axis = kd_normalize(p - LIGHT_POSITION(L));
        float3 t, b;
        basis(axis, &t, &b);
        float2 d = concentric_disk(u1, u2);
        pos += LIGHT_RADIUS(L) * (d.x * t + d.y * b);
    }
#endif
    float3 to = pos - p;
    float dist2 = kd_dot(to, to);
    float dl = sqrt(dist2);
    if (!(dl > 0.0f))
        return (float3)(0.0f, 0.0f, 0.0f);
    *wi = to / dl;
    *dist = dl;
    *target = pos;
    float cos_out = -kd_dot(*wi, LIGHT_DIRECTION(L));
#ifdef HAS_SPOT
    if (kind == LIGHT_SPOT) {
        // The cone is measured from the light's centre (Cycles: smoothstep over the blend).
        float3 from_centre = kd_normalize(p - LIGHT_POSITION(L));
        float c = kd_dot(from_centre, LIGHT_DIRECTION(L));
        float cos_half = LIGHT_SPOT_COS_HALF(L), smooth = LIGHT_SPOT_SMOOTH(L);
        emit = smooth > 0.0f ? smoothstep01((c - cos_half) * smooth) : (c > cos_half ? 1.0f : 0.0f);
    }
#endif
#ifdef HAS_AREA
    if (kind == LIGHT_AREA) {
        emit = fmax(cos_out, 0.0f);     // one-sided Lambertian emitter
        float area = area_light_area(L);
        *pdf = cos_out > 0.0f && area > 0.0f ? dist2 / (area * cos_out) : 0.0f;
    }
#endif
    return LIGHT_INTENSITY(L) * (emit / dist2);
}

#ifdef HAS_AREA
// The nearest area light that the ray (o, unit d) reaches on its emitting side before t_max:
// returns its radiance (0 when none), *t_light and *pdf (solid angle, as sample_light).
inline float3 area_light_hit(const Scene *sc, float3 o, float3 d, float t_max, float *pdf)
{
    float3 found = (float3)(0.0f, 0.0f, 0.0f);
    float best = t_max;
    *pdf = 0.0f;
    for (uint l = 0; l < sc->light_count; ++l) {
        __global const float4 *L = sc->lights + LIGHT_SIZE * l;
        if ((int)LIGHT_KIND(L) != LIGHT_AREA)
            continue;
        float3 n = LIGHT_DIRECTION(L);
        float denom = kd_dot(d, n);
        if (!(denom < 0.0f))
            continue;
        float t = kd_dot(LIGHT_POSITION(L) - o, n) / denom;
        if (!(t > 0.0f) || !(t < best))
            continue;
        float3 q = o + t * d - LIGHT_POSITION(L);
        float3 au = LIGHT_AREA_U(L), av = LIGHT_AREA_V(L);
        float a = kd_dot(q, au) / kd_dot(au, au), b = kd_dot(q, av) / kd_dot(av, av);
        bool inside = LIGHT_AREA_SHAPE(L) == LIGHT_SHAPE_ELLIPSE ? 4.0f * (a * a + b * b) <= 1.0f
                                                                 : fabs(a) <= 0.5f && fabs(b) <= 0.5f;
        float area = area_light_area(L);
        if (!inside || !(area > 0.0f))
            continue;
        best = t;
        found = LIGHT_INTENSITY(L) / area;
        *pdf = t * t / (area * -denom);
    }
    return found;
}
#endif

#if defined(HAS_SUN) && defined(HAS_SOFT_LIGHTS)
// Suns with an angle that a ray leaving the scene in unit direction d looks into: their
// radiance, with the MIS weight against a BSDF density pdf_bsdf (0: a mirror, weight 1).
inline float3 sun_disks(const Scene *sc, float3 d, float pdf_bsdf, float n_light)
{
    float3 sum = (float3)(0.0f, 0.0f, 0.0f);
    for (uint l = 0; l < sc->light_count; ++l) {
        __global const float4 *L = sc->lights + LIGHT_SIZE * l;
        float cos_half = LIGHT_SUN_COS_HALF_ANGLE(L);
        if ((int)LIGHT_KIND(L) != LIGHT_SUN || !(cos_half < 1.0f)
            || kd_dot(d, -LIGHT_DIRECTION(L)) < cos_half)
            continue;
        float pdf_l = 1.0f / (2.0f * M_PI_F * (1.0f - cos_half));
        float w = pdf_bsdf > 0.0f ? mis_weight(pdf_bsdf, n_light * pdf_l) : 1.0f;
        sum += LIGHT_INTENSITY(L) * (pdf_l * w);
    }
    return sum;
}
#endif
