"""Slaves on this machine: `python -m kdtrace.slave` processes run from the extension's root folder,
bound to loopback and not advertised (only this master uses them). A frame session starts them
when no other slave is known and keeps them between frames; closing it stops them.

They are trusted both ways without pairing: each is started with `--allow <this master's ID>`
and prints its own ID on its listening line, which the master then trusts (they share one
identity, in a private temporary folder of the session)."""
from __future__ import annotations

import os
import pathlib
import platform
import queue
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time

from ..net.trust import SECRET_ENV

EXTENSION_ROOT = pathlib.Path(__file__).resolve().parent.parent.parent
READY_LINE = re.compile(r"listening on (?P<host>[^\s:]+):(?P<port>\d+) id (?P<id>[A-Z2-7]{52})")


class LocalSlaveError(RuntimeError):
    pass


def has_bundled_cpu_device() -> bool:
    """PoCL, the CPU OpenCL device the zips bundle, has wheels for Linux x86-64 only."""
    return sys.platform.startswith("linux") and platform.machine().lower() in ("x86_64", "amd64")


# Shown in the Slaves panel and added to a local slave's start error where PoCL is not bundled.
NO_CPU_DEVICE = ("local slaves need an OpenCL device on this system (PoCL, the CPU device, is "
                 "bundled for Linux x64 only): a GPU driver with OpenCL, or on Windows Intel's "
                 "CPU runtime (README: \"Local slaves on Windows and macOS\")")


def slave_environment(**variables) -> dict:
    """The environment of a slave run by Blender's Python: Blender's sys.path holds the folder
    where it installed the extension's wheels (zeroconf, pyopencl, PoCL), and the slave needs
    them too. The slave runs from the extension's root folder (`python -m kdtrace.slave`)."""
    return dict(os.environ, PYTHONUNBUFFERED="1",
                PYTHONPATH=os.pathsep.join(p for p in sys.path if p and os.path.isdir(p)),
                **variables)


def host_label() -> str:
    """This machine's short host name, for local slave names (os.uname() is POSIX-only)."""
    name = re.sub(r"[^A-Za-z0-9_-]", "-", socket.gethostname().split(".")[0])[:40]
    return name or "localhost"


class LocalSlave:
    def __init__(self, name: str, python: str, device: str, threads: int, master_id: str,
                 identity_dir: str):
        env = slave_environment(POCL_MAX_PTHREAD_COUNT=str(threads))
        env.pop(SECRET_ENV, None)       # it serves this master by ID, nobody else
        env.pop("KDTRACE_SLAVE_HOME", None)
        command = [python, "-m", "kdtrace.slave", "--port", "0", "--bind", "127.0.0.1",
                   "--name", name, "--device", device, "--no-zeroconf",
                   "--identity-dir", identity_dir, "--allow", master_id, "--status-port", "off"]
        self.name = name
        self.id = None
        self.process = subprocess.Popen(command, cwd=EXTENSION_ROOT, env=env, text=True,
                                        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                        stderr=subprocess.STDOUT)
        self.lines: queue.Queue = queue.Queue()
        self.endpoint = None
        # The slave's output is read on a thread so a silent slave cannot block Blender.
        threading.Thread(target=self._read_output, name=f"kdtrace-{name}-output", daemon=True).start()

    def _read_output(self):
        for line in self.process.stdout:
            self.lines.put(line.rstrip())
        self.lines.put(None)

    def wait_ready(self, deadline: float, cancelled=lambda: False) -> tuple[str, int]:
        """Block until the slave prints its listening line; raise with its output if it fails."""
        output = []
        while time.monotonic() < deadline:
            if cancelled():
                raise LocalSlaveError(f"starting local slave {self.name} was cancelled")
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                continue
            if line is None:
                hint = "" if has_bundled_cpu_device() else f" ({NO_CPU_DEVICE})"
                raise LocalSlaveError(f"local slave {self.name} exited: "
                                      + " | ".join(output[-5:]) + hint)
            output.append(line)
            match = READY_LINE.search(line)
            if match:
                self.endpoint = (match["host"], int(match["port"]))
                self.id = match["id"]
                return self.endpoint
        raise LocalSlaveError(f"local slave {self.name} did not start in time: " + " | ".join(output[-5:]))

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self):
        if self.alive:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


class LocalSlaves:
    """The pool of local slave processes of one Blender session."""

    def __init__(self):
        self._slaves: list[LocalSlave] = []
        self._master_id: str | None = None
        self._identity_dir: str | None = None    # their identity: private, this session's
        self._lock = threading.Lock()

    def ensure(self, count: int, python: str = "", device: str = "auto", master_id: str = "",
               timeout: float = 60.0, cancelled=lambda: False) -> list[tuple[str, int]]:
        """Have `count` live local slaves that serve the master `master_id`; return their
        endpoints (ids() are theirs)."""
        with self._lock:
            if master_id != self._master_id:  # slaves started for another master refuse us
                self._stop_locked()
                self._master_id = master_id
            if self._identity_dir is None:
                self._identity_dir = tempfile.mkdtemp(prefix="kdtrace-local-slaves-")
            for slave in [s for s in self._slaves if not s.alive]:
                slave.stop()
                self._slaves.remove(slave)
            for slave in self._slaves[count:]:
                slave.stop()
            del self._slaves[count:]
            threads = max(1, (os.cpu_count() or 1) // max(1, count))
            started = [LocalSlave(f"{host_label()}-local-{len(self._slaves) + i + 1}",
                                  python or sys.executable, device, threads, master_id,
                                  os.path.join(self._identity_dir, "identity"))
                       for i in range(count - len(self._slaves))]
            deadline = time.monotonic() + timeout
            try:
                for slave in started:
                    slave.wait_ready(deadline, cancelled)
            except LocalSlaveError:
                for slave in started:
                    slave.stop()
                raise
            self._slaves += started
            return [s.endpoint for s in self._slaves]

    def pids(self) -> list[int]:
        return [s.process.pid for s in self._slaves if s.alive]

    def ids(self) -> list[str]:
        """The IDs the local slaves printed: the master trusts these without approval."""
        return [s.id for s in self._slaves if s.id]

    def stop_all(self):
        with self._lock:
            self._stop_locked()
            if self._identity_dir is not None:
                shutil.rmtree(self._identity_dir, ignore_errors=True)
                self._identity_dir = None

    def _stop_locked(self):
        for slave in self._slaves:
            slave.stop()
        self._slaves.clear()
