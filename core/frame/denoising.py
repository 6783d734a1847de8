"""The master denoises an F12 frame as Cycles does (Render > Sampling > Denoise): on by default,
Open Image Denoise's RT filter (core/denoise.py: Blender's own library) over the whole image
once the last tile is in, so tiles leave no seams, guided by the slaves' albedo and normal
passes (kernels/shade/film.cl: Cycles' guides). Where no library is found the frame says so
once per session and keeps the noisy image. The settings' defaults and choices live here and
in core/denoise.py; the panel reads them."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..denoise import PREFILTERS, QUALITIES, Denoiser, DenoiseError, find_library

# Cycles' final-render defaults: denoising on, prefilter Accurate, quality High, albedo and
# normal as guides.
DENOISE = True
PREFILTER = "ACCURATE"
QUALITY = "HIGH"
PREFILTER_CHOICES = PREFILTERS
QUALITY_CHOICES = tuple(QUALITIES)
GUIDE_PASSES = ("albedo", "denoising_normal")     # the tile passes the denoiser reads


@dataclass
class DenoiseSettings:
    enabled: bool = DENOISE
    prefilter: str = PREFILTER
    quality: str = QUALITY

    def __post_init__(self):
        if self.prefilter not in PREFILTER_CHOICES:
            raise ValueError(f"denoising prefilter must be one of {PREFILTER_CHOICES}, "
                             f"got {self.prefilter!r}")
        if self.quality not in QUALITY_CHOICES:
            raise ValueError(f"denoising quality must be one of {QUALITY_CHOICES}, "
                             f"got {self.quality!r}")

    def passes(self) -> tuple:
        """The tile passes a frame must ask for to be denoised."""
        return GUIDE_PASSES if self.enabled else ()

    def describe(self) -> str:
        return f"prefilter {self.prefilter.title()}, quality {self.quality.title()}"


class FrameDenoiser:
    """One session's denoiser: the OIDN device is made at the first denoised frame (its set-up,
    about 0.3 s, is paid once) and kept; a missing library is reported once."""

    def __init__(self):
        self._denoiser = None
        self.missing_reported = False

    def denoiser(self) -> Denoiser | None:
        if self._denoiser is None and find_library() is not None:
            self._denoiser = Denoiser()
        return self._denoiser

    def close(self) -> None:
        if self._denoiser is not None:
            self._denoiser.close()
            self._denoiser = None


def with_guides(job_options: dict, settings: DenoiseSettings) -> dict:
    """Master.render's keyword arguments with the passes the denoiser reads added (computed
    and sent only when the frame is denoised)."""
    passes = list(job_options["passes"])
    return {**job_options, "passes": passes + [p for p in settings.passes() if p not in passes]}


def denoise_frame(frame_denoiser: FrameDenoiser, settings: DenoiseSettings, job, host) -> dict:
    """Denoise a finished frame's Combined pass in place (job.image; alpha as it is) from its
    guides, and tell the host (host.denoised with the noisy image). Returns the report's
    fields: "denoised" (bool), "denoise_seconds", "denoise_note" (why not, or how)."""
    if not settings.enabled:
        return {"denoised": False, "denoise_seconds": 0.0, "denoise_note": "off"}
    if job.cancelled or job.error or not job.finished:
        return {"denoised": False, "denoise_seconds": 0.0, "denoise_note": "frame not finished"}
    started = time.perf_counter()
    denoiser = frame_denoiser.denoiser()
    if denoiser is None:
        note = ("no Open Image Denoise library found (Blender ships one; elsewhere install "
                "pyoidn or set $KDTRACE_OIDN_LIBRARY): the image is not denoised")
        if not frame_denoiser.missing_reported:
            host.report("WARNING", f"KD Trace: {note}")
            frame_denoiser.missing_reported = True
        return {"denoised": False, "denoise_seconds": 0.0, "denoise_note": note}
    host.status("Denoising")
    image = job.image
    noisy = image["combined"].copy()
    try:
        clean = denoiser.denoise(noisy, image["albedo"], image["denoising_normal"],
                                 prefilter=settings.prefilter, quality=settings.quality)
    except DenoiseError as error:
        host.report("WARNING", f"KD Trace: {error}; the image is not denoised")
        return {"denoised": False, "denoise_seconds": time.perf_counter() - started,
                "denoise_note": str(error)}
    np.copyto(image["combined"], clean)
    seconds = time.perf_counter() - started
    host.denoised(job, noisy)
    return {"denoised": True, "denoise_seconds": seconds, "denoise_note": settings.describe()}
