"""Intel Open Image Denoise (OIDN) through its C API with ctypes: the RT filter on a rendered
image, guided by its albedo and normal passes, with Cycles' denoising choices (prefilter None /
Fast / Accurate, quality High / Balanced / Fast).

No wheel is needed inside Blender: Blender ships the library and has it loaded. Elsewhere (a
Tracer user, the tests) it is found in an installed `pyoidn` package or `bpy` wheel, or at the
path in $KDTRACE_OIDN_LIBRARY. Where there is none, `find_library` says None and callers keep
the noisy image (docs/denoising.md)."""
from __future__ import annotations

import ctypes
import importlib.util
import os
import pathlib
import sys
import threading

import numpy as np

LIBRARY_ENV = "KDTRACE_OIDN_LIBRARY"
LIBRARY_NAMES = {"linux": "libOpenImageDenoise.so.2", "win32": "OpenImageDenoise.dll",
                 "darwin": "libOpenImageDenoise.2.dylib"}
PREFILTERS = ("NONE", "FAST", "ACCURATE")       # Cycles' Denoising Prefilter
QUALITIES = {"HIGH": 6, "BALANCED": 5, "FAST": 4}   # OIDNQuality (OIDN 2.3+)
_DEVICE_CPU = 1
_FORMAT_FLOAT3 = 3

_lock = threading.Lock()
_library = None          # the loaded library once found (False: looked, none)


class DenoiseError(RuntimeError):
    """OIDN refused: its own message."""


def library_name() -> str:
    return LIBRARY_NAMES.get(sys.platform if sys.platform in LIBRARY_NAMES else "linux")


def _package_folder(name: str, *parts) -> pathlib.Path | None:
    """A folder inside an installed package, found without importing the package."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        return None
    return pathlib.Path(list(spec.submodule_search_locations)[0], *parts)


def _candidates():
    """Library files to try, in order: $KDTRACE_OIDN_LIBRARY, pyoidn's, the bpy wheel's."""
    name = library_name()
    if os.environ.get(LIBRARY_ENV):
        yield pathlib.Path(os.environ[LIBRARY_ENV])
    for folder in (_package_folder("pyoidn", "oidn", "lib"), _package_folder("bpy", "lib")):
        if folder is not None:
            yield folder / name


def find_library():
    """The OIDN library as a ctypes.CDLL, or None. Blender's own (already loaded in Blender's
    process) comes first; the result is kept."""
    global _library
    with _lock:
        if _library is None:
            _library = _load() or False
        return _library or None


def _load():
    if hasattr(os, "RTLD_NOLOAD"):
        try:
            return _declare(ctypes.CDLL(library_name(), mode=os.RTLD_NOLOAD | os.RTLD_NOW))
        except OSError:
            pass
    for path in _candidates():
        if path.is_file():
            try:
                return _declare(ctypes.CDLL(str(path)))
            except OSError:
                continue
    return None


def _declare(lib):
    """The C signatures of the calls used (pointers must not be truncated to int)."""
    p, s, c = ctypes.c_void_p, ctypes.c_size_t, ctypes.c_char_p
    signatures = {
        "oidnNewDevice": ([ctypes.c_int], p), "oidnCommitDevice": ([p], None),
        "oidnReleaseDevice": ([p], None),
        "oidnGetDeviceError": ([p, ctypes.POINTER(c)], ctypes.c_int),
        "oidnNewFilter": ([p, c], p), "oidnCommitFilter": ([p], None),
        "oidnExecuteFilter": ([p], None), "oidnReleaseFilter": ([p], None),
        "oidnSetSharedFilterImage": ([p, c, p, ctypes.c_int, s, s, s, s, s], None),
        "oidnSetFilterBool": ([p, c, ctypes.c_bool], None),
        "oidnSetFilterInt": ([p, c, ctypes.c_int], None),
    }
    for name, (arguments, result) in signatures.items():
        function = getattr(lib, name)
        function.argtypes, function.restype = arguments, result
    return lib


class Denoiser:
    """One OIDN CPU device; denoise() may be called many times (the device's set-up, about
    0.3 s, is paid once). Not for several threads at once."""

    def __init__(self, library=None):
        self.lib = library or find_library()
        if self.lib is None:
            raise DenoiseError("no Open Image Denoise library found (Blender ships one; "
                               f"elsewhere install pyoidn or set ${LIBRARY_ENV})")
        self.device = self.lib.oidnNewDevice(_DEVICE_CPU)
        self.lib.oidnCommitDevice(self.device)
        self._check()

    def _check(self):
        message = ctypes.c_char_p()
        if self.lib.oidnGetDeviceError(self.device, ctypes.byref(message)):
            raise DenoiseError(f"Open Image Denoise: {(message.value or b'').decode(errors='replace')}")

    def denoise(self, color: np.ndarray, albedo: np.ndarray | None = None,
                normal: np.ndarray | None = None, prefilter: str = "ACCURATE",
                quality: str = "HIGH", hdr: bool = True) -> np.ndarray:
        """The denoised (h, w, 3) float32 image of `color` (h, w, 3 or 4: alpha is kept as
        is), guided by `albedo` and `normal` (h, w, 3; a normal needs the albedo, as in OIDN).
        prefilter: Cycles' choice: NONE (the guides are clean), FAST (the guides are denoised
        together with the image), ACCURATE (each guide is denoised first)."""
        if prefilter not in PREFILTERS:
            raise ValueError(f"prefilter must be one of {PREFILTERS}, got {prefilter!r}")
        if quality not in QUALITIES:
            raise ValueError(f"quality must be one of {tuple(QUALITIES)}, got {quality!r}")
        if normal is not None and albedo is None:
            raise ValueError("a normal guide needs an albedo guide")
        height, width = color.shape[:2]
        rgb = np.ascontiguousarray(color[..., :3], np.float32)
        guides = {name: np.ascontiguousarray(array, np.float32)
                  for name, array in (("albedo", albedo), ("normal", normal)) if array is not None}
        for name, array in guides.items():
            if array.shape != (height, width, 3):
                raise ValueError(f"{name} must be ({height}, {width}, 3), got {array.shape}")
        if prefilter == "ACCURATE":
            guides = {name: self._run({name: array}, name, quality, hdr=None)
                      for name, array in guides.items()}
        output = self._run({"color": rgb, **guides}, "color", quality, hdr=hdr,
                           clean_aux=bool(guides) and prefilter != "FAST")
        if color.shape[-1] == 4:
            output = np.concatenate([output, color[..., 3:].astype(np.float32)], axis=-1)
        return output

    def _run(self, images: dict, main: str, quality: str, hdr: bool | None,
             clean_aux: bool = False) -> np.ndarray:
        """One RT filter over `images` (name -> (h, w, 3) float32), its output the denoised
        `main` image; hdr None: a filter of one guide (albedo or normal) alone."""
        height, width = images[main].shape[:2]
        output = np.empty((height, width, 3), np.float32)
        lib = self.lib
        handle = lib.oidnNewFilter(self.device, b"RT")
        try:
            for name, array in [*images.items(), ("output", output)]:
                lib.oidnSetSharedFilterImage(handle, name.encode(), array.ctypes.data,
                                             _FORMAT_FLOAT3, width, height, 0, 0, 0)
            if hdr is not None:
                lib.oidnSetFilterBool(handle, b"hdr", hdr)
            if clean_aux:
                lib.oidnSetFilterBool(handle, b"cleanAux", True)
            lib.oidnSetFilterInt(handle, b"quality", QUALITIES[quality])
            lib.oidnCommitFilter(handle)
            self._check()
            lib.oidnExecuteFilter(handle)
            self._check()
        finally:
            lib.oidnReleaseFilter(handle)
        return output

    def close(self):
        if self.device:
            self.lib.oidnReleaseDevice(self.device)
            self.device = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
