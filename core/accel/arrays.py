"""numpy helpers over index arrays that the builders, the compaction, the validator and the
treelet order share: prefix sums, concatenated ranges and runs of equal values."""
from __future__ import annotations

import numpy as np


def exclusive_cumsum(counts) -> np.ndarray:
    """int64 [0, c0, c0 + c1, ...]: len(counts) + 1 values, the last one the total."""
    out = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=out[1:])
    return out


def concat_ranges(starts, lengths) -> np.ndarray:
    """Concatenation of arange(s, s + n) for every (s, n)."""
    lengths = np.asarray(lengths, np.int64)
    total = int(lengths.sum())
    if not total:
        return np.zeros(0, np.int64)
    shift = np.asarray(starts, np.int64) - exclusive_cumsum(lengths)[:-1]
    return np.arange(total, dtype=np.int64) + np.repeat(shift, lengths)


def run_starts(*keys) -> np.ndarray:
    """Start positions of runs of equal consecutive key tuples."""
    n = len(keys[0])
    if not n:
        return np.zeros(0, np.int64)
    change = np.zeros(n, bool)
    change[0] = True
    for key in keys:
        change[1:] |= key[1:] != key[:-1]
    return np.flatnonzero(change)


def run_lengths(values) -> np.ndarray:
    """How often each distinct value occurs (np.unique's counts), without a sort where the
    values come sorted (the kernel compaction's lifts come by node)."""
    values = np.asarray(values)
    if len(values) and not (values[1:] >= values[:-1]).all():
        return np.unique(values, return_counts=True)[1]
    return np.diff(np.append(run_starts(values), len(values)))


def distinct_count(values) -> int:
    """How many distinct values (non-negative integers) there are: marks in a bool array,
    cheaper than np.bincount's counts (docs/kdtree_native.md)."""
    values = np.asarray(values)
    seen = np.zeros(int(values.max(initial=-1)) + 1, bool)
    seen[values] = True
    return int(np.count_nonzero(seen))
