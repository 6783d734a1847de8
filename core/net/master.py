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

The master's other modules, one job each: connection.py (a handshaken slave), frame_loop.py
(the one thread), slave_worker.py (one slave's part in a frame, as one explicit state) and
render_job.py (the frame and the caller's side of it).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from . import protocol, trust
from .connection import (MasterError, SlaveBusy, SlaveConnection, SlaveNotApproved, connect_slave,
                         describe)
from .frame_loop import FrameLoop
from .identity import Identity
from .protocol import MsgType, ProtocolError
from .render_job import RenderJob, SpareFrames, TileBudget
from .slave_worker import DEFAULT_TILES_IN_FLIGHT
from ..scene.model import SceneError, View
from ..scene.scene import Scene
from .tiles import TileGrid, fit_tile_work, partition_tile_size, tile_dims

POLL_S = 0.2             # how often waiting for a scene to load looks at its deadlines
# Per-slave upload deadline: a slave makes a scene present (the query, the transfer and its
# validation) within UPLOAD_BASE_S plus the bytes sent at UPLOAD_MIN_BPS, or is dropped for
# the frame (a slave that reads a scene slowly, above the channel's own minimum rate, no
# longer holds up everyone else's frame for hours).
UPLOAD_BASE_S = 60.0
UPLOAD_MIN_BPS = 1 << 20
DEFAULT_TILE_SIZE = 64
MAX_TILES_IN_FLIGHT = protocol.MAX_TILES_IN_FLIGHT
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
RETRY_DELAYS_S = (0.5, 1.0, 2.0, 4.0, 8.0)   # reconnecting to a lost (or busy) slave
# At most this many slaves (endpoints) a master; one thread at most per endpoint while it
# connects. More (a LAN where anyone can advertise) are refused with a message, not served.
MAX_SLAVES = 64


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


class LoadCancelled(MasterError):
    """load_scene's `cancelled()` said so (Esc): the uploads under way were abandoned."""


def _in_parallel(function, items, cancelled=None, deadline=None, give_up=None) -> list:
    """function(item) for each item on its own thread; returns [(item, result or exception)].
    The caller's thread waits, and every POLL_S looks at `cancelled()` (true: give_up(item,
    why) for each item still running, then LoadCancelled) and at `deadline(item)` (a
    time.monotonic(), or None: past it, give_up(item, why) for that item, whose function
    then fails)."""
    outcomes = [None] * len(items)

    def call(i, item):
        try:
            outcomes[i] = (item, function(item))
        except Exception as exc:
            outcomes[i] = (item, exc)

    threads = [threading.Thread(target=call, args=(i, item), daemon=True) for i, item in enumerate(items)]
    for thread in threads:
        thread.start()
    while True:
        running = [(thread, item) for thread, item in zip(threads, items) if thread.is_alive()]
        if not running:
            return outcomes
        running[0][0].join(POLL_S)
        if cancelled is not None and cancelled():
            for thread, item in running:
                give_up(item, "cancelled")
            for thread, _ in running:
                thread.join(2.0)     # its socket is closed: it ends within a poll of its own
            raise LoadCancelled("cancelled while the scene was being sent")
        now = time.monotonic()
        for thread, item in running:
            due = None if deadline is None else deadline(item)
            if due is not None and now > due:
                give_up(item, "deadline")


def _mesh_proofs(scene: Scene, held, nonce: str) -> np.ndarray:
    """u1 (M, 16): for each mesh the slave takes from its cache (held), the proof that this
    master holds it; zeros for the meshes that travel."""
    proofs = np.zeros((len(held), trust.MESH_PROOF_BYTES), np.uint8)
    for m, ((geometry, _), digest) in enumerate(zip(scene.mesh_parts, scene.mesh_hashes)):
        if held[m]:
            proofs[m] = np.frombuffer(trust.mesh_holder_proof(
                geometry.content_hash(), bytes(digest), nonce), np.uint8)
    return proofs


class Master:
    """A set of slave connections that render frames of one scene."""

    def __init__(self, endpoints, connect_timeout: float = 3.0, name: str = "master",
                 secret=FROM_ENVIRONMENT, silence_timeout: float = protocol.SILENCE_S,
                 heartbeat_s: float = protocol.HEARTBEAT_S, tile_budget: TileBudget = TileBudget(),
                 retry_delays=RETRY_DELAYS_S, *, identity: Identity | None = None,
                 approved_slaves=(), pairing: dict | None = None):
        """`secret`: the farm secret (generated: trust.new_farm_secret), None for none,
        default: $KDTRACE_SECRET if set. `identity`: this master's (the add-on's, kept in its
        user folder; None: a new one for this master only). A slave gets a scene only if its
        ID is in `approved_slaves` (IDs or their first 16+ characters, or a trust.AllowList),
        is a key of `pairing` (slave ID -> the pairing code its owner gave) or it proves the
        farm secret; any other is refused and listed in `unapproved`. A slave that owes an
        answer and says nothing for `silence_timeout` seconds is dropped (busy slaves say so
        every `heartbeat_s`), as is one whose step takes longer than `tile_budget` allows;
        either way its tiles go to the others, and the master tries to reconnect after each
        of `retry_delays` (seconds)."""
        self.endpoints = [(str(host), int(port)) for host, port in endpoints]
        self.connect_timeout = connect_timeout
        self.name = trust.sanitize(name)
        if secret is FROM_ENVIRONMENT:
            try:
                secret = trust.load_secret()
            except trust.AuthError as exc:
                raise MasterError(str(exc)) from None
        elif isinstance(secret, (str, bytes)):
            raw = secret.encode("utf-8") if isinstance(secret, str) else secret
            try:
                secret = trust.check_farm_secret(raw.strip(), "the secret given to the master")
            except trust.AuthError as exc:
                raise MasterError(str(exc)) from None
        self.secret = secret
        self.identity = identity or Identity.ephemeral("master")
        self.approved = (approved_slaves if isinstance(approved_slaves, trust.AllowList)
                         else trust.AllowList(approved_slaves))
        self.pairing = dict(pairing or {})
        self.unapproved: dict = {}       # endpoint -> ID of a slave refused as not approved
        if len(self.endpoints) > MAX_SLAVES:
            raise MasterError(f"{len(self.endpoints)} slaves given, at most {MAX_SLAVES}")
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
        self._frames: FrameLoop | None = None   # the thread that runs every frame
        self._spares = SpareFrames()     # frames handed back (RenderJob.release), for reuse
        self._lock = threading.RLock()
        self._closed = False
        self._upload_due: dict = {}      # connection -> its upload deadline (time.monotonic())
        self._upload_lost: dict = {}     # connection -> why its upload was given up

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
        try:
            connection = connect_slave(endpoint[0], endpoint[1], self.connect_timeout, self.name,
                                       self.secret, self.heartbeat_s, self.silence_timeout,
                                       identity=self.identity, approved=self.approved,
                                       pairing=self.pairing)
        except SlaveNotApproved as exc:
            with self._lock:
                self.unapproved[endpoint] = exc.slave_id
            raise
        with self._lock:
            self.unapproved.pop(endpoint, None)
        return connection

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
                if len(self.endpoints) >= MAX_SLAVES:
                    self.errors.append(f"slave {host}:{port} not used: this master has "
                                       f"{MAX_SLAVES} slaves already")
                    return
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
                job.join_started()
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
                except SlaveNotApproved as exc:
                    reason = str(exc)       # asking again changes nothing
                    return
                except MasterError as exc:
                    reason = str(exc)
                    self._set_state(endpoint, "reconnecting", reason)
                    continue
                outcome = None if self.scene is None else \
                    self._make_present([connection], self.scene)[0][1]
                if isinstance(outcome, Exception):
                    connection.close()
                    reason = self._upload_failure(connection, outcome)
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
                job.join_over(endpoint, reason)

    # -- the scene

    def load_scene(self, scene: Scene, cancelled=None) -> str:
        """Make the scene present on every slave, uploading only where its hash is unknown.
        Slaves that fail, or do not take the scene within their upload deadline
        (UPLOAD_BASE_S + its bytes at UPLOAD_MIN_BPS), are dropped (see .errors). `cancelled`:
        a function polled every POLL_S while the slaves load (Esc); when it returns true the
        uploads under way are abandoned (their connections closed) and LoadCancelled is
        raised. Returns the scene hash."""
        if self._job is not None:
            self._job.wait()  # its frame may still read the sockets (copies being cancelled)
        self.scene = scene
        self.uploaded_to = []
        self.scene_bytes = {}
        for connection, outcome in self._make_present(self.slaves, scene, cancelled):
            if outcome is True:
                self.uploaded_to.append(connection.label)
            elif isinstance(outcome, Exception):
                reason = self._upload_failure(connection, outcome)
                self.errors.append(f"slave {connection.label} dropped while loading the scene: "
                                   f"{reason}")
                self._set_state(connection.endpoint, "lost", reason)
                connection.close()
        if not self.slaves:
            raise MasterError("no slave could load the scene: " + "; ".join(self.errors))
        return scene.hash

    def _make_present(self, connections: list, scene: Scene, cancelled=None) -> list:
        """_ensure_scene on each connection at once, each within its upload deadline, Esc
        polled (_in_parallel); [(connection, True, False or the exception)]."""
        def give_up(connection, why):
            if why == "deadline":
                with self._lock:
                    self._upload_lost[connection] = (
                        f"did not take the scene within its upload deadline ({UPLOAD_BASE_S:.0f} "
                        f"s + {UPLOAD_MIN_BPS / 2 ** 20:.0f} s a MiB)")
            connection.close()
        try:
            outcomes = _in_parallel(lambda c: self._ensure_scene(c, scene), connections,
                                    cancelled, self._upload_due.get, give_up)
            with self._lock:
                for connection, outcome in outcomes:
                    if not isinstance(outcome, Exception):  # it made it after all
                        self._upload_lost.pop(connection, None)
            return outcomes
        except LoadCancelled:
            for connection in connections:
                if connection.closed:
                    self._set_state(connection.endpoint, "lost", "the scene upload was cancelled")
            raise

    def _upload_failure(self, connection: SlaveConnection, exc: Exception) -> str:
        """Why making the scene present on `connection` failed, for the user."""
        with self._lock:
            return self._upload_lost.pop(connection, None) or describe(exc)

    def _upload_deadline(self, connection: SlaveConnection, nbytes: int = 0) -> None:
        """The connection's upload deadline: from now (nbytes 0), or `nbytes` later."""
        with self._lock:
            if nbytes:
                self._upload_due[connection] += nbytes / UPLOAD_MIN_BPS
            else:
                self._upload_due[connection] = time.monotonic() + UPLOAD_BASE_S

    def _ensure_scene(self, connection: SlaveConnection, scene: Scene) -> bool:
        """Make `scene` present on the slave; True if it was uploaded whole. Where the slave
        holds an instanced scene's meshes (the same meshes_hash: only instances changed), it is
        sent the instance arrays alone (SCENE_INSTANCES; it builds only its top level); where
        it holds some of them, the others (SCENE_MESHES, by mesh hash). Within the
        connection's upload deadline (_make_present watches it)."""
        self._upload_deadline(connection)
        try:
            return self._send_scene(connection, scene)
        finally:
            with self._lock:
                self._upload_due.pop(connection, None)

    def _upload(self, connection: SlaveConnection, msg_type: MsgType, header: dict,
                arrays: dict) -> None:
        """Send a scene message, its bytes added to the connection's upload deadline."""
        self._set_state(connection.endpoint, "uploading", connection=connection)
        self._upload_deadline(connection, sum(a.nbytes for a in arrays.values()))
        connection.send(msg_type, header, arrays)

    def _send_scene(self, connection: SlaveConnection, scene: Scene) -> bool:
        sent_before = connection.channel.bytes_sent
        query = {"scene_hash": scene.hash}
        if scene.meshes_hash is not None:
            query["meshes_hash"] = scene.meshes_hash
        hashes = {"mesh_hashes": scene.mesh_hashes} if scene.meshes_travel_alone else None
        # What proves that this master holds the scene (a slave renders a cached scene only
        # for a connection that uploaded it or proves it holds it).
        proofs = trust.scene_proofs(scene, connection.slave_nonce)
        connection.send(MsgType.SCENE_QUERY, {**query, **proofs}, hashes)
        present, meshes_present, held = self._scene_ready(connection, scene.hash)
        uploaded = False
        # Not present after SCENE_INSTANCES or SCENE_MESHES: the slave let meshes go since it
        # answered; the whole scene is uploaded.
        if not present and meshes_present:
            self._upload(connection, MsgType.SCENE_INSTANCES, query, scene.instance_arrays())
            present = self._scene_ready(connection, scene.hash)[0]
        elif not present and hashes is not None and held is not None and \
                held.shape == (len(scene.mesh_hashes),) and held.any():
            self._upload(connection, MsgType.SCENE_MESHES, {"scene_hash": scene.hash},
                         {**scene.mesh_wire_arrays(held == 0),
                          "mesh_proofs": _mesh_proofs(scene, held, connection.slave_nonce)})
            present = self._scene_ready(connection, scene.hash)[0]
        if not present:
            self._upload(connection, MsgType.SCENE_UPLOAD, {"scene_hash": scene.hash},
                         scene.wire_arrays())
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
        try:    # smaller tiles where a tile would be over the slaves' work budget
            dims = fit_tile_work(view, dims, protocol.MAX_TILE_RAYS, protocol.MAX_SAMPLE_RAYS)
        except ValueError as exc:
            raise MasterError(f"the frame cannot be rendered: {exc}") from None
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
                        self._frame_loop(), report_state=self._set_state, rejoin=self._rejoin,
                        spares=self._spares, on_complete=self._remember_tile_costs, order=order,
                        model=model, payload=payload, compress=bool(compress), passes=passes,
                        duplicates=duplicates, silence_timeout=self.silence_timeout,
                        tile_budget=self.tile_budget, hold_when_stranded=hold_when_stranded)
        with self._lock:
            self._job = job
        job.start()
        return job

    def _frame_loop(self) -> FrameLoop:
        with self._lock:
            if self._frames is None:
                self._frames = FrameLoop(self.name)
            return self._frames

    def _rejoin(self, endpoint, job: RenderJob) -> None:
        """A slave lost in `job`'s frame: reconnect to it after each retry delay."""
        self._start_join(endpoint, job, self.retry_delays)

    def _remember_tile_costs(self, job: RenderJob) -> None:
        """The frame is complete: its tiles' render times order the next frame of its grid."""
        self._tile_ms[(tuple(job.view.region), (job.tile_w, job.tile_h))] = list(job.tile_ms)

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
        for connection, outcome in self._make_present(stale, self.scene):
            if isinstance(outcome, Exception):
                reason = self._upload_failure(connection, outcome)
                problems.append(f"slave {connection.label} dropped while loading the scene: "
                                f"{reason}")
                self._set_state(connection.endpoint, "lost", reason)
                connection.close()
        self.errors += problems
        return problems

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._spares.close()
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

