"""Process workers forked from the pre-imported zygote (``server/zygote.py``), with real
processes: they serve, a killed one is reaped by the zygote and its replacement forked, and
when the zygote itself is gone the pool falls back to fresh interpreters."""

from __future__ import annotations

import os
import signal
import subprocess
import threading

import pytest

from sfmloc.bench.transport import _child_pids
from sfmloc.server import protocol as P
from sfmloc.server.pool import WorkerPool
from sfmloc_client import CameraSpec


def _ppid(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[1])


def _zombies(parent: int) -> list[str]:
    out = subprocess.run(["ps", "-o", "stat=", "--ppid", str(parent)], capture_output=True)
    return [s for s in out.stdout.decode().split() if s.startswith("Z")]


@pytest.fixture
def pool():
    lost = threading.Event()
    p = WorkerPool(2, "process", "{}", on_result=lambda r: None, on_lost=lambda i: lost.set())
    p.lost = lost  # type: ignore[attr-defined]
    p.start(timeout=120)
    yield p
    p.stop()


def test_workers_are_forked_by_the_zygote_and_serve(pool, world):
    zygote = pool._zygote
    assert zygote is not None and zygote.alive
    pids = [h.pid for h in pool.workers]
    assert len(set(pids)) == 2 and all(_ppid(pid) == zygote.proc.pid for pid in pids)
    for pid, name in [(zygote.proc.pid, "sfmloc-zygote")] + [
        (pid, "sfmloc-worker") for pid in pids
    ]:
        with open(f"/proc/{pid}/comm") as f:
            assert f.read().strip() == name  # what ps shows, and how the benches find them
    assert set(pids) | {zygote.proc.pid} <= set(_child_pids(os.getpid()))  # the benches' CPU
    summary = pool.load_map("room", 1, str(world.maps_dir / "room"), "", timeout=120)
    assert summary.points > 0 and summary.index_in_place
    cam = P.camera_tuple(CameraSpec.parse(world.camera_spec))
    res = pool.relocalize(P.Relocalize(0, "room", 1, cam, "png", None, data=world.png[3]))
    assert res.result(120).pose.status != "LOST"


def test_a_killed_worker_is_reaped_and_its_replacement_forked_with_the_maps(pool, world):
    zygote = pool._zygote
    assert zygote is not None
    pool.load_map("room", 1, str(world.maps_dir / "room"), "", timeout=120)
    victim = pool.workers[0]
    os.kill(victim.pid, signal.SIGKILL)
    assert pool.lost.wait(60)  # replaced and the map reloaded
    victim.runner.join(5)
    assert victim.runner.exitcode == -signal.SIGKILL  # the status the zygote reaped
    new = pool.workers[0]
    assert new.pid != victim.pid and _ppid(new.pid) == zygote.proc.pid
    assert pool.is_alive(0) and not _zombies(zygote.proc.pid)


def test_without_the_zygote_workers_start_as_fresh_interpreters(pool):
    zygote = pool._zygote
    assert zygote is not None
    os.kill(zygote.proc.pid, signal.SIGKILL)
    zygote._reader.join(30)  # the server side saw it go
    assert not zygote.alive and zygote.proc.returncode == -signal.SIGKILL  # and reaped it
    victim = pool.workers[1]
    os.kill(victim.pid, signal.SIGKILL)  # an orphan now: its death is still noticed
    assert pool.lost.wait(120)
    new = pool.workers[1]
    assert new.pid != victim.pid and _ppid(new.pid) == os.getpid()
    assert victim.runner.exitcode is not None and pool.is_alive(1)
    assert not _zombies(os.getpid())


def test_the_startup_bench_replaces_a_killed_worker_in_both_modes(world):
    """``python -m sfmloc.bench.startup``'s restart part: a killed worker of a forked pool and
    of a fresh-interpreter pool is replaced and serves the map again, timed."""
    from sfmloc.bench.startup import MODES, restart_times

    times = restart_times(world.maps_dir / "room", 1)
    assert set(times) == set(MODES)
    assert all(len(v) == 1 and 0 < v[0] < 120 for v in times.values())
