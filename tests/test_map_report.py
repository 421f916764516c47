"""The builder's map report and sparse-map warning, and ``--min-track-length``: numbers checked
on a hand-made map with exact geometry, and on maps triangulated at known poses from the
ray-cast room corner of test_mapping_sfm (points against the true planes)."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from sfmloc.builder import build, sfm
from sfmloc.cameras import Camera
from sfmloc.config import merge_presets
from sfmloc.io.poses import write_colmap_list
from sfmloc.map.bundle import MapBundle
from sfmloc.map.report import SPARSE_POINTS_PER_IMAGE, map_report
from sfmloc.transforms import Rigid3d
from test_mapping_sfm import CAM, Corner, arc_poses


def _at_pixels(cam: Camera, uv: list[tuple[float, float]], depth: float) -> np.ndarray:
    (fx, fy), (cx, cy) = cam.focal, cam.principal_point
    uv = np.asarray(uv, np.float64)
    x, y = (uv[:, 0] - cx) / fx * depth, (uv[:, 1] - cy) / fy * depth
    return np.stack([x, y, np.full(len(uv), depth)], 1)


def test_report_numbers_on_a_hand_made_map():
    cam = Camera.pinhole(640, 480, 500.0, 500.0, 320.0, 240.0)
    # Image 0 at the origin, image 1 shifted 0.1 along x (its pixels move 25 px left at depth 2).
    poses = [Rigid3d(np.eye(3), np.zeros(3)), Rigid3d(np.eye(3), np.array([-0.1, 0.0, 0.0]))]
    X = _at_pixels(cam, [(40, 40), (45, 50), (600, 440), (330, 250), (330, 250)], 2.0)
    X[4, 2] = -2.0  # behind both cameras: never counted as covering a cell
    # image 0 sees points 0-4; image 1 sees points 0, 2, 3 and 4
    ptr = np.array([0, 5, 9])
    idx = np.array([0, 1, 2, 3, 4, 0, 2, 3, 4])
    r = map_report(X, ptr, idx, [cam], np.array([0, 0]), poses)
    assert r["images"] == 2 and r["points"] == 5
    assert r["points_per_image"] == {"min": 4, "median": 4.5, "max": 5}
    # tracks: point 1 in one image, the others in two
    assert r["track_length"]["histogram"] == {"1": 1, "2": 4, "10+": 0}
    assert r["track_length"]["min"] == 1 and r["track_length"]["max"] == 2
    assert r["track_length"]["median"] == 2 and r["track_length"]["mean"] == pytest.approx(1.8)
    # 8x6 cells of 80x80 px. Image 0: (40,40) and (45,50) share cell (0,0); (600,440) is cell
    # (7,5); (330,250) is cell (4,3): 3 of 48. Image 1 sees its points 25 px further left:
    # (15,40) cell (0,0), (575,440) cell (7,5), (305,250) cell (3,3): 3 of 48.
    assert r["coverage"]["min"] == r["coverage"]["max"] == round(3 / 48, 3)
    assert r["sparse"] and len(r["warnings"]) == 1 and "sparse" in r["warnings"][0]


@pytest.fixture(scope="module")
def corner_maps(tmp_path_factory) -> dict:
    """Bundles from 3 and 4 views of the room corner at known poses, min track length 2 and 3."""
    root = tmp_path_factory.mktemp("corner-maps")
    scene = Corner(seed=0)
    out = {"scene": scene}
    for n in (3, 4):
        d = root / f"views{n}"
        (d / "images").mkdir(parents=True)
        poses = arc_poses(n)
        names = [f"view-{k:03d}.png" for k in range(n)]
        for name, T in zip(names, poses):
            assert cv2.imwrite(str(d / "images" / name), scene.render(CAM, T))
        pose_file = write_colmap_list(d / "poses.txt", names, poses)
        out[n] = {"dir": d, "pose_file": pose_file}
        for mt in (2, 3) if n == 3 else (3,):
            # SfM points only: these tests are about the SfM tracks (min track length) and the
            # sparse-map threshold, which was measured on maps of SfM points
            conf = merge_presets(build.preset("default"), harris_points={"enabled": False})
            out[n][mt] = build.main(
                conf,
                f"t{mt}",
                d / "maps",
                images=d / "images",
                poses=pose_file,
                camera=CAM,
                sfm_conf=sfm.sfm_conf("default", min_track_length=mt, two_view_below=0),
            )
    return out


def test_sparse_warning_fires_on_few_views_and_not_on_a_normal_map(corner_maps):
    few = MapBundle(corner_maps[3][3], verify=False)
    normal = MapBundle(corner_maps[4][3], verify=False)
    rf, rn = few.manifest.report, normal.manifest.report  # written by the builder
    assert rf["sparse"] and rf["points_per_image"]["median"] < SPARSE_POINTS_PER_IMAGE
    assert "too sparse" in rf["warnings"][0]
    assert not rn["sparse"] and rn["warnings"] == []
    # The manifest's numbers are those of the bundle's own arrays.
    assert rn["points"] == normal.n_points
    assert rn["points_per_image"]["median"] == float(np.median(np.diff(normal.image_points_ptr)))
    tracks = np.bincount(normal.image_points_idx, minlength=normal.n_points)
    assert rn["track_length"]["min"] >= 3 and rn["track_length"]["max"] == tracks.max()


def test_min_track_length_2_adds_correct_points_with_known_poses(corner_maps):
    scene = corner_maps["scene"]
    b2 = MapBundle(corner_maps[3][2], verify=False)
    b3 = MapBundle(corner_maps[3][3], verify=False)
    assert b2.n_points > 3 * b3.n_points
    tracks = np.bincount(b2.image_points_idx, minlength=b2.n_points)
    assert tracks.min() == 2 and np.sum(tracks == 2) > b3.n_points
    # The two-view points lie on the true planes (~3 m scene, ~2.6 m away, 10 mm pixels).
    d = scene.distance(b2.points_xyz[tracks == 2])
    assert np.median(d) < 0.005
    assert np.percentile(d, 90) < 0.02
    assert b2.manifest.report["track_length"]["histogram"]["2"] == int(np.sum(tracks == 2))


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "sfmloc", *args], capture_output=True, text=True, timeout=300
    )


def test_cli_min_track_length_flag_and_inspect_report(corner_maps, tmp_path):
    d = corner_maps[3]
    posed = [
        "--images",
        str(d["dir"] / "images"),
        "--poses",
        str(d["pose_file"]),
        "--camera",
        CAM.to_string(),
    ]
    r = _cli(
        "build",
        "few",
        "--out",
        str(tmp_path),
        *posed,
        "--min-track-length",
        "2",
        "--preset",
        "fast",
    )
    assert r.returncode == 0, r.stderr
    assert "points/image" in r.stdout and "track length" in r.stdout and "coverage" in r.stdout
    m = MapBundle(tmp_path / "few", verify=False)
    assert m.manifest.params["sfm"]["min_track_length"] == 2
    assert np.bincount(m.image_points_idx, minlength=m.n_points).min() == 2
    # The sparse map (track >= 3 from 3 views) warns in map inspect too.
    r = _cli("map", "inspect", str(corner_maps[3][3]))
    assert r.returncode == 0 and "WARNING" in r.stdout and "too sparse" in r.stdout, r.stderr
    r = _cli("build", "bad", "--out", str(tmp_path), *posed, "--min-track-length", "1")
    assert r.returncode != 0 and "--min-track-length must be >= 2" in r.stderr
    r = _cli(
        "build",
        "bad",
        "--out",
        str(tmp_path),
        "--images",
        str(d["dir"] / "images"),
        "--min-track-length",
        "2",
    )
    assert r.returncode != 0 and ">= 3 for images-only" in r.stderr


def test_two_view_points_are_kept_only_where_the_map_would_be_sparse(corner_maps):
    d3 = corner_maps[3]
    b3 = MapBundle(d3[3], verify=False)
    dense = corner_maps[4]
    # 3 views: with tracks >= 3 the median image sees ~80 points, under the switch (default
    # 400): two-view points kept
    rec = sfm.triangulate_known_poses(d3["dir"] / "images", d3["pose_file"], CAM)
    tracks = np.array([len(p.track_image_ids) for p in rec.points3D.values()])
    assert tracks.min() == 2 and len(tracks) > 3 * b3.n_points
    # 4 views: dense enough with tracks >= 3 (~570 points/image), so the map is the one built
    # without the switch
    rec = sfm.triangulate_known_poses(dense["dir"] / "images", dense["pose_file"], CAM)
    b4 = MapBundle(dense[3], verify=False)
    assert min(len(p.track_image_ids) for p in rec.points3D.values()) == 3
    assert len(rec.points3D) == b4.n_points


def test_known_poses_harris_points_keep_two_view_tracks_when_the_sfm_did(corner_maps, tmp_path):
    """With known poses, the Harris stage keeps two-view tracks when the SfM stage kept
    two-view points (HarrisPointsConf.follow_sfm_two_view), whatever its own count rule (here
    off: two_view_below 0); the two-view Harris points lie on the true planes. When the SfM
    kept none, or the switch is off, every Harris point has 3+ views."""
    from sfmloc.builder.harris_points import HARRIS_POINT_ID_BASE

    d3 = corner_maps[3]
    scene = corner_maps["scene"]

    def build_with(min_track: int, follow: bool) -> MapBundle:
        conf = merge_presets(
            build.preset("default"),
            harris_points={"two_view_below": 0, "follow_sfm_two_view": follow},
            refine={"enabled": False},
        )
        name = f"h{min_track}{int(follow)}"
        build.main(
            conf,
            name,
            tmp_path,
            images=d3["dir"] / "images",
            poses=d3["pose_file"],
            camera=CAM,
            sfm_conf=sfm.sfm_conf("default", min_track_length=min_track, two_view_below=0),
        )
        return MapBundle(tmp_path / name, verify=False)

    def harris_tracks(b: MapBundle) -> tuple[np.ndarray, np.ndarray]:
        tracks = np.bincount(b.image_points_idx, minlength=b.n_points)
        h = b.array("point_ids") >= HARRIS_POINT_ID_BASE
        return tracks[h], b.points_xyz[h]

    kept = build_with(2, True)
    assert kept.manifest.params["harris_points"]["keep_two_view"] is True
    tracks, xyz = harris_tracks(kept)
    assert np.sum(tracks == 2) > 100, np.bincount(tracks)
    d = scene.distance(xyz[tracks == 2])  # ~3 m scene, ~2.6 m away
    assert np.median(d) < 0.005, np.median(d)
    assert np.percentile(d, 80) < 0.02, np.percentile(d, 80)
    for b in (build_with(3, True), build_with(2, False)):
        assert b.manifest.params["harris_points"]["keep_two_view"] is False
        tracks, _ = harris_tracks(b)
        assert len(tracks) == 0 or tracks.min() >= 3
