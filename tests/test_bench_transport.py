"""sfmloc bench-transport end to end: the command a user runs (README: `sfmloc bench-transport
--only overhead`), on the synthetic world with real server subprocesses and real Zenoh, so
that its report (each section formatted from the measured numbers) is executed by a test."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import cv2
import pytest


@pytest.fixture(scope="module")
def inputs(world, tmp_path_factory):
    """The world's map alone in a maps folder (the server loads all of it), and its frames as
    JPEG files (the command reads a camera's recording)."""
    d = tmp_path_factory.mktemp("bench-transport")
    shutil.copytree(world.maps_dir / "room", d / "maps" / "room")
    (d / "frames").mkdir()
    for k, path in enumerate(world.frames[:12]):
        cv2.imwrite(str(d / "frames" / f"{k:06d}.jpg"), cv2.imread(str(path)))
    return d


def _bench(world, d, json_out, *only: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable, "-m", "sfmloc", "bench-transport",
            "--maps", str(d / "maps"), "--map", "room",
            "--frames", str(d / "frames"), "--camera", world.camera_spec,
            "--only", ",".join(only), "--n", "8", "--repeat", "1", "--workers", "1",
            "--clients", "1", "--rate", "10", "--duration", "1",
            "--json", str(json_out),
        ],
        capture_output=True, text=True, timeout=180,
    )  # fmt: skip


def test_bench_transport_wire_overhead_and_clients(world, inputs, tmp_path):
    r = _bench(world, inputs, tmp_path / "b.json", "wire", "overhead", "clients")
    assert r.returncode == 0, r.stderr[-3000:]
    for heading in ("== wire:", "== overhead:", "== 1 clients x 10 Hz x 1 s, jpeg frames"):
        assert heading in r.stdout, r.stdout
    report = json.loads((tmp_path / "b.json").read_text())
    assert report["wire"]["jpeg_bytes"] > 0 and report["overhead"]["jpeg_e2e_ms_p50"] > 0
    (client,) = report["clients"]["clients"]
    assert client["sent"] > 0 and client["received"] > 0 and client["errors"] == 0


def test_bench_transport_engine_section(world, inputs, tmp_path):
    r = _bench(world, inputs, tmp_path / "b.json", "engine")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "== engine scaling:" in r.stdout and "1 Localizers in processes" in r.stdout, r.stdout
    assert json.loads((tmp_path / "b.json").read_text())["engine"]["process_fps"] > 0


def test_throughput_clients_loop_without_a_jump_and_send_spread_when_asked():
    """The throughput suite's frame loop and send phases (issue 10's drop diagnosis): "pingpong"
    steps to a neighbouring frame every time, the wrap included, where "wrap" jumps from the
    last frame to the first (a relocalization for every session that wraps); "spread" gives
    each client its own phase within a frame interval, "aligned" the same one to all."""
    from sfmloc.bench.transport import loop_order, phase_of

    n = 7
    ping = loop_order(n, "pingpong")
    assert sorted(set(ping)) == list(range(n))
    steps = [abs(b - a) for a, b in zip(ping, ping[1:] + ping[:1])]  # cyclic: the loop too
    assert steps == [1] * len(ping)
    wrap = loop_order(n, "wrap")
    assert wrap == list(range(n)) and abs(wrap[0] - wrap[-1]) == n - 1
    assert [phase_of(i, 4, "aligned") for i in range(4)] == [0.0] * 4
    spread = [phase_of(i, 4, "spread") for i in range(4)]
    assert spread == [0.0, 0.25, 0.5, 0.75]
    with pytest.raises(ValueError):
        loop_order(n, "shuffle")
    with pytest.raises(ValueError):
        phase_of(0, 4, "random")


def test_throughput_suite_streams_spread_without_jumps_and_keeps_an_aligned_wrapping_row(
    world, inputs, tmp_path
):
    """The throughput suite's own runs (real server processes, real Zenoh clients): by default
    independent cameras (spread sends, no jump), plus one stress row of clients sending together
    and jumping from the last frame to the first, labelled as such in the report."""
    from sfmloc.bench import report
    from sfmloc.bench.config import BenchConf
    from sfmloc.bench.throughput import run_throughput

    conf = BenchConf()
    assert (conf.client_phases, conf.frame_loop, conf.stress_clients) == ("spread", "pingpong", 8)
    t = run_throughput(
        tmp_path,
        inputs / "maps" / "room",
        inputs / "frames",
        world.camera_spec,
        [2],
        10.0,
        1.0,
        1,
        memory_workers=(),
        phases=conf.client_phases,
        frame_loop=conf.frame_loop,
        stress_clients=2,
    )
    (row,) = t["rows"]
    (stress,) = t["stress_rows"]
    assert (row["client_phases"], row["frame_loop"]) == ("spread", "pingpong")
    assert (stress["client_phases"], stress["frame_loop"]) == ("aligned", "wrap")
    assert row["clients"] == stress["clients"] == 2 and row["delivered_hz_total"] > 0
    assert stress["delivered_hz_total"] > 0
    cells = report.throughput_rows({"suites": {"throughput": t}})
    assert [c[0] for c in cells] == ["2", "2 (aligned, wrap)"]
    mode = report.throughput_mode(t)
    assert "independent cameras" in mode and "no jump" in mode and "stress row" in mode
