"""``sfmloc bench --quick`` end to end, as a user runs it: the command renders the synthetic
room, builds its maps, replays our engine and both peers (our engine and global-every-frame
twice, interleaved), runs two robust rows, a real ``sfmloc serve`` under Zenoh clients and the
map suite on its map, and writes results.json, report.md, the figures and the summary. Asserts
what it produces (fields, rows, targets evaluated), never its timings."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from sfmloc.bench import readme, report
from sfmloc.bench.config import OURS, PEERS, QUICK_ROBUST_ROWS, QUICK_SUITES

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> tuple[Path, dict, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("bench") / "out"
    # The timeout only stops a hung run (the quick bench takes about a minute on 2 cores).
    proc = subprocess.run(
        [sys.executable, "-m", "sfmloc", "bench", "--quick", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return out, json.loads((out / "results.json").read_text()), proc


def test_quick_runs_every_kind_of_suite_on_the_synthetic_room(quick_run):
    out, res, proc = quick_run
    assert res["format"] == "sfmloc-bench-results"
    assert res["command"] == f"sfmloc bench --quick --out {out}"
    assert res["conf"]["quick"] and res["conf"]["reps"] == 2
    assert set(res["suites"]) == set(QUICK_SUITES)
    assert {s["kind"] for s in res["suites"].values()} == {
        "localization",
        "robust",
        "throughput",
        "map",
    }
    for key in ("load_average_start", "load_average_end", "git", "cpus"):
        assert key in res["machine"]
    assert "results" in proc.stderr and "Table 2" in proc.stdout


def test_quick_localization_suite_reports_the_median_of_its_reps(quick_run):
    out, res, _ = quick_run
    s = res["suites"]["synthetic-walk"]
    ours = s["methods"][OURS]
    assert ours["F"] == 40 and s["frames_replayed"] == 40  # the quick room's video
    assert set(s["methods"]) == {OURS, *PEERS}
    assert s["peer_frames"] == {"count": 10, "stride": 4}
    for m in PEERS:
        assert s["methods"][m]["F"] == 10 and s["ratios"][m]["rate_ratio"] > 0
    assert ours["wrong_poses"] == 0 and ours["F_loc"] > 0  # exact ground truth
    reps = s["reps"]
    assert reps["count"] == 2 and len(reps["per_rep"]) == 2
    # pycolmap-sift once, after every rep of ours and global-every-frame (bench.reps)
    assert reps["order"] == [
        [OURS, "global-every-frame"],
        ["global-every-frame", OURS, "pycolmap-sift"],
    ]
    # the engine is repeatable: the second replay gave the first one's poses, frame by frame
    assert reps["repeatable"]["identical"]
    assert reps["repeatable"]["methods"][OURS] == {
        "frames": 40,
        "frames_differing_per_rep": [0],
        "first_differing": [],
    }
    # what is published is the median of the reps, inside their min-max
    sp = reps["spread"]
    assert ours["T_ms_mean"] == pytest.approx(sp["ours_T_ms_mean"]["median"])
    assert s["ratios"]["global-every-frame"]["rate_ratio"] == pytest.approx(
        sp["rate_ratio_gef"]["median"]
    )
    for v in sp.values():
        assert v["min"] <= v["median"] <= v["max"]
    assert s["stages_ms"]["total"]["frames"] == 40
    assert s["relocalization_ms"]["calls"] == 10
    for key in ("fig_per_frame", "fig_trajectory", "fig_compare"):
        assert (out / s["files"][key]).read_bytes()[:8] == PNG
    assert len(s["files"]["tum"]) == 6 and all((out / p).is_file() for p in s["files"]["tum"])
    frames = json.loads((out / "synthetic-walk" / f"frames-{OURS}.json").read_text())
    assert len(frames) == 40


def test_quick_robust_throughput_and_map_suites(quick_run):
    _, res, _ = quick_run
    rows = res["suites"]["robust"]["rows"]
    assert [r["name"] for r in rows] == list(QUICK_ROBUST_ROWS)
    assert all(r.get("status") != "crash" for r in rows), rows
    # walk-10hz pools 2 of its 3 offsets in a quick run (every one in a full run), and says so
    assert rows[1]["offsets"] == {"step": 3, "run": [0, 1], "of": 3}
    assert rows[1]["frames"] == rows[1]["ours"]["F"] == 20
    t = res["suites"]["throughput"]
    assert t["map"] == "synthetic-walk" and t["encoding"] == "png"
    assert [r["clients"] for r in t["rows"]] == [1, 2]
    assert [(r["clients"], r["client_phases"], r["frame_loop"]) for r in t["stress_rows"]] == [
        (2, "aligned", "wrap")
    ]
    for r in t["rows"]:
        assert r["delivered_hz_total"] > 0 and 0 <= r["dropped_pct"] <= 100
    assert [r["workers"] for r in t["memory"]["rows"]] == [1, 2]
    mp = res["suites"]["map"]
    assert mp["map"] == "synthetic-walk" and mp["descriptors"] > 0 and mp["rss_mb"] > 0


def test_quick_targets_report_and_readme_block(quick_run):
    out, res, proc = quick_run
    names = [t["target"] for t in res["targets"]]
    assert names[:3] == [
        "synthetic-walk: mean time per frame <= 33.3 ms (the paper's 'over 30 Hz')",
        "synthetic-walk: the same poses in every rep (accuracy is rep 1's)",
        "synthetic-walk: no wrong pose (any status but LOST; > 5% of the scene scale or > 10 deg)",
    ]
    assert "median of 2 reps" in res["targets"][0]["measured"]
    by_name = {t["target"]: t for t in res["targets"]}
    assert by_name[names[1]]["met"] is True and by_name[names[2]]["met"] is True
    robust = [n for n in names if n.startswith("robust")]
    assert robust, names
    for t in res["targets"]:
        assert t["met"] in (True, False, None) and t["measured"]
        assert f"{report.verdict(t).upper():7s}{t['target']}" in proc.stdout
    md = (out / "report.md").read_text()
    for heading in ("## Targets", "## synthetic-walk", "## throughput", "## map", "## Notes"):
        assert f"\n{heading}\n" in md
    assert "Repeats: our engine and global-every-frame ran 2 times" in md
    assert "| median |" in md and "| min-max |" in md
    assert "--quick: a smoke run" in md
    block = readme.render_block(res)
    assert report.reps_sentence("synthetic-walk", res["suites"]["synthetic-walk"]["reps"]) in block
    assert "**Throughput**" in block and "**Targets**" in block
