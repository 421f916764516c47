"""Replay timing: the clock is --fps unless --timestamps names another source (numeric file
stems in a stated unit, or a TUM-style timestamps file), and frames with numeric, gapped or
nanosecond names keep tracking on the clock asked for."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from sfmloc.cameras import Camera
from sfmloc.errors import InputError
from sfmloc.eval.replay import replay
from sfmloc.io.frames import FrameSource
from sfmloc.map.bundle import MapBundle

N = 24  # frames replayed per clock


def _folder(tmp_path, world, names, indices=None):
    """Copies of the world's video frames under new names."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    indices = range(len(names)) if indices is None else indices
    for name, i in zip(names, indices):
        shutil.copyfile(world.frames[i], tmp_path / name)
    return tmp_path


def _touch(folder, names):
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"")
    return folder


# ----------------------------------------------------------------------------- the clock
def test_numeric_names_are_not_timestamps_unless_asked(tmp_path):
    folder = _touch(tmp_path / "f", [f"{2 * i:06d}.png" for i in range(5)])
    src = FrameSource(folder, fps=10)
    assert [src.stamp(i) for i in range(5)] == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])
    assert src.clock == "frame index / 10 fps" and src.gaps_over(1.0) == 0
    src = FrameSource(folder, fps=10, timestamps="stem-s")
    assert [src.stamp(i) for i in range(5)] == [0.0, 2.0, 4.0, 6.0, 8.0]
    assert src.clock == "file-name stems in s" and src.gaps_over(1.0) == 4
    assert src.nominal_fps == pytest.approx(0.5)


def test_stems_in_each_unit_and_nanosecond_precision(tmp_path):
    t0 = 1_700_000_000_123_456_789  # ns since the epoch: beyond float64's exact integers
    ns = [t0 + i * 33_333_333 for i in range(4)]
    src = FrameSource(_touch(tmp_path / "ns", [f"{t}.png" for t in ns]), timestamps="stem-ns")
    d = np.diff([src.stamp(i) for i in range(4)])
    assert np.allclose(d, 0.033333333, atol=1e-6)
    assert src.stamp(0) == pytest.approx(1_700_000_000.123456789, abs=1e-6)
    src = FrameSource(_touch(tmp_path / "ms", ["0.png", "33.png", "100.png"]), timestamps="stem-ms")
    assert [src.stamp(i) for i in range(3)] == pytest.approx([0.0, 0.033, 0.1])
    src = FrameSource(_touch(tmp_path / "us", ["5000000.png", "5033333.png"]), timestamps="stem-us")
    assert [src.stamp(i) for i in range(2)] == pytest.approx([5.0, 5.033333])
    # fractional seconds, as in TUM RGB-D folders
    src = FrameSource(
        _touch(tmp_path / "tum", ["1305031102.175304.png", "1305031102.211214.png"]),
        timestamps="stem-s",
    )
    assert src.stamp(1) - src.stamp(0) == pytest.approx(0.03591, abs=1e-5)


def test_timestamps_file_by_name_or_in_order(tmp_path):
    folder = _touch(tmp_path / "f", ["a.png", "b.png", "c.png"])
    rgb = tmp_path / "rgb.txt"
    rgb.write_text("# timestamp filename\n10.0 rgb/c.png\n9.5 rgb/b.png\n9.0 rgb/a.png\n")
    src = FrameSource(folder, timestamps=str(rgb))
    assert [src.stamp(i) for i in range(3)] == [9.0, 9.5, 10.0]
    assert src.clock == f"timestamps file {rgb}"
    tum = tmp_path / "traj.tum"
    tum.write_text("1.0 0 0 0 0 0 0 1\n1.1 0 0 0 0 0 0 1\n1.25 0 0 0 0 0 0 1\n")
    src = FrameSource(folder, timestamps=str(tum))
    assert [src.stamp(i) for i in range(3)] == [1.0, 1.1, 1.25]


@pytest.mark.parametrize(
    "names, spec, message",
    [
        (["frame-1.png", "frame-2.png"], "stem-s", "no numeric stem"),
        (["3.png", "2.png", "1a.png"], "stem-ms", "no numeric stem"),
        (["1.png", "1.0.png"], "stem-s", "do not increase"),
        (["1.png", "2.png"], "stem-hours", "neither one of stem-s"),
    ],
)
def test_bad_clocks_are_clear_errors(tmp_path, names, spec, message):
    folder = _touch(tmp_path / "f", names)
    with pytest.raises(InputError, match=message):
        FrameSource(folder, timestamps=spec)


def test_timestamps_file_errors(tmp_path):
    folder = _touch(tmp_path / "f", ["a.png", "b.png"])
    short = tmp_path / "short.txt"
    short.write_text("1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="1 timestamps for 2 frames"):
        FrameSource(folder, timestamps=str(short))
    missing = tmp_path / "missing.txt"
    missing.write_text("1.0 a.png\n2.0 z.png\n")
    with pytest.raises(InputError, match="no line for frame 'b.png'"):
        FrameSource(folder, timestamps=str(missing))
    with pytest.raises(InputError, match="must be positive"):
        FrameSource(folder, fps=0)


# ----------------------------------------------------------------------------- the engine
def _run(world, folder, **kw):
    src = FrameSource(folder, **kw)
    records, _ = replay(MapBundle(world.maps_dir / "room"), src, Camera.parse(world.camera_spec))
    return src, records


def _kept_tracking(records):
    """Only the first frame relocalizes; every later frame is tracked."""
    return records[0].status == "RELOCALIZED" and all(
        r.status == "TRACKING" and r.matching != "global" for r in records[1:]
    )


def test_numeric_names_keep_tracking_on_the_fps_clock(world, tmp_path):
    # frames named 000000, 000002, ...: the default clock is index / fps, not 2 s per frame
    folder = _folder(tmp_path / "even", world, [f"{2 * i:06d}.png" for i in range(N)])
    src, rec = _run(world, folder)
    assert src.clock == "frame index / 30 fps"
    assert [r.stamp for r in rec] == pytest.approx([i / 30 for i in range(N)])
    assert _kept_tracking(rec)
    # the same names read as seconds (asked for): 2 s gaps, every frame starts over
    src, rec = _run(world, folder, timestamps="stem-s")
    assert src.gaps_over(1.0) == N - 1
    assert all(r.status == "RELOCALIZED" for r in rec)


def test_nanosecond_and_gapped_names_keep_tracking_on_their_clock(world, tmp_path):
    t0 = 1_700_000_000_000_000_000
    folder = _folder(tmp_path / "ns", world, [f"{t0 + round(i * 1e9 / 30)}.png" for i in range(N)])
    src, rec = _run(world, folder, timestamps="stem-ns")
    assert src.clock == "file-name stems in ns"
    assert np.allclose(np.diff([r.stamp for r in rec]), 1 / 30, atol=1e-6)
    assert _kept_tracking(rec)
    # dropped frames: millisecond names with gaps of 2-3 frame intervals
    keep = [i for i in range(N + 12) if i % 3 != 1][:N]
    names = [f"{round(i * 1000 / 30)}.png" for i in keep]
    folder = _folder(tmp_path / "gapped", world, names, keep)
    src, rec = _run(world, folder, timestamps="stem-ms")
    assert [r.stamp for r in rec] == pytest.approx([round(i * 1000 / 30) / 1000 for i in keep])
    assert _kept_tracking(rec)


def test_replay_cli_names_the_clock(world, tmp_path, capsys):
    from sfmloc.cli.main import main

    folder = _folder(tmp_path / "ms", world, [f"{round(i * 1000 / 30)}.png" for i in range(8)])
    out = tmp_path / "summary.json"
    rc = main(
        [
            "replay",
            str(world.maps_dir / "room"),
            str(folder),
            "--camera",
            world.camera_spec,
            "--timestamps",
            "stem-ms",
            "--json",
            str(out),
        ]
    )
    assert rc == 0
    assert "clock                file-name stems in ms (30.3 frames/s)" in capsys.readouterr().out
    s = json.loads(out.read_text())
    assert s["clock"] == "file-name stems in ms" and s["clock_gaps_over_max"] == 0
    assert s["status_counts"]["LOST"] == 0
    # per-frame records say why a frame has no pose ("" for every posed frame here)
    assert [r["message"] for r in s["per_frame"]] == [""] * 8


def test_replay_cli_counts_the_gaps_of_the_frames_it_replayed(world, tmp_path, capsys):
    """The summary's clock gaps are those between the frames replayed (``--start``,
    ``--max-frames``), as the engine saw them, not the whole source's."""
    from sfmloc.cli.main import main

    # 30 Hz stamps in ms, one 2 s gap between frames 2 and 3 (over max_frame_gap_s)
    stamps_ms = [round(i * 1000 / 30) + (2000 if i >= 3 else 0) for i in range(9)]
    folder = _folder(tmp_path / "gap", world, [f"{t}.png" for t in stamps_ms])
    assert FrameSource(folder, timestamps="stem-ms").gaps_over(0.9) == 1
    base = ["replay", str(world.maps_dir / "room"), str(folder), "--camera", world.camera_spec]
    base += ["--timestamps", "stem-ms"]
    for window, gaps in (
        (["--start", "3"], 0),  # the gap is before the first frame replayed
        (["--max-frames", "3"], 0),  # after the last
        (["--start", "1", "--max-frames", "4"], 1),  # between frames 2 and 3, replayed
    ):
        out = tmp_path / "summary.json"
        assert main([*base, *window, "--json", str(out)]) == 0
        s = json.loads(out.read_text())
        assert s["clock_gaps_over_max"] == gaps, window
        printed = capsys.readouterr().out
        assert ("1 gaps over max_frame_gap_s 0.9 s reset tracking" in printed) == bool(gaps)
        if gaps:  # the engine relocalized there: the count is what it saw
            frames = s["per_frame"]
            assert [f["index"] for f in frames] == [1, 2, 3, 4]
            assert frames[2]["matching"] == "global"


def test_replay_cli_resets_the_session_every_n_frames(world, tmp_path):
    """``--reset-every N``: the tracker relocalizes on every N-th frame (its own
    relocalizations, measured as a reconnecting client sees them) and tracks the others."""
    from sfmloc.cli.main import main

    folder = _folder(tmp_path / "reset", world, [f"{i:06d}.png" for i in range(9)])
    out = tmp_path / "summary.json"
    args = ["replay", str(world.maps_dir / "room"), str(folder), "--camera", world.camera_spec]
    assert main([*args, "--reset-every", "4", "--json", str(out)]) == 0
    frames = json.loads(out.read_text())["per_frame"]
    assert [f["matching"] == "global" for f in frames] == [i % 4 == 0 for i in range(9)]
    assert [f["status"] for f in frames] == [
        "RELOCALIZED" if i % 4 == 0 else "TRACKING" for i in range(9)
    ]
