"""Child processes for the network tests: real slaves (or fakes) whose output is collected on
threads, so a silent or dead process fails the test with its log instead of hanging it."""
import os
import pathlib
import signal
import subprocess
import sys
import threading
import time

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
START_TIMEOUT = 60
LINE_PREFIX = "KD Trace slave "  # the start line of `python -m kdtrace.slave`


class ChildProcess:
    """`python <argv>` from the repository root (behind `wrapper`, e.g. `ip netns exec NS`)."""

    def __init__(self, argv: list, wrapper: tuple = (), env: dict | None = None):
        # One PoCL thread per slave so that several slaves share this machine's two cores.
        # A variable given as None is left out (a slave without the tests' farm secret).
        env = dict(os.environ, POCL_MAX_PTHREAD_COUNT="1", PYTHONUNBUFFERED="1", **(env or {}))
        env = {name: value for name, value in env.items() if value is not None}
        self.proc = subprocess.Popen([*wrapper, sys.executable, *argv], cwd=ROOT, env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines, self.stderr_lines = [], []
        for stream, lines in ((self.proc.stdout, self.lines), (self.proc.stderr, self.stderr_lines)):
            threading.Thread(target=lambda s=stream, l=lines: l.extend(s), daemon=True).start()

    def wait_line(self, prefix: str, timeout: float = START_TIMEOUT) -> str:
        """The first output line starting with `prefix`; fail the test if none comes."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in self.lines:
                if line.startswith(prefix):
                    return line.strip()
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        self.stop()
        pytest.fail(f"process did not print {prefix!r}: {self.log}")

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self):
        if self.alive():
            self.proc.kill()
        self.proc.wait(10)

    def stop(self):
        if self.alive():
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()

    @property
    def log(self) -> str:
        return "".join(self.stderr_lines)


class SlaveProcess(ChildProcess):
    """A `python -m kdtrace.slave` subprocess on loopback; its start line gives the port."""

    def __init__(self, name: str, *extra: str, env: dict | None = None):
        super().__init__(["-m", "kdtrace.slave", "--port", "0", "--bind", "127.0.0.1",
                          "--name", name, *extra], env=env)
        self.name = name
        line = self.wait_line(LINE_PREFIX)
        assert line.startswith(LINE_PREFIX + name + " listening on 127.0.0.1:"), line
        self.port = int(line.split("listening on 127.0.0.1:")[1].split()[0])
        self.endpoint = ("127.0.0.1", self.port)
        self.id = line.split(" id ")[1].split()[0]     # the slave's identity (its TLS ID)
