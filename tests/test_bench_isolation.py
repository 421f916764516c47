"""The process in which ``sfmloc bench`` times our engine builds no map and runs no SIFT before
the engine's reps (bench/prepare.py, bench/reps.py): the maps are built by a child process, the
pycolmap-sift peer runs after every rep of ours and global-every-frame. A process that built a
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
    from sfmloc.builder import build
    from sfmloc.synth import main as synth_main

    # In this process the builder and the renderer refuse: the bench must leave them to its
    # child (a fresh interpreter, untouched by the patch).
    monkeypatch.setattr(build, "main", _refuse)
    monkeypatch.setattr(synth_main, "run", _refuse)
    conf = quick_conf(suites=["synthetic-walk"], reps=3, tune=False)
    out = tmp_path / "out"
    res = json.loads(Path(bench_main(conf, out)).read_text())
    s = res["suites"]["synthetic-walk"]
    assert res["prepare_child_s"] > 0
    assert (out / "work" / "maps" / "synthetic-walk" / "manifest.json").is_file()
    # pycolmap-sift once, after the last rep; reps alternate their order
    assert s["reps"]["order"] == [[OURS, GEF], [GEF, OURS], [OURS, GEF, SIFT]]
    assert s["methods"][SIFT]["F"] == s["peer_frames"]["count"] > 0
    assert s["reps"]["repeatable"]["identical"]

    # The same bench again, maps reused: the child finds them stamped and builds nothing
    # (its builder is the real one; only its log would say), and so does this process.
    again = json.loads(
        Path(bench_main(conf.model_copy(update={"reuse": True, "reps": 1}), out)).read_text()
    )
    assert again["suites"]["synthetic-walk"]["reps"]["order"] == [[OURS, GEF, SIFT]]


def test_a_missing_data_folder_is_the_users_error_from_the_child(tmp_path):
    conf = quick_conf(suites=["redkitchen"], data=str(tmp_path / "nowhere"), tune=False)
    with pytest.raises(InputError, match="real data not found"):
        bench_main(conf, tmp_path / "out")
