"""slave/adaptive.py's schedule, as Cycles' adaptive sampling: the minimum, then 16 samples at a
time while a pixel's noise (Cycles' estimate: all samples against the odd-numbered half) or a
neighbour's exceeds 5 x the Noise Threshold; smooth pixels between converged ones are
interpolated. Run against a tile on the host whose pixels have known noise."""
from __future__ import annotations

import math

import numpy as np

from core.layout import ACCUM
from core.scene.model import RenderSettings
from slave.adaptive import ADAPTIVE_STEP, THRESHOLD_SCALE, pixel_error, sample_tile


class NoisyTile:
    """A w x h tile whose pixel p's samples are mean[p] + spread[p] x (+1 or -1 by sample
    parity and pixel), grey, accumulated as the kernel does (ACCUM, the odd samples' half)."""

    def __init__(self, mean, spread):
        self.mean, self.spread = np.ravel(mean), np.ravel(spread)
        self.accum = np.zeros((len(self.mean), 4 * ACCUM.size), np.float32)

    def run(self, pixels, start, count, aux):
        records = self.accum.reshape(len(self.accum), ACCUM.size, 4)
        for p in pixels:
            for s in range(start, start + count):
                sign = 1.0 if (s + p) % 2 else -1.0
                c = self.mean[p] + self.spread[p] * sign
                record = records[p]
                ACCUM.put(record, "color", ACCUM.get(record, "color") + c)
                ACCUM.put(record, "samples", ACCUM.get(record, "samples") + 1)
                ACCUM.put(record, "alpha", ACCUM.get(record, "alpha") + 1)
                if s % 2:
                    ACCUM.put(record, "half", ACCUM.get(record, "half") + c)

    def read(self):
        return self.accum

    def write_accum(self, values):
        self.accum = values

    def samples(self, w, h):
        return ACCUM.get(self.accum.reshape(len(self.accum), ACCUM.size, 4), "samples").reshape(h, w)


def render(mean, spread, **settings):
    h, w = np.shape(mean)
    tile = NoisyTile(mean, spread)
    sample_tile(tile, RenderSettings(**settings), 0, 0, w, h, np.arange(w * h))
    return tile.samples(w, h)


def test_automatic_minimum_is_cycles():
    assert RenderSettings(adaptive_threshold=0.01).min_samples == 64
    assert RenderSettings(adaptive_threshold=0.1).min_samples == math.ceil(16 / 0.1 ** 0.3)
    assert RenderSettings(adaptive_threshold=0.001).min_samples == 128
    assert RenderSettings(adaptive_threshold=0.01, adaptive_min_samples=7).min_samples == 7
    assert RenderSettings(adaptive_threshold=0.0, samples_per_axis=16).noise_threshold == 1 / 256


def test_noise_estimate_is_cycles_half_buffer():
    """One pixel of 32 samples whose odd samples are brighter: (|sum - 2 half| summed over
    RGB) / n over 1e-4 + sqrt(mean's RGB sum)."""
    tile = NoisyTile([[0.5]], [[0.1]])
    tile.run([0], 0, 32, 0)
    expected = 3 * abs(16 * 0.6 + 16 * 0.4 - 2 * 16 * 0.6) / 32 / (1e-4 + math.sqrt(3 * 0.5))
    assert math.isclose(pixel_error(tile.read(), 1, 1)[0], expected, rel_tol=1e-5)


def test_clean_pixels_stop_at_the_first_check_noisy_ones_and_their_neighbours_go_on():
    h, w = 8, 8
    spread = np.zeros((h, w))
    spread[4, 4] = 0.3                      # one noisy pixel
    samples = render(np.full((h, w), 0.5), spread, samples_per_axis=16, adaptive_min_samples=16,
                     adaptive_threshold=0.01)
    first_check = 16 + ADAPTIVE_STEP
    assert samples[4, 4] == 256                         # never converges: up to the max
    assert (samples[3:6, 3:6] > first_check).all()      # its 8 neighbours follow it
    far = np.ones((h, w), bool)
    far[3:6, 3:6] = False
    # Clean pixels: converged after the minimum and one step, or interpolated (1 sample).
    assert set(np.unique(samples[far])) <= {1.0, float(first_check)}
    assert (samples[far] == 1).any() and (samples[far] == first_check).any()


def test_threshold_is_five_times_the_noise_threshold():
    """A pixel whose estimate after the first check lies between 1 and 5 x the Noise Threshold
    stops there; above 5 x it goes on."""
    tile = NoisyTile([[0.5]], [[0.05]])
    tile.run([0], 0, 32, 0)
    error = pixel_error(tile.read(), 1, 1)[0]
    calm = render([[0.5]], [[0.05]], samples_per_axis=16, adaptive_min_samples=16,
                  adaptive_threshold=error / THRESHOLD_SCALE * 1.01)
    busy = render([[0.5]], [[0.05]], samples_per_axis=16, adaptive_min_samples=16,
                  adaptive_threshold=error / THRESHOLD_SCALE * 0.99)
    assert calm[0, 0] == 32 and busy[0, 0] > 32


def test_uniform_when_the_minimum_covers_the_max():
    samples = render(np.full((4, 4), 0.5), np.full((4, 4), 0.3), samples_per_axis=4)
    assert (samples == 16).all()
