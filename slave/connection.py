"""One master's connection on the slave (MasterConnection), the paper's Fig. 3b on this side:
its handshake and admission, its threads and the messages it handles.

Per admitted connection four threads:
- the reader receives messages; it answers scene queries/uploads, validates frames, and puts
  tile requests (and cancels) on the work queue at once, so a cancel is seen while a tile renders;
- the connection's main thread renders tiles from the work queue (the one OpenCL device is
  shared by all connections: render calls are serialised with a lock);
- the sender transmits finished tiles and replies, so rendering never waits on the network;
- the keeper says what the slave is doing (HEARTBEAT) while it has work, so a long tile or a
  kernel build is never mistaken for silence, and closes the connection when the master has
  been idle too long.
The queues between them are slave/queues.py's; the server that accepts connections, gives them
slots and owns the device is slave/server.py's.

Every connection is TLS 1.3 with the master's identity certificate (core/net/secure.py); the
slave serves a master whose ID its owner allowed, that pairs with the slave's pairing code or
that proves the farm secret (core/net/trust.py), and renders for a connection only the scenes
it uploaded or proved it holds.
"""
from __future__ import annotations

import logging
import socket
import ssl
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from ..core.net import protocol, secure, trust
from ..core.net.channel import POLL_S, Channel, end_writing
from ..core.net.identity import short_id
from ..core.net.protocol import MsgType, ProtocolError
from ..core.net.tile_payloads import encode_tile
from ..core.net.tiles import TileGrid, frame_work_problem
from ..core.scene.model import SCENE_FORMAT_VERSION, SceneError, View
from ..core.scene.scene import Scene

from .queues import Frame, Outbox, WorkQueue
from .tracer import RenderStopped

if TYPE_CHECKING:
    from .server import SlaveServer

log = logging.getLogger("kdtrace.slave")

HANDSHAKE_TIMEOUT_S = 10.0  # for the whole handshake, from accept to WELCOME
EVICTABLE_AFTER_S = 5.0     # an idle master (heartbeats alone) gives its slot to a new one
                            # after this long
LINGER_S = 1.0              # reading what a closed peer still sends, so it sees our last words


class MasterConnection:
    """One master's connection; run() is its main (render) thread."""

    def __init__(self, server: "SlaveServer", sock: socket.socket, peer: str):
        self.server, self.peer = server, peer
        self.sock = sock                 # the TCP socket, then the TLS socket
        self.channel: Channel | None = None     # once TLS is up
        self.master_id = ""              # pinned in the TLS handshake
        self.slave_nonce = trust.new_nonce()   # this connection's, for holder proofs
        self.granted: set = set()        # scene hashes this connection uploaded or proved
        self.meshes_proven: set = set()  # meshes hashes it proved it holds
        self.accepted = time.monotonic()
        self.work = WorkQueue()
        self.outbox = Outbox()
        self.frame: Frame | None = None
        self.heartbeat_s = protocol.HEARTBEAT_S
        self.last_heard = self.accepted        # the master's last complete message
        self.last_work = self.accepted         # ... of those other than HEARTBEAT (its slot)
        self.doing = None          # the render loop's (state, frame id, tile), None when idle
        self.reader_doing = None   # the reader's, while it validates a scene upload
        self.ended = threading.Event()
        self._refused = False

    # -- threads

    def run(self) -> None:
        try:
            admitted = self._handshake()
        except Exception:  # never let one connection take the server down
            log.exception("master %s: unexpected error in the handshake", self.peer)
            admitted = False
        finally:
            self.server._handshake_over(self)
        if not admitted:
            self._close_socket(linger=self._refused)
            self.server.activity.master_left(self.peer)
            return
        threads = [threading.Thread(target=target, name=f"{what} {self.peer}", daemon=True)
                   for what, target in (("send", self._send_loop), ("read", self._read_loop),
                                        ("keep", self._keep_loop))]
        for thread in threads:
            thread.start()
        try:
            self._render_loop()
        except Exception:
            log.exception("master %s: unexpected error", self.peer)
            self._end()
        finally:
            self._end()
            threads[0].join()   # the sender: bounded by the channel's send deadline
            self._close_socket(linger=True, reader=threads[1])
            self.server.activity.master_left(self.peer)
            self.server._connection_closed(self)

    def _end(self, error: str | None = None) -> None:
        """Wind the connection down: `error` (if any) is the last thing sent; the sender then
        ends the stream, the reader sees the master close, the render loop stops."""
        if error is not None:
            self.outbox.put((MsgType.ERROR, {"message": error}, None), block=False)
        self.ended.set()
        self.work.close()
        self.outbox.close()

    def abort(self) -> None:
        """Close the connection under whichever thread uses it (eviction, the server's close)."""
        try:
            socket.socket.shutdown(self.sock, socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()

    def _close_socket(self, linger: bool, reader: threading.Thread | None = None) -> None:
        """Close so that the master reads our last message: end our direction, let it close
        (reading and discarding what it still sends), then close."""
        if linger:
            try:
                end_writing(self.sock)
            except OSError:
                linger = False
        if linger and reader is not None and reader.is_alive():
            reader.join(LINGER_S)
        elif linger and self.channel is not None:
            self.channel.drain(LINGER_S)
        elif linger:
            deadline = time.monotonic() + LINGER_S
            try:
                while time.monotonic() < deadline:
                    try:
                        self.sock.settimeout(POLL_S)
                        if not self.sock.recv(65536):
                            break
                    except socket.timeout:
                        pass
            except OSError:
                pass
        if self.channel is not None:
            self.channel.close()
        else:
            self.abort()
        if reader is not None:
            reader.join(LINGER_S)

    def _handshake(self) -> bool:
        """OPEN, TLS (the master's certificate: its ID), HELLO, admission, WELCOME."""
        deadline = self.accepted + HANDSHAKE_TIMEOUT_S
        server = self.server
        try:
            tls, self.master_id = secure.open_server(self.sock, server.identity, deadline)
        except protocol.VersionMismatch as exc:
            return self._refuse_plain(f"protocol version mismatch: master speaks version "
                                      f"{exc.peer_version}, slave speaks version "
                                      f"{protocol.PROTOCOL_VERSION}")
        except protocol.ConnectionClosed:
            return False
        except ProtocolError as exc:
            return self._refuse_plain(str(exc) or type(exc).__name__)
        except ssl.SSLError as exc:
            log.warning("master %s refused: TLS handshake failed (%s): a master must present "
                        "a KD Trace identity", self.peer, exc.reason or exc)
            return False
        except OSError as exc:
            log.info("master %s: left during the handshake: %s", self.peer, exc)
            return False
        self.sock = tls
        self.channel = Channel(tls, "slave", grace_s=HANDSHAKE_TIMEOUT_S,
                               budget=server.uploads)
        self.peer = f"{self.peer} (ID {short_id(self.master_id)})"
        try:
            msg = self.channel.recv(server.limits, {MsgType.HELLO}, deadline=deadline)
            peer_scene = msg.header.get("scene_format_version")
            if peer_scene != SCENE_FORMAT_VERSION:
                raise ProtocolError(f"scene format version mismatch: master uses version "
                                    f"{peer_scene}, slave uses version {SCENE_FORMAT_VERSION}")
            name = trust.sanitize(protocol.get_str(msg.header, "name", 64)) or "?"
            self.peer = f"{name}@{self.peer}"
            if "heartbeat_s" in msg.header:
                low, high = protocol.HEARTBEAT_RANGE_S
                self.heartbeat_s = min(max(protocol.get_float(msg.header, "heartbeat_s"), low), high)
            nonce = protocol.get_str(msg.header, "nonce", trust.NONCE_HEX)
            if len(nonce) != trust.NONCE_HEX:
                raise ProtocolError("bad master nonce")
            admission = self._admission(msg.header, nonce, name)
            if admission is None:
                return False
            admitted_by, proved = admission
            admitted, reason = server._admit(self)
            if not admitted:
                return self._refuse(f"slave busy: {reason}", busy=True)
        except protocol.VersionMismatch as exc:
            return self._refuse(f"protocol version mismatch: master speaks version "
                                f"{exc.peer_version}, slave speaks version {protocol.PROTOCOL_VERSION}")
        except protocol.ConnectionClosed:
            log.info("master %s left before its HELLO (it does not know this slave's ID)",
                     self.peer)
            return False
        except (ProtocolError, OSError) as exc:
            return self._refuse(str(exc) or type(exc).__name__)
        try:
            self.channel.grace_s = protocol.SILENCE_S
            info = server.device_info
            welcome = {"protocol_version": protocol.PROTOCOL_VERSION,
                       "scene_format_version": SCENE_FORMAT_VERSION,
                       "name": server.name, "id": server.slave_id, "nonce": self.slave_nonce,
                       "instance": server.instance,
                       "device": info["name"], "compute_units": info["compute_units"],
                       "memory": info["memory"], "platform": info.get("platform", ""),
                       "admitted_by": admitted_by}
            if proved:      # only after the master proved the secret: nothing guessable before
                welcome["proof"] = trust.slave_farm_proof(server.secret, nonce, self.slave_nonce,
                                                          self.master_id, server.slave_id)
            self.channel.send(MsgType.WELCOME, welcome)
        except (ProtocolError, OSError) as exc:
            log.info("master %s: left during the handshake: %s", self.peer, exc)
            self.server._connection_closed(self)
            return False
        self.last_heard = self.last_work = time.monotonic()
        log.info("master %s connected (%s)", self.peer, {
            "allowed": "allowed by ID", "farm secret": "proved the farm secret",
            "pairing": "paired with the pairing code"}[admitted_by])
        self.server.activity.master_connected(self.peer)
        return True

    def _admission(self, hello: dict, nonce: str, name: str):
        """(how the master is admitted: "allowed", "farm secret" or "pairing", whether it
        proved the farm secret), or None after refusing it. The master proves first; nothing
        derived from a secret goes to a master that has not."""
        server, master_id = self.server, self.master_id
        proved = None
        if server.secret is not None and "proof" in hello:
            proved = trust.proof_ok(trust.master_farm_proof(server.secret, nonce, master_id,
                                                            server.slave_id), hello.get("proof"))
        if server.allowed.allows(master_id):
            return "allowed", bool(proved)
        if proved:
            return "farm secret", True
        if proved is False:
            time.sleep(0.2)  # a little friction for guessers
            self._refuse("authentication failed: wrong farm secret")
            return None
        if "pairing" in hello and server.pairing is not None:
            if server.pairing.check(hello.get("pairing"), nonce, master_id, server.slave_id):
                server.allowed.add(master_id, f"{name}, paired {time.strftime('%Y-%m-%d %H:%M')}")
                log.info("master %s paired with the pairing code: allowed from now on (the code "
                         "is used up)", self.peer)
                return "pairing", False
            time.sleep(0.2)
            left = max(0, trust.PAIRING_TRIES - server.pairing.failures)
            self._refuse("pairing failed: wrong pairing code" + (
                f" ({left} tries left)" if left else
                "; the code is retired after too many wrong tries: restart the slave with "
                "--pair for a new one"))
            return None
        self._refuse(f"this slave does not serve master ID {short_id(master_id)}: it serves the "
                     f"masters its owner allowed" + (" or that prove its farm secret"
                                                     if server.secret is not None else "")
                     + f"; to allow this one, on the slave: kdtrace-slave --allow "
                     f"{short_id(master_id)} (or pair with the code the slave shows)")
        return None

    def _refuse_plain(self, reason: str) -> bool:
        """Refuse before TLS (a bad opening): the reason in plaintext, the opening's framing."""
        log.warning("master %s refused: %s", self.peer, reason)
        self._refused = True
        try:
            self.sock.settimeout(1.0)
            protocol.send_message(self.sock, MsgType.ERROR, {"message": reason})
        except OSError:
            pass
        return False

    def _refuse(self, reason: str, busy: bool = False) -> bool:
        log.warning("master %s refused: %s", self.peer, reason)
        self._refused = True
        try:
            self.channel.send(MsgType.ERROR, {"message": reason, **({"busy": True} if busy else {})})
        except (OSError, ProtocolError):
            pass
        return False

    def _read_loop(self) -> None:
        try:
            while True:
                msg = self.channel.recv(self.server.limits, protocol.MASTER_TO_SLAVE)
                self.last_heard = time.monotonic()
                if msg.type != MsgType.HEARTBEAT:
                    self.last_work = self.last_heard
                if msg.type == MsgType.BYE:
                    log.info("master %s said bye", self.peer)
                    return
                if msg.type == MsgType.ERROR:
                    log.warning("master %s reported: %s", self.peer, msg.header.get("message"))
                    return
                self._handle(msg)
        except protocol.ConnectionClosed:
            if not self.ended.is_set():
                log.info("master %s disconnected", self.peer)
        except ProtocolError as exc:
            log.warning("master %s: closing connection: %s", self.peer, exc)
            self._end(str(exc))
        except ssl.SSLError as exc:
            if not self.ended.is_set():
                log.warning("master %s: closing connection: TLS refused what arrived (%s): "
                            "injected, replayed or damaged on the way", self.peer,
                            exc.reason or exc)
        except OSError as exc:
            if not self.ended.is_set():
                log.info("master %s: connection lost: %s", self.peer, exc)
        except Exception:  # a bug or MemoryError: end this connection, keep the server
            log.exception("master %s: unexpected error", self.peer)
            self._end("internal error in the slave")
        finally:
            self.reader_doing = None
            self._end()

    def _keep_loop(self) -> None:
        try:
            self._keep()
        except Exception:
            log.exception("master %s: unexpected error", self.peer)
            self._end()

    def _keep(self) -> None:
        """Heartbeats while there is work for this master; the idle deadline when there is none."""
        while not self.ended.wait(self.heartbeat_s / 4):
            now = time.monotonic()
            if self.busy:
                if now - self.channel.last_sent >= self.heartbeat_s / 2:
                    try:
                        self.channel.try_send(MsgType.HEARTBEAT, self._heartbeat())
                    except (OSError, ProtocolError) as exc:
                        log.info("master %s: heartbeat failed: %s", self.peer, exc)
                        self._end()
            elif now - self.last_heard > protocol.IDLE_S:
                log.info("master %s: closing: idle for %.0f s", self.peer, now - self.last_heard)
                self._end(f"closing: idle for {now - self.last_heard:.0f} s")

    @property
    def busy(self) -> bool:
        """Something for this master is under way: the master may be waiting for it."""
        return (self.doing is not None or self.reader_doing is not None or self.work.pending
                or self.outbox.pending)

    def evictable(self, now: float) -> float | None:
        """Seconds this master has been idle if it may give its slot to another, else None:
        nothing under way for it, and nothing but heartbeats from it for EVICTABLE_AFTER_S
        (a heartbeat keeps a connection open, not a slot against a master with work)."""
        idle = now - self.last_work
        return idle if not self.busy and idle >= EVICTABLE_AFTER_S else None

    def _heartbeat(self) -> dict:
        doing = self.doing or self.reader_doing or ("waiting", None, None)
        state, frame_id, tile = doing[:3]
        fields = {"state": state}
        if frame_id is not None:
            fields["frame_id"] = frame_id
        if tile is not None:
            fields["tile"] = tile
        return fields

    def _render_loop(self) -> None:
        while True:
            item = self.work.get()
            if item is None:
                return
            if item[0] == "cancel_ack":
                if not self.outbox.put((MsgType.CANCEL, {"frame_id": item[1]}, None)):
                    return
                continue
            _, frame, index = item
            if frame.cancelled:
                self.work.done(frame, index)
                continue
            x, y, w, h = frame.tiles[index]
            built_before = self.server.tracer.build_seconds
            try:
                passes, ms = self.server.render_tile(
                    frame, x, y, w, h, lambda state: self._doing(state, frame, index),
                    stop=lambda: frame.cancelled or self.ended.is_set())
            except RenderStopped:      # cancelled, superseded or the master gone: no tile
                log.debug("master %s: tile %d of frame %d stopped", self.peer, index,
                          frame.frame_id)
                self.work.done(frame, index)
                continue
            except Exception as exc:  # a tracer failure ends this frame, not the slave
                log.exception("master %s: rendering tile %d failed", self.peer, index)
                frame.cancelled = True
                self.work.done(frame, index)
                self.outbox.put((MsgType.ERROR, {"frame_id": frame.frame_id,
                                                 "message": f"rendering failed: {exc}"}, None))
                continue
            finally:
                self.doing = None
            self.server.activity.tile_rendered(self.peer, frame.frame_id, ms,
                                               self.server.tracer.build_seconds - built_before)
            tile = ("tile", frame, index, {"frame_id": frame.frame_id, "tile": index, "x": x,
                                           "y": y, "w": w, "h": h, "render_ms": round(ms, 3)},
                    passes)
            if frame.model == "3a":
                # Fig. 3a: this thread transmits the tile itself before it renders the next.
                try:
                    self._send(tile)
                except (OSError, ProtocolError) as exc:
                    log.info("master %s: send failed: %s", self.peer, exc)
                    return
            elif not self.outbox.put(tile, is_tile=True):
                return

    def _doing(self, state: str, frame: Frame, index: int) -> None:
        self.doing = (state, frame.frame_id, index)

    def _send(self, item) -> None:
        if item[0] == "tile":  # encoding (float16, zlib) happens here, off the render thread in 3b
            _, frame, index, header, passes = item
            self.work.done(frame, index)   # before the master can see it and ask for the next
            fields, arrays = encode_tile(passes, frame.payload, frame.compress, frame.passes)
            item = (MsgType.TILE_RESULT, {**header, **fields}, arrays)
            self.server.activity.sent(self.peer, frame.frame_id,
                                      sum(a.nbytes for a in arrays.values()))
        self.channel.send(*item)

    def _send_loop(self) -> None:
        try:
            while True:
                item = self.outbox.get()
                if item is None:
                    return
                self._send(item)
        except protocol.PeerTooSlow as exc:
            log.warning("master %s: closing connection: %s", self.peer, exc)
            self.outbox.close(discard=True)
        except (OSError, ProtocolError) as exc:
            if not self.ended.is_set():
                log.info("master %s: send failed: %s", self.peer, exc)
            self.outbox.close(discard=True)
        except Exception:
            log.exception("master %s: unexpected error", self.peer)
            self.outbox.close(discard=True)
        finally:
            self._end()
            try:   # our direction is over: the master sees the end after our last message
                end_writing(self.channel.sock)
            except OSError:
                pass

    # -- messages (reader thread)

    def _handle(self, msg: protocol.Message) -> None:
        h = msg.header
        if msg.type == MsgType.SCENE_QUERY:
            # A scene held here counts as present for this connection only if the master
            # proves it holds it too (its hash alone is not enough: hashes are no secret).
            scene_hash = protocol.check_scene_hash(h.get("scene_hash"))
            present = self._proved(self.server.scenes.get(scene_hash), "scene", scene_hash,
                                   h.get("holds"))
            if present:
                self.granted.add(scene_hash)
            answer, held = {"scene_hash": scene_hash, "present": present}, None
            if not present and "meshes_hash" in h:
                meshes_hash = protocol.check_scene_hash(h.get("meshes_hash"))
                base = self.server.scenes.with_meshes(meshes_hash)
                answer["meshes_present"] = self._proved(base, "meshes", meshes_hash,
                                                        h.get("meshes_holds"))
                if answer["meshes_present"]:
                    self.meshes_proven.add(meshes_hash)
            if not present and not answer.get("meshes_present") and "mesh_hashes" in msg.arrays:
                held = {"mesh_held": self._held_meshes(msg.arrays["mesh_hashes"])}
            self.outbox.put((MsgType.SCENE_READY, answer, held))
        elif msg.type == MsgType.SCENE_INSTANCES:
            self._place_instances(h, msg.arrays)
        elif msg.type == MsgType.SCENE_MESHES:
            self._assemble_meshes(h, msg.arrays)
        elif msg.type == MsgType.SCENE_UPLOAD:
            scene_hash = protocol.check_scene_hash(h.get("scene_hash"))
            scene = self._checked_scene(scene_hash, "upload", lambda: Scene.from_wire(msg.arrays))
            self.server.scenes.put(scene)
            self.granted.add(scene_hash)
            log.info("master %s uploaded scene %s (%d triangles)", self.peer, scene_hash[:12],
                     scene.geometry.triangle_count)
            self.outbox.put((MsgType.SCENE_READY, {"scene_hash": scene_hash, "present": True}, None))
        elif msg.type == MsgType.FRAME_START:
            self._start_frame(h)
        elif msg.type == MsgType.TILE_REQUEST:
            frame_id = protocol.get_int(h, "frame_id")
            frame = self.frame
            # Requests for a frame that failed to start or was cancelled are dropped quietly:
            # the master pipelines them before it can know.
            if frame is None or frame.frame_id != frame_id or frame.cancelled:
                return
            index = protocol.get_int(h, "tile", 0, len(frame.tiles) - 1)
            self.work.request(frame, index)
        elif msg.type == MsgType.CANCEL:
            frame_id = protocol.get_int(h, "frame_id")
            frame = self.frame if self.frame and self.frame.frame_id == frame_id else None
            self.work.cancel(frame, frame_id)
            self.server.activity.frame_over(self.peer)
        elif msg.type == MsgType.HEARTBEAT:
            pass        # the master is still there (last_heard): nothing to answer
        else:
            raise ProtocolError(f"unexpected {msg.type.name} after the handshake")

    def _place_instances(self, h: dict, arrays: dict) -> None:
        """SCENE_INSTANCES: the meshes of `meshes_hash` (held here) placed by the instance
        arrays, checked once; only the top level is built. SCENE_READY present=false when the
        meshes went since the query (the master then uploads the whole scene)."""
        scene_hash = protocol.check_scene_hash(h.get("scene_hash"))
        meshes_hash = protocol.check_scene_hash(h.get("meshes_hash"))
        # Only meshes this connection proved it holds (in its SCENE_QUERY).
        base = (self.server.scenes.with_meshes(meshes_hash)
                if meshes_hash in self.meshes_proven else None)
        if base is not None:
            scene = self._checked_scene(scene_hash, "instances",
                                        lambda: base.placed_from_wire(arrays))
            self.server.scenes.put(scene, to_disk=False)
            self.granted.add(scene_hash)
            log.info("master %s placed scene %s (%d instances of held meshes)", self.peer,
                     scene_hash[:12], scene.instances.count)
        self.outbox.put((MsgType.SCENE_READY, {"scene_hash": scene_hash,
                                               "present": base is not None}, None))

    def _held_meshes(self, hashes) -> np.ndarray:
        """u1 (M,): which of the mesh hashes (u1 (M, 16)) a scene held here has."""
        if hashes.dtype != np.uint8 or hashes.ndim != 2 or hashes.shape[1] != 16:
            raise ProtocolError("mesh_hashes must be u1 (M, 16)")
        return np.array([self.server.scenes.held_mesh(bytes(h)) is not None for h in hashes],
                        np.uint8)

    def _assemble_meshes(self, h: dict, arrays: dict) -> None:
        """SCENE_MESHES: the meshes carried, the others taken from the scenes held here by
        their hashes, checked as an upload. SCENE_READY present=false when a mesh not carried
        went since the query (the master then uploads the whole scene)."""
        scene_hash = protocol.check_scene_hash(h.get("scene_hash"))
        cache = self.server.scenes
        new, hashes = arrays.get("mesh_new"), arrays.get("mesh_hashes")
        if hashes is None or new is None or new.dtype != np.uint8 or new.shape != hashes.shape[:1]:
            raise ProtocolError("SCENE_MESHES needs mesh_hashes u1 (M, 16) and mesh_new u1 (M,)")
        proofs = arrays.get("mesh_proofs")
        if proofs is None or proofs.dtype != np.uint8 or \
                proofs.shape != (len(new), trust.MESH_PROOF_BYTES):
            raise ProtocolError(f"SCENE_MESHES needs mesh_proofs u1 (M, {trust.MESH_PROOF_BYTES})")
        lacking = bool(((new == 0) & (self._held_meshes(hashes) == 0)).any())
        # Each mesh taken from the cache only for a master that proves it holds it.
        for m in np.flatnonzero(new == 0):
            if lacking:
                break
            held = cache.held_mesh(bytes(hashes[m]))
            lacking = held is None or not trust.mesh_proof_ok(
                held[0].content_hash(), bytes(hashes[m]), self.slave_nonce, bytes(proofs[m]))
        if not lacking:
            mesh_arrays = {name: a for name, a in arrays.items() if name != "mesh_proofs"}
            scene = self._checked_scene(scene_hash, "meshes",
                                        lambda: Scene.from_mesh_wire(mesh_arrays, cache.held_mesh))
            cache.put(scene)
            self.granted.add(scene_hash)
            log.info("master %s sent %d of the %d meshes of scene %s", self.peer,
                     int(new.sum()), len(new), scene_hash[:12])
        self.outbox.put((MsgType.SCENE_READY, {"scene_hash": scene_hash,
                                               "present": not lacking}, None))

    def _proved(self, scene: Scene | None, what: str, public_hash: str, proof) -> bool:
        """`scene` is held here and the master proved it holds it (what: "scene" or
        "meshes", whose hash is `public_hash`)."""
        if scene is None:
            return False
        return trust.proof_ok(trust.holder_proof(scene.geometry.content_hash(), what,
                                                 public_hash, self.slave_nonce), proof)

    def _checked_scene(self, scene_hash: str, what: str, make) -> Scene:
        """make() (validating what arrived; the keeper heartbeats `loading` meanwhile), whose
        hash must be the one announced; ProtocolError otherwise."""
        self.reader_doing = ("loading", None, None)
        try:
            scene = make()
        except SceneError as exc:
            raise ProtocolError(f"invalid scene {what}: {exc}") from None
        finally:
            self.reader_doing = None
        if scene.hash != scene_hash:
            raise ProtocolError(f"scene {what} hash mismatch: announced {scene_hash}, "
                                f"content hashes to {scene.hash}")
        return scene

    def _start_frame(self, h: dict) -> None:
        """Validate the whole frame now (scene, view against the scene, tiles, formats): a
        frame that is accepted can be rendered."""
        frame_id = protocol.get_int(h, "frame_id")
        if self.frame is not None:   # a new frame supersedes the old one
            self.work.cancel(self.frame, self.frame.frame_id, ack=False)
        self.frame = None
        try:
            scene_hash = protocol.check_scene_hash(h.get("scene_hash"))
            # Only scenes this connection uploaded or proved it holds; the same words for a
            # scene held for others, so that a frame is no oracle for what the cache holds.
            scene = self.server.scenes.get(scene_hash) if scene_hash in self.granted else None
            if scene is None:
                raise SceneError(f"scene {scene_hash} is not loaded on this slave")
            view = View.from_dict(h.get("view"))
            scene.check_view(view)
            tile_w = protocol.get_int(h, "tile_size", 1, protocol.MAX_TILE_SIZE)
            tile_h = protocol.get_int(h, "tile_height", 1, protocol.MAX_TILE_SIZE) \
                if "tile_height" in h else tile_w
            tiles = TileGrid(view.region, (tile_w, tile_h))
            if len(tiles) > protocol.MAX_FRAME_TILES:
                raise ProtocolError(f"{len(tiles)} tiles in the frame, at most "
                                    f"{protocol.MAX_FRAME_TILES}")
            model = h.get("model", protocol.DEFAULT_MODEL)
            payload = h.get("payload", "f32")
            compress = h.get("compress", False)
            if model not in protocol.MODELS or payload not in protocol.PAYLOADS \
                    or not isinstance(compress, bool):
                raise ProtocolError("bad model, payload or compress field")
            try:
                passes = protocol.check_passes(h.get("passes", list(protocol.ALL_PASSES)))
            except ValueError as exc:
                raise ProtocolError(str(exc)) from None
            problem = frame_work_problem(view, (tile_w, tile_h), protocol.MAX_TILE_RAYS,
                                         protocol.MAX_SAMPLE_RAYS)
            if problem:
                raise ProtocolError(f"over the work budget: {problem}")
        except (SceneError, ProtocolError) as exc:
            log.warning("master %s: frame %d refused: %s", self.peer, frame_id, exc)
            self.outbox.put((MsgType.ERROR, {"frame_id": frame_id, "message": str(exc)}, None))
            return
        self.frame = Frame(frame_id, scene, view, tiles, model, payload, compress, passes)
        self.server.activity.frame_started(self.peer, frame_id, scene_hash, len(tiles))
