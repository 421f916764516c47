"""Prometheus metrics in the text exposition format (0.0.4), written by hand (no dependency),
and a tiny HTTP endpoint: ``GET /metrics`` (and ``GET /healthz``: 200 once ready, else 503)."""

from __future__ import annotations

import bisect
import logging
import threading
from collections.abc import Callable, Sequence
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import TypeVar

log = logging.getLogger(__name__)

LATENCY_BUCKETS_S = (0.002, 0.005, 0.01, 0.015, 0.02, 0.03, 0.05, 0.075, 0.1, 0.2, 0.5, 1.0, 2.5)


def _escape(v: str) -> str:
    return v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _labels(names: Sequence[str], values: Sequence[str], extra: str = "") -> str:
    parts = [f'{n}="{_escape(str(v))}"' for n, v in zip(names, values)]
    if extra:
        parts.append(extra)
    return "{" + ",".join(parts) + "}" if parts else ""


def _num(v: float) -> str:
    v = float(v)
    if v == float("inf"):
        return "+Inf"
    return str(int(v)) if v.is_integer() else repr(v)


class _Metric:
    kind = ""

    def __init__(self, name: str, help: str, labels: Sequence[str] = ()) -> None:
        self.name, self.help, self.labelnames = name, help, tuple(labels)
        self._lock = threading.Lock()

    def header(self) -> list[str]:
        return [f"# HELP {self.name} {self.help}", f"# TYPE {self.name} {self.kind}"]

    def render(self) -> list[str]:
        raise NotImplementedError


M = TypeVar("M", bound=_Metric)  # Registry.add returns the metric's own type (Counter, ...)


class Counter(_Metric):
    kind = "counter"

    def __init__(self, name: str, help: str, labels: Sequence[str] = ()) -> None:
        super().__init__(name, help, labels)
        self._values: dict[tuple[str, ...], float] = {}

    def inc(self, *labels: str, value: float = 1.0) -> None:
        with self._lock:
            self._values[labels] = self._values.get(labels, 0.0) + value

    def get(self, *labels: str) -> float:
        return self._values.get(labels, 0.0)

    def render(self) -> list[str]:
        with self._lock:
            items = sorted(self._values.items())
        return self.header() + [
            f"{self.name}{_labels(self.labelnames, k)} {_num(v)}" for k, v in items
        ]


class Gauge(_Metric):
    """A gauge whose values come from a callback at scrape time (or ``set``)."""

    kind = "gauge"

    def __init__(
        self,
        name: str,
        help: str,
        labels: Sequence[str] = (),
        collect: Callable[[], dict[tuple[str, ...], float]] | None = None,
    ) -> None:
        super().__init__(name, help, labels)
        self._values: dict[tuple[str, ...], float] = {}
        self._collect = collect

    def set(self, *labels: str, value: float) -> None:
        with self._lock:
            self._values[labels] = value

    def render(self) -> list[str]:
        if self._collect is not None:
            try:
                values = self._collect()
            except Exception:  # noqa: BLE001 - a broken collector must not break the scrape
                log.exception("metrics collector %s failed", self.name)
                values = {}
        else:
            with self._lock:
                values = dict(self._values)
        return self.header() + [
            f"{self.name}{_labels(self.labelnames, k)} {_num(v)}" for k, v in sorted(values.items())
        ]


class Histogram(_Metric):
    kind = "histogram"

    def __init__(
        self,
        name: str,
        help: str,
        labels: Sequence[str] = (),
        buckets: Sequence[float] = LATENCY_BUCKETS_S,
    ) -> None:
        super().__init__(name, help, labels)
        self.buckets = tuple(sorted(buckets))
        self._counts: dict[tuple[str, ...], list[int]] = {}
        self._sums: dict[tuple[str, ...], float] = {}

    def observe(self, *labels: str, value: float) -> None:
        i = bisect.bisect_left(self.buckets, value)
        with self._lock:
            c = self._counts.setdefault(labels, [0] * (len(self.buckets) + 1))
            c[i] += 1
            self._sums[labels] = self._sums.get(labels, 0.0) + value

    def count(self, *labels: str) -> int:
        return sum(self._counts.get(labels, []))

    def render(self) -> list[str]:
        out = self.header()
        with self._lock:
            items = sorted((k, list(v), self._sums[k]) for k, v in self._counts.items())
        for k, counts, total in items:
            acc = 0
            for b, n in zip((*self.buckets, float("inf")), counts):
                acc += n
                le = 'le="' + _num(b) + '"'
                out.append(f"{self.name}_bucket{_labels(self.labelnames, k, le)} {acc}")
            out.append(f"{self.name}_sum{_labels(self.labelnames, k)} {_num(total)}")
            out.append(f"{self.name}_count{_labels(self.labelnames, k)} {acc}")
        return out


class Registry:
    def __init__(self) -> None:
        self._metrics: list[_Metric] = []

    def add(self, metric: M) -> M:
        self._metrics.append(metric)
        return metric

    def render(self) -> str:
        lines: list[str] = []
        for m in self._metrics:
            lines += m.render()
        return "\n".join(lines) + "\n"


class ServerMetrics:
    """The server's metrics (names are the contract with dashboards)."""

    def __init__(self) -> None:
        self.registry = Registry()
        r = self.registry
        self.frames_in = r.add(
            Counter("sfmloc_frames_received_total", "Frames received.", ("map", "transport"))
        )
        self.frames_dropped = r.add(
            Counter(
                "sfmloc_frames_dropped_total",
                "Stale frames dropped (latest-frame-only intake).",
                ("map",),
            )
        )
        self.frames_done = r.add(
            Counter(
                "sfmloc_frames_processed_total",
                "Frames processed by the engine, by result status.",
                ("map", "status"),
            )
        )
        self.frame_errors = r.add(
            Counter(
                "sfmloc_frame_errors_total", "Frames rejected, by status code.", ("map", "code")
            )
        )
        self.frames_refused = r.add(
            Counter(
                "sfmloc_frames_refused_total",
                "Frames refused by a per-client limit, by limit.",
                ("limit",),
            )
        )
        self.latency = r.add(
            Histogram(
                "sfmloc_frame_latency_seconds", "Frame receipt to pose publication.", ("map",)
            )
        )
        self.engine_latency = r.add(
            Histogram("sfmloc_engine_latency_seconds", "Engine time per frame.", ("map",))
        )
        self.relocalize = r.add(
            Counter(
                "sfmloc_relocalize_total",
                "Single-image relocalizations, by status.",
                ("map", "status"),
            )
        )
        self.relocalize_latency = r.add(
            Histogram("sfmloc_relocalize_latency_seconds", "Relocalize call time.", ("map",))
        )
        self.sessions_opened = r.add(
            Counter("sfmloc_sessions_opened_total", "Sessions created.", ("map", "transport"))
        )
        self.sessions_closed = r.add(
            Counter("sfmloc_sessions_closed_total", "Sessions ended, by reason.", ("map", "reason"))
        )
        self.worker_restarts = r.add(
            Counter("sfmloc_worker_restarts_total", "Workers restarted after dying.")
        )
        self.map_loads = r.add(
            Counter("sfmloc_map_loads_total", "Map loads, by result.", ("result",))
        )

    def gauges(
        self,
        sessions: Callable[[], dict[tuple[str, ...], float]],
        maps: Callable[[], dict[tuple[str, ...], float]],
        busy: Callable[[], dict[tuple[str, ...], float]],
    ) -> None:
        self.registry.add(
            Gauge("sfmloc_sessions", "Active sessions.", ("map", "transport"), collect=sessions)
        )
        self.registry.add(
            Gauge(
                "sfmloc_maps_loaded",
                "Loaded maps (1 per map, labelled with its build).",
                ("map", "build_id"),
                collect=maps,
            )
        )
        self.registry.add(
            Gauge(
                "sfmloc_worker_inflight",
                "Requests queued or running per worker.",
                ("worker",),
                collect=busy,
            )
        )


class MetricsServer:
    """``GET /metrics`` and ``GET /healthz`` on a background thread."""

    def __init__(self, registry: Registry, host: str, port: int, ready: Callable[[], bool]) -> None:
        reg = registry

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 - http.server's naming
                path = self.path.split("?", 1)[0]
                if path == "/metrics":
                    body, code, ctype = (
                        reg.render().encode(),
                        200,
                        "text/plain; version=0.0.4; charset=utf-8",
                    )
                elif path == "/healthz":
                    ok = ready()
                    body, code, ctype = (
                        (b"ok\n" if ok else b"not ready\n"),
                        (200 if ok else 503),
                        "text/plain",
                    )
                else:
                    body, code, ctype = b"not found: try /metrics\n", 404, "text/plain"
                self.send_response(code)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: object) -> None:  # noqa: A002
                log.debug("metrics http: " + format, *args)

        self.httpd = ThreadingHTTPServer((host, port), Handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self._thread = threading.Thread(
            target=self.httpd.serve_forever, name="sfmloc-metrics", daemon=True
        )

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(timeout=5)
