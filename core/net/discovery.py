"""Finding slaves on the LAN with zeroconf (mDNS/DNS-SD, service type _kdtrace._tcp.local.).

The only module of core that imports zeroconf. Zeroconf's handlers run on its own thread: they
only put events on queues; resolving and everything else happens elsewhere. mDNS is often
blocked (Windows, WSL, Docker, some switches), so callers always offer a manual host:port list.

For tests on one machine pass interfaces=["127.0.0.1"] to both sides: zeroconf's default
interface choice leaves loopback out.
"""
from __future__ import annotations

import queue
import re
import socket
import threading
import time
from dataclasses import dataclass, field

from zeroconf import IPVersion, ServiceBrowser, ServiceInfo, ServiceStateChange, Zeroconf

from .protocol import SERVICE_TYPE
from .trust import sanitize

# Slaves a browser keeps at once: anyone on a LAN can advertise, and each slave found may cost
# the master a connection (a thread while it connects). Further ones are counted, not kept.
MAX_DISCOVERED = 64


@dataclass
class SlaveInfo:
    name: str            # service instance name without the service type
    host: str            # an IPv4 address to connect to
    port: int
    properties: dict = field(default_factory=dict)  # TXT records, decoded as text

    @property
    def endpoint(self) -> tuple:
        return (self.host, self.port)


@dataclass
class SlaveEvent:
    kind: str            # "added", "updated" or "removed"
    name: str
    info: SlaveInfo | None = None  # None for "removed"


def all_ipv4_addresses() -> list:
    """Every IPv4 address of this machine, loopback included, so that a master also finds the
    slaves that run on its own machine bound to loopback."""
    import ifaddr  # a dependency of zeroconf
    return sorted({ip.ip for adapter in ifaddr.get_adapters() for ip in adapter.ips if ip.is_IPv4})


def _zeroconf(interfaces) -> Zeroconf:
    if interfaces:
        return Zeroconf(interfaces=list(interfaces), ip_version=IPVersion.V4Only)
    return Zeroconf(ip_version=IPVersion.V4Only)


def _short_name(full_name: str) -> str:
    suffix = "." + SERVICE_TYPE
    return full_name[:-len(suffix)] if full_name.endswith(suffix) else full_name


def _slave_info(info: ServiceInfo) -> SlaveInfo | None:
    addresses = info.parsed_addresses(IPVersion.V4Only)
    if not addresses or not info.port:
        return None
    properties = {}
    for key, value in list((info.properties or {}).items())[:32]:
        properties[sanitize(key.decode("utf-8", "replace"), 32)] = (
            sanitize(value.decode("utf-8", "replace"), 128) if value is not None else "")
    return SlaveInfo(sanitize(_short_name(info.name)), addresses[0], info.port, properties)


def _server_name(name: str, port: int, instance=None) -> str:
    """The host name the address records are published under. It must differ between slaves:
    containers and network namespaces share one host name, and one server name announced with
    two addresses makes every browser resolve both slaves to the same address. (Not the
    slave's ID: slaves of one user may share their identity.)"""
    host = re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname().split(".")[0])[:20] or "host"
    label = re.sub(r"[^A-Za-z0-9-]", "-", str(instance or name))[:24]
    return f"{host}-{label}-{port}.local."


class Advertisement:
    """A slave's registered service; close() unregisters it (call it in `finally`)."""

    def __init__(self, name: str, port: int, properties: dict, addresses, interfaces=None,
                 instance=None):
        self._zeroconf = _zeroconf(interfaces)
        self.info = ServiceInfo(
            SERVICE_TYPE, f"{name}.{SERVICE_TYPE}", port=port,
            addresses=[socket.inet_aton(a) for a in addresses],
            properties={str(k): str(v) for k, v in properties.items()},
            server=_server_name(name, port, instance))
        try:
            # Two slaves with one name (two on a host) get "name (2)" rather than an error.
            self._zeroconf.register_service(self.info, allow_name_change=True)
        except BaseException:
            self._zeroconf.close()
            raise

    @property
    def name(self) -> str:
        return _short_name(self.info.name)

    def close(self) -> None:
        try:
            self._zeroconf.unregister_service(self.info)
        finally:
            self._zeroconf.close()


def advertise(name: str, port: int, properties: dict, addresses, interfaces=None,
              instance=None) -> Advertisement:
    """Register a slave under `name` at `addresses` (IPv4 strings) and `port`; `instance`
    tells apart slaves that share a name and a host name (containers, namespaces)."""
    return Advertisement(name, port, properties, addresses, interfaces, instance)


class SlaveBrowser:
    """Long-lived browser: `events` (a queue.Queue of SlaveEvent) and `slaves()` (a snapshot).

    Zeroconf calls the handler on its own thread, which must not block: the handler only queues
    names; a resolver thread of ours looks up address, port and TXT records.
    """

    def __init__(self, interfaces=None, resolve_timeout: float = 3.0):
        self.events: queue.Queue = queue.Queue()
        self._names: queue.Queue = queue.Queue(maxsize=4 * MAX_DISCOVERED)
        self._slaves: dict = {}
        self.ignored = 0        # slaves found beyond MAX_DISCOVERED
        self._lock = threading.Lock()
        self._resolve_timeout = resolve_timeout
        self._closed = threading.Event()
        self._zeroconf = _zeroconf(interfaces)
        self._resolver = threading.Thread(target=self._resolve_loop, name="kdtrace-resolver",
                                          daemon=True)
        self._resolver.start()
        self._browser = ServiceBrowser(self._zeroconf, SERVICE_TYPE, handlers=[self._on_change])

    def _on_change(self, zeroconf, service_type, name, state_change) -> None:
        try:
            self._names.put_nowait((name, state_change))
        except queue.Full:      # a flood of names: the handler must not block zeroconf
            self.ignored += 1

    def _resolve_loop(self) -> None:
        while not self._closed.is_set():
            try:
                name, change = self._names.get(timeout=0.2)
            except queue.Empty:
                continue
            short = _short_name(name)
            if change is ServiceStateChange.Removed:
                with self._lock:
                    known = self._slaves.pop(short, None)
                if known:
                    self.events.put(SlaveEvent("removed", short))
                continue
            try:
                info = self._zeroconf.get_service_info(SERVICE_TYPE, name,
                                                       int(self._resolve_timeout * 1000))
            except Exception:  # zeroconf closing or a malformed record: skip this name
                info = None
            slave = _slave_info(info) if info else None
            if slave is None:
                continue
            with self._lock:
                kind = "updated" if short in self._slaves else "added"
                if kind == "added" and len(self._slaves) >= MAX_DISCOVERED:
                    self.ignored += 1
                    continue
                self._slaves[short] = slave
            self.events.put(SlaveEvent(kind, short, slave))

    def slaves(self) -> list:
        with self._lock:
            return sorted(self._slaves.values(), key=lambda s: s.name)

    def close(self) -> None:
        self._closed.set()
        try:
            self._browser.cancel()
        finally:
            self._zeroconf.close()
        self._resolver.join(timeout=5)


def browse_slaves(timeout: float = 2.0, interfaces=None) -> list:
    """Browse for `timeout` seconds and return the slaves found (a one-shot SlaveBrowser)."""
    browser = SlaveBrowser(interfaces)
    try:
        time.sleep(timeout)
        return browser.slaves()
    finally:
        browser.close()
