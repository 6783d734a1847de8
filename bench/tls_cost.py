"""What TLS costs a tile and an upload (issue 39): the same messages through a protocol Channel
over a plain socket pair and over TLS 1.3 with two identities (core/net/secure.py), in one
process, both ends on their own threads. CPU is the process's (both ends: encryption and
decryption, and the framing both ways), per tile and per MiB of scene.

    .venv/bin/python bench/tls_cost.py [--tiles 2000] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import pathlib
import socket
import sys
import threading
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from kdtrace.core.net import protocol, secure  # noqa: E402
from kdtrace.core.net.channel import Channel  # noqa: E402
from kdtrace.core.net.identity import Identity  # noqa: E402
from kdtrace.core.net.protocol import MsgType  # noqa: E402
from kdtrace.core.net.tile_payloads import encode_tile  # noqa: E402


IDENTITIES = {}


def pair(tls: bool):
    a, b = socket.socketpair()
    if not tls:
        return Channel(a, "master"), Channel(b, "slave")
    if not IDENTITIES:
        IDENTITIES.update(master=Identity.ephemeral("master"), slave=Identity.ephemeral("slave"))
    master, slave, out = IDENTITIES["master"], IDENTITIES["slave"], {}
    server = threading.Thread(target=lambda: out.update(
        s=secure.open_server(b, slave, time.monotonic() + 10)[0]))
    server.start()
    client = secure.open_client(a, master, time.monotonic() + 10)[0]
    server.join()
    return Channel(client, "master"), Channel(out["s"], "slave")


def run(tls: bool, count: int, msg_type, header, arrays, limits) -> tuple:
    """(wall s, process CPU s) to send `count` messages one way and receive them."""
    master, slave = pair(tls)
    encoded = protocol.encode_message(msg_type, header, arrays)

    def send():
        for _ in range(count):
            slave.send_encoded(encoded)
    started, cpu = time.perf_counter(), time.process_time()
    sender = threading.Thread(target=send)
    sender.start()
    for _ in range(count):
        master.recv(limits)
    sender.join()
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu
    master.close()
    slave.close()
    return wall, cpu


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiles", type=int, default=2000)
    parser.add_argument("--uploads", type=int, default=20)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    limits = protocol.Limits()
    rows = {}
    for label, edge, passes in (("64 px combined f32", 64, ("combined",)),
                                ("64 px combined u8", 64, ("combined",)),
                                ("256 px all passes f32", 256, protocol.ALL_PASSES)):
        payload = "u8" if "u8" in label else "f32"
        tile = {"combined": np.random.rand(edge, edge, 4).astype(np.float32),
                "depth": np.random.rand(edge, edge).astype(np.float32),
                "normal": np.random.rand(edge, edge, 3).astype(np.float32)}
        fields, arrays = encode_tile(tile, payload, False, passes)
        limits.tile_bytes_per_pixel = protocol.tile_bytes_per_pixel(payload, passes)
        count = args.tiles if edge == 64 else args.tiles // 8
        header = {"frame_id": 1, "tile": 0, "x": 0, "y": 0, "w": edge, "h": edge,
                  "render_ms": 1.0, **fields}
        nbytes = sum(a.nbytes for a in arrays.values())
        plain = run(False, count, MsgType.TILE_RESULT, header, arrays, limits)
        secured = run(True, count, MsgType.TILE_RESULT, header, arrays, limits)
        rows[label] = {"bytes": nbytes, "count": count,
                       "plain_us_cpu": plain[1] / count * 1e6, "tls_us_cpu": secured[1] / count * 1e6,
                       "plain_us_wall": plain[0] / count * 1e6, "tls_us_wall": secured[0] / count * 1e6}
    scene = {"vertices": np.random.rand(1 << 18, 3).astype(np.float32),        # 3 MiB
             "triangles": np.random.randint(0, 1 << 18, (1 << 17, 3)).astype(np.uint32)}
    mib = sum(a.nbytes for a in scene.values()) / 2 ** 20
    plain = run(False, args.uploads, MsgType.SCENE_UPLOAD, {"scene_hash": "0" * 32}, scene, limits)
    secured = run(True, args.uploads, MsgType.SCENE_UPLOAD, {"scene_hash": "0" * 32}, scene, limits)
    rows["scene upload"] = {"bytes": int(mib * 2 ** 20), "count": args.uploads,
                            "plain_ms_cpu_per_mib": plain[1] / args.uploads / mib * 1e3,
                            "tls_ms_cpu_per_mib": secured[1] / args.uploads / mib * 1e3,
                            "plain_ms_wall_per_mib": plain[0] / args.uploads / mib * 1e3,
                            "tls_ms_wall_per_mib": secured[0] / args.uploads / mib * 1e3}
    handshakes = []
    for _ in range(20):
        started = time.perf_counter()
        master, slave = pair(True)
        handshakes.append(time.perf_counter() - started)
        master.close()
        slave.close()
    rows["handshake"] = {"median_ms": float(np.median(handshakes)) * 1e3}
    print(f"{'message':24} {'bytes':>9} {'plain':>12} {'TLS':>12} {'TLS extra':>12}   (CPU of both ends)")
    for label, row in rows.items():
        if "plain_us_cpu" in row:
            print(f"{label:24} {row['bytes']:>9} {row['plain_us_cpu']:>9.1f} us {row['tls_us_cpu']:>9.1f} us "
                  f"{row['tls_us_cpu'] - row['plain_us_cpu']:>9.1f} us")
        elif "plain_ms_cpu_per_mib" in row:
            print(f"{label + ' (per MiB)':24} {row['bytes']:>9} {row['plain_ms_cpu_per_mib']:>9.2f} ms "
                  f"{row['tls_ms_cpu_per_mib']:>9.2f} ms {row['tls_ms_cpu_per_mib'] - row['plain_ms_cpu_per_mib']:>9.2f} ms")
    print(f"TLS handshake (both identities, loopback): {rows['handshake']['median_ms']:.1f} ms median")
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
