/* The plain kd-tree node format (docs/architecture.md, core/accel/kdtree.py): two uint words
   per node. Word 0: bits 0-1 split axis (inner) or KD_LEAF_TAG, bits 2-31 the first child's
   index (inner; children c and c + 1) or the leaf's reference count. Word 1: the split as
   float32 bits (inner) or the offset of the leaf's list in leaf_indices. */

#define KD_LEAF_TAG 3u
#define KD_FIELD_SHIFT 2
#define KD_MAX_FIELD ((1u << 30) - 1u)
