"""`sfmloc replay --plot` and `sfmloc stream --plot`: a trajectory PNG against ground truth, on
the synthetic world (exact ground truth) through a real server over Zenoh."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from server_helpers import running_server, server_config, zenoh_endpoint

pytest.importorskip("matplotlib", reason="the trajectory plot needs matplotlib (bench extra)")

# matplotlib's tab:red (the estimates) in BGR, as cv2 reads the PNG.
EST_BGR = np.array([40, 39, 214])


def _cli(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "sfmloc", *args], capture_output=True, text=True, timeout=timeout
    )


def _ink(path) -> tuple[int, int]:
    """Pixels of the estimate colour, and near-black pixels (ground truth line, axes, text)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 300
    red = int((np.abs(img.astype(int) - EST_BGR).max(axis=2) < 40).sum())
    black = int((img.max(axis=2) < 60).sum())
    return red, black


def test_replay_plot_against_groundtruth(world, tmp_path):
    png = tmp_path / "replay.png"
    r = _cli(
        "replay",
        str(world.maps_dir / "room"),
        str(world.frames[0].parent),
        "--camera",
        world.camera_spec,
        "--groundtruth",
        str(world.root / "synth" / "video_poses.txt"),
        "--max-frames",
        "15",
        "--plot",
        str(png),
    )
    assert r.returncode == 0, r.stderr
    assert f"plot                 {png}" in r.stderr
    red, black = _ink(png)
    assert red > 30 and black > 500


def test_stream_records_match_groundtruth_by_frame(world, tmp_path):
    """The plot's records pair each answered frame with its own ground truth: on exact synthetic
    ground truth the errors are millimetres (a pairing off by one frame would be centimetres)."""
    from server_helpers import camera, client_zenoh
    from sfmloc.cli._trajplot import StreamRecorder, write_plot
    from sfmloc_client import PoseSubscriber, open_source
    from sfmloc_client.streamer import FrameStreamer

    ep = zenoh_endpoint()
    rec = StreamRecorder()
    with running_server(server_config(world, ep)), client_zenoh(ep) as z:
        with (
            PoseSubscriber(z, "room", "plotter", callback=rec.pose) as poses,
            FrameStreamer(z, "room", "plotter", camera(world), encoding="png") as fs,
        ):
            assert fs.wait_for_server(10)
            source = open_source(str(world.frames[0].parent), passthrough="png")
            stats = fs.run(
                source,
                lockstep=True,
                poses=poses,
                pose_timeout=10,
                max_frames=20,
                on_sent=lambda seq, fr, _t: rec.sent(seq, fr),
            )
            poses.wait_for(stats.last_seq, 10)
    records = rec.records(str(world.root / "synth" / "video_poses.txt"), 30.0)
    assert [r.index for r in records] == list(range(20))  # lockstep: every frame answered
    assert [r.name for r in records] == [f.name for f in world.frames[:20]]
    errs = [r.position_error_m for r in records if r.position_error_m is not None]
    assert len(errs) >= 15 and float(np.median(errs)) < 0.01
    png = write_plot(records, tmp_path / "stream.png", "stream")
    red, black = _ink(png)
    assert red > 30 and black > 500


def test_stream_plot_cli_and_without_groundtruth(world, tmp_path):
    ep = zenoh_endpoint()
    png = tmp_path / "s.png"
    with running_server(server_config(world, ep)):
        r = _cli(
            "stream",
            "--map",
            "room",
            "--source",
            str(world.frames[0].parent),
            "--camera",
            world.camera_spec,
            "--max-frames",
            "10",
            "--zenoh-connect",
            ep,
            "--no-multicast",
            "--encoding",
            "png",
            "--plot",
            str(png),
        )
    assert r.returncode == 0, r.stderr
    assert f"plot: {png}" in r.stdout
    red, _ = _ink(png)
    assert red > 20  # the estimates alone set the view


def test_plot_needs_matplotlib_and_says_so(monkeypatch):
    from sfmloc.cli._trajplot import check_plot_path
    from sfmloc.errors import InputError

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import fails as if not installed
    with pytest.raises(InputError, match=r"sfmloc\[bench\]"):
        check_plot_path("x.png")


def test_plot_into_a_missing_folder_is_a_clear_error(tmp_path):
    from sfmloc.cli._trajplot import write_plot
    from sfmloc.errors import InputError

    with pytest.raises(InputError, match="does not exist"):
        write_plot([], tmp_path / "nope" / "x.png", "t")


def test_stream_records_leave_out_frames_the_server_skipped():
    """A frame dropped as stale gets no answer and no status in the plot; a LOST one is drawn
    as lost."""
    from types import SimpleNamespace

    from sfmloc.cli._trajplot import StreamRecorder
    from sfmloc_client.wire import PoseMessage, Transform

    rec = StreamRecorder()
    for k in range(4):
        rec.sent(k, SimpleNamespace(name=f"f{k}.png", stamp_ns=None))
    T = Transform((0.0, 0.0, 0.0, 1.0), (1.0, 2.0, 3.0))
    rec.pose(PoseMessage(seq=0, stamp_ns=0, status="TRACKING", cam_from_world=T, world_from_cam=T))
    rec.pose(PoseMessage(seq=2, stamp_ns=0, status="LOST"))
    out = rec.records(None, 30.0)
    assert [(r.index, r.name, r.status) for r in out] == [
        (0, "f0.png", "TRACKING"),
        (2, "f2.png", "LOST"),
    ]
    np.testing.assert_allclose(out[0].cam_from_world.translation, [1.0, 2.0, 3.0])
    assert out[1].cam_from_world is None
