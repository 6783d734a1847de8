"""The wire protocol: round trips, and every kind of bad input rejected with a clear error."""
from __future__ import annotations

import json
import socket
import struct
import threading
import time

import numpy as np
import pytest

from kdtrace.core.net import protocol
from kdtrace.core.net.channel import RECV_KEEP_BYTES, Channel
from kdtrace.core.net.protocol import (HEADER, MAGIC, PROTOCOL_VERSION, Limits, MsgType,
                                       ProtocolError)
from kdtrace.core.net.tile_payloads import decode_tile
from kdtrace.core.accel.kdtree import KDTree
from kdtrace.core.scene.model import Geometry, SceneError
from kdtrace.core.net.tiles import TilePool, tile_grid
from kdtrace.core.scene.scene import Scene


@pytest.fixture
def pair():
    a, b = socket.socketpair()
    a.settimeout(5)
    b.settimeout(5)
    yield a, b
    a.close()
    b.close()


def raw(msg_type, header: dict, payload: bytes = b"", version=PROTOCOL_VERSION, magic=MAGIC,
        payload_length=None) -> bytes:
    text = json.dumps(header).encode()
    length = len(payload) if payload_length is None else payload_length
    return HEADER.pack(magic, version, int(msg_type), len(text), length) + text + payload


def send_raw(sock, data: bytes, close=True):
    # From a thread: a large write must not block the test before it starts reading.
    def write():
        try:
            sock.sendall(data)
            if close:
                sock.shutdown(socket.SHUT_WR)
        except OSError:
            pass
    thread = threading.Thread(target=write, daemon=True)
    thread.start()
    return thread


def test_round_trip_with_every_allowed_dtype(pair):
    a, b = pair
    arrays = {code: (np.arange(24) % 7).astype("<" + code).reshape(2, 3, 4)
              for code in protocol.ALLOWED_DTYPES}
    arrays["empty"] = np.zeros((0, 3), np.float32)
    protocol.send_message(a, MsgType.TILE_RESULT, {"frame_id": 7, "tile": 3, "text": "é"}, arrays)
    msg = protocol.recv_message(b)
    assert msg.type == MsgType.TILE_RESULT
    assert msg.header == {"frame_id": 7, "tile": 3, "text": "é"}
    assert list(msg.arrays) == list(arrays)
    for name, array in arrays.items():
        assert msg.arrays[name].dtype == array.dtype.newbyteorder("<")
        np.testing.assert_array_equal(msg.arrays[name], array)


def test_big_endian_and_non_contiguous_arrays_are_sent_little_endian(pair):
    a, b = pair
    big = np.arange(6, dtype=">f4").reshape(2, 3)
    strided = np.arange(12, dtype=np.uint32).reshape(3, 4)[:, ::2]
    protocol.send_message(a, MsgType.TILE_RESULT, {}, {"big": big, "strided": strided})
    msg = protocol.recv_message(b)
    np.testing.assert_array_equal(msg.arrays["big"], big)
    np.testing.assert_array_equal(msg.arrays["strided"], strided)


def test_control_message_and_clean_close(pair):
    a, b = pair
    protocol.send_message(a, MsgType.TILE_REQUEST, {"frame_id": 1, "tile": 0})
    a.shutdown(socket.SHUT_WR)
    assert protocol.recv_message(b).header == {"frame_id": 1, "tile": 0}
    with pytest.raises(protocol.ConnectionClosed):
        protocol.recv_message(b)


def test_sending_a_disallowed_dtype_fails_locally(pair):
    with pytest.raises(ValueError, match="cannot be sent"):
        protocol.send_message(pair[0], MsgType.TILE_RESULT, {}, {"x": np.zeros(3, np.float64)})


@pytest.mark.parametrize("data, match", [
    (b"GET / HTTP/1.1\r\nHost: x\r\n\r\n", "not a KD Trace message"),
    (raw(MsgType.BYE, {}, magic=b"XXXX"), "not a KD Trace message"),
    (raw(MsgType.HELLO, {}, version=PROTOCOL_VERSION + 1),
     f"peer speaks version {PROTOCOL_VERSION + 1}, this side speaks version {PROTOCOL_VERSION}"),
    (raw(99, {}), "unknown message type 99"),
    (HEADER.pack(MAGIC, PROTOCOL_VERSION, MsgType.BYE, 5, 0) + b"\xff\xfe{}}", "invalid JSON"),
    (HEADER.pack(MAGIC, PROTOCOL_VERSION, MsgType.BYE, 2, 0) + b"[]", "not an object"),
    (HEADER.pack(MAGIC, PROTOCOL_VERSION, MsgType.BYE, 10, 0) + b'{"a": NaN}', "invalid JSON"),
    (HEADER.pack(MAGIC, PROTOCOL_VERSION, MsgType.BYE, 2000, 0) + b"[" * 2000, "invalid JSON"),
    (raw(MsgType.BYE, {})[:10], "in the middle of a message"),
    (raw(MsgType.BYE, {"a": 1})[:-2], "in the middle of a message"),
    (raw(MsgType.TILE_RESULT, {"arrays": [{"name": "a", "dtype": "f4", "shape": [4]}]},
         b"\0" * 8, payload_length=16), "in the middle of a message"),
])
def test_garbage_and_truncation_are_rejected(pair, data, match):
    a, b = pair
    send_raw(a, data)
    with pytest.raises(ProtocolError, match=match):
        protocol.recv_message(b)


def test_version_mismatch_names_both_versions(pair):
    a, b = pair
    send_raw(a, raw(MsgType.HELLO, {}, version=9))
    with pytest.raises(protocol.VersionMismatch) as info:
        protocol.recv_message(b)
    assert info.value.peer_version == 9
    assert "version 9" in str(info.value) and f"version {PROTOCOL_VERSION}" in str(info.value)


@pytest.mark.parametrize("specs, payload, match", [
    ([{"name": "a", "dtype": "f8", "shape": [2]}], b"\0" * 16, "dtype 'f8' not allowed"),
    ([{"name": "a", "dtype": "O", "shape": [2]}], b"\0" * 16, "not allowed"),
    ([{"name": "a", "dtype": "f4", "shape": [3]}], b"\0" * 16, "do not match"),
    ([{"name": "a", "dtype": "f4", "shape": [5]}], b"\0" * 16, "do not match"),
    ([{"name": "a", "dtype": "f4", "shape": [-4]}], b"\0" * 16, "bad shape"),
    ([{"name": "a", "dtype": "f4", "shape": [2.0]}], b"\0" * 8, "bad shape"),
    ([{"name": "a", "dtype": "f4", "shape": "2"}], b"\0" * 8, "bad shape"),
    ([{"name": "a", "dtype": "u1", "shape": [1, 1, 1, 1, 1]}], b"\0", "bad shape"),
    ([{"name": "a", "dtype": "u1", "shape": [1]}, {"name": "a", "dtype": "u1", "shape": [1]}],
     b"\0\0", "duplicate"),
    ([{"dtype": "u1", "shape": [1]}], b"\0", "array name"),
    ({"name": "a"}, b"", "must be a list"),
    (["a"], b"", "not an object"),
])
def test_bad_array_descriptions_are_rejected(pair, specs, payload, match):
    a, b = pair
    send_raw(a, raw(MsgType.TILE_RESULT, {"arrays": specs}, payload))
    with pytest.raises(ProtocolError, match=match):
        protocol.recv_message(b)


def test_oversized_messages_are_rejected_before_reading(pair):
    a, b = pair
    # A control message may carry no payload at all, whatever it claims.
    a.sendall(HEADER.pack(MAGIC, PROTOCOL_VERSION, MsgType.TILE_REQUEST, 2, 1 << 40))
    with pytest.raises(ProtocolError, match="TILE_REQUEST payload of 1099511627776 bytes exceeds"):
        protocol.recv_message(b)
    a.sendall(HEADER.pack(MAGIC, PROTOCOL_VERSION, MsgType.BYE, 1 << 30, 0))
    with pytest.raises(ProtocolError, match="JSON of 1073741824 bytes exceeds"):
        protocol.recv_message(b)
    # A tile bigger than the tiles of the frame.
    limits = Limits(max_tile_pixels=16 * 16)
    a.sendall(HEADER.pack(MAGIC, PROTOCOL_VERSION, MsgType.TILE_RESULT, 2,
                          17 * 16 * protocol.TILE_BYTES_PER_PIXEL))
    with pytest.raises(ProtocolError, match="TILE_RESULT payload .* exceeds"):
        protocol.recv_message(b, limits)
    a.sendall(HEADER.pack(MAGIC, PROTOCOL_VERSION, MsgType.SCENE_UPLOAD, 2, 1001))
    with pytest.raises(ProtocolError, match="SCENE_UPLOAD payload of 1001 bytes exceeds the limit of 1000"):
        protocol.recv_message(b, Limits(max_scene_bytes=1000))


def test_unexpected_message_type_for_the_direction(pair):
    a, b = pair
    protocol.send_message(a, MsgType.HELLO, {})
    with pytest.raises(ProtocolError, match="unexpected message type HELLO"):
        protocol.recv_message(b, allowed=protocol.SLAVE_TO_MASTER)


# -- scenes ---------------------------------------------------------------------------------
def small_scene():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    triangles = np.array([[0, 1, 2], [1, 3, 2]], np.uint32)
    geometry = Geometry(vertices, triangles, np.zeros(2, np.uint16))
    tree = KDTree(np.array([[(2 << 2) | 3, 0]], np.uint32), np.array([0, 1], np.uint32),
                  np.array([[0, 0, 0], [1, 1, 0]], np.float32))
    return geometry, tree


def test_scene_round_trip_and_hash(pair):
    a, b = pair
    geometry, tree = small_scene()
    scene_hash = Scene.from_parts(geometry, tree).hash
    protocol.send_message(a, MsgType.SCENE_UPLOAD, {"scene_hash": scene_hash},
                          Scene.from_parts(geometry, tree).wire_arrays())
    msg = protocol.recv_message(b)
    assert Scene.from_wire(msg.arrays).hash == scene_hash
    assert protocol.check_scene_hash(scene_hash) == scene_hash
    # The hash covers the tree as well as the geometry.
    tree.bounds = tree.bounds + np.float32(1)
    assert Scene.from_parts(geometry, tree).hash != scene_hash


def test_scene_hash_depends_on_the_kdtree_mode():
    """The mode and thresholds are part of what the master builds: other arrays, another hash;
    the compact arrays round-trip through the upload unchanged."""
    from kdtrace.core.accel.kdtree import build_kdtree
    from kdtrace.core.accel.compact import compact_tree
    from tests.meshes import uv_sphere
    vertices, triangles = uv_sphere(32, 16)
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    tree = build_kdtree(vertices, triangles)
    trees = {mode: compact_tree(tree, len(triangles), mode) for mode in ("standard", "choi", "compressed")}
    hashes = {mode: Scene.from_parts(geometry, ct).hash for mode, ct in trees.items()}
    assert len(set(hashes.values())) == 3
    assert Scene.from_parts(geometry, tree).hash == hashes["standard"]   # plain = standard
    loose = compact_tree(tree, len(triangles), "compressed", tau_occu=0.05, tau_freq=0.05)
    assert Scene.from_parts(geometry, loose).hash != hashes["compressed"]
    received = Scene.from_wire(Scene.from_parts(geometry, trees["compressed"]).wire_arrays())
    assert received.hash == hashes["compressed"]
    assert np.array_equal(received.tree.leaf_index16, trees["compressed"].leaf_index16)
    assert received.tree.leaf_shift == trees["compressed"].leaf_shift


def test_a_geometry_takes_a_hash_only_from_the_same_bits():
    """Geometry.take_hash (the add-on's reuse of the last render's mesh hashes): the hash it
    takes is the one hashing would give, and any difference of bits, shape or arrays present
    (-0.0 against 0.0, one normal, normals against none) makes it hash instead."""
    from tests.meshes import uv_sphere
    vertices, triangles = uv_sphere(16, 8)
    ids = np.zeros(len(triangles), np.uint16)
    normals = np.tile(np.float32([0, 0, 1]), (3 * len(triangles), 1))

    def made(v=vertices, n=normals):
        return Geometry(v.copy(), triangles.copy(), ids.copy(), None if n is None else n.copy())

    old = made()
    digest = old.content_hash()
    same = made()
    assert same.take_hash(digest, old.arrays())
    assert same.content_hash() == digest == made().content_hash()
    signed_zero = vertices.copy()
    signed_zero[vertices == 0] = -0.0
    assert (signed_zero == vertices).all() and (vertices == 0).any()
    one_normal = normals.copy()
    one_normal[5] = [0, 1, 0]
    for changed in (made(v=signed_zero), made(n=one_normal), made(n=None), made(v=vertices[:-1])):
        assert not changed.take_hash(digest, old.arrays())
        assert changed.content_hash() != digest


@pytest.mark.parametrize("change, match", [
    (lambda s: s.pop("bounds"), "must carry the arrays"),
    (lambda s: s.update(colours=s["bounds"]), "must carry the arrays"),
    (lambda s: s.update(normals=s["vertices"][:5]), "normals"),
    (lambda s: s.update(nodes=s["nodes"].astype(np.int32)), "'nodes' must be"),
    (lambda s: s.update(vertices=s["vertices"].reshape(-1)), "'vertices' must be"),
    (lambda s: s.update(triangles=s["triangles"] + 7), "vertex that does not exist"),
    (lambda s: s.update(vertices=s["vertices"] * np.float32(np.nan)), "NaN"),
    (lambda s: s.update(nodes=np.array([[(9 << 3) | 3, 0]], np.uint32)), "past the end"),
    (lambda s: s.update(nodes=np.array([[(5 << 5) | 0, 0]], np.uint32)), "outside the tree"),
    (lambda s: s.update(nodes=np.array([[(0 << 5) | 0, 0]], np.uint32)), "backwards"),
    (lambda s: s.update(leaf_index32=np.array([0, 5], np.uint32)), "triangle that does not exist"),
    # 16-bit leaf (W = 1, count 2, base 0) whose second entry names triangle 7 of 2.
    (lambda s: s.update(nodes=np.array([[(2 << 3) | 4 | 3, 0]], np.uint32),
                        leaf_index16=np.array([0, 7], np.uint16)), "triangle that does not exist"),
    # Inner node with a reference slot naming triangle 9, two leaves.
    (lambda s: s.update(nodes=np.array([[(1 << 5) | 4, 0], [9, 0xFFFFFFFF], [3, 0], [3, 0]],
                                       np.uint32)), "slot names a triangle"),
    # Indices at 32 bits (tests/test_bounds.py): a 32-bit leaf of one triangle at offset
    # 2^32 - 1 or 2^31; a 16-bit leaf whose (base << leaf_shift) + entry is 2^32 - 1; a slot.
    (lambda s: s.update(nodes=np.array([[(1 << 3) | 3, 2 ** 32 - 1]], np.uint32)),
     "past the end of leaf_index32"),
    (lambda s: s.update(nodes=np.array([[(1 << 3) | 3, 2 ** 31]], np.uint32)),
     "past the end of leaf_index32"),
    (lambda s: s.update(nodes=np.array([[(0xFFFF << 16) | (1 << 3) | 4 | 3, 0]], np.uint32),
                        leaf_index16=np.array([0xFFFF], np.uint16),
                        leaf_shift=np.array([16], np.uint32)), "triangle that does not exist"),
    (lambda s: s.update(nodes=np.array([[(1 << 5) | 4, 0], [2 ** 32 - 2, 0xFFFFFFFF], [3, 0],
                                        [3, 0]], np.uint32)), "slot names a triangle"),
    (lambda s: s.update(leaf_shift=np.array([40], np.uint32)), "leaf_shift"),
    (lambda s: s.update(leaf_shift=np.array([0, 0], np.uint32)), "'leaf_shift' must be"),
    (lambda s: s.pop("leaf_index16"), "must carry the arrays"),
    (lambda s: s.update(nodes=np.zeros((0, 2), np.uint32)), "no nodes"),
])
def test_bad_scenes_are_rejected(change, match):
    geometry, tree = small_scene()
    arrays = Scene.from_parts(geometry, tree).wire_arrays()
    change(arrays)
    with pytest.raises(SceneError, match=match):
        Scene.from_wire(arrays)


def test_tile_pass_validation():
    """The master's check of a received tile (decode_tile): names, shapes, finite values."""
    good = {"combined": np.zeros((3, 4, 4), np.float32), "depth": np.zeros((3, 4), np.float32),
            "normal": np.zeros((3, 4, 3), np.float32)}
    assert set(decode_tile({}, good, 4, 3, "f32")) == set(good)
    with pytest.raises(ProtocolError, match=r"must be <f4 \(4, 3, 4\)"):
        decode_tile({}, good, 3, 4, "f32")
    bad = dict(good, depth=np.full((3, 4), np.inf, np.float32))
    with pytest.raises(ProtocolError, match="NaN or infinity"):
        decode_tile({}, bad, 4, 3, "f32")
    with pytest.raises(ProtocolError, match="tile passes must be"):
        decode_tile({}, {"combined": good["combined"]}, 4, 3, "f32")


def test_field_helpers():
    assert protocol.get_int({"a": 3}, "a", 0, 5) == 3
    for value in (True, 3.0, "3", 9, None):
        with pytest.raises(ProtocolError, match="'a' must be an integer"):
            protocol.get_int({"a": value}, "a", 0, 5)
    with pytest.raises(ProtocolError):
        protocol.check_scene_hash("../../etc/passwd")


# -- tiles ----------------------------------------------------------------------------------
def test_tile_grid_covers_the_region_row_by_row():
    tiles = tile_grid((3, 2, 13, 9), 4)
    assert tiles[:3] == [(3, 2, 4, 4), (7, 2, 4, 4), (11, 2, 2, 4)]
    assert tiles[3] == (3, 6, 4, 3)
    covered = np.zeros((9, 13), int)
    for x, y, w, h in tiles:
        covered[y:y + h, x:x + w] += 1
    assert (covered[2:9, 3:13] == 1).all() and covered.sum() == 70
    with pytest.raises(ValueError):
        tile_grid((0, 0, 4, 4), 0)


def test_tile_pool_hands_out_puts_back_and_finishes():
    pool = TilePool(3)
    assert [pool.take(0), pool.take(0), pool.take(0)] == [0, 1, 2]
    assert pool.take(0.01) is None
    pool.put_back(1)
    assert pool.take(0) == 1
    for index in (0, 1, 2):
        assert pool.mark_done(index)
    assert not pool.mark_done(2)          # a duplicate
    assert pool.all_done and pool.take(1.0) is None   # returns at once when all are done
    closed = TilePool(2)
    closed.close()
    assert closed.take(1.0) is None


def test_the_end_of_a_long_part_arriving_late_is_received():
    """A long payload whose last bytes come after a pause (as over a slow link): the read of
    those last bytes must not wait for a low-water mark set for the bytes before them."""
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)   # holds all but the tail
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    sender = socket.create_connection(listener.getsockname())
    receiver, _ = listener.accept()
    listener.close()
    data = b"".join(bytes(b) for b in protocol.encode_message(
        MsgType.SCENE_UPLOAD, {"scene_hash": "0" * 32},
        {"values": np.arange(1 << 19, dtype=np.float32)}))           # 2 MiB
    tail = 20_000

    def write():
        sender.sendall(data[:-tail])
        threading.Event().wait(0.5)
        sender.sendall(data[-tail:])
    thread = threading.Thread(target=write, daemon=True)
    thread.start()
    threading.Event().wait(0.2)     # all but the tail waits in the receive buffer
    try:
        channel = Channel(receiver, "slave")
        msg = channel.recv(deadline=time.monotonic() + 5)
        np.testing.assert_array_equal(msg.arrays["values"], np.arange(1 << 19, dtype=np.float32))
    finally:
        thread.join(5)
        sender.close()
        receiver.close()


def test_a_channel_parses_messages_where_they_lie_and_big_ones_in_their_own_buffer(pair):
    """Several messages in one write come out of one channel buffer, the frame loop's arrays
    as views of it (valid until the next read), recv()'s as copies of their own; a message
    over RECV_KEEP_BYTES (a scene) arrives whole in a buffer of its own, and the messages
    after it still arrive; a message cut short names the part it was cut in."""
    a, b = pair
    tile = np.arange(64 * 64 * 4, dtype=np.float32).reshape(64, 64, 4)
    scene = np.arange((RECV_KEEP_BYTES + 4096) // 4, dtype=np.float32)
    data = b"".join(bytes(part) for msg in (
        (MsgType.TILE_RESULT, {"tile": 1}, {"combined": tile}),
        (MsgType.HEARTBEAT, {"state": "idle"}, None),
        (MsgType.SCENE_UPLOAD, {"scene_hash": "0" * 32}, {"values": scene}),
        (MsgType.TILE_RESULT, {"tile": 2}, {"combined": tile + 1}),
    ) for part in protocol.encode_message(*msg))
    writer = send_raw(a, data)
    channel = Channel(b, "master")
    received = []
    while len(received) < 2:
        for msg in channel.recv_available():    # handled before the next read, as it must
            received.append(msg.type)
            if msg.type == MsgType.TILE_RESULT:
                np.testing.assert_array_equal(msg.arrays["combined"], tile)
                assert np.shares_memory(msg.arrays["combined"],
                                        np.frombuffer(channel._buffer, np.uint8))
    assert received[:2] == [MsgType.TILE_RESULT, MsgType.HEARTBEAT]
    big = channel.recv(deadline=time.monotonic() + 5)       # its own buffer, its own arrays
    np.testing.assert_array_equal(big.arrays["values"], scene)
    assert not np.shares_memory(big.arrays["values"], np.frombuffer(channel._buffer, np.uint8))
    last = channel.recv(deadline=time.monotonic() + 5)
    assert last.header["tile"] == 2
    assert not np.shares_memory(last.arrays["combined"], np.frombuffer(channel._buffer, np.uint8))
    np.testing.assert_array_equal(last.arrays["combined"], tile + 1)
    writer.join(5)
    with pytest.raises(protocol.ConnectionClosed):
        channel.recv(deadline=time.monotonic() + 5)


def test_a_message_cut_short_in_a_channel_names_its_part():
    for cut, part in ((10, "header"), (HEADER.size + 5, "JSON"), (-100, "payload")):
        a, b = socket.socketpair()
        try:
            data = b"".join(bytes(p) for p in protocol.encode_message(
                MsgType.TILE_RESULT, {"tile": 1}, {"combined": np.zeros((8, 8, 4), np.float32)}))
            send_raw(a, data[:cut]).join(5)
            with pytest.raises(protocol.ConnectionBroken, match=f"middle of a message \\({part}: "):
                Channel(b, "master").recv(deadline=time.monotonic() + 5)
        finally:
            a.close()
            b.close()


def test_messages_lent_by_one_read_stay_intact_while_the_next_one_waits(pair):
    """recv_available lends every message of a read until the next read: one that completes
    a tile and also holds the start of a tile too long for the rest of the buffer must not
    move that start over the tile lent (the frame loop composes tiles after the call)."""
    a, b = pair
    tiles = [np.full((48, 48, 4), i, np.float32) + np.arange(4, dtype=np.float32)
             for i in range(6)]              # 36 KiB each: two do not fit the 64 KiB buffer
    data = b"".join(bytes(part) for i, tile in enumerate(tiles)
                    for part in protocol.encode_message(MsgType.TILE_RESULT, {"tile": i},
                                                        {"combined": tile}))
    writer = send_raw(a, data)
    channel = Channel(b, "master")
    seen = []
    while len(seen) < len(tiles):
        batch = channel.recv_available()
        for msg in batch:                    # after the whole batch is parsed, as the master
            np.testing.assert_array_equal(msg.arrays["combined"], tiles[msg.header["tile"]])
            seen.append(msg.header["tile"])
    assert seen == list(range(len(tiles)))
    writer.join(5)
