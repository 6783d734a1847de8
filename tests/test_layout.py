"""The host/kernel layouts (core/layout.py): the generated header against the Python tables on
the OpenCL device, and no kernel file with layout numbers of its own."""
from __future__ import annotations

import re

import numpy as np
import pytest

from core import layout
from core.opencl import KERNEL_DIR, Programs, ensure_pocl_cache_dir, select_device

FIELDS = [f for node in layout.NODE_FORMATS for f in node.fields]


def header_numbers() -> dict:
    """Every number the header should define, by C name, as the tables give it."""
    numbers = {}
    for node in layout.NODE_FORMATS:
        numbers.update({c.name: c.value for c in node.constants})
        for f in node.fields:
            numbers.update({f"{f.name}_SHIFT": f.shift, f"{f.name}_BITS": f.bits,
                            f"{f.name}_MAX": f.max})
            if f.bits == 1:
                numbers[f"{f.name}_BIT"] = f.bit
    for codes in layout.CODES:
        numbers.update({f"{codes.prefix}_{name}": value for name, value in codes.codes.items()})
    for record in layout.RECORDS:
        numbers[f"{record.prefix}_SIZE"] = record.size
        numbers.update({f"{record.prefix}_{s.name.upper()}_SLOT": s.index for s in record.slots})
    for table in layout.COLUMNS:
        numbers[f"{table.prefix}_COLUMNS"] = len(table.columns)
        numbers.update({f"{table.prefix}_{name.upper()}": table.index(name)
                        for name in table.columns})
    return numbers


@pytest.fixture(scope="module")
def device():
    ensure_pocl_cache_dir()
    import pyopencl as cl
    dev = select_device(cl, None)
    context = cl.Context([dev])
    return cl, context, cl.CommandQueue(context), Programs(cl, context, dev)


def run_kernel(device, source, name, out_count, *inputs, dtype=np.uint32):
    """Build header + source, run `name(out, inputs...)` on one work-item, return out."""
    cl, context, queue, programs = device
    kernel = programs.kernels(layout.c_header() + source, [])[name]
    mf = cl.mem_flags
    out = np.zeros(out_count, dtype)
    out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
    buffers = [cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a))
               for a in inputs]
    kernel(queue, (1,), None, out_buf, *buffers)
    cl.enqueue_copy(queue, out, out_buf)
    queue.finish()
    return out


def test_header_numbers_match_the_tables(device):
    numbers = header_numbers()
    body = "\n".join(f"    out[{i}] = (uint)({name});" for i, name in enumerate(numbers))
    source = f"__kernel void numbers(__global uint *out)\n{{\n{body}\n}}\n"
    got = run_kernel(device, source, "numbers", len(numbers))
    assert dict(zip(numbers, got.tolist())) == numbers
    # Every number in the header is one of these (nothing defined that the tables lack).
    defined = set(re.findall(r"^#define (\w+)(?: |$)", layout.c_header(), re.M))
    assert defined == set(numbers) | {"KDTRACE_LAYOUT"}


def test_node_field_macros_decode_and_encode_as_the_tables(device):
    rng = np.random.default_rng(5)
    words = np.concatenate([rng.integers(0, 1 << 32, 200, dtype=np.uint64),
                            [0, 0xFFFFFFFF, 1, 1 << 31]]).astype(np.uint32)
    n = len(words)
    lines = []
    for k, f in enumerate(FIELDS):
        lines.append(f"        out[(2 * {k}) * {n} + i] = {f.name}(w);")
        lines.append(f"        out[(2 * {k} + 1) * {n} + i] = {f.name}_PUT({f.name}(w));")
    body = "\n".join(lines)
    source = (f"__kernel void fields(__global uint *out, __global const uint *words)\n{{\n"
              f"    for (uint i = 0; i < {n}u; ++i) {{\n        uint w = words[i];\n{body}\n"
              f"    }}\n}}\n")
    got = run_kernel(device, source, "fields", 2 * len(FIELDS) * n, words).reshape(-1, n)
    for k, f in enumerate(FIELDS):
        value = f.get(words.astype(np.int64))
        np.testing.assert_array_equal(got[2 * k], value, err_msg=f.name)
        np.testing.assert_array_equal(got[2 * k + 1], f.put(value) & 0xFFFFFFFF, err_msg=f.name)
        assert f.put(f.max) >> f.shift == f.max and f.shift + f.bits <= 32


def test_node_fields_tile_their_words():
    """Within each kind of node word the fields do not overlap; the tag is bits 0-1 of all."""
    kinds = {"plain": [layout.PLAIN_TAG, layout.PLAIN_FIELD],
             "inner": [layout.TAG, layout.INNER_REF, layout.INNER_EMPTY_BELOW,
                       layout.INNER_EMPTY_ABOVE, layout.INNER_GROUP],
             "leaf32": [layout.TAG, layout.LEAF_WIDE, layout.LEAF32_COUNT],
             "leaf16": [layout.TAG, layout.LEAF_WIDE, layout.LEAF16_COUNT, layout.LEAF16_BASE]}
    for kind, fields in kinds.items():
        masks = [f.put(f.max) for f in fields]
        assert sum(masks) == 0xFFFFFFFF and np.bitwise_or.reduce(masks) == 0xFFFFFFFF, kind


# Names under the layout's prefixes that kernels define for their own purposes (not layouts).
LAYOUT_PREFIXES = ("KD_", "LIGHT_", "MATERIAL_", "CAMERA_", "BOUNDS_", "TRIANGLE_", "ACCUM_",
                   "STATS_", "TEXTURE_SIZE_")


def kernel_files():
    files = sorted(KERNEL_DIR.rglob("*.cl"))
    assert files
    return files


def test_no_kernel_defines_layout_numbers():
    """Kernels take layout numbers from the header only: none defines a header name again, nor
    an integer constant under a layout prefix (a private node bit, slot count or code)."""
    header = set(re.findall(r"^#define (\w+)", layout.c_header(), re.M))
    own_number = re.compile(r"^\s*#\s*define\s+((?:%s)\w*)\s+\(?(0x[0-9a-fA-F]+|\d+)u?\)?\s*(//.*)?$"
                            % "|".join(LAYOUT_PREFIXES), re.M)
    for path in kernel_files():
        text = path.read_text()
        defined = set(re.findall(r"^\s*#\s*define\s+(\w+)", text, re.M))
        assert not defined & header, f"{path.name} defines {sorted(defined & header)} again"
        assert not own_number.findall(text), f"{path.name} defines {own_number.findall(text)}"
