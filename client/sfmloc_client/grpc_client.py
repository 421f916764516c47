"""gRPC client of the localization server: single-image relocalization, a frame stream for
clients without Zenoh, and map/session management. Sync (``LocalizationClient``) and asyncio
(``AsyncLocalizationClient``) flavours with the same methods.

Errors come back as ``RemoteError`` with the gRPC status code name in ``code`` (NOT_FOUND for
an unknown map, INVALID_ARGUMENT for a bad image or camera, RESOURCE_EXHAUSTED for an
oversized message or a server at capacity, FAILED_PRECONDITION for a corrupt bundle, ...).
Maps and sessions are returned as the protobuf messages ``MapInfo`` and ``SessionInfo``.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import AsyncIterator, Iterable, Iterator
from typing import Any

import grpc
import numpy as np

from .convert import (
    camera_to_pb,
    image_to_pb,
    pose_from_estimate_pb,
    pose_from_update_pb,
    transform_to_pb,
)
from .errors import InputError, RemoteError
from .images import encode_image
from .pb import localization_pb2 as pb
from .pb import localization_pb2_grpc as pb_grpc
from .sources import SourceFrame
from .wire import CameraSpec, PoseMessage, Transform

DEFAULT_TARGET = "localhost:50051"
SERVICE_NAME = "sfmloc.v1.Localization"


def _options(max_message_mb: float) -> list[tuple[str, int]]:
    n = int(max_message_mb * 1024 * 1024)
    return [("grpc.max_send_message_length", n), ("grpc.max_receive_message_length", n)]


def _credentials(
    tls_ca: str | None, tls_cert: str | None, tls_key: str | None
) -> grpc.ChannelCredentials | None:
    """TLS channel credentials from PEM files (``tls_ca``: the CA that signed the server's
    certificate, None for the system's roots; ``tls_cert``/``tls_key``: ours, for mutual TLS)."""

    def read(path: str | None) -> bytes | None:
        return None if not path else open(path, "rb").read()

    return grpc.ssl_channel_credentials(read(tls_ca), read(tls_key), read(tls_cert))


def _channel(
    target: str,
    max_message_mb: float,
    tls: bool,
    tls_ca: str | None,
    tls_cert: str | None,
    tls_key: str | None,
    aio: bool,
) -> Any:
    """A channel to ``target``: TLS when asked for or when a CA or our certificate is given."""
    mod = grpc.aio if aio else grpc
    options = _options(max_message_mb)
    if tls or tls_ca or tls_cert:
        return mod.secure_channel(target, _credentials(tls_ca, tls_cert, tls_key), options=options)
    return mod.insecure_channel(target, options=options)


def _remote(exc: grpc.RpcError) -> RemoteError:
    code = exc.code() if hasattr(exc, "code") else None
    details = exc.details() if hasattr(exc, "details") else str(exc)
    return RemoteError(code.name if code is not None else "UNKNOWN", details or "")


def _image(image: Any, encoding: str, jpeg_quality: int) -> tuple[str, bytes]:
    if isinstance(image, (bytes, bytearray, memoryview)):
        return encoding, bytes(image)
    if isinstance(image, SourceFrame):
        if image.data is not None:
            return image.encoding or encoding, image.data
        image = image.image
    return encoding, encode_image(np.asarray(image), encoding, jpeg_quality)


def relocalize_request(
    image: Any,
    map_name: str,
    camera: CameraSpec,
    encoding: str = "jpeg",
    prior: Transform | None = None,
    jpeg_quality: int = 95,
) -> pb.RelocalizeRequest:
    enc, data = _image(image, encoding, jpeg_quality)
    req = pb.RelocalizeRequest(
        map=map_name,
        image=image_to_pb(enc, data, camera.width, camera.height),
        camera=camera_to_pb(camera),
    )
    if prior is not None:
        req.prior_cam_from_world.CopyFrom(transform_to_pb(prior))
    return req


def _camera(camera: CameraSpec | str) -> CameraSpec:
    """A ``CameraSpec``, or one parsed from a camera.json path / ``"MODEL w h params..."``."""
    return camera if isinstance(camera, CameraSpec) else CameraSpec.parse(camera)


def _paced(frames: Iterable[Any], rate: float | None) -> Iterator[Any]:
    """``frames`` at most ``rate`` per second (None: as fast as they come)."""
    if rate is None:
        yield from frames
        return
    period, t_next = 1.0 / rate, time.monotonic()
    for fr in frames:
        delay = t_next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        t_next = max(t_next + period, time.monotonic() - period)  # no burst after a stall
        yield fr


def _check_rate(rate: float | None) -> None:
    if rate is not None and not rate > 0:
        raise InputError(f"rate must be positive (frames per second), got {rate}")


def _stream_requests(
    frames: Iterable[Any],
    map_name: str,
    camera: CameraSpec,
    client_id: str,
    encoding: str,
    jpeg_quality: int,
    rate: float | None = None,
    stop: threading.Event | None = None,
    busy: threading.Lock | None = None,
) -> Iterator[pb.StreamFrame]:
    """The stream's requests. ``stop``: end before the next frame; ``busy``: held while a frame
    is read and encoded (the blocking client waits on it, see ``LocalizationClient.stream``)."""
    paced = iter(_paced(frames, rate))
    seq = 0
    while True:
        with busy or _NO_LOCK:
            if stop is not None and stop.is_set():
                return
            fr = next(paced, _END)
            if fr is _END:
                return
            enc, data = _image(fr, encoding, jpeg_quality)
            stamp = (
                fr.stamp_ns
                if isinstance(fr, SourceFrame) and fr.stamp_ns is not None
                else time.time_ns()
            )
            msg = pb.StreamFrame(
                seq=seq, stamp_ns=stamp, image=image_to_pb(enc, data, camera.width, camera.height)
            )
            if isinstance(fr, SourceFrame) and fr.prior is not None:
                msg.prior_cam_from_world.CopyFrom(transform_to_pb(fr.prior))
            if seq == 0:  # map, client and camera are only required on the first frame
                msg.map, msg.client_id = map_name, client_id
                msg.camera.CopyFrom(camera_to_pb(camera))
        yield msg
        seq += 1


_END = object()
_NO_LOCK = contextlib.nullcontext()


class LocalizationClient:
    """Blocking gRPC client. ``target`` is ``host:port``.

    ``token``: a bearer token for servers with authentication (``sfmloc auth add-token``).
    ``tls``/``tls_ca``: a TLS channel (``tls_ca``: PEM of the CA that signed the server's
    certificate; default the system's roots); ``tls_cert``/``tls_key``: our certificate, for
    servers that require one (mutual TLS).
    """

    def __init__(
        self,
        target: str = DEFAULT_TARGET,
        *,
        timeout: float = 30.0,
        max_message_mb: float = 64.0,
        token: str | None = None,
        tls: bool = False,
        tls_ca: str | None = None,
        tls_cert: str | None = None,
        tls_key: str | None = None,
    ) -> None:
        self.target = target
        self.timeout = timeout
        self.channel = _channel(target, max_message_mb, tls, tls_ca, tls_cert, tls_key, aio=False)
        self.stub = pb_grpc.LocalizationStub(self.channel)
        # Sent with every call (servers with authentication need it; others ignore it).
        self.metadata = (("authorization", f"Bearer {token}"),) if token else None

    def _call(self, method: Any, request: Any, timeout: float | None) -> Any:
        try:
            return method(
                request,
                timeout=self.timeout if timeout is None else timeout,
                metadata=self.metadata,
            )
        except grpc.RpcError as exc:
            raise _remote(exc) from None

    def relocalize(
        self,
        image: Any,
        map_name: str,
        camera: CameraSpec | str,
        *,
        encoding: str = "jpeg",
        prior: Transform | None = None,
        timeout: float | None = None,
    ) -> PoseMessage:
        """Localize one image (numpy uint8 gray/BGR, or bytes already in ``encoding``)."""
        req = relocalize_request(image, map_name, _camera(camera), encoding, prior)
        return pose_from_estimate_pb(self._call(self.stub.Relocalize, req, timeout).pose)

    def stream(
        self,
        frames: Iterable[Any],
        map_name: str,
        camera: CameraSpec | str,
        *,
        client_id: str = "",
        encoding: str = "jpeg",
        jpeg_quality: int = 90,
        timeout: float | None = None,
        rate: float | None = None,
    ) -> Iterator[PoseMessage]:
        """Stream frames (numpy images, bytes in ``encoding`` or ``SourceFrame``s) and yield a
        pose per processed frame. ``rate``: send at most this many frames per second (a video
        file's frames at its own rate, say); without it they go as fast as they are read and
        the server drops those that queue up behind a busy one (latest frame only).
        ``camera``: a ``CameraSpec``, a camera.json path or ``"MODEL w h params..."``."""
        _check_rate(rate)
        # The requests are read, decoded and encoded on grpc's own (daemon) thread. When the
        # stream ends early (the server refused it, the caller stopped iterating) that thread
        # may be inside OpenCV, and a process exiting then is killed there (std::terminate,
        # SIGABRT: README's client block with an unknown map exited 134 in 7 of 8 runs). So
        # the end stops the requests and waits for the frame in hand.
        stop, busy = threading.Event(), threading.Lock()
        calls = self.stub.StreamLocalize(
            _stream_requests(
                frames, map_name, _camera(camera), client_id, encoding, jpeg_quality, rate,
                stop, busy,
            ),
            timeout=timeout,
            metadata=self.metadata,
        )  # fmt: skip
        try:
            for update in calls:
                yield pose_from_update_pb(update)
        except grpc.RpcError as exc:
            raise _remote(exc) from None
        finally:
            stop.set()
            calls.cancel()
            # A frame takes milliseconds; a camera read that hangs is not waited out.
            if busy.acquire(timeout=10.0):
                busy.release()

    def list_maps(self) -> list[pb.MapInfo]:
        return list(self._call(self.stub.ListMaps, pb.ListMapsRequest(), None).maps)

    def get_map(self, name: str) -> pb.MapInfo:
        return self._call(self.stub.GetMap, pb.GetMapRequest(name=name), None)

    def load_map(self, path: str, name: str = "", timeout: float | None = None) -> pb.MapInfo:
        """Load (or atomically replace) a map from a bundle folder on the server's machine."""
        return self._call(self.stub.LoadMap, pb.LoadMapRequest(path=str(path), name=name), timeout)

    def unload_map(self, name: str) -> pb.UnloadMapResponse:
        return self._call(self.stub.UnloadMap, pb.UnloadMapRequest(name=name), None)

    def list_sessions(self, map_name: str = "") -> list[pb.SessionInfo]:
        return list(
            self._call(self.stub.ListSessions, pb.ListSessionsRequest(map=map_name), None).sessions
        )

    def reset_session(self, client_id: str, map_name: str = "") -> bool:
        return self._call(
            self.stub.ResetSession, pb.ResetSessionRequest(client_id=client_id, map=map_name), None
        ).reset

    def health(self, service: str = "", timeout: float = 5.0) -> str:
        """The standard health status name ("SERVING", "NOT_SERVING", ...) of ``service``
        ("" for the server as a whole)."""
        from grpc_health.v1 import health_pb2, health_pb2_grpc

        stub = health_pb2_grpc.HealthStub(self.channel)
        resp = self._call(stub.Check, health_pb2.HealthCheckRequest(service=service), timeout)
        return health_pb2.HealthCheckResponse.ServingStatus.Name(resp.status)

    def wait_ready(self, timeout: float = 30.0) -> bool:
        """Wait until the server reports SERVING (maps loaded)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if (
                    self.health(timeout=max(0.1, min(2.0, deadline - time.monotonic())))
                    == "SERVING"
                ):
                    return True
            except RemoteError:
                pass
            time.sleep(0.05)
        return False

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> LocalizationClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class AsyncLocalizationClient:
    """asyncio gRPC client (``grpc.aio``), the same methods as ``LocalizationClient``."""

    def __init__(
        self,
        target: str = DEFAULT_TARGET,
        *,
        timeout: float = 30.0,
        max_message_mb: float = 64.0,
        token: str | None = None,
        tls: bool = False,
        tls_ca: str | None = None,
        tls_cert: str | None = None,
        tls_key: str | None = None,
    ) -> None:
        self.target = target
        self.timeout = timeout
        self.channel = _channel(target, max_message_mb, tls, tls_ca, tls_cert, tls_key, aio=True)
        self.stub = pb_grpc.LocalizationStub(self.channel)
        # Sent with every call (servers with authentication need it; others ignore it).
        self.metadata = (("authorization", f"Bearer {token}"),) if token else None

    async def _call(self, method: Any, request: Any, timeout: float | None) -> Any:
        try:
            return await method(
                request,
                timeout=self.timeout if timeout is None else timeout,
                metadata=self.metadata,
            )
        except grpc.RpcError as exc:
            raise _remote(exc) from None

    async def relocalize(
        self,
        image: Any,
        map_name: str,
        camera: CameraSpec | str,
        *,
        encoding: str = "jpeg",
        prior: Transform | None = None,
        timeout: float | None = None,
    ) -> PoseMessage:
        req = relocalize_request(image, map_name, _camera(camera), encoding, prior)
        return pose_from_estimate_pb((await self._call(self.stub.Relocalize, req, timeout)).pose)

    async def stream(
        self,
        frames: Iterable[Any],
        map_name: str,
        camera: CameraSpec | str,
        *,
        client_id: str = "",
        encoding: str = "jpeg",
        jpeg_quality: int = 90,
        timeout: float | None = None,
        rate: float | None = None,
    ) -> AsyncIterator[PoseMessage]:
        _check_rate(rate)
        call = self.stub.StreamLocalize(
            _stream_requests(
                frames, map_name, _camera(camera), client_id, encoding, jpeg_quality, rate
            ),
            timeout=timeout,
            metadata=self.metadata,
        )
        try:
            async for update in call:
                yield pose_from_update_pb(update)
        except grpc.RpcError as exc:
            raise _remote(exc) from None

    async def list_maps(self) -> list[pb.MapInfo]:
        return list((await self._call(self.stub.ListMaps, pb.ListMapsRequest(), None)).maps)

    async def get_map(self, name: str) -> pb.MapInfo:
        return await self._call(self.stub.GetMap, pb.GetMapRequest(name=name), None)

    async def load_map(self, path: str, name: str = "", timeout: float | None = None) -> pb.MapInfo:
        return await self._call(
            self.stub.LoadMap, pb.LoadMapRequest(path=str(path), name=name), timeout
        )

    async def unload_map(self, name: str) -> pb.UnloadMapResponse:
        return await self._call(self.stub.UnloadMap, pb.UnloadMapRequest(name=name), None)

    async def list_sessions(self, map_name: str = "") -> list[pb.SessionInfo]:
        return list(
            (
                await self._call(self.stub.ListSessions, pb.ListSessionsRequest(map=map_name), None)
            ).sessions
        )

    async def reset_session(self, client_id: str, map_name: str = "") -> bool:
        req = pb.ResetSessionRequest(client_id=client_id, map=map_name)
        return (await self._call(self.stub.ResetSession, req, None)).reset

    async def health(self, service: str = "", timeout: float = 5.0) -> str:
        from grpc_health.v1 import health_pb2, health_pb2_grpc

        stub = health_pb2_grpc.HealthStub(self.channel)
        resp = await self._call(stub.Check, health_pb2.HealthCheckRequest(service=service), timeout)
        return health_pb2.HealthCheckResponse.ServingStatus.Name(resp.status)

    async def close(self) -> None:
        await self.channel.close()

    async def __aenter__(self) -> AsyncLocalizationClient:
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()
