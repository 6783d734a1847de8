"""What a scene from the network is held to: `SceneError`, the limits on what a scene may
hold, the checks of JSON numbers that the `from_dict` constructors of core/scene/model.py use,
and `check_node_program`, the check of a material's node program rows.
"""
from __future__ import annotations

import math

import numpy as np

# What a scene may hold (Geometry, Shading and View of core/scene/model.py check against these).
MAX_MATERIALS = 65535
MAX_LIGHTS = 4096
MAX_TEXTURES = 4096
# Texels a texture may have per side: then w x h <= 2^32, and the kernel's texel index
# (kernels/shade/shading.cl `texel`) is exact. Blender's images are at most 65536 per side too.
MAX_TEXTURE_SIDE = 65536
# Triangles of a scene: the kernels address a triangle's corner rows as 3 * tri + k and its
# TRIANGLE record as TRIANGLE_SIZE * tri in 32 bits (a billion triangles is 12 GiB of indices
# alone, far past what a slave takes).
MAX_TRIANGLES = 1 << 30
MAX_RADIANCE = 1e30
MAX_NODE_ROWS = 1 << 20
MAX_IMAGE_SIDE = 65536


class SceneError(ValueError):
    """Scene content that cannot be rendered; the message names the problem."""


def finite_floats(value, count: int, what: str) -> tuple:
    try:
        numbers = tuple(float(v) for v in value)
    except (TypeError, ValueError, OverflowError):     # OverflowError: a JSON integer past float
        raise SceneError(f"{what} must be {count} numbers") from None
    if len(numbers) != count or not all(math.isfinite(v) for v in numbers):
        raise SceneError(f"{what} must be {count} finite numbers")
    return numbers


def finite_float(value, what: str, low: float = -math.inf, high: float = math.inf) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        raise SceneError(f"{what} must be a number") from None
    if not math.isfinite(number) or not low <= number <= high:
        raise SceneError(f"{what} must be a finite number in [{low}, {high}], got {value!r}")
    return number


def checked_int(value, what: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise SceneError(f"{what} must be an integer in [{low}, {high}], got {value!r}")
    return value


def same_arrays(a: dict, b: dict) -> bool:
    """Whether two dicts of contiguous arrays have the same names, dtypes, shapes and bytes
    (bit for bit: -0.0 is not 0.0, a NaN equals itself), without copying either."""
    if a.keys() != b.keys():
        return False
    for name, x in a.items():
        y = b[name]
        if x.dtype != y.dtype or x.shape != y.shape:
            return False
        if x is y or not x.size:
            continue
        as_bits = np.dtype(f"u{x.itemsize}") if x.itemsize in (1, 2, 4, 8) else np.dtype("u1")
        if not np.array_equal(x.reshape(-1).view(as_bits), y.reshape(-1).view(as_bits)):
            return False
    return True



def check_node_program(rows, starts) -> np.ndarray:
    """The node program rows from the network, checked: whole-number operations, registers
    and operands in range, normal map spaces known, every table (colour ramps, coordinate and
    object normal transforms) inside the rows, and from each start in `starts`
    (>= 0) instructions up to an END (the kernel runs them so). A program's ramp tables
    follow its END (addon/node_program.py compiles them).

    In time linear in the rows and starts (issue 39: a check per start, and a search of every
    table at every row, took minutes on a 16 MiB frame): one walk over the rows finds the
    instructions (a table's rows are skipped where an END is followed by them), then the
    instructions' fields and each start's way to its END are checked with numpy. The first
    problem by row is reported, as a walk that checked each row in full would."""
    from ..layout import (NODE_NORMAL_SPACE_CODES, NODE_OBJECT_NORMAL_SPACES, NODE_OP_CODES,
                          NODE_OUT_CODES, NODE_RAMP_SIZE, NODE_REF_REGISTER, NODE_REGISTERS,
                          NODE_TRANSFORM_SIZE)
    tables = {NODE_OP_CODES["RAMP"]: NODE_RAMP_SIZE, NODE_OP_CODES["TRANSFORM"]: NODE_TRANSFORM_SIZE,
              NODE_OP_CODES["NORMAL_MAP"]: NODE_TRANSFORM_SIZE,     # object space: its rows
              NODE_OP_CODES["OBJECT_INFO"]: NODE_TRANSFORM_SIZE}
    normal_map, end_op = NODE_OP_CODES["NORMAL_MAP"], NODE_OP_CODES["END"]
    object_spaces = {float(NODE_NORMAL_SPACE_CODES[k]) for k in NODE_OBJECT_NORMAL_SPACES}
    spaces = {float(v) for v in NODE_NORMAL_SPACE_CODES.values()}
    operations = {float(v) for v in NODE_OP_CODES.values()}
    if not isinstance(rows, list) or len(rows) > MAX_NODE_ROWS or len(rows) % 2:
        raise SceneError("node_program must be an even number of rows")
    program = _node_rows(rows)
    n = len(program)
    # The walk: instruction rows, tables by their first row -> the row after the longest that
    # starts there (a table is declared by an instruction before it, so before the walk gets
    # there). Stops at the first problem it can see: an operation, a normal map space, a table.
    ops, tables_at, spaces_at = (program[k::2, c].tolist() for k, c in ((0, 0), (1, 1), (1, 2)))
    pc, table_end, pcs, problem = 0, {}, [], None
    while pc < n:
        op, i = ops[pc >> 1], pc >> 1
        if op not in operations:
            problem = (pc, f"node program row {pc}: unknown operation {op}")
            break
        op = int(op)
        if op == normal_map and spaces_at[i] not in spaces:
            problem = (pc, f"node program row {pc}: unknown normal map space {spaces_at[i]}")
            break
        if op in tables and (op != normal_map or spaces_at[i] in object_spaces):
            start = tables_at[i]
            if start != int(start) or not 2 <= start or not pc + start <= n - tables[op]:
                problem = (pc, f"node program row {pc}: table outside the program")
                break
            first = pc + int(start)
            table_end[first] = max(table_end.get(first, 0), first + tables[op])
        pcs.append(pc)
        pc += 2
        while pc in table_end:          # the tables after an END, whatever their order
            pc = table_end[pc]
        if pc % 2:
            problem = (pc - 0.5, "node program tables must end on an even row")
            break
    pcs = np.array(pcs, np.int64)
    # The fields of the instructions the walk passed, each row's problems in the order above.
    w0, w1 = program[pcs], program[pcs + 1]
    op = w0[:, 0]
    limit = NODE_REGISTERS * NODE_REF_REGISTER

    def bad_ref(r):
        return (r != np.trunc(r)) | (r < 0) | (r >= limit)
    const = op == NODE_OP_CODES["CONST"]
    # A CONST's second row is its value (the kernel reads its first lane as an operand too:
    # kernels/shade/nodes.cl node_operand clamps it); its register and first-row operands are
    # checked as every instruction's.
    registers = (op != end_op) & (bad_ref(w0[:, 2]) | bad_ref(w0[:, 3]) | (~const & bad_ref(w1[:, 0]))
                                  | ~((w0[:, 1] >= 0) & (w0[:, 1] < NODE_REGISTERS)))
    outs = (op == NODE_OP_CODES["OUT"]) & ~np.isin(w1[:, 1], list(NODE_OUT_CODES.values()))
    images = np.isin(op, [NODE_OP_CODES["IMAGE"], NODE_OP_CODES["ATTRIBUTE"]]) & ~(
        (w1[:, 1] == np.trunc(w1[:, 1])) & (w1[:, 1] >= 0) & (w1[:, 1] < MAX_TEXTURES))
    bad = np.flatnonzero(registers | outs | images)
    if len(bad) and (problem is None or pcs[bad[0]] < problem[0]):
        k, row = bad[0], int(pcs[bad[0]])
        what = ("register out of range" if registers[k] else
                f"unknown BSDF input {w1[k, 1]}" if outs[k] else f"bad texture {w1[k, 1]}")
        raise SceneError(f"node program row {row}: {what}")
    if problem is not None:
        raise SceneError(problem[1])
    # From each start, consecutive instruction rows up to an END, at most 1024 instructions
    # before it (the kernel runs at most that many): the next END at or after it, and no
    # gap (a table, the program's end) before that END.
    starts = np.unique(np.asarray([int(v) for v in starts if v >= 0], np.int64))
    at = np.searchsorted(pcs, starts)
    found = at < len(pcs)
    found[found] = pcs[at[found]] == starts[found]
    ends = np.flatnonzero(op == end_op)
    gaps = np.append(np.flatnonzero(np.diff(pcs) != 2), len(pcs) - 1)   # last of each run
    k = np.minimum(at, max(len(pcs) - 1, 0))
    end_at = np.append(ends, len(pcs))[np.searchsorted(ends, k)]
    gap_at = gaps[np.minimum(np.searchsorted(gaps, k), len(gaps) - 1)] if len(pcs) else k
    ok = found & (end_at < len(pcs)) & (end_at <= gap_at) & (end_at - k <= 1024)
    if not ok.all():
        start = int(starts[np.flatnonzero(~ok)[0]])
        raise SceneError(f"the node program at row {start} does not end (with END) in its rows")
    return program


def _node_rows(rows) -> np.ndarray:
    """The rows as float32 (n, 4), each 4 finite numbers (as finite_floats takes them)."""
    if not rows:
        return np.zeros((0, 4), np.float32)
    try:
        program = np.array(rows, np.float64)
    except (TypeError, ValueError, OverflowError):
        program = None
    if program is None or program.shape != (len(rows), 4) or not np.isfinite(program).all():
        program = np.array([finite_floats(r, 4, "node program row") for r in rows])
    return program.astype(np.float32)

