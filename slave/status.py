"""The slave's status on request: a small HTTP server on loopback that answers GET / with a JSON
object (what slave.activity.Activity.status() gives, with the slave's name and device), and
the client side of `kdtrace-slave --status`, which prints it as lines.

Loopback only: the status names masters and scenes, and it is not authenticated (ask it on the
slave's machine, or through an SSH tunnel). It answers only requests addressed to 127.0.0.1 or
localhost by their Host header (a web page that rebinds a name of its own to 127.0.0.1 cannot
read it), and it shows only the first digits of scene hashes.
"""
from __future__ import annotations

import json
import threading
import urllib.error
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

STATUS_HOST = "127.0.0.1"


class StatusServer:
    """Serves status() as JSON at http://127.0.0.1:<port>/ on a thread of its own."""

    def __init__(self, port: int, status):
        hosts = set()

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):
                if self.headers.get("Host", "").lower() not in hosts:
                    self.send_response(421)     # Misdirected Request: not our name
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                body = json.dumps(status(), indent=1).encode()
                self.send_response(200 if self.path in ("/", "/status") else 404)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args):  # requests are not worth a log line
                pass

        self._http = ThreadingHTTPServer((STATUS_HOST, port), Handler)
        self._http.daemon_threads = True
        self.port = self._http.server_address[1]
        hosts.update({f"{STATUS_HOST}:{self.port}", f"localhost:{self.port}"})
        self._thread = threading.Thread(target=self._http.serve_forever, name="status",
                                        daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://{STATUS_HOST}:{self.port}/"

    def close(self) -> None:
        self._http.shutdown()
        self._http.server_close()


def query_status(port: int, timeout: float = 5.0) -> dict:
    """The status of the slave whose status port is `port` on this machine; OSError if none
    answers."""
    try:
        with urllib.request.urlopen(f"http://{STATUS_HOST}:{port}/", timeout=timeout) as reply:
            return json.loads(reply.read())
    except urllib.error.URLError as exc:
        raise OSError(f"no slave answers on status port {port} ({exc.reason})") from None


def format_status(status: dict) -> str:
    totals = status["totals"]
    lines = [f"KD Trace slave {status['name']} (ID {status.get('id', '?')}) on "
             f"{status['listening']}, device {status['device']}, up "
             f"{status['uptime_seconds']:.0f} s",
             f"totals: {totals['frames']} frames, {totals['tiles']} tiles, "
             f"{totals['bytes_sent'] / 2 ** 20:.2f} MiB sent, kernel builds "
             f"{totals['build_seconds']:.2f} s"]
    for master in status["masters"]:
        lines.append(f"master {master['master']} connected {master['connected_seconds']:.0f} s ago")
    for frame in status["frames"]:
        lines.append(f"rendering frame {frame['frame_id']} for {frame['master']}: scene "
                     f"{frame['scene']}, {frame['tiles']} of {frame['tiles_in_frame']} "
                     f"tiles so far")
    if not status["frames"]:
        lines.append("not rendering")
    lines += ["last frames:"] + [f"  {line}" for line in status["recent_frames"]] \
        if status["recent_frames"] else []
    return "\n".join(lines)
