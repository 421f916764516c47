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


def _bench_world(world):
    """The test world as the reliability/scale benches' ``World``."""
    import numpy as np

    from sfmloc.bench.reliability import World
    from sfmloc.map.bundle import MapBundle

    return World(
        maps_dir=world.maps_dir,
        camera=world.camera_spec,
        gray=world.gray,
        gt_cam_from_world=[np.asarray(g.matrix()) for g in world.gt_cam_from_world],
        scene_scale=MapBundle(world.maps_dir / "room", verify=False).scene_scale,
    )


def _stream(bw, endpoint: str, client_id: str, stamp_hz: float | None, frames: int = 8):
    """A lockstep StreamClient against the server at ``endpoint`` until ``frames`` answers."""
    import threading
    import time

    from sfmloc.bench.reliability import StreamClient
    from sfmloc.bench.scale import wait_warm

    stop = threading.Event()
    c = StreamClient(bw, endpoint, client_id, stop, stamp_hz=stamp_hz)
    t_wall0 = time.time_ns()
    c.start()
    assert c.ready.wait(60), c.failure
    waited = wait_warm([c], frames, 90)
    assert len(c.log.answered) >= frames, (waited, c.failure)
    assert waited < 90
    stop.set()
    c.join(30)
    assert c.failure is None, c.failure
    assert len(c.log.answered) >= frames, f"{len(c.log.answered)} answers"
    return c, t_wall0, time.time_ns()


def test_lockstep_frames_carry_the_video_clock_not_the_send_time(world):
    """--stamps video (the scale bench's default): frame k is stamped k / stamp_hz after the
    first, whatever the server's latency (the engine sees the clip's own motion); without
    stamp_hz each is stamped when sent (the server's latency becomes the camera's speed)."""
    from sfmloc.bench.scale import frame_mix
    from sfmloc.testing import ServerProcess

    bw = _bench_world(world)
    with ServerProcess(world.maps_dir, workers=1) as sp:
        video, w0, w1 = _stream(bw, sp.endpoint, "stamps-video", 30.0)
        wall, v0, v1 = _stream(bw, sp.endpoint, "stamps-wall", None)
    st = {q: a["stamp_ns"] for q, a in video.log.answers.items()}
    first = st[0]
    assert w0 <= first <= w1
    assert all(st[q] - first == round(q * 1e9 / 30.0) for q in st), st
    # the server's answers are what it localized with that stamp: poses, not errors
    assert len(video.log.localized) >= len(st) // 2
    sw = {q: a["stamp_ns"] for q, a in wall.log.answers.items()}
    assert all(v0 <= t <= v1 for t in sw.values())
    # lockstep: frame q+1 is sent after frame q's answer, its wall stamp after q's receipt
    for q in sorted(sw)[:-1]:
        if q + 1 in sw:
            assert sw[q + 1] > sw[q]
    mix = frame_mix([video], 0.0, float("inf"))
    assert sum(mix["matching"].values()) == len(video.log.answered)
    assert mix["interval_ms_mean"] > 0


def test_alone_gives_each_server_the_clients_it_owns_together():
    from sfmloc.bench.scale import owned_clients
    from sfmloc_client.placement import rendezvous_owner

    ids = ["s0", "s1", "s2"]
    clients = [f"scale-client-{i}" for i in range(12)]
    got = owned_clients("room", clients, ids)
    assert sorted(c for cs in got.values() for c in cs) == sorted(clients)  # a partition
    for sid, cs in got.items():
        assert all(rendezvous_owner("room", c, ids) == sid for c in cs)
    # the bench's 12 clients do not spread 4/4/4: alone must not assume they do
    assert sorted(len(cs) for cs in got.values()) != [4, 4, 4]
    assert owned_clients("room", [], ids) == {"s0": [], "s1": [], "s2": []}


def test_same_frames_phase_covers_exactly_the_frames_between_the_holds(world):
    """Two lockstep clients against a real server: both wait at the first hold, run frames
    3..7 together on release and wait at the second; the phase counts exactly those 2 x 5
    poses and the server's CPU for them; released, they go on past it."""
    import threading

    from sfmloc.bench.reliability import StreamClient
    from sfmloc.bench.scale import CpuMeter, same_frame_holds, same_frames_phase, wait_warm
    from sfmloc.testing import ServerProcess

    bw = _bench_world(world)
    holds = same_frame_holds(3, 5)
    assert sorted(holds) == [3, 8] and same_frame_holds(3, 0) == {}
    stop = threading.Event()
    with ServerProcess(world.maps_dir, workers=1) as sp:
        cl = [
            StreamClient(bw, sp.endpoint, f"held-{i}", stop, stamp_hz=30.0, holds=holds)
            for i in range(2)
        ]
        for c in cl:
            c.start()
        try:
            for c in cl:
                assert c.ready.wait(60), c.failure
            got = same_frames_phase(cl, holds, CpuMeter({"s0": sp}), 120)
            assert wait_warm(cl, 11, 120) < 120  # released: they go on
        finally:
            stop.set()
            for c in cl:
                c.join(30)
    assert all(c.failure is None for c in cl), [c.failure for c in cl]
    assert got["complete"] and got["frames"] == [3, 8]
    assert got["expected"] == 10 and got["answered"] == 10 and got["errors"] == 0
    assert sum(got["matching"].values()) == 10
    assert got["servers_cpu_s"] > 0 and got["seconds"] > 0
    assert got["servers_cpu_ms_per_pose"] == pytest.approx(1e3 * got["servers_cpu_s"] / 10)
    for c in cl:
        assert all(q in c.log.answered for q in range(3, 8))
    # the holds: no client sent frame 3 before both had frame 2's answer, nor 8 before 7's
    for k in (3, 8):
        assert min(c.log.sent[k] for c in cl) >= max(c.log.answered[k - 1] for c in cl)


def test_same_frames_comparison_adds_the_alone_times_and_weighs_the_cpu():
    from sfmloc.bench.scale import same_frames_comparison

    def row(cpu_s, poses, secs):
        return {
            "complete": True,
            "answered": poses,
            "expected": poses,
            "servers_cpu_s": cpu_s,
            "seconds": secs,
            "frames": [10, 70],
            "matching": {"none": poses},
        }

    alone = [
        {"clients": 3, "same_frames": row(2.7, 180, 3.0)},
        {"clients": 6, "same_frames": row(5.4, 360, 6.0)},
        {"clients": 0, "poses_per_s": 0.0},  # owned no client: not run
    ]
    together = {"same_frames": row(9.0, 540, 10.0)}
    got = same_frames_comparison(alone, together)
    assert got["servers_cpu_ms_per_pose"]["alone"] == pytest.approx(15.0)
    assert got["servers_cpu_ms_per_pose"]["together"] == pytest.approx(9000 / 540)
    assert got["servers_cpu_per_pose_together_vs_alone"] == pytest.approx((9000 / 540) / 15)
    assert got["time_alone_sum_vs_together"] == pytest.approx(0.9)
    assert got["poses"] == {"alone": 540, "together": 540, "expected": 540}
    assert got["matching"]["alone"] == {"none": 540}
    assert same_frames_comparison(alone, {}) == {}
    assert same_frames_comparison(alone[:1] + [{"clients": 6}], together) == {}


def test_held_parts_keep_sessions_and_the_kill_part_runs_servers_as_deployed(tmp_path):
    """The servers' options as ``sfmloc serve`` parses them: lockstep parts (clients held
    for the same-frames phase) keep an idle session 600 s and wait for no frame budget; the
    kill part (paced clients, never held) runs the server's defaults (30 s, the budget on)."""
    from sfmloc.bench.scale import server_args
    from sfmloc.cli.main import build_parser
    from sfmloc.cli.serve import overrides_from_args
    from sfmloc.config import load_config
    from sfmloc.server.config import ServerConfig

    def conf(extra: tuple[str, ...]) -> ServerConfig:
        args = build_parser().parse_args(["serve", "--maps", str(tmp_path), *extra])
        return load_config(ServerConfig, None, environ={}, overrides=overrides_from_args(args))

    default = load_config(ServerConfig, None, environ={}, overrides={"maps": str(tmp_path)})
    eps = ["tcp/127.0.0.1:7447"]
    held = conf(server_args("s1", eps, wait_budget=False))
    assert held.idle_timeout_s == 600.0 and held.frame_budget_ms == 0
    assert held.server_id == "s1" and held.zenoh.connect == eps
    kill = conf(server_args("s1", eps, idle_timeout_s=None))
    assert kill.idle_timeout_s == default.idle_timeout_s == 30.0
    assert kill.frame_budget_ms == default.frame_budget_ms > 0
    assert kill.server_id == "s1" and kill.zenoh.connect == eps
