/* The compaction of a builder-ordered plain kd-tree (core/accel/compact_cl.py), step for step
   core/accel/compact.py's numpy post-pass, with the same float64 arithmetic (IEEE double:
   cl_khr_fp64), so the compact tree is the same bits.

   A builder-ordered tree is breadth-first with the k-th inner node's children at 1 + 2k: each
   level is a contiguous range of nodes and the children of its inner nodes, pair by pair,
   are the next level. Per-level kernels get the level's range [first, end). */

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
   Topology (compact.py _Topology, _falls_going_up, subtree sums), level by level: subtree
   sizes and non-empty leaves going up, then going down the cells (CELL rows, by position in
   its level), areas and preorder numbers, and each node's records at its preorder number p
   (so that climbing stays near its start: a below child follows its parent directly):
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

/* ----------------------------------------------------------------------------------------
   Gap j lies before sorted reference j: the LCA of references j-1 and j when they hold the
   same triangle (climbing from the first until its subtree holds the second), and its depth;
   -1 between triangles and at both ends (compact.py _neighbour_lcas). */

/* In preorder numbers: x holds b when x <= b < end(x). gap_pre: the LCA's preorder number. */
__kernel void neighbour_lcas(__global const uint* restrict s_pre, __global const uint* restrict s_tri,
                             __global const uint4* restrict climb, __global uint* restrict gap_node,
                             __global uint* restrict gap_pre, __global int* restrict gap_depth,
                             uint ref_count)
{
    uint j = get_global_id(0);
    if (j > ref_count)
        return;
    if (j == 0 || j == ref_count || s_tri[j] != s_tri[j - 1]) {
        gap_node[j] = 0u;
        gap_pre[j] = 0u;
        gap_depth[j] = -1;
        return;
    }
    uint x = s_pre[j - 1], b = s_pre[j];
    uint4 cx = climb[x];
    while (!(x <= b && b < CLIMB_END_OF(cx))) {
        x = CLIMB_PARENT_OF(cx);
        cx = climb[x];
    }
    gap_node[j] = CLIMB_NODE_OF(cx);
    gap_pre[j] = x;
    gap_depth[j] = (int)CLIMB_DEPTH_OF(cx);
}

/* ----------------------------------------------------------------------------------------
   Lift candidates (compact.py _lift_candidates), one work-item per triangle: its references
   are one range of the sorted list, its gaps the range's inner gaps (the range's end gaps are
   -1). Runs from the nearest lower gaps on both sides (stacks in the scratch arrays), then
   each run walked up from its LCA while it qualifies. */

/* numpy's pairwise sum (what np.add.reduceat uses) of values[s_leaf[k]] over k in
   [first, first + n): below 8 terms in order, up to 128 in 8 accumulators, above that the two
   halves (split at a multiple of 8) summed separately; an explicit stack replaces the
   recursion. */
#define PAIRWISE_STACK 40

#define AREA_OF(k) walk[s_pre[k]].area

inline double pairwise_block(__global const WalkRecord* walk, __global const uint* s_pre, uint first,
                          uint n)
{
    if (n < 8u) {
        double res = 0.0;
        for (uint i = 0; i < n; i++)
            res = (res + AREA_OF(first + i));
        return res;
    }
    double r[8];
    for (int j = 0; j < 8; j++)
        r[j] = AREA_OF(first + j);
    uint i = 8u;
    for (; i < n - (n % 8u); i += 8u)
        for (int j = 0; j < 8; j++)
            r[j] = (r[j] + AREA_OF(first + i + j));
    double res = (((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7])));
    for (; i < n; i++)
        res = (res + AREA_OF(first + i));
    return res;
}

inline double pairwise_sum(__global const WalkRecord* walk, __global const uint* s_pre, uint first,
                        uint n)
{
    /* A frame per pending half: its range, and whether its left half is done (then kept). */
    uint f_first[PAIRWISE_STACK], f_n[PAIRWISE_STACK];
    int f_right[PAIRWISE_STACK];
    double f_left[PAIRWISE_STACK];
    int sp = 0;
    f_first[0] = first;
    f_n[0] = n;
    for (;;) {
        while (f_n[sp] > 128u) {                  /* down the left halves */
            uint n2 = f_n[sp] / 2u;
            n2 -= n2 % 8u;
            f_right[sp] = 0;
            f_first[sp + 1] = f_first[sp];
            f_n[sp + 1] = n2;
            sp++;
        }
        double value = pairwise_block(walk, s_pre, f_first[sp], f_n[sp]);
        for (;;) {                                /* up, until a right half is pending */
            if (sp == 0)
                return value;
            sp--;
            if (!f_right[sp]) {
                uint n2 = f_n[sp] / 2u;
                n2 -= n2 % 8u;
                f_left[sp] = value;
                f_right[sp] = 1;
                f_first[sp + 1] = f_first[sp] + n2;
                f_n[sp + 1] = f_n[sp] - n2;
                sp++;
                break;
            }
            value = (f_left[sp] + value);
        }
    }
}

inline double run_area(__global const WalkRecord* walk, __global const uint* s_pre, uint first, uint n)
{
    double head = AREA_OF(first);
    return n > 1u ? (head + pairwise_sum(walk, s_pre, first + 1u, n - 1u)) : head;
}

/* Candidates (LIFT_CANDIDATE rows, core/layout.py) are appended in blocks through `used`
   (in any order: cand_group groups them). */
#define CANDIDATE_BLOCK 32
/* PRIVATE_GAPS (-D, compact_cl.py): triangles with more references use the scratch. */

/* Per triangle: its reference count when it needs the scratch (more than PRIVATE_GAPS),
   else 0; their prefix sum places each one's stacks. */
__kernel void scratch_spans(__global const uint* restrict tri_first, __global uint* restrict spans,
                            uint triangle_count)
{
    uint t = get_global_id(0);
    if (t < triangle_count) {
        uint span = tri_first[t + 1u] - tri_first[t];
        spans[t] = span > PRIVATE_GAPS ? span : 0u;
    }
}

__kernel void lift_candidates(__global const uint* restrict tri_first,
                              __global const uint* restrict s_pre,
                              __global const uint* restrict gap_pre,
                              __global const int* restrict gap_depth,
                              __global const uint4* restrict climb,
                              __global const WalkRecord* restrict walk,
                              __global const uint* restrict big_first,
                              __global uint* restrict scratch, __global uint* restrict out,
                              __global uint* restrict used, uint capacity,
                              uint triangle_count, uint min_refs, ulong tau_occu_bits,
                              ulong tau_freq_bits)
{
    uint t = get_global_id(0);
    if (t >= triangle_count)
        return;
    uint a = tri_first[t], e = tri_first[t + 1];
    if (e == a)
        return;
    double tau_occu = as_double((ulong)tau_occu_bits), tau_freq = as_double((ulong)tau_freq_bits);
    /* Nearest gap to the left with depth <= ours, to the right with depth < ours (by gap
       index relative to a; private arrays, or for a triangle with many references its
       part of the scratch: three arrays of its reference count). */
    uint own[LIFT_SCRATCH_WORDS * PRIVATE_GAPS];
    uint span = e - a;
    __global uint* far = scratch + LIFT_SCRATCH_WORDS * (size_t)big_first[t];
    uint* near = own;
    int private_gaps = span <= PRIVATE_GAPS;
#define LEFT(g) (private_gaps ? near[(g) - a] : far[(g) - a])
#define RIGHT(g) (private_gaps ? near[PRIVATE_GAPS + (g) - a] : far[span + (g) - a])
#define STACK(k) (private_gaps ? near[2 * PRIVATE_GAPS + (k)] : far[2 * span + (k)])
#define SET(where, value) do { if (private_gaps) near[where] = (value); else far[where] = (value); } while (0)
    uint sp = 0;
    SET(private_gaps ? 2 * PRIVATE_GAPS : 2 * span, a);
    sp = 1;
    for (uint g = a + 1; g < e; g++) {
        int dg = gap_depth[g];
        while (gap_depth[STACK(sp - 1)] > dg)
            sp--;
        SET(g - a, STACK(sp - 1));
        SET((private_gaps ? 2 * PRIVATE_GAPS : 2 * span) + sp, g);
        sp++;
    }
    SET(private_gaps ? 2 * PRIVATE_GAPS : 2 * span, e);
    sp = 1;
    for (uint g = e - 1; g > a; g--) {
        int dg = gap_depth[g];
        while (gap_depth[STACK(sp - 1)] >= dg)
            sp--;
        SET((private_gaps ? PRIVATE_GAPS : span) + g - a, STACK(sp - 1));
        SET((private_gaps ? 2 * PRIVATE_GAPS : 2 * span) + sp, g);
        sp++;
    }
    uint block[LIFT_CANDIDATE_COLUMNS * CANDIDATE_BLOCK];
    uint held = 0u;
    /* Runs of two or more references (one per gap that is the first of its depth in its
       run), then, with min_refs <= 1, every single reference below the root. */
    for (uint g = a + 1; g < e + (min_refs <= 1u ? e - a : 0u); g++) {
        uint run_lo, run_hi, node;
        int run_depth;
        if (g < e) {
            int dg = gap_depth[g];
            if (dg < 0 || !(gap_depth[LEFT(g)] < dg))
                continue;
            run_lo = LEFT(g);
            run_hi = RIGHT(g);
            node = gap_pre[g];
            run_depth = dg;
            /* Copies of a triangle in one leaf: the LCA is that leaf (a preorder number names
               a node; the test on the node's word cost two cache misses, half the kernel). */
            if (node == s_pre[g]) {
                node = walk[node].parent;
                run_depth -= 1;
            }
        } else {
            uint k = a + (g - e);
            uint leaf = s_pre[k];
            uint leaf_depth = CLIMB_DEPTH_OF(climb[leaf]);
            if (leaf_depth == 0u)
                continue;
            run_lo = k;
            run_hi = k + 1u;
            node = walk[leaf].parent;
            run_depth = (int)leaf_depth - 1;
        }
        int bound_lo = gap_depth[run_lo], bound_hi = gap_depth[run_hi];
        int top_depth = (bound_lo < 0 && bound_hi < 0) ? run_depth
                                                       : (bound_lo > bound_hi ? bound_lo : bound_hi) + 1;
        uint r = run_hi - run_lo;
        if (!(r >= min_refs && run_depth >= top_depth && run_depth >= 0))
            continue;
        double area_sum = run_area(walk, s_pre, run_lo, r);
        double count = (double)r;
        int d = run_depth;
        for (;;) {
            WalkRecord w = walk[node];
            double occupancy = (area_sum / w.area);
            uint ne = w.nonempty_stops & 0x7FFFFFFFu;
            double frequency = (count / (double)(ne > 1u ? ne : 1u));
            int ok = (occupancy >= tau_occu) && (frequency >= tau_freq);
            if (ok) {
                if (held == CANDIDATE_BLOCK) {
                    uint at = atomic_add(used, held);
                    uint words = LIFT_CANDIDATE_COLUMNS * held;
                    for (uint i = 0; i < words && at + held <= capacity; i++)
                        out[LIFT_CANDIDATE_COLUMNS * (size_t)at + i] = block[i];
                    held = 0u;
                }
                uint* c = block + LIFT_CANDIDATE_COLUMNS * held++;
                c[LIFT_CANDIDATE_DEPTH] = (uint)d;
                c[LIFT_CANDIDATE_NODE] = CLIMB_NODE_OF(climb[node]);
                c[LIFT_CANDIDATE_TRIANGLE] = t;
                c[LIFT_CANDIDATE_REFERENCES] = r;
                c[LIFT_CANDIDATE_FIRST] = run_lo;
                c[LIFT_CANDIDATE_END] = run_hi;
            }
            if (!(d > top_depth && (ok || !(w.nonempty_stops >> 31))))
                break;
            node = w.parent;
            d--;
        }
    }
    if (held) {
        uint at = atomic_add(used, held);
        for (uint i = 0; i < LIFT_CANDIDATE_COLUMNS * held && at + held <= capacity; i++)
            out[LIFT_CANDIDATE_COLUMNS * (size_t)at + i] = block[i];
    }
}

/* ----------------------------------------------------------------------------------------
   The greedy choice of lifts (compact.py _choose_lifts): the candidates grouped by node, then
   level by level from the root, each node of a level takes its best candidates still live. */

/* Per candidate: one more for its node. */
__kernel void cand_count(__global const uint* restrict cand, __global uint* restrict node_next,
                         uint count)
{
    uint j = get_global_id(0);
    if (j < count)
        atomic_inc(node_next + cand[LIFT_CANDIDATE_COLUMNS * (size_t)j + LIFT_CANDIDATE_NODE]);
}

/* Per candidate: into its node's range, in any order (the choice ranks them by a total
   order). node_next starts at each node's first place and ends at the next node's. */
__kernel void cand_group(__global const uint* restrict cand, __global uint* restrict node_next,
                         __global uint4* restrict grouped, __global uint* restrict grouped_node,
                         uint count)
{
    uint j = get_global_id(0);
    if (j >= count)
        return;
    __global const uint* c = cand + LIFT_CANDIDATE_COLUMNS * (size_t)j;
    uint at = atomic_inc(node_next + c[LIFT_CANDIDATE_NODE]);
    uint4 g;
    LIFT_GROUPED_TRIANGLE_OF(g) = c[LIFT_CANDIDATE_TRIANGLE];
    LIFT_GROUPED_REFERENCES_OF(g) = c[LIFT_CANDIDATE_REFERENCES];
    LIFT_GROUPED_FIRST_OF(g) = c[LIFT_CANDIDATE_FIRST];
    LIFT_GROUPED_END_OF(g) = c[LIFT_CANDIDATE_END];
    grouped[at] = g;
    grouped_node[at] = c[LIFT_CANDIDATE_NODE];
}

/* Per node of a level: of its candidates whose run no lift above removed, the ones that
   remove the most references (ties: the lower triangle, then the earlier run), as many as
   the node and the path allow. They move to the front of the node's range in that order,
   flagged in `taken`; their runs are removed. A node's candidates are distinct triangles, so
   their runs are disjoint, and nodes of one level have disjoint subtrees. */
__kernel void choose_lifts(__global const uint* restrict node_end, __global uint4* restrict grouped,
                           __global uchar* restrict removed, __global uint* restrict taken,
                           __global uint* restrict refs_at, __global const uint* restrict on_path,
                           uint first, uint end, uint refs_per_node, uint path_cap, uint limited)
{
    uint i;
    if (!level_node(first, end, &i))
        return;
    uint a = i > 0u ? node_end[i - 1u] : 0u, b = node_end[i];
    uint cap = refs_per_node;
    if (limited) {
        uint above = on_path[i];
        cap = min(cap, path_cap > above ? path_cap - above : 0u);
    }
    uint k = 0u;
    for (; k < cap && a + k < b; k++) {
        uint best = b;
        uint4 bc = (uint4)(0u);
        for (uint j = a + k; j < b; j++) {
            uint4 c = grouped[j];
            if (removed[LIFT_GROUPED_FIRST_OF(c)])
                continue;
            uint refs = LIFT_GROUPED_REFERENCES_OF(c), best_refs = LIFT_GROUPED_REFERENCES_OF(bc);
            uint tri = LIFT_GROUPED_TRIANGLE_OF(c), best_tri = LIFT_GROUPED_TRIANGLE_OF(bc);
            if (best == b || refs > best_refs
                || (refs == best_refs && (tri < best_tri
                                          || (tri == best_tri && LIFT_GROUPED_FIRST_OF(c)
                                                                 < LIFT_GROUPED_FIRST_OF(bc))))) {
                best = j;
                bc = c;
            }
        }
        if (best == b)
            break;
        grouped[best] = grouped[a + k];
        grouped[a + k] = bc;
        taken[a + k] = 1u;
        for (uint r = LIFT_GROUPED_FIRST_OF(bc); r < LIFT_GROUPED_END_OF(bc); r++)
            removed[r] = 1;
    }
    refs_at[i] = k;
}

/* Per candidate: a taken one to its place among the lifts (slot: the exclusive prefix sum of
   the taken flags), node by node, each node's in the order chosen. */
__kernel void lifts_out(__global const uint* restrict slot, __global const uint4* restrict grouped,
                        __global const uint* restrict grouped_node, __global uint* restrict lift_node,
                        __global uint* restrict lift_tri, __global uint* restrict lift_first,
                        uint count)
{
    uint j = get_global_id(0);
    if (j >= count || slot[j + 1u] == slot[j])
        return;
    uint s = slot[j];
    uint4 c = grouped[j];
    lift_node[s] = grouped_node[j];
    lift_tri[s] = LIFT_GROUPED_TRIANGLE_OF(c);
    lift_first[s] = LIFT_GROUPED_FIRST_OF(c);
}

/* ----------------------------------------------------------------------------------------
   Distinct triangles below each node (compact.py _distinct_below): kept references and lifts
   count +1 at their node, the gap before each of them -1 at its LCA; then summed over
   subtrees. Also each leaf's kept references (leaf_count). Then the collapse. */

__kernel void distinct_refs(__global const uchar* restrict removed,
                            __global const uint* restrict s_leaf,
                            __global const uint* restrict gap_node,
                            __global const int* restrict gap_depth, __global int* restrict per_node,
                            __global uint* restrict leaf_count, uint ref_count)
{
    uint j = get_global_id(0);
    if (j >= ref_count || removed[j])
        return;
    atomic_inc(per_node + s_leaf[j]);
    atomic_inc(leaf_count + s_leaf[j]);
    if (gap_depth[j] >= 0)
        atomic_dec(per_node + gap_node[j]);
}

__kernel void distinct_lifts(__global const uint* restrict lift_node,
                             __global const uint* restrict lift_first,
                             __global const uint* restrict gap_node,
                             __global const int* restrict gap_depth, __global int* restrict per_node,
                             uint lift_count)
{
    uint j = get_global_id(0);
    if (j >= lift_count)
        return;
    atomic_inc(per_node + lift_node[j]);
    uint f = lift_first[j];
    if (gap_depth[f] >= 0)
        atomic_dec(per_node + gap_node[f]);
}

/* Per node of a level, bottom-up: values summed over its subtree. */
__kernel void subtree_sums(__global const uint2* restrict nodes, __global int* restrict values,
                           uint first, uint end)
{
    uint i;
    uint2 w;
    uint c = level_inner(nodes, first, end, &i, &w);
    if (c != NONE)
        values[i] += values[c] + values[c + 1];
}

/* ----------------------------------------------------------------------------------------
   Collapse (compact.py _collapse), bottom-up per level in double: a subtree becomes one leaf
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
   The layout (compact.py _layout). For a tree in the builders' order, groups are handed out
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
