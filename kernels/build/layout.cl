/* Moving subtree records (subtree.cl) into one store, and from there into the final
   breadth-first tree. One work-item per subtree, sequential over its records. */

/* moves: a STORE_MOVE row per subtree (core/layout.py). */
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
    __global const uint* m = moves + STORE_MOVE_COLUMNS * s;
    uint from = m[STORE_MOVE_RECORD_FROM], to = m[STORE_MOVE_RECORD_TO];
    for (uint i = 0; i < m[STORE_MOVE_RECORDS]; i++) {
        store_words[to + i] = rec_words[from + i];
        store_meta[to + i] = rec_meta[from + i];
    }
    from = m[STORE_MOVE_LEAF_FROM];
    to = m[STORE_MOVE_LEAF_TO];
    for (uint i = 0; i < m[STORE_MOVE_LEAF_REFS]; i++)
        store_leaf_refs[to + i] = leaf_refs[from + i];
}

/* places: a SUBTREE_PLACE row per subtree; bases: a LEVEL_BASE row per (subtree, relative
   level), where the level's first node of this subtree and its first leaf reference go in the
   final tree (core/layout.py). */
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
    uint leaf_run = SUBTREE_PLACE_LEAF_FIRST_OF(p), levels = SUBTREE_PLACE_LEVEL_OFFSET_OF(p);
    uint first = SUBTREE_PLACE_RECORD_FIRST_OF(p);
    for (uint r = first; r < first + SUBTREE_PLACE_RECORDS_OF(p); r++) {
        uint2 w = store_words[r];
        uint meta = store_meta[r];
        uint2 base = bases[levels + META_LEVEL(meta)];
        uint at = LEVEL_BASE_NODE_OF(base) + META_RANK(meta);
        if (is_leaf(w)) {
            uint count = KD_PLAIN_FIELD(w.x), offset = LEVEL_BASE_LEAF_OF(base) + w.y;
            nodes[at] = (uint2)(w.x, offset);
            for (uint j = 0; j < count; j++)
                leaf_indices[offset + j] = store_leaf_refs[leaf_run + j];
            leaf_run += count;
        } else {
            uint below = LEVEL_BASE_NODE_OF(bases[levels + META_LEVEL(meta) + 1u]);
            uint child = below + KD_PLAIN_FIELD(w.x);
            nodes[at] = (uint2)(KD_PLAIN_TAG_PUT(KD_PLAIN_TAG(w.x)) | KD_PLAIN_FIELD_PUT(child), w.y);
        }
    }
}
