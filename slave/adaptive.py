"""How the samples of a tile are spent (docs/shading.md): N x N everywhere, or adaptively,
with undersampling of smooth regions and doubling where pixels are still noisy.

The policy runs against a `tile` that traces and holds the tile's accumulators on the device:
    tile.run(pixels, first_sample, sample_count, aux)   trace (aux: also depth and normal)
    tile.read() -> (accum (n, 8), stats (n, 2))          the accumulators, copied to the host
                                                         (accum: RGB sum, samples, alpha sum, 0 0 0)
    tile.write_accum(accum)                              write the accumulated colours back
Seeds depend only on the global pixel and the sample number, so the pixels are the same
whichever slave renders the tile.
"""
from __future__ import annotations

import numpy as np

from core.layout import ACCUM, STATS


def sample_tile(tile, settings, x: int, y: int, w: int, h: int, every: np.ndarray) -> None:
    """Trace the tile's samples as `settings` (core.scene.model.RenderSettings) say; `every`:
    all tile-local pixel indices in the order the kernel should take them."""
    total = settings.samples_per_axis ** 2
    if not settings.adaptive or total <= settings.adaptive_min_samples:
        tile.run(every, 0, total, 1)
        return
    count = max(1, settings.adaptive_min_samples)
    tile.run(every, 0, 0, 1)                     # depth and normal of every pixel
    active = _undersample(tile, x, y, w, h, count, settings.adaptive_threshold)
    while count < total:
        _, stats = tile.read()
        error = pixel_error(stats, count, w, h)
        active = active[error[active] > settings.adaptive_threshold]
        if len(active) == 0:
            break
        batch = min(count, total - count)        # doubling
        tile.run(active, count, batch, 0)
        count += batch


def _undersample(tile, x, y, w, h, count, threshold):
    """Adaptive undersampling (after Kim et al. 2016): trace the pixels with even global
    coordinates (and the tile's last row and column, so every other pixel has traced
    neighbours inside the tile); a pixel between them whose traced neighbours agree (their
    luminance within 4 x threshold) and are converged is their average and traces nothing;
    the others are traced. Global parity, so the same pixels are traced in every tiling of
    the rows and columns. Returns the traced pixels (tile-local indices)."""
    gy, gx = np.meshgrid(np.arange(y, y + h), np.arange(x, x + w), indexing="ij")
    coarse = ((gx % 2 == 0) & (gy % 2 == 0)) | (gx == x + w - 1) & (gy % 2 == 0) \
        | (gy == y + h - 1) & (gx % 2 == 0) | ((gx == x + w - 1) & (gy == y + h - 1))
    traced = np.flatnonzero(coarse.ravel()).astype(np.int32)
    tile.run(traced, 0, count, 0)
    accum, stats = tile.read()
    colour = pixel_rgba(accum).reshape(h, w, 4)
    lum = (stat(stats, "sum") / count).reshape(h, w)
    error = pixel_error(stats, count, w, h).reshape(h, w)
    sum_c = np.zeros((h, w, 4), np.float32)
    n_c = np.zeros((h, w), np.int32)
    lo = np.full((h, w), np.inf, np.float32)
    hi = np.full((h, w), -np.inf, np.float32)
    worst = np.zeros((h, w), np.float32)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx == dy == 0:
                continue
            # neighbour (r + dy, c + dx) of pixel (r, c), when traced
            src = (slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0)))
            dst = (slice(max(-dy, 0), h + min(-dy, 0)), slice(max(-dx, 0), w + min(-dx, 0)))
            # Of the 8 neighbours, the traced ones are the nearest ring: left/right or
            # up/down for pixels on a traced row or column, the diagonals for the others.
            ok = coarse[src]
            sum_c[dst] += np.where(ok[..., None], colour[src], 0)
            n_c[dst] += ok
            lo[dst] = np.where(ok, np.minimum(lo[dst], lum[src]), lo[dst])
            hi[dst] = np.where(ok, np.maximum(hi[dst], lum[src]), hi[dst])
            worst[dst] = np.where(ok, np.maximum(worst[dst], error[src]), worst[dst])
    smooth = ~coarse & (n_c >= 2) & (hi - lo <= 4 * threshold) & (worst <= threshold)
    fill = np.flatnonzero(smooth.ravel())
    if len(fill):
        interpolated = (sum_c / np.maximum(n_c, 1)[..., None]).reshape(-1, 4)[fill]
        records = accum.reshape(len(accum), ACCUM.size, 4)
        filled = records[fill]
        ACCUM.put(filled, "color", interpolated[:, :3])
        ACCUM.put(filled, "samples", 1.0)
        ACCUM.put(filled, "alpha", interpolated[:, 3])
        records[fill] = filled
        stats[fill] = 0.0                   # converged: never refined
        tile.write_accum(accum)
    rest = np.flatnonzero((~coarse & ~smooth).ravel()).astype(np.int32)
    if len(rest):
        tile.run(rest, 0, count, 0)
    done = ~smooth.ravel()
    return np.flatnonzero(done).astype(np.int32)


def pixel_rgba(accum: np.ndarray) -> np.ndarray:
    """Each pixel's mean RGB and alpha, (n, 4), from its accumulator record (n, 4 * ACCUM.size;
    core/layout.py ACCUM)."""
    records = accum.reshape(len(accum), ACCUM.size, 4)
    sums = np.concatenate([ACCUM.get(records, "color"), ACCUM.get(records, "alpha")[:, None]], 1)
    return sums / np.maximum(ACCUM.get(records, "samples"), 1.0)[:, None]


def stat(stats: np.ndarray, name: str) -> np.ndarray:
    """Slot `name` of each pixel's error statistics (n, STATS.width; core/layout.py STATS)."""
    return STATS.get(stats.reshape(len(stats), STATS.size, STATS.width), name)


def pixel_error(stats: np.ndarray, count: int, w: int, h: int) -> np.ndarray:
    """Per pixel, Cycles' noise estimate: the expected difference between the mean of all
    samples and of half of them, summed over RGB, over the square root of the pixel's RGB sum
    (Cycles' film convergence test), here from the samples' luminance (clamped to 1): with
    standard error sigma / sqrt(n) per channel that is 3 sqrt(2 / pi) sigma / sqrt(n) over
    1e-4 + sqrt(3 mean). A pixel is done when it is below the Noise Threshold, as in Cycles.
    Widened to half its 4-neighbours' value (in the spirit of Kim et al. 2016: what a coarse
    pass finds noisy or at an edge, and its neighbourhood, is refined; smooth regions keep the
    minimum)."""
    mean = stat(stats, "sum") / count
    variance = np.maximum(stat(stats, "sum_squares") / count - mean * mean, 0.0) \
        * (count / max(count - 1, 1))
    difference = 3.0 * np.sqrt(2.0 / np.pi) * np.sqrt(variance / count)
    error = (difference / (1e-4 + np.sqrt(3.0 * np.maximum(mean, 0.0)))).reshape(h, w)
    widened = error.copy()
    widened[1:] = np.maximum(widened[1:], 0.5 * error[:-1])
    widened[:-1] = np.maximum(widened[:-1], 0.5 * error[1:])
    widened[:, 1:] = np.maximum(widened[:, 1:], 0.5 * error[:, :-1])
    widened[:, :-1] = np.maximum(widened[:, :-1], 0.5 * error[:, 1:])
    return widened.reshape(-1)
