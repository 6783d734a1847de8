"""`python -m slave`: the KD Trace render slave (run from the extension's root folder).

On start it prints one line, flushed, that a launcher can parse:
    KD Trace slave <name> listening on <host>:<port> device <device name>
Bad arguments or an unusable device print one line and exit with status 2 (no traceback).
"""
from __future__ import annotations

import argparse
import ipaddress
import logging
import re
import signal
import socket
import sys
import threading

from core.net import protocol

PROG = "python -m slave"
EXIT_USAGE = 2


class UsageError(Exception):
    """Something the user can fix; printed as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse prints usage + message over two lines: keep it to one
        raise UsageError(message)


def _port(text: str) -> int:
    if not text.isdigit() or int(text) > 65535:
        raise argparse.ArgumentTypeError(f"port must be 0-65535, got {text!r}")
    return int(text)


def _ipv4(text: str) -> str:
    try:
        return str(ipaddress.IPv4Address(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an IPv4 address: {text!r}") from None


def _device(text: str) -> str:
    if text in ("auto", "cpu", "gpu") or re.fullmatch(r"\d+:\d+", text):
        return text
    raise argparse.ArgumentTypeError(f"device must be auto, cpu, gpu or P:D, got {text!r}")


def _name(text: str) -> str:
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9 _-]{0,62}", text):
        raise argparse.ArgumentTypeError(
            f"name must be 1-63 letters, digits, spaces, '-' or '_', got {text!r}")
    return text


def parse_args(argv):
    parser = _Parser(prog=PROG, description="KD Trace render slave")
    parser.add_argument("--port", type=_port, default=protocol.DEFAULT_PORT,
                        help=f"TCP port (default {protocol.DEFAULT_PORT}; 0 = any free port)")
    parser.add_argument("--bind", type=_ipv4, default="0.0.0.0",
                        help="address to listen on (default 0.0.0.0: all)")
    parser.add_argument("--advertise-ip", type=_ipv4, action="append", default=[],
                        help="address to advertise over zeroconf, and interface to advertise "
                             "on (repeatable; default: the bind address, or all interfaces)")
    parser.add_argument("--device", type=_device, default="auto",
                        help="OpenCL device: auto, cpu, gpu or P:D platform:device indices")
    parser.add_argument("--name", type=_name, default=None,
                        help="slave name shown to masters (default: host name)")
    parser.add_argument("--no-zeroconf", action="store_true", help="do not advertise on the LAN")
    parser.add_argument("--max-scene-mib", type=int, default=4096,
                        help="largest scene upload accepted, MiB (default 4096)")
    parser.add_argument("--secret-file", default=None,
                        help="file holding the secret shared with masters (default: the "
                             f"{protocol.SECRET_ENV} environment variable; neither: no "
                             "authentication)")
    parser.add_argument("--cache-dir", default=None,
                        help="also keep uploaded scenes on disk in this folder")
    parser.add_argument("--cache-disk-mib", type=int, default=2048,
                        help="size limit of the disk scene cache, MiB (default 2048)")
    parser.add_argument("--cache-scenes", type=int, default=2,
                        help="scenes kept in memory (default 2)")
    parser.add_argument("--list-devices", action="store_true", help="list OpenCL devices and exit")
    parser.add_argument("--verbose", action="store_true", help="log every connection event")
    args = parser.parse_args(argv)
    if args.max_scene_mib < 1:
        raise UsageError("--max-scene-mib must be at least 1")
    if args.cache_disk_mib < 1 or args.cache_scenes < 1:
        raise UsageError("--cache-disk-mib and --cache-scenes must be at least 1")
    return args


def list_devices() -> int:
    try:
        import pyopencl as cl
        platforms = cl.get_platforms()
    except Exception as exc:
        raise UsageError(f"no OpenCL available: {exc}") from None
    for p, platform in enumerate(platforms):
        for d, device in enumerate(platform.get_devices()):
            print(f"{p}:{d}  {device.name.strip()}  ({cl.device_type.to_string(device.type)}, "
                  f"{device.max_compute_units} compute units, "
                  f"{device.global_mem_size // 2 ** 20} MiB, {platform.name.strip()})")
    return 0


def _default_name() -> str:
    name = re.sub(r"[^A-Za-z0-9_-]", "-", socket.gethostname().split(".")[0])[:63]
    return name if name and name[0].isalnum() else "kdtrace-slave"


def _advertise_addresses(bind: str, chosen: list) -> tuple:
    """(addresses to publish, interfaces for zeroconf or None for all)."""
    if chosen:
        return chosen, chosen
    if bind != "0.0.0.0":
        return [bind], [bind]
    import ifaddr  # a dependency of zeroconf
    found = [ip.ip for adapter in ifaddr.get_adapters() for ip in adapter.ips
             if ip.is_IPv4 and not ip.ip.startswith("127.")]
    return (found or ["127.0.0.1"]), None


def run(args) -> int:
    if args.list_devices:
        return list_devices()
    from .server import SlaveServer
    from .tracer import Tracer

    try:
        secret = protocol.load_secret(args.secret_file)
    except protocol.AuthError as exc:
        raise UsageError(str(exc)) from None
    try:
        tracer = Tracer(device=args.device)
    except Exception as exc:
        raise UsageError(f"cannot use OpenCL device {args.device!r}: {exc}") from None
    name = args.name or _default_name()
    limits = protocol.Limits(max_scene_bytes=args.max_scene_mib * 2 ** 20)
    try:
        server = SlaveServer(tracer, name, args.bind, args.port, limits,
                             cache_size=args.cache_scenes, secret=secret,
                             cache_dir=args.cache_dir,
                             cache_disk_bytes=args.cache_disk_mib * 2 ** 20)
    except OSError as exc:
        raise UsageError(f"cannot listen on {args.bind}:{args.port}: {exc.strerror or exc}") from None

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    advertisement = None
    try:
        server.start()
        host, port = server.address
        addresses, interfaces = _advertise_addresses(args.bind, args.advertise_ip)
        if not args.no_zeroconf:
            from core.net.discovery import advertise
            info = server.device_info
            try:
                advertisement = advertise(name, port, {
                    "protocol": protocol.PROTOCOL_VERSION, "name": name, "id": server.slave_id,
                    "device": info["name"], "compute_units": info["compute_units"],
                    "memory": info["memory"], "auth": "hmac" if secret else "none"},
                    addresses, interfaces)
            except Exception as exc:  # no multicast here: masters can still connect by address
                logging.getLogger("kdtrace.slave").warning("zeroconf advertising failed: %s", exc)
        shown_host = addresses[0] if host == "0.0.0.0" else host
        print(f"KD Trace slave {name} listening on {shown_host}:{port} device {server.device_info['name']}",
              flush=True)
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        if advertisement is not None:
            advertisement.close()
        server.close()
    return 0


def main(argv=None) -> int:
    try:
        args = parse_args(sys.argv[1:] if argv is None else argv)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="kdtrace-slave: %(levelname)s: %(message)s")
        return run(args)
    except UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr, flush=True)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
