"""OpenCL for the tracer (slave/tracer.py) and anything else that runs kernels/ sources: the
device a user names, and programs built from kernel files and cached by a key that hashes the
sources and every build option.

Imports pyopencl only when a device is opened, so core stays importable without it.
"""
from __future__ import annotations

import hashlib
import os
import pathlib
import tempfile
import time

from .layout import c_header
from .private import private_folder

KERNEL_DIR = pathlib.Path(__file__).resolve().parent.parent / "kernels"


class OpenCLError(RuntimeError):
    """No OpenCL device, a device that does not exist, or a kernel that does not build."""


def kernel_source(files) -> str:
    """The layout header (core/layout.py c_header: node bits, buffer slots, codes), then the
    kernel files (paths relative to kernels/) concatenated in the given order: each file uses
    only what the ones before it define."""
    return "\n".join([c_header()] + [(KERNEL_DIR / name).read_text() for name in files])


def ensure_pocl_cache_dir() -> None:
    """PoCL needs a writable cache dir even with caching off; give it one of ours: this user's
    alone (0700, owned by this user), since PoCL runs the kernels it finds there. The fallback
    in the temporary folder is per user (kdtrace-pocl-<uid>) and refused if another user made
    it first (a kernel planted there would run as this user). Call before the ICD loader
    initialises PoCL (before the first pyopencl call)."""
    if os.environ.get("POCL_CACHE_DIR"):
        return
    base = pathlib.Path(os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache")
    user = f"-{os.getuid()}" if hasattr(os, "getuid") else ""
    for candidate in (base / "kdtrace" / "pocl",
                      pathlib.Path(tempfile.gettempdir()) / f"kdtrace-pocl{user}"):
        try:
            private_folder(candidate)
            if os.access(candidate, os.W_OK):
                os.environ["POCL_CACHE_DIR"] = str(candidate)
                return
        except OSError:
            continue


def select_device(cl, device, error=OpenCLError):
    """None/"auto": the first GPU, else the first CPU device; "cpu"; "gpu"; or "P:D" indices.
    Of several of the kind wanted, the first that compiles. Raises `error` with the devices
    found when there is no such device."""
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        platforms, reason = [], str(exc)
    else:
        reason = "none installed"
    if not platforms:
        raise error(f"no OpenCL platform found ({reason}); install a GPU driver or "
                    "`pip install pocl-binary-distribution` for the CPU device")
    devices = [(p, d) for p in platforms for d in p.get_devices()]
    spec = "auto" if device is None else str(device).strip().lower()
    if spec in ("auto", "gpu", "cpu"):
        want = {"gpu": (cl.device_type.GPU,), "cpu": (cl.device_type.CPU,),
                "auto": (cl.device_type.GPU, cl.device_type.CPU)}[spec]
        for kind in want:
            candidates = [d for p, d in devices if d.type & kind]
            if candidates:
                return _first_that_compiles(cl, candidates)
        if spec == "auto" and devices:
            return devices[0][1]
        raise error(f"no OpenCL {spec} device; found: "
                    + ", ".join(f"{p.name}: {d.name}" for p, d in devices))
    try:
        p_index, d_index = (int(part) for part in spec.split(":"))
        return platforms[p_index].get_devices()[d_index]
    except (ValueError, IndexError):
        raise error(f"device {device!r} not found: use auto, cpu, gpu or P:D with "
                    f"{len(platforms)} platform(s)") from None


def _first_that_compiles(cl, candidates):
    """The first device that builds a trivial kernel, when there is a choice: a system may
    hold two of a kind, one of them unable to compile here (PoCL 3.0 of the
    pocl-binary-distribution wheel, LLVM 14, does not know AMD Zen 5 CPUs, while the system's
    newer PoCL does). With none that builds, the first, whose kernel build error says why."""
    if len(candidates) == 1:
        return candidates[0]
    for device in candidates:
        try:
            cl.Program(cl.Context([device]), "__kernel void probe(__global int *a) { a[0] = 1; }"
                       ).build(devices=[device])
            return device
        except cl.Error:
            continue
    return candidates[0]


# A kernel build log that means the OpenCL compiler does not know this CPU, and what to do.
UNKNOWN_CPU_LOG = "unknown target CPU"
UNKNOWN_CPU_HINT = ("this OpenCL compiler does not know the machine's CPU (PoCL 3.0 of the "
                    "pocl-binary-distribution wheel, on LLVM 14, predates AMD Zen 5): install a "
                    "newer PoCL, e.g. `apt-get install pocl-opencl-icd` on Debian or Ubuntu, and "
                    "KD Trace takes the first CPU device that builds")


class Programs:
    """Programs built on one device of one context, by build key (a hash of the source and the
    options, also passed as -DKDTRACE_HASH so that no driver cache can serve a stale binary).
    Kernel objects are retrieved once per program: each retrieval makes a new, costly object."""

    def __init__(self, cl, context, device, error=OpenCLError):
        self._cl, self.context, self.device, self._error = cl, context, device, error
        self._built = {}            # (source, options) -> {kernel name: kernel}
        self.build_seconds = 0.0    # wall time of every build so far (the slave logs it)

    def kernels(self, source: str, options) -> dict:
        """The kernels of `source` built with `options`, built on first use. (A str caches its
        hash, so looking up the same source again does not re-read or re-hash it.)"""
        key = (source, tuple(options))
        kernels = self._built.get(key)
        if kernels is None:
            started = time.perf_counter()
            kernels = self._built[key] = self._build(source, list(options))
            self.build_seconds += time.perf_counter() - started
        return kernels

    def _build(self, source: str, options: list) -> dict:
        cl = self._cl
        digest = hashlib.sha256((source + "\0" + " ".join(options)).encode()).hexdigest()[:16]
        options = options + [f"-DKDTRACE_HASH=0x{digest}"]
        program = cl.Program(self.context, source)
        try:
            program.build(options=options, devices=[self.device])
        except cl.Error as exc:
            try:
                log = program.get_build_info(self.device, cl.program_build_info.LOG)
            except cl.Error:
                log = str(exc)
            saved = pathlib.Path(tempfile.gettempdir()) / f"kdtrace-failed-{digest}.cl"
            saved.write_text(source)
            hint = f"\n{UNKNOWN_CPU_HINT}" if UNKNOWN_CPU_LOG in log else ""
            raise self._error(f"kernel build failed on {self.device.name.strip()} with "
                              f"options {' '.join(options)}; source saved to {saved}\n"
                              f"{log}{hint}") from None
        return {k.function_name: k for k in program.all_kernels()}
