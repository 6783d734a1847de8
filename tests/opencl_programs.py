"""An OpenCL device for tests that build small kernels of their own around the kernel files."""
from kdtrace.core.opencl import Programs, ensure_pocl_cache_dir, select_device


def programs_on(device="cpu"):
    """(pyopencl, context, queue, Programs) on `device` (select_device's spec)."""
    ensure_pocl_cache_dir()
    import pyopencl as cl
    dev = select_device(cl, device)
    context = cl.Context([dev])
    return cl, context, cl.CommandQueue(context), Programs(cl, context, dev)
