"""The viewer's live state: every client's latest pose, recent trajectory, status and latency,
from the pose messages servers publish on ``sfmloc/<map>/<client>/pose`` (the same messages
the clients get; the viewer only listens), and the fan-out of updates to the open pages."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from typing import Any

from sfmloc_client.keys import ROOT
from sfmloc_client.wire import PoseMessage, decode_pose

log = logging.getLogger(__name__)

POSE_KEYEXPR = f"{ROOT}/*/*/pose"
RATE_WINDOW_S = 2.0  # a client's pose rate is counted over this window
# A page that falls this many updates behind (a stalled tab) is resynchronised by a snapshot
# instead of holding an ever longer backlog.
LISTENER_BACKLOG = 2000


class _Client:
    def __init__(self, map_name: str, client_id: str, trail: int) -> None:
        self.map = map_name
        self.client = client_id
        self.trail: deque[list[float]] = deque(maxlen=trail)
        self.arrivals: deque[float] = deque()
        self.n_poses = 0
        self.last_seen = 0.0
        self.last: dict[str, Any] = {}

    def rate_hz(self, now: float) -> float:
        while self.arrivals and now - self.arrivals[0] > RATE_WINDOW_S:
            self.arrivals.popleft()
        return len(self.arrivals) / RATE_WINDOW_S


def pose_event(p: PoseMessage) -> dict[str, Any]:
    """The page's view of one pose message: the camera's centre and orientation in the map
    (``world_from_cam``), status, latency; nothing the page does not draw or print."""
    T = p.world_from_cam if p.localized else None
    err = None if p.error is None else f"{p.error.code}: {p.error.message}"
    return {
        "map": p.map,
        "client": p.client_id,
        "seq": p.seq,
        "stamp_ns": p.stamp_ns,
        "status": str(p.status),
        "centre": None if T is None else [float(v) for v in T.t],
        "quat_xyzw": None if T is None else [float(v) for v in T.quat_xyzw],
        "latency_ms": float(p.latency_ms),
        "engine_ms": float(p.engine_ms),
        "inliers": int(p.inliers),
        "matching": str(p.matching),
        "dropped": int(p.dropped),
        "message": p.message,
        "error": err,
        "server_id": p.server_id,
    }


class LiveState:
    """Thread-safe: Zenoh's callback thread updates it, the web server's threads read it."""

    def __init__(self, trail: int = 600, forget_after_s: float = 60.0) -> None:
        self.trail = trail
        self.forget_after_s = forget_after_s
        self._lock = threading.Lock()
        self._clients: dict[tuple[str, str], _Client] = {}
        self._listeners: set[queue.Queue] = set()
        self.poses = 0
        self.bad_messages = 0
        self.last_bad = ""

    # ----- input ------------------------------------------------------------------------
    def on_payload(self, payload: bytes, key: str = "") -> None:
        """One sample from the pose key expression; an undecodable one is counted, not fatal
        (anyone on the network may publish there)."""
        try:
            p = decode_pose(payload)
        except Exception as exc:  # noqa: BLE001 - WireError, and whatever garbage raises
            with self._lock:
                self.bad_messages += 1
                self.last_bad = f"{key}: {exc}"[:300]
            log.debug("undecodable pose message on %s: %s", key, exc)
            return
        self.update(p)

    def update(self, p: PoseMessage, now: float | None = None) -> dict[str, Any]:
        now = time.monotonic() if now is None else now
        ev = pose_event(p)
        with self._lock:
            c = self._clients.get((p.map, p.client_id))
            if c is None:
                c = self._clients[(p.map, p.client_id)] = _Client(p.map, p.client_id, self.trail)
            c.n_poses += 1
            c.last_seen = now
            c.arrivals.append(now)
            if ev["centre"] is not None:
                c.trail.append(ev["centre"])
            ev["n_poses"] = c.n_poses
            ev["rate_hz"] = c.rate_hz(now)
            c.last = ev
            self.poses += 1
            listeners = list(self._listeners)
        for q in listeners:
            _offer(q, ("pose", ev))
        return ev

    # ----- output -----------------------------------------------------------------------
    def subscribe(self) -> queue.Queue:
        q: queue.Queue = queue.Queue(maxsize=LISTENER_BACKLOG)
        with self._lock:
            self._listeners.add(q)
        return q

    def unsubscribe(self, q: queue.Queue) -> None:
        with self._lock:
            self._listeners.discard(q)

    @property
    def n_listeners(self) -> int:
        with self._lock:
            return len(self._listeners)

    def snapshot(self, now: float | None = None) -> list[dict[str, Any]]:
        """Every known client with its trajectory (a page that opens or resynchronises)."""
        now = time.monotonic() if now is None else now
        self.forget(now)
        with self._lock:
            return [
                {**c.last, "trail": list(c.trail), "age_s": now - c.last_seen}
                for c in self._clients.values()
            ]

    def summary(self, now: float | None = None) -> dict[str, Any]:
        """Per-client rate and time since the last pose (sent every second: a client that stops
        sending shows its age growing), and the feed's counters."""
        now = time.monotonic() if now is None else now
        self.forget(now)
        with self._lock:
            clients = [
                {
                    "map": c.map,
                    "client": c.client,
                    "rate_hz": c.rate_hz(now),
                    "age_s": now - c.last_seen,
                    "n_poses": c.n_poses,
                }
                for c in self._clients.values()
            ]
            return {
                "clients": clients,
                "poses": self.poses,
                "bad_messages": self.bad_messages,
                "last_bad": self.last_bad,
            }

    def forget(self, now: float) -> None:
        with self._lock:
            gone = [k for k, c in self._clients.items() if now - c.last_seen > self.forget_after_s]
            for k in gone:
                del self._clients[k]


def _offer(q: queue.Queue, item: tuple[str, Any]) -> None:
    try:
        q.put_nowait(item)
    except queue.Full:
        # A stalled page: drop its backlog, it resynchronises from a snapshot.
        try:
            while True:
                q.get_nowait()
        except queue.Empty:
            pass
        q.put_nowait(("resync", None))


class PoseFeed:
    """A Zenoh subscriber on every map's and client's pose key, feeding ``state``."""

    def __init__(self, session: Any, state: LiveState, keyexpr: str = POSE_KEYEXPR) -> None:
        self.state = state
        self._sub = session.declare_subscriber(keyexpr, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        self.state.on_payload(sample.payload.to_bytes(), str(sample.key_expr))

    def close(self) -> None:
        self._sub.undeclare()

    def __enter__(self) -> PoseFeed:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
