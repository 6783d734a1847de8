"""Units of the distributed runtime: tile pool with end-of-frame copies, partitions, tile
payloads (float16, zlib), farm proofs and secrets, the disk scene cache, the link emulator."""
from __future__ import annotations

import socket
import threading
import time
import zlib

import numpy as np
import pytest

from kdtrace.core.net import trust
from tests.linkemu import LinkEmulator
from kdtrace.core.net.protocol import ProtocolError
from kdtrace.core.net.tiles import TilePool, partition_tile_size, tile_grid
from kdtrace.core.net.tile_payloads import decode_tile, encode_tile
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.scene_cache import SceneCache
from tests.test_network import make_scene


def test_partition_covers_the_region_exactly():
    for n in (2, 4, 8, 16):
        dims = partition_tile_size((0, 0, 1000, 600), n)
        tiles = tile_grid((0, 0, 1000, 600), dims)
        assert len(tiles) == n * n
        assert sum(w * h for _, _, w, h in tiles) == 1000 * 600
    assert tile_grid((0, 0, 10, 4), (4, 3))[-1] == (8, 3, 2, 1)
    with pytest.raises(ValueError):
        tile_grid((0, 0, 10, 10), (0, 3))


def test_pool_hands_out_copies_only_when_nothing_is_pending():
    pool = TilePool(3)
    a, b = object(), object()
    assert [pool.take(0, a, True), pool.take(0, a, True), pool.take(0, b, True)] == [0, 1, 2]
    assert pool.take(0, b, True) == 0          # a copy of the oldest tile b does not hold
    assert pool.take(0, b, True) == 1
    assert pool.take(0, b, True) is None       # b holds a copy of everything it may
    assert pool.take(0, a, False) is None      # no copies asked for
    assert pool.mark_done(0) and not pool.mark_done(0)   # first result wins
    pool.put_back(1, a)                        # a lost: b still has tile 1, nothing pending
    assert pool.take(0, a, False) is None
    pool.put_back(1, b)                        # b lost too: pending again
    assert pool.take(0, a, False) == 1
    assert pool.duplicates_handed_out == 2


@pytest.mark.parametrize("payload, compress", [("f32", False), ("f32", True), ("f16", False), ("f16", True)])
def test_tile_payload_round_trip(payload, compress):
    rng = np.random.default_rng(1)
    w, h = 16, 8
    passes = {"combined": np.zeros((h, w, 4), np.float32),   # compressible: mostly flat
              "depth": np.full((h, w), 1e10, np.float32),
              "normal": rng.normal(size=(h, w, 3)).astype(np.float32)}
    passes["combined"][:2] = rng.random((2, w, 4))
    fields, arrays = encode_tile(passes, payload, compress)
    assert fields["compression"] == ("zlib" if compress else "none")
    decoded = decode_tile(fields, arrays, w, h, payload)
    np.testing.assert_array_equal(decoded["depth"], passes["depth"])   # depth always float32
    tolerance = 0 if payload == "f32" else 2e-3
    for name in ("combined", "normal"):
        assert decoded[name].dtype == np.float32
        np.testing.assert_allclose(decoded[name], passes[name], rtol=tolerance, atol=tolerance)


def test_tile_payload_rejects_bombs_and_lies():
    w = h = 8
    expected = w * h * 32
    bomb = {"zlib": np.frombuffer(zlib.compress(b"\0" * (expected * 100)), np.uint8)}
    with pytest.raises(ProtocolError, match="wrong size"):
        decode_tile({"payload": "f32", "compression": "zlib"}, bomb, w, h, "f32")
    with pytest.raises(ProtocolError, match="inflate"):
        decode_tile({"payload": "f32", "compression": "zlib"},
                    {"zlib": np.arange(50, dtype=np.uint8)}, w, h, "f32")
    f16 = {"combined": np.zeros((h, w, 4), np.float16), "depth": np.zeros((h, w), np.float32),
           "normal": np.zeros((h, w, 3), np.float16)}
    with pytest.raises(ProtocolError, match="expected 'f32'"):
        decode_tile({"payload": "f16"}, f16, w, h, "f32")
    with pytest.raises(ProtocolError, match="must be <f4"):
        decode_tile({"payload": "f32"}, f16, w, h, "f32")
    with pytest.raises(ProtocolError, match="compression"):
        decode_tile({"payload": "f16", "compression": "lz4"}, f16, w, h, "f16")
    f16["normal"][0, 0, 0] = np.inf
    with pytest.raises(ProtocolError, match="NaN or infinity"):
        decode_tile({"payload": "f16"}, f16, w, h, "f16")


def test_farm_proofs_and_secrets(tmp_path, monkeypatch):
    secret, other = trust.new_farm_secret().encode(), trust.new_farm_secret().encode()
    m, s = trust.new_nonce(), trust.new_nonce()
    master, slave = "A" * 52, "B" * 52
    proof = trust.master_farm_proof(secret, m, master, slave)
    assert trust.proof_ok(trust.master_farm_proof(secret, m, master, slave), proof)
    # Bound to the secret, the nonce, both IDs and the role: worth nothing anywhere else.
    for wrong in (trust.master_farm_proof(other, m, master, slave),
                  trust.master_farm_proof(secret, s, master, slave),
                  trust.master_farm_proof(secret, m, slave, master),
                  trust.slave_farm_proof(secret, m, s, master, slave)):
        assert not trust.proof_ok(wrong, proof)
    assert not trust.proof_ok(proof, None) and not trust.proof_ok(proof, proof[:-1])
    monkeypatch.delenv(trust.SECRET_ENV, raising=False)
    assert trust.load_secret() is None
    monkeypatch.setenv(trust.SECRET_ENV, f" {secret.decode()} ")
    assert trust.load_secret() == secret
    path = tmp_path / "s"
    trust.write_new_secret(path)
    assert trust.load_secret(str(path)).startswith(b"kdtrace-farm-")
    assert path.stat().st_mode & 0o777 == 0o600
    with pytest.raises(trust.AuthError, match="never overwritten"):
        trust.write_new_secret(path)
    # A password chosen by hand is refused, with how to make a real one.
    for typed in ("hunter2\n", "correct horse battery staple", "kdtrace-farm-short"):
        path.write_text(typed)
        with pytest.raises(trust.AuthError, match="does not hold a generated farm secret.*--new-secret"):
            trust.load_secret(str(path))
    path.write_text("  \n")
    with pytest.raises(trust.AuthError, match="empty"):
        trust.load_secret(str(path))
    with pytest.raises(trust.AuthError, match="cannot read"):
        trust.load_secret(str(tmp_path / "missing"))


def test_disk_scene_cache_survives_a_restart_and_drops_damaged_files(tmp_path):
    geometry, tree = make_scene()
    scene = Scene.from_parts(geometry, tree)
    scene_hash = scene.hash
    SceneCache(2, tmp_path).put(scene)
    fresh = SceneCache(2, tmp_path)                       # a restarted slave
    loaded = fresh.get(scene_hash)
    assert loaded is not None and loaded.hash == scene_hash
    path = tmp_path / f"{scene_hash}.npz"
    path.write_bytes(path.read_bytes()[:200])             # damaged on disk
    assert SceneCache(2, tmp_path).get(scene_hash) is None and not path.exists()
    small = SceneCache(1, tmp_path, disk_limit_bytes=1)   # too big for the disk limit: memory only
    small.put(scene)
    assert not path.exists() and small.get(scene_hash) is not None


def test_link_emulator_adds_latency_and_limits_bandwidth():
    server = socket.create_server(("127.0.0.1", 0))

    def echo():
        conn, _ = server.accept()
        with conn:
            while data := conn.recv(65536):
                conn.sendall(data)
    threading.Thread(target=echo, daemon=True).start()
    with LinkEmulator(server.getsockname(), latency_s=0.02, bandwidth_bps=80e6) as link:
        with socket.create_connection(link.endpoint) as sock:
            start = time.perf_counter()
            sock.sendall(b"x")
            assert sock.recv(1) == b"x"
            rtt = time.perf_counter() - start
            payload = b"y" * 1_000_000                    # 8 Mbit each way: >= 0.1 s per direction
            start = time.perf_counter()
            threading.Thread(target=sock.sendall, args=(payload,), daemon=True).start()
            got = 0
            while got < len(payload):
                got += len(sock.recv(1 << 20))
            elapsed = time.perf_counter() - start
    server.close()
    assert 0.04 <= rtt < 0.2
    assert 0.14 <= elapsed < 1.0
