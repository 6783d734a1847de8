"""The viewport's Rendered mode through the slaves (docs/viewport.md): a session that lives
across redraws, keeps a Master connected and the scene on the slaves, and renders the current
view progressively - a quick image at a fraction of the resolution, then the full resolution
at 1, 4, 16, ... samples per pixel (N x N, N doubling) up to the viewport's samples or time
limit, denoised from a few samples on where asked. Any change restarts it: the frame in
flight is cancelled on every slave (its late tiles never reach the image), a new scene is
uploaded as F12 uploads it (only what changed: the instances where objects only moved, the
edited meshes), a new view or shading only starts a new frame.

The host calls update() from Blender's main thread (view_update, view_draw) and reads image()
to draw; everything else runs on the session's own thread, which shares the add-on's
FrameSession (kd-trees, local slaves, the LAN browser) with F12. The final pass at N x N
samples is an F12 frame of that view and those samples: the same pixels, bit for bit (and
denoised as F12 denoises, where the viewport denoises)."""
from __future__ import annotations

import dataclasses
import threading
import time
from dataclasses import dataclass

import numpy as np

from ..scene.model import View
from .denoising import DenoiseSettings, FrameDenoiser, denoise_frame, with_guides
from .options import FrameOptions
from .render import FRAME_ERRORS, FrameHost, Steps, frame_scene, master_for
from .session import FrameSession

PREVIEW_PIXELS = 160        # the first image of a view: its longest side at most this
# The viewport's sampling (Cycles' Viewport Max Samples and Time Limit; the panel reads these).
SAMPLES_PER_AXIS = 8        # N x N = 64 samples per pixel at most
SAMPLES_PER_AXIS_RANGE = (1, 64)
TIME_LIMIT = 0.0            # seconds of refinement after a change, 0: none
TIME_LIMIT_RANGE = (0.0, 86400.0)
# Viewport denoising (Cycles' Viewport > Denoise: off by default, prefilter Fast, quality
# Balanced): each full-resolution pass from DENOISE_START samples on is denoised once whole.
DENOISE = DenoiseSettings(enabled=False, prefilter="FAST", quality="BALANCED")
DENOISE_START = 4
POLL_SECONDS = 0.02         # how often a pass in flight looks for a newer request


@dataclass
class Published:
    """An image for the host to draw: `pixels` (h, w, 4) float32 of a view `width` x `height`
    (fewer pixels than the view for the first, reduced pass: draw it stretched), the change
    (epoch) it shows, its samples per pixel and whether it is the change's last pass."""
    epoch: int
    pixels: np.ndarray
    width: int
    height: int
    samples: int
    final: bool


def passes(view: View, samples_per_axis: int) -> list[View]:
    """The views a change renders, in order: the view at a fraction of its resolution (its
    longest side at most PREVIEW_PIXELS) at one sample, then the view at N x N samples for N =
    1, 2, 4, ... up to `samples_per_axis` (the last one always), uniform."""
    settings = dataclasses.replace(view.settings, adaptive=False, samples_per_axis=1)
    out = []
    scale = max(view.width, view.height) / PREVIEW_PIXELS
    if scale > 1:
        w, h = max(1, round(view.width / scale)), max(1, round(view.height / scale))
        out.append(dataclasses.replace(view, width=w, height=h, region=(0, 0, w, h),
                                       settings=settings))
    n = 1
    while True:
        out.append(dataclasses.replace(view, settings=dataclasses.replace(
            settings, samples_per_axis=n)))
        if n >= samples_per_axis:
            return out
        n = min(2 * n, samples_per_axis)


class ViewportSession:
    def __init__(self, session: FrameSession, options: FrameOptions,
                 samples_per_axis: int = SAMPLES_PER_AXIS, time_limit: float = TIME_LIMIT,
                 denoise: DenoiseSettings = DENOISE, host: FrameHost | None = None):
        """`samples_per_axis`: the viewport's N (N x N samples at most, Cycles' Viewport Max
        Samples); `time_limit`: seconds of refinement after a change (0: none); `denoise`: the
        viewport's denoising. `host` hears the status and reports (the viewport shows them in
        its header)."""
        self.session, self.options = session, options
        self.samples_per_axis, self.time_limit = samples_per_axis, time_limit
        self.denoise = denoise
        self._denoiser = FrameDenoiser()    # its own: F12 may denoise on another thread
        self.host = host or FrameHost()
        self.error = ""             # the last problem, for the host to show ("": none)
        self.cancels = 0            # frames cancelled because something changed
        self.cancel_seconds = []    # for each: from the cancel until every slave confirmed it
        self._changed = threading.Condition()
        self._request = None        # (epoch, exported or None, view, warnings): the newest
        self._epoch = 0
        self._published = None
        self._idle = True           # no change is being rendered
        self._closing = False
        self._master = None
        self._scene = None
        self._thread = threading.Thread(target=self._run, name="kdtrace-viewport", daemon=True)
        self._thread.start()

    # -- the host's side (Blender's main thread) ------------------------------------------------
    def update(self, view: View, exported=None, warnings=()) -> int:
        """A change: a new view (camera, size, shading, settings) and, when the scene changed,
        its export. Returns the change's epoch; what was in flight is cancelled."""
        with self._changed:
            self._epoch += 1
            pending = self._request
            if exported is None and pending is not None and pending[1] is not None:
                exported, warnings = pending[1], pending[3]   # a scene not yet taken up
            self._request = (self._epoch, exported, view, tuple(warnings))
            self._changed.notify_all()
            return self._epoch

    def image(self) -> Published | None:
        """The newest image of the newest change that has one (None before the first)."""
        with self._changed:
            return self._published

    @property
    def epoch(self) -> int:
        with self._changed:
            return self._epoch

    def done(self) -> bool:
        """Nothing is left to render for the newest change (finished, limited or failed)."""
        with self._changed:
            return self._request is None and self._idle

    def close(self) -> None:
        with self._changed:
            self._closing = True
            self._changed.notify_all()
        self._thread.join(timeout=30)

    # -- the session's thread ---------------------------------------------------------------
    def _take(self, wait: bool):
        """The newest request (None when closing; with `wait`, blocks until there is one)."""
        with self._changed:
            while wait and self._request is None and not self._closing:
                self._changed.wait()
            if self._closing:
                return None
            request, self._request = self._request, None
            return request

    def _newer(self, epoch: int) -> bool:
        with self._changed:
            return self._closing or self._epoch != epoch

    def _run(self) -> None:
        try:
            while True:
                request = self._take(wait=True)
                if request is None:
                    return
                epoch, exported, view, warnings = request
                with self._changed:
                    self._idle = False
                try:
                    if exported is not None:
                        self._load(exported, warnings)
                    self._render(epoch, view)
                    self.error = ""
                except FRAME_ERRORS as error:
                    self.error = str(error)
                    self.host.report("WARNING", f"KD Trace: {error}")
                    self._drop_master()
                with self._changed:
                    self._idle = True
        finally:
            self._drop_master()
            self._denoiser.close()

    def _load(self, exported, warnings) -> None:
        """The export's scene on the slaves (the F12 pipeline: kd-trees cached, only what
        changed sent)."""
        for warning in warnings:
            self.host.report("WARNING", f"KD Trace: {warning}")
        self.session.last_warnings = list(warnings)
        self._scene, *_ = frame_scene(self.session, exported, self.options, self.host,
                                      Steps(time.perf_counter()))
        self._connect().load_scene(self._scene)

    def _connect(self):
        """The session's Master, connected (again, after a failure: with the scene)."""
        if self._master is None:
            self._master = master_for(self.session, self.options, self.host)
            if self._scene is not None:
                self._master.load_scene(self._scene)
        return self._master

    def _render(self, epoch: int, view: View) -> None:
        """The passes of one change, until they are done, the time limit is reached or a newer
        change comes."""
        if self._scene is None:
            raise RuntimeError("the viewport has no scene yet")
        self._scene.check_view(view)
        master = self._connect()
        started = time.monotonic()
        for pass_view in passes(view, self.samples_per_axis):
            if self._newer(epoch):
                return
            if self.time_limit and time.monotonic() - started > self.time_limit:
                return
            full = pass_view.width == view.width
            denoised = self.denoise.enabled and full and \
                pass_view.settings.samples_per_axis ** 2 >= DENOISE_START
            job_options = self.options.job_options()
            if denoised:
                job_options = with_guides(job_options, self.denoise)
            job = master.render(pass_view, **job_options)
            while not job.finished:
                if self._newer(epoch):
                    cancelled = time.monotonic()
                    job.cancel()
                    job.wait(60)        # the next frame starts once the slaves are quiet
                    self.cancels += 1
                    self.cancel_seconds.append(time.monotonic() - cancelled)
                    return
                if job.stranded:
                    job.give_up()
                job.next_results(POLL_SECONDS)
            if job.error and not job.cancelled:
                raise RuntimeError(job.error)
            if denoised:
                denoise_frame(self._denoiser, self.denoise, job, self.host)
            self._publish(epoch, job.image["combined"].copy(), pass_view, view)

    def _publish(self, epoch, pixels, pass_view, view) -> None:
        """A whole pass's image for the host, unless a newer change has come (a cancelled
        frame's pixels never reach what is drawn)."""
        n = pass_view.settings.samples_per_axis
        with self._changed:
            if self._epoch == epoch:
                self._published = Published(epoch, pixels, view.width, view.height, n * n,
                                            n >= self.samples_per_axis
                                            and pass_view.width == view.width)

    def _drop_master(self) -> None:
        if self._master is not None:
            try:
                self._master.close()
            finally:
                self._master = None
