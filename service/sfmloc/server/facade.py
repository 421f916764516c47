"""What a front end may ask of the server: the one narrow interface Zenoh and gRPC both use.

Submit a frame (to its session), relocalize one image, list/load/unload maps, list/reset/end
sessions, and the error pose a refused frame gets. The front ends see neither the worker pool
nor the registry nor the session table; the server (``app.py``) builds one ``Localization``
and hands it to each front end.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from pathlib import Path

from sfmloc_client.wire import CameraSpec, Frame, PoseMessage, Transform

from ..errors import DeadlineExceededError, OverloadError
from .maps import MapEntry, MapRegistry, resolve_bundle_path
from .metrics import ServerMetrics
from .pool import WorkerPool
from .protocol import Relocalize, camera_tuple, pose_message
from .sessions import Session, SessionManager, Sink, validate_camera


def answer_by(deadline: float, now: float | None = None) -> float:
    """When a relocalization must end (queued or running) so that its answer reaches the caller
    before ``deadline`` (``time.monotonic()``): a quarter of the time left, at most 2.5 s, is
    kept for stopping at the next stage boundary and sending the answer back. Without it the
    work stopped at the deadline itself and the caller's own deadline fired first (the 100k
    fuzz at load 10-16: 142 Relocalize calls ended DEADLINE_EXCEEDED at 10 s)."""
    now = time.monotonic() if now is None else now
    left = deadline - now
    return deadline - min(2.5, 0.25 * max(0.0, left))


class Localization:
    def __init__(
        self,
        *,
        sessions: SessionManager,
        registry: MapRegistry,
        pool: WorkerPool,
        metrics: ServerMetrics,
        server_id: str,
        map_roots: list[str | Path],
        max_image_pixels: int,
        max_relocalize_per_client: int = 4,
        relocalize_budget_ms: float = 0.0,
    ) -> None:
        self._sessions = sessions
        self._registry = registry
        self._pool = pool
        self._metrics = metrics
        self._roots = map_roots
        self.server_id = server_id
        self.max_image_pixels = max_image_pixels
        self.max_relocalize_per_client = max_relocalize_per_client
        self.relocalize_budget_ms = relocalize_budget_ms
        self._reloc_by_caller: dict[str, int] = {}  # queued or running, per caller
        self._reloc_lock = threading.Lock()

    # ------------------------------------------------------------------ frames
    def check_camera(self, cam: CameraSpec) -> CameraSpec:
        """``cam`` as the engine will use it (``CameraModelError``) within the image size limit
        (``MessageTooLargeError``)."""
        validate_camera(cam, self.max_image_pixels)
        return cam

    def submit_frame(
        self,
        map_name: str,
        client_id: str,
        transport: str,
        frame: Frame,
        t_recv: float,
        make_sink: Callable[[], Sink],
        key_suffix: str = "",
    ) -> Session:
        """Hand a decoded frame to its session (created on first use); its pose goes to the
        session's sink. Raises what the client must hear before any engine work."""
        return self._sessions.submit(
            map_name, client_id, transport, frame, t_recv, make_sink, key_suffix=key_suffix
        )

    def refuse_frame(
        self, map_name: str, client_id: str, seq: int | None, stamp_ns: int, exc: BaseException
    ) -> PoseMessage:
        """Count a refused frame and return the error pose its client gets."""
        self._sessions.count_error(map_name, exc)
        return self._sessions.error_pose(map_name, client_id, seq, stamp_ns, exc)

    def count_refused(self, limit: str) -> None:
        """A frame refused by a per-client limit (e.g. ``"rate"``)."""
        self._metrics.frames_refused.inc(limit)

    def end_session(self, session: Session, reason: str) -> None:
        self._sessions.close(session, reason)

    def wait_idle(self, sessions: list[Session], timeout: float) -> bool:
        """Wait until none of ``sessions`` has a frame in a worker."""
        return self._sessions.wait_idle(timeout, sessions)

    # ------------------------------------------------------------------ single images
    async def relocalize(
        self,
        map_name: str,
        cam: CameraSpec,
        encoding: str,
        data: bytes,
        prior: Transform | None = None,
        t0: float | None = None,
        caller: str = "",
        deadline: float = 0.0,
    ) -> PoseMessage:
        """One image, no session, on the relocalization lane (``cam`` checked by the caller;
        ``t0``: the request's receipt, ``time.perf_counter()``, for its latency). ``caller``:
        who asks (admission: ``max_relocalize_per_client`` at a time); ``deadline``: the
        caller's, ``time.monotonic()`` (0: none). Cancelling the call drops queued work."""
        t0 = time.perf_counter() if t0 is None else t0
        entry = self._registry.get(map_name)
        if deadline and time.monotonic() >= deadline:
            raise DeadlineExceededError("the call's deadline passed before it was queued")
        if deadline:
            deadline = answer_by(deadline)
        msg = Relocalize(
            0,
            entry.name,
            entry.generation,
            camera_tuple(cam),
            encoding,
            prior,
            deadline=deadline,
            budget_ms=self.relocalize_budget_ms,
            data=bytes(data),
        )
        with self._reloc_lock:
            n = self._reloc_by_caller.get(caller, 0)
            if n >= self.max_relocalize_per_client:
                raise OverloadError(
                    f"this caller already has {n} relocalizations queued or running (limit "
                    f"{self.max_relocalize_per_client}); wait for their answers"
                )
            self._reloc_by_caller[caller] = n + 1
        try:
            result = await asyncio.wrap_future(self._pool.relocalize(msg))
        finally:
            with self._reloc_lock:
                n = self._reloc_by_caller.pop(caller) - 1
                if n:
                    self._reloc_by_caller[caller] = n
        pose = pose_message(
            result.pose,
            result.error,
            seq=None,
            stamp_ns=0,
            map_name=entry.name,
            build_id=entry.build_id,
            server_id=self.server_id,
            latency_ms=(time.perf_counter() - t0) * 1e3,
        )
        self._metrics.relocalize.inc(entry.name, pose.status)
        self._metrics.relocalize_latency.observe(entry.name, value=pose.latency_ms / 1e3)
        return pose

    # ------------------------------------------------------------------ maps
    def get_map(self, name: str) -> MapEntry:
        return self._registry.get(name)

    def list_maps(self) -> list[MapEntry]:
        return self._registry.list()

    def map_resident_mb(self, entry: MapEntry) -> float:
        """A sub-map set: the most one engine worker holds of it now (0 for a bundle)."""
        return self._registry.resident_mb(entry)

    def load_map(self, path: str, name: str | None = None) -> MapEntry:
        """Load a bundle given by name or by a path inside the maps folders (LoadMap, builder
        announcements); anything else is refused before it is read. Blocks on the workers."""
        try:
            entry = self._registry.load(resolve_bundle_path(path, self._roots), name)
        except Exception:
            self._metrics.map_loads.inc("failed")
            raise
        self._metrics.map_loads.inc("ok")
        return entry

    def unload_map(self, name: str) -> int:
        """Unload a map; returns how many sessions ended with it."""
        self._registry.unload(name)
        return self._sessions.close_map(name)

    # ------------------------------------------------------------------ sessions
    def list_sessions(self, map_name: str = "") -> list[Session]:
        return self._sessions.list(map_name)

    def reset_sessions(self, client_id: str, map_name: str = "") -> bool:
        """Reset a client's sessions (on one map, or all); False when it has none."""
        return self._sessions.reset(client_id, map_name)


__all__ = ["Localization"]
