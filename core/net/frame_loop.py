"""The master's one thread for every frame (FrameLoop): it reads the sockets of all slaves in a
frame at once and runs each slave's steps (core/net/slave_worker.py) when its socket is
readable or one of its deadlines comes."""
from __future__ import annotations

import collections
import math
import selectors
import socket
import threading
import time
import traceback
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .slave_worker import SlaveWorker


class FrameLoop:
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

    def register(self, worker: SlaveWorker) -> None:
        channel = worker.connection.channel
        self._selector.register(channel.sock, selectors.EVENT_READ, worker)
        self._workers.add(worker)
        if channel.has_pending():    # TLS holds bytes already: no selector would say so
            self.call(worker.readable)

    def unregister(self, worker: SlaveWorker) -> None:
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
        # A slave's steps drop that slave on any exception (SlaveWorker guards each); anything
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
