"""How a tile's passes travel in a TILE_RESULT: encode_tile (the slave), decode_tile (the
master's check of a tile, written straight into the frame), the 8-bit preview's code tables
and the zlib compression. Which passes and payload a frame may ask for, and what a tile pixel
may take on the wire, are protocol.py's (TILE_PASSES, PASS_CODING, PAYLOADS, pass_dtypes,
tile_bytes_per_pixel)."""
from __future__ import annotations

import functools
import math
import zlib

import numpy as np

from .protocol import ALL_PASSES, PASS_CODING, TILE_PASSES, ProtocolError, pass_dtypes

# The payloads (protocol.PAYLOADS) that a frame's passes travel in:
#   f32  every pass float32 (exact);
#   f16  float16 but the "exact" passes (PASS_CODING), float32 (depth's miss value 1e10 does
#        not fit float16);
#   u8   an 8-bit preview: combined's colour and the colour passes as sRGB codes, its alpha and
#        the normals linear codes, the exact passes float32. Decoding is a table lookup, so a
#        decoded value is exactly the centre of its code (PREVIEW_* tables below): "exact to
#        its quantisation".
# With compression on, the slave deflates the passes (zlib level 1) and sends one u1 array
# "zlib" instead, but only when that saves at least 10 %; the master inflates it with a bound
# of exactly the expected size, so a "zip bomb" costs nothing. The master checks a tile (names,
# shapes, dtypes, finite values) before it writes it straight into the frame (decode_tile's
# `out`): no intermediate float32 copy per tile.

F16_MAX = 65504.0


def _srgb_to_linear(code: np.ndarray) -> np.ndarray:
    c = code / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


# The 8-bit preview's codes. Colour: code k decodes to PREVIEW_COLOR[k] = the linear value of
# sRGB k/255; a value encodes to the code whose sRGB interval holds it, found by comparison
# against float64 bounds (no transcendental on the slave, so every slave gives the same codes).
# Alpha and normal: linear codes, rounded in float64.
PREVIEW_COLOR = _srgb_to_linear(np.arange(256.0)).astype(np.float32)
PREVIEW_COLOR_BOUNDS = _srgb_to_linear(np.arange(255.0) + 0.5)          # code k below bound k
PREVIEW_ALPHA = (np.arange(256.0) / 255.0).astype(np.float32)
PREVIEW_NORMAL = (np.arange(256.0) / 127.5 - 1.0).astype(np.float32)
# combined's four channels in one lookup: code + 256 x channel indexes this table
_PREVIEW_RGBA = np.concatenate([PREVIEW_COLOR] * 3 + [PREVIEW_ALPHA])
_RGBA_OFFSETS = (np.arange(4) * 256).astype(np.uint16)


@functools.lru_cache(maxsize=64)
def _checked_pass_dtypes(payload: str, passes: tuple) -> dict:
    # decode_tile's dtypes: checked once per frame format, not once per tile (read only)
    return pass_dtypes(payload, passes)


def _pass_shape(name: str, w: int, h: int) -> tuple:
    return (h, w) if TILE_PASSES[name] == 1 else (h, w, TILE_PASSES[name])


def _encode_pass(name: str, array: np.ndarray, dtype: np.dtype) -> np.ndarray:
    if dtype.kind == "f":
        if dtype.itemsize == 2:
            array = np.clip(array, -F16_MAX, F16_MAX)
        return np.ascontiguousarray(array, dtype)
    if PASS_CODING[name] == "direction":
        return np.rint((np.clip(array, -1.0, 1.0, dtype=np.float64) + 1.0) * 127.5).astype(np.uint8)
    if PASS_CODING[name] == "color":
        return np.searchsorted(PREVIEW_COLOR_BOUNDS, array, side="right").astype(np.uint8)
    codes = np.empty(array.shape, np.uint8)
    codes[..., :3] = np.searchsorted(PREVIEW_COLOR_BOUNDS, array[..., :3], side="right")
    codes[..., 3] = np.rint(np.clip(array[..., 3], 0.0, 1.0, dtype=np.float64) * 255.0)
    return codes


def encode_tile(passes: dict, payload: str = "f32", compress: bool = False,
                names=ALL_PASSES) -> tuple:
    """(header fields, arrays) of a TILE_RESULT carrying the passes `names` of the float32
    `passes` as `payload`."""
    arrays = {name: _encode_pass(name, np.asarray(passes[name], np.float32), dtype)
              for name, dtype in pass_dtypes(payload, names).items()}
    fields = {"payload": payload, "compression": "none"}
    if compress:
        raw = b"".join(memoryview(a).cast("B") for a in arrays.values())
        packed = zlib.compress(raw, 1)
        if len(packed) <= 0.9 * len(raw):
            fields["compression"] = "zlib"
            arrays = {"zlib": np.frombuffer(packed, np.uint8)}
    return fields, arrays


def _all_finite(array: np.ndarray) -> bool:
    # np.isfinite(...).all(): 2-3 x faster here than a float64 sum of the tile (measured on
    # 64- and 256-pixel float32 tiles), the master's largest cost per byte.
    return array.dtype.kind != "f" or bool(np.isfinite(array).all())


def decode_tile(header: dict, arrays: dict, w: int, h: int, payload: str, passes=ALL_PASSES,
                out: dict | None = None) -> dict:
    """Check a w x h TILE_RESULT sent with `payload` and `passes` and return its passes as
    float32; with `out` (name -> float32 array of the tile's shape, e.g. a window of the frame)
    write them there instead and return `out`. ProtocolError if anything is off (format, names,
    shapes, dtypes, sizes, NaN or infinity); nothing is written then."""
    if header.get("payload", "f32") != payload:
        raise ProtocolError(f"tile payload {header.get('payload')!r}, expected {payload!r}")
    try:
        dtypes = _checked_pass_dtypes(payload, tuple(passes))
    except TypeError:        # unhashable: not passes at all, pass_dtypes says why
        dtypes = pass_dtypes(payload, passes)
    compression = header.get("compression", "none")
    if compression == "zlib":
        packed = arrays.get("zlib")
        if set(arrays) != {"zlib"} or packed.dtype != np.uint8 or packed.ndim != 1:
            raise ProtocolError("a zlib tile must carry exactly one u1 array 'zlib'")
        expected = sum(math.prod(_pass_shape(n, w, h)) * d.itemsize for n, d in dtypes.items())
        inflater = zlib.decompressobj()
        try:
            raw = inflater.decompress(packed, expected)
        except zlib.error as exc:
            raise ProtocolError(f"tile does not inflate: {exc}") from None
        if len(raw) != expected or inflater.unconsumed_tail or not inflater.eof:
            raise ProtocolError("inflated tile has the wrong size")
        arrays, offset = {}, 0
        for name, dtype in dtypes.items():
            shape = _pass_shape(name, w, h)
            arrays[name] = np.frombuffer(raw, dtype, math.prod(shape), offset).reshape(shape)
            offset += math.prod(shape) * dtype.itemsize
    elif compression != "none":
        raise ProtocolError(f"unknown tile compression {compression!r}")
    if set(arrays) != set(dtypes):
        raise ProtocolError(f"tile passes must be {sorted(dtypes)}, got {sorted(arrays)}")
    for name, dtype in dtypes.items():
        shape, array = _pass_shape(name, w, h), arrays[name]
        if array.dtype != dtype or array.shape != shape:
            raise ProtocolError(f"pass {name!r} must be {dtype.str} {shape}, "
                                f"got {array.dtype.str} {array.shape}")
        if not _all_finite(array):
            raise ProtocolError(f"pass {name!r} contains NaN or infinity")
    if out is None:
        out = {name: np.empty(_pass_shape(name, w, h), np.float32) for name in dtypes}
    for name, dtype in dtypes.items():
        source, target = arrays[name], out[name]
        if dtype.kind == "f":
            np.copyto(target, source)
        elif PASS_CODING[name] == "direction":
            target[...] = PREVIEW_NORMAL.take(source)
        elif PASS_CODING[name] == "color":
            target[...] = PREVIEW_COLOR.take(source)
        else:
            codes = source.astype(np.uint16)
            codes += _RGBA_OFFSETS
            np.take(_PREVIEW_RGBA, codes, out=target, mode="clip")
    return out
