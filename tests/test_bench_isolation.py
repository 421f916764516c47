"""The process in which ``sfmloc bench`` times our engine builds no map and runs no SIFT before
the engine's reps (bench/prepare.py, bench/reps.py): the maps are built by a child process (the
robust rows' too: sparser maps, peer SIFT maps, renders), the pycolmap-sift peer runs after
every rep of ours and global-every-frame. A process that built a
map in-process replays slower than a server worker (docs/development.md#bench-isolation). Real
runs on the synthetic room; nothing is timed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sfmloc.bench.config import OURS, quick_conf
from sfmloc.bench.main import main as bench_main
from sfmloc.bench.reps import GEF, SIFT
from sfmloc.errors import InputError


def _refuse(*_args, **_kwargs):
    raise AssertionError("a map built (or data rendered) in the bench's own process")


def test_the_bench_builds_its_maps_in_a_child_and_runs_sift_after_the_reps(tmp_path, monkeypatch):
    from sfmloc.bench import robust, robust_data
    from sfmloc.builder import build
    from sfmloc.synth import main as synth_main

    # In this process the builders and the renderers refuse: the bench must leave them to its
    # child (a fresh interpreter, untouched by the patch). A robust row that would build here
    # records the refusal as its crash.
    monkeypatch.setattr(build, "main", _refuse)
    monkeypatch.setattr(synth_main, "run", _refuse)
    monkeypatch.setattr(robust_data, "render_video", _refuse)
    monkeypatch.setattr(robust, "build_sift_map_of_model", _refuse)
    monkeypatch.setattr(robust, "build_known_poses_maps", _refuse)
    # density-3x builds a sparser map and the peer's SIFT map of it, flight-3hz renders the
    # flight video (and pools two of its offsets).
    conf = quick_conf(
        suites=["synthetic-walk", "robust"],
        robust_rows=["density-3x", "flight-3hz"],
        reps=3,
        tune=False,
    )
    out = tmp_path / "out"
    res = json.loads(Path(bench_main(conf, out)).read_text())
    s = res["suites"]["synthetic-walk"]
    assert res["prepare_child_s"] > 0
    assert (out / "work" / "maps" / "synthetic-walk" / "manifest.json").is_file()
    # pycolmap-sift once, after the last rep; reps alternate their order
    assert s["reps"]["order"] == [[OURS, GEF], [GEF, OURS], [OURS, GEF, SIFT]]
    assert s["methods"][SIFT]["F"] == s["peer_frames"]["count"] > 0
    assert s["reps"]["repeatable"]["identical"]
    rows = res["suites"]["robust"]["rows"]
    assert [(r["name"], r["status"]) for r in rows] == [
        ("density-3x", "ran"),
        ("flight-3hz", "ran"),
    ], [r.get("reason") for r in rows]
    assert (out / "work" / "maps" / "robust-density-3x" / "manifest.json").is_file()
    assert rows[1]["offsets"] == {"step": 10, "run": [0, 5], "of": 10}

    # The same bench again, maps reused: the child finds them stamped and builds nothing
    # (its builder is the real one; only its log would say), and so does this process.
    again = json.loads(
        Path(bench_main(conf.model_copy(update={"reuse": True, "reps": 1}), out)).read_text()
    )
    assert again["suites"]["synthetic-walk"]["reps"]["order"] == [[OURS, GEF, SIFT]]
    assert [r["status"] for r in again["suites"]["robust"]["rows"]] == ["ran", "ran"]


def test_a_missing_data_folder_is_the_users_error_from_the_child(tmp_path):
    conf = quick_conf(suites=["redkitchen"], data=str(tmp_path / "nowhere"), tune=False)
    with pytest.raises(InputError, match="real data not found"):
        bench_main(conf, tmp_path / "out")
