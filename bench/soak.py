"""Soak benchmark of the distributed runtime (issue 13): frames keep coming while slaves are
killed and restarted at random, mutated messages and idle sockets are thrown at the slaves.

For --minutes, one master (kept for the whole run, as a long-lived API user would) renders
frame after frame on --slaves local `python -m kdtrace.slave` processes, on loopback, each frame
compared bit for bit with the same frame rendered by the tracer in this process. Meanwhile:
- chaos: every 20-60 s a random slave is SIGKILLed and restarted on its port 0.5-5 s later;
  the restarted slave is joined to the master as discovery would (Master.join), and the
  master's own reconnection with back-off runs too; --steady N slaves are left alone, so that
  their memory is seen over the whole run;
- fuzz: --mutated messages (10,000 by default), spread over the run, each on a connection of
  its own to a random slave: valid messages with flipped bits, truncated or inflated lengths,
  fields replaced by values of other types, huge numbers and nested junk, random message
  types; the slave's answer is read (ERROR, a close, or a reply);
- sockets: --idle sockets (500) in waves, held 5-60 s each: silent, the opening (OPEN) then
  silent, or the opening dribbled a byte a second;
- RSS: every 10 s each slave's resident memory (/proc/<pid>/status).

Trust (--trust): "pairing" (the default) as a new user sets a farm up: no farm secret; each
slave has an identity folder of its own and shows a pairing code at its first start, the
master pairs with it once (Master(pairing=...)) and approves its ID, as the Slaves panel's
Pair does; a restarted slave keeps its identity and its allowed master. The fuzzer's
identity is allowed on every slave (--allow), as an owner allows a master, so that its
messages reach the slave inside TLS. "secret": one generated farm secret for the master, the
fuzzer and every slave. Every connection is TLS 1.3 with both identities either way.

Reported: frames completed, frames lost (the job failed; target 0), wrong frames (pixels that
differ; target 0), frame times, kills, unexpected slave exits (crashes; target 0), fuzz
answers, and each slave's RSS over time. --long-tiles afterwards runs the 2-minute-tile render
(tests/test_reliability.py with KDTRACE_LONG_TESTS=1).

    .venv/bin/python bench/soak.py [--minutes 30] [--slaves 3] [--steady 0] [--mutated 10000]
                                   [--idle 500] [--json out.json] [--long-tiles]
                                   [--trust pairing|secret]
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import random
import re
import socket
import statistics
import subprocess
import sys
import threading
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.network_scaling import bench_scene  # noqa: E402
from kdtrace.core.net import protocol  # noqa: E402
from kdtrace.core.net.master import Master  # noqa: E402
from kdtrace.core.net.protocol import HEADER, MsgType  # noqa: E402
from kdtrace.core.net.tile_payloads import F16_MAX  # noqa: E402
from kdtrace.core.scene.model import Light  # noqa: E402
from kdtrace.core.scene.scene import Scene  # noqa: E402
from tests.test_network import make_view, network_settings  # noqa: E402
from bench.farm import bench_farm  # noqa: E402


def rss_mib(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class SlaveSlot:
    """One slave position: a port, and the process currently serving it (restarted by chaos).
    With `pairing`: an identity folder of its own, a pairing code at its first start
    (`code`), `allow` (master IDs) allowed from its first start."""

    def __init__(self, index: int, log_dir: pathlib.Path, pairing: bool = False, allow=()):
        self.name, self.port = f"soak-{index}", free_port()
        self.endpoint = ("127.0.0.1", self.port)
        self.log_dir = log_dir
        self.pairing, self.allow = pairing, list(allow)
        self.identity_dir = log_dir / f"identity-{self.name}"
        self.id = self.code = None
        self.proc = None
        self.instances = []          # (pid, started at, [(t, rss MiB)])
        self.crashes = []            # exit codes of exits chaos did not cause
        self.lock = threading.Lock()
        self.start()

    def start(self) -> None:
        env = dict(os.environ, POCL_MAX_PTHREAD_COUNT="1", PYTHONUNBUFFERED="1")
        trust = []
        if self.pairing:
            env.pop("KDTRACE_SECRET", None)
            trust = ["--identity-dir", str(self.identity_dir)]
            if not self.instances:       # the first start: a code to pair with, the fuzzer
                trust += ["--pair"] + [a for master in self.allow for a in ("--allow", master)]
        log_path = self.log_dir / f"{self.name}-{len(self.instances)}.log"
        log = open(log_path, "w")
        proc = subprocess.Popen(
            [sys.executable, "-m", "kdtrace.slave", "--port", str(self.port), "--bind", "127.0.0.1",
             "--no-zeroconf", "--name", self.name, "--status-port", "off", *trust],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=log, text=True)
        line = proc.stdout.readline()
        if "listening on" not in line:
            raise RuntimeError(f"{self.name} did not start: {line!r}")
        self.id = line.split(" id ")[1].split()[0]
        if self.pairing and not self.instances:     # its log shows the code after that line
            deadline = time.monotonic() + 30
            while not (code := re.search(r"pairs with the code (\S+?);", log_path.read_text())):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{self.name} showed no pairing code: {log_path}")
                time.sleep(0.05)
            self.code = code.group(1)
        threading.Thread(target=lambda: proc.stdout.read(), daemon=True).start()
        with self.lock:
            self.proc = proc
            self.instances.append((proc.pid, time.monotonic(), []))

    def kill(self) -> None:
        with self.lock:
            proc, self.proc = self.proc, None
        if proc is not None:
            proc.kill()
            proc.wait()

    def check(self) -> None:
        """Record an exit nobody asked for (a crash) and restart."""
        with self.lock:
            proc = self.proc
        if proc is not None and proc.poll() is not None:
            self.crashes.append(proc.returncode)
            with self.lock:
                self.proc = None
            self.start()

    def sample(self, now: float) -> None:
        with self.lock:
            if self.proc is None:
                return
            pid, _, series = self.instances[-1]
        value = rss_mib(pid)
        if value is not None:
            series.append((now, value))

    def stop(self) -> None:
        with self.lock:
            proc, self.proc = self.proc, None
        if proc is not None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()


# -- mutated messages -------------------------------------------------------------------------

def message(msg_type, header=None, arrays=None) -> bytes:
    return b"".join(bytes(b) for b in protocol.encode_message(msg_type, header, arrays))


def raw_message(msg_type, value) -> bytes:
    """Any JSON value as a message body (a mutation may have made it a list or a number)."""
    text = json.dumps(value).encode()
    return HEADER.pack(protocol.MAGIC, protocol.PROTOCOL_VERSION, msg_type, len(text), 0) + text


JUNK = [None, True, -1, 0, 2 ** 63, -2 ** 70, 1e308, "", "x" * 300, [], [[[[[]]]]], {}, {"a": [1]},
        [1, 2, 3, 4], "f4", ["f4"], {"dtype": "O"}, 65536, 65536 ** 2, 0.5]


def mutate_value(value, rng):
    if isinstance(value, dict) and value and rng.random() < 0.7:
        key = rng.choice(list(value))
        copy = dict(value)
        if rng.random() < 0.2:
            del copy[key]
        else:
            copy[key] = mutate_value(copy[key], rng)
        return copy
    if isinstance(value, list) and value and rng.random() < 0.7:
        copy = list(value)
        i = rng.randrange(len(copy))
        copy[i] = mutate_value(copy[i], rng)
        return copy
    return rng.choice(JUNK)


def mutated_message(rng, scene_hash: str, view: dict, arrays: dict) -> bytes:
    """One hostile message, after a valid HELLO."""
    frame = {"frame_id": rng.randrange(1 << 40), "scene_hash": scene_hash, "view": view,
             "tile_size": rng.choice([1, 16, 64, 1024]), "tile_height": rng.choice([1, 8, 64])}
    kind = rng.randrange(7)
    if kind == 0:            # a frame with a field (deep inside) replaced
        return raw_message(MsgType.FRAME_START, mutate_value(frame, rng))
    if kind == 1:            # a valid frame with bits flipped anywhere
        data = bytearray(message(MsgType.FRAME_START, frame))
        for _ in range(rng.randrange(1, 8)):
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        return bytes(data)
    if kind == 2:            # lengths that lie
        data = message(MsgType.SCENE_UPLOAD, {"scene_hash": scene_hash}, arrays)
        magic, version, kind_, json_length, payload_length = HEADER.unpack(data[:HEADER.size])
        json_length = rng.choice([0, json_length - 1, json_length + 7, 1 << 31])
        payload_length = rng.choice([0, payload_length - 4, payload_length * 3, 1 << 62])
        return HEADER.pack(magic, version, kind_, json_length, payload_length) + data[HEADER.size:]
    if kind == 3:            # array specs that lie
        specs = [{"name": "vertices", "dtype": rng.choice(["f4", "f8", ["f4"], {"x": 1}, 7]),
                  "shape": rng.choice([[3, 3], [-1], [2 ** 39, 2 ** 39], "3", [1, 1, 1, 1, 1]])}]
        text = json.dumps({"scene_hash": scene_hash, "arrays": specs}).encode()
        return HEADER.pack(protocol.MAGIC, protocol.PROTOCOL_VERSION, MsgType.SCENE_UPLOAD,
                           len(text), 36) + text + bytes(36)
    if kind == 4:            # requests for tiles of frames that do not exist, and floods
        return b"".join(message(MsgType.TILE_REQUEST, {"frame_id": rng.choice([0, 1, -1, "x"]),
                                                       "tile": rng.choice([0, -5, 2 ** 40, None])})
                        for _ in range(rng.randrange(1, 50)))
    if kind == 5:            # a frame and then the same tile again and again
        tiles = message(MsgType.TILE_REQUEST, {"frame_id": frame["frame_id"], "tile": 0})
        return message(MsgType.FRAME_START, dict(frame, tile_size=64)) + tiles * 40
    return HEADER.pack(protocol.MAGIC, protocol.PROTOCOL_VERSION, rng.randrange(65536),
                       rng.randrange(64), 0) + os.urandom(rng.randrange(64))


class Fuzzer:
    def __init__(self, slots, count: int, seconds: float, scene, view, seed: int):
        self.slots, self.count, self.seconds = slots, count, seconds
        self.scene_hash, self.view = scene.hash, view.to_dict()
        small = {k: v[:3] for k, v in scene.wire_arrays().items()}
        self.arrays = small
        self.rng = random.Random(seed)
        self.sent = 0
        self.answers = {"error": 0, "closed": 0, "reply": 0, "unreachable": 0}
        self.stop = threading.Event()

    def run(self) -> None:
        started = time.monotonic()
        while self.sent < self.count and not self.stop.is_set():
            due = started + self.sent * self.seconds / self.count
            if self.stop.wait(max(0.0, due - time.monotonic())):
                return
            self.one(self.rng.choice(self.slots))

    def one(self, slot) -> None:
        from tests.tls_peers import tls_exchange
        data = mutated_message(self.rng, self.scene_hash, self.view, self.arrays)
        self.sent += 1
        try:
            # Inside TLS after a valid HELLO (the run's farm secret); a TLS connection is not
            # half-closed, so what the slave says comes within a second or not at all.
            reply = tls_exchange(slot.endpoint, data, timeout=1.0)
        except (OSError, protocol.ProtocolError):
            self.answers["unreachable"] += 1   # that slave was down (chaos)
            return
        # The first reply is WELCOME; what follows says what became of the mutated message.
        after = reply[reply.find(b"KDTR", 4):] if reply.count(b"KDTR") > 1 else b""
        if after[4:8] and HEADER.unpack(after[:HEADER.size])[2] == MsgType.ERROR:
            self.answers["error"] += 1
        elif after:
            self.answers["reply"] += 1
        else:
            self.answers["closed"] += 1


class IdleSockets:
    """`count` sockets in waves: silent, HELLO then silent, or a dribbled HELLO."""

    def __init__(self, slots, count: int, seconds: float, seed: int):
        self.slots, self.count, self.seconds = slots, count, seconds
        self.rng = random.Random(seed)
        self.attempted = self.opened = 0
        self.kinds = {"silent": 0, "hello": 0, "dribble": 0}
        self.count_lock = threading.Lock()
        self.stop = threading.Event()

    def run(self) -> None:
        waves = max(1, self.count // 10)
        started = time.monotonic()
        for wave in range(waves):
            due = started + wave * self.seconds / waves
            if self.stop.wait(max(0.0, due - time.monotonic())):
                return
            for _ in range(self.count // waves):
                kind = self.rng.choice(list(self.kinds))
                hold = self.rng.uniform(5, 60)
                threading.Thread(target=self.hold, args=(self.rng.choice(self.slots), kind, hold),
                                 daemon=True).start()

    def hold(self, slot, kind: str, seconds: float) -> None:
        with self.count_lock:
            self.attempted += 1
        try:
            sock = socket.create_connection(slot.endpoint, timeout=3)
        except OSError:
            return      # that slave was down (chaos)
        with self.count_lock:
            self.opened += 1
            self.kinds[kind] += 1
        data = message(MsgType.OPEN, {})   # the opening; TLS would follow
        end = time.monotonic() + seconds
        try:
            if kind == "hello":
                sock.sendall(data)
            i = 0
            while time.monotonic() < end and not self.stop.is_set():
                if kind == "dribble" and i < len(data):
                    sock.send(data[i:i + 1])
                    i += 1
                time.sleep(1.0)
        except OSError:
            pass
        finally:
            sock.close()


# -- the run -----------------------------------------------------------------------------------

def frame_views():
    """Three frames the renders cycle through (each with its tracer reference)."""
    base = make_view(128, 96)
    lit = make_view(128, 96)
    lit.shading.lights.append(Light("AREA", (1, 1, 1), 200.0, (0, 0, 4), size_u=1, size_v=1))
    lit.settings = network_settings(samples_per_axis=2, light_samples_per_axis=2)
    border = make_view(128, 96, region=(10, 8, 110, 90))
    return [("plain 3b", base, {"tile_size": 16}),
            ("area light 3a", lit, {"tile_size": 24, "model": "3a"}),
            ("border f16+zlib", border, {"tile_size": 16, "payload": "f16", "compress": True})]


def expected(tracer, view, options) -> dict:
    image = tracer.render_tile(view, 0, 0, view.width, view.height)
    if options.get("payload") == "f16":   # what float16 transport makes of it, exactly
        for name in ("combined", "normal"):
            image[name] = np.clip(image[name], -F16_MAX, F16_MAX) \
                .astype(np.float16).astype(np.float32)
    return image


def render_frame(master, view, options, reference, timeout: float):
    job = master.render(view, **options)
    images = {k: np.full_like(v, np.nan) for k, v in reference.items()}
    deadline = time.monotonic() + timeout
    while not job.finished:
        if time.monotonic() > deadline:
            job.cancel()
            return job, "timed out", None
        result = job.next_result(0.1)
        if result is not None:
            for name, image in images.items():
                image[result.y:result.y + result.h, result.x:result.x + result.w] = result.passes[name]
    job.wait(30)
    if job.error:
        return job, "lost", None
    x0, y0, x1, y1 = view.region
    same = all(np.array_equal(images[n][y0:y1, x0:x1], reference[n][y0:y1, x0:x1]) for n in images)
    return job, "completed" if same else "wrong", job.elapsed_s


def main(argv=None) -> int:
    bench_farm()      # one farm secret for the master and every slave of the run
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--slaves", type=int, default=3)
    parser.add_argument("--steady", type=int, default=0,
                        help="slaves that chaos leaves alone (their RSS over the whole run)")
    parser.add_argument("--mutated", type=int, default=10_000)
    parser.add_argument("--idle", type=int, default=500)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", default=None)
    parser.add_argument("--long-tiles", action="store_true",
                        help="afterwards, render with 2-minute tiles (the long test)")
    parser.add_argument("--trust", choices=("pairing", "secret"), default="pairing",
                        help="how master and slaves trust each other (see the docstring)")
    args = parser.parse_args(argv)
    command = "bench/soak.py " + " ".join(sys.argv[1:] if argv is None else argv)
    print(f"command: .venv/bin/python {command}")
    print(f"machine: {platform.node()}, {os.cpu_count()} cores, {platform.processor() or platform.machine()}, "
          f"Python {platform.python_version()}; load average at start {os.getloadavg()}")
    seconds = args.minutes * 60
    rng = random.Random(args.seed)

    from kdtrace.slave.tracer import Tracer
    scene = Scene.from_parts(*bench_scene())
    tracer = Tracer()
    tracer.load(scene)
    views = frame_views()
    references = [expected(tracer, view, options) for _, view, options in views]

    log_dir = pathlib.Path(os.environ.get("TMPDIR", "/tmp")) / f"kdtrace-soak-{os.getpid()}"
    log_dir.mkdir(parents=True, exist_ok=True)
    pairing = args.trust == "pairing"
    if pairing:       # the slaves get no secret; the fuzzer is a master their owner allowed
        from tests.tls_peers import identity as probe_identity
        slots = [SlaveSlot(i, log_dir, pairing=True, allow=[probe_identity().id])
                 for i in range(args.slaves)]
        master = Master([s.endpoint for s in slots], name="soak", secret=None,
                        pairing={s.id: s.code for s in slots})
    else:
        slots = [SlaveSlot(i, log_dir) for i in range(args.slaves)]
        master = Master([s.endpoint for s in slots], name="soak")
    fuzzer = Fuzzer(slots, args.mutated, seconds, scene, views[0][1], args.seed)
    idle = IdleSockets(slots, args.idle, seconds, args.seed + 1)
    stop = threading.Event()
    kills = []

    victims = slots[args.steady:]

    def chaos():
        while victims and not stop.wait(rng.uniform(20, 60)):
            slot = rng.choice(victims)
            slot.kill()
            kills.append((time.monotonic(), slot.name))
            if stop.wait(rng.uniform(0.5, 5)):
                return
            slot.start()
            master.join(*slot.endpoint)        # as discovery would report it

    def watch():
        while not stop.wait(10):
            now = time.monotonic()
            for slot in slots:
                slot.check()
                slot.sample(now)

    outcomes = {"completed": 0, "lost": 0, "wrong": 0, "timed out": 0}
    frame_times = {name: [] for name, _, _ in views}
    errors_seen = 0
    try:
        master.connect()
        if pairing:   # paired once: approved from now on, as the Slaves panel's Pair does
            assert {c.trusted_by for c in master.slaves} == {"paired"}, \
                [(c.label, c.trusted_by) for c in master.slaves]
            for slot in slots:
                master.approved.add(slot.id)
        master.load_scene(scene)
        started = time.monotonic()
        threads = [threading.Thread(target=t, daemon=True)
                   for t in (chaos, watch, fuzzer.run, idle.run)]
        for thread in threads:
            thread.start()
        frame = 0
        while time.monotonic() - started < seconds:
            name, view, options = views[frame % len(views)]
            try:
                job, outcome, elapsed = render_frame(master, view, options, references[frame % 3], 300)
                errors_seen += len(job.errors)
            except Exception as exc:     # no slave connected at all: a lost frame too
                print(f"frame {frame}: {type(exc).__name__}: {exc}", flush=True)
                outcome, elapsed = "lost", None
            outcomes[outcome] += 1
            if elapsed is not None:
                frame_times[name].append(elapsed)
            if outcome != "completed":
                print(f"frame {frame} ({name}): {outcome}: {job.error if outcome == 'lost' else ''}",
                      flush=True)
            frame += 1
            if frame % 100 == 0:
                print(f"{(time.monotonic() - started) / 60:.1f} min: {frame} frames {outcomes}, "
                      f"{len(kills)} kills, {fuzzer.sent} mutated, {idle.opened} idle sockets",
                      flush=True)
        elapsed_total = time.monotonic() - started
    finally:
        stop.set()
        fuzzer.stop.set()
        idle.stop.set()
        master.close()
        for slot in slots:
            slot.check()
            slot.stop()

    rss = []
    for slot in slots:
        for pid, born, series in slot.instances:
            if len(series) >= 2:
                values = [v for _, v in series]
                rss.append({"slave": slot.name, "pid": pid, "minutes": round((series[-1][0] - born) / 60, 1),
                            "first_mib": round(values[0], 1), "last_mib": round(values[-1], 1),
                            "max_mib": round(max(values), 1),
                            "series": [(round((t - started) / 60, 2), round(v, 1)) for t, v in series]})
    report = {
        "command": command, "trust": args.trust, "minutes": round(elapsed_total / 60, 1),
        "frames": outcomes,
        "frame_seconds": {n: {"count": len(t), "median": round(statistics.median(t), 3),
                              "p95": round(sorted(t)[int(0.95 * (len(t) - 1))], 3)}
                          for n, t in frame_times.items() if t},
        "slave_problems_recovered": errors_seen, "kills": len(kills),
        "crashes": {s.name: s.crashes for s in slots if s.crashes},
        "mutated_messages": fuzzer.sent, "mutated_answers": fuzzer.answers,
        "idle_sockets": idle.attempted, "idle_sockets_connected": idle.opened,
        "idle_kinds": idle.kinds, "steady_slaves": [s.name for s in slots[:args.steady]],
        "rss": rss, "logs": str(log_dir)}
    print(json.dumps({k: v for k, v in report.items() if k != "rss"}, indent=1))
    print("slave RSS (MiB): instance, minutes alive, first, last, max")
    for entry in rss:
        print(f"  {entry['slave']} pid {entry['pid']}: {entry['minutes']} min, {entry['first_mib']}"
              f" -> {entry['last_mib']} (max {entry['max_mib']})")
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(report, indent=1))
    if args.long_tiles:
        print("2-minute tiles:", flush=True)
        subprocess.run([sys.executable, "-m", "pytest", "-q", "-s", "tests/test_reliability.py",
                        "-k", "two_minute"], cwd=ROOT, env=dict(os.environ, KDTRACE_LONG_TESTS="1"))
    return 0 if outcomes["lost"] == outcomes["wrong"] == outcomes["timed out"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
