"""The viewer's web server: the standard library's threading HTTP server (one thread per
request; a page holds one for its event stream), no framework.

=================================  ===================================================
``GET /``                          the page (``static/index.html``; ``?map=NAME``)
``GET /static/<file>``             the page's script and three.js (``static/``)
``GET /api/maps``                  the bundles under the maps folders
``GET /api/maps/<name>``           one map: cameras, scene scale, up, centre (JSON)
``GET /api/maps/<name>/points``    its points: N x 3 float32 (little-endian), N x 3 uint8
``GET /api/status``                clients (rate, age), poses seen, undecodable messages
``GET /events``                    server-sent events: ``snapshot`` (every client with its
                                   trajectory) on connect, then ``pose`` per pose message,
                                   ``summary`` every second
=================================  ===================================================

Read-only: no request changes anything. It binds to loopback unless told otherwise.
"""

from __future__ import annotations

import json
import logging
import math
import mimetypes
import queue
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from ..errors import SfmlocError
from ..map.bundle import read_manifest
from .live import LiveState
from .mapdata import DEFAULT_MAX_POINTS, MapView, find_maps, load_map_view

log = logging.getLogger(__name__)

STATIC = Path(__file__).parent / "static"
SUMMARY_EVERY_S = 1.0


def _finite(obj: Any) -> Any:
    """JSON for a browser: NaN and infinities (which JSON.parse refuses) become null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def to_json(obj: Any) -> bytes:
    return json.dumps(_finite(obj), separators=(",", ":"), allow_nan=False).encode()


class ViewerServer:
    """``with ViewerServer(["maps"], state, port=0) as v: v.url`` serves until the block ends."""

    def __init__(
        self,
        map_roots: list[str | Path],
        state: LiveState,
        *,
        host: str = "127.0.0.1",
        port: int = 8090,
        max_points: int = DEFAULT_MAX_POINTS,
    ) -> None:
        self.host = host
        self.map_roots = [Path(r) for r in map_roots]
        find_maps(self.map_roots)  # a missing folder fails now, with its name
        self.state = state
        self.max_points = max_points
        self._maps: dict[str, MapView] = {}
        self._maps_lock = threading.Lock()
        self._static = {
            p.relative_to(STATIC).as_posix(): p for p in STATIC.rglob("*") if p.is_file()
        }
        self.stopping = threading.Event()
        self.httpd = ThreadingHTTPServer((host, port), _make_handler(self))
        self.httpd.daemon_threads = True
        self._thread = threading.Thread(
            target=self.httpd.serve_forever, name="sfmloc-view-http", daemon=True
        )

    @property
    def port(self) -> int:
        return int(self.httpd.server_address[1])

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/"

    def start(self) -> ViewerServer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self.stopping.set()  # event streams end within a second
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(5)

    def __enter__(self) -> ViewerServer:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    # ----- maps -------------------------------------------------------------------------
    def maps(self) -> dict[str, Path]:
        return find_maps(self.map_roots)

    def map_view(self, name: str) -> MapView | None:
        """The map called ``name`` (loaded once per build; a rebuilt bundle is reloaded)."""
        path = self.maps().get(name)
        if path is None:
            return None
        build_id = read_manifest(path).build_id
        with self._maps_lock:
            mv = self._maps.get(name)
            if mv is None or mv.build_id != build_id or mv.path != path:
                mv = self._maps[name] = load_map_view(path, self.max_points)
            return mv


def _make_handler(viewer: ViewerServer) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        server_version = "sfmloc-view"

        def log_message(self, fmt: str, *args: Any) -> None:
            log.debug("%s " + fmt, self.client_address[0], *args)

        def _send(self, status: int, body: bytes, ctype: str, cache: bool = False) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _json(self, obj: Any, status: int = 200) -> None:
            self._send(status, to_json(obj), "application/json")

        def _error(self, status: HTTPStatus, message: str) -> None:
            self._json({"error": message}, int(status))

        def do_HEAD(self) -> None:
            self.do_GET()

        def do_GET(self) -> None:
            path = unquote(urlsplit(self.path).path)
            try:
                self._route(path)
            except (BrokenPipeError, ConnectionResetError):
                pass  # the page went away
            except SfmlocError as exc:  # a corrupt or unreadable bundle: say which
                self._error(HTTPStatus.UNPROCESSABLE_ENTITY, str(exc))
            except Exception as exc:  # noqa: BLE001 - one bad request must not stop the viewer
                log.exception("viewer: %s failed", path)
                self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(exc).__name__}: {exc}")

        def _route(self, path: str) -> None:
            if path in ("/", "/index.html"):
                self._static_file("index.html")
            elif path.startswith("/static/"):
                self._static_file(path[len("/static/") :])
            elif path == "/api/maps":
                self._json({"maps": sorted(viewer.maps())})
            elif path.startswith("/api/maps/"):
                parts = path[len("/api/maps/") :].split("/")
                mv = viewer.map_view(parts[0])
                if mv is None:
                    self._error(HTTPStatus.NOT_FOUND, f"no map {parts[0]!r} under the maps folders")
                elif len(parts) == 1:
                    self._json(mv.meta())
                elif parts[1:] == ["points"]:
                    self._send(200, mv.points_bytes(), "application/octet-stream")
                else:
                    self._error(HTTPStatus.NOT_FOUND, f"no such resource {path}")
            elif path == "/api/status":
                self._json(viewer.state.summary())
            elif path == "/events":
                self._events()
            else:
                self._error(HTTPStatus.NOT_FOUND, f"no such resource {path}")

        def _static_file(self, rel: str) -> None:
            # Only the files shipped in static/ (a fixed table: no path is ever joined).
            f = viewer._static.get(rel)
            if f is None:
                self._error(HTTPStatus.NOT_FOUND, f"no such file {rel}")
                return
            ctype = mimetypes.guess_type(f.name)[0] or "application/octet-stream"
            if ctype in ("text/javascript", "application/javascript", "text/html", "text/css"):
                ctype += "; charset=utf-8"
            self._send(200, f.read_bytes(), ctype, cache=rel.startswith("vendor/"))

        def _events(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            q = viewer.state.subscribe()
            try:
                self._event("snapshot", viewer.state.snapshot())
                self._event("summary", viewer.state.summary())
                last_summary = time.monotonic()
                while not viewer.stopping.is_set():
                    try:
                        kind, data = q.get(timeout=0.25)
                    except queue.Empty:
                        kind, data = "", None
                    if kind == "resync":
                        self._event("snapshot", viewer.state.snapshot())
                    elif kind:
                        self._event(kind, data)
                    if time.monotonic() - last_summary >= SUMMARY_EVERY_S:
                        last_summary = time.monotonic()
                        self._event("summary", viewer.state.summary())
            finally:
                viewer.state.unsubscribe(q)

        def _event(self, kind: str, data: Any) -> None:
            self.wfile.write(b"event: " + kind.encode() + b"\ndata: " + to_json(data) + b"\n\n")
            self.wfile.flush()

    return Handler
