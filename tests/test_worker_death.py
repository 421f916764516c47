"""A stream worker's death, with real processes (a forked worker pool, its zygote) and real
Zenoh sessions (issue 16, "no silent frame"): every frame a dead worker had, or that waited for
it, is answered, also when no other worker is alive to take its sessions; a session moved to
another worker is found there around its last pose. No assertion on how long anything takes:
waits are for answers, with generous limits."""

from __future__ import annotations

import contextlib
import os
import signal

import pytest

from server_helpers import (
    Collected,
    camera,
    client_zenoh,
    running_server,
    server_config,
    wait_until,
    zenoh_endpoint,
)
from sfmloc_client import FrameStreamer, PoseSubscriber


@pytest.fixture(scope="module")
def zep():
    return zenoh_endpoint()


@pytest.fixture(scope="module")
def srv(world, zep):
    # Frames held in a stopped worker must not be answered by their time budget meanwhile
    # (that is tests/test_frame_budget.py): only the worker's death answers them here.
    conf = server_config(
        world,
        zep,
        workers=2,
        worker_kind="process",
        relocalize_workers=0,
        frame_budget_ms=600_000.0,
        frame_hang_ms=600_000.0,
    )
    with running_server(conf) as s:
        yield s


@pytest.fixture()
def z(zep, srv):
    with client_zenoh(zep) as session:
        yield session


def _all_serving(pool) -> bool:
    return all(h.alive and h.serving and h.ready.is_set() for h in pool.workers)


def _session(srv, client_id: str):
    return next(s for s in srv.server.sessions.list("room") if s.client_id == client_id)


def test_frames_waiting_for_a_worker_are_answered_when_no_worker_is_left(world, z, srv):
    """Both stream workers die while a session has a frame in its worker and the next one
    waiting for it, and no replacement can start yet (the zygote is stopped): both frames are
    answered UNAVAILABLE at once. The waiting one used to stay with the session without an
    answer, and was dropped without a word once a replacement served."""
    pool = srv.server.pool
    assert pool.wait_for(lambda: _all_serving(pool), 120)
    zygote = pool._zygote
    assert zygote is not None and zygote.alive  # replacements are forked by it
    got = Collected()
    with (
        PoseSubscriber(z, "room", "alone", callback=got.append),
        FrameStreamer(z, "room", "alone", camera(world)) as fs,
    ):
        assert fs.wait_for_server(30)
        fs.publish(data=world.png[0], encoding="png", seq=0, stamp_ns=0)
        assert got.has_seq(0)
        s = _session(srv, "alone")
        mine = pool.workers[s.worker]
        other = pool.workers[1 - s.worker]
        os.kill(zygote.proc.pid, signal.SIGSTOP)  # no replacement until it goes on
        try:
            os.kill(mine.pid, signal.SIGSTOP)  # frame 1 stays in it
            os.kill(other.pid, signal.SIGKILL)
            assert pool.wait_for(lambda: not other.alive, 60)
            fs.publish(data=world.png[1], encoding="png", seq=1, stamp_ns=int(1e9 / 30))
            assert wait_until(lambda: s.busy, 60)
            fs.publish(data=world.png[2], encoding="png", seq=2, stamp_ns=int(2e9 / 30))
            assert wait_until(lambda: len(s.pending) == 1, 60)  # frame 2 waits for frame 1
            os.kill(mine.pid, signal.SIGKILL)
            assert got.has_seq(1, timeout=60) and got.has_seq(2, timeout=60), sorted(
                p.seq for p in got
            )
        finally:
            os.kill(zygote.proc.pid, signal.SIGCONT)
            with contextlib.suppress(ProcessLookupError):
                os.kill(mine.pid, signal.SIGKILL)
        answers = {p.seq: p for p in got}
        assert answers[1].error.code == answers[2].error.code == "UNAVAILABLE"
        assert "no other engine worker" in answers[2].message
        # The replacements serve; the same session goes on there, every frame answered.
        assert pool.wait_for(lambda: _all_serving(pool), 120)
        for k in range(3, 13):
            fs.publish(data=world.png[k], encoding="png", seq=k, stamp_ns=int(k * 1e9 / 30))
            assert got.has_seq(k)
    assert sorted({p.seq for p in got}) == list(range(13))
    assert len(got) == 13  # one answer each
    assert sum(p.localized for p in got if p.seq >= 3) >= 8


def test_a_moved_session_is_found_around_its_last_pose(world, z, srv):
    """A tracking session's worker is killed: the session's next frame goes to the surviving
    worker with its last pose as the prior, and is found around it (guided matching, a
    relocalization), not by global matching from nothing."""
    pool = srv.server.pool
    assert pool.wait_for(lambda: _all_serving(pool), 120)
    got = Collected()
    with (
        PoseSubscriber(z, "room", "mover", callback=got.append),
        FrameStreamer(z, "room", "mover", camera(world)) as fs,
    ):
        assert fs.wait_for_server(30)
        for k in range(8):
            fs.publish(data=world.png[k], encoding="png", seq=k, stamp_ns=int(k * 1e9 / 30))
            assert got.has_seq(k)
        assert [p.status for p in got][-1] == "TRACKING"
        s = _session(srv, "mover")
        victim = pool.workers[s.worker]
        os.kill(victim.pid, signal.SIGKILL)
        assert pool.wait_for(lambda: not victim.alive, 60)
        assert wait_until(lambda: s.worker != victim.index, 60)  # moved at once
        for k in range(8, 20):
            fs.publish(data=world.png[k], encoding="png", seq=k, stamp_ns=int(k * 1e9 / 30))
            assert got.has_seq(k)
    after = [p for p in got if p.seq >= 8]
    assert all(p.error is None for p in after)
    first = next(p for p in after if p.localized)
    assert (first.status, first.matching) == ("RELOCALIZED", "guided"), first
    assert all(p.localized for p in after[after.index(first) :])
    assert pool.wait_for(lambda: _all_serving(pool), 120)


def test_a_frame_left_on_its_old_worker_is_answered_by_it_when_the_new_one_dies(world, z, srv):
    """A replacement takes a session over (``_rebalance_to``) while the session's frame still
    runs on its old worker, and the replacement dies: that frame is the old worker's to
    answer, with its pose, once (it was answered UNAVAILABLE at the replacement's death and the
    old worker's pose was dropped as stale)."""
    pool = srv.server.pool
    assert pool.wait_for(lambda: _all_serving(pool), 120)
    zygote = pool._zygote
    assert zygote is not None and zygote.alive
    # The earlier tests' idle sessions would be rebalanced first (idle before busy): end them.
    for s in srv.server.sessions.list():
        srv.server.sessions.close(s, "test")
    got = {c: Collected() for c in ("left", "right")}
    with contextlib.ExitStack() as stack:
        fs = {}
        for c in got:
            stack.enter_context(PoseSubscriber(z, "room", c, callback=got[c].append))
            fs[c] = stack.enter_context(FrameStreamer(z, "room", c, camera(world)))
        for c in got:
            assert fs[c].wait_for_server(30)
            fs[c].publish(data=world.png[0], encoding="png", seq=0, stamp_ns=0)
            assert got[c].has_seq(0)
        ss = [_session(srv, c) for c in got]
        old = pool.workers[ss[0].worker]
        other = pool.workers[1 - old.index]
        os.kill(zygote.proc.pid, signal.SIGSTOP)  # the replacement waits until both are busy
        try:
            os.kill(other.pid, signal.SIGKILL)
            assert pool.wait_for(lambda: not other.alive, 60)
            assert wait_until(lambda: all(s.worker == old.index for s in ss), 60)
            os.kill(old.pid, signal.SIGSTOP)  # frame 1 of both stays in it
            for c in got:
                fs[c].publish(data=world.png[1], encoding="png", seq=1, stamp_ns=int(1e9 / 30))
            assert wait_until(lambda: all(s.busy for s in ss), 60)
        finally:
            os.kill(zygote.proc.pid, signal.SIGCONT)
        try:
            # The replacement serves and takes one of the two (both busy) over.
            assert wait_until(lambda: any(s.worker != old.index for s in ss), 120)
            moved = next(s for s in ss if s.worker != old.index)
            new = pool.workers[moved.worker]
            assert moved.busy and new is not other
            os.kill(new.pid, signal.SIGKILL)
            assert pool.wait_for(lambda: not new.alive, 60)
            assert wait_until(lambda: moved.worker == old.index, 60)  # moved back at its death
        finally:
            os.kill(old.pid, signal.SIGCONT)
        for c in got:
            assert got[c].has_seq(1)
            fs[c].publish(data=world.png[2], encoding="png", seq=2, stamp_ns=int(2e9 / 30))
            assert got[c].has_seq(2)
    for c in got:
        assert [p.seq for p in got[c]] == [0, 1, 2]  # one answer each
        assert all(p.error is None for p in got[c]), [(p.seq, p.error) for p in got[c]]
    assert pool.wait_for(lambda: _all_serving(pool), 120)
