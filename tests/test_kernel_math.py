"""The geometric functions of kernels/trace/trace.cl (kd_dot, kd_cross, kd_length,
kd_normalize, kd_next_float): one formula on every device, in place of OpenCL's builtins, whose
rounding each implementation chooses. Checked against float64 references on ordinary and
extreme vectors, and on the sources: no tracer kernel calls the builtins."""
import re

import numpy as np
import pytest

from kdtrace.core.opencl import KERNEL_DIR, kernel_source
from kdtrace.slave.tracer import KERNEL_FILES
from tests.opencl_programs import programs_on

PROBE = r"""
__kernel void probe(__global const float *a, __global const float *b, __global float *out)
{
    uint i = get_global_id(0);
    float3 x = vload3(i, a), y = vload3(i, b);
    __global float *o = out + 12 * i;
    o[0] = kd_dot(x, y);
    vstore3(kd_cross(x, y), 0, o + 1);
    o[4] = kd_length(x);
    vstore3(kd_normalize(x), 0, o + 5);
    o[8] = kd_next_float(x.x, true);
    o[9] = kd_next_float(x.x, false);
    o[10] = kd_dot4((float4)(x, y.x), (float4)(y, x.x));
    o[11] = 0.0f;
}
"""

BUILTINS = re.compile(r"(?<![\w.])(dot|cross|length|normalize|nextafter)\s*\(")


@pytest.fixture(scope="module")
def probe():
    cl, context, queue, programs = programs_on("cpu")
    source = kernel_source(["trace/trace.cl"]) + PROBE
    kernel = programs.kernels(source, ["-DKD_STACK_SIZE=32"])["probe"]

    def run(a, b):
        a, b = np.ascontiguousarray(a, np.float32), np.ascontiguousarray(b, np.float32)
        out = np.empty((len(a), 12), np.float32)
        flags = cl.mem_flags
        bufs = [cl.Buffer(context, flags.READ_ONLY | flags.COPY_HOST_PTR, hostbuf=x) for x in (a, b)]
        out_buf = cl.Buffer(context, flags.WRITE_ONLY, out.nbytes)
        kernel(queue, (len(a),), None, *bufs, out_buf)
        cl.enqueue_copy(queue, out, out_buf)
        queue.finish()
        return out
    return run


def test_tracer_kernels_do_not_call_the_builtins():
    for name in KERNEL_FILES:
        code = re.sub(r"//[^\n]*|/\*.*?\*/", "", (KERNEL_DIR / name).read_text(), flags=re.S)
        calls = sorted({m.group(1) for m in BUILTINS.finditer(code)})
        assert not calls, f"kernels/{name} calls OpenCL's {', '.join(calls)}: use the kd_ versions"


def test_dot_and_cross_round_as_written(probe):
    rng = np.random.default_rng(3)
    a = (rng.standard_normal((2000, 3)) * 10.0 ** rng.integers(-6, 6, (2000, 1))).astype(np.float32)
    b = (rng.standard_normal((2000, 3)) * 10.0 ** rng.integers(-6, 6, (2000, 1))).astype(np.float32)
    out = probe(a, b)
    x, y = a.T, b.T
    with np.errstate(all="ignore"):     # float32 operations in the kernel's order
        dot = (x[0] * y[0] + x[1] * y[1]) + x[2] * y[2]
        cross = np.stack([x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2],
                          x[0] * y[1] - x[1] * y[0]], 1)
        dot4 = dot + y[0] * x[0]
    assert np.array_equal(out[:, 0], dot)
    assert np.array_equal(out[:, 1:4], cross)
    assert np.array_equal(out[:, 10], dot4)


def test_length_and_normalize_on_ordinary_and_extreme_vectors(probe):
    rng = np.random.default_rng(4)
    scales = 10.0 ** np.array([0, -18, -25, -40, 18, 25, 35], np.float64)   # squares leave
    v = np.concatenate([rng.standard_normal((300, 3)) * s for s in scales])  # float's range
    v = np.concatenate([v, [[1e-45, 0, 0], [0, -2e38, 2e38], [0, 0, 0]]]).astype(np.float32)
    out = probe(v, v)
    exact = np.linalg.norm(v.astype(np.float64), axis=1)
    nonzero = exact > 0
    assert np.all(np.abs(out[:, 4] - exact) <= 4e-7 * exact + 1.5e-45)   # + a denormal's step
    unit = out[nonzero, 5:8].astype(np.float64)
    assert np.all(np.abs(np.linalg.norm(unit, axis=1) - 1) < 1e-6)
    assert np.all(np.abs(unit - v[nonzero] / exact[nonzero, None]) < 1e-6)
    assert np.array_equal(out[~nonzero, 5:8], v[~nonzero])    # the zero vector stays zero
    special = np.array([[np.inf, 1, 0], [np.nan, 1, 0], [0, 0, -np.inf]], np.float32)
    lengths = probe(special, special)[:, 4]
    assert lengths[0] == np.inf and np.isnan(lengths[1]) and lengths[2] == np.inf


def test_next_float_is_nextafter_to_infinity(probe):
    f32 = np.finfo(np.float32)
    x = np.array([0.0, -0.0, 1.0, -1.0, 1.5e-45, -1.5e-45, f32.tiny, f32.max, -f32.max, 3.7e5,
                  -2.2e-7, np.inf, -np.inf], np.float32)
    out = probe(np.stack([x, x, x], 1), np.ones((len(x), 3), np.float32))
    up, down = out[:, 8], out[:, 9]
    with np.errstate(over="ignore"):    # numpy warns on the step from max to inf
        assert np.array_equal(up.view(np.uint32), np.nextafter(x, np.float32(np.inf)).view(np.uint32))
        assert np.array_equal(down.view(np.uint32),
                              np.nextafter(x, np.float32(-np.inf)).view(np.uint32))
    nan = probe(np.full((1, 3), np.nan, np.float32), np.ones((1, 3), np.float32))
    assert np.isnan(nan[0, 8]) and np.isnan(nan[0, 9])
