"""sfmloc stream and the client API edges (issue 13, part 5): exit codes, error reasons, the
frames' own timestamps, the per-frame side file, clean errors for bad sources, a paced gRPC
stream, cameras as strings, and the README's in-process example run as written."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from server_helpers import running_server, server_config, zenoh_endpoint

REPO = Path(__file__).resolve().parents[1]


def _cli(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "sfmloc", *args], capture_output=True, text=True, timeout=timeout
    )


@pytest.fixture(scope="module")
def server(world):
    ep = zenoh_endpoint()
    with running_server(server_config(world, ep)) as srv:
        yield srv, ep


def _stream(world, ep, source, *extra: str) -> subprocess.CompletedProcess:
    return _cli(
        "stream",
        "--source",
        str(source),
        "--camera",
        world.camera_spec,
        "--zenoh-connect",
        ep,
        "--no-multicast",
        "--encoding",
        "png",
        "--wait-server",
        "20",
        *extra,
    )


def test_stream_stamps_frames_on_their_own_clock_with_a_side_file(world, server, tmp_path):
    _, ep = server
    # Frames named by their time in ms (a ROS/TUM-like export), 50 ms apart from 1000 s.
    src = tmp_path / "frames"
    src.mkdir()
    names = [f"{1_000_000 + 50 * k}.png" for k in range(12)]
    for name, f in zip(names, world.frames):
        shutil.copy(f, src / name)
    out = tmp_path / "t.tum"
    r = _stream(world, ep, src, "--map", "room", "--timestamps", "stem-ms", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "clock: file-name stems in ms" in r.stdout
    rows = [ln.split() for ln in (tmp_path / "t.tum.frames").read_text().splitlines()[1:]]
    assert [int(row[0]) for row in rows] == list(range(12))  # every frame, LOST ones too
    for row in rows:
        assert float(row[1]) == pytest.approx(1000 + 0.05 * int(row[0]), abs=1e-9)
        assert row[2] in ("TRACKING", "RELOCALIZED", "UNVERIFIED", "LOST") and len(row) == 42
    tum = [ln.split() for ln in out.read_text().splitlines()[1:]]
    localized = [row for row in rows if row[2] != "LOST"]
    assert [t[0] for t in tum] == [row[1] for row in localized] and len(tum) >= 10
    # Positions at their stamps: frame k's pose is at the ground truth of frame k.
    for t in tum:
        k = round((float(t[0]) - 1000) / 0.05)
        gt = world.gt_cam_from_world[k].inverse().translation
        assert np.linalg.norm(np.array([float(v) for v in t[1:4]]) - gt) < 0.05
    # The default clock of a folder: frame index / fps.
    r = _stream(
        world, ep, src, "--map", "room", "--fps", "10", "--max-frames", "4", "--out", str(out)
    )
    assert r.returncode == 0, r.stderr
    rows = [ln.split() for ln in (tmp_path / "t.tum.frames").read_text().splitlines()[1:]]
    assert {(int(row[0]), float(row[1])) for row in rows} <= {(k, k / 10) for k in range(4)}


def test_stream_unknown_map_and_nothing_localized_exit_1(world, server, tmp_path):
    _, ep = server
    r = _stream(world, ep, world.frames[0].parent, "--map", "atlantis", "--max-frames", "20")
    assert r.returncode == 1
    assert re.search(r"error: NOT_FOUND: .*atlantis.* \(\d+ frames?\)", r.stderr), r.stderr
    assert "does not host map 'atlantis'" in r.stderr
    assert int(r.stdout.split(" poses received for ")[1].split()[0]) < 20  # stopped early
    blank = tmp_path / "blank"
    blank.mkdir()
    for k in range(3):
        cv2.imwrite(str(blank / f"{k:03d}.png"), np.full((480, 640), 128, np.uint8))
    r = _stream(world, ep, blank, "--map", "room")
    assert r.returncode == 1 and "no frame was localized" in r.stderr, r.stderr
    assert "0 localized" in r.stdout


def test_stream_bad_sources_fail_cleanly_before_connecting(world, tmp_path):
    ep = zenoh_endpoint()  # nobody there: the source is checked first
    r = _stream(world, ep, tmp_path / "nope", "--map", "room")
    assert r.returncode == 2 and "no such file or folder" in r.stderr
    assert "Traceback" not in r.stderr
    (tmp_path / "empty").mkdir()
    r = _stream(world, ep, tmp_path / "empty", "--map", "room")
    assert r.returncode == 2 and "no images" in r.stderr and "Traceback" not in r.stderr
    (tmp_path / "broken.mp4").write_bytes(b"not a video")
    r = _stream(world, ep, tmp_path / "broken.mp4", "--map", "room")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    r = _stream(world, ep, world.frames[0].parent, "--map", "room", "--timestamps", "stem-s")
    assert r.returncode == 2 and "no numeric stem" in r.stderr


def test_stream_from_a_missing_camera_says_so_before_connecting(world):
    """`--source DEVICE` (README: `sfmloc stream --map lab --source 0 ...`) with no such camera:
    exit 2 naming the camera and where it would be, before any wait for a server."""
    device = 93
    if Path(f"/dev/video{device}").exists():
        pytest.skip(f"/dev/video{device} exists here: this test needs a camera index with none")
    r = _stream(world, zenoh_endpoint(), device, "--map", "room")  # nobody at the endpoint
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert f"cannot open camera {device}" in r.stderr and f"/dev/video{device}" in r.stderr
    assert "no server" not in r.stderr  # checked before connecting


def _source_args(source: str, timestamps: str | None = None):
    import argparse

    return argparse.Namespace(
        source=source, timestamps=timestamps, fps=None, pattern="*", encoding="png"
    )


def test_a_number_is_a_camera_even_beside_a_folder_of_that_name(world, tmp_path, monkeypatch):
    """`--source 93` with a folder named 93 in the working directory: the frames and their
    clock both come from camera 93, the note on stderr names the folder and how to stream it
    (./93), and ./93 streams the folder on its own clock. The CLI once took the folder's
    timestamps (and accepted --timestamps for them) and camera 93's frames."""
    from sfmloc.cli.stream import open_stamped_source
    from sfmloc.errors import InputError

    device = 93
    if Path(f"/dev/video{device}").exists():
        pytest.skip(f"/dev/video{device} exists here: this test needs a camera index with none")
    folder = tmp_path / str(device)
    folder.mkdir()
    for k in range(3):  # named by their time in s: --timestamps stem-s reads them
        shutil.copy(world.frames[k], folder / f"{1000 + k}.png")
    monkeypatch.chdir(tmp_path)
    for stamps in (None, "stem-s"):
        with pytest.raises(InputError) as err:
            frames, _ = open_stamped_source(_source_args(str(device), stamps))
            next(frames)
        if stamps is None:
            assert f"cannot open camera {device}" in str(err.value)
        else:  # a camera has its own clock: the folder's stamps are not taken for it
            assert "--timestamps applies to an image folder" in str(err.value)
    frames, clock = open_stamped_source(_source_args(f"./{device}", "stem-s"))
    got = [(f.name, f.stamp_ns) for f in frames]
    assert got == [(f"{1000 + k}.png", (1000 + k) * 10**9) for k in range(3)], got
    assert "stem" in clock, clock


def test_stream_cli_names_both_readings_of_a_number(world, tmp_path):
    """The note, as the CLI prints it (exit 2: no camera 93 here, before any wait)."""
    device = 93
    if Path(f"/dev/video{device}").exists():
        pytest.skip(f"/dev/video{device} exists here: this test needs a camera index with none")
    (tmp_path / str(device)).mkdir()
    shutil.copy(world.frames[0], tmp_path / str(device) / "a.png")
    r = subprocess.run(
        [sys.executable, "-m", "sfmloc", "stream", "--source", str(device), "--map", "room",
         "--camera", world.camera_spec, "--zenoh-connect", zenoh_endpoint(), "--no-multicast"],
        capture_output=True, text=True, timeout=180, cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert f"--source {device} is camera {device}" in r.stderr
    assert f"a folder named {device} is here too: write --source ./{device}" in r.stderr
    assert f"cannot open camera {device}" in r.stderr


def test_grpc_stream_is_paced_and_takes_a_camera_string(world, server):
    """Frames 1 s apart. On an idle machine each is answered before the next comes; on a
    starved one it is not: at load ~10 on 2 cores a relocalization (0.13-0.36 s of CPU here)
    took up to 5.3 s, and the server kept the newest frame (latest-frame-only), counting the one
    it skipped in its next answer's ``dropped`` (31 of 41 such streams in a row, load 7.7-12;
    this test asserted one pose each and failed 1 of 4 runs at load 8-10). What the stream
    promises, checked here: every frame is answered or counted skipped, the last one is
    answered, and an answer is a pose or an error that names why."""
    from sfmloc_client import LocalizationClient

    srv, _ = server
    n, rate = 5, 1.0
    with LocalizationClient(f"127.0.0.1:{srv.grpc_port}", timeout=60) as c:
        t0 = time.monotonic()
        poses = list(c.stream(world.png[:n], "room", world.camera_spec, encoding="png", rate=rate))
        elapsed = time.monotonic() - t0
        seqs = [p.seq for p in poses]
        assert seqs == sorted(set(seqs)) and seqs[-1] == n - 1, seqs
        # None lost: the answers and the skipped frames the last answer counts are all n.
        assert len(poses) + poses[-1].dropped == n, [(p.seq, p.dropped) for p in poses]
        assert elapsed >= (n - 1) / rate
        # Each a pose, or DEADLINE_EXCEEDED naming why: a frame its worker could not start
        # within frame_budget_ms, or one a starved worker had not finished at frame_hang_ms
        # (once in 27 such streams at load 8: a relocalization 10 s in the worker).
        for p in poses:
            assert p.localized or (p.error is not None and p.error.code == "DEADLINE_EXCEEDED"), p
        assert any(p.localized for p in poses)
        one = c.relocalize(world.png[3], "room", world.camera_spec, encoding="png")
        assert one.localized
        from sfmloc_client.errors import InputError

        with pytest.raises(InputError, match="rate must be positive"):
            list(c.stream(world.png[:1], "room", world.camera_spec, rate=0))


def test_readme_client_example_runs_as_written(world, tmp_path, monkeypatch):
    """README's gRPC client block (From Python, ...) against a real server, its address and
    map name replaced (the block ran in no test)."""
    text = (REPO / "README.md").read_text()
    block = text.split("<!-- client example -->", 1)[1].split("```python\n", 1)[1]
    code = block.split("```", 1)[0]
    assert '"SERVER:50051"' in code and '"lab"' in code
    (tmp_path / "frames").symlink_to(world.frames[0].parent)
    shutil.copy(world.root / "synth" / "camera.json", tmp_path / "camera.json")
    monkeypatch.chdir(tmp_path)
    with running_server(server_config(world, zenoh_endpoint())) as srv:
        code = code.replace("SERVER:50051", f"127.0.0.1:{srv.grpc_port}")
        code = code.replace('"lab"', '"room"')
        r = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=300
        )
    assert r.returncode == 0, r.stderr
    rows = [line.split(maxsplit=2) for line in r.stdout.splitlines()]
    seqs = [int(row[0]) for row in rows]
    assert len(rows) >= 10 and seqs == sorted(seqs) and seqs[-1] == len(world.frames) - 1
    assert all(row[2].startswith("Transform(quat_xyzw=") for row in rows if row[1] != "LOST")
    assert sum(row[1] in ("TRACKING", "RELOCALIZED") for row in rows) >= 0.8 * len(rows)


_EARLY_END = """
import sys
from sfmloc_client import LocalizationClient, open_source

target, frames, camera, map_name = sys.argv[1:]
with LocalizationClient(target) as client:
    for pose in client.stream(open_source(frames), map_name, camera, rate=30):
        if pose.seq >= 3:
            break
"""


def test_a_grpc_stream_ended_early_exits_cleanly(world, server):
    """A blocking gRPC stream that ends before its frames do (the server refuses it, or the
    caller breaks out) lets the process exit normally: the requests were read on grpc's thread,
    inside OpenCV when the interpreter exited (SIGABRT, exit -6: 7 of 8 runs with an unknown
    map, 2 of 4 breaking out, before the stream stopped them)."""
    srv, _ = server
    target = f"127.0.0.1:{srv.grpc_port}"
    frames = str(world.frames[0].parent)
    for map_name, code in (("atlantis", 1), ("room", 0), ("atlantis", 1), ("room", 0)):
        r = subprocess.run(
            [sys.executable, "-c", _EARLY_END, target, frames, world.camera_spec, map_name],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == code, r.stderr[-2000:]
        assert code == 0 or "NOT_FOUND" in r.stderr


def test_readme_in_process_example_runs_as_written(world, tmp_path, monkeypatch):
    text = (REPO / "README.md").read_text()
    block = text.split("<!-- in-process example -->", 1)[1].split("```python\n", 1)[1]
    code = block.split("```", 1)[0]
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "lab").symlink_to(world.maps_dir / "room")
    (tmp_path / "frames").symlink_to(world.frames[0].parent)
    shutil.copy(world.root / "synth" / "camera.json", tmp_path / "camera.json")
    monkeypatch.chdir(tmp_path)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 31 and lines[-1] == "single image: RELOCALIZED"
    statuses = [ln.split()[1] for ln in lines[:30]]
    assert statuses.count("TRACKING") >= 20


def test_cameras_as_strings_in_process(world, bundle):
    from sfmloc.engine import Localizer, relocalize

    loc = Localizer(bundle, str(world.root / "synth" / "camera.json"))
    assert loc.localize(world.gray[0], 0.0).localized
    assert relocalize(world.gray[5], world.camera_spec, bundle).localized
    with pytest.raises(TypeError, match="camera must be"):
        Localizer(bundle, 42)  # type: ignore[arg-type]
