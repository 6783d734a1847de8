/* The compaction's (compact*.cl) plain-node tests and the share of work of one work-item. */

#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define NONE 0xFFFFFFFFu

inline int is_leaf(uint2 w)
{
    return KD_PLAIN_TAG(w.x) == KD_LEAF_TAG;
}

/* The first child of an inner node (the above child follows it); NONE for a leaf. */
inline uint first_child(uint2 w)
{
    return is_leaf(w) ? NONE : KD_PLAIN_FIELD(w.x);
}

/* The work-item's block [*first, *last) of `block` consecutive items out of n; 0 when it has
   none. */
inline int item_block(uint block, uint n, uint* first, uint* last)
{
    uint f = (uint)get_global_id(0) * block;
    if (f >= n)
        return 0;
    *first = f;
    *last = f + block < n ? f + block : n;
    return 1;
}

/* The work-item's node of the level [first, end) of a breadth-first tree; 0 when it has none. */
inline int level_node(uint first, uint end, uint* i)
{
    *i = first + (uint)get_global_id(0);
    return *i < end;
}

/* The work-item's node of the level [first, end) (*i, its words in *w) when it is an inner
   node: its first child; NONE otherwise. */
inline uint level_inner(__global const uint2* nodes, uint first, uint end, uint* i, uint2* w)
{
    if (!level_node(first, end, i))
        return NONE;
    *w = nodes[*i];
    return first_child(*w);
}
