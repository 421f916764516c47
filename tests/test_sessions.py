"""The session manager and the map registry against a fake pool (``fake_workers.FakePool``):
latest-frame-only intake, worker loss, and the generation swap of a replaced map. The test
plays the worker by calling ``on_result``; nothing waits on time."""

from __future__ import annotations

import threading

import pytest

from fake_workers import FakePool, ListSink, pose
from sfmloc.errors import BundleError, MapNotFoundError
from sfmloc.server import protocol as P
from sfmloc.server.maps import MapEntry, MapRegistry
from sfmloc.server.metrics import ServerMetrics
from sfmloc.server.sessions import SessionManager
from sfmloc_client.errors import MessageTooLargeError
from sfmloc_client.wire import CameraSpec, Frame

CAM = CameraSpec("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))


class _Registry:
    """The registry's read side with entries set by the test (the real one needs bundles)."""

    def __init__(self) -> None:
        self.entries: dict[str, MapEntry] = {}

    def set(self, name: str, gen: int, build_id: str) -> None:
        self.entries[name] = MapEntry(name, f"/maps/{name}", build_id, gen, 1, 1, 1, 1, 1.0, "")

    def find(self, name: str) -> MapEntry | None:
        return self.entries.get(name)

    def get(self, name: str) -> MapEntry:
        if name not in self.entries:
            raise MapNotFoundError(f"map {name!r} is not loaded on this server")
        return self.entries[name]


@pytest.fixture
def env():
    pool, reg = FakePool(n=2), _Registry()
    reg.set("room", 1, "build-1")
    sm = SessionManager(pool, reg, ServerMetrics(), server_id="srv", max_image_pixels=64 * 48)
    sinks: dict[str, ListSink] = {}

    def submit(client: str, seq: int, map_name: str = "room", camera: CameraSpec = CAM):
        frame = Frame(seq, seq * 1000, camera, "gray8", bytes(64 * 48))
        return sm.submit(
            map_name,
            client,
            "zenoh",
            frame,
            0.0,
            make_sink=lambda: sinks.setdefault(client, ListSink()),
        )

    return pool, reg, sm, sinks, submit


def _answer(sm: SessionManager, msg: P.LocalizeFrame, status: str = "TRACKING") -> None:
    """The worker's answer to ``msg`` (it ran on build ``build-<generation>``)."""
    sm.on_result(
        P.Result(
            msg.sid,
            msg.seq,
            msg.stamp_ns,
            msg.gen,
            f"build-{msg.gen}",
            pose(status),
            None,
            0.1,
            1.0,
            msg.ticket,
        )
    )


def test_latest_frame_only_one_in_the_worker_and_the_newest_waiting(env):
    pool, _, sm, sinks, submit = env
    s = submit("c", 0)
    for seq in (1, 2, 3):  # the worker is busy with frame 0: only the newest waits
        submit("c", seq)
    assert [m.seq for _, m in pool.frames] == [0]
    assert [p.frame.seq for p in s.pending] == [3] and s.dropped == 2
    _answer(sm, pool.frames[0][1])
    assert [m.seq for _, m in pool.frames] == [0, 3]  # the waiting frame went on at once
    _answer(sm, pool.frames[1][1])
    got = sinks["c"].poses
    assert [(p.seq, p.status, p.dropped) for p in got] == [(0, "TRACKING", 2), (3, "TRACKING", 2)]
    assert got[0].build_id == "build-1" and got[0].server_id == "srv" and got[0].map == "room"
    assert sm.wait_idle(0) and (s.frames, s.processed, s.localized) == (4, 2, 2)


def test_a_frame_past_its_budget_is_answered_and_its_late_result_is_dropped(env):
    """A frame stuck in its worker (starved, or a huge image) is answered DEADLINE_EXCEEDED
    once its budget (wall, from receipt) passes; the frame behind it goes on at once; the stuck
    frame's result, when it comes, is no second answer, even with the same seq (gRPC's 0)."""
    pool, _, sm, sinks, _ = env
    sink = ListSink()

    def send(t_recv: float) -> None:
        frame = Frame(7, 1000, CAM, "gray8", bytes(64 * 48))
        sm.submit("room", "c", "zenoh", frame, t_recv, make_sink=lambda: sink)

    budget = sm.frame_budget_ms / 1e3
    send(t_recv=100.0)
    send(t_recv=100.0 + budget - 0.1)  # waits behind the first
    ((_, stuck),) = pool.frames
    assert stuck.deadline > 0 and stuck.cpu_budget_ms == sm.frame_cpu_budget_ms
    assert sm.expire_late(now=100.0 + budget - 0.05) == 0 and not sink.poses
    assert sm.expire_late(now=100.0 + budget + 0.05) == 1
    assert [(p.seq, p.error.code) for p in sink.poses] == [(7, "DEADLINE_EXCEEDED")]
    assert "time budget" in sink.poses[0].message
    assert len(pool.frames) == 2  # the waiting frame went on, with its own ticket
    nxt = pool.frames[1][1]
    assert nxt.ticket != stuck.ticket
    _answer(sm, stuck, status="RELOCALIZED")  # the stuck frame's result, late
    assert len(sink.poses) == 1 and sm.late_results == 1
    _answer(sm, nxt)
    assert [(p.seq, p.status) for p in sink.poses[1:]] == [(7, "TRACKING")]
    assert sm.wait_idle(0)


def test_a_frame_in_the_works_is_left_to_its_cpu_budget_until_the_hang_limit(env):
    """A frame its worker has started is not answered at the budget (that threw its CPU away
    and queued the next frame behind it: under load every frame of most short-lived clients
    went so); its result, past the budget, is its answer. Only past ``frame_hang_ms`` (its
    worker stopped or stuck) is it answered DEADLINE_EXCEEDED."""
    pool, _, sm, sinks, submit = env
    budget, hang = sm.frame_budget_ms / 1e3, sm.frame_hang_ms / 1e3
    assert hang > budget
    submit("c", 0)  # at t=0
    submit("c", 1)  # waits behind it
    ((w, first),) = pool.frames
    pool.working[w] = first.ticket
    assert sm.expire_late(now=budget + 0.5) == 0 and not sinks["c"].poses  # in the works
    _answer(sm, first, status="RELOCALIZED")  # its result, late: the answer
    assert [(p.seq, p.status) for p in sinks["c"].poses] == [(0, "RELOCALIZED")]
    assert sm.late_results == 0
    # the waiting frame went on though its budget had passed (its worker will not work on it)
    assert [m.seq for _, m in pool.frames] == [0, 1]
    pool.working[w] = pool.frames[1][1].ticket
    _answer(sm, pool.frames[1][1])
    # a frame its worker never finishes: answered at the hang limit, not before
    submit("c", 2)
    third = pool.frames[2][1]
    pool.working[w] = third.ticket
    assert sm.expire_late(now=hang - 0.1) == 0
    assert sm.expire_late(now=hang + 0.1) == 1
    last = sinks["c"].poses[-1]
    assert (last.seq, last.error.code) == (2, "DEADLINE_EXCEEDED")
    assert "has not answered it" in last.message
    assert sm.wait_idle(0)


def test_frames_all_past_their_budget_are_all_answered(env):
    pool, _, sm, sinks, submit = env
    submit("c", 0)  # the fixture's frames arrive at t=0
    submit("c", 1)
    assert sm.expire_late(now=sm.frame_budget_ms / 1e3 + 1.0) == 2
    assert [(p.seq, p.error.code) for p in sinks["c"].poses] == [
        (0, "DEADLINE_EXCEEDED"),
        (1, "DEADLINE_EXCEEDED"),
    ]
    assert len(pool.frames) == 1 and sm.wait_idle(0)  # nothing was sent on: too old already


def test_sessions_spread_over_workers_and_other_clients_never_wait(env):
    pool, _, sm, sinks, submit = env
    a, b = submit("a", 0), submit("b", 0)
    assert {a.worker, b.worker} == {0, 1}
    submit("a", 1)  # a is busy: waits; b's next frame goes straight to its worker
    _answer(sm, pool.frames[1][1])
    submit("b", 1)
    assert [(w, m.sid, m.seq) for w, m in pool.frames] == [
        (a.worker, a.sid, 0),
        (b.worker, b.sid, 0),
        (b.worker, b.sid, 1),
    ]


def test_a_dead_worker_answers_its_frames_and_its_sessions_move_on(env):
    pool, _, sm, sinks, submit = env
    a, b = submit("a", 0), submit("b", 0)
    submit("a", 1)  # waits behind frame 0
    dead = a.worker
    pool.alive[dead] = False
    sm.on_worker_dead(dead)
    err = [p for p in sinks["a"].poses if p.error is not None]
    assert [(p.seq, p.error.code) for p in err] == [(0, "UNAVAILABLE")]
    assert a.worker == b.worker != dead  # moved to the live worker
    assert pool.frames[-1] == (a.worker, pool.frames[-1][1]) and pool.frames[-1][1].seq == 1
    assert not sinks.get("b", ListSink()).poses  # b was not touched
    _answer(sm, pool.frames[-1][1])
    assert sinks["a"].poses[-1].seq == 1 and sinks["a"].poses[-1].localized


def test_a_replacement_takes_back_sessions_until_the_workers_are_balanced(env):
    """After a worker died (its sessions moved to the survivor), its replacement gets sessions
    back: each moved session's state is freed on the old worker after what it has in flight
    there, and its next frame goes to the replacement."""
    pool, _, sm, sinks, submit = env
    sessions = [submit(f"c{i}", 0) for i in range(4)]
    for _, m in list(pool.frames):
        _answer(sm, m)
    dead = sessions[0].worker
    pool.alive[dead] = False
    sm.on_worker_dead(dead)
    assert {s.worker for s in sessions} == {1 - dead}  # all on the survivor
    busy = submit("c1", 1)  # a frame in flight on the survivor while the replacement comes
    pool.alive[dead] = True
    sm.on_worker_lost(dead)
    on = [sum(s.worker == w for s in sessions) for w in (0, 1)]
    assert on == [2, 2]
    moved = [s for s in sessions if s.worker == dead]
    assert sorted(pool.closed) == sorted((1 - dead, s.sid) for s in moved)
    assert busy not in moved  # the idle ones went first
    n = len(pool.frames)
    for s in moved:
        submit(s.client_id, 5)
    assert [w for w, _ in pool.frames[n:]] == [dead, dead]
    sm.on_worker_lost(dead)  # balanced: a second call moves nothing
    assert [sum(s.worker == w for s in sessions) for w in (0, 1)] == [2, 2]


def test_every_worker_dead_answers_the_frame_now(env):
    pool, _, sm, sinks, submit = env
    pool.alive = [False, False]
    submit("c", 0)
    assert not pool.frames
    assert [(p.seq, p.error.code) for p in sinks["c"].poses] == [(0, "UNAVAILABLE")]
    assert sm.wait_idle(0)


class _Window:
    """Runs ``then`` once, at the next ``is_alive`` of ``pool``: with the pool armed after the
    session exists, that is ``_dispatch``'s check, after ``_start`` let go of the lock (where
    another thread's frame, or a worker's death, can come in)."""

    def __init__(self, pool: FakePool, then) -> None:
        self.pool, self.then, self.fired = pool, then, False
        self.is_alive = pool.is_alive
        pool.is_alive = self  # type: ignore[method-assign]

    def __call__(self, worker: int) -> bool:
        if not self.fired:
            self.fired = True
            self.then()
        return self.is_alive(worker)


def test_a_frame_that_came_while_the_last_worker_was_found_dead_is_answered(env):
    """Frame 1 has started (the session is busy) when its dispatch finds no worker alive;
    frame 2 came meanwhile and waits for it: both are answered UNAVAILABLE, not frame 1 alone
    (frame 2 waited in silence until the session's next frame, never for a lockstep client)."""
    pool, _, sm, sinks, submit = env
    s = submit("c", 0)
    _answer(sm, pool.frames[-1][1])
    pool.alive = [False, False]  # both died; on_worker_dead has run (nothing was in them)
    _Window(pool, lambda: submit("c", 2))
    submit("c", 1)
    assert [(p.seq, p.error.code) for p in sinks["c"].poses[1:]] == [
        (1, "UNAVAILABLE"),
        (2, "UNAVAILABLE"),
    ]
    assert not s.pending and not s.busy and s.errors == 2 and sm.wait_idle(0)
    pool.alive = [True, True]  # a replacement serves: the session goes on
    submit("c", 3)
    _answer(sm, pool.frames[-1][1])
    assert [p.seq for p in sinks["c"].poses] == [0, 1, 2, 3]


def test_a_frame_its_dead_worker_answered_is_not_answered_again_by_its_dispatch(env):
    """The worker a frame was started for dies before its dispatch looks (the pool's reader
    thread answers it in on_worker_dead): the dispatch must not answer it a second time."""
    pool, _, sm, sinks, submit = env
    s = submit("c", 0)
    _answer(sm, pool.frames[-1][1])
    n = len(pool.frames)

    def dies() -> None:
        pool.alive = [False, False]
        sm.on_worker_dead(s.worker)

    _Window(pool, dies)
    submit("c", 1)
    assert [(p.seq, p.error.code) for p in sinks["c"].poses[1:]] == [(1, "UNAVAILABLE")]
    assert len(pool.frames) == n and not s.busy and s.errors == 1


def test_frames_follow_a_replaced_map_to_its_new_generation(env):
    pool, reg, sm, sinks, submit = env
    submit("c", 0)
    submit("c", 1)  # waits
    reg.set("room", 2, "build-2")  # the registry's swap
    _answer(sm, pool.frames[0][1])  # frame 0 ran on generation 1, which is no longer current
    assert [m.gen for _, m in pool.frames] == [1, 2]  # the waiting frame went to generation 2
    _answer(sm, pool.frames[1][1])
    # each pose names the build it was computed on
    assert [(p.seq, p.build_id) for p in sinks["c"].poses] == [(0, "build-1"), (1, "build-2")]


def test_unknown_map_and_oversized_camera_are_refused_before_any_work(env):
    pool, _, sm, _, submit = env
    with pytest.raises(MapNotFoundError, match="not loaded"):
        submit("c", 0, map_name="nope")
    with pytest.raises(MessageTooLargeError, match="exceeds"):
        submit("c", 0, camera=CameraSpec("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0)))
    assert not pool.frames


def test_an_unloaded_map_answers_its_frames_not_found_and_ends_its_sessions(env):
    pool, reg, sm, sinks, submit = env
    s = submit("c", 0)
    del reg.entries["room"]
    assert sm.close_map("room") == 1
    assert [(p.seq, p.error.code) for p in sinks["c"].poses] == [(0, "NOT_FOUND")]
    assert sinks["c"].closed and pool.closed == [(s.worker, s.sid)] and len(sm) == 0
    _answer(sm, pool.frames[0][1])  # its late result finds no session: nothing more is sent
    assert len(sinks["c"].poses) == 1


# ============================================================================ worker queue
def _queued(n: int):
    """A session manager with ``worker_queue=1`` (one frame per worker at once), ``n`` workers."""
    pool, reg = FakePool(n=n), _Registry()
    reg.set("room", 1, "build-1")
    sm = SessionManager(
        pool, reg, ServerMetrics(), server_id="srv", max_image_pixels=64 * 48, worker_queue=1
    )
    sinks: dict[str, ListSink] = {}

    def submit(client: str, seq: int, t_recv: float = 0.0):
        frame = Frame(seq, int(t_recv * 1e9), CAM, "gray8", bytes(64 * 48))  # stamped at receipt
        return sm.submit(
            "room",
            client,
            "zenoh",
            frame,
            t_recv,
            make_sink=lambda: sinks.setdefault(client, ListSink()),
        )

    return pool, sm, sinks, submit


@pytest.fixture
def queued():
    return _queued(2)


def _sent(pool: FakePool, worker: int) -> list[tuple[int, int]]:
    return [(m.sid, m.seq) for w, m in pool.frames if w == worker]


def test_a_full_worker_queues_its_sessions_and_they_take_turns_with_their_newest_frame(queued):
    pool, sm, sinks, submit = queued
    a, b, c, d = (submit(x, 0) for x in "abcd")  # a, c on one worker; b, d on the other
    w = a.worker
    assert c.worker == w and b.worker == d.worker != w
    assert _sent(pool, w) == [(a.sid, 0)]  # c waits in the server, not in the worker's pipe
    assert c.waiting and not c.busy
    submit("c", 1, t_recv=0.5)  # replaces c's waiting frame 0 (latest-frame-only)
    submit("a", 1, t_recv=0.95)  # a is busy: waits behind its frame 0
    assert [p.frame.seq for p in c.pending] == [1] and c.dropped == 1
    # a's frame 0 done: a's next frame will track (due 0.1), c's will relocalize (new: due
    # cold_gap_s = 1.0 after it began to wait at 0), so a goes first
    _answer(sm, pool.frames[0][1])
    assert _sent(pool, w) == [(a.sid, 0), (a.sid, 1)]
    submit("a", 2, t_recv=1.0)
    _answer(sm, pool.frames[-1][1])  # a is due at 1.05 now, after c: c's turn
    assert _sent(pool, w) == [(a.sid, 0), (a.sid, 1), (c.sid, 1)]
    assert a.waiting and [p.frame.seq for p in a.pending] == [2]
    submit("a", 3, t_recv=1.1)  # the newest of a goes on in its turn
    _answer(sm, pool.frames[-1][1])
    assert _sent(pool, w) == [(a.sid, 0), (a.sid, 1), (c.sid, 1), (a.sid, 3)] and a.dropped == 1
    _answer(sm, pool.frames[-1][1])
    assert [(p.seq, p.dropped) for p in sinks["a"].poses] == [(0, 0), (1, 0), (3, 1)]
    assert [p.seq for p in sinks["c"].poses] == [1]
    submit("c", 2)  # the worker is idle: straight to it
    assert _sent(pool, w)[-1] == (c.sid, 2) and c.busy and not c.waiting
    assert _sent(pool, b.worker) == [(b.sid, 0)]  # the other worker: b's frame, d waiting
    assert d.waiting


def test_a_session_that_tracks_goes_before_one_that_relocalizes_until_its_deadline(queued):
    """Turns of a full worker, earliest deadline first: a session whose frame will track (its
    last was posed, within the engine's frame gap) is due live_gap_s after its last frame; one
    whose frame will relocalize (new here) cold_gap_s after it began to wait. So c (new, waiting
    since t=0: due at 1.0) waits behind a's tracked frames until a's next one is due later."""
    pool, sm, sinks, submit = queued
    a = submit("a", 0, t_recv=0.0)
    submit("b", 0, t_recv=0.0)  # the other worker
    c = submit("c", 0, t_recv=0.0)
    w = a.worker
    assert c.worker == w and c.waiting
    t = 0.0
    for k in range(1, 60):  # a tracks at 30 Hz; each of its frames waits behind the last
        t = k / 30
        submit("a", k, t_recv=t)
        _answer(sm, [m for ww, m in pool.frames if ww == w][-1])
        if _sent(pool, w)[-1][0] == c.sid:
            break
    # a's frames went first while a was due before c: a's last frame before c's turn came
    # after 1.0 - live_gap_s; c's turn came then, not later
    assert _sent(pool, w)[-1] == (c.sid, 0)
    first_a = [seq for sid, seq in _sent(pool, w) if sid == a.sid]
    assert first_a == list(range(len(first_a)))  # every frame of a, newest each time
    due = [k / 30 + sm.live_gap_s for k in first_a[-2:]]  # a's two last deadlines
    assert due[0] < sm.cold_gap_s <= due[1]  # (a tie goes to the one queued first: c)
    assert c.dropped == 0 and [p.seq for p in sinks["c"].poses] == []
    _answer(sm, pool.frames[-1][1])  # c relocalized: c and a (both waiting) take turns now
    assert [p.seq for p in sinks["c"].poses] == [0]


def test_a_lost_or_stale_session_waits_as_one_that_relocalizes():
    pool, sm, sinks, submit = _queued(1)
    a = submit("a", 0, t_recv=0.0)
    c = submit("c", 0, t_recv=0.0)
    assert c.waiting
    _answer(sm, pool.frames[0][1], status="LOST")  # a lost its track; c's turn
    _answer(sm, pool.frames[-1][1])  # c posed (its first frame, t=0)
    assert [p.seq for p in sinks["c"].poses] == [0]
    submit("x", 0, t_recv=0.1)  # a third session holds the worker meanwhile
    submit("a", 1, t_recv=0.2)  # LOST: relocalizes, due 1.2
    submit("c", 1, t_recv=0.2)  # posed 0.2 s before: tracks, due 0.1
    assert a.waiting and c.waiting
    _answer(sm, pool.frames[-1][1])  # x done: c before a, which waited first
    assert _sent(pool, 0)[-2:] == [(3, 0), (c.sid, 1)]
    _answer(sm, pool.frames[-1][1])
    assert _sent(pool, 0)[-1] == (a.sid, 1)
    _answer(sm, pool.frames[-1][1])  # a posed now (at 0.2)
    # A posed session whose newest frame comes past the engine's frame gap (track_gap_s)
    # relocalizes: it waits as one that relocalizes, due cold_gap_s after it began to wait
    submit("x", 1, t_recv=5.0)  # x's frame holds the worker
    submit("c", 2, t_recv=5.0)  # c's last frame came at 0.2: 4.8 s, relocalizes (due 6.0)
    submit("a", 2, t_recv=0.25)  # a's last frame came at 0.2: tracks (due 0.3)
    assert c.waiting and a.waiting
    _answer(sm, pool.frames[-1][1])
    assert _sent(pool, 0)[-1] == (a.sid, 2)
    _answer(sm, pool.frames[-1][1])
    assert _sent(pool, 0)[-1] == (c.sid, 2)  # and c is not left behind


def test_a_session_waiting_for_its_turn_is_not_idle_and_a_closed_one_answers_its_frames():
    """A session whose frame waits for a full worker is not ended as idle (its frame would
    never be answered: client churn with a 1 s idle timeout lost first frames so); ending a
    waiting session answers its frames with the in-flight ones, or counts them dropped."""
    pool, sm, sinks, submit = _queued(1)
    submit("a", 0)
    b = submit("b", 0)
    assert b.waiting
    assert sm.expire_idle(now=b.last_seen + sm.idle_timeout_s + 5) == 0  # a busy, b waiting
    assert not b.closed and b.pending
    sm.close(b, "map_unloaded", answer_inflight=MapNotFoundError("map 'room' was unloaded"))
    assert [(p.seq, p.error.code) for p in sinks["b"].poses] == [(0, "NOT_FOUND")]
    c = submit("c", 0)
    assert c.waiting
    sm.close(c, "replaced")  # no answer to give: counted dropped, in its session_close
    assert c.dropped == 1 and not c.pending and not sinks["c"].poses


def test_a_frame_past_its_budget_frees_its_slot_once():
    """A stuck frame answered DEADLINE_EXCEEDED gives its worker's slot to the next session at
    once (as without a queue); its late result frees nothing more."""
    pool, sm, sinks, submit = _queued(1)
    budget = sm.frame_budget_ms / 1e3
    submit("a", 0, t_recv=100.0)
    b = submit("b", 0, t_recv=100.0 + budget)  # waits for the worker
    assert b.waiting
    assert sm.expire_late(now=100.0 + budget + 0.05) == 1  # a's frame
    stuck = pool.frames[0][1]
    assert _sent(pool, 0) == [(1, 0), (b.sid, 0)]  # b's went on at once
    c = submit("c", 0, t_recv=100.0 + budget)
    assert c.waiting  # b's frame holds the slot
    _answer(sm, stuck)  # late: no second answer, and it frees no slot (b's still holds it)
    assert sm.late_results == 1 and [p.seq for p in sinks["a"].poses] == [0]
    assert c.waiting and len(pool.frames) == 2
    _answer(sm, pool.frames[-1][1])  # b done: c's turn
    assert _sent(pool, 0)[-1] == (c.sid, 0)


def test_frames_waiting_for_a_full_worker_past_their_budget_are_answered(queued):
    pool, sm, sinks, submit = queued
    a = submit("a", 0, t_recv=100.0)
    submit("b", 0, t_recv=100.0)
    c = submit("c", 0, t_recv=100.0)
    assert c.worker == a.worker and c.waiting
    budget = sm.frame_budget_ms / 1e3
    sm.expire_late(now=100.0 + budget + 0.05)
    assert [(p.seq, p.error.code) for p in sinks["c"].poses] == [(0, "DEADLINE_EXCEEDED")]
    assert not c.pending


def test_a_dead_worker_s_queued_sessions_move_and_wait_for_the_survivor(queued):
    pool, sm, sinks, submit = queued
    a, b, c = submit("a", 0), submit("b", 0), submit("c", 0)
    dead = a.worker
    assert c.worker == dead and c.waiting and b.worker != dead
    submit("a", 1)
    pool.alive[dead] = False
    sm.on_worker_dead(dead)
    assert [(p.seq, p.error.code) for p in sinks["a"].poses] == [(0, "UNAVAILABLE")]
    assert a.worker == c.worker == b.worker
    # the survivor is busy with b's frame: a and c wait for it, nothing went to the dead one
    assert len(pool.frames) == 2 and a.waiting and c.waiting
    _answer(sm, pool.frames[1][1])  # b done: the sessions that waited take their turns
    _answer(sm, pool.frames[2][1])
    _answer(sm, pool.frames[3][1])
    assert sorted((m.sid, m.seq) for _, m in pool.frames[2:]) == [(a.sid, 1), (c.sid, 0)]
    assert all(w == b.worker for w, _ in pool.frames[1:])
    assert sm.wait_idle(0)


def test_a_session_closed_while_it_waits_is_skipped(queued):
    pool, sm, sinks, submit = queued
    a, _, c, _ = submit("a", 0), submit("b", 0), submit("c", 0), submit("d", 0)
    e = submit("e", 0)
    assert c.waiting and e.waiting and e.worker == a.worker
    sm.close(c, "test")
    _answer(sm, pool.frames[0][1])
    assert _sent(pool, a.worker) == [(a.sid, 0), (e.sid, 0)]


# ============================================================================ map registry
def test_registry_swaps_generations_in_one_step_and_drops_the_old_one(world):
    pool = FakePool()
    changes: list[tuple[str, int | None, int | None]] = []
    reg = MapRegistry(
        pool, on_change=lambda n, o, e: changes.append((n, o and o.generation, e and e.generation))
    )
    first = reg.load(world.maps_dir / "room")
    assert (first.name, first.generation) == ("room", 1) and pool.maps == {("room", 1): first.path}
    pool.loading[("room", 2)] = release = threading.Event()
    done: list[MapEntry] = []
    loader = threading.Thread(target=lambda: done.append(reg.load(world.room_rebuilt, "room")))
    loader.start()
    # While generation 2 loads on the workers, frames keep going to generation 1.
    assert reg.get("room") is first and not pool.dropped
    release.set()
    loader.join(30)
    second = done[0]
    assert second.generation == 2 and reg.get("room") is second
    assert second.build_id != first.build_id
    assert pool.dropped == [("room", 1)] and set(pool.maps) == {("room", 2)}
    assert changes == [("room", None, 1), ("room", 1, 2)]
    reg.unload("room")
    assert pool.dropped[-1] == ("room", 2) and changes[-1] == ("room", 2, None)
    with pytest.raises(MapNotFoundError, match="no maps are loaded"):
        reg.get("room")


def test_registry_refuses_a_corrupt_bundle_before_any_worker_sees_it(world):
    pool = FakePool()
    reg = MapRegistry(pool)
    with pytest.raises(BundleError, match="corrupt"):
        reg.load(world.corrupt)
    assert not pool.maps and reg.list() == []


def test_a_frame_whose_session_closes_as_it_arrives_goes_to_the_next_session(env, monkeypatch):
    """A session closed (map unload, drain, reset, expiry) between a frame's lookup of it and
    the frame's hand-over: the frame opens the key's next session and is dispatched there,
    rather than vanishing unanswered and uncounted with the closed one."""
    import sfmloc.server.sessions as sessions_mod

    pool, _, sm, sinks, submit = env
    real = sessions_mod.validate_camera
    first: list = []

    def close_while_validating(cam, max_pixels):  # the other thread's close, at this instant
        if not first:
            first.append(next(iter(sm._by_key.values())))
            sm.close(first[0], "reset")
        return real(cam, max_pixels)

    monkeypatch.setattr(sessions_mod, "validate_camera", close_while_validating)
    s = submit("c", 0)
    assert first and first[0].closed and s is not first[0] and not s.closed
    assert [m.seq for _, m in pool.frames] == [0] and pool.frames[0][1].sid == s.sid
    _answer(sm, pool.frames[0][1])
    assert [(p.seq, p.status) for p in sinks["c"].poses] == [(0, "TRACKING")]
