/* One work-item builds one whole subtree (a node small enough, or a big node that became a
   leaf), depth first with an explicit stack, every node decided by split.cl.

   Output, in depth-first order, one record per node: its words with the fields that depend
   on the rest of the tree left local (an inner node's child pair as its rank among this
   subtree's nodes of the next level, a leaf's offset as the number of leaf references before
   it at its level in this subtree), and meta = relative level | rank in that level << 6.
   Depth-first order visits each level's nodes in the order of their paths from the root, which
   is their breadth-first order, so ranks are simply counted per level. kdtree_cl.py places
   every subtree's levels among the rest of the tree; layout.cl writes the final words.

   A node's references live in the work-item's scratch as a stack: the node on top, its above
   child written in place of it, its below child after that. Overflowing any of its buffers
   stops the work-item with a status; the host runs it again with larger buffers (the result
   does not depend on their sizes). */

/* A record's meta: its relative level (below SUBTREE_MAX_LEVELS, which the host keeps every
   subtree's depth span below) in the low 6 bits, its rank in that level above them (layout.cl
   reads it back). */
#define META_LEVEL_BITS 6
#define RANK_LIMIT (1u << (32 - META_LEVEL_BITS))
#define META(level, rank) ((level) | ((rank) << META_LEVEL_BITS))
#define META_LEVEL(meta) ((meta) & ((1u << META_LEVEL_BITS) - 1u))
#define META_RANK(meta) ((meta) >> META_LEVEL_BITS)

typedef struct {
    Cell cell;
    uint start, count, level, bad, rank;
    int chained;           /* same references as the exact node decided last: reuse its counts */
} Entry;

/* Subtree s of the launch: its root is row s of `roots` (SUBTREE_ROOT, core/layout.py), its
   outcome goes to row s of `result` (SUBTREE_RESULT). */
inline void build_subtree(uint s, __global const Ref* restrict queue,
                          __global const float* restrict corners,
                          __global const uint* restrict roots,
                          __global Ref* restrict scratch,
                          __global uint2* restrict rec_words,
                          __global uint* restrict rec_meta,
                          __global uint* restrict leaf_refs,
                          __global uint2* restrict level_counts,
                          __global uint* restrict result,
                          __global long* restrict sah,
                          float pow2, float inv_root_half_area, uint depth_cap)
{
    __global const uint* root = roots + SUBTREE_ROOT_COLUMNS * s;
    uint root_level = root[SUBTREE_ROOT_LEVEL], ref_start = root[SUBTREE_ROOT_REF_FIRST];
    uint n = root[SUBTREE_ROOT_REF_COUNT];
    uint rec_off = root[SUBTREE_ROOT_RECORD_OFFSET], rec_cap = root[SUBTREE_ROOT_RECORD_CAPACITY];
    uint leaf_off = root[SUBTREE_ROOT_LEAF_OFFSET], leaf_cap = root[SUBTREE_ROOT_LEAF_CAPACITY];
    uint scr_cap = root[SUBTREE_ROOT_SCRATCH_CAPACITY];
    uint lvl_off = root[SUBTREE_ROOT_LEVEL_OFFSET], span = root[SUBTREE_ROOT_LEVEL_SPAN];
    __global Ref* scr = scratch + root[SUBTREE_ROOT_SCRATCH_OFFSET];

    uint node_count[SUBTREE_MAX_LEVELS], leaf_prefix[SUBTREE_MAX_LEVELS];
    for (uint l = 0; l < span; l++) {
        node_count[l] = 0u;
        leaf_prefix[l] = 0u;
    }
    node_count[0] = 1u;
    uint recs = 0u, lrefs = 0u, levels = 1u;
    long sah_sum = 0;
    int status = SUBTREE_OK;

    Entry stack[SUBTREE_MAX_LEVELS];
    ExactBoxes x;              /* the last exact node's boxes and counts */
    uint sp = 0u;
    Entry first;
    for (int a = 0; a < 3; a++) {
        first.cell.lo[a] = as_float(root[SUBTREE_ROOT_LO_X + a]);
        first.cell.hi[a] = as_float(root[SUBTREE_ROOT_HI_X + a]);
    }
    first.start = 0u;
    first.count = n;
    first.level = 0u;
    first.bad = root[SUBTREE_ROOT_BAD_REFINES];
    first.rank = 0u;
    first.chained = 0;
    if (n > scr_cap)
        status = SUBTREE_SCRATCH;
    else
        for (uint i = 0; i < n; i++)
            scr[i] = queue[ref_start + i];
    stack[sp++] = first;

    while (sp > 0u && status == SUBTREE_OK) {
        Entry e = stack[--sp];
        uint level = root_level + e.level;
        uint top = e.start + e.count;
        Choice ch = {0, 0, 0.0f};
        Decision d = {1, 1, e.bad};
        uint counts[3] = {0u, 0u, 0u};       /* below, above, planar at the chosen plane */
        if (e.count > 0u && level < depth_cap) {
            if (e.count <= KD_EXACT_MAX) {
                if (!e.chained) {
                    int w = exact_width(e.count);
                    x.width = w;
                    for (uint i = 0; i < e.count; i++) {
                        Ref r = scr[e.start + i];
                        x.cand[0].s[i] = r.lo.x;
                        x.cand[1].s[i] = r.lo.y;
                        x.cand[2].s[i] = r.lo.z;
                        x.cand[0].s[w + i] = r.hi.x;
                        x.cand[1].s[w + i] = r.hi.y;
                        x.cand[2].s[w + i] = r.hi.z;
                    }
                    for (int i = (int)e.count; i < w; i++)
                        for (int a = 0; a < 3; a++) {
                            x.cand[a].s[i] = INFINITY;
                            x.cand[a].s[w + i] = -INFINITY;
                        }
                    count_exact(&x);
                }
                ch = rank_exact(&x, &e.cell, counts);
            } else {
                BinPlanes bp;
                bin_planes(&e.cell, e.count, &bp);
                uint h[HIST_WORDS];
                hist_clear(h);
                for (uint i = 0; i < e.count; i++)
                    hist_add(h, &bp, scr[e.start + i]);
                ch = choose_binned(h, &bp, &e.cell, e.count);
                if (ch.valid)
                    for (uint i = 0; i < e.count; i++)
                        count_at_plane(scr[e.start + i], ch.axis, ch.plane, counts);
            }
            if (ch.valid)
                d = decide(e.count, level, depth_cap, e.bad, ch, counts[0], counts[1], counts[2],
                           &e.cell);
        }
        if (recs >= rec_cap) {
            status = SUBTREE_RECORDS;
            break;
        }
        uint meta = META(e.level, e.rank);
        if (d.leaf) {
            if (lrefs + e.count > leaf_cap) {
                status = SUBTREE_LEAF_REFS;
                break;
            }
            rec_words[rec_off + recs] = (uint2)(KD_PLAIN_TAG_PUT(KD_LEAF_TAG)
                                                | KD_PLAIN_FIELD_PUT(e.count),
                                                leaf_prefix[e.level]);
            rec_meta[rec_off + recs] = meta;
            recs++;
            for (uint i = 0; i < e.count; i++)
                leaf_refs[leaf_off + lrefs + i] = ref_triangle(scr[e.start + i]);
            lrefs += e.count;
            leaf_prefix[e.level] += e.count;
            sah_sum += sah_fixed(&e.cell, pow2, inv_root_half_area, KD_KI * (float)e.count);
            continue;
        }
        uint child_rank = node_count[e.level + 1];
        if (child_rank + 2u > RANK_LIMIT) {
            status = SUBTREE_RANKS;
            break;
        }
        node_count[e.level + 1] = child_rank + 2u;
        levels = levels > e.level + 2u ? levels : e.level + 2u;
        rec_words[rec_off + recs] = (uint2)(KD_PLAIN_TAG_PUT(ch.axis)
                                            | KD_PLAIN_FIELD_PUT(child_rank),
                                            as_uint(ch.plane));
        rec_meta[rec_off + recs] = meta;
        recs++;
        sah_sum += sah_fixed(&e.cell, pow2, inv_root_half_area, KD_KT);

        /* An empty-space cut (everything strictly on one side, planar references too) moves
           nothing: the non-empty child has the node's references where they are, and, for an
           exact node, its counts. Otherwise the above child goes in place (it never overtakes
           the reading position), the below child after the top, then down next to it. Order
           within each child is kept. */
        int all_below = counts[1] == 0u && (counts[2] == 0u || d.planar_below);
        int all_above = counts[0] == 0u && (counts[2] == 0u || !d.planar_below);
        Entry child;
        child.level = e.level + 1u;
        child.bad = d.bad;
        if (all_below || all_above) {
            child.chained = 0;
            child_cell(&e.cell, ch.axis, ch.plane, 1, &child.cell);
            child.start = e.start;
            child.count = all_above ? e.count : 0u;
            child.chained = all_above && e.count <= KD_EXACT_MAX;
            child.rank = child_rank + 1u;
            stack[sp++] = child;
            child_cell(&e.cell, ch.axis, ch.plane, 0, &child.cell);
            child.count = all_below ? e.count : 0u;
            child.chained = all_below && e.count <= KD_EXACT_MAX;
            child.rank = child_rank;
            stack[sp++] = child;
            continue;
        }
        uint ka = 0u, kb = 0u;
        for (uint i = 0; i < e.count; i++) {
            Ref below, above;
            int sides = ref_children(corners, scr[e.start + i], &e.cell, ch.axis, ch.plane,
                                     d.planar_below, &below, &above);
            if (sides & 1) {
                if (top + kb >= scr_cap) {
                    status = SUBTREE_SCRATCH;
                    break;
                }
                scr[top + kb] = below;
                kb++;
            }
            if (sides & 2) {
                scr[e.start + ka] = above;
                ka++;
            }
        }
        if (status != SUBTREE_OK)
            break;
        for (uint j = 0; j < kb; j++)
            scr[e.start + ka + j] = scr[top + j];
        child.chained = 0;
        child_cell(&e.cell, ch.axis, ch.plane, 1, &child.cell);
        child.start = e.start;
        child.count = ka;
        child.rank = child_rank + 1u;
        stack[sp++] = child;
        child_cell(&e.cell, ch.axis, ch.plane, 0, &child.cell);
        child.start = e.start + ka;
        child.count = kb;
        child.rank = child_rank;
        stack[sp++] = child;
    }

    for (uint l = 0; l < levels; l++) {
        uint2 count;
        LEVEL_COUNT_NODES_OF(count) = node_count[l];
        LEVEL_COUNT_LEAF_REFS_OF(count) = leaf_prefix[l];
        level_counts[lvl_off + l] = count;
    }
    __global uint* out = result + SUBTREE_RESULT_COLUMNS * s;
    out[SUBTREE_RESULT_STATUS] = (uint)status;
    out[SUBTREE_RESULT_RECORDS] = recs;
    out[SUBTREE_RESULT_LEAF_REFS] = lrefs;
    out[SUBTREE_RESULT_LEVELS] = levels;
    sah[s] = sah_sum;
}

/* With KD_SUBTREE_QUEUE (CPU devices) a few work-items take the launch's subtrees in turn from
   the counter next_subtree (0 at launch), one at a time as each finishes one: subtrees differ
   in cost many times over, and PoCL hands a launch's work-groups to its threads in chunks of up
   to half of those left, so the thread that drew the big subtrees (they come first) worked on
   while the other waited. Otherwise one work-item per subtree. A subtree's output does not
   depend on which work-item builds it. */
__kernel void build_subtrees(__global const Ref* restrict queue,
                             __global const float* restrict corners,
                             __global const uint* restrict roots,
                             __global Ref* restrict scratch,
                             __global uint2* restrict rec_words,
                             __global uint* restrict rec_meta,
                             __global uint* restrict leaf_refs,
                             __global uint2* restrict level_counts,
                             __global uint* restrict result,
                             __global long* restrict sah,
                             volatile __global uint* next_subtree,
                             uint subtree_count, float pow2, float inv_root_half_area,
                             uint depth_cap)
{
#ifdef KD_SUBTREE_QUEUE
    for (uint s = atomic_inc(next_subtree); s < subtree_count; s = atomic_inc(next_subtree))
#else
    uint s = get_global_id(0);
    if (s < subtree_count)
#endif
        build_subtree(s, queue, corners, roots, scratch, rec_words, rec_meta, leaf_refs,
                      level_counts, result, sah, pow2, inv_root_half_area, depth_cap);
}
