"""The KD Trace render slave: `kdtrace-slave` once installed (pyproject.toml), `python -m
kdtrace.slave` from a checkout or the extension's folder, `blender --background --command
kdtrace_slave` with the extension installed (addon/slave_command.py registers the command).

On start it prints one line to stdout, flushed, that a launcher can parse:
    KD Trace slave <name> listening on <host>:<port> id <ID> device <device name>
Then it logs to stderr (and --log-file), with timestamps: its short ID, whom it serves (and,
on a first start, how to pair a master), connections and one line per frame.
`--status` asks a running slave on this machine what it is doing (slave/status.py).
Bad arguments or an unusable device print one line and exit with status 2 (no traceback).
"""
from __future__ import annotations

import argparse
import ctypes
import ipaddress
import logging
import os
import re
import signal
import socket
import sys
import threading

EXIT_USAGE = 2
EXIT_NO_ANSWER = 1          # --status: no slave answered
LOG_FORMAT = "%(asctime)s kdtrace-slave %(levelname)s: %(message)s"
log = logging.getLogger("kdtrace.slave")


def default_prog() -> str:
    """How the user started us, for usage and error lines (Blender's kdtrace_slave command says
    so in KDTRACE_SLAVE_PROG)."""
    if os.environ.get("KDTRACE_SLAVE_PROG"):
        return os.environ["KDTRACE_SLAVE_PROG"]
    name = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    return "python -m kdtrace.slave" if name in ("", "-c", "__main__.py") else name


try:
    from ..core.net import protocol, trust
except ModuleNotFoundError as missing:  # a Python without the slave's packages
    sys.exit(f"{default_prog()}: error: the slave needs {missing.name}, which this Python lacks: "
             "install the slave with pip (README: \"A slave on every other machine\")")


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


def _master_id(text: str) -> str:
    from ..core.net.identity import check_id_pattern
    try:
        return check_id_pattern(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def default_identity_dir() -> str:
    """$KDTRACE_SLAVE_HOME, else kdtrace-slave in this user's configuration folder."""
    if os.environ.get("KDTRACE_SLAVE_HOME"):
        return os.environ["KDTRACE_SLAVE_HOME"]
    home = os.path.expanduser("~")
    if sys.platform == "win32":
        base = os.environ.get("APPDATA") or os.path.join(home, "AppData", "Roaming")
    elif sys.platform == "darwin":
        base = os.path.join(home, "Library", "Application Support")
    else:
        base = os.environ.get("XDG_CONFIG_HOME") or os.path.join(home, ".config")
    return os.path.join(base, "kdtrace-slave")


def _status_port(text: str):
    return text if text in ("auto", "off") else _port(text)


def parse_args(argv, prog: str = "python -m kdtrace.slave"):
    parser = _Parser(prog=prog, description="KD Trace render slave")
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
    parser.add_argument("--upload-mib", type=int, default=None,
                        help="what all masters' uploads in progress may hold at once, MiB "
                             "(default: --max-scene-mib); one more waits, then is refused")
    parser.add_argument("--secret-file", default=None,
                        help="file holding the farm secret: masters that prove it are served "
                             f"(default: the {trust.SECRET_ENV} environment variable)")
    parser.add_argument("--new-secret", metavar="FILE", default=None,
                        help="write a new farm secret to FILE (readable by you only) and exit; "
                             "give the same file to every slave and to the add-on")
    parser.add_argument("--allow", type=_master_id, action="append", default=[],
                        metavar="MASTER_ID",
                        help="serve the master with this ID (the Slaves panel shows it as "
                             "'This computer'), from now on (kept in the identity folder); "
                             "repeatable")
    parser.add_argument("--pair", action="store_true",
                        help="show a one-time pairing code for one more master (one is shown "
                             "anyway while no master is allowed and there is no farm secret)")
    parser.add_argument("--identity-dir", default=None,
                        help="folder of this slave's identity (key, certificate, allowed "
                             "masters; default: $KDTRACE_SLAVE_HOME, else kdtrace-slave in "
                             "your configuration folder)")
    parser.add_argument("--show-id", action="store_true", help="print this slave's ID and exit")
    parser.add_argument("--cache-dir", default=None,
                        help="also keep uploaded scenes on disk in this folder")
    parser.add_argument("--cache-disk-mib", type=int, default=2048,
                        help="size limit of the disk scene cache, MiB (default 2048)")
    parser.add_argument("--cache-scenes", type=int, default=2,
                        help="scenes kept in memory (default 2)")
    parser.add_argument("--list-devices", action="store_true", help="list OpenCL devices and exit")
    parser.add_argument("--log-file", default=None,
                        help="also append the log to this file")
    parser.add_argument("--status-port", type=_status_port, default="auto",
                        help="loopback port of the status query (default 'auto': the slave's "
                             "port + 1, or any free port if that is taken; 'off': none)")
    parser.add_argument("--status", action="store_true",
                        help="ask the slave running on this machine with this --port (or "
                             "--status-port) what it is doing, print it and exit")
    parser.add_argument("--verbose", action="store_true", help="also log every tile")
    args = parser.parse_args(argv)
    if args.max_scene_mib < 1:
        raise UsageError("--max-scene-mib must be at least 1")
    if args.upload_mib is not None and args.upload_mib < 1:
        raise UsageError("--upload-mib must be at least 1")
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


def setup_logging(verbose: bool, log_file: str | None) -> None:
    handlers = [logging.StreamHandler(sys.stderr)]
    if log_file:
        try:
            handlers.append(logging.FileHandler(log_file, encoding="utf-8"))
        except OSError as exc:
            raise UsageError(f"cannot write the log file {log_file}: {exc.strerror or exc}") from None
    formatter = logging.Formatter(LOG_FORMAT, datefmt="%Y-%m-%d %H:%M:%S")
    for handler in handlers:
        handler.setFormatter(formatter)
    root = logging.getLogger()   # other packages' warnings (zeroconf's) get the same format
    root.handlers[:] = handlers
    root.setLevel(logging.WARNING)
    log.setLevel(logging.DEBUG if verbose else logging.INFO)


def print_status(args) -> int:
    from .status import format_status, query_status
    if args.status_port == "off" or (args.status_port == "auto" and not 0 < args.port < 65535):
        raise UsageError("--status needs the slave's --port, or its --status-port")
    port = args.port + 1 if args.status_port == "auto" else args.status_port
    try:
        print(format_status(query_status(port)), flush=True)
    except OSError as exc:
        print(f"{args.prog}: {exc}", file=sys.stderr, flush=True)
        return EXIT_NO_ANSWER
    return 0


def _start_status(server, choice, name: str, shown_address: str):
    """The status server at `choice` (a port, or "auto": the slave's port + 1, any free port
    if that is taken); None when it cannot listen: the slave works without it."""
    from .status import StatusServer

    def status() -> dict:
        return {"name": name, "id": server.identity.short_id, "listening": shown_address,
                "device": server.device_info["name"], **server.activity.status()}

    listening = server.address[1]
    ports = [choice] if choice != "auto" else [listening + 1 if listening < 65535 else 0, 0]
    for port in ports:
        try:
            return StatusServer(port, status)
        except OSError as exc:
            reason = exc.strerror or exc
    log.warning("no status query: cannot listen on 127.0.0.1:%d (%s)", ports[0], reason)
    return None


def _stop_on_signals(stop: threading.Event) -> None:
    for name in ("SIGTERM", "SIGINT"):
        try:
            signal.signal(getattr(signal, name), lambda *_: stop.set())
        except ValueError:  # not the main thread: the caller stops us another way
            pass


def load_trust(args):
    """(identity, allowed masters, farm secret or None) of this slave, from its options."""
    from ..core.net.identity import Identity, IdentityError
    folder = args.identity_dir or default_identity_dir()
    try:
        identity = Identity.load_or_create(folder, "slave")
        allowed = trust.AllowList(path=os.path.join(folder, trust.ALLOWED_MASTERS_FILE))
        for master_id in args.allow:
            if allowed.add(master_id, "--allow"):
                log.info("master %s allowed from now on (kept in %s)", master_id,
                         allowed.path)
        secret = trust.load_secret(args.secret_file)
    except (IdentityError, trust.AuthError, OSError) as exc:
        raise UsageError(str(exc)) from None
    return identity, allowed, secret


def pairing_instructions(name: str, identity, code: str, prog: str) -> list:
    """What the owner reads on a start that serves no master yet (or with --pair)."""
    return [f"To let a master use this slave, once: in Blender, Render Properties > KD Trace > "
            f"Slaves, click Pair beside {name} (ID {identity.short_id}) and enter the pairing "
            f"code {code}.",
            f"Or allow the master by its ID (the Slaves panel shows 'This computer: ID ...'): "
            f"{prog} --allow MASTER-ID; or give this slave and the add-on the same farm secret "
            f"({prog} --new-secret FILE, then --secret-file FILE here and the file in the "
            f"add-on's preferences)."]


def run(args) -> int:
    if args.list_devices:
        return list_devices()
    if args.status:
        return print_status(args)
    if args.new_secret:
        try:
            trust.write_new_secret(args.new_secret)
        except (trust.AuthError, OSError) as exc:
            raise UsageError(str(exc)) from None
        print(f"farm secret written to {args.new_secret} (readable by you only): give the "
              f"same file to every slave (--secret-file) and to the add-on (its preferences)",
              flush=True)
        return 0
    identity, allowed, secret = load_trust(args)
    if args.show_id:
        print(identity.id, flush=True)
        return 0
    from .server import SlaveServer
    from .tracer import Tracer
    try:
        tracer = Tracer(device=args.device)
    except Exception as exc:
        raise UsageError(f"cannot use OpenCL device {args.device!r}: {exc}") from None
    name = args.name or _default_name()
    limits = protocol.Limits(max_scene_bytes=args.max_scene_mib * 2 ** 20)
    try:
        pairing = trust.PairingCode() if args.pair or (secret is None and not len(allowed)) \
            else None
        server = SlaveServer(tracer, name, args.bind, args.port, limits,
                             cache_size=args.cache_scenes, secret=secret,
                             cache_dir=args.cache_dir,
                             cache_disk_bytes=args.cache_disk_mib * 2 ** 20, identity=identity,
                             allowed=allowed, pairing=pairing,
                             upload_bytes=None if args.upload_mib is None
                             else args.upload_mib * 2 ** 20)
    except OSError as exc:
        raise UsageError(f"cannot listen on {args.bind}:{args.port}: {exc.strerror or exc}") from None

    stop = threading.Event()
    _stop_on_signals(stop)
    advertisement = status_server = None
    try:
        server.start()
        host, port = server.address
        addresses, interfaces = _advertise_addresses(args.bind, args.advertise_ip)
        if not args.no_zeroconf:
            from ..core.net.discovery import advertise
            info = server.device_info
            try:
                advertisement = advertise(name, port, {
                    "protocol": protocol.PROTOCOL_VERSION, "name": name, "id": server.slave_id,
                    "device": info["name"], "compute_units": info["compute_units"],
                    "memory": info["memory"], "farm": "1" if secret else "0",
                    "pairing": "1" if pairing is not None else "0"},
                    addresses, interfaces, instance=server.instance)
            except Exception as exc:  # no multicast here: masters can still connect by address
                log.warning("zeroconf advertising failed: %s", exc)
        shown_host = addresses[0] if host == "0.0.0.0" else host
        print(f"KD Trace slave {name} listening on {shown_host}:{port} id {identity.id} "
              f"device {server.device_info['name']}", flush=True)
        if args.status_port != "off":
            status_server = _start_status(server, args.status_port, name, f"{shown_host}:{port}")
        log.info("slave %s ready on %s:%d (%s), device %s%s", name, shown_host, port,
                 "advertised on the LAN" if advertisement else "not advertised",
                 server.device_info["name"],
                 f"; status: {args.prog} --status --status-port {status_server.port}"
                 if status_server else "")
        serves = [f"{len(allowed)} allowed master(s) ({allowed.path})"] if len(allowed) else []
        serves += ["masters that prove the farm secret"] if secret is not None else []
        serves += [f"one master that pairs with the code {pairing.code}"] if pairing else []
        log.info("slave ID %s (full: %s); serves %s; all traffic TLS 1.3", identity.short_id,
                 identity.id, ", ".join(serves))
        if pairing is not None:
            for line in pairing_instructions(name, identity, pairing.code, args.prog):
                log.info("%s", line)
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        if status_server is not None:
            status_server.close()
        if advertisement is not None:
            advertisement.close()
        server.close()
        log.info("slave %s stopped", name)
    return 0


# glibc's mallopt parameter for the number of malloc arenas.
M_ARENA_MAX = -8
MALLOC_ARENAS = 2


def limit_malloc_arenas() -> None:
    """Two malloc arenas for the whole process, as MALLOC_ARENA_MAX=2 would (unless that is
    set). glibc gives new threads arenas of their own, up to 8 per core, and each keeps what is
    freed in it: a slave that serves connection after connection, each with its threads, grew
    by 9 MiB in 12 minutes of fuzzed connections with the default and by 2-3 MiB with two
    arenas (docs/distributed.md, "Soak"). Only on Linux (glibc); elsewhere nothing changes."""
    if not sys.platform.startswith("linux") or "MALLOC_ARENA_MAX" in os.environ:
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return          # not glibc (musl)
    mallopt(M_ARENA_MAX, MALLOC_ARENAS)


def main(argv=None) -> int:
    limit_malloc_arenas()       # before any thread starts
    prog = default_prog()
    try:
        args = parse_args(sys.argv[1:] if argv is None else argv, prog)
        args.prog = prog
        setup_logging(args.verbose, args.log_file)
        return run(args)
    except UsageError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr, flush=True)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
