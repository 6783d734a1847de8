/* The big nodes of one level, data-parallel over their references: one work-item per chunk
   (consecutive references of one node, sequential in the chunk) or per node. Chunks, node
   cells and what the passes hand each other are rows of core/layout.py: BIG_CHUNK, CELL,
   NODE_CHUNKS, BIG_CHOICE, PLANE_COUNTS, BIG_DECISION, CHILD_COUNTS, BIG_DEST.

   big_bin -> big_choose: binned SAH (histograms summed over a node's chunks);
   big_recount -> big_decide: exact counts at the chosen plane, leaf or split;
   big_classify: references per child (straddlers clipped to know which halves survive);
   big_scatter: every reference written to its child's place (next level, or the queue of
   subtrees when the child is small) or, for a node that became a leaf, to the queue as it is
   (the subtree builder turns it into the same leaf). Places come from the host's prefix sums,
   so nothing depends on scheduling. */

inline Cell load_cell(__global const float* cells, uint node)
{
    Cell c;
    for (int a = 0; a < 3; a++) {
        c.lo[a] = cells[CELL_COLUMNS * node + CELL_LO_X + a];
        c.hi[a] = cells[CELL_COLUMNS * node + CELL_HI_X + a];
    }
    return c;
}

__kernel void big_bin(__global const Ref* restrict refs, __global const uint4* restrict chunks,
                      __global const float* restrict cells, __global const uint* restrict node_n,
                      __global uint* restrict hist,
                      uint chunk_count)
{
    uint c = get_global_id(0);
    if (c >= chunk_count)
        return;
    uint4 ch = chunks[c];
    uint node = BIG_CHUNK_NODE_OF(ch), first = BIG_CHUNK_REF_FIRST_OF(ch);
    Cell cell = load_cell(cells, node);
    BinPlanes bp;
    bin_planes(&cell, node_n[node], &bp);
    uint h[HIST_WORDS];
    hist_clear(h);
    for (uint i = first; i < first + BIG_CHUNK_REF_COUNT_OF(ch); i++)
        hist_add(h, &bp, refs[i]);
    for (int k = 0; k < HIST_WORDS; k++)
        hist[(size_t)HIST_WORDS * c + k] = h[k];
}

/* Per node: its chunks' histograms summed, the best binned split. */
__kernel void big_choose(__global const uint2* restrict node_chunks,
                         __global const uint* restrict hist, __global const float* restrict cells,
                         __global const uint* restrict node_n, __global uint4* restrict choice,
                         uint node_count)
{
    uint j = get_global_id(0);
    if (j >= node_count)
        return;
    uint2 nc = node_chunks[j];
    uint h[HIST_WORDS];
    hist_clear(h);
    uint chunk_end = NODE_CHUNKS_FIRST_OF(nc) + NODE_CHUNKS_COUNT_OF(nc);
    for (uint c = NODE_CHUNKS_FIRST_OF(nc); c < chunk_end; c++) {
        __global const uint* src = hist + (size_t)HIST_WORDS * c;
        for (int k = 0; k < HIST_BOUNDS; k++)
            h[k] += src[k];
        for (int a = 0; a < 3; a++) {
            h[HIST_BOUNDS + a] = as_uint(kd_min(as_float(h[HIST_BOUNDS + a]),
                                                as_float(src[HIST_BOUNDS + a])));
            h[HIST_BOUNDS + 3 + a] = as_uint(kd_max(as_float(h[HIST_BOUNDS + 3 + a]),
                                                    as_float(src[HIST_BOUNDS + 3 + a])));
        }
    }
    Cell cell = load_cell(cells, j);
    BinPlanes bp;
    bin_planes(&cell, node_n[j], &bp);
    Choice best = choose_binned(h, &bp, &cell, node_n[j]);
    uint4 k = (uint4)(0u);
    BIG_CHOICE_VALID_OF(k) = (uint)best.valid;
    BIG_CHOICE_AXIS_OF(k) = (uint)best.axis;
    BIG_CHOICE_PLANE_OF(k) = as_uint(best.plane);
    choice[j] = k;
}

/* Per chunk: references below, above and planar at its node's chosen plane. */
__kernel void big_recount(__global const Ref* restrict refs, __global const uint4* restrict chunks,
                          __global const uint4* restrict choice, __global uint4* restrict counts,
                          uint chunk_count)
{
    uint c = get_global_id(0);
    if (c >= chunk_count)
        return;
    uint4 ch = chunks[c];
    uint4 k = choice[BIG_CHUNK_NODE_OF(ch)];
    int axis = (int)BIG_CHOICE_AXIS_OF(k);
    float plane = as_float(BIG_CHOICE_PLANE_OF(k));
    uint n[3] = {0u, 0u, 0u};
    uint first = BIG_CHUNK_REF_FIRST_OF(ch);
    for (uint i = first; i < first + BIG_CHUNK_REF_COUNT_OF(ch); i++)
        count_at_plane(refs[i], axis, plane, n);
    uint4 out = (uint4)(0u);
    PLANE_COUNTS_BELOW_OF(out) = n[0];
    PLANE_COUNTS_ABOVE_OF(out) = n[1];
    PLANE_COUNTS_PLANAR_OF(out) = n[2];
    counts[c] = out;
}

/* Per node: leaf or split (its BIG_DECISION); sah: the node's SAH share if it splits (a leaf's
   is taken by its subtree). */
__kernel void big_decide(__global const uint2* restrict node_chunks,
                         __global const uint4* restrict counts,
                         __global const uint4* restrict choice,
                         __global const float* restrict cells, __global const uint* restrict node_n,
                         __global const uint* restrict node_bad, __global uint4* restrict decision,
                         __global long* restrict sah, uint node_count, uint level, uint depth_cap,
                         float pow2, float inv_root_half_area)
{
    uint j = get_global_id(0);
    if (j >= node_count)
        return;
    uint2 nc = node_chunks[j];
    uint nb = 0u, na = 0u, np = 0u;
    uint chunk_end = NODE_CHUNKS_FIRST_OF(nc) + NODE_CHUNKS_COUNT_OF(nc);
    for (uint c = NODE_CHUNKS_FIRST_OF(nc); c < chunk_end; c++) {
        uint4 n = counts[c];
        nb += PLANE_COUNTS_BELOW_OF(n);
        na += PLANE_COUNTS_ABOVE_OF(n);
        np += PLANE_COUNTS_PLANAR_OF(n);
    }
    uint4 k = choice[j];
    Choice ch = {(int)BIG_CHOICE_VALID_OF(k), (int)BIG_CHOICE_AXIS_OF(k),
                 as_float(BIG_CHOICE_PLANE_OF(k))};
    Cell cell = load_cell(cells, j);
    Decision d = decide(node_n[j], level, depth_cap, node_bad[j], ch, nb, na, np, &cell);
    uint4 out;
    BIG_DECISION_FLAGS_OF(out) = (d.leaf ? DECISION_LEAF : 0u)
                                 | (d.planar_below ? DECISION_PLANAR_BELOW : 0u);
    BIG_DECISION_BAD_REFINES_OF(out) = d.bad;
    BIG_DECISION_AXIS_OF(out) = BIG_CHOICE_AXIS_OF(k);
    BIG_DECISION_PLANE_OF(out) = BIG_CHOICE_PLANE_OF(k);
    decision[j] = out;
    sah[j] = d.leaf ? 0 : sah_fixed(&cell, pow2, inv_root_half_area, KD_KT);
}

/* A chunk's references split at its node's decision d, counted or, where below_to and
   above_to are given, also written there in order; returns their CHILD_COUNTS. A leaf's
   references all go "below", as they are. */
inline uint2 split_chunk(__global const Ref* refs, uint4 ch, uint4 d,
                         __global const float* cells, __global const float* corners,
                         __global Ref* below_to, __global Ref* above_to)
{
    uint first = BIG_CHUNK_REF_FIRST_OF(ch), count = BIG_CHUNK_REF_COUNT_OF(ch);
    uint flags = BIG_DECISION_FLAGS_OF(d);
    uint2 out = (uint2)(0u);
    if (flags & DECISION_LEAF) {
        if (below_to)
            for (uint i = 0; i < count; i++)
                below_to[i] = refs[first + i];
        CHILD_COUNTS_BELOW_OF(out) = count;
        return out;
    }
    Cell cell = load_cell(cells, BIG_CHUNK_NODE_OF(ch));
    int axis = (int)BIG_DECISION_AXIS_OF(d);
    float plane = as_float(BIG_DECISION_PLANE_OF(d));
    int planar_below = (flags & DECISION_PLANAR_BELOW) != 0u;
    uint nb = 0u, na = 0u;
    for (uint i = first; i < first + count; i++) {
        Ref below, above;
        int sides = ref_children(corners, refs[i], &cell, axis, plane, planar_below, &below,
                                 &above);
        if (sides & 1) {
            if (below_to)
                below_to[nb] = below;
            nb++;
        }
        if (sides & 2) {
            if (above_to)
                above_to[na] = above;
            na++;
        }
    }
    CHILD_COUNTS_BELOW_OF(out) = nb;
    CHILD_COUNTS_ABOVE_OF(out) = na;
    return out;
}

/* Per chunk: how many of its references each child receives. */
__kernel void big_classify(__global const Ref* restrict refs, __global const uint4* restrict chunks,
                           __global const uint4* restrict decision,
                           __global const float* restrict cells,
                           __global const float* restrict corners, __global uint2* restrict out,
                           uint chunk_count)
{
    uint c = get_global_id(0);
    if (c < chunk_count)
        out[c] = split_chunk(refs, chunks[c], decision[BIG_CHUNK_NODE_OF(chunks[c])], cells,
                             corners, 0, 0);
}

/* Per chunk, its references written to their children's places (its BIG_DEST). */
__kernel void big_scatter(__global const Ref* restrict refs, __global const uint4* restrict chunks,
                          __global const uint4* restrict decision,
                          __global const float* restrict cells,
                          __global const float* restrict corners,
                          __global const uint4* restrict dest, __global Ref* restrict next,
                          __global Ref* restrict queue, uint chunk_count)
{
    uint c = get_global_id(0);
    if (c >= chunk_count)
        return;
    uint4 to = dest[c];
    split_chunk(refs, chunks[c], decision[BIG_CHUNK_NODE_OF(chunks[c])], cells, corners,
                (BIG_DEST_BELOW_TO_QUEUE_OF(to) ? queue : next) + BIG_DEST_BELOW_FIRST_OF(to),
                (BIG_DEST_ABOVE_TO_QUEUE_OF(to) ? queue : next) + BIG_DEST_ABOVE_FIRST_OF(to));
}

/* The first references: box of every triangle and whether it is kept (its cross product in
   double is not exactly zero, the same operations as numpy's np.cross in kdtree.py); and the
   triangles' corners side by side (CORNERS rows) for the clipping. */
__kernel void init_refs(__global const float* restrict vertices,
                        __global const uint* restrict triangles, __global Ref* restrict refs,
                        __global uchar* restrict keep, __global float* restrict corners,
                        uint triangle_count)
{
    uint t = get_global_id(0);
    if (t >= triangle_count)
        return;
    float p[3][3];
    for (int k = 0; k < 3; k++) {
        uint v = triangles[3 * t + k];
        for (int a = 0; a < 3; a++) {
            p[k][a] = vertices[3 * v + a];
            corners[CORNERS_COLUMNS * (size_t)t + CORNERS_V0_X + 3 * k + a] = p[k][a];
        }
    }
    dbl e1[3], e2[3];
    for (int a = 0; a < 3; a++) {
        e1[a] = D_SUB(D_FROM_F(p[1][a]), D_FROM_F(p[0][a]));
        e2[a] = D_SUB(D_FROM_F(p[2][a]), D_FROM_F(p[0][a]));
    }
    int nonzero = 0;
    for (int a = 0; a < 3; a++) {
        int b = a == 2 ? 0 : a + 1, c = a == 0 ? 2 : a - 1;
        nonzero |= !D_EQ(D_SUB(D_MUL(e1[b], e2[c]), D_MUL(e1[c], e2[b])), D_ZERO);
    }
    keep[t] = (uchar)nonzero;
    float lo[3], hi[3];
    for (int a = 0; a < 3; a++) {
        lo[a] = kd_min(kd_min(p[0][a], p[1][a]), p[2][a]) + 0.0f;    /* + 0: no -0 */
        hi[a] = kd_max(kd_max(p[0][a], p[1][a]), p[2][a]) + 0.0f;
    }
    Ref r;
    r.lo = (float4)(lo[0], lo[1], lo[2], as_float(t));
    r.hi = (float4)(hi[0], hi[1], hi[2], 0.0f);
    refs[t] = r;
}

/* Kept references moved to their places (an exclusive prefix sum of keep, from the host). */
__kernel void compact_refs(__global const Ref* restrict refs, __global const uchar* restrict keep,
                           __global const uint* restrict place, __global Ref* restrict out,
                           uint triangle_count)
{
    uint t = get_global_id(0);
    if (t < triangle_count && keep[t])
        out[place[t]] = refs[t];
}

/* Per chunk of references: the box around them (a CELL row). */
__kernel void chunk_bounds(__global const Ref* restrict refs, __global float* restrict out,
                           uint ref_count, uint chunk)
{
    uint c = get_global_id(0), first, last;
    if (!item_block(chunk, ref_count, &first, &last))
        return;
    float4 lo = (float4)(INFINITY), hi = (float4)(-INFINITY);
    for (uint i = first; i < last; i++) {
        Ref r = refs[i];
        lo = r.lo < lo ? r.lo : lo;
        hi = r.hi > hi ? r.hi : hi;
    }
    for (int a = 0; a < 3; a++) {
        out[CELL_COLUMNS * c + CELL_LO_X + a] = axis_of(lo, a);
        out[CELL_COLUMNS * c + CELL_HI_X + a] = axis_of(hi, a);
    }
}
