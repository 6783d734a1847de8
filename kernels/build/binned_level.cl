/* The binned builder's kernels, one level at a time (after binned.cl, whose records and SAH
   search they use; its head comment says how a level goes): the choice of each node's split,
   big nodes' histograms by chunks, the level's sums, emit, the straddlers' clipping and the
   references' scatter to the children, and the first references. */

/* ----------------------------------------------------------------------------------------
   choose_nodes: one work-item per node of at most KD_BIG_REFS references. */

__kernel void choose_nodes(__global const LevelNode* restrict nodes,
                           __global const Ref* restrict refs,
                           __global Split* restrict splits,
                           uint n_nodes, uint level, uint depth_cap, float pow2)
{
    uint i = (uint)get_global_id(0);
    if (i >= n_nodes)
        return;
    LevelNode node = nodes[i];
    if (node.count > KD_BIG_REFS)
        return;                          /* choose_big's */
    __global const Ref* r = refs + node.first;
    Search s;
    uint n = 0u;
    if (node.count <= KD_EXACT_MAX) {
        float lo[3][KD_EXACT_MAX], hi[3][KD_EXACT_MAX];
        for (uint j = 0u; j < node.count; j++) {
            Ref x = r[j];
            if (ref_tri(x) == HOLE)
                continue;
            for (int a = 0; a < 3; a++) {
                lo[a][n] = lane(x.lo, a);
                hi[a][n] = lane(x.hi, a);
            }
            n++;
        }
        search_init(&s, node.lo, node.hi, n, pow2);
        if (level < depth_cap)
            for (int a = 0; a < 3; a++)
                exact_axis(&s, a, lo[a], hi[a], n, bin_count(node.count), pow2);
    } else {
        Planes pl;
        planes_of(&pl, node.lo, node.hi, node.count);
        uint h[HIST_WORDS];
        bin_refs(r, node.count, &pl, node.lo, h);
        n = h[HIST_VALID];
        search_init(&s, node.lo, node.hi, n, pow2);
        if (level < depth_cap)
            consider_bins(&s, h, &pl, n, pow2);
    }
    decide(splits + i, &s, n, node.bad, level, depth_cap);
}

/* ----------------------------------------------------------------------------------------
   Big nodes: histograms per chunk of references (bin_chunks), summed in chunk order per node
   (choose_big), which also gives each chunk its first places in the children. Chunk rows:
   BIN_CHUNK (node, first, count, and the places choose_big writes); big node rows:
   BIN_BIG (node, first chunk, chunks). */

__kernel void bin_chunks(__global const LevelNode* restrict nodes,
                         __global const Ref* restrict refs,
                         __global const uint* restrict chunks,
                         __global uint* restrict hist, uint n_chunks)
{
    uint c = (uint)get_global_id(0);
    if (c >= n_chunks)
        return;
    __global const uint* row = chunks + BIN_CHUNK_COLUMNS * c;
    LevelNode node = nodes[row[BIN_CHUNK_NODE]];
    Planes pl;
    planes_of(&pl, node.lo, node.hi, node.count);
    uint h[HIST_WORDS];
    bin_refs(refs + row[BIN_CHUNK_FIRST], row[BIN_CHUNK_COUNT], &pl, node.lo, h);
    __global uint* out = hist + (size_t)HIST_WORDS * c;
    for (uint k = 0u; k < HIST_WORDS; k++)
        out[k] = h[k];
}

/* A chunk's references below / above the chosen plane, from its histogram. */
inline void chunk_sides(__global const uint* h, const Split* d, const Planes* pl,
                        const LevelNode* node, uint* below, uint* above)
{
    uint n = h[HIST_VALID];
    if (d->flags & SPLIT_LEAF) {
        *below = *above = 0u;
        return;
    }
    int a = (int)SPLIT_AXIS(d->flags);
    float p = d->plane;
    /* The chosen plane is a bin plane (the last of equal ones) or a tight-bound cut. */
    uint k = 0u;
    for (uint j = 1u; j < pl->bins; j++)
        if (pl->p[a][j] == p)
            k = j;
    uint nb = 0u, na = 0u, np = 0u;
    if (k) {
        for (uint j = 0u; j < k; j++)
            nb += h[HIST_LO(a, j)];
        for (uint j = k; j < pl->bins; j++)
            na += h[HIST_HI(a, j)];
        np = h[HIST_FLAT(a, k)];
    } else {
        /* A tight-bound cut of the node: every reference of the chunk on one side. */
        int low_cut = d->below == 0u;
        nb = low_cut ? 0u : n;
        na = low_cut ? n : 0u;
    }
    if (d->flags & SPLIT_PLANAR_ABOVE)
        na += np;
    else
        nb += np;
    *below = nb;
    *above = na;
}

__kernel void choose_big(__global const LevelNode* restrict nodes,
                         __global const uint* restrict big,
                         __global uint* restrict chunks,
                         __global const uint* restrict hist,
                         __global Split* restrict splits,
                         uint n_big, uint level, uint depth_cap, float pow2)
{
    uint b = (uint)get_global_id(0);
    if (b >= n_big)
        return;
    __global const uint* row = big + BIN_BIG_COLUMNS * b;
    uint i = row[BIN_BIG_NODE], first = row[BIN_BIG_FIRST_CHUNK], count = row[BIN_BIG_CHUNKS];
    LevelNode node = nodes[i];
    Planes pl;
    planes_of(&pl, node.lo, node.hi, node.count);
    uint h[HIST_WORDS];
    for (uint k = 0u; k < HIST_WORDS; k++)
        h[k] = 0u;
    for (int a = 0; a < 3; a++) {
        h[HIST_TIGHT + a] = as_uint(INFINITY);
        h[HIST_TIGHT + 3 + a] = as_uint(-INFINITY);
    }
    for (uint c = first; c < first + count; c++) {
        __global const uint* hc = hist + (size_t)HIST_WORDS * c;
        for (uint k = 0u; k < 3u * HIST_AXIS; k++)
            h[k] += hc[k];
        h[HIST_VALID] += hc[HIST_VALID];
        for (int a = 0; a < 3; a++) {
            h[HIST_TIGHT + a] = as_uint(f_min(as_float(h[HIST_TIGHT + a]),
                                              as_float(hc[HIST_TIGHT + a])));
            h[HIST_TIGHT + 3 + a] = as_uint(f_max(as_float(h[HIST_TIGHT + 3 + a]),
                                                  as_float(hc[HIST_TIGHT + 3 + a])));
        }
    }
    uint n = h[HIST_VALID];
    Search s;
    search_init(&s, node.lo, node.hi, n, pow2);
    if (level < depth_cap)
        consider_bins(&s, h, &pl, n, pow2);
    decide(splits + i, &s, n, node.bad, level, depth_cap);
    Split d = splits[i];
    /* Each chunk's first places among its node's children's references (and leaf entries). */
    uint at_below = 0u, at_above = 0u, at_leaf = 0u;
    for (uint c = first; c < first + count; c++) {
        __global const uint* hc = hist + (size_t)HIST_WORDS * c;
        __global uint* cr = chunks + BIN_CHUNK_COLUMNS * c;
        uint nb, na;
        chunk_sides(hc, &d, &pl, &node, &nb, &na);
        cr[BIN_CHUNK_BELOW] = at_below;
        cr[BIN_CHUNK_ABOVE] = at_above;
        cr[BIN_CHUNK_LEAF] = at_leaf;
        at_below += nb;
        at_above += na;
        at_leaf += hc[HIST_VALID];
    }
}

/* ----------------------------------------------------------------------------------------
   The level's sums by blocks of KD_SUM_BLOCK nodes (BIN_SUMS rows): the host turns them into
   each block's first places (BIN_PLACES rows) for emit. */

inline void sah_term(const LevelNode* node, const Split* d, float pow2, float inv_root,
                     long* sah)
{
    float d0 = (node->hi[0] - node->lo[0]) * pow2, d1 = (node->hi[1] - node->lo[1]) * pow2,
          d2 = (node->hi[2] - node->lo[2]) * pow2;
    float share = (d0 * d1 + d1 * d2 + d2 * d0) * inv_root;
    float cost = (d->flags & SPLIT_LEAF) ? KD_KI * (float)d->valid * share : KD_KT * share;
    *sah += convert_long_rte(cost * 4294967296.0f);
}

__kernel void level_sums(__global const LevelNode* restrict nodes,
                         __global const Split* restrict splits,
                         __global uint* restrict sums, uint n_nodes, float pow2,
                         float inv_root)
{
    uint blk = (uint)get_global_id(0);
    uint first = blk * KD_SUM_BLOCK;
    if (first >= n_nodes)
        return;
    uint last = min(first + KD_SUM_BLOCK, n_nodes);
    uint inner = 0u, places = 0u, leaf_refs = 0u, leaves = 0u, empty = 0u, widest = 0u;
    long sah = 0;
    for (uint i = first; i < last; i++) {
        Split d = splits[i];
        LevelNode node = nodes[i];
        sah_term(&node, &d, pow2, inv_root, &sah);
        if (d.flags & SPLIT_LEAF) {
            leaves++;
            empty += d.valid == 0u;
            leaf_refs += d.valid;
        } else {
            inner++;
            places += d.below + d.above;
            widest = max(widest, max(d.below, d.above));
        }
    }
    __global uint* row = sums + BIN_SUMS_COLUMNS * blk;
    row[BIN_SUMS_INNER] = inner;
    row[BIN_SUMS_PLACES] = places;
    row[BIN_SUMS_LEAF_REFS] = leaf_refs;
    row[BIN_SUMS_LEAVES] = leaves;
    row[BIN_SUMS_EMPTY_LEAVES] = empty;
    row[BIN_SUMS_WIDEST] = widest;
    row[BIN_SUMS_SAH_LOW] = (uint)((ulong)sah & 0xFFFFFFFFUL);
    row[BIN_SUMS_SAH_HIGH] = (uint)((ulong)sah >> 32);
}

/* The level's node words, at level_base in the tree's nodes (final: child index and leaf
   offset absolute), and the next level's nodes; every split record learns its children's
   places and its leaf's place in the tree's lists. */
__kernel void emit(__global const LevelNode* restrict nodes,
                   __global Split* restrict splits,
                   __global const uint* restrict places,
                   __global uint2* restrict words,
                   __global LevelNode* restrict next,
                   uint n_nodes, uint level_base, uint next_base, uint leaf_base)
{
    uint blk = (uint)get_global_id(0);
    uint first = blk * KD_SUM_BLOCK;
    if (first >= n_nodes)
        return;
    uint last = min(first + KD_SUM_BLOCK, n_nodes);
    __global const uint* at = places + BIN_PLACES_COLUMNS * blk;
    uint inner = at[BIN_PLACES_INNER], place = at[BIN_PLACES_PLACES];
    uint leaf = at[BIN_PLACES_LEAF_REFS];
    for (uint i = first; i < last; i++) {
        Split d = splits[i];
        LevelNode node = nodes[i];
        if (d.flags & SPLIT_LEAF) {
            words[level_base + i] = (uint2)(KD_PLAIN_TAG_PUT(KD_LEAF_TAG)
                                            | KD_PLAIN_FIELD_PUT(d.valid), leaf_base + leaf);
            d.base = leaf_base + leaf;
            leaf += d.valid;
        } else {
            int a = (int)SPLIT_AXIS(d.flags);
            words[level_base + i] = (uint2)(KD_PLAIN_TAG_PUT(a)
                                            | KD_PLAIN_FIELD_PUT(next_base + 2u * inner),
                                            as_uint(d.plane));
            d.child = 2u * inner;
            d.base = place;
            LevelNode c = node;
            c.hi[a] = d.plane;
            c.first = place;
            c.count = d.below;
            c.bad = d.bad;
            c.unused = 0u;
            next[2u * inner] = c;
            c = node;
            c.lo[a] = d.plane;
            c.first = place + d.below;
            c.count = d.above;
            c.bad = d.bad;
            c.unused = 0u;
            next[2u * inner + 1u] = c;
            inner++;
            place += d.below + d.above;
        }
        splits[i] = d;
    }
}

/* ----------------------------------------------------------------------------------------
   The perfect split of a straddler: the triangle clipped to its reference's box (which is its
   piece of the cell: the piece's box, rounded outward and clamped to the cell), then cut by
   the plane; each half's box rounded outward to float32 and clamped to the half of the box.
   Returns bit 1: the below half kept, bit 2: the above half kept (a half of zero area - fewer
   than 3 vertices, or flat in an axis where the triangle is not - only touches that side). */

#define POLY_MAX 10

inline int clip_polygon(double (*in)[3], int n, double (*out)[3], int a, double v, int keep_below)
{
    int m = 0;
    for (int i = 0; i < n; i++) {
        int j = i + 1 == n ? 0 : i + 1;
        double di = keep_below ? v - in[i][a] : in[i][a] - v;
        double dj = keep_below ? v - in[j][a] : in[j][a] - v;
        if (di >= 0.0)
            for (int b = 0; b < 3; b++)
                out[m][b] = in[i][b];
        m += di >= 0.0;
        if ((di > 0.0 && dj < 0.0) || (di < 0.0 && dj > 0.0)) {
            double t = di / (di - dj);
            for (int b = 0; b < 3; b++)
                out[m][b] = in[i][b] + t * (in[j][b] - in[i][b]);
            out[m][a] = v;
            m++;
        }
    }
    return m;
}

inline int half_kept(const float* lo, const float* hi, const float* tlo, const float* thi,
                     int verts)
{
    if (verts < 3)
        return 0;
    for (int b = 0; b < 3; b++)
        if (lo[b] == hi[b] && tlo[b] < thi[b])
            return 0;
    return 1;
}

inline uint split_straddler(__global const float* restrict corners, Ref r, int axis, float plane,
                            Ref* below, Ref* above)
{
    uint tri = ref_tri(r);
    double poly[2][POLY_MAX][3];
    float tlo[3], thi[3], blo[3], bhi[3];
    __global const float* c = corners + (size_t)9 * tri;
    for (int k = 0; k < 3; k++)
        for (int b = 0; b < 3; b++)
            poly[0][k][b] = (double)c[3 * k + b];
    for (int b = 0; b < 3; b++) {
        tlo[b] = f_min(f_min(c[b], c[3 + b]), c[6 + b]);
        thi[b] = f_max(f_max(c[b], c[3 + b]), c[6 + b]);
        blo[b] = lane(r.lo, b);
        bhi[b] = lane(r.hi, b);
    }
    int n = 3, cur = 0;
    for (int b = 0; b < 3 && n >= 3; b++) {
        if (tlo[b] < blo[b]) {
            n = clip_polygon(poly[cur], n, poly[1 - cur], b, (double)blo[b], 0);
            cur = 1 - cur;
        }
        if (thi[b] > bhi[b] && n >= 3) {
            n = clip_polygon(poly[cur], n, poly[1 - cur], b, (double)bhi[b], 1);
            cur = 1 - cur;
        }
    }
    double lo2[2][3], hi2[2][3];
    int verts[2] = {0, 0};
    for (int s = 0; s < 2; s++)
        for (int b = 0; b < 3; b++) {
            lo2[s][b] = INFINITY;
            hi2[s][b] = -INFINITY;
        }
    double p = (double)plane;
    if (n >= 3)
        for (int i = 0; i < n; i++) {
            int j = i + 1 == n ? 0 : i + 1;
            double di = poly[cur][i][axis] - p, dj = poly[cur][j][axis] - p;
            for (int s = 0; s < 2; s++)
                if (s == 0 ? di <= 0.0 : di >= 0.0) {
                    verts[s]++;
                    for (int b = 0; b < 3; b++) {
                        lo2[s][b] = d_min(lo2[s][b], poly[cur][i][b]);
                        hi2[s][b] = d_max(hi2[s][b], poly[cur][i][b]);
                    }
                }
            if ((di > 0.0 && dj < 0.0) || (di < 0.0 && dj > 0.0)) {
                double t = di / (di - dj);
                double x[3];
                for (int b = 0; b < 3; b++)
                    x[b] = poly[cur][i][b] + t * (poly[cur][j][b] - poly[cur][i][b]);
                x[axis] = p;
                for (int s = 0; s < 2; s++) {
                    verts[s]++;
                    for (int b = 0; b < 3; b++) {
                        lo2[s][b] = d_min(lo2[s][b], x[b]);
                        hi2[s][b] = d_max(hi2[s][b], x[b]);
                    }
                }
            }
        }
    uint kept = 0u;
    for (int s = 0; s < 2; s++) {
        float lo[3], hi[3];
        for (int b = 0; b < 3; b++) {
            lo[b] = verts[s] ? f_max(convert_float_rtn(lo2[s][b]) + 0.0f, blo[b]) : 0.0f;
            hi[b] = verts[s] ? f_min(convert_float_rtp(hi2[s][b]) + 0.0f, bhi[b]) : 0.0f;
        }
        if (s == 0)
            hi[axis] = f_min(hi[axis], plane);
        else
            lo[axis] = f_max(lo[axis], plane);
        if (!half_kept(lo, hi, tlo, thi, verts[s]))
            continue;
        kept |= 1u << s;
        Ref h;
        h.lo = (float4)(lo[0], lo[1], lo[2], as_float(tri));
        h.hi = (float4)(hi[0], hi[1], hi[2], 0.0f);
        if (s == 0)
            *below = h;
        else
            *above = h;
    }
    return kept;
}

/* Move references [first, first + count) of a node with decision d: to its leaf list, or to
   its children in the next level (straddlers clipped; a half not kept leaves a hole). */
inline void move_refs(__global const Ref* restrict refs, uint first, uint count, const Split* d,
                      uint below_at, uint above_at, uint leaf_at,
                      __global const float* restrict corners, __global Ref* restrict next,
                      __global uint* restrict leaf_tris)
{
    if (d->flags & SPLIT_LEAF) {
        for (uint j = 0u; j < count; j++) {
            uint t = ref_tri(refs[first + j]);
            if (t != HOLE)
                leaf_tris[leaf_at++] = t;
        }
        return;
    }
    int a = (int)SPLIT_AXIS(d->flags);
    float p = d->plane;
    int planar_above = (d->flags & SPLIT_PLANAR_ABOVE) != 0u;
    Ref hole;
    hole.lo = (float4)(0.0f, 0.0f, 0.0f, as_float(HOLE));
    hole.hi = (float4)(0.0f);
    for (uint j = 0u; j < count; j++) {
        Ref r = refs[first + j];
        if (ref_tri(r) == HOLE)
            continue;
        float lo = lane(r.lo, a), hi = lane(r.hi, a);
        int goes_below = lo < p, goes_above = hi > p;
        if (lo == p && hi == p) {
            goes_below = !planar_above;
            goes_above = planar_above;
        }
        if (goes_below && goes_above) {
            Ref b = hole, c = hole;
            split_straddler(corners, r, a, p, &b, &c);
            next[below_at++] = b;
            next[above_at++] = c;
        } else if (goes_below) {
            next[below_at++] = r;
        } else {
            next[above_at++] = r;
        }
    }
}

__kernel void scatter_nodes(__global const LevelNode* restrict nodes,
                            __global const Ref* restrict refs,
                            __global const Split* restrict splits,
                            __global const float* restrict corners,
                            __global Ref* restrict next,
                            __global uint* restrict leaf_tris, uint n_nodes)
{
    uint i = (uint)get_global_id(0);
    if (i >= n_nodes)
        return;
    LevelNode node = nodes[i];
    if (node.count > KD_BIG_REFS)
        return;                          /* scatter_chunks' */
    Split d = splits[i];
    move_refs(refs, node.first, node.count, &d, d.base, d.base + d.below, d.base, corners, next,
              leaf_tris);
}

__kernel void scatter_chunks(__global const Ref* restrict refs,
                             __global const uint* restrict chunks,
                             __global const Split* restrict splits,
                             __global const float* restrict corners,
                             __global Ref* restrict next,
                             __global uint* restrict leaf_tris, uint n_chunks)
{
    uint c = (uint)get_global_id(0);
    if (c >= n_chunks)
        return;
    __global const uint* row = chunks + BIN_CHUNK_COLUMNS * c;
    Split d = splits[row[BIN_CHUNK_NODE]];
    move_refs(refs, row[BIN_CHUNK_FIRST], row[BIN_CHUNK_COUNT], &d, d.base + row[BIN_CHUNK_BELOW],
              d.base + d.below + row[BIN_CHUNK_ABOVE], d.base + row[BIN_CHUNK_LEAF], corners, next,
              leaf_tris);
}

/* ----------------------------------------------------------------------------------------
   The first references: each triangle's box and corners; a triangle of zero area (its cross
   product exactly zero in double) is a hole from the start. */

__kernel void first_refs(__global const float* restrict vertices,
                         __global const uint* restrict triangles,
                         __global float* restrict corners,
                         __global Ref* restrict refs, uint n)
{
    uint t = (uint)get_global_id(0);
    if (t >= n)
        return;
    float v[3][3];
    for (int k = 0; k < 3; k++) {
        uint at = triangles[3 * t + k];
        for (int b = 0; b < 3; b++) {
            v[k][b] = vertices[3 * at + b] + 0.0f;
            corners[(size_t)9 * t + 3 * k + b] = v[k][b];
        }
    }
    double e1[3], e2[3];
    for (int b = 0; b < 3; b++) {
        e1[b] = (double)v[1][b] - (double)v[0][b];
        e2[b] = (double)v[2][b] - (double)v[0][b];
    }
    double nx = e1[1] * e2[2] - e1[2] * e2[1];
    double ny = e1[2] * e2[0] - e1[0] * e2[2];
    double nz = e1[0] * e2[1] - e1[1] * e2[0];
    Ref r;
    float lo[3], hi[3];
    for (int b = 0; b < 3; b++) {
        lo[b] = f_min(f_min(v[0][b], v[1][b]), v[2][b]);
        hi[b] = f_max(f_max(v[0][b], v[1][b]), v[2][b]);
    }
    uint tri = (nx != 0.0 || ny != 0.0 || nz != 0.0) ? t : HOLE;
    r.lo = (float4)(lo[0], lo[1], lo[2], as_float(tri));
    r.hi = (float4)(hi[0], hi[1], hi[2], 0.0f);
    refs[t] = r;
}

/* The bounds and count of the kept triangles' boxes, per block of KD_SUM_BLOCK * 64 of them
   (BIN_BOUNDS rows). */
__kernel void ref_bounds(__global const Ref* restrict refs, __global float* restrict out, uint n)
{
    uint blk = (uint)get_global_id(0);
    uint first = blk * KD_SUM_BLOCK * 64u;
    if (first >= n)
        return;
    uint last = min(first + KD_SUM_BLOCK * 64u, n);
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    uint kept = 0u;
    for (uint i = first; i < last; i++) {
        Ref r = refs[i];
        if (ref_tri(r) == HOLE)
            continue;
        kept++;
        for (int a = 0; a < 3; a++) {
            lo[a] = f_min(lo[a], lane(r.lo, a));
            hi[a] = f_max(hi[a], lane(r.hi, a));
        }
    }
    __global float* row = out + BIN_BOUNDS_COLUMNS * blk;
    for (int a = 0; a < 3; a++) {
        row[BIN_BOUNDS_LO_X + a] = lo[a];
        row[BIN_BOUNDS_HI_X + a] = hi[a];
    }
    row[BIN_BOUNDS_KEPT] = as_float(kept);
}
