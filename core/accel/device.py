"""One OpenCL device as the kd-tree builder (binned.py) and the compaction (compact_cl.py)
use it: its context and in-order queue, programs built once, device memory from a pool
(buffer_pool.py), launches in pieces with the progress callback between them, and reads.

Everything that touches a buffer is a command on the one in-order queue, so the commands of a
pooled region's next user run after those of its last one, and a read sees every launch
before it. pyopencl is imported only when a DeviceContext is made.
"""
from __future__ import annotations

import functools

import numpy as np

from .buffer_pool import MIN_POOLED_BYTES, BufferPool

FILL_BYTES = 64 << 20      # zeros(): fills of this many bytes, with the heartbeat between


class DeviceContext:
    """An OpenCL device, its context, queue, programs and buffer pool.

    device: a core.opencl.select_device spec (None: a GPU if any, else the CPU), which must
    have double precision (cl_khr_fp64: the clipping and the compaction's areas; OpenCLError
    otherwise); profile_kernels: each launch's event is kept, so that kernel_times() can sum device time
    per kernel (for the benchmark's profile; off otherwise).
    """

    def __init__(self, device=None, profile_kernels: bool = False):
        from ..opencl import OpenCLError, Programs, ensure_pocl_cache_dir, select_device
        ensure_pocl_cache_dir()
        import pyopencl as cl
        self._cl = cl
        self.device = select_device(cl, device)
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.context, properties=(
            cl.command_queue_properties.PROFILING_ENABLE if profile_kernels else 0))
        self._events = [] if profile_kernels else None
        self._programs = Programs(cl, self.context, self.device)
        self.buffers = BufferPool(cl, self.context, self.device)
        self.is_cpu = bool(self.device.type & cl.device_type.CPU)
        if "cl_khr_fp64" not in self.device.extensions.split():
            raise OpenCLError(f"{self.device_name} has no double precision (cl_khr_fp64), "
                              "which the kd-tree build and compaction need")
        self._progress = None          # the running work's callback (reporting, heartbeat)
        self._last_progress = (0.0, "")

    @property
    def device_name(self) -> str:
        return f"{self.device.platform.name.strip()}: {self.device.name.strip()}"

    @property
    def compute_units(self) -> int:
        return int(self.device.max_compute_units)

    def kernels(self, source: str, options) -> dict:
        """The kernels of `source` built with `options`, built once."""
        return self._programs.kernels(source, list(options))

    # -- progress --------------------------------------------------------------------------
    def reporting(self, progress):
        """A progress callback that also serves heartbeat() until replaced."""
        if progress is None:
            self._progress = None
            return lambda fraction, message: None

        def report(fraction, message):
            self._last_progress = (fraction, message)
            progress(fraction, message)
        self._progress = progress
        return report

    def heartbeat(self):
        """Wait for the queued commands, then call the current progress callback with the last
        fraction and message: between steps, its exception (Esc) stops the work at once."""
        if self._progress is not None:
            self.queue.finish()
            self._progress(*self._last_progress)

    # -- buffers ---------------------------------------------------------------------------
    def buffer(self, array=None, nbytes=None):
        """A READ_WRITE buffer of nbytes (contents undefined), or holding a copy of `array`,
        from the pool (buffer_pool.py)."""
        cl = self._cl
        if array is None:
            return self.buffers.take(int(nbytes))
        array = np.ascontiguousarray(array)
        if array.nbytes < MIN_POOLED_BYTES:
            if array.nbytes == 0:
                array = np.zeros(4, np.uint8)
            return cl.Buffer(self.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR,
                             hostbuf=array)
        buffer = self.buffers.take(array.nbytes)
        cl.enqueue_copy(self.queue, buffer, array)        # blocking: `array` may go after
        return buffer

    def standalone(self, nbytes: int):
        """A buffer of its own, outside the pool: for results that outlive the work (take)."""
        return self.buffers.standalone(nbytes)

    def view(self, array):
        """A read-only buffer of a host array: the array itself on CPU devices (no copy; the
        array must outlive the buffer)."""
        cl = self._cl
        array = np.ascontiguousarray(array)
        if self.is_cpu and array.nbytes:
            return cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR,
                             hostbuf=array)
        return self.buffer(array)

    def clear(self, buffer, nbytes: int):
        """Zeros over the buffer's first nbytes, filled in pieces: a fresh buffer's pages are
        first touched by the fill, and Esc is seen between the pieces."""
        for start in range(0, nbytes, FILL_BYTES):
            self._cl.enqueue_fill_buffer(self.queue, buffer, np.uint8(0), start,
                                         min(FILL_BYTES, nbytes - start))
            if nbytes > FILL_BYTES:
                self.heartbeat()

    def zeros(self, nbytes):
        """A new buffer of zeros (from the pool)."""
        nbytes = max(int(nbytes), 4)
        buffer = self.buffer(nbytes=nbytes)
        self.clear(buffer, nbytes)
        return buffer

    def copy(self, dest, src, nbytes: int):
        """The first nbytes of buffer src into buffer dest (queued)."""
        self._cl.enqueue_copy(self.queue, dest, src, byte_count=int(nbytes))

    def release(self) -> None:
        """Let the pool's memory go (at the end of a build or compaction)."""
        self.buffers.release()

    # -- launches --------------------------------------------------------------------------
    def run(self, kernel, count, *args, local_size: int, piece=None):
        """kernel over `count` work-items (padded to the work-group size; kernels skip ids
        past their count). With `piece`, in launches of that many work-items (by global
        offset), each waited for and followed by heartbeat(): the progress callback, whose
        exception (Esc) then stops the work within one piece."""
        if count == 0:
            return
        ls = local_size
        count = int(count)
        if piece is None or count <= piece:
            self._launched(kernel, kernel(self.queue, (-(-count // ls) * ls,), (ls,), *args))
            return
        piece = -(-int(piece) // ls) * ls
        for start in range(0, count, piece):
            size = -(-min(piece, count - start) // ls) * ls
            self._launched(kernel, kernel(self.queue, (size,), (ls,), *args,
                                          global_offset=(start,)))
            self.heartbeat()

    def _launched(self, kernel, event):
        if self._events is not None:
            self._events.append((kernel.function_name, event))

    def finish(self):
        """Wait for every queued command."""
        self.queue.finish()

    def kernel_times(self) -> dict:
        """Device seconds and launches per kernel since the last call (profile_kernels only)."""
        self.queue.finish()
        times = {}
        for name, event in self._events or ():
            seconds, launches = times.get(name, (0.0, 0))
            times[name] = (seconds + (event.profile.end - event.profile.start) * 1e-9, launches + 1)
        if self._events is not None:
            self._events.clear()
        return times

    # -- reads -----------------------------------------------------------------------------
    def read(self, buffer, dtype, shape) -> np.ndarray:
        """A copy of the buffer's first values as a host array of `shape`."""
        out = np.empty(shape, dtype)
        if out.nbytes:
            self._cl.enqueue_copy(self.queue, out, buffer)
        return out

    def value_at(self, buffer, index, dtype=np.uint32) -> int:
        out = np.empty(1, dtype)
        self._cl.enqueue_copy(self.queue, out, buffer, src_offset=int(index) * out.itemsize)
        return int(out[0])

    def take(self, buffer, dtype, shape) -> np.ndarray:
        """A buffer's contents as a host array, for a buffer no kernel uses again: on a CPU
        device the buffer's own memory, mapped (a copy of a tree's arrays, into pages first
        touched by the copy, took longer than the kernels that wrote them)."""
        if not self.is_cpu or not np.prod(shape):
            return self.read(buffer, dtype, shape)
        cl = self._cl
        array, _ = cl.enqueue_map_buffer(self.queue, buffer, cl.map_flags.READ | cl.map_flags.WRITE,
                                         0, shape, dtype, is_blocking=True)
        return array


@functools.lru_cache(maxsize=None)
def device_for(spec) -> DeviceContext:
    """The DeviceContext of a core.opencl.select_device spec, made once per spec."""
    return DeviceContext(spec)
