// Image textures (docs/shading.md, Image Texture and World): texels of the geometry's texture
// table (Geometry.texels, TEXTURE_SIZE rows of core/layout.py), in Cycles' extension modes,
// bilinear or closest. Material textures, node programs' Image Texture nodes and the world's
// Environment Texture read them.

#if defined(HAS_TEXTURES) || defined(HAS_WORLD_TEXTURE)
// Texel (x, y) of the w x h texture at `offset`, the coordinates clamped into it (a NaN or
// infinite coordinate from a node program converts to any int) and the index taken in 64 bits:
// no read leaves the texture, which the host checked lies inside texels (Geometry.validate).
inline float4 texel(const Scene *sc, uint offset, int w, int h, int x, int y)
{
    x = clamp(x, 0, max(w - 1, 0));
    y = clamp(y, 0, max(h - 1, 0));
    return vload_half4((size_t)((ulong)offset + (ulong)y * (ulong)w + (ulong)x), sc->texels);
}

// Texel i of a row or column of n in an Image Texture extension mode (Cycles'); -1: outside
// the image (Clip: black and transparent).
inline int wrap_texel(int i, int n, int extension)
{
    if (extension == NODE_EXTENSION_EXTEND)
        return clamp(i, 0, n - 1);
    if (extension == NODE_EXTENSION_CLIP)
        return i < 0 || i >= n ? -1 : i;
    if (extension == NODE_EXTENSION_MIRROR) {
        int m = i % (2 * n);
        m = m < 0 ? m + 2 * n : m;
        return m < n ? m : 2 * n - 1 - m;
    }
    return i < 0 ? n - 1 : (i >= n ? 0 : i);           // repeat (i is in [-1, n])
}

inline float4 texel_or_clear(const Scene *sc, uint offset, int w, int h, int x, int y)
{
    return x < 0 || y < 0 ? (float4)(0.0f, 0.0f, 0.0f, 0.0f) : texel(sc, offset, w, h, x, y);
}

// Bilinear (or closest) lookup; uv (0, 0) is the first texel (Blender's bottom-left).
// `extension`: a NODE_EXTENSION code (material textures and the world repeat).
inline float4 texture_lookup_ext(const Scene *sc, int tex, float2 uv, bool closest,
                                 int extension)
{
    __global const uint *size = sc->tex_sizes + TEXTURE_SIZE_COLUMNS * tex;
    uint offset = size[TEXTURE_SIZE_OFFSET];
    int w = (int)size[TEXTURE_SIZE_WIDTH], h = (int)size[TEXTURE_SIZE_HEIGHT];
    if (extension == NODE_EXTENSION_REPEAT)
        uv = uv - floor(uv);                           // [0, 1), also for huge uv
    else
        uv = clamp(uv, -4.0f, 5.0f);                   // the same texels, no int overflow
    if (closest) {
        int x = (int)floor(uv.x * (float)w), y = (int)floor(uv.y * (float)h);
        if (extension == NODE_EXTENSION_REPEAT)
            return texel(sc, offset, w, h, x, y);
        return texel_or_clear(sc, offset, w, h, wrap_texel(x, w, extension),
                              wrap_texel(y, h, extension));
    }
    float x = uv.x * (float)w - 0.5f, y = uv.y * (float)h - 0.5f;
    float fx = floor(x), fy = floor(y);
    float tx = x - fx, ty = y - fy;
    int x0 = wrap_texel((int)fx, w, extension), y0 = wrap_texel((int)fy, h, extension);
    int x1 = wrap_texel((int)fx + 1, w, extension), y1 = wrap_texel((int)fy + 1, h, extension);
    float4 c00 = texel_or_clear(sc, offset, w, h, x0, y0), c10 = texel_or_clear(sc, offset, w, h, x1, y0);
    float4 c01 = texel_or_clear(sc, offset, w, h, x0, y1), c11 = texel_or_clear(sc, offset, w, h, x1, y1);
    return (1.0f - ty) * ((1.0f - tx) * c00 + tx * c10) + ty * ((1.0f - tx) * c01 + tx * c11);
}

inline float4 texture_lookup(const Scene *sc, int tex, float2 uv, bool closest)
{
    return texture_lookup_ext(sc, tex, uv, closest, NODE_EXTENSION_REPEAT);
}
#endif
