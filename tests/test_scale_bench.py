"""The scale bench's core accounting (issue 14): servers pinned to cores, and what they can
deliver together given the cores each had."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sfmloc.bench.scale import core_share, pinning


def test_pinning_puts_server_i_on_core_i_mod_cores():
    cores = sorted(os.sched_getaffinity(0))
    got = pinning(["s0", "s1", "s2"], pin=True)
    assert got == {f"s{i}": {cores[i % len(cores)]} for i in range(3)}
    assert pinning(["s0"], pin=False) is None


def test_core_share_divides_a_rate_by_the_servers_on_its_core():
    alone = [
        {"server": "s0", "poses_per_s": 100.0},
        {"server": "s1", "poses_per_s": 90.0},
        {"server": "s2", "poses_per_s": 80.0},
    ]
    # 3 servers on 2 cores: s0 and s2 share core 0, s1 has core 1 to itself
    assert core_share(alone, {"s0": {0}, "s1": {1}, "s2": {0}}) == pytest.approx(
        100 / 2 + 90 + 80 / 2
    )
    # one core each: the plain sum
    assert core_share(alone[:2], {"s0": {0}, "s1": {1}}) == pytest.approx(190.0)
    # unpinned: every server had the whole machine alone, together they share it
    assert core_share(alone, None) == pytest.approx(270 / 3)


def _allowed(pid: int) -> str:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("Cpus_allowed_list:"):
            return line.split(":", 1)[1].strip()
    raise AssertionError(f"no Cpus_allowed_list for {pid}")


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(stat[1]) == pid:
                out.append(int(d.name))
    return out


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc")
def test_a_pinned_server_and_its_workers_run_on_its_core(world):
    from sfmloc.testing import ServerProcess

    core = max(os.sched_getaffinity(0))
    with ServerProcess(world.maps_dir, workers=1, cpus={core}) as sp:
        tree, todo = [], [sp.proc.pid]
        while todo:
            p = todo.pop()
            tree.append(p)
            todo += _children(p)
        assert len(tree) >= 2, tree  # the server and at least its worker
        assert {_allowed(p) for p in tree} == {str(core)}


def test_the_client_core_is_left_to_the_clients():
    from sfmloc.bench.scale import client_cores

    cores = sorted(os.sched_getaffinity(0))
    got = pinning(["s0", "s1", "s2"], pin=True, client_core=True)
    if len(cores) >= 2:
        servers = cores[:-1]
        assert got == {f"s{i}": {servers[i % len(servers)]} for i in range(3)}
        assert client_cores(True, True) == {cores[-1]}
        assert all(cores[-1] not in c for c in got.values())
    else:  # one core: nothing to leave
        assert got == {f"s{i}": {cores[0]} for i in range(3)}
        assert client_cores(True, True) is None
    assert client_cores(False, True) is None and client_cores(True, False) is None


def test_cpu_rows_and_the_together_vs_alone_comparison():
    from sfmloc.bench.scale import cpu_comparison, cpu_rows

    # 10 s: s0 used 8 CPU s, the clients 1, the machine 15 (6 by others); 500 poses
    c0 = {"s0": 100.0, "clients": 50.0, "machine": 1000.0}
    c1 = {"s0": 108.0, "clients": 51.0, "machine": 1015.0}
    r = cpu_rows(c0, c1, 10.0, 500)
    assert r["cores_used"]["servers"] == pytest.approx(0.8)
    assert r["cores_used"]["other"] == pytest.approx(0.6)
    assert r["cpu_ms_per_pose"]["servers"] == pytest.approx(16.0)
    assert r["cpu_ms_per_pose"]["clients"] == pytest.approx(2.0)
    alone = [
        {"answered_in_window": 500, "cpu_ms_per_pose": {"servers": 16.0, "clients": 2.0}},
        {"answered_in_window": 1500, "cpu_ms_per_pose": {"servers": 12.0, "clients": 2.0}},
    ]
    together = {"cpu_ms_per_pose": {"servers": 14.0, "clients": 3.0}}
    got = cpu_comparison(alone, together)
    assert got["cpu_ms_per_pose"]["alone"]["servers"] == pytest.approx(13.0)  # weighted
    assert got["servers_cpu_per_pose_together_vs_alone"] == pytest.approx(14.0 / 13.0)
    assert cpu_comparison(alone, {}) == {}


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
def test_pin_process_pins_every_thread_of_this_process():
    import threading

    from sfmloc.bench.scale import pin_process

    before = os.sched_getaffinity(0)
    started, stop = threading.Event(), threading.Event()

    def spin() -> None:  # a thread that exists before the pinning
        started.set()
        stop.wait(10)

    t = threading.Thread(target=spin)
    t.start()
    started.wait(5)
    core = {max(before)}
    try:
        pin_process(core)
        tids = [int(x) for x in os.listdir("/proc/self/task")]
        assert all(os.sched_getaffinity(tid) == core for tid in tids)
    finally:
        pin_process(before)
        stop.set()
        t.join()
    assert os.sched_getaffinity(0) == before
