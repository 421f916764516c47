"""Process workers forked from the pre-imported zygote (``server/zygote.py``), with real
processes: they serve, a killed one is reaped by the zygote and its replacement forked, and
when the zygote itself is gone the pool falls back to fresh interpreters."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
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


def _environ(pid: int) -> dict[str, str]:
    with open(f"/proc/{pid}/environ", "rb") as f:
        items = [kv.split(b"=", 1) for kv in f.read().split(b"\0") if b"=" in kv]
    return {k.decode(): v.decode() for k, v in items}


def test_a_prestarted_zygote_is_taken_by_the_pool(world):
    """``sfmloc serve`` starts the zygote before its own imports (``zygote.prestart``): the
    pool forks its workers from that very process when the image limit it guessed is the
    configuration's."""
    from sfmloc.server import zygote as Z

    Z.prestart(4096 * 4096)
    early = Z._prestarted
    assert early is not None and early.alive
    p = WorkerPool(1, "process", "{}", on_result=lambda r: None, max_image_pixels=4096 * 4096)
    try:
        p.start(timeout=120)
        assert p._zygote is early and Z._prestarted is None
        assert _ppid(p.workers[0].pid) == early.proc.pid
        summary = p.load_map("room", 1, str(world.maps_dir / "room"), "", timeout=120)
        assert summary.points > 0
    finally:
        p.stop()
    assert early.proc.returncode is not None  # stopped with the pool


def test_a_prestarted_zygote_with_another_image_limit_is_replaced():
    """A wrong guess costs only that zygote: it is stopped, and the workers come from one
    with the configuration's OpenCV decoding limit (read by OpenCV once, when it loads)."""
    from sfmloc.server import zygote as Z

    Z.prestart(1000)
    early = Z._prestarted
    assert early is not None
    p = WorkerPool(1, "process", "{}", on_result=lambda r: None, max_image_pixels=2_000_000)
    try:
        p.start(timeout=120)
        assert p._zygote is not None and p._zygote is not early
        assert early.proc.returncode is not None  # stopped and reaped, not left behind
        assert _environ(p._zygote.proc.pid)["OPENCV_IO_MAX_IMAGE_PIXELS"] == "2000000"
        assert _ppid(p.workers[0].pid) == p._zygote.proc.pid
    finally:
        p.stop()


def test_an_unused_prestarted_zygote_is_stopped():
    from sfmloc.cli.main import _prestart_serve
    from sfmloc.server import zygote as Z

    assert not _prestart_serve(["stream", "--map", "room"])
    assert not _prestart_serve(["serve", "--help"])
    assert not _prestart_serve(["serve", "--worker-kind", "thread"])
    assert Z._prestarted is None
    assert _prestart_serve(["-q", "serve", "--maps", "maps"])
    early = Z._prestarted
    assert early is not None and early.alive
    Z.discard_prestarted()
    assert Z._prestarted is None and early.proc.returncode is not None


def test_the_server_process_does_not_import_what_only_workers_use():
    """The server process imports the engine's configuration, hence the engine package, but
    not scipy (2.2 of its 5.4 s of imports at load 14; only the engine's scope weights use
    it, in the workers): a fresh interpreter importing the server has no scipy."""
    code = "import sys, sfmloc.server.app; print('scipy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stderr


def test_a_dead_workers_sessions_move_before_its_exit_status_arrives(world, caplog):
    """The death is the socket's EOF: its frames are answered and its sessions moved
    (``on_dead``) at once, not after the zygote reports the exit status (a wake-up of another
    process, late on a loaded machine). With the zygote stopped, ``on_dead`` still runs;
    ``worker_lost`` with exit code -9 follows once the zygote reports it."""
    import logging

    dead = threading.Event()
    logged_before: list[bool] = []

    def on_dead(i: int) -> None:
        logged_before.append(any("worker_lost" in r.getMessage() for r in caplog.records))
        dead.set()

    caplog.set_level(logging.INFO)
    p = WorkerPool(2, "process", "{}", on_result=lambda r: None, on_dead=on_dead)
    try:
        p.start(timeout=120)
        p.load_map("room", 1, str(world.maps_dir / "room"), "", timeout=120)
        zygote = p._zygote
        assert zygote is not None
        victim = p.workers[0]
        os.kill(zygote.proc.pid, signal.SIGSTOP)  # it cannot reap nor report for now
        try:
            os.kill(victim.pid, signal.SIGKILL)
            assert dead.wait(60)
            assert logged_before == [False]  # moved before the exit status was known
            assert not p.is_alive(0)
        finally:
            os.kill(zygote.proc.pid, signal.SIGCONT)
        assert p.wait_for(lambda: p.workers[0] is not victim and p.is_alive(0), 120)
        lost = [r.getMessage() for r in caplog.records if "worker_lost" in r.getMessage()]
        assert len(lost) == 1 and "exitcode=-9" in lost[0] and f"pid={victim.pid}" in lost[0]
    finally:
        p.stop()
