"""Exit 0 when an OpenCL CPU device here compiles a kernel (printing which), 1 with the reason
when none does. .ci/setup runs it to decide whether the system's PoCL is needed."""
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent))
from kdtrace.core.opencl import (OpenCLError, Programs, ensure_pocl_cache_dir,  # noqa: E402
                                 select_device)

ensure_pocl_cache_dir()
import pyopencl as cl  # noqa: E402

try:
    device = select_device(cl, "cpu")
    Programs(cl, cl.Context([device]), device).kernels("__kernel void probe(void) {}", [])
except OpenCLError as exc:
    sys.exit(f"no OpenCL CPU device compiles here: {exc}")
print(f"OpenCL CPU device: {device.name.strip()} ({device.platform.version.strip()})")
