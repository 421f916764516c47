"""The gRPC ``sfmloc.v1.Localization`` service (grpc.aio), with health and reflection.

Handlers validate requests on the event loop (cheap) and hand the engine work to the worker
pool, awaiting its futures; blocking registry calls (LoadMap) run in an executor. Handlers
raise; ``ErrorStatusInterceptor`` ends the call with the status the one table gives the error.
Per-frame failures of a ``StreamLocalize`` stream (a corrupt image) come back as a LOST
``PoseUpdate`` with ``error_code``/``error_message`` and the stream goes on; failures of the
stream itself (unknown map, first frame without camera) end it with their status.
"""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from collections.abc import AsyncIterator
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_health.v1.health import aio as health_aio

from sfmloc_client.convert import (
    camera_from_pb,
    image_from_pb,
    pose_to_estimate_pb,
    pose_to_update_pb,
    transform_from_pb,
)
from sfmloc_client.pb import localization_pb2 as pb
from sfmloc_client.pb import localization_pb2_grpc as pb_grpc
from sfmloc_client.wire import Frame, PoseMessage, check_name

from ..errors import (
    ConfigError,
    InputError,
    MapNotFoundError,
    PermissionDeniedError,
    SessionNotFoundError,
    UnavailableError,
    WireError,
)
from ..interceptors import ErrorStatusInterceptor, MalformedRequestInterceptor
from ..reflection import enable_reflection
from .auth import AuthInterceptor, TokenTable, caller
from .config import GrpcConf
from .facade import Localization
from .logfmt import event
from .status import error_info

log = logging.getLogger(__name__)

SERVICE_NAME = pb.DESCRIPTOR.services_by_name["Localization"].full_name


class _StreamSink:
    """Poses of a gRPC stream's sessions: onto the stream's asyncio queue, from any thread.
    ``answered`` counts them as they are queued (on the event loop), so that the stream's end
    comes after its last pose (``changed``: set at each)."""

    def __init__(self, loop: asyncio.AbstractEventLoop, q: asyncio.Queue[Any]) -> None:
        self.loop, self.q = loop, q
        self.answered = 0
        self.changed = asyncio.Event()

    def send(self, pose: PoseMessage) -> None:
        self.loop.call_soon_threadsafe(self._put, pose)

    def _put(self, pose: PoseMessage) -> None:
        self.q.put_nowait(pose)
        self.answered += 1
        self.changed.set()

    def close(self) -> None:
        pass


def _checked_camera(loc: Localization, msg: Any) -> Any:
    """The request's camera as a ``CameraSpec``, validated like the engine's (an InputError:
    INVALID_ARGUMENT; too large: RESOURCE_EXHAUSTED)."""
    return loc.check_camera(camera_from_pb(msg))


def _map_info(loc: Localization, e: Any) -> pb.MapInfo:
    n = len(loc.list_sessions(e.name))
    return pb.MapInfo(
        name=e.name,
        path=e.path,
        build_id=e.build_id,
        points=e.points,
        descriptors=e.descriptors,
        images=e.images,
        clusters=e.clusters,
        memory_mb=e.memory_mb,
        sessions=n,
        loaded_utc=e.loaded_utc,
        submaps=e.submaps,
        map_memory_mb=e.map_memory_mb,
        resident_mb=loc.map_resident_mb(e),
    )


class LocalizationService(pb_grpc.LocalizationServicer):
    """The gRPC API over the server's ``Localization`` facade (``executor``: blocking calls
    such as LoadMap; ``grace_s``: how long a finished stream waits for its last poses)."""

    def __init__(
        self, loc: Localization, tokens: TokenTable | None, executor: Executor, grace_s: float
    ) -> None:
        self.loc = loc
        self.tokens = tokens
        self.executor = executor
        self.grace_s = grace_s

    # ------------------------------------------------------------------ single images
    async def Relocalize(
        self, request: pb.RelocalizeRequest, context: grpc.aio.ServicerContext
    ) -> pb.RelocalizeResponse:
        t0 = time.perf_counter()
        loc = self.loc
        loc.get_map(request.map)  # NOT_FOUND before any complaint about the image
        cam = _checked_camera(loc, request.camera)
        enc, data = image_from_pb(request.image, cam)
        prior = None
        if request.HasField("prior_cam_from_world"):
            prior = transform_from_pb(request.prior_cam_from_world, True)
        who = caller(self.tokens, context)
        remaining = context.time_remaining()  # None: the caller set no deadline
        deadline = 0.0 if remaining is None else time.monotonic() + remaining
        pose = await loc.relocalize(
            request.map,
            cam,
            enc,
            bytes(data),
            prior,
            t0=t0,
            caller=who.name if who is not None else context.peer(),
            deadline=deadline,
        )
        return pb.RelocalizeResponse(pose=pose_to_estimate_pb(pose))

    # ------------------------------------------------------------------ streams
    async def StreamLocalize(
        self, request_iterator: AsyncIterator[pb.StreamFrame], context: grpc.aio.ServicerContext
    ) -> AsyncIterator[pb.PoseUpdate]:
        loc = self.loc
        loop = asyncio.get_running_loop()
        q: asyncio.Queue[Any] = asyncio.Queue()
        state: dict[str, Any] = {"session": None, "map": "", "client": "", "camera": None}
        stream_id = uuid.uuid4().hex[:8]
        # One sink for the stream's sessions (a new one after its map was unloaded and loaded
        # again), and the frames handed to them: each is answered through the sink or counted
        # in its session's ``dropped`` (superseded by a newer one), never neither.
        sink = _StreamSink(loop, q)
        sessions: list[Any] = []
        submitted = 0

        async def settled() -> None:
            """Until every frame handed to a session is answered (its pose queued) or counted
            dropped, at most ``grace_s`` + 30 s. Waiting for no frame in a worker was not
            enough: a session's last frame waiting for its turn at a full worker
            (``worker_queue``) is in none, and the stream ended and dropped it unanswered; and
            a pose's queueing (on the worker's result thread, after the session went idle)
            could come after the stream's end."""
            deadline = loop.time() + self.grace_s + 30.0
            while sink.answered + sum(x.dropped for x in sessions) < submitted:
                left = deadline - loop.time()
                if left <= 0:
                    return
                sink.changed.clear()
                try:  # drops made off the event loop are seen at the next poll
                    await asyncio.wait_for(sink.changed.wait(), min(left, 0.25))
                except asyncio.TimeoutError:
                    pass

        async def read() -> None:
            nonlocal submitted
            try:
                async for req in request_iterator:
                    t_recv = time.perf_counter()
                    first = state["session"] is None
                    if first:
                        # Stream-level checks: failing them ends the stream.
                        if not req.map:
                            raise WireError("the first frame of a stream must name the map")
                        loc.get_map(req.map)
                        state["map"] = req.map
                        state["client"] = (
                            check_name(req.client_id, "client id")
                            if req.client_id
                            else f"grpc-{stream_id}"
                        )
                        who = caller(self.tokens, context)
                        if who is not None and not who.admin:
                            # A caller's sessions carry its identity: it cannot pose as
                            # another client.
                            if req.client_id and req.client_id != who.name:
                                raise PermissionDeniedError(
                                    f"{who.name!r} may stream only as client {who.name!r}, not "
                                    f"{req.client_id!r}"
                                )
                            state["client"] = who.name
                        if not req.HasField("camera"):
                            raise WireError("the first frame of a stream must carry the camera")
                        state["camera"] = _checked_camera(loc, req.camera)  # no camera, no stream
                    try:
                        if req.map and req.map != state["map"]:
                            raise WireError(
                                f"a stream stays on one map ({state['map']!r}), this frame names "
                                f"{req.map!r}"
                            )
                        if req.HasField("camera") and not first:
                            state["camera"] = _checked_camera(loc, req.camera)
                        cam = state["camera"]
                        enc, data = image_from_pb(req.image, cam)
                        prior = transform_from_pb(
                            req.prior_cam_from_world, req.HasField("prior_cam_from_world")
                        )
                        stamp = req.stamp_ns or time.time_ns()
                        frame = Frame(req.seq, stamp, cam, enc, data, prior=prior)
                        s = loc.submit_frame(
                            state["map"],
                            state["client"],
                            "grpc",
                            frame,
                            t_recv,
                            make_sink=lambda: sink,
                            key_suffix=f":{stream_id}",
                        )
                        state["session"] = s
                        submitted += 1
                        if s not in sessions:
                            sessions.append(s)
                    except (
                        InputError,
                        MapNotFoundError,
                    ) as exc:  # this frame only: the stream goes on
                        # (an unloaded map too: its frames are answered NOT_FOUND until it is back)
                        q.put_nowait(
                            loc.refuse_frame(
                                state["map"], state["client"], req.seq, req.stamp_ns, exc
                            )
                        )
                # The client is done sending: every frame answered or counted, then the end.
                await settled()
                q.put_nowait(None)
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # noqa: BLE001
                q.put_nowait(exc)

        reader = asyncio.create_task(read())
        try:
            while True:
                item = await q.get()
                if item is None:
                    return
                if isinstance(item, BaseException):
                    event(
                        log,
                        logging.INFO,
                        "stream_failed",
                        client=state["client"],
                        map=state["map"],
                        code=error_info(item).code,
                        error=str(item),
                    )
                    raise item  # ErrorStatusInterceptor ends the stream with its status
                yield pose_to_update_pb(item)
        finally:
            reader.cancel()
            if state["session"] is not None:
                loc.end_session(state["session"], "stream_end")

    # ------------------------------------------------------------------ maps
    async def ListMaps(
        self, request: pb.ListMapsRequest, context: grpc.aio.ServicerContext
    ) -> pb.ListMapsResponse:
        return pb.ListMapsResponse(maps=[_map_info(self.loc, e) for e in self.loc.list_maps()])

    async def GetMap(
        self, request: pb.GetMapRequest, context: grpc.aio.ServicerContext
    ) -> pb.MapInfo:
        return _map_info(self.loc, self.loc.get_map(request.name))

    async def LoadMap(
        self, request: pb.LoadMapRequest, context: grpc.aio.ServicerContext
    ) -> pb.MapInfo:
        if not request.path:
            raise WireError(
                "LoadMap needs a map name or the path of a bundle folder in the maps folders"
            )
        loop = asyncio.get_running_loop()
        entry = await loop.run_in_executor(
            self.executor, self.loc.load_map, request.path, request.name or None
        )
        return _map_info(self.loc, entry)

    async def UnloadMap(
        self, request: pb.UnloadMapRequest, context: grpc.aio.ServicerContext
    ) -> pb.UnloadMapResponse:
        closed = self.loc.unload_map(request.name)
        return pb.UnloadMapResponse(unloaded=True, sessions_closed=closed)

    # ------------------------------------------------------------------ sessions
    async def ListSessions(
        self, request: pb.ListSessionsRequest, context: grpc.aio.ServicerContext
    ) -> pb.ListSessionsResponse:
        from sfmloc_client.convert import STATUS_TO_PB
        from sfmloc_client.pb.common_pb2 import LOCALIZATION_STATUS_UNSPECIFIED

        now = time.monotonic()
        out = []
        who = caller(self.tokens, context)
        for s in self.loc.list_sessions(request.map):
            if who is not None and not who.admin and s.client_id != who.name:
                continue  # a localize caller sees its own sessions only
            out.append(
                pb.SessionInfo(
                    client_id=s.client_id,
                    map=s.map,
                    transport=s.transport,
                    frames=s.frames,
                    localized=s.localized,
                    dropped=s.dropped,
                    last_latency_ms=s.last_latency_ms,
                    mean_latency_ms=s.mean_latency_ms,
                    status=STATUS_TO_PB.get(s.last_status, LOCALIZATION_STATUS_UNSPECIFIED),
                    idle_s=max(0.0, now - s.last_seen),
                )
            )
        return pb.ListSessionsResponse(sessions=out)

    async def ResetSession(
        self, request: pb.ResetSessionRequest, context: grpc.aio.ServicerContext
    ) -> pb.ResetSessionResponse:
        if not request.client_id:
            raise WireError("ResetSession needs a client_id")
        who = caller(self.tokens, context)
        if who is not None and not who.admin and request.client_id != who.name:
            raise PermissionDeniedError(
                f"{who.name!r} may reset only its own sessions (needs the admin role)"
            )
        if not self.loc.reset_sessions(request.client_id, request.map):
            raise SessionNotFoundError(
                f"no session of client {request.client_id!r}"
                + (f" on map {request.map!r}" if request.map else "")
            )
        return pb.ResetSessionResponse(reset=True)


def _read_pem(path: str, what: str) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read the {what} {path}: {exc.strerror}") from None


def _server_credentials(gc: Any) -> grpc.ServerCredentials | None:
    if not (gc.tls_cert or gc.tls_key or gc.tls_client_ca):
        return None
    if not (gc.tls_cert and gc.tls_key):
        raise ConfigError("TLS needs both grpc.tls_cert and grpc.tls_key (--tls-cert, --tls-key)")
    pair = (_read_pem(gc.tls_key, "TLS key"), _read_pem(gc.tls_cert, "TLS certificate"))
    ca = _read_pem(gc.tls_client_ca, "client CA") if gc.tls_client_ca else None
    return grpc.ssl_server_credentials(
        [pair], root_certificates=ca, require_client_auth=ca is not None
    )


def _is_loopback(address: str) -> bool:
    host = address.rsplit(":", 1)[0].strip("[]")
    return host in ("localhost", "::1") or host.startswith("127.")


def make_grpc_server(
    loc: Localization, gc: GrpcConf, tokens: TokenTable | None, executor: Executor, grace_s: float
) -> tuple[grpc.aio.Server, health_aio.HealthServicer, int]:
    """The grpc.aio server with our service over ``loc``, health (NOT_SERVING until maps are
    loaded) and reflection; returns (server, health servicer, bound port)."""
    n = int(gc.max_message_mb * 1024 * 1024)
    interceptors: list[grpc.aio.ServerInterceptor] = [
        MalformedRequestInterceptor(),
        ErrorStatusInterceptor(),
    ]
    if tokens is not None:
        interceptors.insert(0, AuthInterceptor(tokens))
    creds = _server_credentials(gc)
    if tokens is not None and creds is None and not _is_loopback(gc.address):
        raise ConfigError(
            f"gRPC tokens without TLS would travel in the clear on {gc.address}: set grpc.tls_cert "
            "and "
            "grpc.tls_key (--tls-cert/--tls-key), or listen on loopback only"
        )
    g = grpc.aio.server(
        interceptors=interceptors,
        options=[
            ("grpc.max_receive_message_length", n),
            ("grpc.max_send_message_length", n),
            ("grpc.so_reuseport", 0),
        ],
    )
    pb_grpc.add_LocalizationServicer_to_server(
        LocalizationService(loc, tokens, executor, grace_s), g
    )
    health = health_aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health, g)
    enable_reflection((SERVICE_NAME, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name), g)
    try:
        port = (
            g.add_insecure_port(gc.address)
            if creds is None
            else g.add_secure_port(gc.address, creds)
        )
    except RuntimeError as exc:  # grpc's way of saying the address is taken or invalid
        raise UnavailableError(f"cannot listen for gRPC on {gc.address}: {exc}") from None
    if port == 0:
        raise UnavailableError(f"cannot listen for gRPC on {gc.address}")
    return g, health, port


__all__ = ["LocalizationService", "SERVICE_NAME", "make_grpc_server"]
