"""sfmloc bench's repeated replays (bench/reps.py): the published timing numbers are the
median over the reps with their min-max, the ratio to global-every-frame is taken rep by rep,
accuracy is rep 1's, and a rep whose poses differ from rep 1's is caught (fabricated records:
the arithmetic and the check; the bench's own run is test_bench_quick)."""

from __future__ import annotations

import dataclasses

import pytest

from sfmloc.bench import readme, report
from sfmloc.bench.config import OURS
from sfmloc.bench.main import summarize_suite, targets
from sfmloc.bench.reps import GEF, SIFT, SuiteRuns, differing_frames, summarize_repeated
from sfmloc.eval.metrics import FrameRecord
from sfmloc.transforms import Rigid3d
from test_bench import fake_records


def _scaled(recs: list[FrameRecord], k: float) -> list[FrameRecord]:
    """The same frames and poses, every time ``k`` times longer (another rep on a busier core)."""
    return [
        dataclasses.replace(
            r,
            latency_ms=r.latency_ms * k,
            cpu_ms=r.cpu_ms * k,
            timings_ms={s: v * k for s, v in r.timings_ms.items()},
        )
        for r in recs
    ]


def _runs(ours_k: list[float], gef_k: list[float]) -> SuiteRuns:
    ours, gef = fake_records(), fake_records(method="x", seed=1)[::5]
    sift = _scaled(fake_records(method="x", seed=2)[::5], 20.0)
    return SuiteRuns(
        [_scaled(ours, k) for k in ours_k],
        [_scaled(gef, k) for k in gef_k],
        sift,
        [0.5 + 0.1 * i for i in range(len(ours_k))],
        [[OURS, GEF, SIFT], [GEF, OURS], [OURS, GEF]][: len(ours_k)],
    )


def _summary(runs: SuiteRuns) -> dict:
    idx = [r.index for r in runs.sift]
    return summarize_repeated(runs, lambda recs: summarize_suite(recs, idx, 5, 2.0))


def test_the_median_rep_is_published_with_the_spread():
    runs = _runs([1.0, 1.3, 0.9], [3.0, 3.0, 3.6])
    one = summarize_suite(runs.first(), [r.index for r in runs.sift], 5, 2.0)
    s = _summary(runs)
    o, o1 = s["methods"][OURS], one["methods"][OURS]
    # rep 1 (x1.0) is the median of x1.0, x1.3, x0.9; its p99, CPU and stages too
    assert o["T_ms_mean"] == pytest.approx(o1["T_ms_mean"])
    assert o["T_ms_p99"] == pytest.approx(o1["T_ms_p99"])
    assert o["rate_hz"] == pytest.approx(1000 / o1["T_ms_mean"])
    assert s["stages_ms"]["detect"]["mean"] == pytest.approx(5.0)
    assert s["stages_ms"]["detect"]["frames"] == 50
    # global-every-frame: x3.0, x3.0, x3.6 -> median x3.0 (rep 1's); the ratio rep by rep:
    # rep 1's, /1.3 (ours slower, gef the same), x1.2/0.9 (both moved)
    assert s["methods"][GEF]["T_ms_mean"] == pytest.approx(one["methods"][GEF]["T_ms_mean"])
    base = one["ratios"][GEF]["rate_ratio"]
    sp = s["reps"]["spread"]
    assert sp["rate_ratio_gef"]["min"] == pytest.approx(base / 1.3)
    assert sp["rate_ratio_gef"]["max"] == pytest.approx(base * 1.2 / 0.9)
    assert s["ratios"][GEF]["rate_ratio"] == pytest.approx(base)
    # pycolmap-sift ran once: its ratio moves with ours only
    sift_base = one["ratios"][SIFT]["rate_ratio"]
    assert sp["rate_ratio_sift"]["max"] == pytest.approx(sift_base / 0.9)
    assert s["ratios"][SIFT]["rate_ratio"] == pytest.approx(sift_base)
    assert s["methods"][SIFT] == one["methods"][SIFT]
    # relocalization p95: global-every-frame's calls, median over the reps (x3.0, rep 1's)
    p95 = one["relocalization_ms"]["wall"]["p95"]
    assert s["relocalization_ms"]["wall"]["p95"] == pytest.approx(p95)
    assert sp["relocalization_p95_ms"]["max"] == pytest.approx(1.2 * p95)
    assert sp["ours_T_ms_mean"]["max"] == pytest.approx(1.3 * o1["T_ms_mean"])
    assert sp["load_average"] == {"median": 0.6, "min": 0.5, "max": 0.7}
    # accuracy is rep 1's, and every rep gave its poses
    for k in ("median_position_error_m", "wrong_poses", "F_loc", "recall_5cm_5deg_pct"):
        assert o[k] == o1[k]
    rp = s["reps"]["repeatable"]
    assert rp["identical"]
    assert rp["methods"][OURS]["frames_differing_per_rep"] == [0, 0]

    results = {"suites": {"redkitchen": {**s, "data": "synthetic"}}}
    tg = {t["target"]: t for t in targets(results)}
    same = tg["redkitchen: the same poses in every rep (accuracy is rep 1's)"]
    assert same["met"] and same["measured"] == (
        "sfmloc 50 frames x 3: identical; global-every-frame 10 frames x 3: identical"
    )
    gef_t = tg["redkitchen: our frame rate >= 3x global-every-frame's"]
    assert gef_t["measured"].endswith(
        f"; median of 3 reps of both, back to back, {base / 1.3:.1f}-{base * 1.2 / 0.9:.1f}x"
    )
    assert (
        "median of 3 reps of ours against one pycolmap-sift run"
        in (tg["redkitchen: our frame rate >= 10x pycolmap-sift's"]["measured"])
    )
    assert (
        "; median of 3 reps, "
        in tg["redkitchen: mean time per frame <= 33.3 ms (the paper's 'over 30 Hz')"]["measured"]
    )

    rows = report.reps_rows(s["reps"])
    assert [r[0] for r in rows] == ["1", "2", "3", "median", "min-max"]
    assert rows[1][2] == "gef, ours" and rows[0][2] == "ours, gef, sift"
    lines = "\n".join(report.reps_lines(s))
    assert "Repeats: our engine and global-every-frame ran 3 times" in lines
    assert "| min-max | 0.50-0.70 |" in lines
    sentence = report.reps_sentence("redkitchen", s["reps"])
    assert "median of 3 replays" in sentence and "identical in every rep" in sentence
    block = readme.render_block({"suites": {"redkitchen": s}, "machine": {}})
    assert f"- {sentence}." in block


def test_a_rep_with_another_pose_is_reported_not_hidden():
    runs = _runs([1.0, 1.0, 1.0], [3.0, 3.0, 3.0])
    r = runs.ours[2][7]
    assert r.cam_from_world is not None
    t = r.cam_from_world.translation.copy()
    t[0] = t[0] + 1e-12  # one bit is enough: the engine is repeatable, bit for bit
    runs.ours[2][7] = dataclasses.replace(r, cam_from_world=Rigid3d(r.cam_from_world.rotation, t))
    runs.gef[1][3] = dataclasses.replace(runs.gef[1][3], status="LOST", cam_from_world=None)
    assert differing_frames(runs.ours[0], runs.ours[2]) == [7]
    s = _summary(runs)
    rp = s["reps"]["repeatable"]
    assert not rp["identical"]
    assert rp["methods"][OURS]["frames_differing_per_rep"] == [0, 1]
    assert rp["methods"][OURS]["first_differing"] == [7]
    assert rp["methods"][GEF]["frames_differing_per_rep"] == [1, 0]
    (same,) = [t for t in targets({"suites": {"synthetic-walk": s}}) if "same poses" in t["target"]]
    assert same["met"] is False
    assert "sfmloc 50 frames x 3: 1 frames differ (first [7])" in same["measured"]
    assert "differ between reps" in report.reps_sentence("rk", s["reps"])


def test_one_rep_is_the_single_run_as_before():
    runs = _runs([1.0], [3.0])
    s = _summary(runs)
    one = summarize_suite(runs.first(), [r.index for r in runs.sift], 5, 2.0)
    assert {k: v for k, v in s.items() if k != "reps"} == one
    assert report.reps_lines(s) == []
    assert not [
        t for t in targets({"suites": {"synthetic-walk": s}}) if "same poses" in t["target"]
    ]


def _split(recs: list[FrameRecord], detect: float, match: float) -> list[FrameRecord]:
    """The same frames and poses, every frame's time split ``detect`` + ``match`` ms (its
    latency is the timers' total, as the engine's)."""
    return [
        dataclasses.replace(
            r,
            latency_ms=detect + match,
            cpu_ms=detect + match,
            timings_ms={"detect": detect, "match": match, "total": detect + match},
        )
        for r in recs
    ]


def test_the_stage_table_is_the_median_reps_and_sums(tmp_path):
    # three reps whose stage splits differ: per-cell medians would read detect 3, match 4,
    # total 6 (rows summing to 7); the median rep (total 6) is rep 3's 1 + 5
    ours, gef = fake_records(), fake_records(method="x", seed=1)[::5]
    sift = _scaled(fake_records(method="x", seed=2)[::5], 20.0)
    splits = [(4.0, 1.0), (3.0, 4.0), (1.0, 5.0)]  # totals 5, 7, 6
    gef_splits = [(20.0, 10.0), (5.0, 20.0), (30.0, 2.0)]  # totals 30, 25, 32: rep 1 the median
    runs = SuiteRuns(
        [_split(ours, d, m) for d, m in splits],
        [_split(gef, d, m) for d, m in gef_splits],
        sift,
        [0.5, 0.6, 0.7],
        [[OURS, GEF, SIFT], [GEF, OURS], [OURS, GEF]],
    )
    s = _summary(runs)
    st = s["stages_ms"]
    assert st["detect"]["mean"] + st["match"]["mean"] == pytest.approx(st["total"]["mean"])
    assert st["detect"]["share"] + st["match"]["share"] == pytest.approx(1.0)
    assert st["detect"]["mean"] == 1.0 and st["match"]["mean"] == 5.0
    assert st["total"]["mean"] == 6.0 == s["methods"][OURS]["T_ms_mean"]
    assert s["reps"]["stage_table_rep"] == 3
    # global-every-frame's stage line: its own median rep's (rep 1), summing to its mean
    assert s["reps"]["peer_stage_rep"] == {GEF: 1}
    assert s["peer_stages_ms"][GEF] == {"detect": 20.0, "match": 10.0}
    assert sum(s["peer_stages_ms"][GEF].values()) == s["methods"][GEF]["T_ms_mean"] == 30.0
    # the targets still read the median of the totals (6.0: rep 3's, the median of 5, 7, 6)
    suite = {**s, "data": "synthetic", "frames_replayed": 50, "start": 0, "files": {}}
    results = {"suites": {"redkitchen": suite}, "machine": {}}
    tg = {t["target"]: t for t in targets(results)}
    mean_t = tg["redkitchen: mean time per frame <= 33.3 ms (the paper's 'over 30 Hz')"]
    assert mean_t["measured"].startswith("6.0 ms (167 Hz)")
    # the report says which rep the table is, and its rows are that rep's
    md = report.write_report(results, tmp_path).read_text()
    assert "Where our time goes (rep 3 of 3, the one whose mean per frame is the median" in md
    assert "| detect | 1.00 | 17% |" in md and "| match | 5.00 | 83% |" in md
    assert "| total | 6.00 | 100% |" in md
    assert "global-every-frame (rep 1, its median rep): detect 20.0, match 10.0" in md
    assert "the stage table is one rep's, rep 3 " in md
    printed = report.summary_text(results)
    assert "Where our time goes, redkitchen (rep 3 of 3, the one whose" in printed


def test_an_even_count_of_reps_takes_the_lower_middle_rep():
    from sfmloc.bench.reps import median_rep

    assert median_rep([7.0, 5.0, 6.0]) == 2
    assert median_rep([7.0, 5.0]) == 1
    assert median_rep([5.0, 5.0, 5.0]) == 0
    assert median_rep([float("nan"), 5.0, 6.0]) == 2
