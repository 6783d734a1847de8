"""slave/adaptive.py's schedule, as Cycles' adaptive sampling: the minimum, then 16 samples at a
time while a pixel's noise (Cycles' estimate: all samples against its class A half) or a
neighbour's exceeds 5 x the Noise Threshold; with undersampling, smooth pixels between converged
ones are interpolated. Run against a tile on the host whose pixels have known noise."""
from __future__ import annotations

import math

import numpy as np

from kdtrace.core.layout import ACCUM
from kdtrace.core.scene.model import RenderSettings
from kdtrace.slave.adaptive import (ADAPTIVE_STEP, THRESHOLD_SCALE, LaunchPlan, pixel_error,
                                    sample_tile)


class NoisyTile:
    """A w x h tile whose pixel p's samples are mean[p] + spread[p] x (+1 or -1 by the
    sample's half and the pixel), grey, accumulated as the kernel does (ACCUM: the half of
    Cycles' class A samples, render.cl)."""

    def __init__(self, mean, spread):
        self.mean, self.spread = np.ravel(mean), np.ravel(spread)
        self.accum = np.zeros((len(self.mean), 4 * ACCUM.size), np.float32)

    def run(self, pixels, start, count, aux):
        records = self.accum.reshape(len(self.accum), ACCUM.size, 4)
        for p in pixels:
            for s in range(start, start + count):
                in_half = class_a(s)
                sign = 1.0 if (in_half + p) % 2 else -1.0
                c = self.mean[p] + self.spread[p] * sign
                record = records[p]
                ACCUM.put(record, "color", ACCUM.get(record, "color") + c)
                ACCUM.put(record, "samples", ACCUM.get(record, "samples") + 1)
                ACCUM.put(record, "alpha", ACCUM.get(record, "alpha") + 1)
                if in_half:
                    ACCUM.put(record, "half", ACCUM.get(record, "half") + c)

    def read(self):
        return self.accum

    def write_accum(self, values):
        self.accum = values

    def samples(self, w, h):
        return ACCUM.get(self.accum.reshape(len(self.accum), ACCUM.size, 4), "samples").reshape(h, w)


def class_a(sample: int) -> int:
    """Cycles' sample_is_class_A: the sample's odd bits have an odd count."""
    return bin(sample & 0xAAAAAAAA).count("1") % 2


def test_class_a_is_half_of_every_aligned_four_in_pairs():
    for start in range(0, 1024, 4):
        quad = [class_a(s) for s in range(start, start + 4)]
        assert sum(quad) == 2 and quad[0] == quad[1] and quad[2] == quad[3]


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
    """A pixel of 32 samples whose half's samples are brighter: (|sum - 2 half| summed over
    RGB) / n over 1e-4 + sqrt(mean's RGB sum) where that sum is below 1, else over 1e-4 + the
    sum itself (Cycles' film_adaptive_sampling_convergence_check)."""
    for mean, spread, scale in ((0.2, 0.05, math.sqrt(3 * 0.2)), (0.5, 0.1, 3 * 0.5)):
        tile = NoisyTile([[mean]], [[spread]])
        tile.run([0], 0, 32, 0)
        bright = 16 * (mean + spread)
        expected = 3 * abs(bright + 16 * (mean - spread) - 2 * bright) / 32 / (1e-4 + scale)
        assert math.isclose(pixel_error(tile.read(), 1, 1)[0], expected, rel_tol=1e-5)


def test_clean_pixels_stop_at_the_first_check_noisy_ones_and_their_neighbours_go_on():
    h, w = 8, 8
    spread = np.zeros((h, w))
    spread[4, 4] = 0.3                      # one noisy pixel
    first_check = 16 + ADAPTIVE_STEP
    far = np.ones((h, w), bool)
    far[3:6, 3:6] = False
    for undersample in (False, True):
        samples = render(np.full((h, w), 0.5), spread, samples_per_axis=16,
                         adaptive_min_samples=16, adaptive_threshold=0.01, undersample=undersample)
        assert samples[4, 4] == 256                         # never converges: up to the max
        assert (samples[3:6, 3:6] > first_check).all()      # its 8 neighbours follow it
        if not undersample:     # as Cycles: every clean pixel stops at the first check
            assert (samples[far] == first_check).all()
        else:                   # or it is interpolated from its neighbours (1 sample)
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


# -- launches (LaunchPlan) -------------------------------------------------------------------------
def launches_of(pixel_count, start, count, aux, budgets, min_pixels=1):
    """[(launch, the budget it was cut within)] of a LaunchPlan fed `budgets` in turn."""
    plan = LaunchPlan(pixel_count, start, count, aux, min_pixels)
    out = []
    while (launch := plan.next(budget := budgets[len(out) % len(budgets)])) is not None:
        out.append((launch, budget))
    return out


def test_launches_trace_each_sample_of_each_pixel_once_in_order_within_the_budget():
    """Whatever the budgets, every pixel gets every sample of the run exactly once, in
    increasing order; depth and normal (aux) come with the run's first sample only, once per
    pixel. Each launch holds at most its budget of pixel-samples (at least one sample of one
    pixel; a run of no samples counts one a pixel), or where the budget shrank in the middle
    of a block of pixels, one sample of that block (cut within an earlier budget)."""
    rng = np.random.default_rng(3)
    for _ in range(300):
        pixels, start = int(rng.integers(1, 300)), int(rng.integers(0, 40))
        count, aux = int(rng.integers(0, 70)), int(rng.integers(0, 2))
        budgets = [int(b) for b in rng.integers(1, 3 * pixels * max(count, 1), 5)]
        if rng.random() < 0.3:
            budgets = budgets[:1]
        min_pixels = int(rng.integers(1, 64))
        seen = [[] for _ in range(pixels)]
        aux_seen = np.zeros(pixels, int)
        for (first, end, sample, samples, launch_aux), budget in launches_of(
                pixels, start, count, aux, budgets, min_pixels):
            assert 0 <= first < end <= pixels and 0 <= samples <= count
            work = (end - first) * max(samples, 1)
            assert work <= budget or end - first == 1 or samples == 1 and work <= max(budgets)
            if len(budgets) == 1:
                assert work <= max(budget, 1)
            for p in range(first, end):
                seen[p] += list(range(sample, sample + samples))
            aux_seen[first:end] += launch_aux
            assert not launch_aux or sample == start
        for p in range(pixels):
            assert seen[p] == list(range(start, start + count)), (pixels, start, count, budgets)
        assert (aux_seen == aux).all()


def test_launches_keep_a_pixels_samples_together_and_the_device_busy():
    """A budget for 10 of a block's pixels with all their samples: blocks of 10 pixels x all
    64 samples; a budget below min_pixels x samples: min_pixels pixels with fewer samples."""
    launches = [launch for launch, _ in launches_of(100, 0, 64, 1, [640])]
    assert launches[0] == (0, 10, 0, 64, 1) and len(launches) == 10
    launches = [launch for launch, _ in launches_of(100, 0, 64, 1, [640], min_pixels=32)]
    assert launches[0] == (0, 32, 0, 20, 1) and launches[1] == (0, 32, 20, 20, 0)


def test_sampling_cut_into_launches_gives_the_same_bits():
    """The adaptive schedule run through LaunchPlan's launches (tiny budgets) accumulates
    exactly what whole runs do: the same records, bit for bit."""
    class Launched(NoisyTile):
        def __init__(self, mean, spread, budget):
            super().__init__(mean, spread)
            self.budget = budget

        def run(self, pixels, start, count, aux):
            pixels = np.asarray(pixels)
            plan = LaunchPlan(len(pixels), start, count, aux, 3)
            while (launch := plan.next(self.budget)) is not None:
                first, end, sample, samples, _ = launch
                super().run(pixels[first:end], sample, samples, 0)

    rng = np.random.default_rng(5)
    mean, spread = rng.uniform(0.1, 1.0, (12, 10)), rng.uniform(0.0, 0.4, (12, 10))
    for undersample in (False, True):
        settings = RenderSettings(samples_per_axis=8, adaptive_min_samples=8,
                                  adaptive_threshold=0.02, undersample=undersample)
        whole = NoisyTile(mean, spread)
        sample_tile(whole, settings, 0, 0, 10, 12, np.arange(120))
        for budget in (1, 7, 100, 10_000):
            cut = Launched(mean, spread, budget)
            sample_tile(cut, settings, 0, 0, 10, 12, np.arange(120))
            assert cut.accum.tobytes() == whole.accum.tobytes()
