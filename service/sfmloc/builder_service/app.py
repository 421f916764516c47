"""``sfmloc builder serve``: the MapBuilder gRPC service, health and reflection, and Zenoh
announcements of finished bundles (``sfmloc/maps/<name>``: ``{name, build_id, path}``).

Announcements reach servers that start later too: the builder repeats its current ones when a
server appears (its liveliness token ``sfmloc/servers/<id>``), and answers queries on
``sfmloc/maps/*`` with them. Servers that cannot see the builder's folder fetch the announced
bundles' files from it (``sfmloc/bundles/...``, ``bundle_share.py``)."""

from __future__ import annotations

import logging
import signal
import threading
from concurrent import futures
from pathlib import Path
from typing import TYPE_CHECKING

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from pydantic import Field

from sfmloc_client.pb import builder_pb2, builder_pb2_grpc
from sfmloc_client.wire import (
    BUNDLES_KEYEXPR,
    MAPS_KEYEXPR,
    SERVERS_KEYEXPR,
    MapAnnouncement,
    encode_map_announcement,
    map_announce_key,
)
from sfmloc_client.zconfig import make_zenoh_config

from ..config import StrictModel
from ..interceptors import SyncErrorStatusInterceptor, SyncMalformedRequestInterceptor
from ..reflection import enable_reflection
from .bundle_share import BundleShare
from .grpc_service import MapBuilderServicer
from .jobs import Job, JobManager

if TYPE_CHECKING:  # imported when announcing (start)
    import zenoh

log = logging.getLogger(__name__)

SERVICE_NAME = builder_pb2.DESCRIPTOR.services_by_name["MapBuilder"].full_name


class BuilderConfig(StrictModel):
    out: str = Field("maps", description="default folder for bundles")
    grpc: str = Field("127.0.0.1:50052", description="gRPC listen address HOST:PORT")
    max_concurrent: int = Field(1, ge=1, description="builds running at once (one process each)")
    workdir: str | None = Field(
        None, description="parent of per-job work folders (default: a temporary folder)"
    )
    cancel_grace_s: float = Field(
        10.0, gt=0, description="seconds a cancelled build may take to stop"
    )
    announce: bool = True
    zenoh_mode: str = "peer"
    zenoh_listen: list[str] = []
    zenoh_connect: list[str] = []
    zenoh_multicast: bool | None = None
    zenoh_config: str | None = None
    max_message_mb: int = 4


class BuilderService:
    """Owns the job manager, the gRPC server and the Zenoh session; ``start``/``stop``."""

    def __init__(self, config: BuilderConfig) -> None:
        self.config = config
        self.session: zenoh.Session | None = None
        self._zenoh_lock = threading.Lock()
        self.jobs = JobManager(
            config.out,
            config.workdir,
            config.max_concurrent,
            config.cancel_grace_s,
            on_success=self._announce,
        )
        self.server: grpc.Server | None = None
        self.port: int | None = None
        self.health = health.HealthServicer()
        self._announced: dict[str, bytes] = {}  # map name -> its latest announcement
        self.share = BundleShare()  # their files, for servers that cannot see ``out``
        self._zenoh_objects: list = []

    def _announce(self, job: Job) -> None:
        if self.session is None:
            return
        ann = MapAnnouncement(job.spec.name, job.build_id, str(Path(job.bundle_path).resolve()))
        payload = encode_map_announcement(ann)
        self.share.publish(ann.name, ann.build_id, ann.path)
        with self._zenoh_lock:
            self._announced[job.spec.name] = payload
            self.session.put(map_announce_key(job.spec.name), payload)
        log.info(
            "announced %s (build %s) on %s",
            job.spec.name,
            job.build_id,
            map_announce_key(job.spec.name),
        )

    def _reannounce(self, sample) -> None:  # noqa: ANN001 - a zenoh liveliness Sample
        """A server appeared: repeat the current announcements (it may have missed them)."""
        import zenoh

        if sample.kind != zenoh.SampleKind.PUT or self.session is None:
            return
        with self._zenoh_lock:
            for name, payload in self._announced.items():
                self.session.put(map_announce_key(name), payload)
        if self._announced:
            log.info(
                "server %s appeared: repeated %d announcement(s)",
                sample.key_expr,
                len(self._announced),
            )

    def _on_query(self, query) -> None:  # noqa: ANN001 - a zenoh Query
        with self._zenoh_lock:
            current = dict(self._announced)
        for name, payload in current.items():
            key = map_announce_key(name)
            if query.key_expr.intersects(key):
                query.reply(key, payload)

    def start(self) -> int:
        c = self.config
        if c.announce:
            import zenoh

            zconf = make_zenoh_config(
                c.zenoh_mode, c.zenoh_listen, c.zenoh_connect, c.zenoh_multicast, c.zenoh_config
            )
            self.session = zenoh.open(zconf)
            self._zenoh_objects = [
                self.session.liveliness().declare_subscriber(SERVERS_KEYEXPR, self._reannounce),
                self.session.declare_queryable(MAPS_KEYEXPR, self._on_query),
                self.session.declare_queryable(BUNDLES_KEYEXPR, self.share.on_query),
            ]
        limit = c.max_message_mb * 1024 * 1024
        self.server = grpc.server(
            futures.ThreadPoolExecutor(max_workers=16),
            # Unparsable requests: INVALID_ARGUMENT; errors: the one status table.
            interceptors=[SyncMalformedRequestInterceptor(), SyncErrorStatusInterceptor()],
            options=[
                ("grpc.max_receive_message_length", limit),
                ("grpc.max_send_message_length", limit),
            ],
        )
        builder_pb2_grpc.add_MapBuilderServicer_to_server(
            MapBuilderServicer(self.jobs, c.out), self.server
        )
        health_pb2_grpc.add_HealthServicer_to_server(self.health, self.server)
        enable_reflection((SERVICE_NAME, health.SERVICE_NAME), self.server)
        self.port = self.server.add_insecure_port(c.grpc)
        if not self.port:
            raise OSError(f"cannot listen on {c.grpc}")
        self.server.start()
        self.health.set("", health_pb2.HealthCheckResponse.SERVING)
        self.health.set(SERVICE_NAME, health_pb2.HealthCheckResponse.SERVING)
        log.info("builder serving on %s (port %d), bundles in %s", c.grpc, self.port, c.out)
        return self.port

    def stop(self, grace: float = 5.0) -> None:
        self.health.enter_graceful_shutdown()
        if self.server is not None:
            self.server.stop(grace).wait()
        self.jobs.close(cancel_running=True, timeout=self.config.cancel_grace_s + 10)
        if self.session is not None:
            for obj in self._zenoh_objects:
                obj.undeclare()
            self._zenoh_objects = []
            self.session.close()
            self.session = None


def serve(config: BuilderConfig) -> int:
    """Run until SIGTERM/SIGINT: then stop taking requests, cancel running builds, close Zenoh."""
    svc = BuilderService(config)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    svc.start()
    print(
        f"sfmloc builder: gRPC {config.grpc} (port {svc.port}), bundles in {config.out}", flush=True
    )
    try:
        stop.wait()
    finally:
        log.info("shutting down")
        svc.stop()
    return 0
