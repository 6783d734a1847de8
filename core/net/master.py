"""The master: connects to slaves, uploads the scene where needed, and renders frames.

Usable without Blender (plain threads, no bpy). One thread per master, its frame loop, runs
every frame for all slaves at once: it waits on their sockets with a selector, hands out the
next tile index as soon as a slave has a free slot (the paper's Fig. 3b: several tiles in
flight hide the network latency), validates finished tiles, writes them into the frame and puts
them on the job's results queue. The caller's thread (Blender's render thread) only polls that
queue with a timeout, so it can check for cancel in between:

    master = Master([("127.0.0.1", 47600)]); master.connect()
    master.load_scene(scene)               # a core.scene.scene.Scene
    job = master.render(view, tile_size=64)
    while not job.finished:
        result = job.next_result(0.1)      # TileResult or None
        ...                                # job.cancel() on user break
    job.error                              # None, or why the frame could not be finished

Liveness is not work: a busy slave sends heartbeats (what it is doing), and a slave is dropped
only for silence (`silence_timeout`) or for a step that exceeds its TileBudget, which scales
with the tile's work. A dropped slave's tiles go back to the pool for the others, and the master
reconnects to it with back-off; `master.join(host, port)` brings a slave found later (or
restarted) into the frame in progress. The frame fails only when no slave is left.
"""
from __future__ import annotations

import collections
import math
import queue
import selectors
import socket
import threading
import time
import traceback
import uuid
from dataclasses import dataclass

import numpy as np

from . import protocol
from .connection import MasterError, SlaveBusy, SlaveConnection, connect_slave, describe
from .protocol import MsgType, ProtocolError
from ..scene.model import SceneError, View
from ..scene.scene import Scene
from .tiles import TileGrid, TilePool, partition_tile_size, tile_dims

POLL_S = 0.2             # how often waiting for a scene to load looks at its deadlines
DEFAULT_TILE_SIZE = 64
DEFAULT_TILES_IN_FLIGHT = 2
MAX_TILES_IN_FLIGHT = protocol.MAX_TILES_IN_FLIGHT
# tiles_in_flight="auto": per slave, 1 + as many tiles as it renders in one round trip (the
# least time from a request to its result, less the render time, seen in this frame), at
# least AUTO_IN_FLIGHT and at most AUTO_MAX_IN_FLIGHT: a slave whose tiles take less than a
# round trip gets more requests ahead, one with long tiles does not hoard them.
AUTO_IN_FLIGHT = 2
AUTO_MAX_IN_FLIGHT = 8
# tile_size="auto": the largest of these edges that gives each slave about
# AUTO_TILES_PER_SLAVE tiles (AUTO_SLACK: 16 slaves on 1024 x 1024 get 64-pixel tiles), but
# no smaller than needed to keep a frame within AUTO_MAX_TILES. Eight a slave, not fewer: with
# fewer, the most expensive tile of the bench frame takes as long as a slave's whole share of
# it; at most 256 a frame: the master's own time per tile (about 0.26 ms of a core on the
# bench machine) then stays below a tenth of a 1024 x 1024 frame's (docs/distributed.md,
# "Many slaves": 64 slaves, 1024 tiles of 32 px made the frame slower than 256 of 64 px).
AUTO_TILE_EDGES = (32, 64, 128, 256)
AUTO_TILES_PER_SLAVE = 8
AUTO_MAX_TILES = 256
AUTO_SLACK = 1.25
DEPTH_MISS = 1e10        # the tracer's depth where a pixel sees nothing (kernels/shade/render.cl)
RETRY_DELAYS_S = (0.5, 1.0, 2.0, 4.0, 8.0)   # reconnecting to a lost (or busy) slave
MAX_SPARE_FRAMES = 2     # frames handed back by RenderJob.release() kept for reuse
RESULTS_EVERY_S = 0.02   # RenderJob.next_results returns at most 50 times a second while tiles
                         # come: smooth to watch, and a wake-up takes the tiles that came meanwhile


def auto_tile_size(region, slaves: int) -> tuple:
    """tile_size="auto": square tiles as large as possible while each of `slaves` still gets
    about AUTO_TILES_PER_SLAVE of them, then larger if the frame would have more than about
    AUTO_MAX_TILES. By count, not by measured speed: a slave's pixels per
    second depend as much on which tiles it drew (background or the model: 100 x apart here)
    as on the slave; per-slave speed sets its tiles in flight instead."""
    x0, y0, x1, y1 = region
    share = (x1 - x0) * (y1 - y0) / max(1, slaves)
    fitting = [e for e in AUTO_TILE_EDGES if e * e * AUTO_TILES_PER_SLAVE <= share * AUTO_SLACK]
    edge = max(fitting) if fitting else AUTO_TILE_EDGES[0]
    for larger in AUTO_TILE_EDGES:
        if larger >= edge and len(TileGrid(region, larger)) <= AUTO_MAX_TILES * AUTO_SLACK:
            return (larger, larger)
    return (AUTO_TILE_EDGES[-1],) * 2


def _empty_frame(shape: tuple, passes: tuple, reuse: dict | None = None) -> dict:
    """pass -> the empty float32 frame (zero colour and normal, depth DEPTH_MISS: no surface),
    written into `reuse` (an earlier frame of this shape and passes) when given."""
    if reuse is None:
        return {name: (np.full(shape, DEPTH_MISS, np.float32) if name == "depth" else
                       np.zeros(shape + (protocol.TILE_PASSES[name],), np.float32))
                for name in passes}
    for name, array in reuse.items():
        array.fill(DEPTH_MISS if name == "depth" else 0.0)
    return reuse


@dataclass(frozen=True)
class TileBudget:
    """How long one step of a slave (loading a scene, compiling, waiting for its device,
    rendering one tile) may take before the slave is dropped although it says it is busy:
    base_s for any step, plus s_per_ray for each ray a tile may trace at most (samples x
    (1 + shadow rays) x (1 + bounces) per pixel). Generous: it catches a slave stuck for good,
    never a slow one (the default allows a device 500 times slower than one core here)."""

    base_s: float = 600.0
    s_per_ray: float = 1e-4

    def seconds(self, view: View, w: int, h: int) -> float:
        s = view.settings
        shadow_rays = len(view.shading.lights) * s.light_samples_per_axis ** 2
        rays = w * h * s.max_samples * (1 + shadow_rays) * (1 + s.max_bounces)
        return self.base_s + rays * self.s_per_ray


@dataclass
class TileResult:
    index: int
    x: int
    y: int
    w: int
    h: int
    passes: dict            # the frame's passes ("combined" (h,w,4), "depth" (h,w), "normal" (h,w,3)):
                            # float32 windows of job.image, top row first
    slave_name: str
    slave_id: str
    render_ms: float


@dataclass
class SlaveState:
    """What one slave is doing, for the panel: connecting, uploading, idle, waiting, loading,
    compiling, rendering, reconnecting or lost (`reason` says why)."""
    host: str
    port: int
    name: str
    device: str = ""
    state: str = "connecting"
    reason: str = ""


FROM_ENVIRONMENT = object()   # Master(secret=...) default: read $KDTRACE_SECRET if it is set


def _in_parallel(function, items) -> list:
    """function(item) for each item on its own thread; returns [(item, result or exception)]."""
    outcomes = [None] * len(items)

    def call(i, item):
        try:
            outcomes[i] = (item, function(item))
        except Exception as exc:
            outcomes[i] = (item, exc)

    threads = [threading.Thread(target=call, args=(i, item), daemon=True) for i, item in enumerate(items)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return outcomes


class Master:
    """A set of slave connections that render frames of one scene."""

    def __init__(self, endpoints, connect_timeout: float = 3.0, name: str = "master",
                 secret=FROM_ENVIRONMENT, silence_timeout: float = protocol.SILENCE_S,
                 heartbeat_s: float = protocol.HEARTBEAT_S, tile_budget: TileBudget = TileBudget(),
                 retry_delays=RETRY_DELAYS_S):
        """`secret`: bytes/str shared with the slaves, None for none, default: $KDTRACE_SECRET
        if set. A slave that owes an answer and says nothing for `silence_timeout` seconds is
        dropped (busy slaves say so every `heartbeat_s`), as is one whose step takes longer
        than `tile_budget` allows; either way its tiles go to the others, and the master tries
        to reconnect after each of `retry_delays` (seconds)."""
        self.endpoints = [(str(host), int(port)) for host, port in endpoints]
        self.connect_timeout = connect_timeout
        self.name = name
        if secret is FROM_ENVIRONMENT:
            try:
                secret = protocol.load_secret()
            except protocol.AuthError as exc:
                raise MasterError(str(exc)) from None
        self.secret = secret.encode("utf-8") if isinstance(secret, str) else secret
        low, high = protocol.HEARTBEAT_RANGE_S
        if not low <= heartbeat_s <= high:
            raise MasterError(f"heartbeat interval must be {low} to {high} s, got {heartbeat_s}")
        if not silence_timeout >= 2 * heartbeat_s:
            raise MasterError(f"the silence timeout ({silence_timeout} s) must be at least two "
                              f"heartbeat intervals ({heartbeat_s} s)")
        self.silence_timeout, self.heartbeat_s = float(silence_timeout), float(heartbeat_s)
        self.tile_budget = tile_budget
        self.retry_delays = tuple(retry_delays)
        self.connections: list = []      # every connection made, closed ones too
        self.errors: list = []           # connection and upload problems, readable
        self.scene: Scene | None = None
        self.uploaded_to: list = []      # labels of the slaves the last load_scene uploaded to
                                         # (whole: meshes and instances)
        self.scene_bytes: dict = {}      # label -> bytes sent to make the last scene present
        self._job: RenderJob | None = None
        self._states: dict = {}          # endpoint -> SlaveState
        self._joining: set = set()       # endpoints a thread is connecting to
        self._tile_ms: dict = {}         # (region, tile dims) -> render ms per tile, last frame
        self._frames: _FrameLoop | None = None   # the thread that runs every frame
        self._spare_frames: list = []    # frames handed back (RenderJob.release), for reuse
        self._lock = threading.RLock()
        self._closed = False

    @property
    def scene_hash(self) -> str | None:
        return None if self.scene is None else self.scene.hash

    @property
    def slaves(self) -> list:
        with self._lock:
            return [c for c in self.connections if not c.closed]

    # -- what the panel shows

    def slave_states(self) -> list:
        """A snapshot of what each slave is doing (SlaveState copies), in the order first seen."""
        with self._lock:
            return [SlaveState(**vars(s)) for s in self._states.values()]

    def _set_state(self, endpoint, state: str, reason: str = "", connection=None) -> None:
        with self._lock:
            status = self._states.get(endpoint)
            if status is None:
                status = self._states[endpoint] = SlaveState(endpoint[0], endpoint[1],
                                                             f"{endpoint[0]}:{endpoint[1]}")
            if connection is not None:
                status.name, status.device = connection.name, connection.device
            status.state, status.reason = state, reason

    # -- connecting

    def _dial(self, endpoint) -> SlaveConnection:
        return connect_slave(endpoint[0], endpoint[1], self.connect_timeout, self.name,
                             self.secret, self.heartbeat_s, self.silence_timeout)

    def _connect(self, endpoint, busy_retries: bool = True) -> SlaveConnection:
        """Connect and handshake; a busy slave is asked again after each retry delay."""
        delays = list(self.retry_delays) if busy_retries else []
        self._set_state(endpoint, "connecting")
        while True:
            try:
                connection = self._dial(endpoint)
            except SlaveBusy as exc:
                if not delays or self._closed:
                    self._set_state(endpoint, "lost", str(exc))
                    raise
                self._set_state(endpoint, "reconnecting", str(exc))
                time.sleep(delays.pop(0))
                continue
            except MasterError as exc:
                self._set_state(endpoint, "lost", str(exc))
                raise
            self._set_state(endpoint, "idle", connection=connection)
            return connection

    def connect(self) -> list:
        """Connect to every endpoint; MasterError if none answers. Returns the connections."""
        outcomes = _in_parallel(self._connect, self.endpoints)
        with self._lock:
            for _, outcome in outcomes:
                if isinstance(outcome, SlaveConnection):
                    self.connections.append(outcome)
                else:
                    self.errors.append(str(outcome))
        if not self.slaves:
            raise MasterError("no slave reachable: " + "; ".join(self.errors or ["no endpoints given"]))
        return self.slaves

    def join(self, host: str, port: int) -> None:
        """Bring a slave into this master: found by discovery, restarted, or started late. It
        is connected (a busy one is asked again), given the scene and, when a frame is in
        progress, joins that frame and takes tiles. Returns at once; see slave_states()."""
        endpoint = (str(host), int(port))
        with self._lock:
            if endpoint not in self.endpoints:
                self.endpoints.append(endpoint)
            if any(c.endpoint == endpoint for c in self.slaves):
                return
        self._start_join(endpoint, None, (0.0,) + self.retry_delays)

    def _start_join(self, endpoint, job, delays) -> bool:
        """Connect to `endpoint` on a thread, trying after each of `delays`; `job` (if any)
        waits for the outcome before it may fail for want of slaves. False if a thread is
        already at it."""
        with self._lock:
            if endpoint in self._joining or self._closed:
                return False
            self._joining.add(endpoint)
            if job is None and self._job is not None and not self._job.over:
                job = self._job
            if job is not None:
                job._joins_started()
        threading.Thread(target=self._join_loop, args=(endpoint, job, delays),
                         name=f"join {endpoint[0]}:{endpoint[1]}", daemon=True).start()
        return True

    def _join_loop(self, endpoint, job, delays) -> None:
        reason = "no attempt"
        try:
            for attempt, delay in enumerate(delays, 1):
                self._set_state(endpoint, "connecting" if job is None and attempt == 1
                                else "reconnecting", f"attempt {attempt} of {len(delays)}")
                end = time.monotonic() + delay
                while time.monotonic() < end and not self._closed:
                    time.sleep(min(0.05, max(0.0, end - time.monotonic())))
                if self._closed or (job is not None and job.over):
                    reason = "the frame ended first"
                    return
                try:
                    connection = self._dial(endpoint)
                except MasterError as exc:
                    reason = str(exc)
                    self._set_state(endpoint, "reconnecting", reason)
                    continue
                try:
                    if self.scene is not None:
                        self._ensure_scene(connection, self.scene)
                except Exception as exc:
                    connection.close()
                    reason = describe(exc)
                    self._set_state(endpoint, "reconnecting", reason)
                    continue
                with self._lock:
                    if self._closed:
                        connection.close()
                        reason = "the master was closed"
                        return
                    self.connections.append(connection)
                    current = self._job
                self._set_state(endpoint, "idle", connection=connection)
                if current is not None:
                    current.add_connection(connection)
                reason = None
                return
        finally:
            with self._lock:
                self._joining.discard(endpoint)
            if reason is not None:
                self._set_state(endpoint, "lost", reason)
            if job is not None:
                job._join_over(endpoint, reason)

    # -- the scene

    def load_scene(self, scene: Scene) -> str:
        """Make the scene present on every slave, uploading only where its hash is unknown.
        Slaves that fail are dropped (see .errors). Returns the scene hash."""
        if self._job is not None:
            self._job.wait()  # its frame may still read the sockets (copies being cancelled)
        self.scene = scene
        self.uploaded_to = []
        self.scene_bytes = {}
        for connection, outcome in _in_parallel(lambda c: self._ensure_scene(c, scene), self.slaves):
            if outcome is True:
                self.uploaded_to.append(connection.label)
            elif isinstance(outcome, Exception):
                self.errors.append(f"slave {connection.label} dropped while loading the scene: "
                                   f"{describe(outcome)}")
                self._set_state(connection.endpoint, "lost", describe(outcome))
                connection.close()
        if not self.slaves:
            raise MasterError("no slave could load the scene: " + "; ".join(self.errors))
        return scene.hash

    def _ensure_scene(self, connection: SlaveConnection, scene: Scene) -> bool:
        """Make `scene` present on the slave; True if it was uploaded whole. Where the slave
        holds an instanced scene's meshes (the same meshes_hash: only instances changed), it is
        sent the instance arrays alone (SCENE_INSTANCES; it builds only its top level); where
        it holds some of them, the others (SCENE_MESHES, by mesh hash)."""
        sent_before = connection.channel.bytes_sent
        query = {"scene_hash": scene.hash}
        if scene.meshes_hash is not None:
            query["meshes_hash"] = scene.meshes_hash
        hashes = {"mesh_hashes": scene.mesh_hashes} if scene.meshes_travel_alone else None
        connection.send(MsgType.SCENE_QUERY, query, hashes)
        present, meshes_present, held = self._scene_ready(connection, scene.hash)
        uploaded = False
        # Not present after SCENE_INSTANCES or SCENE_MESHES: the slave let meshes go since it
        # answered; the whole scene is uploaded.
        if not present and meshes_present:
            self._set_state(connection.endpoint, "uploading", connection=connection)
            connection.send(MsgType.SCENE_INSTANCES, query, scene.instance_arrays())
            present = self._scene_ready(connection, scene.hash)[0]
        elif not present and hashes is not None and held is not None and \
                held.shape == (len(scene.mesh_hashes),) and held.any():
            self._set_state(connection.endpoint, "uploading", connection=connection)
            connection.send(MsgType.SCENE_MESHES, {"scene_hash": scene.hash},
                            scene.mesh_wire_arrays(held == 0))
            present = self._scene_ready(connection, scene.hash)[0]
        if not present:
            self._set_state(connection.endpoint, "uploading", connection=connection)
            connection.send(MsgType.SCENE_UPLOAD, {"scene_hash": scene.hash}, scene.wire_arrays())
            if not self._scene_ready(connection, scene.hash)[0]:
                raise MasterError("slave did not accept the scene")
            uploaded = True
        connection.scene_hash = scene.hash
        self.scene_bytes[connection.label] = connection.channel.bytes_sent - sent_before
        self._set_state(connection.endpoint, "idle", connection=connection)
        return uploaded

    def _scene_ready(self, connection: SlaveConnection, scene_hash: str) -> tuple:
        """(present, meshes present, which meshes are held: u1 (M,) or None) from SCENE_READY;
        the slave heartbeats while it validates
        a large upload, within the budget of a step (TileBudget.base_s)."""
        started = heard = time.monotonic()
        while True:
            reply = connection.recv(wait=POLL_S)
            now = time.monotonic()
            if now - started > self.tile_budget.base_s:
                raise MasterError(f"did not load the scene within its budget of "
                                  f"{self.tile_budget.base_s:.0f} s")
            if reply is None:
                if now - heard > self.silence_timeout:
                    raise MasterError(f"did not answer within {self.silence_timeout:g} s")
                continue
            heard = time.monotonic()
            if reply.type == MsgType.HEARTBEAT:
                state = reply.header.get("state")
                if state in protocol.SLAVE_STATES:
                    self._set_state(connection.endpoint, state, connection=connection)
                continue
            if reply.type == MsgType.ERROR:
                raise MasterError(f"slave error: {reply.header.get('message')}")
            if reply.type != MsgType.SCENE_READY or reply.header.get("scene_hash") != scene_hash:
                raise ProtocolError(f"expected SCENE_READY for {scene_hash}, got {reply.type.name}")
            held = reply.arrays.get("mesh_held")
            return (reply.header.get("present") is True,
                    reply.header.get("meshes_present") is True,
                    held if held is not None and held.dtype == np.uint8 else None)

    # -- frames

    def render(self, view: View, tile_size=DEFAULT_TILE_SIZE,
               tiles_in_flight: int = DEFAULT_TILES_IN_FLIGHT, *, partition: int | None = None,
               model: str = protocol.DEFAULT_MODEL, payload: str = "f32",
               compress: bool = False, passes=protocol.ALL_PASSES, duplicates: bool = True,
               hold_when_stranded: bool = False) -> "RenderJob":
        """Start rendering `view` on every connected slave; returns at once with the job.

        tile_size: pixels (int, square tiles, or a (w, h) pair), or "auto" (auto_tile_size:
        about AUTO_TILES_PER_SLAVE tiles per slave); partition=N instead cuts the
        render region into N x N tiles (Table 5b). tiles_in_flight: requests outstanding per
        slave (model 3b), or "auto": per slave, enough to cover a round trip (AUTO_IN_FLIGHT).
        model: "3b" (requests overlap the results, the default) or "3a" (each slave is
        asked for one tile and for the next once that one has arrived: for comparison).
        payload: "f32", "f16" (combined and normal as float16) or "u8" (an 8-bit preview:
        sRGB colour, see protocol); compress: zlib when it pays. passes: the passes the frame
        needs (combined, plus depth and/or normal); only those travel. The tiles are written
        into job.image (name -> float32 array of the render region) as they arrive.
        duplicates: near the end idle slaves take copies of tiles still outstanding elsewhere.
        hold_when_stranded: when every slave is lost and no reconnection is left, the job waits
        (job.stranded) for the caller to join() more slaves or give_up(), instead of failing.
        """
        if self.scene is None:
            raise MasterError("no scene loaded: call load_scene first")
        if model not in protocol.MODELS:
            raise MasterError(f"model must be one of {protocol.MODELS}, got {model!r}")
        if tiles_in_flight != "auto" and not (isinstance(tiles_in_flight, int)
                                              and 1 <= tiles_in_flight <= MAX_TILES_IN_FLIGHT):
            raise MasterError(f"tiles in flight must be 1 to {MAX_TILES_IN_FLIGHT} or 'auto', "
                              f"got {tiles_in_flight!r}")
        if payload not in protocol.PAYLOADS:
            raise MasterError(f"payload must be one of {protocol.PAYLOADS}, got {payload!r}")
        try:
            passes = protocol.check_passes(passes)
            if partition:
                dims = partition_tile_size(view.region, partition)
            elif tile_size == "auto":
                dims = self._auto_tile_size(view)
            else:
                dims = tile_dims(tile_size)
        except ValueError as exc:
            raise MasterError(str(exc)) from None
        if not all(1 <= d <= protocol.MAX_TILE_SIZE for d in dims):
            raise MasterError(f"tile size must be 1 to {protocol.MAX_TILE_SIZE}, got {dims}")
        try:
            self.scene.check_view(view)   # what every slave checks at FRAME_START
        except SceneError as exc:
            raise MasterError(f"the frame cannot be rendered: {exc}") from None
        tiles = TileGrid(view.region, dims)
        if len(tiles) > protocol.MAX_FRAME_TILES:
            raise MasterError(f"{len(tiles)} tiles in the frame, at most {protocol.MAX_FRAME_TILES}: "
                              f"use larger tiles")
        if self._job is not None:
            self._job.wait()  # one reader per socket: the previous frame must be quiet
        problems = self._heal()
        with self._lock:
            slaves = [c for c in self.slaves if c.scene_hash == self.scene.hash]
        if not slaves:
            raise MasterError("no slaves connected: " + ("; ".join(problems) or "none given"))
        # The most expensive tiles of the last frame of this grid first: no long tile starts
        # last and holds up the end of the frame.
        costs = self._tile_ms.get((tuple(view.region), dims))
        order = None if costs is None else sorted(range(len(tiles)), key=lambda i: -(costs[i] or 0.0))
        job = RenderJob(slaves, view, tiles, tiles_in_flight, self.scene.hash,
                        self._frame_loop(), master=self, order=order,
                        model=model, payload=payload, compress=bool(compress), passes=passes,
                        duplicates=duplicates, silence_timeout=self.silence_timeout,
                        tile_budget=self.tile_budget, hold_when_stranded=hold_when_stranded)
        with self._lock:
            self._job = job
        job.start()
        return job

    def _frame_loop(self) -> "_FrameLoop":
        with self._lock:
            if self._frames is None:
                self._frames = _FrameLoop(self.name)
            return self._frames

    def _spare_frame(self, shape: tuple, passes: tuple) -> dict | None:
        """A frame handed back (RenderJob.release) of this shape and passes, or None."""
        with self._lock:
            for i, image in enumerate(self._spare_frames):
                if tuple(image) == passes and image["combined"].shape[:2] == shape:
                    return self._spare_frames.pop(i)
        return None

    def _keep_spare(self, image: dict) -> None:
        with self._lock:
            if not self._closed:
                self._spare_frames = [image] + self._spare_frames[:MAX_SPARE_FRAMES - 1]

    def _auto_tile_size(self, view: View) -> tuple:
        with self._lock:
            count = len(self.slaves)
        return auto_tile_size(view.region, count)

    def _heal(self) -> list:
        """Before a frame: reconnect to endpoints without a live connection (in the background
        while other slaves are there, else at once) and make the scene present where it is
        not. Returns the problems found."""
        with self._lock:
            live = {c.endpoint for c in self.slaves}
            missing = [e for e in self.endpoints if e not in live and e not in self._joining]
        problems = []
        if live:
            for endpoint in missing:
                self._start_join(endpoint, None, (0.0,))
        else:
            for _, outcome in _in_parallel(lambda e: self._connect(e, busy_retries=False), missing):
                if isinstance(outcome, SlaveConnection):
                    with self._lock:
                        self.connections.append(outcome)
                else:
                    problems.append(str(outcome))
        stale = [c for c in self.slaves if c.scene_hash != self.scene.hash]
        for connection, outcome in _in_parallel(lambda c: self._ensure_scene(c, self.scene), stale):
            if isinstance(outcome, Exception):
                problems.append(f"slave {connection.label} dropped while loading the scene: "
                                f"{describe(outcome)}")
                self._set_state(connection.endpoint, "lost", describe(outcome))
                connection.close()
        self.errors += problems
        return problems

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._spare_frames = []
            job = self._job
        if job is not None:
            job.cancel()
            job.wait(5)
        for connection in list(self.connections):
            connection.close(say_bye=True)
        if self._frames is not None:
            self._frames.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _SlaveLost(Exception):
    def __init__(self, reason: str, retry: bool):
        super().__init__(reason)
        self.reason, self.retry = reason, retry


class _FrameLoop:
    """The master's one thread for every frame: it waits on the sockets of all slaves in a
    frame at once (a selector), receives and checks their messages as bytes arrive (a message
    under way waits in its Channel), composes tiles, sends the requests, and wakes for the
    next deadline of any slave (silence, a step's budget, a message arriving too slowly, a
    keep-alive, a held tile becoming overdue for a copy). Other threads hand it work with
    call(). It lives as long as its Master: no thread is started per frame or per slave."""

    def __init__(self, name: str):
        self._selector = selectors.DefaultSelector()
        self._wake_in, self._wake_out = socket.socketpair()
        for end in (self._wake_in, self._wake_out):
            end.setblocking(False)
        self._selector.register(self._wake_in, selectors.EVENT_READ, None)
        self._calls: collections.deque = collections.deque()
        self._workers: set = set()      # the slaves whose sockets it reads now
        self._due = math.inf            # the next sweep over the slaves' deadlines
        self._stopped = False
        self.thread = threading.Thread(target=self._run, name=f"frames of {name}", daemon=True)
        self.thread.start()

    def call(self, function, *args) -> None:
        """Run function(*args) on the loop's thread, after what it is doing now."""
        self._calls.append((function, args))
        try:
            self._wake_out.send(b"\0")
        except OSError:          # full (a wake-up is pending anyway) or closed (stopped)
            pass

    def register(self, worker: "_SlaveWorker") -> None:
        self._selector.register(worker.connection.channel.sock, selectors.EVENT_READ, worker)
        self._workers.add(worker)

    def unregister(self, worker: "_SlaveWorker") -> None:
        if worker in self._workers:
            self._workers.discard(worker)
            self._selector.unregister(worker.connection.channel.sock)

    def wake_by(self, when: float | None) -> None:
        if when is not None and when < self._due:
            self._due = when

    def stop(self) -> None:
        self._stopped = True
        self.call(lambda: None)
        self.thread.join(5)
        self._selector.close()
        self._wake_in.close()
        self._wake_out.close()

    def _run(self) -> None:
        while not self._stopped:
            timeout = None if self._due == math.inf else max(0.0, self._due - time.monotonic())
            for key, _ in self._selector.select(timeout):
                if key.data is None:
                    try:
                        while self._wake_in.recv(4096):
                            pass
                    except BlockingIOError:
                        pass
                elif key.data in self._workers:     # not released by an earlier event
                    self._safely(key.data.readable)
            while self._calls:
                function, args = self._calls.popleft()
                self._safely(function, *args)
            if time.monotonic() >= self._due:
                self._safely(self._sweep)

    @staticmethod
    def _safely(function, *args) -> None:
        # A slave's steps drop that slave on any exception (_SlaveWorker._guarded); anything
        # else that fails is a bug, reported, and must not stop every later frame.
        try:
            function(*args)
        except Exception:
            traceback.print_exc()

    def _sweep(self) -> None:
        now, due = time.monotonic(), math.inf
        for worker in list(self._workers):
            worker.sweep(now)
            when = worker.due()
            if when is not None:
                due = min(due, when)
        self._due = due


class _SlaveWorker:
    """One slave's part in one job, run on the master's frame loop: its tiles in flight, what
    it says it is doing and the deadlines it owes. Model 3b keeps `window` requests
    outstanding and sends the next request as a tile arrives, before it is composed; model 3a
    asks for one tile and the next only once that one has been composed."""

    def __init__(self, job: "RenderJob", connection: SlaveConnection):
        self.job, self.connection = job, connection
        self.in_flight: set = set()
        self.alive = True
        self.begun = False              # FRAME_START sent (or being sent)
        self.released = False           # its socket no longer read for this job
        self.cancelling = False         # waiting for the slave to confirm a cancel
        self.cancel_sent = False
        self.last_heard = time.monotonic()
        self._new_step(None, self.last_heard)   # (state, tile) the slave last said it was at
        self.tiles_done = 0
        self.render_s, self.tiles_rendered = 0.0, 0     # this frame: seconds of render, tiles
        self.requested_at: dict = {}    # tile -> when its request went out
        self.round_trip_s = None        # least (result - request - render) this frame
        if job.model == "3a":
            self.window = 1
        else:
            self.window = DEFAULT_TILES_IN_FLIGHT if job.tiles_in_flight == "auto" else job.tiles_in_flight

    # -- what the frame loop calls

    def begin(self) -> None:
        if self.job.over:
            self._release()
            return
        self._guarded(self._start)

    def _start(self) -> None:
        job = self.job
        self.begun = True
        job.loop.register(self)
        channel = self.connection.channel
        with channel.batch():       # FRAME_START and the first requests in one write
            channel.send_encoded(job.frame_start)
            self._fill()

    def readable(self) -> None:
        self._guarded(self._receive)

    def _receive(self) -> None:
        for msg in self.connection.channel.recv_available(self.job.limits, protocol.SLAVE_TO_MASTER):
            self._handle(msg)
            if not self.alive:
                return

    def sweep(self, now: float) -> None:
        self._guarded(self._check, now)

    def _check(self, now: float) -> None:
        self._check_deadlines(now)
        self.connection.channel.check_incoming()
        if not self.job.over:
            if len(self.in_flight) < self.window:
                self._fill()
            self._keep_alive()

    def due(self) -> float | None:
        """When this slave needs looking at next, unless a message comes first."""
        if self.released:
            return None
        job, arriving = self.job, self.connection.channel.incoming_due()
        times = [arriving]
        if self.in_flight or self.cancelling:
            times.append(self.step_since + self.step_budget)
            if arriving is None:
                times.append(self.last_heard + job.silence_timeout)
        if not job.over:
            if not self.in_flight:
                times.append(self.connection.channel.last_sent + protocol.KEEPALIVE_S)
            if len(self.in_flight) < self.window and job.duplicates and not job.pool.has_pending:
                times.append(job.pool.copy_due(self))
        times = [t for t in times if t is not None]
        return min(times) if times else None

    def _guarded(self, step, *args) -> None:
        """Any exception in a step for this slave drops this slave, with the reason: a frame
        never waits on a slave whose handling failed."""
        try:
            step(*args)
        except _SlaveLost as exc:
            self.lose(exc.reason, exc.retry)
        except Exception as exc:
            self.lose(describe(exc), protocol.is_transient(exc))
        self._settle()
        self.job.loop.wake_by(self.due())

    def _settle(self) -> None:
        """Once the frame is over: cancel copies still out (and everything on a cancel), and
        stop reading once nothing is owed."""
        job = self.job
        if self.released or not self.begun:    # not begun: begin() lets it go
            return
        if not job.over:
            if not self.alive:
                self._release()
            return
        if self.alive and not self.cancelling and not self.cancel_sent and (
                self.in_flight or job.cancelled):
            self.cancel()
        if not self.alive or not (self.in_flight or self.cancelling):
            self._release()

    def _release(self) -> None:
        if self.released:
            return
        self.released = True
        self.job.loop.unregister(self)
        master = self.job.master
        if self.alive and master is not None:
            master._set_state(self.connection.endpoint, "idle", connection=self.connection)
        self.job._worker_released()

    # -- tiles

    def _fill(self) -> None:
        """Requests up to the window: the most expensive pending tiles, a cheap one for a slot
        beside another at the start of the frame (to hide the request's latency, see
        TilePool's order), copies of overdue tiles once nothing is pending."""
        job = self.job
        while self.alive and not job.over and len(self.in_flight) < self.window:
            index = self._take(copies=True, cheap=bool(self.in_flight))
            if index is None:
                return
            self._request(index)

    def _take(self, copies: bool, cheap: bool) -> int | None:
        job = self.job
        index = job.pool.take(0, holder=self, duplicates=copies and job.duplicates, cheap=cheap)
        if index is not None:
            if not self.in_flight:      # the deadlines run from the first request
                self.last_heard = time.monotonic()
                self._new_step(None, self.last_heard)
            self.in_flight.add(index)
        return index

    def _request(self, index: int) -> None:
        self.requested_at[index] = time.monotonic()
        self.connection.send(MsgType.TILE_REQUEST, {"frame_id": self.job.frame_id, "tile": index})

    def _keep_alive(self) -> None:
        """A slave with nothing to render while the frame goes on elsewhere (the last tiles
        take long) stays in the frame: tell it before its idle deadline closes the connection."""
        if not self.in_flight and time.monotonic() - self.connection.channel.last_sent >= protocol.KEEPALIVE_S:
            self.connection.send(MsgType.HEARTBEAT, {})

    def _auto_window(self) -> None:
        """tiles_in_flight="auto" (see AUTO_IN_FLIGHT)."""
        tile_s = self.render_s / max(1, self.tiles_rendered)
        trip = max(0.0, self.round_trip_s or 0.0)
        window = 1 + math.ceil(trip / tile_s) if tile_s > 0 else AUTO_MAX_IN_FLIGHT
        self.window = min(AUTO_MAX_IN_FLIGHT, max(AUTO_IN_FLIGHT, window))

    # -- deadlines

    def _check_deadlines(self, now: float) -> None:
        # A cancel is confirmed after the tile being rendered: owed like a tile, so the same
        # liveness rules apply (a slave finishing a long tile says so in its heartbeats).
        if not (self.in_flight or self.cancelling):
            return
        # A message under way is not silence: its own transfer deadline applies to it.
        silence = self.job.silence_timeout
        if now - self.last_heard > silence and self.connection.channel.incoming_due() is None:
            raise _SlaveLost(f"did not answer within {silence:g} s", retry=True)
        if now - self.step_since > self.step_budget:
            budget, what = self._budget()
            raise _SlaveLost(f"{what} took longer than its budget of {budget:.0f} s", retry=False)

    def _new_step(self, step, now: float) -> None:
        self.step, self.step_since = step, now
        self.step_budget = self._budget()[0]

    def _budget(self) -> tuple:
        """(seconds, what) the current step may take."""
        job = self.job
        state, tile = self.step or ("rendering", None)
        if state != "rendering":
            return job.tile_budget.base_s, state
        if tile is not None and 0 <= tile < len(job.tiles):
            _, _, w, h = job.tiles[tile]
            return job.tile_budget.seconds(job.view, w, h), f"tile {tile}"
        return job.tile_budget.seconds(job.view, job.tile_w, job.tile_h), "a tile"

    # -- messages

    def _handle(self, msg: protocol.Message) -> None:
        job, h = self.job, msg.header
        now = self.last_heard = time.monotonic()
        if msg.type == MsgType.HEARTBEAT:
            self._heartbeat(h, now)
            return
        if msg.type == MsgType.CANCEL:
            if h.get("frame_id") == job.frame_id:
                self.cancelling = False
                for index in self.in_flight:  # the slave dropped what it had not rendered
                    job.pool.put_back(index, self)
                self.in_flight.clear()
            return
        if msg.type == MsgType.ERROR:
            raise ProtocolError(f"slave error: {h.get('message')}")
        if msg.type != MsgType.TILE_RESULT:
            raise ProtocolError(f"unexpected {msg.type.name} during a frame")
        if protocol.get_int(h, "frame_id") != job.frame_id:
            return  # a late tile of an earlier, cancelled frame
        index = protocol.get_int(h, "tile", 0, len(job.tiles) - 1)
        if index not in self.in_flight:
            if self.cancelling or job.cancelled:
                return
            raise ProtocolError(f"sent tile {index}, which was not asked of it")
        x, y, w, h_ = job.tiles[index]
        if [h.get(k) for k in ("x", "y", "w", "h")] != [x, y, w, h_]:
            raise ProtocolError(f"tile {index} has the wrong rectangle")
        render_ms = protocol.get_float(h, "render_ms")
        # Model 3b: the next request goes out before this tile is composed, so the slave's
        # queue refills at once (the most expensive pending tile: it starts after the ones
        # queued there).
        if job.model == "3b" and not job.over and len(self.in_flight) - 1 < self.window:
            following = self._take(copies=False, cheap=False)
            if following is not None:
                self._request(following)
        # Checked, then written straight into the frame; a copy of a tile another slave
        # delivered first is checked only (an honest copy has the same bits anyway).
        windows = job.windows(x, y, w, h_)
        protocol.decode_tile(h, msg.arrays, w, h_, job.payload, job.passes,
                             out=None if job.pool.is_done(index) else windows)
        self.render_s += max(render_ms, 0.0) / 1000.0
        self.tiles_rendered += 1
        self.in_flight.discard(index)
        self._new_step(None, now)
        sent = self.requested_at.pop(index, None)
        if sent is not None:
            trip = now - sent - max(render_ms, 0.0) / 1000.0
            self.round_trip_s = trip if self.round_trip_s is None else min(self.round_trip_s, trip)
        if job.tiles_in_flight == "auto" and job.model == "3b" and self.render_s > 0:
            self._auto_window()
        if job.cancelled:
            return
        job.tile_ms[index] = render_ms     # before the frame can be complete
        if job.pool.mark_done(index):
            self.tiles_done += 1
            job._rejoined.discard(self.connection.endpoint)
            job._deliver(TileResult(index, x, y, w, h_, windows, self.connection.name,
                                    self.connection.id, render_ms))
        self._fill()
        if job.duplicates and not job.over and not job.pool.has_pending:
            job.loop.wake_by(job.pool.copy_due())   # the typical tile time changed

    def _heartbeat(self, h: dict, now: float) -> None:
        state = h.get("state")
        if state not in protocol.SLAVE_STATES:
            raise ProtocolError(f"heartbeat with an unknown state {str(state)[:32]!r}")
        frame_id = h.get("frame_id")
        if frame_id is not None and protocol.get_int(h, "frame_id") != self.job.frame_id:
            return   # still busy with an earlier frame: alive, but no step of ours
        tile = protocol.get_int(h, "tile", 0, len(self.job.tiles) - 1) if "tile" in h else None
        if (state, tile) != self.step:
            self._new_step((state, tile), now)
            master = self.job.master
            if master is not None:
                master._set_state(self.connection.endpoint, state, connection=self.connection)

    def cancel(self) -> None:
        if not self.alive or self.cancelling:
            return
        self.cancelling = self.cancel_sent = True
        if not self.in_flight:      # owed from now on
            self.last_heard = time.monotonic()
            self._new_step(None, self.last_heard)
        try:
            self.connection.send(MsgType.CANCEL, {"frame_id": self.job.frame_id})
        except (OSError, ProtocolError) as exc:
            self.lose(f"send failed ({describe(exc)})", retry=True)

    def lose(self, reason: str, retry: bool = False) -> None:
        """Drop this slave: its tiles go back to the pool for the others; with `retry` the
        master tries to reconnect and bring it back into the frame."""
        if not self.alive:
            return
        self.alive = False
        lost = sorted(self.in_flight)
        self.in_flight.clear()
        self.cancelling = False
        self.job.loop.unregister(self)
        self.connection.close()
        for index in lost:
            self.job.pool.put_back(index, self)
        self.job._slave_lost(self, reason, retry)
        self._release()      # after the loss is recorded: wait() may return from here on
        if lost:
            self.job._offer()


class RenderJob:
    """One frame in progress, run by the master's frame loop; the caller polls next_result()."""

    def __init__(self, connections: list, view: View, tiles: TileGrid, tiles_in_flight,
                 scene_hash: str, loop: _FrameLoop, master: Master | None = None,
                 model: str = protocol.DEFAULT_MODEL, payload: str = "f32",
                 compress: bool = False, passes=protocol.ALL_PASSES, duplicates: bool = True,
                 silence_timeout: float = protocol.SILENCE_S,
                 tile_budget: TileBudget = TileBudget(), hold_when_stranded: bool = False,
                 order=None):
        self.master, self.loop = master, loop
        self.view, self.view_dict, self.tiles_in_flight = view, view.to_dict(), tiles_in_flight
        self.tiles = tiles
        self.tile_w, self.tile_h = tiles.tile_w, tiles.tile_h
        self.model, self.payload, self.compress = model, payload, compress
        self.passes = protocol.check_passes(passes)
        # The frame, composed by the frame loop as tiles arrive (what is not rendered stays
        # empty: zero colour, no surface).
        x0, y0, x1, y1 = view.region
        self.origin, shape = (x0, y0), (y1 - y0, x1 - x0)
        spare = None if master is None else master._spare_frame(shape, self.passes)
        self.image = _empty_frame(shape, self.passes, spare)
        self._released = False
        self.duplicates, self.silence_timeout = duplicates, silence_timeout
        self.tile_budget, self.hold_when_stranded = tile_budget, hold_when_stranded
        self.scene_hash = scene_hash
        self.frame_id = uuid.uuid4().int >> 65   # unique across masters and renders; fits JSON ints
        self.frame_start = protocol.encode_message(MsgType.FRAME_START, {   # the same for all
            "frame_id": self.frame_id, "scene_hash": scene_hash, "view": self.view_dict,
            "tile_size": self.tile_w, "tile_height": self.tile_h, "model": model,
            "payload": payload, "compress": compress, "passes": list(self.passes)})
        self.pool = TilePool(len(self.tiles), max_copies=2 if duplicates else 1, order=order)
        self.tile_ms = [None] * len(self.tiles)   # render ms of each delivered tile
        self.limits = protocol.Limits(
            max_tile_pixels=self.tile_w * self.tile_h,
            tile_bytes_per_pixel=protocol.tile_bytes_per_pixel(payload, self.passes))
        self.errors: list = []       # every problem, including slaves lost and recovered from
        self.error: str | None = None  # set when the frame cannot be finished
        self.cancelled = False
        self.stranded = False        # no slave left, none reconnecting (hold_when_stranded)
        self.started = time.monotonic()
        self.first_tile_s: float | None = None   # seconds from start to the first result
        self.elapsed_s: float | None = None      # seconds from start to the last tile
        self._results: queue.Queue = queue.Queue()
        self._results_returned = -math.inf     # when next_results last returned
        self._delivered = self._taken = 0
        self._joins = 0              # reconnections under way that may still bring a slave
        self._rejoined: set = set()  # endpoints reconnected after a loss, no tile since
        self._over = threading.Event()
        self._quiet = threading.Event()   # over, and no slave's socket read for it any more
        self._lock = threading.Lock()
        self._workers = [_SlaveWorker(self, c) for c in connections]

    def start(self) -> None:
        for worker in list(self._workers):
            self._start_worker(worker)

    def windows(self, x: int, y: int, w: int, h: int) -> dict:
        """name -> the tile's window of job.image."""
        left, top = x - self.origin[0], y - self.origin[1]
        return {name: image[top:top + h, left:left + w] for name, image in self.image.items()}

    def _start_worker(self, worker: _SlaveWorker) -> None:
        if self.master is not None:
            self.master._set_state(worker.connection.endpoint, "waiting",
                                   connection=worker.connection)
        self.loop.call(worker.begin)

    def add_connection(self, connection: SlaveConnection) -> bool:
        """Let a slave that connected after the start (reconnected, or found later) take tiles
        of this frame; False if the frame is over or the slave lacks its scene."""
        if connection.scene_hash != self.scene_hash or connection.closed:
            return False
        with self._lock:
            if self._over.is_set():
                return False
            worker = _SlaveWorker(self, connection)
            self._workers.append(worker)
            self.stranded = False
        self._start_worker(worker)
        return True

    # -- the caller's side

    @property
    def over(self) -> bool:
        """No more tiles will be produced (all done, cancelled or failed)."""
        return self._over.is_set()

    @property
    def finished(self) -> bool:
        """Over, and every produced result has been taken with next_result()."""
        with self._lock:
            return self._over.is_set() and self._taken == self._delivered

    @property
    def progress(self) -> tuple:
        return self.pool.done_count, len(self.tiles)

    @property
    def tiles_by_slave(self) -> dict:
        counts: dict = {}
        for worker in list(self._workers):
            label = worker.connection.label
            counts[label] = counts.get(label, 0) + worker.tiles_done
        return counts

    @property
    def duplicates_handed_out(self) -> int:
        return self.pool.duplicates_handed_out

    def next_result(self, timeout: float | None = None) -> TileResult | None:
        """The next finished tile, or None after `timeout` seconds or once the job is over."""
        try:
            result = self._results.get(timeout=timeout)
        except queue.Empty:
            return None
        if result is None:
            self._results.put(None)  # keep the end marker for later callers
            return None
        with self._lock:
            self._taken += 1
        return result

    def next_results(self, timeout: float | None = None) -> list:
        """The finished tiles waiting, within `timeout` seconds ([] if none came, or once the
        job is over), no sooner than RESULTS_EVERY_S after the last call returned while the
        frame goes on: a caller that shows tiles (the add-on's render thread) wakes once for
        the tiles that came meanwhile, not once a tile (64 slaves deliver 256 tiles in 0.2 s;
        every wake-up also costs the frame loop a hand-over of the interpreter)."""
        started = time.monotonic()
        pause = self._results_returned + RESULTS_EVERY_S - started
        if pause > 0 and not self._over.is_set():
            time.sleep(pause if timeout is None else min(pause, timeout))
        left = None if timeout is None else max(0.0, started + timeout - time.monotonic())
        results = []
        result = self.next_result(left)
        while result is not None:
            results.append(result)
            result = self.next_result(0)
        self._results_returned = time.monotonic()
        return results

    def cancel(self) -> None:
        """Stop the frame; every slave is told and confirms (see wait())."""
        with self._lock:
            if self._over.is_set():
                return
            self.cancelled = True
        self._end()

    def give_up(self) -> None:
        """End a stranded frame (hold_when_stranded) with its error."""
        with self._lock:
            if self._over.is_set():
                return
            self.error = self._lost_message()
        self._end()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the frame is over and no slave owes it anything more (copies and
        cancels confirmed); True if so."""
        return self._quiet.wait(timeout)

    def release(self) -> None:
        """The caller is done with job.image and its TileResults' passes: the master writes a
        later frame of the same size and passes into that memory (a new frame's 16 MiB would
        otherwise fault in page by page as tiles arrive). The memory is handed over, and
        job.image set to None, once the frame is quiet (no late tile can be written into it)."""
        with self._lock:
            if self._released:
                return
            self._released = True
        self._hand_back()

    # -- the frame loop's side

    def _deliver(self, result: TileResult) -> None:
        with self._lock:
            self._delivered += 1
            now = time.monotonic() - self.started
            if self.first_tile_s is None:
                self.first_tile_s = now
        self._results.put(result)
        if self.pool.all_done:
            self.elapsed_s = now
            if self.master is not None:
                self.master._tile_ms[(tuple(self.view.region), (self.tile_w, self.tile_h))] = \
                    list(self.tile_ms)
            self._end()

    def _offer(self) -> None:
        """Tiles went back to the pool: slaves with a free slot take them."""
        for worker in list(self._workers):
            if worker.alive and worker.begun and not worker.released:
                worker._guarded(worker._fill)

    def _worker_released(self) -> None:
        with self._lock:
            if self._over.is_set() and all(w.released for w in self._workers):
                self._quiet.set()
        self._hand_back()

    def _hand_back(self) -> None:
        """Once released by the caller and quiet: the frame's memory goes to the master."""
        with self._lock:
            if not (self._released and self._quiet.is_set()) or self.image is None:
                return
            image, self.image = self.image, None
        if self.master is not None:
            self.master._keep_spare(image)

    def _slave_lost(self, worker: _SlaveWorker, reason: str, retry: bool) -> None:
        """A slave that drops is reconnected to, once per loss; one that drops again before
        it delivers a tile is not tried again in this frame (it would only fail again)."""
        connection = worker.connection
        with self._lock:
            self.errors.append(f"slave {connection.label} lost: {reason}")
            retry = retry and not self._over.is_set() and (
                worker.tiles_done > 0 or connection.endpoint not in self._rejoined)
            if retry:
                self._rejoined.add(connection.endpoint)
        if self.master is not None:
            self.master._set_state(connection.endpoint, "lost", reason, connection)
            if retry:
                self.master._start_join(connection.endpoint, self, self.master.retry_delays)
        self._check_stranded()

    def _joins_started(self) -> None:
        with self._lock:
            self._joins += 1

    def _join_over(self, endpoint, reason: str | None) -> None:
        with self._lock:
            self._joins -= 1
            if reason is not None and not self._over.is_set():
                self.errors.append(f"reconnecting to {endpoint[0]}:{endpoint[1]} failed: {reason}")
        self._check_stranded()

    def _lost_message(self) -> str:
        return "all slaves lost before the frame was finished: " + "; ".join(self.errors)

    def _check_stranded(self) -> None:
        """Fail the frame (or, with hold_when_stranded, wait for help) once no slave is left
        and no reconnection is under way."""
        with self._lock:
            if self._over.is_set() or self._joins or any(w.alive for w in self._workers):
                return
            if self.hold_when_stranded:
                self.stranded = True
                return
            self.error = self._lost_message()
        self._end()

    def _end(self) -> None:
        with self._lock:
            if self._over.is_set():
                return
            self._over.set()
        self.pool.close()
        self._results.put(None)
        self.loop.call(self._wind_down)

    def _wind_down(self) -> None:
        """On the frame loop, once the frame is over: each slave cancels what it still has
        (copies, or everything on a cancel) and is let go once it owes nothing."""
        for worker in list(self._workers):
            if not worker.released:
                worker._settle()
                if not worker.released:
                    self.loop.wake_by(worker.due())
        self._worker_released()
