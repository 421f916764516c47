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
