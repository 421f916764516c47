"""Per-client sessions and the latest-frame-only intake.

A session is created on a client's first frame (key: map, client id, transport) and is bound
to one worker, where its ``Localizer`` (track table, motion filter) lives. At most one frame
per session is in a worker at any time, and at most one more waits here (``max_pending``,
default 1): a frame that arrives while another is waiting replaces it, and the replaced one is
counted as dropped. So a client sending faster than it can be served gets the freshest frame
processed next, never a growing queue, and other clients' frames never wait behind its
backlog. (``max_pending`` > 1 keeps that many newest frames instead: fewer drops after a slow
frame, at the price of poses that are older when they come back.)

With ``worker_queue`` = N > 0, at most N frames are in one engine worker at once (one
running, N-1 in its pipe); a session whose worker is full waits here with its newest frame,
and the worker's waiting sessions take turns (round-robin) as frames come back. Without the
limit, each session's frame goes into its worker's pipe at once and waits there behind the
other sessions' frames while newer frames of its own client arrive: under overload every pose
was a pipe's worth of frames old (8 clients on 2 workers: p50 80 ms for 15 ms of engine). With
it, a frame starts at most N-1 frames after it was picked, and it is the newest one then.

Whose turn it is (a full worker, sessions waiting): the earliest *deadline* first. A session
whose next frame will track (its last frame was posed, within the engine's
``max_frame_gap_s`` of this one) is due ``live_gap_s`` (0.1 s) after its last frame's receipt;
one whose frame will relocalize (new, LOST, or past that gap: 5-20x a tracked frame's CPU) is
due ``cold_gap_s`` (1 s) after it began to wait. Among tracked sessions that is round-robin;
a relocalizing one waits behind them for up to about ``cold_gap_s``, then goes first. Plain
round-robin collapsed under overload: when every session relocalized at once (the bench's
start, 16 clients on 2 workers), one round of 8 relocalizations per worker took over a second,
so every session's next frame came after a gap past ``max_frame_gap_s`` and relocalized again,
for good (throughput suite at b6d63a1: 16 clients 44.9 poses/s, 40 ms of CPU per pose, 12
clients 126/s at 14.6 ms). Deadlines let the first relocalized sessions keep tracking while the
others relocalize one by one.

Deadlines alone still collapsed (16 clients: 62% of poses relocalized, 22 poses/s): a
relocalizing session due after ``cold_gap_s`` went before every tracked one, and with one
such session due after another a worker spent whole rounds relocalizing, longer than the
engine's frame gap, so the sessions it had just relocalized fell past the gap and relocalized
again. So relocalization has a share of each worker (``relocalize_share``, 0.5): a frame that
relocalized (sent as one that would, or one whose result says it did: not TRACKING, or global
matching) leaves the worker owing its tracked sessions that much of its time again
(``_owed``), and until they had it, a relocalizing session's turn comes only when no tracked
one waits, and at most one relocalizing frame is in a worker at once (else a tracked frame
could wait behind two in its pipe). The worker never idles for it (with no tracked frame
waiting, relocalizations go on one after another), and no session starves (each tracked frame
pays the debt off; it never adds up past one relocalization's). A session whose frame sent as
one that tracks relocalized instead (served too seldom to track) waits as a relocalizing one
next time (``_live``). On a simulated clock
(``tests/test_overload_turns.py``: 16 clients at 30 Hz, 2 workers, 15 ms per tracked frame,
80 ms per relocalization) this keeps 125 poses/s, 2% relocalized, every client >= 6 Hz, where
deadlines alone gave 42 poses/s, 56% relocalized.

So what a new session is promised is an order and a share of its worker's time, not a wall-clock
wait (``tests/turn_promise.py`` checks it on the timeline): new sessions get their first turns
in the order their first frames came, and once due one waits only for the relocalizations ahead
of it, each followed by at most as much tracked work (give or take a frame per session). On a
loaded machine relocalizations take longer, so the last of several new sessions waits seconds
while the first ones track: equal poses per client over a short window are not promised.

Poses go back through the session's *sink* (a Zenoh publisher, or a gRPC stream's queue).
Zenoh sessions end after ``idle_timeout_s`` without frames; gRPC sessions end with their stream.
"""

from __future__ import annotations

import builtins
import itertools
import json
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from sfmloc_client.wire import ErrorInfo, Frame, PoseMessage, decode_pose, encode_pose_entries

from ..cameras import Camera
from ..engine.types import Matching, Status
from ..errors import OverloadError, PermissionDeniedError
from .limits import LogLimiter
from .logfmt import event
from .maps import MapRegistry
from .metrics import ServerMetrics
from .pool import WorkerPool
from .protocol import LocalizeFrame, Result, camera_tuple, pose_message
from .status import error_info

log = logging.getLogger(__name__)

# A session's sender that has been silent this long may be replaced by another one under the
# same client id (a device that restarted gets a new Zenoh session id); before, the other
# sender is refused. Short against the idle timeout (30 s), long against a frame interval.
SOURCE_TAKEOVER_S = 3.0
# A session moved to another worker (its worker died, or a replacement takes it over) has no
# state there: its frames carry its last pose as the prior (the engine searches around it
# before global matching) until the new worker has posed it, while that pose is at most this
# old. As the client's own handover after a failover (FrameStreamer.handover_max_age_s).
HANDOVER_MAX_AGE_S = 5.0
UNKNOWN_MAP = "(not loaded)"  # metrics label of frames for maps this server does not host
# A per-frame timeline for diagnosing drops and late poses (issue 10): with this environment
# variable set to a directory, the session manager records every frame's receipt, its being
# superseded (dropped), its start in a worker and its result, with perf_counter times (the
# clients' clock on this machine), and writes them at shutdown (``write_timeline``). Unset, the
# default, it costs one attribute test per event.
TIMELINE_ENV = "SFMLOC_TIMELINE"
TIMELINE_ROWS = 500_000  # ~4 rows a frame: the last ~17 min of 4 clients at 30 Hz, ~100 MB
# Last statuses after which the session's next frame tracks (a LOST one relocalizes).
_POSED = frozenset({Status.TRACKING.value, Status.RELOCALIZED.value, Status.UNVERIFIED.value})


class Sink(Protocol):
    """Where a session's poses go. A sink may also have ``send_encoded(data: bytes)``, taking
    a pose message already encoded (``wire.encode_pose``'s bytes): poses the engine worker
    encoded are published without being decoded (``SessionManager._send_encoded``)."""

    def send(self, pose: PoseMessage) -> None: ...

    def close(self) -> None: ...


@dataclass
class _Pending:
    frame: Frame
    t_recv: float  # time.perf_counter() at receipt


@dataclass
class Session:
    sid: int
    map: str
    client_id: str
    transport: str  # "zenoh" or "grpc"
    key: tuple[str, str, str]
    worker: int
    sink: Sink
    created: float = field(default_factory=time.monotonic)
    last_seen: float = field(default_factory=time.monotonic)
    frames: int = 0  # received
    processed: int = 0
    localized: int = 0
    dropped: int = 0
    errors: int = 0
    last_latency_ms: float = 0.0
    latency_sum_ms: float = 0.0
    last_status: str = ""
    busy: bool = False  # a frame of this session is in its worker
    pending: deque[_Pending] = field(default_factory=deque)  # newest frames waiting (bounded)
    camera: Any = None  # the last CameraSpec seen (validated once, not per frame)
    inflight_t_recv: dict[int, float] = field(default_factory=dict)  # seq -> receipt time
    ticket: int = 0  # the dispatch number of the frame in its worker (0: none)
    waiting: bool = False  # queued for its worker (full): its pending frames go on in turn
    closed: bool = False
    source: str = ""  # the sender of its first frame (Zenoh session id); "" = not given
    # Its last localized cam_from_world (a wire Transform) and when (time.monotonic()); while
    # ``handover`` (moved to a worker that has not posed it yet), frames carry it as prior.
    last_pose: Any = None
    last_pose_t: float = 0.0
    handover: bool = False
    # Receipt time and stamp of its last frame sent to a worker (None: none yet), and when it
    # began to wait for its worker's turn (its newest frame's receipt then): its deadline.
    last_t_recv: float | None = None
    last_stamp_ns: int = 0
    wait_since: float = 0.0
    # Its last frame was sent as one that would track and relocalized (or was lost) instead:
    # its next one waits as a relocalizing one (``_live``).
    track_failed: bool = False

    @property
    def mean_latency_ms(self) -> float:
        return self.latency_sum_ms / self.processed if self.processed else 0.0


class SessionManager:
    def __init__(
        self,
        pool: WorkerPool,
        registry: MapRegistry,
        metrics: ServerMetrics,
        *,
        server_id: str,
        max_sessions: int = 256,
        idle_timeout_s: float = 30.0,
        max_image_pixels: int = 4096 * 4096,
        max_pending: int = 1,
        frame_budget_ms: float = 2000.0,
        frame_cpu_budget_ms: float = 1000.0,
        worker_queue: int = 0,
        relocalize_share: float = 0.5,
        frame_hang_ms: float = 8000.0,
        live_gap_s: float = 0.1,
        cold_gap_s: float = 1.0,
        track_gap_s: float = 1.0,
    ) -> None:
        self.pool = pool
        self.registry = registry
        self.metrics = metrics
        self.server_id = server_id
        self.max_sessions = max_sessions
        self.idle_timeout_s = idle_timeout_s
        self.max_image_pixels = max_image_pixels
        self.max_pending = max_pending  # 1: latest-frame-only
        self.frame_budget_ms = frame_budget_ms  # receipt to answer, wall (0: none)
        self.frame_cpu_budget_ms = frame_cpu_budget_ms  # in the worker, once started (0: none)
        # A frame its worker is working on is left to its CPU budget (the worker stops it
        # there) until this much wall time after its receipt: only a worker that does not
        # answer at all (stopped, hung in native code) costs the frame its answer.
        self.frame_hang_ms = max(frame_hang_ms, frame_budget_ms)
        self._tickets = itertools.count(1)
        # Stream frames in a worker at once (0: no limit; see the module's docstring). Each
        # dispatched frame holds a slot of its worker until its result comes back (or it is
        # answered otherwise: time budget, worker death); sessions whose worker is full queue.
        self.worker_queue = worker_queue
        # Turns of a full worker's waiting sessions, earliest deadline first (module docstring):
        # a tracked session is due live_gap_s after its last frame, a relocalizing one
        # cold_gap_s after it began to wait; track_gap_s is the engine's max_frame_gap_s
        # (a longer gap relocalizes).
        self.live_gap_s = live_gap_s
        self.cold_gap_s = cold_gap_s
        self.track_gap_s = track_gap_s
        # The most of a worker's time relocalizing frames take while its tracked sessions wait
        # (module docstring; 1: no cap). ``_owed``: the worker's time (ms) its tracked sessions
        # are owed before the next relocalizing frame's turn, while any of them waits.
        self.relocalize_share = relocalize_share
        self._owed: dict[int, float] = {}  # worker -> ms
        self._slots: dict[int, int] = {}  # ticket -> worker
        self._cold: set[int] = set()  # tickets of frames sent as ones that relocalize
        self._in_worker: dict[int, int] = {}  # worker -> slots held
        self._waiting: dict[int, deque[Session]] = {}  # worker -> sessions in turn
        self.late_results = 0  # results that came after their frame was answered otherwise
        self._late_log = LogLimiter(log, "frame_over_budget")  # an overload must not flood
        self._lock = threading.Lock()
        self._by_key: dict[tuple[str, str, str], Session] = {}
        self._by_sid: dict[int, Session] = {}
        self._sid = itertools.count(1)
        self._idle = threading.Condition(self._lock)  # notified when a session stops being busy
        self.draining = False  # shutting down: no new frames, no more pending dispatches
        # (event, perf_counter, ...) rows while TIMELINE_ENV is set (deque.append is atomic);
        # the newest TIMELINE_ROWS only: a server left recording must not grow without bound
        self.timeline: deque[tuple[Any, ...]] | None = (
            deque(maxlen=TIMELINE_ROWS) if os.environ.get(TIMELINE_ENV) else None
        )

    def write_timeline(self) -> str | None:
        """The recorded timeline (``TIMELINE_ENV``) as JSON lines in that directory; its path."""
        folder = os.environ.get(TIMELINE_ENV)
        if self.timeline is None or not folder:
            return None
        os.makedirs(folder, exist_ok=True)
        path = os.path.join(folder, f"timeline-{os.getpid()}.jsonl")
        with open(path, "w") as f:
            for row in list(self.timeline):
                f.write(json.dumps(row) + "\n")
        return path

    # ------------------------------------------------------------------ intake
    def submit(
        self,
        map_name: str,
        client_id: str,
        transport: str,
        frame: Frame,
        t_recv: float,
        make_sink: Callable[[], Sink],
        key_suffix: str = "",
        _retry: bool = True,
    ) -> Session:
        """Hand a validated frame to its session (created on first use). Raises for what the
        client must hear about before any engine work: unknown map, bad camera, overload."""
        if self.draining:
            from ..errors import UnavailableError

            raise UnavailableError("the server is shutting down")
        entry = self.registry.get(map_name)  # MapNotFoundError
        if _retry:  # once per frame
            self.metrics.frames_in.inc(map_name, transport)
        key = (map_name, client_id, transport + key_suffix)
        replaced = None
        with self._lock:
            s = self._by_key.get(key)
            if s is not None and frame.source != s.source:
                if time.monotonic() - s.last_seen < SOURCE_TAKEOVER_S:
                    raise PermissionDeniedError(
                        f"client id {client_id!r} on map {map_name!r} is in use by another sender; "
                        "give each device its own client id"
                    )
                replaced, s = s, None  # the old sender went quiet (e.g. a device restarted)
            if s is None:
                s = self._open(key, map_name, client_id, transport, make_sink, frame.source)
            s.last_seen = time.monotonic()
            s.frames += 1
        if replaced is not None:
            self.close(replaced, "replaced")
        if s.camera != frame.camera:
            validate_camera(frame.camera, self.max_image_pixels)
            s.camera = frame.camera
        with self._lock:
            closed = s.closed
            if closed and not _retry:  # closed twice in a row around this frame: counted
                s.dropped += 1
                self.metrics.frames_dropped.inc(map_name)
                return s
        if closed:
            # The session ended (map unloaded, drain, reset, expiry) between its lookup and
            # here: the frame goes to the key's next session, or its map's or the server's
            # error is raised to the client, instead of vanishing with the closed one.
            return self.submit(
                map_name, client_id, transport, frame, t_recv, make_sink, key_suffix, False
            )
        with self._lock:
            if self.timeline is not None:
                self.timeline.append(("recv", t_recv, s.sid, frame.seq, s.busy, s.waiting))
            if s.busy or s.waiting:
                if len(s.pending) >= self.max_pending:
                    old = s.pending.popleft()  # the stalest waiting frame makes room
                    s.dropped += 1
                    self.metrics.frames_dropped.inc(map_name)
                    if self.timeline is not None:
                        self.timeline.append(
                            ("drop", time.perf_counter(), s.sid, old.frame.seq, frame.seq)
                        )
                s.pending.append(_Pending(frame, t_recv))
                return s
            if not self._has_room(s.worker):
                s.pending.append(_Pending(frame, t_recv))
                self._wait(s)
                return s
            ticket = self._start(s, _Pending(frame, t_recv))
        self._dispatch(s, frame, entry.generation, ticket)
        return s

    # ------------------------------------------------------------------ worker slots
    # (all of these: the caller holds self._lock)
    def _has_room(self, worker: int) -> bool:
        return not self.worker_queue or self._in_worker.get(worker, 0) < self.worker_queue

    def _start(self, s: Session, p: _Pending) -> int:
        """``s``'s frame ``p`` goes to its worker: the session is busy, the frame holds a slot
        of the worker; its ticket."""
        s.busy = True
        s.inflight_t_recv[p.frame.seq] = p.t_recv
        cold = not self._tracks(s, p.frame)
        s.last_t_recv, s.last_stamp_ns = p.t_recv, p.frame.stamp_ns
        ticket = s.ticket = next(self._tickets)
        if cold:
            self._cold.add(ticket)
        self._slots[ticket] = s.worker
        self._in_worker[s.worker] = self._in_worker.get(s.worker, 0) + 1
        if self.timeline is not None:
            self.timeline.append(
                ("start", time.perf_counter(), s.sid, p.frame.seq, s.worker, ticket, cold)
            )
        return ticket

    def _free(self, ticket: int) -> None:
        self._cold.discard(ticket)
        w = self._slots.pop(ticket, None)
        if w is not None:
            self._in_worker[w] -= 1

    def _free_worker(self, worker: int) -> None:
        """A dead worker's slots (its frames are answered by the caller)."""
        for t in [t for t, w in self._slots.items() if w == worker]:
            del self._slots[t]
            self._cold.discard(t)
        self._in_worker[worker] = 0
        self._owed.pop(worker, None)  # a replacement starts even

    def _unqueue(self, worker: int) -> None:
        """Empty ``worker``'s queue (it died): its sessions that still have frames and live on
        another worker now queue there; the others' frames go with them (the caller)."""
        for s in self._waiting.pop(worker, ()):
            s.waiting = False
            if s.pending and not s.closed and s.worker != worker:
                self._wait(s)

    def _wait(self, s: Session) -> None:
        """``s`` (pending frames, none in a worker) queues for its worker."""
        if not s.waiting:
            s.waiting = True
            s.wait_since = s.pending[-1].t_recv if s.pending else time.perf_counter()
            self._waiting.setdefault(s.worker, deque()).append(s)

    def _tracks(self, s: Session, frame: Frame) -> bool:
        """Whether ``s``'s ``frame`` will track (after ``s``'s last frame sent), as the engine
        decides it: by the frames' stamps. Otherwise it relocalizes."""
        return (
            s.last_t_recv is not None
            and not s.handover
            and s.last_status in _POSED
            and 0 <= frame.stamp_ns - s.last_stamp_ns <= self.track_gap_s * 1e9
        )

    def _deadline(self, s: Session) -> float:
        """When ``s``'s waiting frame is due (module docstring): soon after its last frame if
        it will track, later if it will relocalize. Sessions without a frame to send go first
        (they are skipped at once)."""
        if s.closed or s.busy or not s.pending:
            return float("-inf")
        if self._live(s):
            assert s.last_t_recv is not None
            return s.last_t_recv + self.live_gap_s
        return s.wait_since + self.cold_gap_s

    def _live(self, s: Session) -> bool:
        """Whether ``s``'s waiting frame takes its turn as a tracked one: it will track, and
        the last one sent as one that would did. A session whose tracked frames relocalize
        anyway (served too seldom to track, as on a machine whose CPU is mostly taken) costs a
        relocalization per turn: kept first among the tracked, a few such sessions took every
        turn while the others waited (starved on a simulated clock: worst client 0.1 poses/s
        beside 1.8; demoted, 0.3-1.1, as with deadlines alone)."""
        return bool(s.pending) and not s.track_failed and self._tracks(s, s.pending[-1].frame)

    def _next_turn(self, q: deque[Session], worker: int) -> Session | None:
        """Take the session with the earliest deadline out of a worker's queue (the first
        queued among equals). With a relocalization share (``relocalize_share`` < 1), a
        relocalizing one waits behind every tracked one that waits while the worker owes its
        tracked sessions time (``_owed``: it relocalized lately), and never goes while another
        relocalizing frame is in the worker (a tracked frame would wait behind two in its
        pipe): None when only such sessions wait."""
        capped = self.relocalize_share < 1
        owed = capped and self._owed.get(worker, 0.0) > 0
        if owed and not any(self._live(s) for s in q if not s.closed and not s.busy):
            owed = False  # no tracked frame waits: the worker does not idle for it
        cold_in = capped and any(self._slots.get(t) == worker for t in self._cold)
        best, due = -1, float("inf")
        for i, s in enumerate(q):
            d = self._deadline(s)
            if (owed or cold_in) and d != float("-inf") and not self._live(s):
                continue
            if best < 0 or d < due:
                best, due = i, d
        if best < 0:
            return None
        s = q[best]
        del q[best]
        return s

    def _charge(self, worker: int, relocalized: bool, ms: float) -> None:
        """Account ``ms`` of ``worker``'s time to a relocalizing frame (its tracked sessions
        are owed ``ms * (1 - share) / share`` before the next one) or to a tracked one (paid
        off). Neither adds up: relocalizations back to back while no tracked frame waited (a
        burst of new sessions) leave one relocalization's due, not the burst's, and a quiet
        spell banks no credit for a burst later."""
        share = self.relocalize_share
        if share >= 1 or not self.worker_queue:
            return
        owed = self._owed.get(worker, 0.0)
        if relocalized:
            self._owed[worker] = max(owed, ms * (1.0 - share) / share)
        else:
            self._owed[worker] = max(0.0, owed - ms)

    def _take_turns(self) -> builtins.list[tuple[Session, _Pending, int]]:
        """The frames that go on now: while a worker has room, its longest-waiting session's
        next pending frame (the newest one, with latest-frame-only). The caller dispatches
        them (``_dispatch_all``) once it released the lock."""
        out: builtins.list[tuple[Session, _Pending, int]] = []
        if not self.worker_queue:
            return out
        progress = True
        while progress:  # again when a session moved to another worker's queue
            progress = False
            for w, q in list(self._waiting.items()):
                while q and self._has_room(w):
                    s = self._next_turn(q, w)
                    if s is None:  # only relocalizing sessions wait, and one is in the worker
                        break
                    s.waiting = False
                    progress = True
                    if s.closed or s.busy or not s.pending:
                        continue
                    if s.worker != w:  # moved to another worker meanwhile: wait there
                        self._wait(s)
                        continue
                    if self.draining:
                        s.dropped += len(s.pending)
                        self.metrics.frames_dropped.inc(s.map, value=len(s.pending))
                        s.pending.clear()
                        continue
                    p = s.pending.popleft()
                    out.append((s, p, self._start(s, p)))
        return out

    def _dispatch_all(self, items: builtins.list[tuple[Session, _Pending, int]]) -> None:
        while items:
            for s, p, ticket in items:
                entry = self.registry.find(s.map)
                if entry is None:
                    self._reject_pending(s, p, ticket)
                else:
                    self._dispatch(s, p.frame, entry.generation, ticket)
            if not self.worker_queue:
                return
            with self._lock:  # a rejected frame or a dead worker's slot made room
                items = self._take_turns()

    def _open(
        self,
        key: tuple[str, str, str],
        map_name: str,
        client_id: str,
        transport: str,
        make_sink: Callable[[], Sink],
        source: str = "",
    ) -> Session:
        if len(self._by_key) >= self.max_sessions:
            raise OverloadError(
                f"the server is at its limit of {self.max_sessions} sessions; retry later"
            )
        per_worker = [0] * self.pool.n
        for other in self._by_sid.values():
            per_worker[other.worker] += 1
        inflight = self.pool.inflight()
        live = [i for i in range(self.pool.n) if self.pool.is_alive(i)] or list(range(self.pool.n))
        worker = min(live, key=lambda i: (per_worker[i], inflight[i], i))
        s = Session(
            next(self._sid), map_name, client_id, transport, key, worker, make_sink(), source=source
        )
        self._by_key[key] = s
        self._by_sid[s.sid] = s
        self.metrics.sessions_opened.inc(map_name, transport)
        if self.timeline is not None:
            self.timeline.append(("open", time.perf_counter(), s.sid, client_id, worker))
        event(
            log,
            logging.INFO,
            "session_open",
            map=map_name,
            client=client_id,
            transport=transport,
            sid=s.sid,
            worker=worker,
        )
        return s

    def _dispatch(self, s: Session, frame: Frame, gen: int, ticket: int) -> None:
        """Send ``frame`` (started with ``_start``: ``ticket``) to ``s``'s worker."""
        if not self.pool.is_alive(s.worker):
            waiting: builtins.list[tuple[int, int]] = []  # (seq, stamp_ns)
            with self._lock:
                if s.ticket != ticket:
                    return  # answered meanwhile (its worker's death, its time budget): once
                target = self._live_worker(exclude=s.worker)
                if target is None:  # every worker is down: answer now rather than never
                    s.busy = False
                    s.ticket = 0
                    s.errors += 1
                    s.inflight_t_recv.pop(frame.seq, None)
                    self._free(ticket)
                    # Frames that came since it started wait for it: nothing would send them
                    # on (on_worker_dead has run), and a lockstep client sends no next frame.
                    waiting = [(p.frame.seq, p.frame.stamp_ns) for p in s.pending]
                    s.errors += len(waiting)
                    s.pending.clear()
                    self._idle.notify_all()
                else:
                    s.worker = target
                    s.handover = True  # its state was on the dead worker
                    if ticket in self._slots:  # the slot moves with it
                        self._free(ticket)
                        self._slots[ticket] = target
                        self._in_worker[target] = self._in_worker.get(target, 0) + 1
            if target is None:
                self._answer_unavailable(
                    s,
                    [(frame.seq, frame.stamp_ns), *waiting],
                    "no engine worker is running (one is restarting); retry",
                )
                return
        deadline = 0.0
        with self._lock:
            if self.frame_budget_ms:
                t_recv = s.inflight_t_recv.get(frame.seq, time.perf_counter())
                # t_recv is perf_counter (CLOCK_MONOTONIC on Linux, like time.monotonic, but
                # not promised): the deadline is taken as an age, in the worker's clock.
                age = time.perf_counter() - t_recv
                deadline = time.monotonic() + self.frame_budget_ms / 1e3 - age
        prior = frame.prior  # the client's own estimate comes first
        if prior is None and s.handover and s.last_pose is not None:
            if time.monotonic() - s.last_pose_t <= HANDOVER_MAX_AGE_S:
                # Moved: its state stayed on the old worker. Around its last pose the new one
                # finds it in about half the CPU of global matching (synthetic room, nice 19:
                # median 67 vs 165 ms), so the frames queued behind it wait that much less.
                prior = s.last_pose
        self.pool.submit_frame(
            s.worker,
            LocalizeFrame(
                s.sid,
                s.map,
                gen,
                frame.seq,
                frame.stamp_ns,
                camera_tuple(frame.camera),
                frame.encoding,
                ticket,
                deadline,
                self.frame_cpu_budget_ms,
                prior,
                bytes(frame.data),
            ),
        )

    # ------------------------------------------------------------------ results
    def on_result(self, msg: Result) -> None:
        """A worker finished a frame (called on the pool's pump thread)."""
        now = time.perf_counter()
        turns: builtins.list[tuple[Session, _Pending, int]] = []
        with self._lock:
            ran_on = self._slots.get(msg.ticket)  # the worker it was sent to
            sent_cold = msg.ticket in self._cold
            res = msg.posed
            relocalized = (  # what its work was, as the worker did it
                sent_cold
                or res is None
                or res.status != Status.TRACKING.value
                or res.matching == Matching.GLOBAL.value
            )
            if ran_on is not None:
                self._charge(ran_on, relocalized, msg.worker_ms)
            if self.timeline is not None:
                self.timeline.append(
                    (
                        "res",
                        now,
                        msg.sid,
                        msg.seq,
                        ran_on,
                        msg.ticket,
                        None if res is None else res.status,
                        None if res is None else res.matching,
                        msg.worker_ms,
                        msg.decode_ms,
                        None if res is None else res.engine_ms,
                        relocalized,
                    )
                )
            self._free(msg.ticket)  # its worker has room again, whatever became of the frame
            s = self._by_sid.get(msg.sid)
            if s is not None and msg.ticket and msg.ticket != s.ticket:
                # Its frame was answered already (its time budget passed, or its worker was
                # declared dead): answering again would be a second answer, and late.
                self.late_results += 1
                s = None
            if s is not None:  # None: closed meanwhile, or late
                s.ticket = 0
                s.track_failed = relocalized and not sent_cold
                t_recv = s.inflight_t_recv.pop(msg.seq, now)
                s.busy = False
                if s.pending:
                    if self.draining or s.closed:
                        s.dropped += len(s.pending)
                        self.metrics.frames_dropped.inc(s.map, value=len(s.pending))
                        s.pending.clear()
                    elif self.worker_queue:
                        self._wait(s)  # behind the sessions that waited already: in turn
                    else:
                        nxt = s.pending.popleft()
                        turns.append((s, nxt, self._start(s, nxt)))
                latency_ms = (now - t_recv) * 1e3
                s.processed += 1
                s.last_latency_ms = latency_ms
                s.latency_sum_ms += latency_ms
                if res is not None:
                    s.last_status = res.status
                    s.localized += res.status != Status.LOST
                    if res.status != Status.LOST and res.cam_from_world is not None:
                        s.last_pose, s.last_pose_t = res.cam_from_world, time.monotonic()
                        if ran_on == s.worker:  # not the old worker's last frame after a move
                            s.handover = False  # its worker holds its state now
                else:
                    s.errors += 1
                    s.last_status = Status.LOST.value
                dropped = s.dropped
            if self.worker_queue:
                turns += self._take_turns()
            if s is not None and not s.busy:
                self._idle.notify_all()
        self._dispatch_all(turns)  # the next frames first: the worker is idle meanwhile
        if s is None:
            return
        if res is not None:
            self.metrics.frames_done.inc(s.map, res.status)
            self.metrics.engine_latency.observe(s.map, value=res.engine_ms / 1e3)
        self.metrics.latency.observe(s.map, value=latency_ms / 1e3)
        if msg.pose_wire and res is not None:
            self._send_encoded(s, msg, latency_ms, dropped)
            return
        pose = self._pose(s, msg, latency_ms, dropped)
        if res is None:
            self.metrics.frame_errors.inc(s.map, pose.error.code if pose.error else "INTERNAL")
        self._send(s, pose)

    def _send_encoded(self, s: Session, msg: Result, latency_ms: float, dropped: int) -> None:
        """Publish a pose the worker encoded (``Result.pose_wire``) with the server's fields
        (the same bytes ``encode_pose`` writes): a sink that publishes pose messages takes the
        bytes; another (gRPC, ROS 2) gets them decoded."""
        data = encode_pose_entries(
            msg.pose_wire,
            seq=msg.seq,
            stamp_ns=msg.stamp_ns,
            latency_ms=latency_ms,
            dropped=dropped,
            map_name=s.map,
            client_id=s.client_id,
            build_id=msg.build_id,  # the build the frame ran on, as in _pose
            server_id=self.server_id,
        )
        self._send(s, data)

    def _reject_pending(self, s: Session, p: _Pending, ticket: int) -> None:
        from ..errors import MapNotFoundError

        with self._lock:
            self._free(ticket)
            if s.ticket == ticket:
                s.ticket = 0
            s.busy = False
            s.inflight_t_recv.pop(p.frame.seq, None)
            self._idle.notify_all()
        self._send(
            s,
            self.error_pose(
                s.map,
                s.client_id,
                p.frame.seq,
                p.frame.stamp_ns,
                MapNotFoundError(f"map {s.map!r} was unloaded"),
                dropped=s.dropped,
            ),
        )

    def _send(self, s: Session, pose: PoseMessage | bytes) -> None:
        """``pose`` to the session's sink; bytes (an encoded pose message) to its
        ``send_encoded`` where it has one, else decoded."""
        try:
            if not isinstance(pose, bytes):
                s.sink.send(pose)
            elif (send_encoded := getattr(s.sink, "send_encoded", None)) is not None:
                send_encoded(pose)
            else:
                s.sink.send(decode_pose(pose))
        except Exception as exc:  # noqa: BLE001 - a broken sink ends that session only
            event(
                log, logging.WARNING, "sink_failed", map=s.map, client=s.client_id, error=str(exc)
            )

    def _pose(self, s: Session, msg: Result, latency_ms: float, dropped: int) -> PoseMessage:
        # The build the frame ran on, as the worker says: a frame in flight while its map was
        # replaced keeps the old build id (the registry's current entry would be the new one).
        return pose_message(
            msg.pose,
            msg.error,
            seq=msg.seq,
            stamp_ns=msg.stamp_ns,
            map_name=s.map,
            client_id=s.client_id,
            build_id=msg.build_id,
            server_id=self.server_id,
            latency_ms=latency_ms,
            dropped=dropped,
        )

    def _answer_unavailable(
        self, s: Session, frames: builtins.list[tuple[int, int]], message: str
    ) -> None:
        """Answer each (seq, stamp_ns) of ``s`` with an UNAVAILABLE error pose (a worker's
        death), counted in the metric as the caller counted it in ``s.errors``."""
        from ..errors import UnavailableError

        for seq, stamp_ns in frames:
            self.metrics.frame_errors.inc(s.map, "UNAVAILABLE")
            self._send(
                s,
                self.error_pose(
                    s.map,
                    s.client_id,
                    seq,
                    stamp_ns,
                    UnavailableError(message),
                    dropped=s.dropped,
                ),
            )

    def error_pose(
        self,
        map_name: str,
        client_id: str,
        seq: int | None,
        stamp_ns: int,
        exc: BaseException,
        dropped: int = 0,
    ) -> PoseMessage:
        info: ErrorInfo = error_info(exc)
        return PoseMessage(
            seq=seq,
            stamp_ns=stamp_ns,
            status=Status.LOST.value,
            map=map_name,
            client_id=client_id,
            server_id=self.server_id,
            dropped=dropped,
            message=info.message,
            error=info,
        )

    def count_error(self, map_name: str, exc: BaseException) -> None:
        # Names of maps we do not host come from clients: one label for all of them, so that
        # garbage cannot grow the metrics without bound.
        label = map_name if self.registry.find(map_name) is not None else UNKNOWN_MAP
        self.metrics.frame_errors.inc(label, error_info(exc).code)

    # ------------------------------------------------------------------ management
    def close(self, s: Session, reason: str, answer_inflight: Exception | None = None) -> None:
        """End a session. With ``answer_inflight``, the frames it has in a worker are answered
        with that error now (their results will find no session)."""
        with self._lock:
            if s.closed:
                return
            s.closed = True
            if self._by_key.get(s.key) is s:  # a replacement may hold the key already
                del self._by_key[s.key]
            self._by_sid.pop(s.sid, None)
            inflight = list(s.inflight_t_recv) if answer_inflight is not None else []
            s.inflight_t_recv.clear()
            s.busy = False
            # Frames waiting for their turn (a worker queue) are answered with the in-flight
            # ones, else counted dropped: never silent.
            if answer_inflight is not None:
                inflight += [p.frame.seq for p in s.pending]
            elif s.pending:
                s.dropped += len(s.pending)
                self.metrics.frames_dropped.inc(s.map, value=len(s.pending))
            s.pending.clear()
            self._idle.notify_all()
        self.pool.close_session(s.worker, s.sid)
        for seq in inflight:
            assert answer_inflight is not None
            self._send(s, self.error_pose(s.map, s.client_id, seq, 0, answer_inflight))
        try:
            s.sink.close()
        except Exception:  # noqa: BLE001
            pass
        self.metrics.sessions_closed.inc(s.map, reason)
        event(
            log,
            logging.INFO,
            "session_close",
            map=s.map,
            client=s.client_id,
            transport=s.transport,
            sid=s.sid,
            reason=reason,
            frames=s.frames,
            processed=s.processed,
            localized=s.localized,
            dropped=s.dropped,
            errors=s.errors,
            mean_latency_ms=round(s.mean_latency_ms, 2),
        )

    def close_map(self, map_name: str, reason: str = "map_unloaded") -> int:
        """End the sessions of an unloaded map; the frames they had in a worker are answered
        NOT_FOUND (their results would find no session). A client that keeps sending gets
        NOT_FOUND per frame, and a fresh session once the map is loaded again."""
        from ..errors import MapNotFoundError

        with self._lock:
            victims = [s for s in self._by_sid.values() if s.map == map_name]
        for s in victims:
            self.close(
                s, reason, answer_inflight=MapNotFoundError(f"map {map_name!r} was unloaded")
            )
        return len(victims)

    def reset(self, client_id: str, map_name: str = "") -> bool:
        with self._lock:
            hits = [
                s
                for s in self._by_sid.values()
                if s.client_id == client_id and (not map_name or s.map == map_name)
            ]
        for s in hits:
            self.pool.reset_session(s.worker, s.sid)
            event(log, logging.INFO, "session_reset", map=s.map, client=s.client_id, sid=s.sid)
        return bool(hits)

    def list(self, map_name: str = "") -> list[Session]:
        with self._lock:
            return sorted(
                (s for s in self._by_sid.values() if not map_name or s.map == map_name),
                key=lambda s: (s.map, s.client_id, s.sid),
            )

    def expire_idle(self, now: float | None = None) -> int:
        """End Zenoh sessions without frames for ``idle_timeout_s`` (gRPC ones end with their
        stream)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            idle = [
                s
                for s in self._by_sid.values()
                if s.transport == "zenoh"
                and not s.busy
                and not s.pending  # waiting for its turn: not idle (its frame is answered)
                and now - s.last_seen > self.idle_timeout_s
            ]
        for s in idle:
            self.close(s, "idle")
        return len(idle)

    def expire_late(self, now: float | None = None) -> int:
        """Answer DEADLINE_EXCEEDED each frame still waiting for its worker past its time
        budget (``frame_budget_ms``), or in the works past ``frame_hang_ms`` (its worker does
        not answer: stopped, stuck), both counted from its receipt, and send the session's next
        frame on: a late or stuck frame costs its client that frame, never the ones behind it.
        The frame's own result, if it comes, is dropped (its ticket is no longer the session's).
        Returns the frames answered."""
        if not self.frame_budget_ms:
            return 0
        from ..errors import DeadlineExceededError

        now = time.perf_counter() if now is None else now
        limit = self.frame_budget_ms / 1e3
        hang = self.frame_hang_ms / 1e3
        late: builtins.list[tuple[Session, int, bool]] = []  # (session, seq, hung)
        resume: builtins.list[tuple[Session, _Pending, int]] = []
        with self._lock:
            for s in self._by_sid.values():
                if s.waiting:  # queued for a full worker: its frames may have waited too long
                    while s.pending and now - s.pending[0].t_recv > limit:
                        late.append((s, s.pending.popleft().frame.seq, False))
                    continue
                if not s.busy or not s.inflight_t_recv:
                    continue
                seq, t_recv = next(iter(s.inflight_t_recv.items()))
                if now - t_recv <= limit:
                    continue
                started = self.pool.started(s.worker, s.ticket)
                if started and now - t_recv <= hang:
                    # In the works: its CPU budget bounds it. Answering now would throw the
                    # CPU it has spent away and queue the next frame behind it on the same
                    # worker, late in its turn: under load (server niced, load 18-37) every
                    # frame of 519 of 934 short-lived clients went so, none localized.
                    continue
                s.inflight_t_recv.clear()
                # Its slot is freed with its answer: the frames behind go on at once, as
                # without a worker queue (they wait in the worker's pipe if it is still busy).
                self._free(s.ticket)
                s.ticket = 0
                s.busy = False
                late.append((s, seq, started))
                while s.pending and now - s.pending[0].t_recv > limit:
                    late.append((s, s.pending.popleft().frame.seq, False))  # late: answered too
                if s.pending and not self.draining:
                    if self.worker_queue:
                        self._wait(s)
                    else:
                        nxt = s.pending.popleft()
                        resume.append((s, nxt, self._start(s, nxt)))
            if self.worker_queue and late:
                resume += self._take_turns()
            if late:
                self._idle.notify_all()
        for s, seq, hung in late:
            s.errors += 1
            self.metrics.frame_errors.inc(s.map, "DEADLINE_EXCEEDED")
            exc = DeadlineExceededError(
                f"its worker has not answered it {self.frame_hang_ms:.0f} ms after its receipt "
                "(stopped or stuck); the session goes on with the next frame"
                if hung
                else f"no answer within the frame's time budget of {self.frame_budget_ms:.0f} ms "
                "(the server is overloaded); the session goes on with the next frame"
            )
            if self._late_log.allow(s.client_id, "DEADLINE_EXCEEDED"):
                event(
                    log,
                    logging.WARNING,
                    "frame_over_budget",
                    map=s.map,
                    client=s.client_id,
                    sid=s.sid,
                    seq=seq,
                    worker=s.worker,
                )
            self._send(s, self.error_pose(s.map, s.client_id, seq, 0, exc, dropped=s.dropped))
        self._dispatch_all(resume)
        self._late_log.flush()
        return len(late)

    def _live_worker(self, exclude: int = -1) -> int | None:
        """The live worker with the fewest sessions (caller holds the lock)."""
        per_worker = [0] * self.pool.n
        for other in self._by_sid.values():
            if 0 <= other.worker < self.pool.n:
                per_worker[other.worker] += 1
        live = [i for i in range(self.pool.n) if i != exclude and self.pool.is_alive(i)]
        return min(live, key=lambda i: (per_worker[i], i)) if live else None

    def _rebalance_to(self, worker: int) -> builtins.list[tuple[int, int]]:
        """Move sessions from the live worker holding the most to ``worker`` (a replacement)
        while it holds two more (caller holds the lock); ``(from, sid)`` of each. A dead
        worker's sessions all went to the survivors: without this, after a kill one worker
        would carry every stream (over its core at 8 clients x 30 Hz) and the replacement
        none. A moved session relocalizes on its next frame; a frame in flight finishes where
        it is (at most one per session), the next goes to ``worker``."""
        if not self.pool.is_alive(worker):
            return []
        moved: builtins.list[tuple[int, int]] = []
        while True:
            per = {i: 0 for i in range(self.pool.n) if self.pool.is_alive(i)}
            for s in self._by_sid.values():
                if s.worker in per:
                    per[s.worker] += 1
            src = max(per, key=lambda i: (per[i], -i))
            if per[src] - per[worker] < 2:
                return moved
            # The idle ones first (nothing in flight), then the longest-open.
            s = min(
                (s for s in self._by_sid.values() if s.worker == src),
                key=lambda s: (s.busy, s.sid),
            )
            s.worker = worker
            s.handover = True  # its state stays on src: its frames carry its last pose
            moved.append((src, s.sid))

    def on_worker_dead(self, worker: int) -> None:
        """A worker died: every frame it had gets an UNAVAILABLE error pose now, and its
        sessions move to a live worker at once (their next frame relocalizes there, around
        their last pose), so that no frame waits in silence for the restart.

        Its frames are found by the worker each was sent to (the ticket's slot), not by the
        session's worker: a session a replacement took over (``_rebalance_to``) may still
        have its last frame on the old worker. With no live worker to move to, the frames
        waiting for one are answered too: kept, they waited in silence until a replacement
        served (and on_worker_lost then dropped them without a word)."""
        with self._lock:
            on_it = {t for t, w in self._slots.items() if w == worker}
            hit = [
                s
                for s in self._by_sid.values()
                if s.worker == worker or (s.busy and s.ticket in on_it)
            ]
            lost: builtins.list[tuple[Session, int]] = []
            resume: builtins.list[tuple[Session, _Pending, int]] = []
            self._free_worker(worker)  # its frames are answered here
            self._unqueue(worker)
            target: int | None = None
            for s in hit:
                # Only a frame sent to it: a session moved here (``_rebalance_to``) while its
                # frame still ran on its old worker keeps that frame, which the old worker
                # answers with its pose (or whose own death answers it). A busy session's
                # ticket always holds a slot (``_start``; freed only with its answer).
                if s.busy and s.ticket in on_it:
                    lost += [(s, seq) for seq in s.inflight_t_recv]
                    s.inflight_t_recv.clear()
                    s.busy = False
                    s.ticket = 0
                if s.worker == worker:
                    target = self._live_worker(exclude=worker)
                    s.handover = True  # no worker holds its state now
                    if target is not None:
                        s.worker = target
                else:
                    target = s.worker if self.pool.is_alive(s.worker) else None
                if not s.pending or s.busy or s.waiting:
                    continue
                if target is None:
                    lost += [(s, p.frame.seq) for p in s.pending]
                    s.pending.clear()
                    continue
                nxt = s.pending.pop()  # the newest waiting frame goes on, on the new worker
                if s.pending:
                    s.dropped += len(s.pending)
                    self.metrics.frames_dropped.inc(s.map, value=len(s.pending))
                    s.pending.clear()
                if self.worker_queue:
                    s.pending.append(nxt)
                    self._wait(s)
                else:
                    resume.append((s, nxt, self._start(s, nxt)))
            resume += self._take_turns()
            for s, _ in lost:
                s.errors += 1
            self._idle.notify_all()
        for s, seq in lost:
            self._answer_unavailable(
                s,
                [(seq, 0)],
                "the worker processing this frame died; the session goes on (worker "
                f"{s.worker}) and relocalizes"
                if self.pool.is_alive(s.worker)
                else "the worker processing this frame died and no other engine worker "
                "is running (one is restarting); retry",
            )
        self._dispatch_all(resume)
        event(
            log,
            logging.WARNING,
            "worker_sessions_moved",
            worker=worker,
            sessions=len(hit),
            to=sorted({s.worker for s in hit if s.worker != worker}),
            frames_answered=len(lost),
        )

    def on_worker_lost(self, worker: int) -> None:
        """A worker's replacement serves (it holds no session's state): sessions move to it
        until the workers are balanced again. Everything the dead worker had was answered by
        ``on_worker_dead`` when it died; sessions found on it now live there from now on
        (moved there since it serves, or left there when no worker was alive), with frames
        that are theirs to keep."""
        with self._lock:
            moved = self._rebalance_to(worker)
        for src, sid in moved:  # after the frame it may have in flight there
            self.pool.close_session(src, sid)
        if moved:
            event(log, logging.INFO, "sessions_rebalanced", worker=worker, sessions=len(moved))

    # builtins.list: inside this class `list` is the method below
    def wait_idle(self, timeout: float, sessions: builtins.list[Session] | None = None) -> bool:
        """Wait until no session (or none of ``sessions``) has a frame in a worker."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while True:
                pool = sessions if sessions is not None else list(self._by_sid.values())
                if not any(s.busy for s in pool):
                    return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._idle.wait(left)

    def counts_by_map(self) -> dict[tuple[str, ...], float]:
        out: dict[tuple[str, ...], float] = {}
        with self._lock:
            for s in self._by_sid.values():
                k = (s.map, s.transport)
                out[k] = out.get(k, 0) + 1
        return out

    def __len__(self) -> int:
        return len(self._by_sid)


def validate_camera(cam: Any, max_pixels: int) -> Camera:
    """A client's ``CameraSpec`` checked as the engine will use it (``CameraModelError``), and
    against the server's image size limit (``MessageTooLargeError``)."""
    from ..errors import MessageTooLargeError

    if cam.width * cam.height > max_pixels:
        raise MessageTooLargeError(
            f"a {cam.width}x{cam.height} camera exceeds this server's limit of {max_pixels} pixels "
            "per image"
        )
    return Camera(cam.model, cam.width, cam.height, np.asarray(cam.params, dtype=np.float64))
