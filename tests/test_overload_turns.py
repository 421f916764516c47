"""The session manager's turns under overload (``relocalize_share``), played on a simulated
clock: 16 clients at 30 Hz on 2 workers, each worker an engine of fixed cost (a tracked frame
15 ms, a relocalization 80 ms: the ratio measured on redkitchen) that tracks a session's frame
when it comes at most ``TRACK_GAP_S`` after that session's last one and relocalizes it
otherwise. The manager is the real one; the test plays the clients and the workers (each works
its frames in the order they were handed over, one at a time) and decides nothing by wall time.

16 x 30 Hz is 3.6x what 2 such workers serve. Turns by deadline alone collapsed there (the
throughput bench: 22 poses/s, 62% relocalized): the start relocalizes every session at once, a
worker's round of relocalizations outlasts the gap, so the sessions it relocalized first fall
past it and relocalize again, for good. With relocalization's share of a worker capped, the
sessions relocalize one after another while those relocalized keep tracking."""

from __future__ import annotations

import heapq
from collections import deque
from types import SimpleNamespace

from fake_workers import TF, FakePool
from sfmloc.server import protocol as P
from sfmloc.server import sessions as sessions_module
from sfmloc.server.maps import MapEntry
from sfmloc.server.metrics import ServerMetrics
from sfmloc.server.sessions import SessionManager
from sfmloc_client.wire import CameraSpec, Frame
from turn_promise import first_turn_breaches

CAM = CameraSpec("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
# A tracked frame, a relocalization (ms), and the longest gap since the session's last frame
# that tracking bridges (s): a longer one loses the track, and the frame relocalizes.
QUIET = (15.0, 80.0, 0.4)
STARVED = (60.0, 400.0, 0.5)  # a machine whose CPU others mostly take (load 10, nice 19)
RATE_HZ = 30.0


class _Registry:
    entry = MapEntry("room", "/maps/room", "build-1", 1, 1, 1, 1, 1, 1.0, "")

    def find(self, name: str) -> MapEntry:
        return self.entry

    def get(self, name: str) -> MapEntry:
        return self.entry


def _pose(status: str, matching: str, ms: float) -> P.PoseResult:
    return P.PoseResult(
        status, TF, TF, None, None, 30, 100, 80, 40, matching, ms, "", tuple([0.0] * 36)
    )


def _overload(clients: int, share: float, duration_s: float = 6.0, engine: tuple = QUIET) -> dict:
    """``clients`` clients streaming for ``duration_s`` (simulated) to a 2-worker manager
    (``worker_queue`` 2, as the server's default) whose workers cost ``engine``; per client
    its poses."""
    return _play(clients, share, duration_s, engine)[0]


def _play(
    clients: int,
    share: float,
    duration_s: float,
    engine: tuple,
    workers: int = 2,
    aligned: bool = False,
) -> tuple[dict, list]:
    """``_overload`` on ``workers`` workers; ``aligned``: the clients send their frames at the
    same instants (1 ms apart, as tests/test_overload.py's clients after their barrier), not
    spread over the frame interval. Also the manager's timeline (``sessions.TIMELINE_ENV``'s
    rows), its times on the simulated clock."""
    clock = [0.0]
    real_time = sessions_module.time
    # the manager stamps its timeline rows with perf_counter: the simulated clock's time here
    sessions_module.time = SimpleNamespace(  # type: ignore[assignment]
        perf_counter=lambda: clock[0], monotonic=real_time.monotonic
    )
    try:
        return _run(clients, share, duration_s, engine, workers, aligned, clock)
    finally:
        sessions_module.time = real_time


def _run(
    clients: int,
    share: float,
    duration_s: float,
    engine: tuple,
    workers: int,
    aligned: bool,
    clock: list[float],
) -> tuple[dict, list]:
    track_ms, reloc_ms, track_gap_s = engine
    pool = FakePool(n=workers)
    sm = SessionManager(
        pool,
        _Registry(),  # type: ignore[arg-type]
        ServerMetrics(),
        server_id="srv",
        max_image_pixels=64 * 48,
        worker_queue=2,
        relocalize_share=share,
        frame_budget_ms=0,  # nothing is answered by the wall clock
    )
    sm.timeline = deque()
    sinks: dict[int, list] = {i: [] for i in range(clients)}
    events: list[tuple[float, int, str, object]] = []
    order = 0
    for i in range(clients):  # every client starts at once (the bench's barrier), own phase
        for k in range(int(duration_s * RATE_HZ)):
            t = k / RATE_HZ + i * 1e-3 if aligned else (k + i / clients) / RATE_HZ
            events.append((t, order, "frame", (i, k)))
            order += 1
    heapq.heapify(events)
    handed = 0
    backlog: list[list[P.LocalizeFrame]] = [[] for _ in range(workers)]
    busy = [False] * workers
    last_stamp: dict[int, float] = {}  # sid -> stamp of its last frame worked (engine state)
    while events:
        now, _, kind, data = heapq.heappop(events)
        clock[0] = now
        if kind == "frame":
            i, k = data  # type: ignore[misc]

            class _Sink:
                def send(self, p, i=i) -> None:
                    sinks[i].append(p)

                def close(self) -> None:
                    pass

            frame = Frame(k, int(now * 1e9), CAM, "gray8", b"")
            sm.submit("room", f"c{i}", "zenoh", frame, now, make_sink=_Sink)
        else:
            w, m, ms, status, matching = data  # type: ignore[misc]
            busy[w] = False
            sm.on_result(
                P.Result(
                    m.sid,
                    m.seq,
                    m.stamp_ns,
                    m.gen,
                    "build-1",
                    _pose(status, matching, ms),
                    None,
                    0.0,
                    ms,
                    m.ticket,
                )
            )
        for w, m in pool.frames[handed:]:
            backlog[w].append(m)
        handed = len(pool.frames)
        for w in range(workers):  # each idle worker takes its next frame
            if busy[w] or not backlog[w]:
                continue
            m = backlog[w].pop(0)
            busy[w] = True
            stamp = m.stamp_ns / 1e9
            last = last_stamp.get(m.sid)
            tracks = last is not None and 0 <= stamp - last <= track_gap_s
            last_stamp[m.sid] = stamp
            ms, status, matching = (
                (track_ms, "TRACKING", "guided") if tracks else (reloc_ms, "RELOCALIZED", "global")
            )
            heapq.heappush(events, (now + ms / 1e3, order, "done", (w, m, ms, status, matching)))
            order += 1
    return sinks, list(sm.timeline)


def _summary(sinks: dict, duration_s: float = 6.0) -> tuple[float, float, float]:
    """Poses per second in total and of the client served least, and the share of poses
    that relocalized."""
    rates = [len(p) / duration_s for p in sinks.values()]
    poses = [p for ps in sinks.values() for p in ps]
    assert all(p.error is None for p in poses)
    reloc = sum(p.status == "RELOCALIZED" for p in poses) / len(poses)
    return sum(rates), min(rates), reloc


def test_sixteen_clients_keep_tracking_on_two_workers_with_relocalization_capped():
    total8, worst8, reloc8 = _summary(_overload(8, share=0.5))
    total16, worst16, reloc16 = _summary(_overload(16, share=0.5))
    # 2 workers at 15 ms per tracked frame serve ~133 frames/s: 8 clients already fill them
    assert 110 < total8 and reloc8 < 0.05
    # 16 do not collapse: about as many poses, nearly all tracked, and every client served at
    # a rate it tracks at (the fair share is 133 / 16 = 8 Hz; none below half of it)
    assert total16 > 0.9 * total8
    assert reloc16 < 0.05
    assert worst16 > 4.0


def test_without_the_cap_the_same_overload_collapses_into_relocalizations():
    """Deadlines alone (``relocalize_share`` 1): the collapse the cap is for, on the same
    clients and engine (were this to pass without the cap, the test above would prove
    nothing)."""
    total16, worst16, reloc16 = _summary(_overload(16, share=1.0))
    total8, _, _ = _summary(_overload(8, share=1.0))
    assert reloc16 > 0.3 and total16 < 0.6 * total8


def test_on_a_starved_machine_every_client_is_still_served_in_turn():
    """Where the workers get too little CPU for anyone to track at a fair share (STARVED: ~9
    frames/s for 16 clients), the sessions served first must not keep every turn: one whose
    tracked frame relocalized anyway waits as a relocalizing one. (Kept first, the worst
    client got 1 pose in 20 s, beside 7 with deadlines alone.)"""
    d = 20.0
    total, worst, reloc = _summary(_overload(16, 0.5, d, STARVED), d)
    total1, worst1, reloc1 = _summary(_overload(16, 1.0, d, STARVED), d)
    assert worst * d >= 5 and worst * d >= worst1 * d - 1  # as fair as deadlines alone
    assert total >= total1 and reloc < reloc1  # and more poses, fewer of them relocalized


def test_new_sessions_on_one_worker_get_their_first_turns_as_promised_at_any_speed():
    """tests/test_overload.py's first part: one worker, six clients starting together at 30 Hz
    for 2 s, here at engine speeds from twice a quiet machine's down to a twelfth of it. What
    the manager promises new sessions (tests/turn_promise.py: first turns in the order they
    came, each after no more tracked frames than the relocalizations ahead of it allow) holds at
    every speed. Equal poses per client in those 2 s do not, by design: at 2-6x a quiet
    engine's times the first two sessions track while the others wait their turns one
    relocalization apart, and the least served got under a quarter of the mean (the count the
    real test asserted, which failed at load 8-9). A manager that starves new sessions
    (relocalization's share 0.05) breaks the promise, also where the counts look even."""
    counts_uneven, starved_caught = [], []
    for slow in (0.5, 1, 2, 3, 4, 6, 8, 12):
        engine = (10.0 * slow, 60.0 * slow, 1.0)
        sinks, rows = _play(6, 0.5, 2.0, engine, workers=1, aligned=True)
        assert first_turn_breaches(rows) == [], slow
        served = [len(p) for p in sinks.values()]
        assert min(served) >= 1  # every client answered (its last frame at least)
        if min(served) < 0.25 * sum(served) / len(served):
            counts_uneven.append(slow)
        _, starved = _play(6, 0.05, 2.0, engine, workers=1, aligned=True)
        if first_turn_breaches(starved):
            starved_caught.append(slow)
    assert counts_uneven == [2, 3, 4, 6]
    assert starved_caught == [1, 2, 3, 4, 6, 8]


def test_a_wait_the_time_budget_cut_is_not_held_against_the_turns():
    """A new session whose first frame the time budget answered before its turn (no "start"
    nor "drop" row for it: DEADLINE_EXCEEDED, as promised on a starved machine) waits anew
    from its next frame, behind sessions that came after it: not a breach of the first turns'
    order (the real overload test at load 14-16 had such sessions). The same wait with that
    frame superseded by its next one instead, uncut, is one."""
    head = [
        ("recv", 0.00, 1, 0, False, False),
        ("start", 0.00, 1, 0, 0, 1, True),  # the worker had room: no wait
        ("recv", 0.01, 2, 0, False, False),
        ("recv", 0.02, 3, 0, False, False),
        ("res", 0.50, 1, 0, 0, 1, "RELOCALIZED", "global", 500.0, 1.0, 499.0, True),
        ("start", 0.50, 3, 0, 0, 2, True),  # session 3 before session 2, which came first
        ("res", 0.90, 3, 0, 0, 2, "RELOCALIZED", "global", 400.0, 1.0, 399.0, True),
    ]
    tail = [
        ("recv", 2.50, 2, 1, False, False),
        ("start", 2.50, 2, 1, 0, 3, True),
        ("res", 2.90, 2, 1, 0, 3, "RELOCALIZED", "global", 400.0, 1.0, 399.0, True),
    ]
    assert first_turn_breaches(head + tail) == []  # session 2's frame 0: the budget's
    superseded = [("recv", 0.30, 2, 1, False, True), ("drop", 0.30, 2, 0, 1)]
    late = [r for r in tail if r[0] != "recv"]
    assert first_turn_breaches(head + superseded + late) == [
        "first turns out of order: came [2, 3], served [3, 2]"
    ]
