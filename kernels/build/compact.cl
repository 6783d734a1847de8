/* The compaction of a builder-ordered plain kd-tree (core/accel/compact_cl.py), step for step
   core/accel/compact.py's numpy post-pass, with the same float64 arithmetic (IEEE double:
   cl_khr_fp64), so the compact tree is the same bits.

   A builder-ordered tree is breadth-first with the k-th inner node's children at 1 + 2k: each
   level is a contiguous range of nodes and the children of its inner nodes, pair by pair,
   are the next level. Per-level kernels get the level's range [first, end).

   The kernels, in the order core/accel/compact_cl.py's KERNEL_FILES concatenates them (each
   file uses what the ones before it define): this file, the builders' order check, the
   topology and the references sorted by triangle; compact_lifts.cl, the gaps' LCAs, the lift
   candidates, the choice of lifts and the distinct triangles below each node;
   compact_layout.cl, the collapse, the final leaves' items, prefix sums and the layout. */

#pragma OPENCL FP_CONTRACT OFF

inline int d_finite(double x)
{
    return x == x && x != INFINITY && x != -INFINITY;
}

inline double cell_area(const float* lo, const float* hi)
{
    double d[3];
    for (int a = 0; a < 3; a++)
        d[a] = ((double)hi[a] - (double)lo[a]);
    double sum = (((d[0] * d[1]) + (d[1] * d[2])) + (d[2] * d[0]));
    return 2.0 * sum;
}

/* ----------------------------------------------------------------------------------------
   The builders' order: is node i's first child at 1 + 2 (inner nodes before i)? inner_before
   is the exclusive prefix sum of inner_flags. */

__kernel void inner_flags(__global const uint2* restrict nodes, __global uint* restrict flags, uint n)
{
    uint i = get_global_id(0);
    if (i < n)
        flags[i] = !is_leaf(nodes[i]);
}

__kernel void order_check(__global const uint2* restrict nodes,
                          __global const uint* restrict inner_before, __global uint* restrict bad,
                          uint n)
{
    uint i = get_global_id(0);
    if (i < n && !is_leaf(nodes[i]) && KD_PLAIN_FIELD(nodes[i].x) != 1u + 2u * inner_before[i])
        *bad = 1u;               /* every writer writes the same value */
}

/* ----------------------------------------------------------------------------------------
   Topology (compact_topology.py Topology, compact_lifts.py _falls_going_up, subtree sums),
   level by level: subtree sizes and non-empty leaves going up, then going down the cells
   (CELL rows, by position in its level), areas and preorder numbers, and each node's records
   at its preorder number p (so that climbing stays near its start: a below child follows its
   parent directly):
     climb[p], a CLIMB row: end of its preorder range, the parent's preorder number, depth,
                the node;
     walk[p] = (area, the parent's preorder number, non-empty leaves below | whether the area
                never shrinks from here up to the root << 31). */

typedef struct {
    double area;
    uint parent;             /* preorder number, NONE at the root */
    uint nonempty_stops;
} WalkRecord;

/* Per node of a level, bottom-up: subtree size and non-empty leaves below (leaves: 1 and
   count > 0). */
__kernel void topo_up(__global const uint2* restrict nodes, __global uint* restrict size,
                      __global uint* restrict nonempty, uint first, uint end)
{
    uint i;
    if (!level_node(first, end, &i))
        return;
    uint2 w = nodes[i];
    if (is_leaf(w)) {
        size[i] = 1u;
        nonempty[i] = KD_PLAIN_FIELD(w.x) > 0u;
    } else {
        uint c = KD_PLAIN_FIELD(w.x);
        size[i] = 1u + size[c] + size[c + 1];
        nonempty[i] = nonempty[c] + nonempty[c + 1];
    }
}

/* Returns whether the area never shrinks from x up to the root (its children's parent_stops). */
inline int put_records(uint x, uint p, uint parent_pre, uint depth, int parent_stops,
                        double parent_area, double A, __global const uint* size,
                        __global const uint* nonempty, __global uint4* climb,
                        __global WalkRecord* walk)
{
    int stops = d_finite(A) && (0.0 < A) && parent_stops && (parent_area >= A);
    uint4 c;
    CLIMB_END_OF(c) = p + size[x];
    CLIMB_PARENT_OF(c) = parent_pre;
    CLIMB_DEPTH_OF(c) = depth;
    CLIMB_NODE_OF(c) = x;
    climb[p] = c;
    WalkRecord w;
    w.area = A;
    w.parent = parent_pre;
    w.nonempty_stops = nonempty[x] | ((uint)stops << 31);
    walk[p] = w;
    return stops;
}

__kernel void topo_root(__global const float* restrict bounds, __global float* restrict cells,
                        __global const uint* restrict size, __global const uint* restrict nonempty,
                        __global uint* restrict pre, __global uint4* restrict climb,
                        __global WalkRecord* restrict walk)
{
    float lo[3], hi[3];
    for (int a = 0; a < 3; a++) {
        lo[a] = bounds[a];
        hi[a] = bounds[3 + a];
        cells[CELL_LO_X + a] = lo[a];
        cells[CELL_HI_X + a] = hi[a];
    }
    double A = cell_area(lo, hi);
    pre[0] = 0u;
    put_records(0u, 0u, NONE, 0u, 1, A, A, size, nonempty, climb, walk);
}

/* Per node of level [first, end), top-down: its children's cells (for the next level),
   preorder numbers and records. */
__kernel void topo_down(__global const uint2* restrict nodes, __global const float* restrict cells,
                        __global float* restrict next_cells, __global const uint* restrict size,
                        __global const uint* restrict nonempty, __global uint* restrict pre,
                        __global uint4* restrict climb, __global WalkRecord* restrict walk,
                        uint first, uint end, uint level)
{
    uint i;
    uint2 w;
    uint c = level_inner(nodes, first, end, &i, &w);
    if (c == NONE)
        return;
    int axis = (int)KD_PLAIN_TAG(w.x);
    float split = as_float(w.y);
    uint p = pre[i];
    WalkRecord parent = walk[p];
    int stops = parent.nonempty_stops >> 31;
    __global const float* cell = cells + CELL_COLUMNS * (i - first);
    for (int side = 0; side < 2; side++) {
        float lo[3], hi[3];
        for (int a = 0; a < 3; a++) {
            lo[a] = cell[CELL_LO_X + a];
            hi[a] = cell[CELL_HI_X + a];
        }
        if (side)
            lo[axis] = split;
        else
            hi[axis] = split;
        uint child = c + (uint)side;
        __global float* out = next_cells + CELL_COLUMNS * (child - end);
        for (int a = 0; a < 3; a++) {
            out[CELL_LO_X + a] = lo[a];
            out[CELL_HI_X + a] = hi[a];
        }
        uint pc = side ? p + 1u + size[c] : p + 1u;
        pre[child] = pc;
        put_records(child, pc, p, level + 1u, stops, parent.area, cell_area(lo, hi), size,
                    nonempty, climb, walk);
    }
}

/* Per node of level [first, end): the rest of topo_down for its whole subtree, depth first,
   so that the records go out in preorder, one after another (a subtree is a contiguous range
   of preorder numbers; level by level they would land spread over the whole range, each
   write touching a cache line of its own). The node's own record and cell come from the
   level above. The node being split stays in registers and only the above child is pushed,
   field by field: a stack of structs, written a field at a time and read back whole, stalled
   on store forwarding (docs/kdtree_native.md). */
__kernel void topo_subtrees(__global const uint2* restrict nodes, __global const float* restrict cells,
                            __global const uint* restrict size, __global const uint* restrict nonempty,
                            __global uint* restrict pre, __global uint4* restrict climb,
                            __global WalkRecord* restrict walk, uint first, uint end, uint level)
{
    uint i;
    if (!level_node(first, end, &i))
        return;
    float s_lo[3][TOPO_STACK], s_hi[3][TOPO_STACK];
    double s_area[TOPO_STACK];
    uint s_node[TOPO_STACK], s_pre[TOPO_STACK], s_depth[TOPO_STACK];
    int s_stops[TOPO_STACK];
    int sp = 0;
    float lo[3], hi[3];
    __global const float* cell = cells + CELL_COLUMNS * (i - first);
    for (int a = 0; a < 3; a++) {
        lo[a] = cell[CELL_LO_X + a];
        hi[a] = cell[CELL_HI_X + a];
    }
    uint node = i, p = pre[i], depth = level;
    WalkRecord own = walk[p];
    double area = own.area;
    int stops = own.nonempty_stops >> 31;
    while (true) {
        uint2 w = nodes[node];
        uint c = first_child(w);
        if (c == NONE) {
            if (sp == 0)
                break;
            sp--;
            for (int a = 0; a < 3; a++) {
                lo[a] = s_lo[a][sp];
                hi[a] = s_hi[a][sp];
            }
            node = s_node[sp];
            p = s_pre[sp];
            depth = s_depth[sp];
            area = s_area[sp];
            stops = s_stops[sp];
            continue;
        }
        int axis = (int)KD_PLAIN_TAG(w.x);
        float split = as_float(w.y);
        /* The above child (preorder p + 1 + size of the below one) waits on the stack; the
           below child (p + 1) is next. */
        uint below_pre = p + 1u, above_pre = p + 1u + size[c];
        float above_lo[3];
        for (int a = 0; a < 3; a++) {
            s_hi[a][sp] = hi[a];
            above_lo[a] = a == axis ? split : lo[a];
            s_lo[a][sp] = above_lo[a];
        }
        double above_area = cell_area(above_lo, hi);
        pre[c + 1u] = above_pre;
        s_stops[sp] = put_records(c + 1u, above_pre, p, depth + 1u, stops, area, above_area,
                                  size, nonempty, climb, walk);
        s_node[sp] = c + 1u;
        s_pre[sp] = above_pre;
        s_depth[sp] = depth + 1u;
        s_area[sp] = above_area;
        sp++;
        hi[axis] = split;
        double below_area = cell_area(lo, hi);
        pre[c] = below_pre;
        stops = put_records(c, below_pre, p, depth + 1u, stops, area, below_area, size,
                            nonempty, climb, walk);
        node = c;
        p = below_pre;
        depth++;
        area = below_area;
    }
}

/* ----------------------------------------------------------------------------------------
   References sorted by (triangle, preorder of the leaf): counted per triangle, scattered into
   their triangle's range (in any order), then each range sorted by preorder. */

/* Per reference: one more for its triangle (the ranges' sizes, before their prefix sum), and
   its rank among its triangle's references (its place in the range, in any order). */
__kernel void refs_count(__global const uint* restrict leaf_indices, __global uint* restrict counts,
                         __global uint* restrict rank, uint count)
{
    uint j = get_global_id(0);
    if (j < count)
        rank[j] = atomic_inc(counts + leaf_indices[j]);
}

/* Per node (leaves only): its references scattered into their triangles' ranges. No atomics
   here: a locked instruction waits for the stores before it, and these stores miss the cache
   (with the rank taken here, that wait was most of the kernel; docs/kdtree_native.md). */
__kernel void refs_scatter(__global const uint2* restrict nodes,
                           __global const uint* restrict leaf_indices,
                           __global const uint* restrict tri_first, __global const uint* restrict rank,
                           __global const uint* restrict pre, __global uint* restrict s_leaf,
                           __global uint* restrict s_pre, uint n)
{
    uint node = get_global_id(0);
    if (node >= n)
        return;
    uint2 w = nodes[node];
    if (!is_leaf(w))
        return;
    uint count = KD_PLAIN_FIELD(w.x), p = pre[node];
    for (uint j = w.y; j < w.y + count; j++) {
        uint at = tri_first[leaf_indices[j]] + rank[j];
        s_leaf[at] = node;
        s_pre[at] = p;
    }
}

/* key[0..n) sorted ascending, val[] moved along (val may be key itself): insertion sort for
   short ranges, heap sort for long ones. */
inline void sort_pairs(__global uint* key, __global uint* val, uint n)
{
    if (n <= 32u) {
        for (uint i = 1; i < n; i++) {
            uint k = key[i], v = val[i];
            uint j = i;
            while (j > 0 && key[j - 1] > k) {
                key[j] = key[j - 1];
                val[j] = val[j - 1];
                j--;
            }
            key[j] = k;
            val[j] = v;
        }
        return;
    }
    for (uint start = n / 2, last = n; last > 1;) {
        uint r;
        if (start > 0) {                      /* heapify (a max-heap) */
            r = --start;
        } else {                              /* the largest to the end */
            last--;
            uint k = key[0], v = val[0];
            key[0] = key[last];
            val[0] = val[last];
            key[last] = k;
            val[last] = v;
            r = 0;
        }
        for (;;) {                            /* sift down within [0, last) */
            uint child = 2 * r + 1;
            if (child >= last)
                break;
            if (child + 1 < last && key[child + 1] > key[child])
                child++;
            if (key[r] >= key[child])
                break;
            uint k = key[r], v = val[r];
            key[r] = key[child];
            val[r] = val[child];
            key[child] = k;
            val[child] = v;
            r = child;
        }
    }
}

/* Per triangle: its range sorted by preorder (a triangle's leaves have distinct preorder
   numbers). */
__kernel void refs_sort(__global const uint* restrict tri_first, __global uint* restrict s_leaf,
                        __global uint* restrict s_pre, __global uint* restrict s_tri,
                        uint triangle_count)
{
    uint t = get_global_id(0);
    if (t >= triangle_count)
        return;
    uint a = tri_first[t], n = tri_first[t + 1] - a;
    sort_pairs(s_pre + a, s_leaf + a, n);
    for (uint i = 0; i < n; i++)
        s_tri[a + i] = t;
}
