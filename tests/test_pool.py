"""The worker pool against fake workers (``fake_workers.FakeWorkers``: the real protocol over
real socket pairs, no engine): requests and answers, worker loss and the restart window."""

from __future__ import annotations

import threading
import time

import pytest

from fake_workers import FakeWorkers
from sfmloc.errors import OverloadError, UnavailableError
from sfmloc.server import protocol as P
from sfmloc.server.pool import WorkerPool

CAM = ("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))


class _Pool:
    """A started pool of thread workers running ``FakeWorkers``, with its callbacks as events."""

    def __init__(self, n: int = 2, reloc_workers: int = 0) -> None:
        self.fake = FakeWorkers()
        self.results: list[P.Result] = []
        self.dead: list[int] = []
        self.restarted = threading.Event()
        self.died = threading.Event()
        self.got_result = threading.Condition()
        self.pool = WorkerPool(
            n,
            "thread",
            "{}",
            on_result=self._on_result,
            on_dead=self._on_dead,
            on_lost=lambda i: self.restarted.set(),
            thread_target=self.fake,
            reloc_workers=reloc_workers,
        )
        self.pool.start(timeout=30)

    def _on_result(self, r: P.Result) -> None:
        with self.got_result:
            self.results.append(r)
            self.got_result.notify_all()

    def _on_dead(self, i: int) -> None:
        self.dead.append(i)
        self.died.set()

    def frame(self, worker: int, sid: int, seq: int, encoding: str = "gray8") -> None:
        self.pool.submit_frame(
            worker, P.LocalizeFrame(sid, "a", 1, seq, seq * 10, CAM, encoding, data=b"x")
        )

    def kill(self, worker: int) -> None:
        """The worker dies as a killed process does (its socket closes mid-frame)."""
        self.frame(worker, 99, 0, encoding="die")
        assert self.died.wait(30)


@pytest.fixture
def fp():
    p = _Pool()
    yield p
    p.pool.stop(timeout=10)


def test_frames_go_to_their_worker_and_results_come_back_in_order(fp):
    for seq in range(5):
        fp.frame(seq % 2, sid=seq % 2 + 1, seq=seq)
    with fp.got_result:
        assert fp.got_result.wait_for(lambda: len(fp.results) == 5, 30)
    assert sorted(r.seq for r in fp.results) == list(range(5))
    assert [m.seq for m in fp.fake.messages(0, 1, P.LocalizeFrame)] == [0, 2, 4]
    assert [m.seq for m in fp.fake.messages(1, 1, P.LocalizeFrame)] == [1, 3]
    assert all(r.pose is not None and r.pose.status == "TRACKING" for r in fp.results)
    assert fp.pool.inflight() == [0, 0]


def test_load_reaches_every_worker_and_relocalize_answers_with_its_pose(fp):
    s = fp.pool.load_map("a", 1, "/maps/a", "build-1")
    assert s.build_id == "build-1" and s.index_in_place
    for i in range(2):
        assert [(m.name, m.gen, m.path) for m in fp.fake.messages(i, 1, P.Load)] == [
            ("a", 1, "/maps/a")
        ]
    r = fp.pool.relocalize(P.Relocalize(0, "a", 1, CAM, "gray8", None, data=b"img")).result(30)
    assert isinstance(r, P.RelocResult) and r.pose.status == "RELOCALIZED"
    fp.pool.drop_map("a", 1)
    assert fp.fake.wait_for(lambda: all(fp.fake.messages(i, 1, P.Drop) for i in range(2)))


def test_a_lost_worker_is_replaced_at_once_and_serves_after_reloading_the_current_maps(fp):
    """The restart window (issue 11): the replacement is in the pool from the start (stop and
    drops reach it), sessions avoid it until it holds the maps, and a LoadMap meanwhile is
    answered by the live worker without waiting; the replacement then loads that map too."""
    pool, fake = fp.pool, fp.fake
    pool.load_map("a", 1, "/maps/a", "b1")
    dead = pool.workers[0]
    fake.hold_load[(0, 2)] = hold = threading.Event()  # the replacement's reload waits here
    fp.kill(0)
    assert fp.dead == [0]
    assert fake.wait_for(lambda: len(fake.messages(0, 2, P.Load)) == 1)  # reloading "a"
    new = pool.workers[0]
    assert new is not dead and new.alive and new.ready.is_set() and not dead.alive
    assert not pool.is_alive(0) and pool.is_alive(1)  # sessions go to worker 1 meanwhile
    s = pool.load_map("b", 2, "/maps/b", "b2", timeout=30)  # the live worker answers
    assert s.build_id == "b2"
    assert [m.name for m in fake.messages(1, 1, P.Load)] == ["a", "b"]
    hold.set()
    assert fp.restarted.wait(30)
    assert pool.is_alive(0) and pool.workers[0] is new
    assert sorted(m.name for m in fake.messages(0, 2, P.Load)) == ["a", "b"]
    assert pool.restarts == 1


def test_stop_reaches_a_replacement_that_is_still_reloading(fp):
    pool, fake = fp.pool, fp.fake
    pool.load_map("a", 1, "/maps/a", "b1")
    fake.hold_load[(0, 2)] = hold = threading.Event()
    fp.kill(0)
    assert fake.wait_for(lambda: len(fake.messages(0, 2, P.Load)) == 1)
    new = pool.workers[0]
    stopper = threading.Thread(target=pool.stop)
    stopper.start()
    hold.set()
    stopper.join(30)
    assert not stopper.is_alive()
    assert fake.messages(0, 2, P.Stop), "the replacement was not told to stop"
    assert not new.runner.is_alive()


def test_a_relocalization_in_a_worker_that_dies_fails_with_unavailable(fp):
    fut = fp.pool.relocalize(P.Relocalize(0, "a", 1, CAM, "die", None, data=b""))
    with pytest.raises(UnavailableError, match="died"):
        fut.result(30)
    assert fp.died.is_set() and fp.restarted.wait(30)
    ok = fp.pool.relocalize(P.Relocalize(0, "a", 1, CAM, "gray8", None, data=b"img")).result(30)
    assert ok.pose.status == "RELOCALIZED"


def test_relocalizations_wait_for_an_idle_lane_worker_and_dropped_ones_never_reach_it():
    """Issue 16: with a relocalization lane, requests wait in the pool (not in the worker's
    socket), one per lane worker at a time; one cancelled by its caller, or whose deadline
    passed while it waited, is dropped before any work."""
    fp = _Pool(n=1, reloc_workers=1)
    try:
        fp.fake.hold_reloc = gate = threading.Event()
        first = fp.pool.relocalize(P.Relocalize(0, "a", 1, CAM, "hold", None, data=b"x"))
        assert fp.fake.wait_for(lambda: len(fp.fake.messages(1, 1, P.Relocalize)) == 1)
        cancelled = fp.pool.relocalize(P.Relocalize(0, "a", 1, CAM, "gray8", None, data=b"x"))
        expired = fp.pool.relocalize(
            P.Relocalize(0, "a", 1, CAM, "gray8", None, deadline=time.monotonic(), data=b"x")
        )
        last = fp.pool.relocalize(P.Relocalize(0, "a", 1, CAM, "gray8", None, data=b"x"))
        assert cancelled.cancel()
        assert len(fp.fake.messages(1, 1, P.Relocalize)) == 1  # the others wait in the pool
        # What the server's reaper does every 0.1 s: the expired one is answered now, while the
        # lane is still busy (RESOURCE_EXHAUSTED before the caller's deadline, not after it)
        assert fp.pool.expire_relocalizations() == 1
        with pytest.raises(OverloadError, match="relocalization lane was busy"):
            expired.result(0)
        assert not last.done()
        gate.set()
        assert first.result(30).pose.status == "RELOCALIZED"
        assert last.result(30).pose.status == "RELOCALIZED"
        assert len(fp.fake.messages(1, 1, P.Relocalize)) == 2  # first and last only
        assert not fp.fake.messages(0, 1, P.Relocalize)  # never on the stream worker
        assert fp.pool.wait_for(lambda: fp.pool._reloc_pending == 0, 30)
    finally:
        fp.fake.hold_reloc = None
        fp.pool.stop(timeout=10)
