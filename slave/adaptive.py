"""How the samples of a tile are spent (docs/shading.md): N x N everywhere, or adaptively as
Cycles does (its minimum, then 16 more at a time where pixels are still noisy), optionally with
undersampling of smooth regions.

The policy runs against a `tile` that traces and holds the tile's accumulators on the device:
    tile.run(pixels, first_sample, sample_count, aux)   trace (aux: also depth and normal)
    tile.read() -> accum (n, 4 * ACCUM.size)             the accumulators, copied to the host
    tile.write_accum(accum)                              write the accumulators back
Seeds depend only on the global pixel and the sample number, so the pixels are the same
whichever slave renders the tile.

A run is traced in launches of bounded work (LaunchPlan), so that a stop (a cancelled frame)
takes effect between them: the kernel adds a pixel's samples in order to its accumulator
record, so a run's samples split into consecutive ranges give the same bits.
"""
from __future__ import annotations

import numpy as np

from ..core.layout import ACCUM

# Cycles' adaptive sampling (integrator.cpp get_adaptive_sampling): its noise estimate is
# compared with 5 x the Noise Threshold ("an arbitrary factor that makes the threshold more
# similar to what it was before"), and pixels are checked every ADAPTIVE_STEP samples once they
# have the minimum (the first check after min + ADAPTIVE_STEP samples).
THRESHOLD_SCALE = 5.0
ADAPTIVE_STEP = 16


def sample_tile(tile, settings, x: int, y: int, w: int, h: int, every: np.ndarray) -> None:
    """Trace the tile's samples as `settings` (core.scene.model.RenderSettings) say; `every`:
    all tile-local pixel indices in the order the kernel should take them."""
    total = settings.samples_per_axis ** 2
    count = settings.min_samples
    if not settings.adaptive or total <= count:
        tile.run(every, 0, total, 1)
        return
    threshold = THRESHOLD_SCALE * settings.noise_threshold
    if settings.undersample:
        tile.run(every, 0, 0, 1)                 # depth and normal of every pixel
        active = _undersample(tile, x, y, w, h, count, settings.noise_threshold, threshold)
    else:
        tile.run(every, 0, count, 1)             # the minimum, depth and normal
        active = every
    while count < total and len(active):
        batch = min(ADAPTIVE_STEP, total - count)
        tile.run(active, count, batch, 0)
        count += batch
        noisy = pixel_error(tile.read(), w, h) > threshold
        active = active[noisy[active]]


def _undersample(tile, x, y, w, h, count, agreement, threshold):
    """Adaptive undersampling (after Kim et al. 2016): trace the pixels with even global
    coordinates (and the tile's last row and column, so every other pixel has traced
    neighbours inside the tile); a pixel between them whose traced neighbours agree (their
    luminance within 4 x the Noise Threshold, `agreement`) and are converged (their noise below
    `threshold`) is their average and traces nothing; the others are traced. Global parity,
    so the same pixels are traced in every tiling of the rows and columns. Returns the traced
    pixels (tile-local indices)."""
    gy, gx = np.meshgrid(np.arange(y, y + h), np.arange(x, x + w), indexing="ij")
    coarse = ((gx % 2 == 0) & (gy % 2 == 0)) | (gx == x + w - 1) & (gy % 2 == 0) \
        | (gy == y + h - 1) & (gx % 2 == 0) | ((gx == x + w - 1) & (gy == y + h - 1))
    traced = np.flatnonzero(coarse.ravel()).astype(np.int32)
    tile.run(traced, 0, count, 0)
    accum = tile.read()
    colour = pixel_rgba(accum).reshape(h, w, 4)
    lum = colour[..., :3] @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    error = pixel_error(accum, w, h, neighbours=False).reshape(h, w)
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
    smooth = ~coarse & (n_c >= 2) & (hi - lo <= 4 * agreement) & (worst <= threshold)
    fill = np.flatnonzero(smooth.ravel())
    if len(fill):
        interpolated = (sum_c / np.maximum(n_c, 1)[..., None]).reshape(-1, 4)[fill]
        records = accum.reshape(len(accum), ACCUM.size, 4)
        filled = records[fill]
        ACCUM.put(filled, "color", interpolated[:, :3])
        ACCUM.put(filled, "samples", 1.0)
        ACCUM.put(filled, "alpha", interpolated[:, 3])
        ACCUM.put(filled, "half", interpolated[:, :3] / 2)    # no noise: converged
        records[fill] = filled
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


def pixel_error(accum: np.ndarray, w: int, h: int, neighbours: bool = True) -> np.ndarray:
    """Per pixel, Cycles' noise estimate (film_adaptive_sampling_convergence_check): the
    difference between the mean of all its samples and twice the mean of the stratified
    half, summed over RGB, over 1e-4 + the square root of the mean's RGB sum, or the sum
    itself where it is 1 or more (Cycles: bright pixels, near or past white, need less). With
    `neighbours`, as Cycles' filter after each check, a pixel counts as noisy where one of its
    8 neighbours in the tile is (what a check finds noisy at an edge is refined on both
    sides)."""
    records = accum.reshape(len(accum), ACCUM.size, 4)
    count = np.maximum(ACCUM.get(records, "samples"), 1.0)[:, None]
    total = ACCUM.get(records, "color")
    difference = np.abs(total - 2.0 * ACCUM.get(records, "half")).sum(1) / count[:, 0]
    intensity = np.maximum((total / count).sum(1), 0.0)
    scale = np.where(intensity < 1.0, np.sqrt(intensity), intensity)
    error = (difference / (1e-4 + scale)).reshape(h, w)
    if neighbours:
        rows = error.copy()
        rows[1:] = np.maximum(rows[1:], error[:-1])
        rows[:-1] = np.maximum(rows[:-1], error[1:])
        error = rows.copy()
        error[:, 1:] = np.maximum(error[:, 1:], rows[:, :-1])
        error[:, :-1] = np.maximum(error[:, :-1], rows[:, 1:])
    return error.reshape(-1)


class LaunchPlan:
    """How one run (pixels, first sample, sample count, aux) is cut into kernel launches of at
    most a given number of pixel-samples each: blocks of consecutive pixels, each with all of
    the run's samples in one launch where that fits (a pixel's samples one after another, as one
    launch traces them: its rays meet the same nodes while they are in cache), else with as
    many consecutive samples as fit beside at least `min_pixels` pixels (the device's
    parallelism). Every pixel gets its samples in order, so the bits are those of one launch.
    Only the launches with the run's first sample write depth and normal (aux): the kernel
    writes them at its first sample (or, stratified, from the pixel centre), so once is what
    one launch does. A run of no samples (depth and normal alone) counts a sample per pixel.

        plan = LaunchPlan(len(pixels), start, count, aux, min_pixels)
        while (launch := plan.next(pixel_samples)) is not None:
            first, end, sample, samples, aux = launch   # pixels[first:end]
    """

    def __init__(self, pixel_count: int, start: int, count: int, aux: int, min_pixels: int = 1):
        self.pixel_count, self.start, self.count, self.aux = pixel_count, start, count, aux
        self.min_pixels = max(1, int(min_pixels))
        self._pixel = 0             # the block under way: its first pixel ...
        self._end = 0               # ... its end (0: none under way)
        self._sample = start        # ... and the next sample to launch for it
        self.launches = 0

    @property
    def done(self) -> bool:
        return self._pixel >= self.pixel_count

    def next(self, budget: int):
        """The next launch as (first pixel, end pixel, first sample, samples, aux) within
        `budget` pixel-samples (at least one sample of one pixel), or None when the run is
        traced."""
        if self.done:
            return None
        budget = max(1, int(budget))
        per_pixel = max(self.count, 1)
        if self._end == 0:          # a new block: as many pixels as the budget allows
            samples = min(per_pixel, max(1, budget // self.min_pixels))
            self._end = min(self.pixel_count, self._pixel + max(1, budget // samples))
        first, end, sample = self._pixel, self._end, self._sample
        samples = min(self.start + self.count - sample,
                      max(1, budget // (end - first)))
        aux = self.aux if sample == self.start else 0
        self._sample += max(samples, 1)
        if self._sample >= self.start + per_pixel:      # the block is traced
            self._pixel, self._end, self._sample = end, 0, self.start
        self.launches += 1
        return first, end, sample, samples, aux
