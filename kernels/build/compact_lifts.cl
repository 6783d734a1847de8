/* The compaction's lifts (after compact.cl; compact_lifts.py neighbour_lcas, lift_candidates,
   _choose_lifts, distinct_below): the LCA of each gap between a triangle's references, the
   candidate lifts of each triangle, the greedy choice of lifts level by level, and the
   distinct triangles below each node. Then compact_layout.cl. */

/* ----------------------------------------------------------------------------------------
   Gap j lies before sorted reference j: the LCA of references j-1 and j when they hold the
   same triangle (climbing from the first until its subtree holds the second), and its depth;
   -1 between triangles and at both ends (compact_lifts.py neighbour_lcas). */

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
   Lift candidates (compact_lifts.py lift_candidates), one work-item per triangle: its references
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
   The greedy choice of lifts (compact_lifts.py _choose_lifts): the candidates grouped by node, then
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
   Distinct triangles below each node (compact_lifts.py distinct_below): kept references and lifts
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
