/* Moving subtree records (subtree.cl) into one store, and from there into the final
   breadth-first tree. One work-item per subtree, sequential over its records. */

/* moves per subtree: record source, record destination, record count, leaf reference source,
   leaf reference destination, leaf reference count. */
__kernel void store_subtrees(__global const uint2* restrict rec_words,
                             __global const uint* restrict rec_meta,
                             __global const uint* restrict leaf_refs,
                             __global const uint* restrict moves,
                             __global uint2* restrict store_words,
                             __global uint* restrict store_meta,
                             __global uint* restrict store_leaf_refs, uint subtree_count)
{
    uint s = get_global_id(0);
    if (s >= subtree_count)
        return;
    __global const uint* m = moves + 6 * s;
    for (uint i = 0; i < m[2]; i++) {
        store_words[m[1] + i] = rec_words[m[0] + i];
        store_meta[m[1] + i] = rec_meta[m[0] + i];
    }
    for (uint i = 0; i < m[5]; i++)
        store_leaf_refs[m[4] + i] = leaf_refs[m[3] + i];
}

/* places per subtree: first record, record count, first leaf reference, offset of its levels
   in bases. bases per (subtree, relative level): index of the level's first node of this
   subtree in the final tree, offset of its first leaf reference in leaf_indices. */
__kernel void place_subtrees(__global const uint2* restrict store_words,
                             __global const uint* restrict store_meta,
                             __global const uint* restrict store_leaf_refs,
                             __global const uint4* restrict places,
                             __global const uint2* restrict bases, __global uint2* restrict nodes,
                             __global uint* restrict leaf_indices, uint subtree_count)
{
    uint s = get_global_id(0);
    if (s >= subtree_count)
        return;
    uint4 p = places[s];
    uint leaf_run = p.z;
    for (uint r = p.x; r < p.x + p.y; r++) {
        uint2 w = store_words[r];
        uint meta = store_meta[r];
        uint2 base = bases[p.w + (meta & 63u)];
        uint at = base.x + (meta >> 6);
        if (is_leaf(w)) {
            uint count = KD_PLAIN_FIELD(w.x), offset = base.y + w.y;
            nodes[at] = (uint2)(w.x, offset);
            for (uint j = 0; j < count; j++)
                leaf_indices[offset + j] = store_leaf_refs[leaf_run + j];
            leaf_run += count;
        } else {
            uint child = bases[p.w + (meta & 63u) + 1u].x + KD_PLAIN_FIELD(w.x);
            nodes[at] = (uint2)(KD_PLAIN_TAG_PUT(KD_PLAIN_TAG(w.x)) | KD_PLAIN_FIELD_PUT(child), w.y);
        }
    }
}
