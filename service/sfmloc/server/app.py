"""The server: wiring, start-up order, graceful shutdown.

Processes and threads
=====================
- the main process runs the asyncio loop (gRPC, grpc.aio), Zenoh's callbacks (on Zenoh's
  threads: decode + hand over, no engine work), two pump threads per worker (pipe writer and
  reader: results are published from the reader), the idle-session reaper and the metrics
  HTTP thread;
- ``workers`` engine processes (default: one per core), each single-threaded (OpenCV, BLAS,
  OpenMP and faiss pinned to one thread) and holding every map; a session is bound to one
  worker, where its Localizer lives, and each frame runs start to end on that worker.

Why worker processes (``sfmloc bench-transport --only engine``, this 2-core machine, best of
3 runs since other jobs shared it): two Localizers flat out reach 1.77x the frames/s of one in
processes, at the same per-frame latency as alone (9.3 ms p50 vs 9.2), but only 1.39x in
threads, with every frame slower (12.6 ms p50): the GIL serializes the engine's Python-level
steps. The transport itself is cheap: with 4 clients at 30 Hz the main process used 0.06 of a
core (``--only clients``); the workers are where the CPU goes.

Start-up: metrics -> workers -> Zenoh session (info queryable) -> gRPC (health NOT_SERVING)
-> maps loaded on every worker -> Zenoh frame intake + liveliness token -> health SERVING.

Shutdown (SIGTERM/SIGINT, or ``stop()``): health NOT_SERVING, Zenoh intake and token withdrawn,
gRPC stops accepting calls; frames in the workers finish (within ``grace_s``) and their poses
go out; then the Zenoh session is closed, the workers stopped, and the process exits 0.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from sfmloc_client.wire import MapAnnouncement, ServerInfo, check_name

from .. import __version__
from ..errors import ConfigError
from ..map.bundle import read_manifest
from .auth import TokenTable
from .bundle_fetch import fetch_bundle
from .config import ServerConfig
from .facade import Localization
from .logfmt import event
from .maps import MapEntry, MapRegistry, resolve_bundle_path
from .metrics import MetricsServer, ServerMetrics
from .pool import WorkerPool
from .protocol import Result
from .sessions import SessionManager
from .submaps import add_submap_metrics
from .zygote import discard_prestarted

log = logging.getLogger(__name__)


def default_server_id() -> str:
    host = (
        "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())[:40]
        or "host"
    )
    return f"{host}-{os.getpid()}"


class Server:
    """One localization server. ``await start()``, ``await stop()``; or ``run_server`` for the
    CLI, and ``sfmloc.testing.ServerThread`` for tests and tools. Its front ends (Zenoh,
    gRPC) see only ``self.facade``."""

    def __init__(self, conf: ServerConfig) -> None:
        self.conf = conf
        self.server_id = check_name(conf.server_id or default_server_id(), "server id")
        self.metrics = ServerMetrics()
        n = conf.workers or os.cpu_count() or 1
        self.pool = WorkerPool(
            n,
            conf.worker_kind,
            conf.engine.model_dump_json(),
            on_result=self._on_result,
            on_lost=self._on_worker_lost,
            on_dead=self._on_worker_dead,
            log_level=logging.getLogger().getEffectiveLevel(),
            log_format=conf.log_format,
            max_pending_relocalize=conf.max_pending_relocalize,
            max_image_pixels=conf.max_image_pixels,
            reloc_workers=conf.relocalize_workers,
            reloc_nice=conf.relocalize_nice,
            worker_slice_ms=conf.worker_slice_ms,
            fork=conf.worker_start == "fork",
        )
        self.registry = MapRegistry(
            self.pool, on_change=self._on_map_change, map_memory_mb=conf.engine.map_memory_mb
        )
        # gRPC bearer tokens and roles (None: authentication off).
        self.tokens = TokenTable.load(conf.grpc.tokens_file) if conf.grpc.tokens_file else None
        self.sessions = SessionManager(
            self.pool,
            self.registry,
            self.metrics,
            server_id=self.server_id,
            max_sessions=conf.max_sessions,
            idle_timeout_s=conf.idle_timeout_s,
            max_image_pixels=conf.max_image_pixels,
            max_pending=conf.max_pending,
            frame_budget_ms=conf.frame_budget_ms,
            frame_cpu_budget_ms=conf.frame_cpu_budget_ms,
            worker_queue=conf.worker_queue,
            relocalize_share=conf.relocalize_share,
            frame_hang_ms=conf.frame_hang_ms,
            track_gap_s=conf.engine.max_frame_gap_s,
        )
        # All the front ends see of the server.
        self.facade = Localization(
            sessions=self.sessions,
            registry=self.registry,
            pool=self.pool,
            metrics=self.metrics,
            server_id=self.server_id,
            map_roots=[conf.maps, *conf.map_roots],
            max_image_pixels=conf.max_image_pixels,
            max_relocalize_per_client=conf.max_relocalize_per_client,
            relocalize_budget_ms=conf.relocalize_budget_ms,
        )
        self.metrics.gauges(
            sessions=self.sessions.counts_by_map,
            maps=lambda: {(e.name, e.build_id): 1.0 for e in self.registry.list()},
            busy=lambda: {(str(i),): float(v) for i, v in enumerate(self.pool.inflight())},
        )
        add_submap_metrics(self.metrics.registry, self.registry)
        self.executor = ThreadPoolExecutor(conf.grpc.threads, thread_name_prefix="sfmloc-blocking")
        self.zenoh: Any = None
        self.grpc: Any = None
        self.health: Any = None
        self.grpc_port: int | None = None
        self.metrics_server: MetricsServer | None = None
        self.ready = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._health_maps: set[str] = set()  # maps whose per-map health entry was set SERVING
        self._stopped = asyncio.Event()
        self._reaper_stop = threading.Event()
        self._reaper: threading.Thread | None = None
        self._load_started = time.monotonic()
        self._rate = (time.monotonic(), 0.0, [0.0] * n)  # for the load figures of ServerInfo

    # ------------------------------------------------------------------ wiring
    def _on_result(self, msg: Result) -> None:
        self.sessions.on_result(msg)

    def _on_worker_dead(self, index: int) -> None:
        self.sessions.on_worker_dead(index)

    def _on_worker_lost(self, index: int) -> None:
        self.metrics.worker_restarts.inc()
        self.sessions.on_worker_lost(index)

    def _on_announcement(self, ann: MapAnnouncement) -> None:
        current = self.registry.find(ann.name)
        if current is not None and current.build_id == ann.build_id:
            return
        event(
            log, logging.INFO, "map_announced", map=ann.name, build_id=ann.build_id, path=ann.path
        )
        try:
            if self._visible(ann) or not self.conf.fetch_bundles:
                self.facade.load_map(ann.path, ann.name)
            else:
                self._fetch_and_load(ann)
        except Exception as exc:  # noqa: BLE001 - keep serving the current map
            event(
                log,
                logging.ERROR,
                "map_announced_load_failed",
                map=ann.name,
                path=ann.path,
                error=str(exc),
            )

    def _visible(self, ann: MapAnnouncement) -> bool:
        """Whether the announced folder is this very build inside our maps folders (shared
        storage, or builder and server on one machine)."""
        try:
            path = resolve_bundle_path(ann.path, [self.conf.maps, *self.conf.map_roots])
            return read_manifest(path).build_id == ann.build_id
        except Exception:  # noqa: BLE001 - outside the roots, absent, unreadable: not visible
            return False

    def _fetch_and_load(self, ann: MapAnnouncement) -> None:
        """The builder is elsewhere: fetch its bundle over Zenoh into ``maps``, then load it."""
        t0 = time.monotonic()
        event(log, logging.INFO, "map_fetch_started", map=ann.name, build_id=ann.build_id)
        path = fetch_bundle(
            self.zenoh.z,
            ann.name,
            ann.build_id,
            self.conf.maps,
            max_bytes=int(self.conf.max_fetch_mb * 2**20),
        )
        event(
            log,
            logging.INFO,
            "map_fetched",
            map=ann.name,
            build_id=ann.build_id,
            path=str(path),
            seconds=round(time.monotonic() - t0, 2),
        )
        self.facade.load_map(ann.name, ann.name)

    def info(self) -> ServerInfo:
        now = time.monotonic()
        t_prev, frames_prev, busy_prev = self._rate
        frames = sum(s.processed for s in self.sessions.list())
        busy = self.pool.busy_ms()
        dt = max(1e-3, now - t_prev)
        if dt > 1.0:
            self._rate = (now, float(frames), busy)
        return ServerInfo(
            server_id=self.server_id,
            version=__version__,
            grpc=self._grpc_address(),
            maps=[e.summary() for e in self.registry.list()],
            sessions=len(self.sessions),
            workers=self.pool.n,
            load={
                "frames_per_s": max(0.0, (frames - frames_prev) / dt),
                "busy": min(
                    1.0,
                    sum(b - p for b, p in zip(busy[: self.pool.n], busy_prev))
                    / 1e3
                    / dt
                    / max(1, self.pool.n),
                ),
                "inflight": float(sum(self.pool.inflight())),
            },
            ready=self.ready,
        )

    def _grpc_address(self) -> str:
        """Where clients reach our gRPC (a wildcard listen address becomes the host name)."""
        if self.grpc_port is None:
            return ""
        host = self.conf.grpc.address.rsplit(":", 1)[0]
        if host in ("", "0.0.0.0", "[::]", "::"):
            host = socket.gethostname()
        return f"{host}:{self.grpc_port}"

    # ------------------------------------------------------------------ lifecycle
    async def start(self, load_maps: bool = True) -> None:
        loop = asyncio.get_running_loop()
        self._loop = loop
        c = self.conf
        if c.metrics_port is not None:
            self.metrics_server = MetricsServer(
                self.metrics.registry, c.metrics_host, c.metrics_port, self.serving
            )
            self.metrics_server.start()
        t0 = time.perf_counter()
        # The workers start while Zenoh and gRPC open (start-up time: their imports and forks
        # overlap the front ends' set-up); no frame is taken before the maps are loaded.
        workers = loop.run_in_executor(self.executor, self.pool.start)
        try:
            await self._open_front_ends()
        finally:
            await workers  # its error first: a front end's own error would follow from it
        discard_prestarted()  # not taken: this configuration does not fork its workers
        event(
            log,
            logging.INFO,
            "workers_started",
            workers=self.pool.n,
            relocalize_workers=self.pool.reloc_workers,
            kind=c.worker_kind,
            ms=round((time.perf_counter() - t0) * 1e3),
        )
        self._reaper = threading.Thread(target=self._reap, name="sfmloc-reaper", daemon=True)
        self._reaper.start()
        if load_maps:
            await self.load_initial_maps()

    async def _open_front_ends(self) -> None:
        loop = asyncio.get_running_loop()
        c = self.conf
        if c.zenoh.enabled:
            from .zenoh_io import ZenohFrontend

            self.zenoh = ZenohFrontend(
                c, self.facade, self.server_id, self.info, self._on_announcement
            )
            await loop.run_in_executor(self.executor, self.zenoh.open)
        if c.grpc.address:
            from grpc_health.v1 import health_pb2

            from .grpc_service import SERVICE_NAME, make_grpc_server

            self.grpc, self.health, self.grpc_port = make_grpc_server(
                self.facade, c.grpc, self.tokens, self.executor, c.grace_s
            )
            for svc in ("", SERVICE_NAME):
                await self.health.set(svc, health_pb2.HealthCheckResponse.NOT_SERVING)
            await self.grpc.start()
            event(log, logging.INFO, "grpc_listening", address=c.grpc.address, port=self.grpc_port)

    async def load_initial_maps(self) -> None:
        """Load every bundle in ``conf.maps``, then accept frames and report SERVING."""
        loop = asyncio.get_running_loop()
        loaded, failed = await loop.run_in_executor(
            self.executor, self.registry.load_dir, self.conf.maps
        )
        for _ in loaded:
            self.metrics.map_loads.inc("ok")
        for _ in failed:
            self.metrics.map_loads.inc("failed")
        await self.mark_ready()
        event(
            log,
            logging.INFO,
            "server_ready",
            server_id=self.server_id,
            maps=[e.name for e in loaded],
            failed=len(failed),
            grpc_port=self.grpc_port,
            workers=self.pool.n,
        )

    async def mark_ready(self) -> None:
        if self.zenoh is not None:
            self.zenoh.start_intake()
        self.ready = True
        await self._update_health()

    def serving(self) -> bool:
        """What health reports: started, and able to localize (a map loaded, or allow_empty)."""
        return self.ready and (self.conf.allow_empty or bool(self.registry.list()))

    async def _update_health(self) -> None:
        """The server's and each map's gRPC health from the registry (``/healthz`` reads
        ``serving()`` directly)."""
        if self.health is None:
            return
        from grpc_health.v1 import health_pb2

        from .grpc_service import SERVICE_NAME

        ok, no = health_pb2.HealthCheckResponse.SERVING, health_pb2.HealthCheckResponse.NOT_SERVING
        up = self.serving()
        for svc in ("", SERVICE_NAME):
            await self.health.set(svc, ok if up else no)
        names = {e.name for e in self.registry.list()} if self.ready else set()
        for name in sorted(names | self._health_maps):
            await self.health.set(f"{SERVICE_NAME}/{name}", ok if name in names else no)
        self._health_maps = names

    def _on_map_change(self, name: str, old: MapEntry | None, new: MapEntry | None) -> None:
        """Registry callback (any thread): health follows the loaded maps."""
        loop = self._loop
        if loop is None or loop.is_closed() or not self.ready:
            return
        try:
            asyncio.run_coroutine_threadsafe(self._update_health(), loop)
        except RuntimeError:  # the loop is shutting down
            pass

    def _reap(self) -> None:
        # Every 0.1 s: frames past their time budget are answered within 0.1 s of it.
        idle_every, t_idle = min(1.0, self.conf.idle_timeout_s / 4), time.monotonic()
        while not self._reaper_stop.wait(0.1):
            try:
                self.sessions.expire_late()
                self.pool.expire_relocalizations()
                if time.monotonic() - t_idle < idle_every:
                    continue
                t_idle = time.monotonic()
                self.sessions.expire_idle()
                if self.zenoh is not None:
                    self.zenoh.rejections.flush()  # the summary of held-back lines, on time
                    self.zenoh.rate_limiter.prune()  # clients gone: their buckets too
            except Exception:  # noqa: BLE001
                log.exception("idle-session reaper failed")

    async def stop(self, grace: float | None = None) -> None:
        """Graceful shutdown (idempotent)."""
        if self._stopped.is_set():
            return
        grace = self.conf.grace_s if grace is None else grace
        loop = asyncio.get_running_loop()
        t0 = time.perf_counter()
        event(log, logging.INFO, "server_stopping", grace_s=grace, sessions=len(self.sessions))
        self.ready = False
        if self.health is not None:
            await self.health.enter_graceful_shutdown()  # everything NOT_SERVING
        if self.zenoh is not None:
            self.zenoh.stop_intake()
        self.sessions.draining = True
        grpc_stop = asyncio.ensure_future(self.grpc.stop(grace)) if self.grpc is not None else None
        finished = await loop.run_in_executor(None, self.sessions.wait_idle, grace)
        if not finished:
            log.warning("frames still in the workers after %.1f s: stopping anyway", grace)
        if grpc_stop is not None:
            await grpc_stop
        for s in self.sessions.list():
            self.sessions.close(s, "shutdown")
        self._reaper_stop.set()
        if self.zenoh is not None:
            await loop.run_in_executor(None, self.zenoh.close)
        await loop.run_in_executor(None, self.pool.stop)
        self.sessions.write_timeline()  # diagnosis only (sessions.TIMELINE_ENV); None when off
        if self.metrics_server is not None:
            self.metrics_server.stop()
        self.executor.shutdown(wait=False, cancel_futures=True)
        self._stopped.set()
        event(log, logging.INFO, "server_stopped", ms=round((time.perf_counter() - t0) * 1e3))

    async def wait_stopped(self) -> None:
        await self._stopped.wait()


async def _serve(conf: ServerConfig) -> int:
    server = Server(conf)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    signals = 0

    def on_signal(signum: int) -> None:
        nonlocal signals
        signals += 1
        if signals > 1:
            log.warning("second signal: exiting now")
            os._exit(1)
        event(log, logging.INFO, "signal", signal=signal.Signals(signum).name)
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, on_signal, sig)
    try:
        starting = asyncio.ensure_future(server.start())
        stopper = asyncio.ensure_future(stop.wait())
        done, _ = await asyncio.wait({starting, stopper}, return_when=asyncio.FIRST_COMPLETED)
        if starting in done:
            starting.result()  # raise start-up errors
            await stop.wait()
        else:
            starting.cancel()
    finally:
        await server.stop()
    return 0


def run_server(conf: ServerConfig) -> int:
    """Serve until SIGTERM/SIGINT; returns the exit code (0 after a graceful shutdown)."""
    if conf.workers < 0:
        raise ConfigError("workers must be >= 0")
    return asyncio.run(_serve(conf))
