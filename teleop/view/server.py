"""The operator view as a web page (stdlib ``http.server``; the browser is the display).

    GET /             the page: the latest view image refreshed periodically, status from /status.json
    GET /frame.jpg    the latest rendered view (JPEG)
    GET /stream.mjpg  the same as an MJPEG stream (multipart/x-mixed-replace), for video players
    GET /status.json  link state, mode, battery, min obstacle distance, warnings, command acks, the measured
                      round trip to the companion (rtt_ms, rtt_p50_ms, rtt_p99_ms) and the force port's energy

One thread serves (ThreadingHTTPServer, daemon request threads); the view thread publishes into a
:class:`ViewHub` (lock + condition, every wait with a timeout).
"""

from __future__ import annotations

import json
import logging
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from quadlink.errors import LinkError

log = logging.getLogger(__name__)

PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>quadlink operator view</title>
<style>
 body { background:#111; color:#ddd; font-family: sans-serif; margin: 8px; }
 #view { border: 1px solid #444; display:block; }
 #status { font-family: monospace; font-size: 14px; margin-top: 6px; }
 .warn { color: #ff5050; font-weight: bold; }
 .ok { color: #50ff50; } .bad { color: #ff5050; }
 table td { padding: 1px 10px 1px 0; }
</style></head>
<body>
<img id="view" src="/frame.jpg" alt="operator view">
<div id="status">
<table>
<tr><td>link</td><td id="link">-</td><td>mode</td><td id="mode">-</td><td>armed</td><td id="armed">-</td></tr>
<tr><td>battery</td><td id="battery">-</td><td>min obstacle</td><td id="obstacle">-</td>
    <td>pan-scan</td><td id="panscan">-</td></tr>
<tr><td>round trip</td><td id="rtt" colspan="3">-</td><td>energy out</td><td id="energy">-</td></tr>
<tr><td>command</td><td id="command" colspan="5">-</td></tr>
</table>
<div id="warnings" class="warn"></div>
<div id="acks"></div>
</div>
<script>
const img = document.getElementById('view');
function refreshImage() {
  const next = new Image();
  next.onload = () => { img.src = next.src; setTimeout(refreshImage, __PERIOD_MS__); };
  next.onerror = () => setTimeout(refreshImage, 500);
  next.src = '/frame.jpg?t=' + Date.now();
}
function set(id, text, cls) { const e = document.getElementById(id); e.textContent = text; if (cls) e.className = cls; }
async function refreshStatus() {
  try {
    const s = await (await fetch('/status.json')).json();
    set('link', s.link, s.link_ok ? 'ok' : 'bad');
    set('mode', s.mode); set('armed', s.armed ? 'yes' : 'no');
    set('battery', s.battery_v == null ? '-' : s.battery_v.toFixed(2) + ' V');
    set('obstacle', s.min_obstacle_m == null ? 'none' : s.min_obstacle_m.toFixed(2) + ' m');
    set('panscan', s.pan_scan_on ? 'on (' + s.pan_scan_hz.toFixed(2) + ' Hz)' : 'off');
    set('command', s.command);
    set('rtt', s.rtt_ms == null ? '-' : s.rtt_ms.toFixed(0) + ' ms (p50 ' + s.rtt_p50_ms.toFixed(0) + ', p99 ' +
        s.rtt_p99_ms.toFixed(0) + ')');
    set('energy', s.passivity == null ? '-' : (1e3 * s.passivity.output_j).toFixed(1) + ' mJ');
    document.getElementById('warnings').textContent = s.warnings.join(' | ');
    document.getElementById('acks').textContent = s.acks.join(' | ');
  } catch (e) { set('link', 'ground station not responding', 'bad'); }
  setTimeout(refreshStatus, 250);
}
setTimeout(refreshImage, __PERIOD_MS__); refreshStatus();
</script>
</body></html>
"""


class ViewHub:
    """Latest JPEG and status, shared between the view thread and the HTTP threads."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._jpeg = b""
        self._seq = 0
        self._status: dict[str, Any] = {}
        self.closed = False

    def publish(self, jpeg: bytes) -> None:
        with self._cond:
            self._jpeg, self._seq = jpeg, self._seq + 1
            self._cond.notify_all()

    def set_status(self, status: dict[str, Any]) -> None:
        with self._cond:
            self._status = status

    def latest(self) -> tuple[int, bytes]:
        with self._cond:
            return self._seq, self._jpeg

    def status(self) -> dict[str, Any]:
        with self._cond:
            return dict(self._status)

    def wait_newer(self, seq: int, timeout_s: float) -> tuple[int, bytes]:
        with self._cond:
            self._cond.wait_for(lambda: self._seq != seq or self.closed, timeout=timeout_s)
            return self._seq, self._jpeg

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()


def _handler(hub: ViewHub, period_ms: int) -> type[BaseHTTPRequestHandler]:
    page = PAGE.replace("__PERIOD_MS__", str(period_ms)).encode()

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, fmt: str, *args: Any) -> None:
            log.debug("http %s: " + fmt, self.client_address[0], *args)

        def _send(self, body: bytes, ctype: str) -> None:
            self.send_response(200)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:  # noqa: N802 - http.server API
            path = self.path.split("?", 1)[0]
            try:
                if path in ("/", "/index.html"):
                    self._send(page, "text/html; charset=utf-8")
                elif path == "/frame.jpg":
                    _, jpeg = hub.latest()
                    if not jpeg:
                        self.send_error(503, "no view rendered yet")
                        return
                    self._send(jpeg, "image/jpeg")
                elif path == "/status.json":
                    self._send(json.dumps(hub.status()).encode(), "application/json")
                elif path == "/stream.mjpg":
                    self._stream()
                else:
                    self.send_error(404)
            except (BrokenPipeError, ConnectionResetError):
                pass

        def _stream(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            seq = -1
            while not hub.closed:
                new_seq, jpeg = hub.wait_newer(seq, timeout_s=1.0)
                if new_seq == seq or not jpeg:
                    continue
                seq = new_seq
                self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                                 + str(len(jpeg)).encode() + b"\r\n\r\n" + jpeg + b"\r\n")

    return Handler


class ViewServer:
    """HTTP server in one thread; ``port=0`` picks a free port (see ``.port``)."""

    def __init__(self, hub: ViewHub, host: str = "127.0.0.1", port: int = 8080, refresh_period_ms: int = 66) -> None:
        self.hub = hub
        try:
            self._server = ThreadingHTTPServer((host, port), _handler(hub, refresh_period_ms))
        except OSError as exc:
            raise LinkError(f"operator view: cannot listen on http://{host}:{port}: {exc}") from exc
        self._server.daemon_threads = True
        host_addr, port_num = self._server.server_address[:2]
        self.host = host_addr.decode() if isinstance(host_addr, bytes) else str(host_addr)
        self.port = int(port_num)
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="view-http", daemon=True)
        self._thread.start()
        log.info("operator view on http://%s:%d", self.host, self.port)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def close(self) -> None:
        self.hub.close()
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=2.0)
