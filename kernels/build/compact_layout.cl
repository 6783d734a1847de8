/* The compaction's layout (after compact_lifts.cl; compact_layout.py collapse, layout):
   the collapse of subtrees into leaves, the final leaves' items, prefix sums, and the nodes' and
   lists' words of the compact tree. */

/* ----------------------------------------------------------------------------------------
   Collapse (compact_layout.py collapse), bottom-up per level in double: a subtree becomes one leaf
   when K_I distinct <= K_T + K_I refs + (A_b cost_b + A_a cost_a) / A. */

__kernel void collapse(__global const uint2* restrict nodes, __global const uint* restrict pre,
                       __global const WalkRecord* restrict walk,
                       __global const uint* restrict leaf_count,
                       __global const uint* restrict refs_at, __global const int* restrict distinct,
                       __global double* restrict cost, __global uchar* restrict collapsed,
                       uint first, uint end, ulong kt_bits, ulong ki_bits)
{
    uint i;
    if (!level_node(first, end, &i))
        return;
    uint2 w = nodes[i];
    double K_T = as_double((ulong)kt_bits), K_I = as_double((ulong)ki_bits);
    if (is_leaf(w)) {
        cost[i] = (K_I * (double)leaf_count[i]);
        collapsed[i] = 0;
        return;
    }
    uint c = KD_PLAIN_FIELD(w.x);
    double below = ((walk[pre[c]].area * cost[c]) + (walk[pre[c + 1]].area * cost[c + 1]));
    double sub = ((K_T + (K_I * (double)refs_at[i])) + (below / walk[pre[i]].area));
    double as_leaf = (K_I * (double)((uint)distinct[i]));
    int take = (as_leaf <= sub);
    collapsed[i] = (uchar)take;
    cost[i] = take ? as_leaf : sub;
}

/* Top-down per level: which nodes are gone (below a collapsed node) and the leaf that takes
   each node's contents. */
__kernel void owners(__global const uint2* restrict nodes, __global const uchar* restrict collapsed,
                     __global uchar* restrict dead, __global uint* restrict owner, uint first,
                     uint end)
{
    uint i;
    uint2 w;
    uint c = level_inner(nodes, first, end, &i, &w);
    if (c == NONE)
        return;
    int gone = dead[i] || collapsed[i];
    for (uint k = c; k < c + 2; k++) {
        dead[k] = (uchar)gone;
        owner[k] = gone ? owner[i] : k;
    }
}

/* ----------------------------------------------------------------------------------------
   Items of the final leaves: the kept references and the lifts of removed nodes, per owner
   leaf sorted by triangle without repeats (compact.py: np.unique of owner * T + triangle). */

__kernel void items_count(__global const uchar* restrict removed, __global const uint* restrict s_leaf,
                          __global const uint* restrict owner, __global uint* restrict per_owner,
                          uint ref_count)
{
    uint j = get_global_id(0);
    if (j < ref_count && !removed[j])
        atomic_inc(per_owner + owner[s_leaf[j]]);
}

__kernel void items_scatter(__global const uchar* restrict removed,
                            __global const uint* restrict s_leaf, __global const uint* restrict s_tri,
                            __global const uint* restrict owner,
                            __global const uint* restrict owner_first, __global uint* restrict cursor,
                            __global uint* restrict items, uint ref_count)
{
    uint j = get_global_id(0);
    if (j >= ref_count || removed[j])
        return;
    uint o = owner[s_leaf[j]];
    items[owner_first[o] + atomic_inc(cursor + o)] = s_tri[j];
}

/* Per node: its bucket [owner_first[i], owner_first[i + 1]) sorted, repeats dropped; the
   number kept. */
__kernel void items_unique(__global const uint* restrict owner_first, __global uint* items,
                           __global uint* restrict kept, uint n)
{
    uint i = get_global_id(0);
    if (i >= n)
        return;
    uint a = owner_first[i], m = owner_first[i + 1] - a;
    __global uint* v = items + a;
    sort_pairs(v, v, m);
    uint k = 0;
    for (uint x = 0; x < m; x++)
        if (k == 0 || v[x] != v[k - 1])
            v[k++] = v[x];
    kept[i] = k;
}

/* Per node: its kept items moved from its bucket to its place in the final lists. */
__kernel void close_buckets(__global const uint* restrict owner_first, __global const uint* restrict kept,
                            __global const uint* restrict item_first, __global const uint* restrict items,
                            __global uint* restrict out, uint n)
{
    uint i = get_global_id(0);
    if (i >= n)
        return;
    for (uint j = 0; j < kept[i]; j++)
        out[item_first[i] + j] = items[owner_first[i] + j];
}

/* ----------------------------------------------------------------------------------------
   Exclusive prefix sums: per block of `block` values their sum, the host sums the blocks,
   then each block is scanned from its offset (in place allowed). */

__kernel void block_sums(__global const uint* restrict values, __global ulong* restrict sums,
                         uint n, uint block)
{
    uint g = get_global_id(0), first, last;
    if (!item_block(block, n, &first, &last))
        return;
    ulong s = 0;
    for (uint i = first; i < last; i++)
        s += values[i];
    sums[g] = s;
}

__kernel void block_scan(__global const uint* values, __global const ulong* restrict offsets,
                         __global uint* out, uint n, uint block)
{
    uint g = get_global_id(0), first, last;
    if (!item_block(block, n, &first, &last))
        return;
    ulong running = offsets[g];
    for (uint i = first; i < last; i++) {
        uint v = values[i];
        out[i] = (uint)running;
        running += v;
    }
}

/* ----------------------------------------------------------------------------------------
   The layout (compact_layout.py layout). For a tree in the builders' order, groups are handed out
   in node index order, so a node's group is 1 + the sizes of the groups of the live inner
   nodes before it: one prefix sum; likewise the leaves' list offsets. */

/* Node classes: bit 0 final leaf, bit 1 live inner node, bit 2 empty final leaf. */
__kernel void layout_classes(__global const uint2* restrict nodes, __global const uchar* restrict dead,
                             __global const uchar* restrict collapsed,
                             __global const uint* restrict final_count,
                             __global uchar* restrict classes, uint n)
{
    uint i = get_global_id(0);
    if (i >= n)
        return;
    int final_leaf = !dead[i] && (is_leaf(nodes[i]) || collapsed[i]);
    int live_inner = !dead[i] && !final_leaf;
    classes[i] = (uchar)(final_leaf | (live_inner << 1) | ((final_leaf && final_count[i] == 0u) << 2));
}

/* Per live inner node: which children are elided, and its group size (reference slot, then
   the children that are stored). */
__kernel void layout_groups(__global const uint2* restrict nodes, __global const uchar* restrict classes,
                            __global const uint* restrict refs_at, __global uchar* restrict elided,
                            __global uint* restrict group_size, uint n, uint elide_empty)
{
    uint i = get_global_id(0);
    if (i >= n)
        return;
    if (!(classes[i] & 2u)) {
        group_size[i] = 0u;
        return;
    }
    uint c = KD_PLAIN_FIELD(nodes[i].x);
    int empty_b = (classes[c] >> 2) & 1, empty_a = (classes[c + 1] >> 2) & 1;
    int elide_b = elide_empty && empty_b && !empty_a, elide_a = elide_empty && empty_a && !empty_b;
    elided[c] = (uchar)elide_b;
    elided[c + 1] = (uchar)elide_a;
    group_size[i] = (refs_at[i] > 0u) + (uint)!elide_b + (uint)!elide_a;
}

/* Per final leaf that is stored: 16-bit or 32-bit list, and how many items go to each. */
__kernel void layout_leaves(__global const uchar* restrict classes, __global const uchar* restrict elided,
                            __global const uint* restrict final_count,
                            __global const uint* restrict item_first,
                            __global const uint* restrict items, __global uint* restrict count32,
                            __global uint* restrict count16, __global uint* restrict base_of,
                            uint n, uint shift, uint leaf16, uint index16_bits)
{
    uint i = get_global_id(0);
    if (i >= n)
        return;
    uint count = final_count[i];
    count32[i] = 0u;
    count16[i] = 0u;
    if (!(classes[i] & 1u) || elided[i] || count == 0u)
        return;
    uint low = items[item_first[i]], high = items[item_first[i] + count - 1u];
    uint base = low >> shift;
    int fits16 = leaf16 && count <= KD_LEAF16_COUNT_MAX
                 && (ulong)high - ((ulong)base << shift) < (1UL << index16_bits);
    base_of[i] = base;
    if (fits16)
        count16[i] = count;
    else
        count32[i] = count;
}

/* Per live inner node: its children's new indices (from its group; NONE when elided), and
   its reference slot filled with KD_NO_TRIANGLE (layout_slots puts the lifts in). The root's
   new index is 0. */
__kernel void layout_places(__global const uint2* restrict nodes, __global const uchar* restrict classes,
                            __global const uchar* restrict elided,
                            __global const uint* restrict refs_at,
                            __global const uint* restrict group_first,
                            __global uint* restrict new_index, __global uint2* restrict out, uint n)
{
    uint i = get_global_id(0);
    if (i >= n || !(classes[i] & 2u))
        return;
    uint c = KD_PLAIN_FIELD(nodes[i].x);
    uint group = 1u + group_first[i];
    uint has_ref = refs_at[i] > 0u;
    new_index[c] = elided[c] ? NONE : group + has_ref;
    new_index[c + 1] = elided[c + 1] ? NONE : group + has_ref + (uint)!elided[c];
    if (has_ref)
        out[group] = (uint2)(KD_NO_TRIANGLE, KD_NO_TRIANGLE);
}

/* The words of live inner nodes and stored leaves, and the leaves' lists. */
__kernel void layout_words(__global const uint2* restrict nodes, __global const uchar* restrict classes,
                           __global const uchar* restrict elided,
                           __global const uint* restrict refs_at,
                           __global const uint* restrict group_first,
                           __global const uint* restrict final_count,
                           __global const uint* restrict item_first,
                           __global const uint* restrict items,
                           __global const uint* restrict count16, __global const uint* restrict off32,
                           __global const uint* restrict off16, __global const uint* restrict base_of,
                           __global const uint* restrict new_index, __global uint2* out,
                           __global uint* restrict index32, __global ushort* restrict index16,
                           uint n, uint shift)
{
    uint i = get_global_id(0);
    if (i >= n)
        return;
    uchar cls = classes[i];
    uint at = i == 0u ? 0u : new_index[i];
    if (cls & 2u) {
        uint2 w = nodes[i];
        uint c = KD_PLAIN_FIELD(w.x);
        out[at] = (uint2)(KD_TAG_PUT(KD_PLAIN_TAG(w.x)) | KD_REF_PUT(refs_at[i] > 0u)
                          | KD_EMPTY_BELOW_PUT(elided[c]) | KD_EMPTY_ABOVE_PUT(elided[c + 1])
                          | KD_GROUP_PUT(1u + group_first[i]), w.y);
    } else if ((cls & 1u) && !elided[i]) {
        uint count = final_count[i];
        if (count16[i]) {
            uint base = base_of[i];
            out[at] = (uint2)(KD_TAG_PUT(KD_LEAF_TAG) | KD_LEAF16_BIT | KD_LEAF16_COUNT_PUT(count)
                              | KD_LEAF16_BASE_PUT(base), off16[i]);
            for (uint j = 0; j < count; j++)
                index16[off16[i] + j] = (ushort)(items[item_first[i] + j] - (base << shift));
        } else {
            out[at] = (uint2)(KD_TAG_PUT(KD_LEAF_TAG) | KD_LEAF32_COUNT_PUT(count),
                              count ? off32[i] : 0u);
            for (uint j = 0; j < count; j++)
                index32[off32[i] + j] = items[item_first[i] + j];
        }
    }
}

/* The lifted triangles into their nodes' slots (lifts sorted by node, then triangle: slot
   0 and 1). */
__kernel void layout_slots(__global const uint* restrict lift_node, __global const uint* restrict lift_tri,
                           __global const uint* restrict lift_slot,
                           __global const uint* restrict group_first, __global uint* restrict out,
                           uint lift_count)
{
    uint j = get_global_id(0);
    if (j < lift_count)
        out[2 * (1u + group_first[lift_node[j]]) + lift_slot[j]] = lift_tri[j];
}

/* Top-down per level: references on the path to every surviving node (the most of them in
   *most); then passed to the children of every inner node. */
__kernel void path_refs(__global const uint2* restrict nodes, __global const uchar* restrict dead,
                        __global const uint* restrict refs_at, __global uint* restrict on_path,
                        __global uint* restrict most, uint first, uint end)
{
    uint i;
    if (!level_node(first, end, &i))
        return;
    uint here = on_path[i] + refs_at[i];
    /* Only a value above the largest seen so far goes to the atomic (every node's atomic was a
       long stretch: the threads take the line from each other); the plain read may be stale,
       but only lower, which costs an atomic, never the maximum. */
    if (!dead[i] && here > *most)
        atomic_max(most, here);
    uint c = first_child(nodes[i]);
    if (c != NONE) {
        on_path[c] = here;
        on_path[c + 1] = here;
    }
}

/* Top-down per level, the lift selection's references on the proper ancestors. */
__kernel void pass_down(__global const uint2* restrict nodes, __global const uint* restrict refs_at,
                        __global uint* restrict on_path, uint first, uint end)
{
    uint i;
    uint2 w;
    uint c = level_inner(nodes, first, end, &i, &w);
    if (c != NONE) {
        uint here = on_path[i] + refs_at[i];
        on_path[c] = here;
        on_path[c + 1] = here;
    }
}

__kernel void gather_bytes(__global const uchar* restrict values, __global const uint* restrict at,
                           __global uint* restrict out, uint count)
{
    uint j = get_global_id(0);
    if (j < count)
        out[j] = values[at[j]];
}

/* Small helpers: values[places[j]] = what[j] (or +=); out[j] = values[at[j]]. */
__kernel void put_values(__global const uint* restrict places, __global const uint* restrict what,
                         __global uint* restrict values, uint count)
{
    uint j = get_global_id(0);
    if (j < count)
        values[places[j]] = what[j];
}

__kernel void add_values(__global const uint* restrict places, __global const uint* restrict what,
                         __global uint* restrict values, uint count)
{
    uint j = get_global_id(0);
    if (j < count)
        values[places[j]] += what[j];        /* places are distinct */
}

__kernel void gather_values(__global const uint* restrict values, __global const uint* restrict at,
                            __global uint* restrict out, uint count)
{
    uint j = get_global_id(0);
    if (j < count)
        out[j] = values[at[j]];
}

/* Counts for the layout's stats, per block of nodes (a LAYOUT_COUNTS row, core/layout.py):
   stored leaves, empty stored leaves, elided leaves, 16-bit leaves, 32-bit non-empty leaves,
   live inner nodes, the largest stored leaf's count, collapsed nodes that survive. */
__kernel void layout_stats(__global const uchar* restrict classes, __global const uchar* restrict elided,
                           __global const uint* restrict final_count,
                           __global const uint* restrict count16,
                           __global const uchar* restrict collapsed,
                           __global const uchar* restrict dead, __global uint* restrict stats,
                           uint n, uint block)
{
    uint g = get_global_id(0), first, last;
    if (!item_block(block, n, &first, &last))
        return;
    uint c[LAYOUT_COUNTS_COLUMNS];
    for (int k = 0; k < LAYOUT_COUNTS_COLUMNS; k++)
        c[k] = 0u;
    for (uint i = first; i < last; i++) {
        uchar cls = classes[i];
        c[LAYOUT_COUNTS_COLLAPSED_KEPT] += collapsed[i] && !dead[i];
        c[LAYOUT_COUNTS_INNER] += (cls >> 1) & 1u;
        c[LAYOUT_COUNTS_EMPTY_LEAVES_ELIDED] += elided[i];
        if (!(cls & 1u) || elided[i])
            continue;
        uint count = final_count[i];
        c[LAYOUT_COUNTS_LEAVES]++;
        if (count == 0u)
            c[LAYOUT_COUNTS_EMPTY_LEAVES_STORED]++;
        else if (count16[i])
            c[LAYOUT_COUNTS_LEAVES_16BIT]++;
        else
            c[LAYOUT_COUNTS_LEAVES_32BIT]++;
        uint largest = c[LAYOUT_COUNTS_LARGEST_LEAF];
        c[LAYOUT_COUNTS_LARGEST_LEAF] = largest > count ? largest : count;
    }
    for (int k = 0; k < LAYOUT_COUNTS_COLUMNS; k++)
        stats[LAYOUT_COUNTS_COLUMNS * g + k] = c[k];
}
