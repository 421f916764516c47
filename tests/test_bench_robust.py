"""The robust bench suite: how its rows are built (scaled scenes, sparser maps, subsampled and
upsampled frames, renders at other sizes) on a tiny synthetic data set, the row summaries and
targets on fabricated records, and that a row that cannot be prepared is recorded and the suite
goes on. The suite's numbers themselves are only ever measured by `sfmloc bench`."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from sfmloc.bench import robust, robust_data
from sfmloc.bench.config import BenchConf
from sfmloc.bench.suites import Prepared
from sfmloc.cameras import Camera
from sfmloc.errors import InputError
from sfmloc.eval.groundtruth import load_groundtruth
from sfmloc.eval.metrics import FrameRecord
from sfmloc.io.colmap import read_model
from sfmloc.io.frames import FrameSource
from sfmloc.io.poses import read_poses
from sfmloc.transforms import Rigid3d, rotmat_from_rotvec


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A tiny `sfmloc synth` data set: 12 mapping views and 30 video frames at 160x120."""
    from server_helpers import room_scene
    from sfmloc.synth import preset
    from sfmloc.synth.main import run

    out = tmp_path_factory.mktemp("robust") / "synth"
    conf = preset("small", width=160, height=120, mapping_views=12, trajectory={"n_frames": 30})
    run(conf, out, scene=room_scene(conf.seed, conf.scene))
    return out


# ----------------------------------------------------------------------------- scene scale
@pytest.mark.parametrize("s", [0.01, 100.0])
def test_scaling_the_scene_scales_points_and_poses_and_keeps_observations(tiny, tmp_path, s):
    rec = read_model(tiny / "sparse")
    scaled = read_model(robust_data.write_scaled_model(tiny / "sparse", tmp_path / "sparse", s))
    assert set(scaled.points3D) == set(rec.points3D) and set(scaled.images) == set(rec.images)
    for pid, p in rec.points3D.items():
        q = scaled.points3D[pid]
        np.testing.assert_allclose(q.xyz, s * p.xyz, rtol=1e-9, atol=1e-12)
        assert q.track_image_ids.tolist() == p.track_image_ids.tolist()
    for iid, im in rec.images.items():
        jm = scaled.images[iid]
        assert jm.name == im.name  # the same image files
        np.testing.assert_allclose(
            jm.cam_from_world.rotation, im.cam_from_world.rotation, atol=1e-9
        )
        np.testing.assert_allclose(
            jm.cam_from_world.center, s * im.cam_from_world.center, rtol=1e-7, atol=1e-9
        )
        np.testing.assert_array_equal(jm.points2D, im.points2D)
        np.testing.assert_array_equal(jm.point3D_ids, im.point3D_ids)
    # The scaled model still explains the unchanged pixels exactly: same projections.
    cam = Camera.from_json(tiny / "camera.json")
    im = next(iter(rec.images.values()))
    ids = im.point3D_ids[im.point3D_ids >= 0][:20]
    a, _ = cam.project(im.cam_from_world, np.array([rec.points3D[i].xyz for i in ids]))
    b, _ = cam.project(
        scaled.images[im.image_id].cam_from_world, np.array([scaled.points3D[i].xyz for i in ids])
    )
    np.testing.assert_allclose(a, b, atol=1e-6)
    # Ground truth of the video scales the same way (centres x s, rotations kept).
    gt = read_poses(
        robust_data.scale_pose_list(tiny / "video_poses.txt", tmp_path / "gt.txt", s)
    ).by_key()
    for e in read_poses(tiny / "video_poses.txt"):
        np.testing.assert_allclose(
            gt[e.key].center, s * e.cam_from_world.center, rtol=1e-7, atol=1e-9
        )
        np.testing.assert_allclose(gt[e.key].rotation, e.cam_from_world.rotation, atol=1e-9)


def test_scene_scale_of_a_bundle_built_from_the_scaled_model_scales(tiny, tmp_path):
    from sfmloc.builder.build import BuildConf, assemble
    from sfmloc.map.bundle import MapBundle, write_bundle

    scales = {}
    for s in (1.0, 0.01):
        rec = read_model(robust_data.write_scaled_model(tiny / "sparse", tmp_path / f"m{s:g}", s))
        data, timings, info = assemble(rec, tiny / "images", BuildConf())
        path = write_bundle(
            data, tmp_path / "maps", f"room{int(s * 100)}", timings_s=timings, index_info=info
        )
        scales[s] = MapBundle(path).scene_scale
    assert scales[0.01] == pytest.approx(0.01 * scales[1.0], rel=1e-6)


# ----------------------------------------------------------------------------- map density
def test_every_kth_mapping_view_keeps_a_consistent_sparser_model(tiny, tmp_path):
    rec = read_model(tiny / "sparse")
    model, names = robust_data.write_subset_model(tiny / "sparse", tmp_path / "sub", 3)
    assert names == sorted(im.name for im in rec.images.values())[::3] and len(names) == 4
    sub = read_model(model)
    sub.check()
    assert sorted(im.name for im in sub.images.values()) == names
    assert 0 < len(sub.points3D) < len(rec.points3D)
    for pid, p in sub.points3D.items():
        assert len(p.track_image_ids) >= 2 and set(p.track_image_ids) <= set(sub.images)
        np.testing.assert_array_equal(p.xyz, rec.points3D[pid].xyz)
    # Every observation the subset keeps points at a kept point; the others are unlinked.
    for im in sub.images.values():
        linked = im.point3D_ids[im.point3D_ids >= 0]
        assert set(linked.tolist()) <= set(sub.points3D)
    with pytest.raises(InputError):
        robust_data.every_kth_image(rec, 0)


# ----------------------------------------------------------------------------- frame rate
def test_subsampling_to_10hz_keeps_every_third_frame_with_its_stamp(tiny, tmp_path):
    src = FrameSource(tiny / "video", fps=30)
    out = robust_data.subsample_frames(src.files, 3, tmp_path / "10hz")
    sub = FrameSource(out, fps=10)
    assert sub.names() == [f"frame-{i:06d}.png" for i in range(0, 30, 3)]
    for k in range(len(sub)):
        assert sub.stamp(k) == pytest.approx(src.stamp(3 * k))  # 0, 0.1, 0.2, ... s
    # Ground truth follows by name: frame k of the 10 Hz folder has original frame 3k's pose.
    gt = load_groundtruth(
        tiny / "video_poses.txt", sub.names(), [sub.stamp(i) for i in range(len(sub))], 10
    )
    full = read_poses(tiny / "video_poses.txt").by_key()
    for k, g in enumerate(gt):
        np.testing.assert_allclose(g.translation, full[f"frame-{3 * k:06d}.png"].translation)
    # The pixels are the original frames'.
    a = next(iter(sub)).image
    b = cv2.imread(str(src.files[0]), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(a, b)
    three = FrameSource(robust_data.subsample_frames(src.files, 10, tmp_path / "3hz"), fps=3)
    assert three.names() == ["frame-000000.png", "frame-000010.png", "frame-000020.png"]
    assert [three.stamp(i) for i in range(3)] == pytest.approx([0.0, 10 / 30, 20 / 30])


# ----------------------------------------------------------------------------- image size
def test_upsampled_frames_and_scaled_intrinsics_agree(tiny, tmp_path):
    cam = Camera.from_json(tiny / "camera.json")
    files = FrameSource(tiny / "video").files[:2]
    out, big = robust_data.upsample_frames(files, 3, tmp_path / "x3", cam)
    assert (big.width, big.height) == (480, 360)
    img = cv2.imread(str(out / files[0].name), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (360, 480)
    # A 3D point projects to 3x the pixel coordinate (COLMAP convention: corner at 0, centre 0.5).
    T = read_poses(tiny / "video_poses.txt").by_key()[files[0].name]
    X = T.inverse().apply(np.array([[0.1, -0.05, 2.0], [-0.3, 0.2, 3.0]]))
    a, _ = cam.project(T, X)
    b, _ = big.project(T, X)
    np.testing.assert_allclose(b, 3 * a, atol=1e-9)
    # Pixel (x, y) of the original is at (3x + 1, 3y + 1) of the upsampled image.
    small = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE).astype(float)
    diff = np.abs(img[1::3, 1::3].astype(float) - small)
    assert np.median(diff) < 3.0


def test_renders_at_another_size_share_the_poses_and_scale_the_focal(tiny, tmp_path):
    from sfmloc.synth import preset

    # The tiny data set's configuration (160x120), rendered at 128x96: the first frames have
    # the poses `sfmloc synth` gave them, and the focal length scales with the width.
    sconf = preset("small", width=160, height=120, mapping_views=12, trajectory={"n_frames": 30})
    b, cam_b = robust_data.render_video(sconf, tmp_path / "b", 3, 128, 96)
    cam = Camera.from_json(tiny / "camera.json")
    assert (cam_b.width, cam_b.height) == (128, 96)
    assert cam_b.focal[0] == pytest.approx(0.8 * cam.focal[0])
    assert cam_b.principal_point == pytest.approx((64.0, 48.0))
    assert sorted(p.name for p in b.glob("*.png")) == [f"frame-{i:06d}.png" for i in range(3)]
    assert cv2.imread(str(b / "frame-000002.png")).shape == (96, 128, 3)
    full = read_poses(tiny / "video_poses.txt").by_key()
    mine = read_poses(b / "video_poses.txt").by_key()
    assert sorted(mine) == [f"frame-{i:06d}.png" for i in range(3)]
    for k in mine:
        np.testing.assert_allclose(mine[k].translation, full[k].translation, atol=1e-6)
        np.testing.assert_allclose(mine[k].rotation, full[k].rotation, atol=1e-6)


# ----------------------------------------------------------------------------- rows
def test_rows_cover_the_issue_and_patterns_select_them():
    names = [r.name for r in robust.ROWS]
    assert len(names) == len(set(names))
    assert {r.group for r in robust.ROWS} == set(robust.GROUPS)
    assert [r.name for r in robust.select_rows(["motion"])] == [
        f"{k}-{hz}hz" for k in ("walk", "flight", "orbit") for hz in (30, 10, 3)
    ]
    assert [r.name for r in robust.select_rows(["size-*"])] == [
        "size-640x480",
        "size-1280x960",
        "size-3072x2048",
    ]
    assert {r.name for r in robust.select_rows(["map density"]) if r.real} == {
        "redkitchen-every-10th",
        "redkitchen-every-30th",
        "redkitchen-every-60th",
    }
    with pytest.raises(InputError, match="match no row"):
        robust.select_rows(["size-*", "nope"])


def test_peer_frames_are_spread_and_never_a_map_image(tmp_path):
    cam = Camera.pinhole(640, 480, 525, 525, 320, 240)
    prep = Prepared(
        "x", "real", tmp_path, cam, [], 0, 300, tmp_path, tmp_path, {"exclude_every": 10}
    )
    idx = robust.peer_frames(prep, 20)
    assert len(idx) == 20 and all(i % 10 for i in idx) and idx == sorted(idx)
    assert idx[0] < 20 and idx[-1] > 280
    synth = Prepared("y", "synthetic", tmp_path, cam, [], 0, 30, tmp_path, tmp_path, {})
    assert robust.peer_frames(synth, 100) == list(range(30))


def _recs(
    n: int, err: float, lost: set[int] = frozenset(), status: str = "TRACKING"
) -> list[FrameRecord]:
    out = []
    for i in range(n):
        gt = Rigid3d(rotmat_from_rotvec([0, 0.01 * i, 0]), np.array([0.1 * i, 0, 0]))
        r = FrameRecord(
            i, f"f{i}", i / 30, "LOST" if i in lost else status, "none", 10.0, 50, 900, 500, 100
        )
        r.gt_cam_from_world = gt
        if i not in lost:
            r.cam_from_world = gt
            r.position_error_m, r.rotation_error_deg = err * (1 + 0.01 * i), 0.1
        out.append(r)
    return out


def test_row_summary_and_targets_on_fabricated_records():
    ours = _recs(30, 0.01)
    peer = [r for r in _recs(30, 0.008, status="RELOCALIZED") if r.index % 3 == 0]
    s = robust.summarize_row(ours, peer, scene_scale=2.0)
    assert s["same_frames"] == 10 and s["ours"]["F"] == 30 and s["ours_same"]["F"] == 10
    t = robust.row_targets(s["ours_same"], s["peer_same"], s["ours"], None, False)
    assert t == {"localized": True, "median_error": True, "no_wrong_pose": True, "no_crash": True}
    # 2x the peer's error misses; one wrong pose (RELOCALIZED, > 5% of the scale) misses; a
    # lost frame the peer localized misses; a crash misses.
    worse = _recs(30, 0.016)
    worse[7].status, worse[7].position_error_m = "RELOCALIZED", 0.2
    for i in (3, 6):
        worse[i].status = "LOST"
    s = robust.summarize_row(worse, peer, scene_scale=2.0)
    t = robust.row_targets(s["ours_same"], s["peer_same"], s["ours"], "RuntimeError: x", False)
    assert t == {
        "localized": False,
        "median_error": False,
        "no_wrong_pose": False,
        "no_crash": False,
    }
    # A peer that localizes nothing leaves the error target to the other checks.
    none = [r for r in _recs(30, 0.0, lost=set(range(30)))]
    s = robust.summarize_row(ours, none, scene_scale=2.0)
    t = robust.row_targets(s["ours_same"], s["peer_same"], s["ours"], None, False)
    assert t["median_error"] and t["localized"]
    # A peer that ran on no frame (its map failed): ours is judged on all its frames.
    s = robust.summarize_row(ours, [], scene_scale=2.0)
    assert s["same_frames"] == 30 and s["ours_same"]["F"] == 30 and s["peer_same"]["F"] == 0
    t = robust.row_targets(s["ours_same"], s["peer_same"], s["ours"], None, False)
    assert all(t.values())


def test_rows_without_data_are_skipped_and_failing_rows_recorded(tmp_path, capsys):
    """No redkitchen data: skipped with the reason. Data that cannot be read: the row records
    the error and the suite goes on to the next row."""
    conf = BenchConf(data=tmp_path / "none", robust_rows=["redkitchen-every-30th"])
    out = robust.run_robust(conf, tmp_path / "work", lambda *a: None)
    (row,) = out["rows"]
    assert row["status"] == "skipped" and "redkitchen data not found" in row["reason"]
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "pgt_sfm_seq01.txt").write_text("not a pose file\n")
    cv2.imwrite(str(bad / "frame-000000.color.jpg"), np.zeros((48, 64), np.uint8))
    conf = BenchConf(data=bad, robust_rows=["redkitchen-every-30th", "redkitchen-every-60th"])
    out = robust.run_robust(conf, tmp_path / "work2", lambda *a: None, out=tmp_path / "o")
    assert [r["status"] for r in out["rows"]] == ["crash", "crash"]
    assert all("preparing the row" in r["reason"] for r in out["rows"])
    from sfmloc.bench.robust_report import main, robust_rows

    cells = robust_rows({"suites": {"robust": out}})
    assert [c[-1].split(":")[0] for c in cells] == ["crash", "crash"]
    # The rows so far are on disk after every row, and print as the table.
    assert main([str(tmp_path / "o" / "robust" / "rows-so-far.json")]) == 0
    printed = capsys.readouterr().out
    assert "redkitchen-every-30th" in printed and "redkitchen-every-60th" in printed


def _tiny_row(tiny: Path, tmp_path: Path, count: int) -> Prepared:
    """A robust row on the tiny data set: our map and the peer's SIFT map of its model (in
    tmp_path), its video's first ``count`` frames with their ground truth."""
    from sfmloc.bench.suites import build_sift_map_of_model
    from sfmloc.builder.build import BuildConf, assemble
    from sfmloc.map.bundle import write_bundle

    cam = Camera.from_json(tiny / "camera.json")
    data, timings, info = assemble(read_model(tiny / "sparse"), tiny / "images", BuildConf())
    bundle = write_bundle(data, tmp_path / "maps", "tiny", timings_s=timings, index_info=info)
    sift = build_sift_map_of_model(
        tiny / "sparse", tiny / "images", cam, tmp_path, tmp_path / "sift.npz", lambda *a: None
    )
    src = FrameSource(tiny / "video")
    gt = load_groundtruth(tiny / "video_poses.txt", src.names(), [src.stamp(i) for i in range(30)])
    return Prepared("robust/tiny", "synthetic", tiny / "video", cam, gt, 0, count, bundle, sift, {})


def test_a_row_runs_both_methods_on_the_same_frames_and_writes_per_frame_records(tiny, tmp_path):
    """One row end to end on the tiny data set: our engine on every frame as a video, the peer
    on evenly strided frames, both summarised on those, per-frame records written."""
    import json

    from sfmloc.bench.config import SiftPeerConf

    prep = _tiny_row(tiny, tmp_path, 12)
    row = robust.run_row(prep, 3, SiftPeerConf(), 600.0, lambda *a: None, tmp_path / "rows" / "t")
    assert row["ours_error"] is None and row["peer_error"] is None, (
        row["ours_error"],
        row["peer_error"],
    )
    assert row["ours"]["F"] == 12 and row["peer"]["F"] == 3 and row["same_frames"] == 3
    assert row["ours_same"]["F"] == 3 and row["peer_frames"] == 3 and row["image_size"] == "160x120"
    assert row["map"]["scene_scale"] > 0 and set(row["targets"]) == {
        "localized",
        "median_error",
        "no_wrong_pose",
        "no_crash",
    }
    ours = json.loads((tmp_path / "rows" / "t" / "frames-sfmloc.json").read_text())
    peer = json.loads((tmp_path / "rows" / "t" / "frames-pycolmap-sift.json").read_text())
    assert [f["index"] for f in ours] == list(range(12))
    assert [f["index"] for f in peer] == robust.peer_frames(prep, 3) == [2, 6, 10]


def test_engine_config_is_checked_named_in_the_suite_and_reaches_our_engine(tiny, tmp_path, caplog):
    """--engine-config: an unknown key is refused naming it (before any suite runs, from the
    CLI too); a valid file is recorded in the suite and the report note, and its settings reach
    our engine in a row (a 50x higher Harris threshold detects fewer corners on every frame),
    not the peer."""
    import json

    from sfmloc.bench.config import SiftPeerConf
    from sfmloc.bench.robust_report import robust_note
    from sfmloc.cli.main import main as cli_main
    from sfmloc.config import ConfigError

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"gamma": 0.05, "no_such_setting": 1}))
    with pytest.raises(ConfigError, match="no_such_setting"):
        robust.load_engine_conf(bad)
    out_dir = tmp_path / "cli-out"
    argv = ["bench", "--suites", "robust", "--engine-config", str(bad), "--out", str(out_dir)]
    assert cli_main(argv) != 0
    assert "no_such_setting" in caplog.text and "Extra inputs are not permitted" in caplog.text
    assert not (out_dir / "results.json").exists()
    with pytest.raises(ConfigError, match="no_such_setting"):  # the suite itself checks too
        robust.run_robust(
            BenchConf(data=tmp_path / "none", robust_engine_config=bad), tmp_path / "w0", print
        )

    good = tmp_path / "fewer.json"
    good.write_text(json.dumps({"gamma": 0.05}))
    caplog.clear()
    argv = ["bench", "--suites", "map", "--engine-config", str(good), "--out", str(out_dir)]
    assert cli_main(argv) != 0  # not silently ignored by the other suites
    assert "robust suite only" in caplog.text and not (out_dir / "results.json").exists()
    assert (
        robust.load_engine_conf(good).gamma == 0.05 and robust.load_engine_conf(None).gamma < 0.05
    )
    conf = BenchConf(
        data=tmp_path / "none", robust_rows=["redkitchen-every-30th"], robust_engine_config=good
    )
    suite = robust.run_robust(conf, tmp_path / "work", lambda *a: None)
    assert suite["engine_config"] == {"file": str(good), "settings": {"gamma": 0.05}}
    note = robust_note({"suites": {"robust": suite}})
    assert f"engine config {good}" in note and '"gamma": 0.05' in note
    default = robust.run_robust(
        BenchConf(data=tmp_path / "none", robust_rows=["redkitchen-every-30th"]),
        tmp_path / "w2",
        lambda *a: None,
    )
    assert default["engine_config"] is None
    assert "engine config" not in robust_note({"suites": {"robust": default}})

    prep = _tiny_row(tiny, tmp_path, 8)
    frames = {}
    for name, ec in (("default", None), ("fewer", robust.load_engine_conf(good))):
        files = tmp_path / "rows" / name
        robust.run_row(prep, 2, SiftPeerConf(), 600.0, lambda *a: None, files, ec)
        frames[name] = {
            m: json.loads((files / f"frames-{m}.json").read_text())
            for m in ("sfmloc", "pycolmap-sift")
        }
    ours_d = [f["detected"] for f in frames["default"]["sfmloc"]]
    ours_f = [f["detected"] for f in frames["fewer"]["sfmloc"]]
    assert len(ours_d) == len(ours_f) == 8
    assert all(f < d for f, d in zip(ours_f, ours_d)), (ours_f, ours_d)
    peer = [
        [(f["index"], f["status"], f["inliers"]) for f in frames[n]["pycolmap-sift"]]
        for n in ("default", "fewer")
    ]
    assert peer[0] == peer[1]  # the peer is not given the engine config


def test_localized_not_wrong_leaves_the_wrong_poses_out():
    """The table's "localized, not wrong" column: a method's localized fraction counts its
    wrong poses (the peer's on a thin map: 19 of 20 localized, 5 wrong), this one does not."""
    from sfmloc.bench.robust_report import ROBUST_HEADER, right_pct

    assert right_pct({"F": 20, "F_loc": 19, "wrong_poses": 5}) == 70.0
    assert right_pct({"F": 20, "F_loc": 16, "wrong_poses": 0}) == 80.0
    assert math.isnan(right_pct({"F": 0, "F_loc": 0, "wrong_poses": 0}))
    assert ROBUST_HEADER.index("localized, not wrong") == ROBUST_HEADER.index("localized") + 1


# ----------------------------------------------------------------------------- low-rate offsets
def test_low_rate_rows_run_every_offset_or_an_even_few():
    assert robust.row_offsets(10, None) == list(range(10))
    assert robust.row_offsets(3, None) == [0, 1, 2]
    assert robust.row_offsets(10, 2) == [0, 5]
    assert robust.row_offsets(3, 2) == [0, 1]
    assert robust.row_offsets(3, 7) == [0, 1, 2] and robust.row_offsets(10, 1) == [0]
    # The thin map at 3 Hz, walk and flight, in the map density group (``density-*`` runs it).
    thin = [r.name for r in robust.select_rows(["density-*"]) if r.name.endswith("hz")]
    assert thin == ["density-6x-walk-3hz", "density-6x-flight-3hz"]


def _offset_row(base: Prepared, tiny: Path, tmp_path: Path, run: list[int]) -> Prepared:
    """The tiny video at 10 Hz (every 3rd frame), one stream per offset in ``run``, as
    ``robust._low_rate_row`` makes it: the row's frames are the 30 Hz video's (``base``'s)."""
    files = FrameSource(tiny / "video").files
    streams = [
        str(robust_data.subsample_frames(files[o:], 3, tmp_path / f"10hz-o{o}")) for o in run
    ]
    info = {"offsets": {"hz": 10, "step": 3, "run": run, "streams": streams}}
    return Prepared(
        "robust/tiny-10hz",
        "synthetic",
        base.frames_dir,
        base.camera,
        base.groundtruth,
        0,
        30,
        base.bundle_path,
        base.sift_map_path,
        info,
    )


def test_a_low_rate_row_pools_its_offsets_frame_by_frame(tiny, tmp_path):
    """Every offset's stream replayed by a fresh engine at 10 Hz and pooled: each 30 Hz frame
    once, under its own index, name and ground truth, in frame order. A row of fewer offsets
    (--quick) runs theirs only, draws the peer's frames from them and says so."""
    import json

    from sfmloc.bench.config import SiftPeerConf
    from sfmloc.bench.robust_report import robust_rows

    full = read_poses(tiny / "video_poses.txt").by_key()
    base = _tiny_row(tiny, tmp_path, 30)
    prep = _offset_row(base, tiny, tmp_path, [0, 1, 2])
    recs, err, stopped = robust.run_ours(prep, _bundle(prep), 600.0, lambda *a: None)
    assert err is None and not stopped
    assert [r.index for r in recs] == list(range(30))
    for r in recs:
        assert r.name == f"frame-{r.index:06d}.png"
        np.testing.assert_allclose(
            r.gt_cam_from_world.translation, full[r.name].translation, atol=1e-12
        )
    # Each stream's clock is 10 Hz from its own first frame (the engine sees 0.1 s gaps).
    assert [round(r.stamp, 6) for r in recs if r.index % 3 == 1] == [
        round(k / 10, 6) for k in range(10)
    ]
    summary = robust.summarize_row(recs, [], 1.0)
    assert summary["ours"]["F"] == 30
    row = {"offsets": {"step": 3, "run": [0, 1, 2], "of": 3}, "status": "ran"}
    row.update(summary, ours_error=None, ours_stopped=False, peer_error=None, met=True)
    assert robust.row_line(row).startswith("offsets 0-2 of every 3rd frame, pooled: ")

    # Two of the three offsets: their 20 frames only, the peer's among them, said in the row.
    few_prep = _offset_row(base, tiny, tmp_path / "few", [0, 1])
    few = robust.run_row(few_prep, 6, SiftPeerConf(), 600.0, lambda *a: None, tmp_path / "f")
    assert few["ours_error"] is None and few["peer_error"] is None
    assert few["frames"] == 20 and few["ours"]["F"] == 20 and few["fps"] == 10
    assert few["offsets"] == {"step": 3, "run": [0, 1], "of": 3}
    ours = json.loads((tmp_path / "f" / "frames-sfmloc.json").read_text())
    assert [f["index"] for f in ours] == [i for i in range(30) if i % 3 != 2]
    peer = json.loads((tmp_path / "f" / "frames-pycolmap-sift.json").read_text())
    assert {f["index"] % 3 for f in peer} == {0, 1} and few["same_frames"] == 6
    few.update(name="tiny-10hz", group="motion", text="", status="ran")
    assert "offsets 0, 1 of every 3rd frame (2 of its 3 offsets only)" in robust.row_line(few)
    suite = {"rows": [few], "frames": {"budget_s": 600.0}}
    (cells,) = robust_rows({"suites": {"robust": suite}})
    assert cells[3] == "10 (2 of 3 offsets)"


def _bundle(prep: Prepared):
    from sfmloc.map.bundle import MapBundle

    return MapBundle(prep.bundle_path, verify=False)


def test_a_rows_step_reads_as_an_ordinal():
    # (the 10 Hz rows read "every 3th frame" before)
    from sfmloc.bench.robust import ordinal, row_specs

    assert [ordinal(n) for n in (1, 2, 3, 4, 10, 11, 12, 13, 21, 22, 23, 30, 111)] == [
        "1st", "2nd", "3rd", "4th", "10th", "11th", "12th", "13th", "21st", "22nd", "23rd",
        "30th", "111th",
    ]  # fmt: skip
    texts = [spec.text for spec in row_specs()]
    assert any("every 3rd frame" in t for t in texts)
    assert not any("3th" in t for t in texts)
