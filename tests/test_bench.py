"""sfmloc bench: the README's results block against the committed results, the table, report
and figure writers on fabricated records (writers only: reported numbers are always measured),
the SIFT peer against exact ground truth, and its ratio test."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

from sfmloc.bench import figures, readme, report
from sfmloc.bench.config import OURS
from sfmloc.bench.main import summarize_suite, targets, write_suite_files
from sfmloc.bench.sift_peer import ratio_test
from sfmloc.bench.stats import method_summary
from sfmloc.eval.metrics import FrameRecord, summarize, wrong_poses
from sfmloc.transforms import Rigid3d, pose_errors, rotmat_from_rotvec

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "docs" / "results.json"
PNG = b"\x89PNG\r\n\x1a\n"


# ----------------------------------------------------------------------------- README block
def test_readme_results_block_matches_the_committed_results():
    results = json.loads(RESULTS.read_text())
    block = readme.current_block((REPO / "README.md").read_text())
    assert block is not None, (
        "README.md has no <!-- results:begin --> ... <!-- results:end --> block"
    )
    expected = readme.render_block(results, "docs/results.json")
    assert block == expected, (
        "README.md's results block differs from docs/results.json: run "
        "`python -m sfmloc.bench.readme docs/results.json README.md`"
    )


def test_committed_results_are_summary_numbers_only():
    results = json.loads(RESULTS.read_text())
    # A size bound as a second guard (the list check below is the first): 188 kB at 7deee34;
    # the reps' medians, spreads and loads per localization suite (~2.8 kB each, benchrep)
    # took 584e48f's to 202 kB, all summary numbers.
    assert RESULTS.stat().st_size < 250_000
    assert results["format"] == "sfmloc-bench-results"

    def no_long_lists(x, path="results"):
        if isinstance(x, list):
            assert len(x) <= 64, f"{path} holds {len(x)} items: per-frame arrays do not belong here"
            for i, v in enumerate(x):
                no_long_lists(v, f"{path}[{i}]")
        elif isinstance(x, dict):
            for k, v in x.items():
                no_long_lists(v, f"{path}.{k}")

    no_long_lists(results)


def test_update_text_touches_only_the_block():
    block = readme.BEGIN + "\nnew\n" + readme.END
    text = (
        "# Title\n\nintro\n\n## Results\n\n"
        + readme.BEGIN
        + "\nold\n"
        + readme.END
        + "\n\n## Later\nmore\n"
    )
    out = readme.update_text(text, block)
    assert out == text.replace("\nold\n", "\nnew\n")
    appended = readme.update_text("# Title\n\nintro\n", block)
    assert appended == "# Title\n\nintro\n\n## Results\n\n" + block + "\n"
    assert readme.update_text(appended, block) == appended
    assert readme.update_text("", block) == "## Results\n\n" + block + "\n"
    # An existing heading without markers gets them (no second heading); text after it stays.
    assert (
        readme.update_text("# T\n\n## Results\n", block) == "# T\n\n## Results\n\n" + block + "\n"
    )
    assert (
        readme.update_text("# T\n## Results\n\nkept\n", block)
        == "# T\n## Results\n\n" + block + "\n\nkept\n"
    )


# ----------------------------------------------------------------------------- writers
def _pose(i: int) -> Rigid3d:
    R = rotmat_from_rotvec([0.0, 0.02 * i, 0.0])
    c = np.array([0.05 * i, 0.0, 0.01 * i])
    return Rigid3d(R, -R @ c)


def fake_records(n: int = 50, method: str = OURS, seed: int = 0) -> list[FrameRecord]:
    """A plausible sequence: one global frame, guided frames, one lost frame, one frame 1 m off
    while TRACKING."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        gt = _pose(i)
        matching = "global" if i == 0 else ("guided" if i % 7 == 0 else "none")
        status = "RELOCALIZED" if i == 0 else "TRACKING"
        if method != OURS:
            matching, status = "global", "RELOCALIZED"
        est = Rigid3d(gt.rotation, gt.translation + rng.normal(0, 0.01, 3))
        if i == 20:
            est = Rigid3d(gt.rotation, gt.translation + np.array([1.0, 0, 0]))
        if i == 30:
            est, status = None, "LOST"
        r = FrameRecord(
            i,
            f"frame-{i:06d}.png",
            i / 30.0,
            status,
            matching,
            10.0 + i % 5 + (90 if i == 0 else 0),
            50,
            900,
            500,
            120,
            timings_ms={"detect": 5.0, "track": 3.0, "total": 10.0},
            cpu_ms=9.0,
        )
        r.cam_from_world, r.gt_cam_from_world = est, gt
        if est is not None:
            r.position_error_m, r.rotation_error_deg = pose_errors(est, gt)
        out.append(r)
    return out


def test_method_summary_has_the_table2_columns():
    recs = fake_records()
    s = method_summary(recs, scene_scale=2.0)
    assert s["F"] == 50 and s["F_loc"] == 49
    assert s["M"] == 1 + len([i for i in range(1, 50) if i % 7 == 0])
    assert s["T_M_ms_mean"] == pytest.approx(
        np.mean([r.latency_ms for r in recs if r.matching != "none"])
    )
    assert s["T_ms_mean"] == pytest.approx(np.mean([r.latency_ms for r in recs]))
    assert s["wrong_poses"] == 1 and s["wrong_statuses"] == {"TRACKING": 1}
    assert 0.005 < s["median_position_error_m"] < 0.03
    assert s["recall_5cm_5deg_pct"] == pytest.approx(
        100 * 48 / 50
    )  # all but the lost and the wrong frame
    assert s["recall_relative_pct"] == pytest.approx(100 * 48 / 50)  # 2.5% of 2.0 is 5 cm
    assert s["median_position_error_rel"] == pytest.approx(s["median_position_error_m"] / 2.0)
    assert s["cpu_ms_mean"] == pytest.approx(9.0)


def test_suite_summary_report_figures_and_readme_on_fabricated_records(tmp_path):
    recs = {
        OURS: fake_records(),
        "global-every-frame": fake_records(method="x", seed=1)[::5],
        "pycolmap-sift": fake_records(method="x", seed=2)[::5],
    }
    for r in recs["pycolmap-sift"]:
        r.latency_ms *= 20
    # relocalization calls of 6, 12, ..., 60 ms wall (a third of that CPU): p95 57.3, over 40
    for k, r in enumerate(recs["global-every-frame"]):
        r.latency_ms, r.cpu_ms = 6.0 * (k + 1), 2.0 * (k + 1)
    idx = [r.index for r in recs["pycolmap-sift"]]
    suite = summarize_suite(recs, idx, 5, 2.0)
    rl = suite["relocalization_ms"]
    assert rl["calls"] == 10
    assert rl["wall"]["mean"] == pytest.approx(33.0) and rl["wall"]["p50"] == pytest.approx(33.0)
    assert rl["wall"]["p95"] == pytest.approx(57.3) and rl["wall"]["p99"] == pytest.approx(59.46)
    assert rl["cpu"]["p95"] == pytest.approx(19.1) and rl["cpu"]["max"] == pytest.approx(20.0)
    assert suite["same_frames"][OURS]["F"] == len(idx)
    assert suite["ratios"]["pycolmap-sift"]["rate_ratio"] > 10
    files = write_suite_files(
        "fake", recs, suite, idx, tmp_path, np.random.default_rng(0).normal(size=(500, 3))
    )
    for key in ("fig_per_frame", "fig_trajectory", "fig_compare"):
        data = (tmp_path / files[key]).read_bytes()
        assert data[:8] == PNG and len(data) > 10_000
    est = (tmp_path / "fake" / f"{OURS}.tum").read_text().splitlines()[1:]
    gt = (tmp_path / "fake" / f"{OURS}.gt.tum").read_text().splitlines()[1:]
    assert len(est) == len(gt) == 49 and [a.split()[0] for a in est] == [b.split()[0] for b in gt]
    thr = [
        {
            "clients": n,
            "offered_hz": 30.0 * n,
            "delivered_hz_total": min(30.0 * n, 70.0),
            "delivered_hz_per_client": min(30.0, 70.0 / n),
            "dropped_pct": max(0.0, 100 - 7000 / (30 * n)),
            "latency_ms_p50": 20.0 * n,
            "latency_ms_p99": 60.0 * n,
        }
        for n in (1, 2, 4, 8)
    ]
    assert figures.throughput(thr, "fake", tmp_path / "t.png").read_bytes()[:8] == PNG
    results = {
        "format": "sfmloc-bench-results",
        "command": "sfmloc bench --quick",
        "created_utc": "now",
        "wall_s": 1.0,
        "machine": {
            "cpus": 2,
            "cpu_model": "test",
            "load_average_start": 0.5,
            "load_average_end": 0.6,
        },
        "suites": {
            "redkitchen": {
                **suite,
                "data": "synthetic",
                "frames_replayed": 50,
                "start": 0,
                "files": files,
                "map": {"map_images": "fake", "images": 3, "points": 500, "descriptors": 4000},
            },
            "throughput": {
                "kind": "throughput",
                "rows": thr,
                "rate_hz": 30.0,
                "workers": 2,
                "duration_s": 1.0,
                "server": "fake",
            },
        },
    }
    results["targets"] = targets(results)
    assert {t["target"].split(":")[0] for t in results["targets"]} == {"redkitchen"}
    (reloc,) = [t for t in results["targets"] if "relocalization p95" in t["target"]]
    assert reloc["target"] == "redkitchen: relocalization p95 <= 40 ms" and not reloc["met"]
    assert reloc["measured"].startswith(
        "p95 57.3 ms (CPU 19.1), mean 33.0, p50 33.0, p99 59.5 ms over 10 calls"
    )
    text = report.summary_text(results)
    assert "redkitchen" in text and "pycolmap-sift" in text and "target" in text
    assert "Where our time goes, redkitchen" in text
    md = report.write_report(results, tmp_path).read_text()
    assert "fig-per-frame.png" in md and "| 8 |" in md
    # the per-stage table: detect 5 ms in every frame of 10, track 3 (50% and 30%)
    assert "| detect | 5.00 | 50% | 50 | 5.0 | 5.0 | 5.0 | 5.0 |" in md
    assert "| track | 3.00 | 30% | 50 |" in md
    assert "| wall | 33.0 | 33.0 | 57.3 | 59.5 | 60.0 |" in md
    assert "| cpu | 11.0 | 11.0 | 19.1 | 19.8 | 20.0 |\n\n" in md  # the table ends
    assert "Relocalization, redkitchen (10 calls, ms): wall mean 33.0 p50 33.0 p95 57.3" in text
    block = readme.render_block(results)
    assert (
        block.startswith(readme.BEGIN) and block.endswith(readme.END) and "pycolmap-sift" in block
    )


def test_per_frame_figure_of_a_run_without_ground_truth(tmp_path):
    recs = fake_records(20)
    for r in recs:
        r.gt_cam_from_world = None
        r.position_error_m = r.rotation_error_deg = None
    assert figures.per_frame(recs, "no gt", tmp_path / "a.png").read_bytes()[:8] == PNG
    assert figures.trajectory(recs, "no gt", tmp_path / "b.png").read_bytes()[:8] == PNG


# ----------------------------------------------------------------------------- wrong poses
def _record(i: int, status: str, dp: float | None, dr: float | None = 0.0) -> FrameRecord:
    r = FrameRecord(i, f"f{i}", i / 30.0, status, "none", 10.0, 50, 900, 500, 120)
    r.gt_cam_from_world = _pose(i)
    if dp is not None:
        r.cam_from_world = _pose(i)
        r.position_error_m, r.rotation_error_deg = dp, dr
    return r


def test_wrong_poses_count_every_status_but_lost():
    """A pose under any status but LOST (including statuses added later) counts when it is off
    by more than 5% of the scene scale or 10 deg; LOST frames never do."""
    recs = [
        _record(0, "TRACKING", 0.2),
        _record(1, "RELOCALIZED", 0.2),
        _record(2, "UNVERIFIED", 0.2),
        _record(3, "RELOCALIZED", 0.01, 11.0),
        _record(4, "LOST", None),
        _record(5, "TRACKING", 0.01),
        _record(6, "NEW_STATUS", 0.01, 10.5),
    ]
    s = summarize(recs, scene_scale=2.0)  # limit 0.1 units
    assert s["confident_wrong"] == 5
    assert s["confident_wrong_frames"] == ["f0", "f1", "f2", "f3", "f6"]
    assert s["wrong_statuses"] == {
        "TRACKING": 1,
        "RELOCALIZED": 2,
        "UNVERIFIED": 1,
        "NEW_STATUS": 1,
    }
    assert s["status_counts"] == {
        "TRACKING": 2,
        "RELOCALIZED": 2,
        "LOST": 1,
        "UNVERIFIED": 1,
        "NEW_STATUS": 1,
    }
    assert s["localized_frames"] == 6 and s["wrong_position_limit"] == pytest.approx(0.1)
    # A LOST frame with a (stale) pose error attached is still not a wrong pose.
    stale = _record(7, "LOST", 5.0)
    assert summarize([stale], scene_scale=2.0)["confident_wrong"] == 0
    assert [r.name for r in wrong_poses(recs, 2.0)] == ["f0", "f1", "f2", "f3", "f6"]


def test_wrong_pose_limit_scales_with_the_scene():
    """The same 0.2-unit error is wrong in a 2-unit scene, fine in a 5-unit one; scaling the
    scene and the errors together changes nothing."""
    recs = [_record(0, "TRACKING", 0.2), _record(1, "RELOCALIZED", 0.04)]
    assert summarize(recs, 2.0)["confident_wrong"] == 1
    assert summarize(recs, 5.0)["confident_wrong"] == 0
    assert summarize(recs, 0.7)["confident_wrong"] == 2  # limit 3.5 cm
    for k, metric in ((0.01, 1.0), (100.0, 0.0)):
        scaled = [_record(0, "TRACKING", 0.2 * k), _record(1, "RELOCALIZED", 0.04 * k)]
        s = summarize(scaled, 2.0 * k)
        assert s["confident_wrong"] == 1 and s["wrong_position_limit"] == pytest.approx(0.1 * k)
        # The scene-relative accuracy bound scales too (2.5% of the scale); 5 cm does not.
        assert s["within_relative_fraction"] == pytest.approx(0.5)
        assert s["within_5cm_5deg_fraction"] == pytest.approx(metric)
    with pytest.raises(ValueError, match="scene_scale"):
        summarize(recs, 0.0)
    with pytest.raises(ValueError, match="scene_scale"):
        wrong_poses(recs, float("nan"))


def test_replay_summary_prints_wrong_poses_and_every_status():
    from sfmloc.cli.replay import format_summary

    recs = [
        _record(0, "TRACKING", 0.2),
        _record(1, "UNVERIFIED", 0.3),
        _record(2, "LOST", None),
        _record(3, "TRACKING", 0.01),
    ]
    text = format_summary(summarize(recs, 2.0))
    assert "wrong poses          2 [TRACKING 1, UNVERIFIED 1]" in text
    assert "UNVERIFIED 1" in text.splitlines()[1] and "LOST 1" in text.splitlines()[1]
    assert "0.1 = 5% of the scene scale 2" in text
    assert "within 5 cm / 5 deg  25.0%" in text


# ----------------------------------------------------------------------------- SIFT peer
def test_ratio_test_compares_against_the_nearest_other_point():
    label = np.array([0, 0, 1, 2])  # descriptors 0 and 1 belong to point 0
    nn = np.array([[0, 1, 2], [2, 3, 0], [0, 1, -1]])
    d = np.array([[1.0, 1.1, 4.0], [1.0, 1.1, 9.0], [1.0, 1.0, 0.0]])  # squared distances
    q, p = ratio_test(d, nn, label, 0.8)
    # query 0: nearest other point at sqrt(4) -> 1 < 0.8 * 2 passes; query 1: 1 vs sqrt(1.1) fails;
    # query 2: no other point among its neighbours passes.
    assert q.tolist() == [0, 2] and p.tolist() == [0, 0]


@pytest.fixture(scope="module")
def sift_world(tmp_path_factory):
    from server_helpers import build_world
    from sfmloc.bench.sift_peer import SiftMap
    from sfmloc.builder import sfm
    from sfmloc.cameras import Camera
    from sfmloc.io.colmap import read_model
    from sfmloc.io.poses import write_colmap_list

    world = build_world(tmp_path_factory.getbasetemp())
    work = tmp_path_factory.mktemp("sift-peer")
    model = read_model(world.root / "synth" / "sparse")
    ims = sorted(model.images.values(), key=lambda im: im.name)
    poses = write_colmap_list(
        work / "poses.txt", [im.name for im in ims], [im.cam_from_world for im in ims]
    )
    cam = Camera.parse(world.camera_spec)
    conf = sfm.SfmConf(keep_workdir=True)
    rec = sfm.triangulate_known_poses(
        world.root / "synth" / "images", poses, cam, conf=conf, workdir=work / "sfm"
    )
    kept = next((work / "sfm").glob("sfmloc-sfm-*"))
    sm = SiftMap.from_sfm_workdir(kept, np.array(sorted(rec.points3D)), conf.model_dump())
    sm = SiftMap.load(sm.save(work / "sift-map.npz"))  # through the file, as the bench does
    return world, cam, sm


@pytest.mark.parametrize("search", ["exact", "hnsw"])
def test_sift_peer_pose_is_right_on_synthetic_frames(sift_world, search):
    from sfmloc.bench.config import SiftPeerConf
    from sfmloc.bench.sift_peer import SiftLocalizer

    world, cam, sm = sift_world
    assert sm.n_points > 500 and len(sm.desc) > 2 * sm.n_points
    loc = SiftLocalizer(sm, cam, SiftPeerConf(search=search))
    for k in (5, len(world.frames) - 5):
        res = loc.localize(world.gray[k])
        assert res.cam_from_world is not None, f"frame {k}: no pose ({res.matches} matches)"
        dp, dr = pose_errors(res.cam_from_world, world.gt_cam_from_world[k])
        assert dp < 0.02 and dr < 0.3, f"frame {k}: {dp * 100:.2f} cm, {dr:.2f} deg"
        assert res.inliers >= 50 and set(res.timings_ms) >= {"extract", "match", "pose", "total"}


def test_throughput_rows_show_the_worst_client_and_the_relocalized_share_of_poses():
    from sfmloc.bench.throughput import aggregate

    def client(received: int, statuses: dict[str, int], after_1s: dict[str, int]) -> dict:
        errors = received - sum(statuses.values())
        return {
            "sent": 300,
            "received": received,
            "drop_pct": 100.0 * (300 - received) / 300,
            "latency_ms_p50": 20.0,
            "latency_ms_p99": 40.0,
            "engine_ms_mean": 12.0,
            "errors": errors,
            "statuses": statuses,
            "statuses_after_1s": after_1s,
            "error_codes": {"DEADLINE_EXCEEDED": errors} if errors else {},
        }

    row = aggregate(
        [
            client(150, {"TRACKING": 140, "RELOCALIZED": 10}, {"TRACKING": 135, "RELOCALIZED": 5}),
            client(60, {"RELOCALIZED": 50}, {"TRACKING": 15, "RELOCALIZED": 45}),
        ],
        30.0,
    )
    # 50 poses of 300 frames at 30 Hz: its 10 error answers (DEADLINE_EXCEEDED) are not poses
    assert row["delivered_hz_worst_client"] == 5.0
    assert row["delivered_hz_per_client"] == 10.0 and row["delivered_hz_total"] == 20.0
    assert row["dropped_pct_worst_client"] == 250 / 3 and row["errors"] == 10
    assert row["dropped_pct"] == 100.0 * 400 / 600  # 200 poses of 600 frames
    assert row["relocalized_pct"] == 30.0  # 60 of the 200 poses without error
    # after the start's burst: 50 of the 200 poses of frames sent after the first second
    assert row["relocalized_pct_after_1s"] == 25.0
    assert row["error_codes"] == {"DEADLINE_EXCEEDED": 10}
    cells = report.throughput_rows({"suites": {"throughput": {"rows": [row]}}})[0]
    assert cells[-4:] == ["5.0", "30.0%", "25.0%", "10"]


def test_throughput_rows_show_the_engines_cpu_by_the_gap_since_the_previous_pose():
    """Poses are bucketed by the frames since their client's previous pose; each bucket's
    share and engine CPU per pose are over all clients' poses (weighted), and the report
    shows them; a run without gap records (older results) has no gap rows."""
    from sfmloc.bench.throughput import aggregate
    from sfmloc.bench.transport import GAP_BUCKETS, gap_bucket

    assert [gap_bucket(g) for g in (1, 2, 3, 4, 7, 8, 300)] == [
        "1",
        "2",
        "3",
        "4-7",
        "4-7",
        "8+",
        "8+",
    ]

    def client(gaps: dict[str, list[float]]) -> dict:
        n = int(sum(v[0] for v in gaps.values()))
        return {
            "sent": 300,
            "received": n,
            "latency_ms_p50": 20.0,
            "latency_ms_p99": 40.0,
            "engine_ms_mean": 12.0,
            "errors": 0,
            "statuses": {"TRACKING": n},
            "gaps": gaps,
        }

    row = aggregate(
        [
            client({"1": [60, 60 * 8.0], "2": [20, 20 * 9.0]}),
            client({"1": [10, 10 * 10.0], "4-7": [5, 5 * 20.0], "8+": [5, 5 * 60.0]}),
        ],
        30.0,
    )
    assert row["gaps"]["1"] == {"poses": 70, "pct": 70.0, "engine_cpu_ms": (480 + 100) / 70}
    assert row["gaps"]["3"]["poses"] == 0 and row["gaps"]["3"]["pct"] == 0.0
    assert list(row["gaps"]) == list(GAP_BUCKETS)
    assert row["gap_4plus_pct"] == 10.0  # 10 of the 100 poses
    assert row["engine_cpu_ms_gap_1_3"] == pytest.approx((480 + 180 + 100) / 90)
    assert row["engine_cpu_ms_gap_4plus"] == pytest.approx(40.0)
    results = {"suites": {"throughput": {"rows": [row]}}}
    assert report.gap_rows(results) == [
        [
            "2",
            "70.0% (8.3)",
            "20.0% (9.0)",
            "0.0% (n/a)",
            "5.0% (20.0)",
            "5.0% (60.0)",
            "8.44",
            "40.00",
        ]
    ]
    old = aggregate([{k: v for k, v in client({"1": [3, 30.0]}).items() if k != "gaps"}], 30.0)
    assert "gaps" not in old
    assert report.gap_rows({"suites": {"throughput": {"rows": [old]}}}) == []


def test_throughput_rows_show_the_servers_cpu_beyond_the_engines():
    """The engine's CPU per pose is the mean over every pose delivered (weighted by the
    clients' poses, not a mean of the clients' means), and the server's CPU beyond it is its
    CPU per pose (process + workers) minus that; a server that does not report the engine's
    CPU gives n/a, not a number."""
    from sfmloc.bench.throughput import aggregate, cpu_per_pose, outside_engine_ms

    def client(poses: int, engine_cpu_ms_sum: float) -> dict:
        return {
            "sent": 300,
            "received": poses,
            "latency_ms_p50": 20.0,
            "latency_ms_p99": 40.0,
            "engine_ms_mean": 12.0,
            "errors": 0,
            "statuses": {"TRACKING": poses},
            "engine_cpu_ms_sum": engine_cpu_ms_sum,
            "engine_cpu_poses": poses,
        }

    row = aggregate([client(300, 300 * 10.0), client(100, 100 * 14.0)], 30.0)
    assert row["engine_cpu_ms_mean"] == 11.0  # (3000 + 1400) / 400
    # 40 poses/s; the server process 0.04 cores (1 ms per pose), its workers 0.5 (12.5 ms)
    row.update(cpu_per_pose({"server": 0.04, "workers": 0.5, "clients": 0.1}, 40.0))
    row["outside_engine_ms"] = outside_engine_ms(row)
    assert row["outside_engine_ms"] == pytest.approx(1.0 + 12.5 - 11.0)
    cells = report.throughput_rows({"suites": {"throughput": {"rows": [row]}}})[0]
    i = report.THROUGHPUT_HEADER.index("engine CPU per pose (ms)")
    assert cells[i - 1 : i + 2] == ["13.50", "11.00", "2.50"]
    old = aggregate([{k: v for k, v in client(300, 0.0).items() if "engine_cpu" not in k}], 30.0)
    old.update(cpu_per_pose({"server": 0.04, "workers": 0.5}, 30.0))
    assert outside_engine_ms(old) != outside_engine_ms(old)  # NaN: not reported
    cells = report.throughput_rows({"suites": {"throughput": {"rows": [old]}}})[0]
    assert cells[i : i + 2] == ["n/a", "n/a"]
    # CPU seconds over the poses counted meanwhile, not CPU per second of the whole run over
    # the rate in the send time: 13 s of CPU for 1000 poses are 13 ms per pose
    got = cpu_per_pose(
        {"server": 0.05, "workers": 0.6}, 0.0, {"server": 1.0, "workers": 12.0}, 1000
    )
    assert got["cpu_ms_per_pose"] == {"server": 1.0, "workers": 12.0}
    assert got["capacity_hz"] == pytest.approx(1e3 * (os.cpu_count() or 1) / 13.0)


def test_throughput_rows_say_which_thread_of_the_server_spends_its_cpu():
    """``throughput.server_threads``: a thread kind's CPU and voluntary context switches
    between the streams' start and end, per delivered pose (read from /proc: a named thread
    of this process that burns 0.2 s of CPU shows up under its name), and the server
    process's CPU per frame sent; the report lists the kinds by CPU per pose."""
    import threading

    from sfmloc.bench.scale import threads_of
    from sfmloc.bench.throughput import server_threads
    from sfmloc.server.zygote import set_process_name

    burned = threading.Event()
    release = threading.Event()

    def burn() -> None:
        set_process_name("wiretest-burn-1")
        t0 = time.thread_time()
        while time.thread_time() - t0 < 0.2:
            pass
        burned.set()
        release.wait(30)

    start = threads_of([os.getpid()])
    t = threading.Thread(target=burn)
    t.start()
    assert burned.wait(60)
    end = threads_of([os.getpid()])
    release.set()
    t.join(30)
    res = {
        "threads": {"start": start, "end": end},
        "cpu_seconds": {"server": 0.6, "workers": 5.0},
        "clients": [{"sent": 300}, {"sent": 300}],
    }
    got = server_threads(res, 10)
    key = [k for k in got["server_threads"] if k.endswith("/wiretest-burn")]
    assert len(key) == 1, sorted(got["server_threads"])
    row = got["server_threads"][key[0]]
    assert row["threads"] == 1 and row["cpu_ms_per_pose"] >= 15.0  # 0.2 s over 10 poses
    assert list(got["server_threads"])[0] == key[0]  # the busiest kind first
    assert got["server_cpu_ms_per_frame_sent"] == pytest.approx(1.0)  # 0.6 s / 600 frames
    assert server_threads({"clients": []}, 10) == {}  # an older run: no thread samples
    results = {"suites": {"throughput": {"rows": [{"clients": 2, **got}]}}}
    (line,) = report.server_thread_lines(results)
    assert line.startswith("2 clients: server 1.000 ms per frame sent; ")
    assert key[0] in line


def test_global_every_frame_prepares_the_bundle_untimed(world, bundle, cam):
    """The peer computes the scope's per-bundle tables when it is made, as our engine's
    Localizer does, not in its first verifying (timed) call; and it localizes a real frame."""
    import cv2

    from sfmloc.bench.peers import global_every_frame
    from sfmloc.engine import EngineConf, scope

    conf = EngineConf()
    scope._cache.pop(bundle, None)
    fn = global_every_frame(bundle, cam, conf)
    assert (conf.scope_radius, conf.scope_min_duplicates) in scope._cache.get(bundle, {})
    k = len(world.frames) // 2
    out = fn(cv2.imread(str(world.frames[k]), cv2.IMREAD_GRAYSCALE))
    assert out.cam_from_world is not None and out.inliers >= 20
    pos_err, _ = pose_errors(out.cam_from_world, world.gt_cam_from_world[k])
    assert pos_err < 0.05 * bundle.scene_scale


def test_robust_cache_keys_hold_in_a_copied_work_folder(tmp_path):
    """A robust row's input inside the work folder is keyed relative to it, so a copied work
    folder (cp -r OUT/work OTHER/work, then --reuse) reuses its rows; one outside is keyed by
    its absolute path."""
    from sfmloc.bench.config import BenchConf
    from sfmloc.bench.robust import RobustData

    a, b = tmp_path / "a" / "work", tmp_path / "b" / "work"
    for w in (a, b):
        (w / "synthetic-walk" / "data").mkdir(parents=True)
    key_a = RobustData(BenchConf(), a, lambda *x: None)._in_work(a / "synthetic-walk" / "data")
    key_b = RobustData(BenchConf(), b, lambda *x: None)._in_work(b / "synthetic-walk" / "data")
    assert key_a == key_b == "synthetic-walk/data"
    outside = RobustData(BenchConf(), a, lambda *x: None)._in_work(tmp_path / "elsewhere")
    assert outside == str((tmp_path / "elsewhere").resolve())


def test_the_map_and_throughput_suites_serve_one_decided_map():
    """One decision names the map the map and throughput suites serve (the child prepares it,
    they read it): redkitchen's, except a smoke run's with a localization suite other than
    redkitchen, which serves its first suite's map rather than build redkitchen's."""
    from sfmloc.bench.config import BenchConf, quick_conf
    from sfmloc.bench.main import real_suites_map

    assert real_suites_map(BenchConf(), ["redkitchen", "synthetic-walk"]) == "redkitchen"
    assert real_suites_map(BenchConf(suites=["synthetic-walk", "map"]), ["synthetic-walk"]) == (
        "redkitchen"
    )
    assert real_suites_map(BenchConf(suites=["throughput"]), []) == "redkitchen"
    assert real_suites_map(BenchConf(suites=["redkitchen", "robust"]), ["redkitchen"]) is None
    quick = quick_conf()  # synthetic-walk, robust, throughput, map
    assert real_suites_map(quick, ["synthetic-walk"]) == "synthetic-walk"
    both = quick_conf(suites=["synthetic-walk", "redkitchen", "map"])
    assert real_suites_map(both, ["redkitchen", "synthetic-walk"]) == "redkitchen"
    assert real_suites_map(quick_conf(suites=["throughput"]), []) == "redkitchen"


def test_reuse_rebuilds_a_map_made_by_another_builder(tmp_path, caplog):
    """--reuse takes a cached map only when its input and the builder that made it are today's:
    a stamp from another builder (as every map cached before a builder change has) is rebuilt,
    and the log says which happened."""
    import logging
    import shutil

    from sfmloc.bench import suites
    from sfmloc.bench.config import BenchConf
    from sfmloc.bench.robust import RobustData

    data = RobustData(BenchConf(reuse=True), tmp_path, lambda *a: None)
    made: list[int] = []
    folder = tmp_path / "row"

    def make() -> None:
        made.append(1)

    caplog.set_level(logging.INFO, logger="sfmloc.bench.suites")
    data._cached(folder, {"base": "x"}, make)
    data._cached(folder, {"base": "x"}, make)
    assert len(made) == 1 and "reusing robust's row" in caplog.text
    stamp = folder / "robust-source.json"
    old = json.loads(stamp.read_text())
    assert old["builder"] == suites.builder_identity()
    stamp.write_text(json.dumps({**old, "builder": {**old["builder"], "source": "0" * 16}}))
    data._cached(folder, {"base": "x"}, make)
    assert len(made) == 2 and "rebuilding robust's row: built by another builder" in caplog.text
    data._cached(folder, {"base": "y"}, make)
    assert len(made) == 3 and "rebuilding robust's row: another input" in caplog.text

    # the identity covers the builder's code and not, e.g., the engine's
    root = Path(suites.__file__).resolve().parent.parent
    copy = tmp_path / "sfmloc"
    shutil.copytree(root, copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert suites.source_hash(copy) == suites.builder_identity()["source"]
    (copy / "engine" / "localizer.py").write_text("# another engine\n")
    assert suites.source_hash(copy) == suites.builder_identity()["source"]
    with open(copy / "builder" / "build.py", "a") as f:
        f.write("# another builder\n")
    assert suites.source_hash(copy) != suites.builder_identity()["source"]


def test_bench_video_encoder_names_a_missing_frame(tmp_path):
    # cv2.imread returns None for a missing file; the encoder read None.shape (AttributeError)
    # until mypy saw it
    from sfmloc.bench.builder import _encode_video
    from sfmloc.errors import ImageDecodeError

    with pytest.raises(ImageDecodeError, match="frame-000000.png"):
        _encode_video(tmp_path, ["frame-000000.png"], tmp_path / "v.avi")


def test_bench_image_reads_name_a_missing_or_broken_frame(tmp_path):
    # what the bench reads frames with (it handed cv2's None on to the engine before)
    import cv2

    from sfmloc.errors import ImageDecodeError
    from sfmloc.io.frames import decode_image, read_image

    broken = tmp_path / "frame-000001.png"
    broken.write_bytes(b"not a png")
    with pytest.raises(ImageDecodeError, match="frame-000002.png"):
        read_image(tmp_path / "frame-000002.png")
    with pytest.raises(ImageDecodeError, match="frame-000001.png"):
        read_image(broken, cv2.IMREAD_GRAYSCALE)
    with pytest.raises(ImageDecodeError, match="frame-000001.png"):
        decode_image(broken.read_bytes(), cv2.IMREAD_GRAYSCALE, str(broken))
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), np.full((4, 6), 7, np.uint8))
    assert read_image(good, cv2.IMREAD_GRAYSCALE).shape == (4, 6)
    assert decode_image(good.read_bytes(), cv2.IMREAD_GRAYSCALE, "good").sum() == 7 * 24
