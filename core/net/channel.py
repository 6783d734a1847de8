"""A peer connection as both sides use it after connecting: `Channel`. Every message, sent or
received, has a deadline for the whole message (a grace, then MIN_RATE_BPS on average); a
channel reads into one buffer, reused message after message, and parses messages where they
lie; over TLS every TLS call holds one lock (one thread reads while another sends). What a
message is (header, types, limits, encoding and checks) is protocol.py's; the opening (OPEN,
then TLS) is secure.py's."""
from __future__ import annotations

import contextlib
import select
import socket
import ssl
import threading
import time

from .protocol import (DEFAULT_LIMITS, HEADER, SILENCE_S, ConnectionBroken, ConnectionClosed,
                       Limits, Message, MsgType, PeerTooSlow, check_header, coalesce,
                       encode_message, parse_body)

# Every message, either way, must arrive or leave within its grace (protocol.SILENCE_S) plus its
# size at MIN_RATE_BPS (docs/protocol.md, "Liveness and deadlines").
MIN_RATE_BPS = 256 * 1024
RECV_BUFFER_BYTES = 64 * 1024   # a channel's receive buffer at first (it grows to fit messages)
RECV_KEEP_BYTES = 2 << 20       # messages up to this size are received in that buffer (tiles up
                                # to 256 x 256 with every pass); larger ones in their own
PREALLOCATE_BYTES = 8 << 20     # such a message's own buffer is allocated at once up to this size
LOW_WATER_BYTES = 256 * 1024    # a long read wakes when this much (or the rest) has arrived
POLL_S = 0.25                   # how often a blocked send or receive looks at its deadline
TLS_RECORD_BYTES = 16384 + 256  # a TLS record's plaintext at most, with its overhead


def end_writing(sock: socket.socket) -> None:
    """End our direction of the stream, so that the peer reads our last message and then the
    end. Only on a plain socket: over TLS, a TCP half-close without TLS's close_notify is an
    unexpected end that OpenSSL treats as fatal (the peer could not answer any more), and
    Python's ssl sends close_notify only by waiting for the peer's. A TLS connection is
    closed whole instead, after its peer has closed (Channel.drain) or a moment has passed."""
    if not isinstance(sock, ssl.SSLSocket):
        socket.socket.shutdown(sock, socket.SHUT_WR)


def socket_ready(sock: socket.socket, for_write: bool, timeout: float) -> bool:
    """Whether `sock` became readable (writable) within `timeout` seconds; OSError once another
    thread has closed it (eviction, the server closing)."""
    if sock.fileno() < 0:
        raise OSError(9, "the connection was closed")
    if hasattr(select, "poll"):
        poller = select.poll()
        poller.register(sock, select.POLLOUT if for_write else select.POLLIN)
        return bool(poller.poll(timeout * 1000))
    wanted = ([], [sock], []) if for_write else ([sock], [], [])
    return any(select.select(*wanted, timeout))


def transfer_deadline(nbytes: int, grace_s: float = SILENCE_S) -> float:
    """Seconds a message of `nbytes` may take to arrive or leave: the grace, then MIN_RATE_BPS."""
    return grace_s + nbytes / MIN_RATE_BPS


class _Incoming:
    """The message being received, once its header is in: its type and length, and, for a
    message too large for the channel's buffer, the rest of it in a buffer of its own."""

    def __init__(self, started: float, msg_type: MsgType, json_length: int, payload_length: int):
        self.started = started          # its first byte
        self.msg_type = msg_type
        self.sizes = (json_length, payload_length)
        self.total = HEADER.size + json_length + payload_length
        self.own: bytearray | None = None   # the bytes after the header, if not in the buffer
        self.head = b""                 # the header's bytes then
        self.filled = 0                 # of them so far
        self.in_place = False           # own preallocated (else grown as data arrives)

    def take_own(self, first) -> None:
        """Receive the rest in a buffer of its own, starting with `first` (bytes after the
        header already read): preallocated up to PREALLOCATE_BYTES, beyond that grown as
        data arrives, so that a lying length costs nothing until bytes really come."""
        rest = self.total - HEADER.size
        self.in_place = rest <= PREALLOCATE_BYTES
        self.own = bytearray(rest) if self.in_place else bytearray()
        self.add(first)

    def add(self, piece) -> None:
        if self.in_place:
            self.own[self.filled:self.filled + len(piece)] = piece
        else:
            self.own += piece
        self.filled += len(piece)

    def where(self, received: int) -> str:
        """Which part `received` bytes of the message end in, for errors."""
        offset = received - HEADER.size
        for what, size in zip(("JSON", "payload"), self.sizes):
            if offset < size:
                return f"{what}: {offset} of {size} bytes"
            offset -= size
        return f"{received} of {self.total} bytes"


class Channel:
    """One peer connection, for one sending thread at a time (sends are locked) and one
    receiving thread. `role` is this side ("master" or "slave"). `grace_s`: how long a message
    may be silent before it must flow at MIN_RATE_BPS on average.

    Over TLS (an ssl.SSLSocket) the socket is non-blocking and every TLS call holds one lock:
    OpenSSL does not allow one connection's reads and writes on two threads at once, and the
    slave reads on one thread while it sends on another. Nobody waits while holding it: a
    thread waits for the socket (poll) first, then reads or writes what is there."""

    def __init__(self, sock: socket.socket, role: str, grace_s: float = SILENCE_S,
                 budget=None):
        """`budget` (the slave's: slave.queues.UploadBudget): a message larger than the
        channel's buffer takes its length from it (take(n), which may refuse with
        ProtocolError) when its header is in, and gives it back (give(n)) at the next
        receive or at close."""
        self.sock, self.role, self.grace_s = sock, role, grace_s
        self.budget, self._budgeted = budget, 0
        self._budget_lock = threading.Lock()     # the receiver gives back, or close()
        self.tls = isinstance(sock, ssl.SSLSocket)
        self._tls_lock = threading.Lock()
        # Blocked calls wake up to look at their deadline; a TLS socket never blocks.
        sock.settimeout(0.0 if self.tls else POLL_S)
        # Received bytes not yet parsed: _buffer[_start:_end]. One buffer per channel, reused
        # message after message (messages up to RECV_KEEP_BYTES are received and parsed in
        # it; larger ones go to a buffer of their own, _Incoming.own).
        self._buffer = bytearray(RECV_BUFFER_BYTES)
        self._start = self._end = 0
        self._began: float | None = None          # the first byte of a message with no header yet
        self._incoming: _Incoming | None = None   # the message under way, its header in
        self._rcvlowat = 1
        self._send_lock = threading.RLock()   # re-entered by sends inside batch()
        self._batch: list | None = None        # buffers of a batch() under way
        self.last_sent = self.last_received = time.monotonic()
        self.bytes_sent = 0     # every byte this side has written to the socket
        self.closed = False

    # -- sending

    def send(self, msg_type: MsgType, header: dict | None = None, arrays: dict | None = None) -> None:
        self.send_encoded(encode_message(msg_type, header, arrays))

    def send_encoded(self, buffers: list) -> None:
        """Send a message as encode_message returned it (one encoding for many peers: the
        master's FRAME_START)."""
        with self._send_lock:
            self._send_locked(buffers)

    def send_bytes(self, data: bytes) -> None:
        """Raw bytes, as they are (tests of peers that misbehave)."""
        with self._send_lock:
            self._write([data])

    def try_send(self, msg_type: MsgType, header: dict | None = None) -> bool:
        """Send unless another send is under way (then bytes are flowing anyway): heartbeats."""
        if not self._send_lock.acquire(blocking=False):
            return False
        try:
            self._send_locked(encode_message(msg_type, header))
        finally:
            self._send_lock.release()
        return True

    @contextlib.contextmanager
    def batch(self):
        """The messages this thread sends inside go out together in one write at the end (one
        system call and one push instead of one each: a frame's start on many slaves)."""
        with self._send_lock:
            self._batch = []
            try:
                yield
            finally:
                buffers, self._batch = self._batch, None
                self._write(buffers)

    def _send_locked(self, buffers: list) -> None:
        if self._batch is not None:
            self._batch += buffers
        else:
            self._write(buffers)

    def _write(self, buffers: list) -> None:
        total = sum(len(b) for b in buffers)
        started, sent = time.monotonic(), 0
        for buffer in coalesce(buffers):
            view = memoryview(buffer).cast("B")
            while len(view):
                count = self._send_some(view[:1 << 20])
                view, sent = view[count:], sent + count
                self.bytes_sent += count
                if len(view):
                    self._check_rate(started, sent, total, "sent", "the peer stopped reading")
        self.last_sent = time.monotonic()

    def _send_some(self, view) -> int:
        """Bytes of `view` written now (0 after waiting POLL_S for room)."""
        if not self.tls:
            try:
                return self.sock.send(view)
            except socket.timeout:
                return 0
        with self._tls_lock:
            try:
                # OpenSSL (no partial writes) sends all of `view` or asks to be called again
                # with the same bytes, which the caller does.
                return self.sock.send(view)
            except (ssl.SSLWantWriteError, ssl.SSLWantReadError):
                pass
        socket_ready(self.sock, True, POLL_S)
        return 0

    def _check_rate(self, started, done, total, verb, what) -> None:
        elapsed = time.monotonic() - started
        if elapsed > self.grace_s and done < (elapsed - self.grace_s) * MIN_RATE_BPS:
            raise PeerTooSlow(f"{what}: {done} of {total} bytes {verb} after {elapsed:.1f} s")

    # -- receiving
    #
    # One code path serves a thread that blocks in recv() (the slave, the handshakes) and the
    # master's single receiving thread, which reads what a readable socket holds
    # (recv_available) and checks the deadline of a message under way (incoming_due). Bytes
    # are read into the channel's buffer, as many as are there (several messages, or the
    # start of the next, in one system call), and messages are parsed where they lie.

    def recv(self, limits: Limits = DEFAULT_LIMITS, allowed: frozenset | None = None,
             wait: float | None = None, deadline: float | None = None) -> Message | None:
        """The next message, validated; None if none began within `wait` seconds (None: wait
        as long as it takes). Once a message begins it must arrive within its transfer
        deadline, and before the absolute `deadline` (time.monotonic()) if given.
        ProtocolError on anything else. Its arrays are its own."""
        self._give_budget()         # the message before is handled
        waited_from = time.monotonic()
        while True:
            msg = self._parse(limits, allowed, borrow=False)
            if msg is not None:
                self._low_water(self._wake_bytes())
                return msg
            if self._start == self._end and self._incoming is None:  # nothing owed yet
                if deadline is not None and time.monotonic() > deadline:
                    raise PeerTooSlow("nothing arrived before the deadline")
            else:
                self.check_incoming(deadline)
            try:
                self._fill()
            except socket.timeout:
                if (self._start == self._end and self._incoming is None and wait is not None
                        and time.monotonic() - waited_from >= wait):
                    return None

    def recv_available(self, limits: Limits = DEFAULT_LIMITS,
                       allowed: frozenset | None = None) -> list:
        """The messages that what the socket holds now completes (one read: call it when the
        socket is readable, e.g. from a selector); [] if none is complete yet. Their arrays
        are views of the channel's buffer, valid until the next receive on this channel:
        handle (or copy) them first. Afterwards the socket signals readable again only when
        the next read can make progress (see _low_water). Deadlines: see incoming_due."""
        try:
            self._fill(wait=0.0)    # the socket is readable: never wait here
        except socket.timeout:      # woken for nothing
            pass
        messages = []
        while (msg := self._parse(limits, allowed, borrow=True)) is not None:
            messages.append(msg)
        self._low_water(self._wake_bytes())
        return messages

    def has_pending(self) -> bool:
        """Bytes wait inside TLS, decrypted: a selector does not see them (the socket is not
        readable for them), so whoever reads by selector reads again at once."""
        if not self.tls:
            return False
        with self._tls_lock:
            try:
                return self.sock.pending() > 0
            except (ValueError, OSError):     # closed
                return False

    def _received(self) -> int:
        """Bytes of the message under way so far."""
        incoming = self._incoming
        if incoming is not None and incoming.own is not None:
            return HEADER.size + incoming.filled
        return self._end - self._start

    def incoming_due(self) -> float | None:
        """When the message under way arrives too slowly (time.monotonic()) unless more of it
        comes first; None when none is under way."""
        incoming = self._incoming
        started = self._began if incoming is None else incoming.started
        if started is None:
            return None
        return started + self.grace_s + self._received() / MIN_RATE_BPS

    def check_incoming(self, deadline: float | None = None) -> None:
        """PeerTooSlow if the message under way is past its transfer deadline (or `deadline`)."""
        incoming = self._incoming
        started = self._began if incoming is None else incoming.started
        if started is None:
            return
        received = self._received()
        total = HEADER.size if incoming is None else incoming.total
        if deadline is not None and time.monotonic() > deadline:
            where = f"header: {received} of {total} bytes" if incoming is None else incoming.where(received)
            raise PeerTooSlow(f"message not complete before the deadline ({where})")
        self._check_rate(started, received, total, "received", "message arrived too slowly")

    def _parse(self, limits: Limits, allowed, borrow: bool) -> Message | None:
        """The next message if its bytes are all in, else None (what is there waits)."""
        incoming = self._incoming
        if incoming is None:
            have = self._end - self._start
            if have < HEADER.size:
                if have == 0:
                    self._start = self._end = 0     # all parsed: the buffer is free again
                elif self._began is None:
                    self._began = time.monotonic()
                return None
            # The header: checked before anything else is read.
            msg_type, json_length, payload_length = check_header(
                memoryview(self._buffer)[self._start:self._start + HEADER.size], limits, allowed)
            incoming = self._incoming = _Incoming(
                self._began or time.monotonic(), msg_type, json_length, payload_length)
            self._began = None
            if incoming.total > RECV_KEEP_BYTES:
                if self.budget is not None:
                    self._give_budget()
                    self.budget.take(incoming.total)
                    with self._budget_lock:
                        self._budgeted = incoming.total
                    if self.closed:         # closed meanwhile: nobody gives it back else
                        self._give_budget()
                # (the buffer, at most RECV_KEEP_BYTES, holds nothing beyond this message)
                with memoryview(self._buffer) as view:
                    incoming.head = bytes(view[self._start:self._start + HEADER.size])
                    incoming.take_own(view[self._start + HEADER.size:self._end])
                self._start = self._end = 0
        if incoming.own is not None:
            if incoming.filled < incoming.total - HEADER.size:
                return None
            body, head = memoryview(incoming.own), incoming.head
            borrow = True            # its own buffer: nobody else's to share
        else:
            if self._end - self._start < incoming.total:
                return None
            start = self._start
            self._start += incoming.total
            with memoryview(self._buffer) as view:
                head = view[start:start + HEADER.size]
                body = view[start + HEADER.size:start + incoming.total]
                if not borrow:
                    body = memoryview(bytearray(body))
        self._incoming = None
        return self._finish(incoming, head, body)

    def _make_room(self, total: int) -> None:
        """The buffer holds the message of `total` bytes that starts at _start: the bytes
        still to parse move to its front, into a larger buffer where it is too small. Only
        at a read (_fill): messages parsed before it were lent views of the buffer until
        then, and moving bytes in place would overwrite them."""
        if self._start + total <= len(self._buffer):
            return
        have = self._end - self._start
        if total > len(self._buffer):
            fresh = bytearray(total)
            fresh[:have] = memoryview(self._buffer)[self._start:self._end]
            self._buffer = fresh
        else:
            self._buffer[:have] = memoryview(self._buffer)[self._start:self._end]
        self._start, self._end = 0, have

    def _finish(self, incoming: _Incoming, head, body) -> Message:
        json_length, payload_length = incoming.sizes
        text = body[:json_length]
        payload = body[json_length:json_length + payload_length]
        self.last_received = time.monotonic()
        return parse_body(incoming.msg_type, text, payload)

    def _wake_bytes(self) -> int:
        """What the next read waits for: once the header is in, the rest of the message (up to
        LOW_WATER_BYTES), so that a tile arriving over a slow link wakes the reader once or
        twice, not for every segment; before, any byte."""
        incoming = self._incoming
        if incoming is None:
            return 1
        return max(1, min(incoming.total - self._received(), LOW_WATER_BYTES))

    def _fill(self, wait: float = POLL_S) -> None:
        """One read from the socket: into the channel's buffer, as much as it has room for
        (made room for the rest of the message under way first), or into the message's
        own buffer (at most its rest: bytes after it go to the channel's buffer on the next
        read). socket.timeout when nothing came. Over TLS a read returns one record (16 KiB
        at most): then it reads on what has arrived, as long as there is room, so that a tile
        wakes its reader once or twice and not once a record."""
        self._low_water(self._wake_bytes())
        if self._read_once(wait, make_room=True) == 0:
            incoming = self._incoming
            if incoming is None and self._start == self._end:
                raise ConnectionClosed("connection closed by peer")
            where = (f"header: {self._received()} of {HEADER.size} bytes" if incoming is None
                     else incoming.where(self._received()))
            raise ConnectionBroken(f"connection closed in the middle of a message ({where})")
        while self.tls and self._room() >= TLS_RECORD_BYTES:
            try:
                if self._read_once(0.0, make_room=False) == 0:
                    return          # the end: the next read says so
            except socket.timeout:
                return

    def _room(self) -> int:
        """What the next read may take without making room."""
        incoming = self._incoming
        if incoming is not None and incoming.own is not None:
            return incoming.total - HEADER.size - incoming.filled
        return len(self._buffer) - self._end

    def _read_once(self, wait: float, make_room: bool) -> int:
        """One read where _fill says; the bytes it took."""
        incoming = self._incoming
        if incoming is not None and incoming.own is not None:
            rest = incoming.total - HEADER.size - incoming.filled
            if incoming.in_place:
                with memoryview(incoming.own) as view:
                    got = self._read(lambda: self.sock.recv_into(view[incoming.filled:],
                                                                 min(rest, 1 << 20)), wait)
                incoming.filled += got
            else:
                chunk = self._read(lambda: self.sock.recv(min(rest, 1 << 20)), wait)
                got = len(chunk)
                incoming.add(chunk)
            return got
        if make_room:
            # Room for the rest of the message under way, or for a header after the bytes
            # still to parse.
            self._make_room(incoming.total if incoming is not None
                            else self._end - self._start + HEADER.size)
        with memoryview(self._buffer) as view:
            got = self._read(lambda: self.sock.recv_into(view[self._end:]), wait)
        self._end += got
        return got

    def _read(self, read, wait: float = POLL_S):
        """read() on the socket; socket.timeout when nothing came within `wait` s. Over TLS: wait
        for the socket (unless TLS holds decrypted bytes, or wait is 0: the caller knows it is
        readable), then read under the lock; a record not complete yet is also 'nothing
        came'."""
        if not self.tls:
            return read()
        if wait > 0:
            with self._tls_lock:
                ready = self.sock.pending() > 0
            if not ready and not socket_ready(self.sock, False, wait):
                raise socket.timeout("nothing to read")
        with self._tls_lock:
            try:
                return read()
            except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
                raise socket.timeout("a TLS record is not complete yet") from None

    def _low_water(self, nbytes: int) -> None:
        """SO_RCVLOWAT: poll() (so a receive with a timeout, and a selector) wakes once this
        much is there, or at the end of the stream or the timeout. Over TLS, a record's worth
        less: TLS may hold the start of a record already (taken from the socket, not yet
        complete), and the kernel must not wait for bytes that never come; what is still to
        arrive is at least the rest of the message less that record."""
        if self.tls:
            nbytes = max(1, nbytes - TLS_RECORD_BYTES)
        if nbytes != self._rcvlowat and hasattr(socket, "SO_RCVLOWAT"):
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVLOWAT, nbytes)
                self._rcvlowat = nbytes
            except OSError:
                pass

    def drain(self, seconds: float) -> None:
        """Read and drop what the peer still sends, until it closes or `seconds` pass (so
        that closing does not reset a connection whose peer has not read our last words)."""
        deadline = time.monotonic() + seconds
        try:
            while time.monotonic() < deadline:
                try:
                    if not self._read(lambda: self.sock.recv(65536)):
                        return
                except socket.timeout:
                    pass
        except (OSError, ValueError):
            pass

    def _give_budget(self) -> None:
        with self._budget_lock:
            budgeted, self._budgeted = self._budgeted, 0
        if budgeted:
            self.budget.give(budgeted)

    def close(self) -> None:
        """Shut the connection down (wakes a thread blocked on it) and close it."""
        self.closed = True
        self._give_budget()
        try:
            socket.socket.shutdown(self.sock, socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
