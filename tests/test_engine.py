"""The localization engine, stage by stage against exact ground truth (synthetic scenes), end
to end on a synthetic video and on real redkitchen frames, and with bad input."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator

import numpy as np
import pytest

from sfmloc.cameras import Camera
from sfmloc.engine import EngineConf, Localizer, Matching, Status, relocalize
from sfmloc.engine.matching import global_matching, guided_matching
from sfmloc.engine.motion_filter import DecoupledPoseFilter
from sfmloc.engine.pose import (
    PoseEstimate,
    estimate_pose,
    estimate_pose_one_to_many,
    pose_covariance,
    pose_covariances,
    pose_error_vector,
    project,
    reprojection_errors,
)
from sfmloc.engine.relocalize import describe
from sfmloc.engine.timing import STAGES
from sfmloc.engine.track_table import TrackTable
from sfmloc.engine.tracker import Keypoints, extract_keypoints, track_2d
from sfmloc.errors import ImageDecodeError
from sfmloc.features.daisy import DaisyExtractor
from sfmloc.features.harris import detect_corners
from sfmloc.map.bundle import MapBundle
from sfmloc.synth.config import SceneConf as SynthSceneConf
from sfmloc.testing import one_to_many_matches, scene_points
from sfmloc.transforms import Rigid3d, pose_errors, rotmat_from_rotvec

K = np.array([[525.0, 0, 320.0], [0, 525.0, 240.0], [0, 0, 1]])


# ----------------------------------------------------------------------------- pose
def test_p3p_ransac_recovers_a_known_pose_with_outliers():
    rng = np.random.default_rng(0)
    gt = Rigid3d(rotmat_from_rotvec([0.1, -0.3, 0.05]), [0.3, -0.2, 1.0])
    X, uv = scene_points(rng, 200, gt, K)
    uv_noisy = uv + rng.normal(0, 0.5, uv.shape)
    bad = rng.random(200) < 0.4
    uv_noisy[bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
    est = estimate_pose(uv_noisy, X, K)
    assert est is not None
    dp, dr = pose_errors(est.cam_from_world, gt)
    assert dp < 0.01 and dr < 0.1, (dp, dr)
    # the inlier mask is the good points (a few random outliers may land near their truth)
    assert np.all(est.inlier_mask[~bad])
    assert est.inlier_mask[bad].mean() < 0.05
    # fewer than min_inliers consistent points: no pose, not a made-up one
    assert estimate_pose(uv_noisy[:9], X[:9], K) is None


def test_robust_refine_converges_to_the_exact_pose():
    from sfmloc.engine.pose import robust_refine

    rng = np.random.default_rng(3)
    gt = Rigid3d(rotmat_from_rotvec([0.2, -0.1, 0.3]), [0.5, 0.1, -0.4])
    X, uv = scene_points(rng, 60, gt, K)
    start = Rigid3d(rotmat_from_rotvec([0.21, -0.11, 0.29]), [0.52, 0.09, -0.38])
    est = robust_refine(start, K, uv, X, 1.0, iterations=8)
    dp, dr = pose_errors(est, gt)
    assert dp < 1e-6 and dr < 1e-5, (dp, dr)


def test_final_refinement_lowers_the_error_of_noisy_matches_with_outliers():
    # Matches with 0.3 px noise, a quarter off by 2-3 px (inside the 3 px refinement threshold,
    # like a wrong corner next to the right one) and a fifth gross outliers.
    from sfmloc.engine.pose import RansacParams

    plain, robust = [], []
    for seed in range(8):
        rng = np.random.default_rng(100 + seed)
        gt = Rigid3d(rotmat_from_rotvec(rng.normal(0, 0.2, 3)), rng.normal(0, 0.5, 3))
        X, uv = scene_points(rng, 80, gt, K)
        uv = uv + rng.normal(0, 0.3, uv.shape)
        kind = rng.random(80)
        near = kind < 0.25
        ang = rng.uniform(0, 2 * np.pi, near.sum())
        uv[near] += rng.uniform(2.0, 3.0, near.sum())[:, None] * np.stack(
            [np.cos(ang), np.sin(ang)], 1
        )
        far = kind > 0.8
        uv[far] = rng.uniform([0, 0], [640, 480], (far.sum(), 2))
        for params, out in ((RansacParams(), plain), (RansacParams(loss_scale=1.0), robust)):
            est = estimate_pose(uv, X, K, params)
            assert est is not None
            out.append(pose_errors(est.cam_from_world, gt))
            # the inlier set returned is the one the refinement used: the matches within 3 px
            err = reprojection_errors(est.cam_from_world, K, uv, X)
            assert np.array_equal(est.inlier_mask, err < params.refine_threshold)
    plain, robust = np.array(plain), np.array(robust)
    assert robust[:, 0].mean() < 0.6 * plain[:, 0].mean(), (robust.mean(0), plain.mean(0))
    assert robust[:, 1].mean() < 0.6 * plain[:, 1].mean(), (robust.mean(0), plain.mean(0))


def test_a_prior_that_is_this_frames_estimate_is_refined_without_ransac(monkeypatch):
    """The tracker's second estimate (after guided matching) starts from the frame's own pose:
    refinement alone, as accurate as the full estimator, and RANSAC is never called."""
    import sfmloc.engine.pose as pose_mod
    from sfmloc.engine.pose import RansacParams

    params = RansacParams(loss_scale=1.0)
    rng = np.random.default_rng(7)
    gt = Rigid3d(rotmat_from_rotvec([0.05, 0.2, -0.1]), [0.2, 0.1, 0.8])
    X, uv = scene_points(rng, 120, gt, K)
    uv = uv + rng.normal(0, 0.3, uv.shape)
    # a third of the matches 3-6 px off (verified within 6 px, like guided matches), a few
    # gross outliers
    off = rng.random(120) < 0.33
    ang = rng.uniform(0, 2 * np.pi, off.sum())
    uv[off] += rng.uniform(3.0, 6.0, off.sum())[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    uv[:5] = rng.uniform([0, 0], [640, 480], (5, 2))
    full = estimate_pose(uv, X, K, params)
    prior = Rigid3d(rotmat_from_rotvec([0.051, 0.199, -0.1]), [0.201, 0.099, 0.802])

    def no_ransac(*a, **k):
        raise AssertionError("RANSAC ran from this frame's own pose")

    monkeypatch.setattr(pose_mod.cv2, "solvePnPRansac", no_ransac)
    est = estimate_pose(uv, X, K, params, prior=prior, prior_threshold=20.0, prior_is_estimate=True)
    assert est is not None and full is not None
    dp, dr = pose_errors(est.cam_from_world, gt)
    dp_full, dr_full = pose_errors(full.cam_from_world, gt)
    assert dp < max(1.5 * dp_full, 2e-3) and dr < max(1.5 * dr_full, 0.05), (
        dp,
        dr,
        dp_full,
        dr_full,
    )
    err = reprojection_errors(est.cam_from_world, K, uv, X)
    assert np.array_equal(est.inlier_mask, err < params.refine_threshold)
    # too few matches explained by it: no pose; no prior: no pose
    assert (
        estimate_pose(uv[:12], X[::10][:12], K, params, prior=prior, prior_is_estimate=True) is None
    )
    assert estimate_pose(uv, X, K, params, prior=None, prior_is_estimate=True) is None


def test_an_estimate_without_its_final_refinement_is_the_one_the_refinement_starts_from():
    """``final=False`` (the tracker's first estimate on a frame with many matches) returns the
    least-squares estimate that ``final_refinement`` turns into the full one: the same pose and
    inliers, from the prior and from RANSAC; its own inliers are the matches within 3 px of it."""
    from sfmloc.engine.pose import RansacParams, final_refinement

    params = RansacParams(loss_scale=1.0)
    rng = np.random.default_rng(11)
    gt = Rigid3d(rotmat_from_rotvec([0.1, -0.15, 0.05]), [0.1, -0.2, 0.9])
    X, uv = scene_points(rng, 100, gt, K)
    uv = uv + rng.normal(0, 0.3, uv.shape)
    near = rng.random(100) < 0.2  # wrong corners next to the right ones, inside 3 px
    uv[near] += rng.uniform(1.5, 2.5, (near.sum(), 2)) * rng.choice([-1, 1], (near.sum(), 2))
    uv[:8] = rng.uniform([0, 0], [640, 480], (8, 2))
    prior = Rigid3d(rotmat_from_rotvec([0.102, -0.149, 0.05]), [0.103, -0.198, 0.902])
    for kw in ({"prior": prior, "prior_threshold": 20.0}, {}):
        full = estimate_pose(uv, X, K, params, **kw)
        first = estimate_pose(uv, X, K, params, final=False, **kw)
        assert full is not None and first is not None
        err = reprojection_errors(first.cam_from_world, K, uv, X)
        assert np.array_equal(first.inlier_mask, err < params.refine_threshold)
        # not refined: the robust refinement moves it (the near corners pull least squares)
        assert not np.allclose(first.cam_from_world.translation, full.cam_from_world.translation)
        again = final_refinement(first, K, uv, X, params)
        assert again is not None
        assert np.array_equal(again.cam_from_world.rotation, full.cam_from_world.rotation)
        assert np.array_equal(again.cam_from_world.translation, full.cam_from_world.translation)
        assert np.array_equal(again.inlier_mask, full.inlier_mask)


def test_one_to_many_ransac_uses_ambiguous_hypotheses():
    rng = np.random.default_rng(1)
    gt = Rigid3d(rotmat_from_rotvec([-0.2, 0.4, 0.0]), [1.0, 0.5, 2.0])
    X, uv = scene_points(rng, 150, gt, K)
    uv = uv + rng.normal(0, 0.5, uv.shape)
    # set 1: 60 keypoints with their best point (25% wrong); set 2: every keypoint with its
    # true point among 3 hypotheses (the others: other keypoints' points)
    n1 = 60
    p1, q2, p2 = one_to_many_matches(rng, 150, n1, 0.25)
    res = estimate_pose_one_to_many(uv[:n1], X[p1], q2, uv[q2], X[p2], K)
    assert res is not None
    est, chosen = res
    dp, dr = pose_errors(est.cam_from_world, gt)
    assert dp < 0.01 and dr < 0.1
    # one chosen hypothesis per keypoint, and it is the true point for nearly all
    assert len(np.unique(q2[chosen])) == chosen.sum()
    assert np.mean(p2[chosen] == q2[chosen]) > 0.95
    assert chosen.sum() > 140


def test_batched_rodrigues_matches_opencv():
    import cv2

    from sfmloc.engine.pose import _rotations_from_rotvecs

    rng = np.random.default_rng(5)
    r = np.vstack([rng.normal(0, 1.5, (50, 3)), np.zeros((1, 3)), [[np.pi, 0, 0]], [[1e-9, 0, 0]]])
    R = _rotations_from_rotvecs(r)
    for v, Rb in zip(r, R):
        assert np.abs(Rb - cv2.Rodrigues(v.reshape(3, 1))[0]).max() < 1e-12


def test_pose_prior_resolves_the_planar_mirror_ambiguity():
    """Points on one small distant plane: minimal solvers can return the mirrored pose; the
    prior (the motion filter's prediction) selects the right one."""
    rng = np.random.default_rng(2)
    gt = Rigid3d(rotmat_from_rotvec([0.0, 0.1, 0.0]), [0.0, 0.0, 0.0])
    uv = rng.uniform([200, 150], [440, 330], (40, 2))
    z = np.full(40, 5.0)  # fronto-parallel plane 5 m away, 2.3 x 1.7 m seen
    Xc = np.hstack([(uv - K[:2, 2]) / K[0, 0] * z[:, None], z[:, None]])
    X = gt.inverse().apply(Xc)
    noisy = uv + rng.normal(0, 1.0, uv.shape)
    prior = Rigid3d(
        gt.rotation @ rotmat_from_rotvec([0.01, -0.01, 0.0]), gt.translation + [0.02, 0.0, 0.01]
    )
    est = estimate_pose(noisy, X, K, prior=prior)
    dp, dr = pose_errors(est.cam_from_world, gt)
    assert dp < 0.1 and dr < 1.5, (dp, dr)


# ----------------------------------------------------------------------------- filter
def test_kalman_filter_follows_constant_velocity_and_angular_velocity():
    rng = np.random.default_rng(3)
    v = np.array([0.8, -0.3, 0.1])  # m/s
    w = np.array([0.0, 0.0, 1.2])  # rad/s (world frame yaw rate)
    R0 = rotmat_from_rotvec([0.2, 0.1, 0.0])
    f = (
        DecoupledPoseFilter()
    )  # the paper's model: exact for this motion (tests/test_motion.py: SE(3))

    def truth(t):
        world_from_cam = Rigid3d(rotmat_from_rotvec(w * t) @ R0, v * t)
        return world_from_cam.inverse()

    dt = 1 / 30
    f.reset(truth(0.0), 0.0)
    for i in range(1, 90):
        t = i * dt
        f.predict(t)
        meas = truth(t).inverse()
        noisy = Rigid3d(
            rotmat_from_rotvec(rng.normal(0, 0.005, 3)) @ meas.rotation,
            meas.translation + rng.normal(0, 0.01, 3),
        )
        f.update(noisy.inverse())
    # velocities learned
    assert np.allclose(f.velocity, v, atol=0.05)
    assert np.allclose(f.angular_velocity, w, atol=0.1)
    # and the prediction one frame ahead is accurate
    pred = f.predict(90 * dt)
    dp, dr = pose_errors(pred, truth(90 * dt))
    assert dp < 0.02 and dr < 0.5


# ----------------------------------------------------------------------------- tracking
def test_per_frame_shortcuts_give_numpy_s_numbers_bit_for_bit():
    """The localizer's cheaper spellings of numpy calls (issue 10, per-frame glue): the
    median image motion by one partition (np.median), a table's rows taken by a mask's
    indices, the rotation angle with min/max for np.clip."""
    from sfmloc.engine.localizer import _median_rows
    from sfmloc.transforms import rotation_angle_deg

    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 4, 9, 10, 251, 252):
        a = rng.normal(0, 30, (n, 2))
        a[rng.random((n, 2)) < 0.2] = 1.5  # ties
        assert np.array_equal(_median_rows(a), np.median(a, axis=0)), n
    n = 300
    table = TrackTable.empty(3)
    table.append(
        np.arange(n), rng.normal(size=(n, 2)), rng.integers(0, 9, (n, 4)).astype(np.uint64)
    )
    table.point[::3] = rng.integers(0, 100, 100)
    mask = rng.random(n) < 0.7
    for name in ("track_id", "xy", "brief", "age", "point", "hyp", "pending"):
        assert np.array_equal(getattr(table.take(mask), name), getattr(table, name)[mask])
    R0 = rotmat_from_rotvec([0.3, -0.2, 0.1])
    for R in (
        R0,
        np.eye(3),
        rotmat_from_rotvec([0.0, 0.0, np.pi]),
        rotmat_from_rotvec([1e-9, 0, 0]),
    ):
        for S in (R, R0, -R0 @ np.diag([1.0, 1.0, -1.0])):
            c = (np.trace(R @ S.T) - 1.0) / 2.0
            assert rotation_angle_deg(R, S) == float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def test_tracked_table_and_refill_coverage_read_the_keypoints_rows(bundle, cam):
    """TRACK-2D's new table (``TrackTable.tracked``) is the rows taken, moved to their
    keypoints and one frame older; the refill coverage test reads each tracked row's cell
    from its keypoint's, as from the row's own position (issue 10: the same answers)."""
    loc = Localizer(bundle, cam)
    rng = np.random.default_rng(5)
    size = np.array([cam.width, cam.height], np.float64)

    def cells(xy: np.ndarray) -> int:
        ij = np.clip((xy * (4.0 / size)).astype(np.int64), 0, 3)
        return len(set((ij[:, 1] * 4 + ij[:, 0]).tolist()))

    answers = set()
    early = 0
    for trial in range(200):
        n, m = int(rng.integers(0, 80)), int(rng.integers(1, 300))
        prev = TrackTable.empty(3)
        prev.append(np.arange(n) + 100, rng.uniform(0, 640, (n, 2)), np.zeros((n, 4), np.uint64))
        prev.age[:] = rng.integers(0, 50, n)
        prev.point[:] = np.where(rng.random(n) < 0.5, rng.integers(0, 1000, n), -1)
        # keypoints bunched in a corner on some trials (the test's two answers), on the image
        # edge and just outside it on others (the clipped cells)
        spread = size * (0.3 if trial % 3 == 0 else 1.0)
        xy = rng.uniform(0, 1, (m, 2)) * spread
        xy[: m // 10] = np.round(xy[: m // 10] / size) * size
        kps = Keypoints(xy, np.ones(m), rng.integers(0, 9, (m, 4)).astype(np.uint64), 1.0)
        rows = np.sort(rng.choice(n, int(rng.integers(0, n + 1)), replace=False))
        used = rng.choice(m, len(rows), replace=len(rows) > m)
        table = prev.tracked(rows, kps.xy[used], kps.brief[used])
        want = prev.take(rows)
        want.xy, want.brief = kps.xy[used], kps.brief[used]
        want.age += 1
        for name in ("track_id", "xy", "brief", "age", "point", "hyp", "pending"):
            got = getattr(table, name)
            assert got.dtype == getattr(want, name).dtype
            assert np.array_equal(got, getattr(want, name))
        covered = cells(table.xy[table.point >= 0])
        plain = covered < loc.conf.refill_coverage * cells(kps.xy)
        assert loc._uncovered(table, kps, used) == plain
        answers.add(plain)
        # (10 of the 16 cells or more: answered without the keypoints' cells)
        early += covered >= 10
    assert answers == {True, False} and early > 0


def test_predicted_positions_are_camera_project_s_bit_for_bit(bundle, cam):
    """TRACK-2D's predicted positions written out for a camera without distortion (issue 10)
    are those of ``Camera.project`` bit for bit: map points in front, behind and in the
    camera's plane, rows without a 3D point moved by the median motion, a pose not finite."""
    loc = Localizer(bundle, cam)
    assert not loc._distorted
    rng = np.random.default_rng(3)
    n = 200
    table = TrackTable.empty(3)
    table.append(np.arange(n), rng.uniform(0, 640, (n, 2)), np.zeros((n, 4), np.uint64))
    table.point[:] = rng.integers(0, len(bundle.points_xyz), n)
    table.point[::4] = -1
    images = bundle.image_cam_from_world
    poses = [images[0], images[len(images) // 2]]
    R = rotmat_from_rotvec([0.1, 2.5, 0.0])  # facing away from most of the room
    poses += [Rigid3d(R, rng.normal(size=3)), Rigid3d(np.eye(3), np.full(3, np.nan))]
    X0 = bundle.points_xyz[table.point[1]]
    in_plane = Rigid3d(np.eye(3), np.array([0.0, 0.0, -X0[2]]))  # point 1 at depth 0
    poses.append(in_plane)
    behind = 0
    for pose in poses:
        got = loc._predict_positions(table, pose)
        loc._distorted = True  # Camera.project's path (a copy where not distorted)
        want = loc._predict_positions(table, pose)
        loc._distorted = False
        assert got.tobytes() == want.tobytes()
        rows = table.point >= 0
        behind += int(
            (
                (bundle.points_xyz[table.point[rows]] @ pose.rotation.T)[:, 2] + pose.translation[2]
                <= 0
            ).sum()
        )
    assert behind > 0
    assert np.array_equal(loc._predict_positions(table, poses[-2]), table.xy)  # nothing finite


def test_tracking_keeps_identities():
    """Keypoints tracked from one rendered frame to the next are the same scene points: back-
    project each through the exact depth map and the ground-truth poses."""
    from server_helpers import room_scene
    from sfmloc.synth import make_trajectory, render

    scene = room_scene(0)
    cam = Camera.pinhole(640, 480, 525.0, 525.0, 320.0, 240.0)
    poses = make_trajectory("walk", 40, seed=0, scene=scene)
    conf = EngineConf()
    checked = []
    for i in (5, 20, 35):
        img0, depth0 = render(scene, cam, poses[i], noise_sigma=2.0, noise_seed=i)
        img1, _ = render(scene, cam, poses[i + 1], noise_sigma=2.0, noise_seed=i + 1)
        g0 = img0.mean(axis=2).astype(np.uint8)
        g1 = img1.mean(axis=2).astype(np.uint8)
        k0 = extract_keypoints(g0, None, conf)
        k1 = extract_keypoints(g1, None, conf)
        table = TrackTable.empty(conf.max_hypotheses)
        table.append(np.arange(len(k0)), k0.xy, k0.brief)
        m = track_2d(table, table.xy, k1, conf)
        ok = m >= 0
        assert ok.mean() > 0.4, ok.mean()
        # where each tracked keypoint's scene point really went
        xy0 = k0.xy[ok]
        z = depth0[np.floor(xy0[:, 1]).astype(int), np.floor(xy0[:, 0]).astype(int)]
        valid = z > 0
        xc = np.hstack([(xy0 - K[:2, 2]) / 525.0 * z[:, None], z[:, None]])
        Xw = poses[i].inverse().apply(xc)
        uv1, _ = cam.project(poses[i + 1], Xw)
        err = np.linalg.norm(uv1 - k1.xy[m[ok]], axis=1)[valid]
        checked.append(np.mean(err < 2.0))
        # identities stay unique
        assert len(np.unique(m[ok])) == ok.sum()
    assert min(checked) > 0.9, checked


# ----------------------------------------------------------------------------- matching
def test_global_matching_finds_the_right_place_and_correct_matches(world, bundle, cam):
    conf = EngineConf()
    ex = DaisyExtractor()
    good = 0
    for i in (0, 20, 40, 59):
        gray = world.gray[i]
        gt = world.gt_cam_from_world[i]
        c = detect_corners(
            gray, rel_threshold=conf.gamma, max_corners=conf.global_max_keypoints, border=16
        )
        desc = describe(ex, bundle, ex.prepare(gray), c.xy)
        gm = global_matching(desc, bundle, conf)
        # the selected images include the map view that sees most of what this frame sees
        uv, z = cam.project(gt, bundle.points_xyz)
        seen = np.nonzero((z > 0) & cam.in_image(uv))[0]
        counts = np.array(
            [np.intersect1d(bundle.image_points(j), seen).size for j in range(bundle.n_images)]
        )
        selected_images = np.unique(
            np.concatenate([bundle.cluster_images(int(cl)) for cl in gm.clusters])
        )
        assert np.argmax(counts) in selected_images
        # the ratio-test set holds enough correct matches (under the exact pose) for RANSAC;
        # repeated textures make many of the others wrong, which RANSAC must survive
        e = reprojection_errors(gt, cam.K, c.xy[gm.set1_q], bundle.points_xyz[gm.set1_p])
        good += np.sum(e < 3.0) >= 30
        r = relocalize(gray, cam, bundle, conf)
        assert r.status is Status.RELOCALIZED
        dp, dr = pose_errors(r.cam_from_world, gt)
        assert dp < 0.05 and dr < 1.0, (i, dp, dr)
    assert good == 4


def _guided_inputs(world, bundle, cam, conf):
    """Frame 30 of the synthetic world as guided matching sees it: (gray, true pose, its
    corners, their descriptors, every map point's projection, the points in view)."""
    ex = DaisyExtractor()
    gray, gt = world.gray[30], world.gt_cam_from_world[30]
    c = detect_corners(gray, rel_threshold=conf.gamma, max_corners=150, border=16)
    desc = describe(ex, bundle, ex.prepare(gray), c.xy)
    uv, z = cam.project(gt, bundle.points_xyz)
    seen = np.nonzero((z > 0) & cam.in_image(uv))[0]
    return gray, gt, c, desc, uv, seen


def test_guided_matching_with_the_pose_gives_correct_matches(world, bundle, cam):
    conf = EngineConf()
    gray, gt, c, desc, uv, seen = _guided_inputs(world, bundle, cam, conf)
    gm = guided_matching(desc, c.xy, bundle, seen, gt, cam.K, conf)
    found = gm.point >= 0
    # the most it could find: keypoints within tau of a visible map point's projection
    from scipy.spatial import cKDTree

    d, _ = cKDTree(uv[seen]).query(c.xy, distance_upper_bound=2.0)
    matchable = int(np.isfinite(d).sum())
    assert found.sum() >= 0.5 * matchable, (found.sum(), matchable)
    e = reprojection_errors(gt, cam.K, c.xy[found], bundle.points_xyz[gm.point[found]])
    assert np.all(e < conf.guided_threshold_px)
    assert gm.n_images <= conf.top_images


def test_guided_matching_on_few_matches_keeps_more_hypotheses_still_verified(
    world, bundle, cam, monkeypatch
):
    """On a frame holding fewer than ``few_matches_below`` 3D matches, guided matching keeps
    the weaker candidates too (``few_matches_ratio``): every keypoint's hypotheses include
    those of the default ratio, more keypoints hold one, and what is verified against the
    pose still reprojects within ``guided_threshold_px`` at the true pose. The localizer
    applies the loose ratio only below ``few_matches_below`` matches."""
    conf = EngineConf()
    assert 0 < conf.few_matches_ratio < conf.ratio and conf.few_matches_below > conf.kappa2
    gray, gt, c, desc, uv, seen = _guided_inputs(world, bundle, cam, conf)
    strict = guided_matching(desc, c.xy, bundle, seen, gt, cam.K, conf)
    loose = guided_matching(desc, c.xy, bundle, seen, gt, cam.K, conf, ratio=conf.few_matches_ratio)
    for hs, hl in zip(strict.hyp, loose.hyp):
        assert set(hs[hs >= 0]) <= set(hl[hl >= 0])
    n_strict = int((strict.hyp >= 0).sum())
    n_loose = int((loose.hyp >= 0).sum())
    assert n_loose > n_strict, (n_loose, n_strict)
    found = loose.point >= 0
    assert found.sum() >= (strict.point >= 0).sum()
    e = reprojection_errors(gt, cam.K, c.xy[found], bundle.points_xyz[loose.point[found]])
    assert np.all(e < conf.guided_threshold_px)

    import sfmloc.engine.localizer as localizer_mod

    used: list[float | None] = []
    real = localizer_mod.guided_matching

    def spy(*args, **kwargs):
        used.append(kwargs.get("ratio"))
        return real(*args, **kwargs)

    monkeypatch.setattr(localizer_mod, "guided_matching", spy)
    loc = Localizer(bundle, cam, conf)
    image = localizer_mod._FrameImage(gray, loc.extractor)
    n = len(c.xy)
    for matched in (conf.few_matches_below - 1, conf.few_matches_below):
        t = TrackTable.empty(conf.max_hypotheses)
        t.append(np.arange(n), c.xy.copy(), np.zeros((n, 4), np.uint64))
        t.point[:matched] = seen[:matched]
        rows = np.arange(matched, n)
        loc._guided_matching(t, rows, image, gt)
    assert used == [conf.few_matches_ratio, None]


def _table_matched(
    conf: EngineConf, xy: np.ndarray, points: np.ndarray, matched: int
) -> TrackTable:
    """A track table of the keypoints ``xy`` whose first ``matched`` rows hold ``points``
    (the guided-search nprobe tests)."""
    n = len(xy)
    t = TrackTable.empty(conf.max_hypotheses)
    t.append(np.arange(n), xy.copy(), np.zeros((n, 4), np.uint64))
    t.point[:matched] = points[:matched]
    return t


@contextlib.contextmanager
def _recorded_nprobe(bundle: MapBundle) -> Iterator[list[int | None]]:
    """The nprobe of every search of the bundle's index while inside: the real search runs,
    only its nprobe is recorded."""
    seen: list[int | None] = []
    search = bundle.index.search

    def spy(*a, **kw):
        seen.append(kw.get("nprobe"))
        return search(*a, **kw)

    bundle.index.search = spy
    try:
        yield seen
    finally:
        del bundle.index.search


def test_guided_search_scans_scope_nprobe_lists_only_on_frames_holding_enough_matches(
    world, bundle, cam
):
    """``scope_nprobe``: the localizer's guided (scoped) k-ANN search scans that many inverted
    lists on a frame holding at least ``few_matches_below`` 3D matches, ``nprobe`` below it
    (where a thin map needs every candidate), and only on maps whose median point is seen by
    at least ``scope_nprobe_min_track`` images; the real search runs (its nprobe recorded),
    and what the fewer lists find still verifies within ``guided_threshold_px``."""
    import sfmloc.engine.localizer as localizer_mod
    from sfmloc.engine.scope import median_track_length

    track = median_track_length(bundle)
    conf = EngineConf(scope_nprobe=8, scope_nprobe_min_track=track)  # off by default (orbit)
    assert 0 < conf.scope_nprobe < conf.nprobe and track >= 2
    gray, gt, c, desc, uv, seen = _guided_inputs(world, bundle, cam, conf)
    fewer = guided_matching(desc, c.xy, bundle, seen, gt, cam.K, conf, nprobe=conf.scope_nprobe)
    found = fewer.point >= 0
    assert found.sum() > 0
    e = reprojection_errors(gt, cam.K, c.xy[found], bundle.points_xyz[fewer.point[found]])
    assert np.all(e < conf.guided_threshold_px)

    loc = Localizer(bundle, cam, conf)
    assert loc.scope_nprobe == conf.scope_nprobe
    thinner = Localizer(bundle, cam, EngineConf(scope_nprobe=8, scope_nprobe_min_track=track + 0.5))
    off = Localizer(bundle, cam, EngineConf(scope_nprobe_min_track=track, scope_nprobe=0))
    assert thinner.scope_nprobe is None and off.scope_nprobe is None
    image = localizer_mod._FrameImage(gray, loc.extractor)
    n = len(c.xy)

    def table(matched: int) -> TrackTable:
        return _table_matched(conf, c.xy, seen, matched)

    with _recorded_nprobe(bundle) as seen_nprobe:
        for matched in (conf.few_matches_below - 1, conf.few_matches_below):
            loc._guided_matching(table(matched), np.arange(matched, n), image, gt)
        for other in (thinner, off):
            m = conf.few_matches_below
            other._guided_matching(table(m), np.arange(m, n), image, gt)
    assert seen_nprobe == [conf.nprobe, conf.scope_nprobe, conf.nprobe, conf.nprobe], seen_nprobe


def test_guided_search_keeps_nprobe_lists_on_frames_holding_many_matches(world, bundle, cam):
    """``scope_nprobe_max_3d``: the scoped search scans ``scope_nprobe`` lists only on frames
    holding fewer than that many 3D matches (and at least ``few_matches_below``); from it on,
    ``nprobe`` (an orbit around an object holds 270-320 matches at its full batches, where
    the narrower search moved the pose; redkitchen 68). The real search runs, its nprobe
    recorded."""
    import sfmloc.engine.localizer as localizer_mod
    from sfmloc.engine.scope import median_track_length

    track = median_track_length(bundle)
    few = EngineConf().few_matches_below
    most = few + 10
    conf = EngineConf(scope_nprobe=8, scope_nprobe_min_track=track, scope_nprobe_max_3d=most)
    gray, gt, c, desc, uv, seen = _guided_inputs(world, bundle, cam, conf)
    n = len(c.xy)
    assert len(seen) > most and n > most + 10
    loc = Localizer(bundle, cam, conf)
    unlimited = Localizer(bundle, cam, conf.model_copy(update={"scope_nprobe_max_3d": 0}))
    image = localizer_mod._FrameImage(gray, loc.extractor)

    def table(matched: int) -> TrackTable:
        return _table_matched(conf, c.xy, seen, matched)

    with _recorded_nprobe(bundle) as seen_nprobe:
        for matched in (few, most - 1, most, most + 5):
            loc._guided_matching(table(matched), np.arange(matched, n), image, gt)
        unlimited._guided_matching(table(most + 5), np.arange(most + 5, n), image, gt)
    narrow, full = conf.scope_nprobe, conf.nprobe
    assert seen_nprobe == [narrow, narrow, full, full, narrow], seen_nprobe


def test_relocalize_with_a_prior(world, bundle, cam):
    gt = world.gt_cam_from_world[45]
    prior = Rigid3d(
        gt.rotation @ rotmat_from_rotvec([0.02, -0.03, 0.01]), gt.translation + [0.05, -0.03, 0.04]
    )
    r = relocalize(world.gray[45], cam, bundle, prior=prior)
    assert r.status is Status.RELOCALIZED
    dp, dr = pose_errors(r.cam_from_world, gt)
    assert dp < 0.05 and dr < 1.0
    # found around the prior: reported as guided matching (it said "global"), and global only
    # when global matching found it (no prior, or one nowhere near)
    assert r.matching is Matching.GUIDED
    assert relocalize(world.gray[45], cam, bundle).matching is Matching.GLOBAL
    far = Rigid3d(gt.rotation, gt.translation + [100.0, 100.0, 100.0])
    r = relocalize(world.gray[45], cam, bundle, prior=far)
    assert r.status is Status.RELOCALIZED and r.matching is Matching.GLOBAL


# ----------------------------------------------------------------------------- end to end
def run_sequence(loc, frames, stamps):
    return [loc.localize(f, t) for f, t in zip(frames, stamps)]


def test_localizer_end_to_end_on_a_synthetic_video(world, bundle, cam):
    loc = Localizer(bundle, cam)
    first = loc.localize(world.gray[0], 0.0)
    # the result and the state describe the table global matching just built
    assert first.status is Status.RELOCALIZED and first.matching is Matching.GLOBAL
    assert first.tracked_3d == loc.table.n_3d() >= first.inliers > 0
    assert np.array_equal(np.sort(loc.scope_points), np.sort(loc.table.point[loc.table.point >= 0]))
    # each frame makes its own table: the previous frame's is never modified (no alias of it
    # can go stale while the frame runs)
    prev = loc.table
    fields = ("track_id", "xy", "brief", "age", "point", "hyp", "pending")
    saved = {k: getattr(prev, k).copy() for k in fields}
    second = loc.localize(world.gray[1], 1 / 30)
    assert second.status is Status.TRACKING and second.matching is not Matching.GLOBAL
    assert loc.table is not prev and second.tracked_3d == loc.table.n_3d() > 0
    assert all(np.array_equal(getattr(prev, k), v) for k, v in saved.items())
    loc.reset()
    res = run_sequence(loc, world.gray, [i / 30 for i in range(len(world.gray))])
    assert res[0].status is Status.RELOCALIZED and res[0].matching == "global"
    localized = [r for r in res if r.status is not Status.LOST]
    assert len(localized) >= 0.95 * len(res)
    errs = np.array(
        [
            pose_errors(r.cam_from_world, g)
            for r, g in zip(res, world.gt_cam_from_world)
            if r.cam_from_world
        ]
    )
    assert np.median(errs[:, 0]) < 0.03 and np.median(errs[:, 1]) < 0.5
    wrong = [
        r
        for r, g in zip(res, world.gt_cam_from_world)
        if r.status is Status.TRACKING
        and (pose_errors(r.cam_from_world, g)[0] > 0.5 or pose_errors(r.cam_from_world, g)[1] > 10)
    ]
    assert not wrong
    # tracking carries most frames (guided matching distributed, global rarely)
    assert sum(r.status is Status.TRACKING for r in res) > 0.8 * len(res)
    assert sum(r.matching == "global" for r in res) <= 5
    for r in res:
        assert r.detected >= r.tracked >= 0 and r.tracked_3d <= max(r.tracked, r.tracked_3d)
        assert "total" in r.timings_ms and r.latency_ms > 0
        # every lap is a named stage
        assert set(r.timings_ms) - {"total"} <= set(STAGES) and {
            "detect",
            "track",
            "filter",
        } <= set(r.timings_ms)
        if r.filtered_cam_from_world is not None:
            dp, _ = pose_errors(r.filtered_cam_from_world, r.cam_from_world)
            assert dp < 0.2
    # the stages account for the frames' time (over all frames: a preemption after the last lap
    # of one frame does not decide it)
    laps = sum(v for r in res for k, v in r.timings_ms.items() if k != "total")
    assert 0.97 * sum(r.latency_ms for r in res) <= laps <= sum(r.latency_ms for r in res)
    # the same laps in the engine thread's CPU time: the same stages, each within its wall time
    # over the frames (one thread; summed: on this VM the thread's CPU clock and the monotonic
    # clock disagree by up to ~0.06 ms on a single interval), adding up to the frames' CPU
    for r in res:
        assert set(r.cpu_timings_ms) == set(r.timings_ms) and r.cpu_timings_ms["total"] > 0
    for k in STAGES:
        cpu_k = sum(r.cpu_timings_ms.get(k, 0.0) for r in res)
        wall_k = sum(r.timings_ms.get(k, 0.0) for r in res)
        assert cpu_k <= 1.01 * wall_k + 0.1
    cpu_laps = sum(v for r in res for k, v in r.cpu_timings_ms.items() if k != "total")
    cpu_total = sum(r.cpu_timings_ms["total"] for r in res)
    assert 0.97 * cpu_total <= cpu_laps <= cpu_total + 1e-6
    assert all("reloc" in r.timings_ms for r in res if r.matching == "global")
    assert all({"match", "reloc"} & set(r.timings_ms) for r in res if r.matching == "guided")


def test_localizer_on_100_real_frames(redkitchen, tmp_path_factory):
    """A map from 40 real frames (every 25th, known poses) and the first 100 frames of the
    sequence replayed: mostly localized, centimetre-level errors, nothing wrong reported."""
    import cv2

    from sfmloc.builder.build import BuildConf, main
    from sfmloc.io.poses import read_poses

    out = tmp_path_factory.mktemp("rk")
    cam_spec = "PINHOLE 640 480 525.505 525.505 320 240"
    path = main(
        BuildConf(),
        "rk",
        out,
        images=redkitchen,
        poses=redkitchen / "pgt_sfm_seq01.txt",
        camera=cam_spec,
        stride=25,
    )
    bundle = MapBundle(path)
    gt = read_poses(redkitchen / "pgt_sfm_seq01.txt").by_stem()
    loc = Localizer(bundle, Camera.parse(cam_spec))
    errs, lost, wrong = [], 0, 0
    for i in range(100):
        img = cv2.imread(str(redkitchen / f"frame-{i:06d}.color.jpg"), cv2.IMREAD_GRAYSCALE)
        r = loc.localize(img, i / 30)
        if r.cam_from_world is None:
            lost += 1
            continue
        dp, dr = pose_errors(r.cam_from_world, gt[f"frame-{i:06d}.color"])
        errs.append((dp, dr))
        wrong += dp > 0.5 or dr > 10  # tracked or relocalized: no pose may be this wrong
    errs = np.array(errs)
    assert lost <= 5
    assert wrong == 0
    assert np.median(errs[:, 0]) < 0.05 and np.median(errs[:, 1]) < 1.5


# ----------------------------------------------------------------------------- uncertainty
def nees(cov: np.ndarray, est: Rigid3d, gt: Rigid3d) -> float:
    e = pose_error_vector(est, gt)
    return float(e @ np.linalg.solve(cov, e))


def test_pose_covariance_jacobian_and_calibration_with_known_pixel_noise():
    """The analytic Jacobian matches finite differences of the stated parameterization, and
    with independent Gaussian pixel noise (the model's assumption) the NEES over 300 poses
    averages 6 (6 dof): the standard error of that mean is sqrt(12/300) = 0.2."""
    rng = np.random.default_rng(3)
    gt = Rigid3d(rotmat_from_rotvec([0.2, -0.1, 0.3]), [0.5, 0.2, 1.0])
    X, uv = scene_points(rng, 6, gt, K)
    world_from_cam = gt.inverse()

    def uv_at(p):  # perturbation [world-side rotation vector, centre shift]
        R = rotmat_from_rotvec(p[:3]) @ world_from_cam.rotation
        return project(Rigid3d(R, world_from_cam.translation + p[3:]).inverse(), K, X)[0].ravel()

    eps = 1e-6
    J = np.stack(
        [(uv_at(eps * np.eye(6)[i]) - uv_at(-eps * np.eye(6)[i])) / (2 * eps) for i in range(6)], 1
    )
    cov = pose_covariance(gt, K, uv, X, min_noise_px=1.0)  # exact points: variance = floor = 1
    assert np.allclose(cov, np.linalg.inv(J.T @ J), rtol=1e-5, atol=1e-12)
    values = []
    for _ in range(300):
        gt = Rigid3d(rotmat_from_rotvec(rng.normal(0, 0.3, 3)), rng.normal(0, 1, 3))
        X, uv = scene_points(rng, int(rng.integers(12, 200)), gt, K)
        est = estimate_pose(uv + rng.normal(0, rng.uniform(0.3, 1.0), uv.shape), X, K)
        cov = pose_covariance(est.cam_from_world, K, est.inlier_xy, est.inlier_X, min_noise_px=0.0)
        values.append(nees(cov, est.cam_from_world, gt))
    assert 5.4 < np.mean(values) < 6.6, np.mean(values)
    # too few points to constrain a pose: infinite, never a made-up certainty
    assert np.all(np.isinf(pose_covariance(gt, K, uv[:3], X[:3])))


def test_the_first_estimate_of_a_frame_with_many_matches_is_refined_once(
    world, bundle, cam, monkeypatch
):
    """A frame holding ``first_unrefined_from`` matches or more skips its first estimate's
    robust final refinement (the second estimate refines it): one refinement a tracked frame
    fewer, the same frames posed, as accurate, no wrong pose (0: every first estimate refined)."""
    import sfmloc.engine.pose as pose_mod

    real = pose_mod.final_refinement
    calls = [0]

    def counted(*a, **k):
        calls[0] += 1
        return real(*a, **k)

    monkeypatch.setattr(pose_mod, "final_refinement", counted)
    stamps = [i / 30 for i in range(len(world.gray))]
    runs = {}
    for name, conf in (("always", EngineConf(first_unrefined_from=0)), ("many", EngineConf())):
        calls[0] = 0
        res = run_sequence(Localizer(bundle, cam, conf), world.gray, stamps)
        runs[name] = (res, calls[0])
    (always, n_always), (many, n_many) = runs["always"], runs["many"]
    tracked = sum(r.status is Status.TRACKING for r in many)
    assert tracked > 0.8 * len(many)
    assert n_many <= n_always - 0.8 * tracked, (n_many, n_always, tracked)
    assert [r.status is Status.LOST for r in many] == [r.status is Status.LOST for r in always]

    def errors(res):
        return np.array(
            [
                pose_errors(r.cam_from_world, g)
                for r, g in zip(res, world.gt_cam_from_world)
                if r.cam_from_world is not None
            ]
        )

    e_many, e_always = errors(many), errors(always)
    assert np.median(e_many[:, 0]) < 1.2 * np.median(e_always[:, 0]) + 1e-3
    assert np.median(e_many[:, 1]) < 1.2 * np.median(e_always[:, 1]) + 0.02
    assert e_many[:, 0].max() < 0.5 and e_many[:, 1].max() < 10


def test_reported_covariance_is_calibrated_on_a_synthetic_video(world, bundle, cam):
    """Every non-LOST frame carries a finite, symmetric, positive definite 6x6 covariance, and
    over the synthetic video (exact ground truth) the NEES averages near its expected value: 6
    for the 6 dof, 3 for the centre alone. Measured (EngineConf.map_noise_px 0.35, with the
    projected matches' refinement, which lowers the error and leaves the covariance to the
    tracked matches): 5.3 and 2.6 (map noise 0.4: 4.85 and 2.4; 0.3: 5.8 and 2.9; without the
    refinement at 0.4: 5.6 and 2.6); the previous model (map noise 0.75 px, the noise from
    the residuals' RMS), pessimistic: 4.6 and 1.7; the frame's pixel noise alone, optimistic:
    10.6 and 4.8. Consecutive frames
    share map points, so the 60 values are far from independent: the band is what separates
    those models, not a standard error."""
    loc = Localizer(bundle, cam)
    values, centre = [], []
    for i, (img, gt) in enumerate(zip(world.gray, world.gt_cam_from_world)):
        r = loc.localize(img, i / 30)
        if r.status is Status.LOST:
            assert r.covariance is None
            continue
        cov = r.covariance
        assert cov.shape == (6, 6) and np.all(np.isfinite(cov)) and np.allclose(cov, cov.T)
        assert np.linalg.eigvalsh(cov).min() > 0
        values.append(nees(cov, r.cam_from_world, gt))
        e = pose_error_vector(r.cam_from_world, gt)[3:]
        centre.append(float(e @ np.linalg.solve(cov[3:, 3:], e)))
    assert len(values) >= 0.95 * len(world.gray)
    assert 5.0 < np.mean(values) < 8.0, np.mean(values)
    assert 2.0 < np.mean(centre) < 4.0, np.mean(centre)


def test_withholding_judges_the_sd_at_the_upper_bound_of_its_noise_estimate():
    """With few inliers the pixel noise rests on few residuals: the withholding rule takes the
    one-sided 95% bound of a chi-square variance estimate with 2N - 6 dof (reference values
    from scipy.stats.chi2.ppf(0.05, dof)), so a 2.5%-sd pose on 12 inliers is withheld and
    the same sd on 200 inliers is published; z = 0 is the plain rule."""
    from sfmloc.engine.certainty import small_sample_factor, withheld

    for n, ref in ((12, 1.3845), (18, 1.2737), (50, 1.1376), (200, 1.0625)):
        assert abs(small_sample_factor(n, 1.645) - ref) < 2e-3
    conf = EngineConf()
    assert conf.max_position_sd == 0.03
    assert "upper bound 3.5%" in withheld(0.025, 12, conf)
    assert withheld(0.025, 200, conf) is None
    assert withheld(0.025, 12, EngineConf(withhold_noise_z=0)) is None
    assert withheld(0.031, 10_000, EngineConf(withhold_noise_z=0)) is not None


def test_unverified_relocalization_and_its_confirmation(world, bundle, cam):
    """A relocalization failing the strict test is UNVERIFIED, and so are the frames tracked
    from it, until one passes the test (then TRACKING); a verified one is RELOCALIZED."""
    strict = EngineConf(verified_min_inliers=10_000)  # no pose can pass: nothing is verified
    loc = Localizer(bundle, cam, strict)
    res = [loc.localize(world.gray[i], i / 30) for i in range(5)]
    assert [r.status for r in res] == [Status.UNVERIFIED] * 5
    for r, gt in zip(res, world.gt_cam_from_world):
        dp, dr = pose_errors(r.cam_from_world, gt)
        assert (
            dp < 0.05
            and dr < 1
            and r.covariance is not None
            and r.matching != "global"
            or r is res[0]
        )
    loc.conf = EngineConf()  # the next tracked frame passes: confirmed
    r = loc.localize(world.gray[5], 5 / 30)
    assert r.status is Status.TRACKING and r.matching != "global"
    first = Localizer(bundle, cam).localize(world.gray[0], 0.0)
    assert first.status is Status.RELOCALIZED


def test_unverified_pose_on_few_inliers_is_withheld(world, bundle, cam):
    """An UNVERIFIED pose on fewer than unverified_min_inliers inliers is LOST (no pose, no
    covariance), but tracking follows it: the first frame passing the strict test is
    published as TRACKING, without a global matching. Above the limit it stays UNVERIFIED."""
    n = Localizer(bundle, cam).localize(world.gray[0], 0.0).inliers
    assert n >= 20
    for limit, expected in ((n + 1_000, Status.LOST), (n // 2, Status.UNVERIFIED)):
        strict = EngineConf(verified_min_inliers=10_000, unverified_min_inliers=limit)
        loc = Localizer(bundle, cam, strict)
        res = [loc.localize(world.gray[i], i / 30) for i in range(4)]
        assert [r.status for r in res] == [expected] * 4, [r.message for r in res]
        if expected is Status.LOST:
            assert all(r.cam_from_world is None and r.covariance is None for r in res)
            assert all("unverified on" in r.message for r in res)
            assert all(r.matching is not Matching.GLOBAL for r in res[1:])  # still tracked
        loc.conf = EngineConf()
        r = loc.localize(world.gray[4], 4 / 30)
        assert r.status is Status.TRACKING and r.matching is not Matching.GLOBAL
        assert pose_errors(r.cam_from_world, world.gt_cam_from_world[4])[0] < 0.05


def test_collapsed_tracked_pose_needs_a_verified_relocalization(world, bundle, cam):
    """A tracked pose failing the strict test on fewer than collapse_ratio x the last posed
    frame's inliers is checked by global matching on the frame; when that is not verified
    either, the frame is LOST (no pose, not adopted). With the check off the same frames are
    UNVERIFIED (tracked from an unverified relocalization)."""
    never = dict(verified_position_sd=0.0, unverified_min_inliers=0)  # nothing is verified
    loc = Localizer(bundle, cam, EngineConf(collapse_ratio=10.0, **never))  # always "collapsed"
    res = [loc.localize(world.gray[i], i / 30) for i in range(6)]
    assert res[0].status is Status.UNVERIFIED and res[1].status is Status.LOST
    for r in res:  # only global matching gives a pose (relocalized: no collapse check)
        assert (r.status is Status.UNVERIFIED) == (r.matching is Matching.GLOBAL), r.message
        if r.status is Status.LOST:
            assert "tracked pose withheld" in r.message and r.cam_from_world is None
            assert r.covariance is None
    assert sum(r.status is Status.UNVERIFIED for r in res[1:]) >= 1  # it relocalizes again
    loc = Localizer(bundle, cam, EngineConf(collapse_ratio=0.0, **never))
    res = [loc.localize(world.gray[i], i / 30) for i in range(4)]
    assert [r.status for r in res] == [Status.UNVERIFIED] * 4
    assert all(r.matching is not Matching.GLOBAL for r in res[1:])
    for r, gt in zip(res, world.gt_cam_from_world):
        assert pose_errors(r.cam_from_world, gt)[0] < 0.05


def _pingpong_with_stalls(n_video: int, n: int, seed: int) -> tuple[list[int], list[float]]:
    """Frames 0..n_video-1 back and forth (the reliability bench's canary), stamped when a
    lockstep client sends them rather than when they were captured: one video frame apart,
    but the intervals are 23-50 ms, and one in seven waits 0.1-0.35 s for the previous answer
    (a loaded server). The constant-velocity prediction then overshoots by 3-10 frames."""
    rng = np.random.default_rng(seed)
    period = 2 * (n_video - 1)
    frames = [k % period if k % period < n_video else period - k % period for k in range(n)]
    t, stamps = 0.0, []
    for _ in range(n):
        t += rng.uniform(0.1, 0.35) if rng.random() < 0.15 else 0.033 * rng.uniform(0.7, 1.5)
        stamps.append(t)
    return frames, stamps


def test_no_wrong_tracked_pose_when_the_motion_prediction_overshoots(world, bundle, cam):
    """Issue 9/12 (the reliability canary's wrong TRACKING poses, 5-19% of the scene scale
    off): frames whose stamps overstate the motion (stalls) put the tracking windows and the
    pose's prior where the camera is not; near-planar tracked matches then admit a second
    solution near the prediction and it was kept (an LM start from the prior explaining 80% of
    the matches skips RANSAC). The second start from the last pose finds the right solution
    with more inliers. Exact ground truth: no pose beyond the wrong-pose limits; with the
    second start and the ambiguity check off, the same frames give wrong TRACKING poses (the
    failure reproduced: main 1cdd020 had 3 in these 40 frames, 13-15% of the scene scale)."""
    frames, stamps = _pingpong_with_stalls(len(world.gray), 40, seed=1)
    limit = 0.05 * bundle.scene_scale

    def wrong(conf: EngineConf) -> tuple[list[tuple[int, str]], int]:
        loc = Localizer(bundle, cam, conf)
        bad, posed = [], 0
        for k, (f, t) in enumerate(zip(frames, stamps)):
            r = loc.localize(world.gray[f], t)
            if r.cam_from_world is None:
                continue
            posed += 1
            dp, dr = pose_errors(r.cam_from_world, world.gt_cam_from_world[f])
            if dp > limit or dr > 10:
                bad.append((k, r.status.value))
        return bad, posed

    bad, posed = wrong(EngineConf())
    assert bad == [] and posed >= 0.97 * len(frames)
    # (the whole-frame re-match of a pose resting on one match, or on a weak consensus of its
    # tracked matches, catches these frames too: off as well; and the tracking window widened
    # with the stalls' intervals, which keeps the right corners tracked there: at rho)
    off = EngineConf(
        second_start_dt_ratio=0,
        ambiguity_check=False,
        covariance_leave_one_out=False,
        track_consensus=0,
        wide_window_gap_s=0,
    )
    bad_off, _ = wrong(off)
    assert bad_off and all(status == "TRACKING" for _, status in bad_off)


def test_every_8th_frame_keeps_tracking_where_a_fixed_window_relocalizes(world, bundle, cam):
    """Issue 10 (a 3-10 Hz camera, or a server session past capacity): frames 8 video frames
    (0.27 s) apart. The constant-velocity prediction then misses the tracked points by more
    than rho / 2, the fixed window loses them and the engine relocalizes every other frame;
    the window widened with the interval (``wide_window_gap_s``) keeps them tracked. The
    synthetic video back and forth, exact ground truth: every frame posed, none beyond the
    wrong-pose limits, global matching only at the start (its first two frames) and at most
    once more; with the fixed window (main 421d4f3) 14 of the 40 frames relocalize."""
    seqs = [8 * j for j in range(40)]
    stamps = [s / 30 for s in seqs]
    bad, posed, relocs = _replay_back_and_forth(world, bundle, cam, EngineConf(), seqs, stamps)
    assert bad == [] and posed == len(seqs)
    assert relocs <= 3
    bad_fixed, _, fixed = _replay_back_and_forth(
        world, bundle, cam, EngineConf(wide_window_gap_s=0), seqs, stamps
    )
    assert bad_fixed == [] and fixed >= 10


def _replay_back_and_forth(
    world, bundle, cam, conf: EngineConf, seqs: list[int], stamps: list[float]
) -> tuple[list[int], int, int]:
    """The synthetic video played back and forth (``seqs`` count frames along that path,
    stamped ``stamps``) through a fresh engine: the wrong ones of ``seqs`` (over 5% of the
    scene scale or 10 deg off), how many were posed, how many ran global matching."""
    n = len(world.gray)
    period = 2 * (n - 1)
    limit = 0.05 * bundle.scene_scale
    loc = Localizer(bundle, cam, conf)
    bad, posed, relocs = [], 0, 0
    for seq, stamp in zip(seqs, stamps):
        f = seq % period if seq % period < n else period - seq % period
        r = loc.localize(world.gray[f], stamp)
        relocs += r.matching is Matching.GLOBAL
        if r.cam_from_world is None:
            continue
        posed += 1
        dp, dr = pose_errors(r.cam_from_world, world.gt_cam_from_world[f])
        if dp > limit or dr > 10:
            bad.append(seq)
    return bad, posed, relocs


# The reliability bench's gaps pattern, seed 1 (10 Hz ping-pong over the video after a 1.1 s
# gap): a fresh engine replays these frames exactly as the bench did.
_GAP_SEQS = [949, 950, 951, 955, 956, 957, 958, 959, 967, 970, 971, 977]


def _replay_gap_frames(world, bundle, cam, conf: EngineConf) -> tuple[list[int], int]:
    """The gap frames through a fresh engine: the wrong ones (over 5% of the scene scale or
    10 deg off) and how many were posed."""
    stamps = [seq * 0.1 for seq in _GAP_SEQS]
    bad, posed, _ = _replay_back_and_forth(world, bundle, cam, conf, _GAP_SEQS, stamps)
    return bad, posed


def test_no_wrong_tracked_pose_after_a_gap_on_one_influential_wrong_match(world, bundle, cam):
    """Issue 9 (the reliability bench's gaps pattern, seed 1: a TRACKING pose 5.1% of the scene
    scale off after a 0.8 s gap, 76 -> 21 inliers, and the two frames tracked from it): after
    the gap 20 right tracked matches lie on a far wall, which leaves the pose free along one
    direction (centre sd 8.6% of the scene scale), and one wrong match on a near point fixed
    it there, wrongly (sd 0.6% with it). Judged without its most influential match the pose
    is too uncertain, and the whole frame re-matched around it gives the right one. The same
    frames as the bench (a relocalization after a 1.1 s gap starts them, so a fresh engine
    replays them exactly), exact ground truth: every frame posed, none wrong; judging all the
    matches (main d1def86), frames 967, 970 and 971 are wrong."""
    seqs = _GAP_SEQS

    def replay(conf: EngineConf) -> tuple[list[int], int]:
        return _replay_gap_frames(world, bundle, cam, conf)

    # (guided batches of 100, as measured: with batches of 50, 34bb399, these frames take other
    # tracks, 3.3% off at worst with the re-match on or off)
    assert replay(EngineConf(batch_max=100)) == ([], len(seqs))
    # (judging all the matches, at rho: the window widened after the gaps tracks other corners)
    bad_all, _ = replay(
        EngineConf(batch_max=100, covariance_leave_one_out=False, wide_window_gap_s=0)
    )
    assert 967 in bad_all
    assert replay(EngineConf()) == ([], len(seqs))


def _thin_rematch(monkeypatch, agreeing: bool) -> list[float]:
    """``Localizer._densify`` patched to the re-match a thin map gives a suspect pose: from the
    pose, agreeing with it, more certain and not verified (``agreeing``), or no pose more
    certain (None). A pose about to be withheld is re-matched as it is. Returns the list that
    collects each suspect pose's sd without its most influential match over its sd."""
    from sfmloc.engine import localizer as L
    from sfmloc.engine.certainty import Certainty

    judged: list[float] = []
    densify = L.Localizer._densify

    def thin_rematch(self, kps, image, est, cert, wider=None):
        if wider is not None:  # (a pose about to be withheld: re-matched as it is)
            return densify(self, kps, image, est, cert, wider)
        judged.append(cert.position_sd_loo / cert.position_sd)
        if not agreeing:
            return None
        return (
            self.table,
            est,
            Certainty(0.81 * cert.covariance, 0.9 * cert.position_sd, False, 0.0),
        )

    monkeypatch.setattr(L.Localizer, "_densify", thin_rematch)
    return judged


def _wrong_only_without(world, bundle, cam, conf: EngineConf, switch: str) -> tuple[list[int], int]:
    """The gap frames replayed with ``switch`` off (frame 967 published wrong), then with
    ``conf`` as it is: its wrong frames and posed count."""
    bad_off, _ = _replay_gap_frames(world, bundle, cam, conf.model_copy(update={switch: False}))
    assert 967 in bad_off
    return _replay_gap_frames(world, bundle, cam, conf)


def test_a_suspect_pose_its_re_match_cannot_check_is_judged_without_its_one_match(
    world, bundle, cam, monkeypatch
):
    """Robust density-6x at 10 Hz, frame 216: 48 right tracked matches on one far patch (sd
    14% of the scene scale) and one wrong guided match to a nearer point that fixed the pose
    15.9% off (sd 1.41%, 13.5% without it). Its whole-frame re-match started from that pose,
    agreed with it (16.2% off) and did not pass the strict test: published TRACKING. Here the
    frames of the gap test above (frame 967: 20 right matches on a far wall, one wrong near
    match; TRACKING 5.1% off with sd 0.6%, 8.6% without it), with the re-match a thin map
    gives (from the pose, agreeing with it, more certain but not verified): without
    ``suspect_leave_out`` a wrong TRACKING pose; with it, judged at its sd without that match,
    the pose is withheld and no frame is wrong."""
    judged = _thin_rematch(monkeypatch, agreeing=True)
    # (at rho, as the gap test's wrong frames: the window widened after the gaps tracks
    # other corners)
    conf = EngineConf(batch_max=100, wide_window_gap_s=0)
    bad_on, posed = _wrong_only_without(world, bundle, cam, conf, "suspect_leave_out")
    assert max(judged) > 10  # (its sd without the one match: an order of magnitude wider)
    assert bad_on == [] and posed >= len(_GAP_SEQS) - 4, (bad_on, posed)


def test_a_suspect_pose_whose_re_match_finds_no_more_certain_pose_is_judged_without_its_one_match(
    world, bundle, cam, monkeypatch
):
    """Robust density-6x walk at 3 Hz, frame 213: 45 right tracked matches on a far patch and
    one wrong guided match (15 px off at the true pose) that fixed the pose 13.4% of the scene
    scale off at sd 1.61% (13.5% without it). Its whole-frame re-match found no more certain
    pose (11.7% off at sd 13.8%), so ``_densify`` returned none and ``suspect_leave_out``
    (which judged only a pose whose re-match agreed) let it through: TRACKING, and two
    odometry frames on points triangulated from it. Here the gap test's frames (frame 967:
    TRACKING 5.1% off with sd 0.6%, 8.6% without its one wrong match), with the re-match a
    thin map gives a suspect pose (none more certain): without ``suspect_leave_out_unchecked``
    a wrong TRACKING pose; with it, judged at its sd without that match, withheld."""
    judged = _thin_rematch(monkeypatch, agreeing=False)
    # (at rho, as the gap test's wrong frames)
    conf = EngineConf(batch_max=100, wide_window_gap_s=0)
    bad_on, posed = _wrong_only_without(world, bundle, cam, conf, "suspect_leave_out_unchecked")
    assert max(judged) > 10  # (its sd without the one match: an order of magnitude wider)
    assert bad_on == [] and posed >= len(_GAP_SEQS) - 4, (bad_on, posed)


def test_the_re_match_replacing_an_uncertain_pose_is_judged_without_its_one_match(
    world, bundle, cam, monkeypatch
):
    """Robust density-6x walk at 3 Hz, frame 191: its tracked pose was too uncertain to publish
    (sd 3.05% of the scene scale), and its whole-frame re-match replaced it: 13.1% off on 63
    inliers at sd 2.36%, resting on one wrong match (7 px off at the true pose; 19.3% without
    it), published TRACKING. Here the gap test's frames (frame 967: one wrong near match fixes
    the pose 5.1% off, 8.6% without it) with a withholding limit under that pose's sd (0.5% of
    the scene scale), so it is about to be withheld, and the re-match a thin map gives: the
    same pose, more certain, not verified. Without ``suspect_leave_out_unchecked`` the
    re-match is published, wrong; with it, judged at its sd without that match, withheld."""
    from sfmloc.engine import localizer as L
    from sfmloc.engine.certainty import Certainty

    tables = []
    estimate = L.Localizer._estimate_pose

    def estimate_pose(self, table, *args, **kwargs):
        out = estimate(self, table, *args, **kwargs)
        tables[:] = [out[0]]  # (the frame's table the re-match replaces)
        return out

    def thin_rematch(self, kps, image, est, cert, wider=None):
        if wider is None:
            return None
        # (the same pose, more certain: the tracked matches' own, not verified)
        sd = 0.2 * cert.position_sd  # (publishable under the lowered limit)
        return tables[0], est, Certainty(0.04 * cert.covariance, sd, False, cert.position_sd_loo)

    monkeypatch.setattr(L.Localizer, "_estimate_pose", estimate_pose)
    monkeypatch.setattr(L.Localizer, "_densify", thin_rematch)

    conf = EngineConf(batch_max=100, wide_window_gap_s=0, max_position_sd=0.005)
    bad_on, _ = _wrong_only_without(world, bundle, cam, conf, "suspect_leave_out_unchecked")
    assert bad_on == [], bad_on


def test_leave_one_out_covariance_is_the_covariance_without_the_worst_match():
    """``pose_covariances``' second matrix is the covariance of the matches without the one
    whose removal widens the centre's sd most (checked by removing each in turn, at a noise
    floor that fixes the variance), and a pose resting on one near point among far ones on a
    plane says so: its sd without it is several times its sd with it."""
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    pose = Rigid3d(np.eye(3), np.zeros(3))
    X = rng.uniform([-1, -1, 4], [1, 1, 6], (30, 3))
    uv = X[:, :2] / X[:, 2:] * 500 + [320, 240] + rng.normal(0, 0.5, (30, 2))
    cov, loo = pose_covariances(pose, K, uv, X, min_noise_px=2.0)
    worst = max(
        (
            pose_covariance(pose, K, np.delete(uv, i, 0), np.delete(X, i, 0), min_noise_px=2.0)
            for i in range(30)
        ),
        key=lambda c: np.linalg.eigvalsh(c[3:, 3:]).max(),
    )
    np.testing.assert_allclose(loo, worst, rtol=1e-8, atol=1e-12)
    assert np.linalg.eigvalsh(loo[3:, 3:]).max() > np.linalg.eigvalsh(cov[3:, 3:]).max()
    # 20 points on a far plane and one near point
    far = np.column_stack([rng.uniform(-3, 3, (20, 2)), np.full(20, 10.0)])
    X2 = np.vstack([far, [[0.3, 0.2, 1.5]]])
    uv2 = X2[:, :2] / X2[:, 2:] * 500 + [320, 240] + rng.normal(0, 0.5, (21, 2))
    cov2, loo2 = pose_covariances(pose, K, uv2, X2)
    sd = np.sqrt(np.linalg.eigvalsh(cov2[3:, 3:]).max())
    sd_loo = np.sqrt(np.linalg.eigvalsh(loo2[3:, 3:]).max())
    assert sd_loo > 3 * sd


def test_a_tracked_pose_its_re_match_places_elsewhere_is_as_uncertain_as_their_distance(bundle):
    """Issue 17 (the --extend map's redkitchen frame 466, motion blur: TRACKING 17.2 cm = 8.6%
    of the scene scale off on 27 tracked matches on one wall, sd 2.2%, centre NEES 40; its
    whole-frame re-match 4.0% off, sd 1.9%, not verified, 4.7% from it). Exact ground truth:
    27 matches on a slanted wall in the upper part of the image, drifted (as blurred corners
    drift) to where a pose 8.5% of the scene scale along the wall's weakest direction projects
    them, 1 px noise; 1.6 px from their points at the true pose. The pose they give is wrong,
    and its own covariance publishes it (sd under the 3% limit, centre NEES far over its
    chi-square bound). A re-match over the whole frame (29 matches at other depths) is more
    certain but not verified, so it does not replace the pose (29 matches over the upper two
    thirds of the image at 1.2-1.5 scene scales, 1.3 px noise); their difference widens the
    covariance (``with_disagreement``): then it covers the error (centre NEES under the 99%
    quantile of chi-square with 3 dof, 11.34) and the pose is withheld."""
    from sfmloc.engine.certainty import certainty, with_disagreement, withheld

    conf = EngineConf(map_noise_px=0)  # exact map points
    S = bundle.scene_scale
    rng = np.random.default_rng(0)
    gt = Rigid3d(rotmat_from_rotvec([0.05, -0.3, 0.02]), np.array([0.1, -0.2, 0.3]) * S)

    def points(uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        return gt.inverse().apply(np.hstack([(uv - K[:2, 2]) / K[0, 0] * z[:, None], z[:, None]]))

    uv = rng.uniform([80, 50], [530, 320], (27, 2))
    X = points(uv, (1.25 + (uv[:, 1] - 50) / 270 * 0.15) * S)
    # the pose 8.5% along the weakest direction that is likeliest given the matches' geometry
    cov = pose_covariance(gt, K, uv, X, min_noise_px=1.0)
    u = np.linalg.eigh(cov[3:, 3:])[1][:, -1]
    delta = cov[:, 3:] @ np.linalg.solve(cov[3:, 3:], u * 0.085 * S)
    wfc = gt.inverse()
    drift = Rigid3d(rotmat_from_rotvec(delta[:3]) @ wfc.rotation, wfc.translation + delta[3:])
    obs = project(drift.inverse(), K, X)[0] + rng.normal(0, 1.0, uv.shape)
    tracked = estimate_pose(obs, X, K, conf.ransac(), prior=gt)
    assert tracked is not None and tracked.num_inliers == 27
    cert = certainty(tracked, K, bundle, conf)
    e = pose_error_vector(tracked.cam_from_world, gt)

    def centre_nees(c: np.ndarray) -> float:
        return float(e[3:] @ np.linalg.solve(c[3:, 3:], e[3:]))

    # the failure: a wrong pose (over 5% of the scene scale), published, overconfident
    assert np.linalg.norm(e[3:]) > 0.05 * S
    assert withheld(cert.position_sd, tracked.num_inliers, conf) is None
    assert centre_nees(cert.covariance) > 30
    # the whole frame re-matched around it
    uv2 = rng.uniform([40, 40], [600, 340], (29, 2))
    X2 = points(uv2, rng.uniform(1.2, 1.5, 29) * S)
    dense = estimate_pose(uv2 + rng.normal(0, 1.3, uv2.shape), X2, K, conf.ransac(), prior=gt)
    assert dense is not None
    cert_d = certainty(dense, K, bundle, conf)
    assert cert_d.position_sd < cert.position_sd and not cert_d.verified
    wide = with_disagreement(cert, tracked, dense, bundle, conf)
    assert withheld(wide.position_sd, tracked.num_inliers, conf) is not None
    assert centre_nees(wide.covariance) < 11.34
    assert not wide.verified
    # a re-match that agrees leaves a right pose published
    right = estimate_pose(uv + rng.normal(0, 1.0, uv.shape), X, K, conf.ransac(), prior=gt)
    assert right is not None
    cert_r = certainty(right, K, bundle, conf)
    same = with_disagreement(cert_r, right, dense, bundle, conf)
    assert withheld(same.position_sd, right.num_inliers, conf) is None


def test_an_unverified_pose_with_another_solution_nearer_the_motion_is_not_published(
    world, bundle, cam
):
    """Issue 9 (robust walk at 3 Hz, a TRACKING pose 11.6% of the scene scale off on 31
    inliers): RANSAC without the prior on the pose's own matches finds another pose, far from
    it on as many inliers. When that one is nearer the motion prediction, the frame's pose is
    not trusted (a message says why); when ours is nearer, or the check is off, it stands."""
    loc = Localizer(bundle, cam)
    first = loc.localize(world.gray[0], 0.0)
    assert first.status is Status.RELOCALIZED
    rows, _ = loc.table.matches()
    n = len(rows)
    true = world.gt_cam_from_world[0]
    # our pose: 0.2 scene scales to the side of the truth, claiming every match as inlier
    shift = np.array([0.2 * bundle.scene_scale, 0.0, 0.0])
    ours = Rigid3d(true.rotation, true.translation + shift)
    est = PoseEstimate(ours, np.ones(n, bool), n, 1.0)
    why = loc._other_solution(loc.table, est, true)  # the prediction at the truth
    assert why.startswith("ambiguous") and "0.20 scene scales" in why, why
    assert loc._other_solution(loc.table, est, ours) == ""  # the motion sides with ours
    off = Localizer(bundle, cam, EngineConf(ambiguity_check=False))
    assert off._other_solution(loc.table, est, true) == ""
    # the true pose itself: RANSAC agrees with it
    right = PoseEstimate(true, np.ones(n, bool), n, 1.0)
    assert loc._other_solution(loc.table, right, true) == ""


def test_an_ambiguous_tracked_pose_is_checked_by_global_matching(world, bundle, cam, monkeypatch):
    """Issue 9 (robust walk at 3 Hz, frame 23: LOST as ambiguous, 61 inliers from the motion
    prior against 60 for a pose 0.10 scene scales away, while global matching on the frame
    finds ~500): a tracked pose the ambiguity check rejects is checked by global matching on
    the same frame and adopted as RELOCALIZED when that passes the strict test; off
    (``ambiguity_relocalize``), or when global matching is not verified either, the frame is
    LOST as before. The check's verdict is forced on frame 7 (this world's frames are not
    ambiguous); everything else runs for real, against exact ground truth."""
    n, k = 9, 7
    probe = Localizer(bundle, cam)
    tracked = [probe.localize(world.gray[i], i / 30) for i in range(n)]
    assert [r.status for r in tracked[1:]] == [Status.TRACKING] * (n - 1)
    # frame k's tracked pose unverified (the check runs on those only), a global one verified:
    # the strict test asks for one inlier more than tracking kept there (90 of ~105)
    strict = tracked[k].inliers + 1
    # (the tracker's global matching runs on every corner: relocalize in one stage, not from a
    # weak first-stage pose on 300 of them, ``relocalize_first_min_inliers``)
    one = EngineConf(relocalize_first_keypoints=0)
    assert relocalize(world.gray[k], cam, bundle, one).inliers >= strict + 5
    original = Localizer._other_solution

    def verdict(self, table, est, pred):
        if self.frames == k + 1:  # Localizer.frames counts frames: frame k is the (k+1)th
            return "ambiguous: forced by the test"
        return original(self, table, est, pred)

    monkeypatch.setattr(Localizer, "_other_solution", verdict)

    def run(conf: EngineConf) -> list:
        loc = Localizer(bundle, cam, conf)
        return [loc.localize(world.gray[i], i / 30) for i in range(n)]

    limit = 0.05 * bundle.scene_scale
    on = run(EngineConf(verified_min_inliers=strict))
    assert on[k].status is Status.RELOCALIZED and on[k].matching is Matching.GLOBAL, on[k].message
    assert on[k].inliers >= strict
    dp, dr = pose_errors(on[k].cam_from_world, world.gt_cam_from_world[k])
    assert dp < 0.01 * bundle.scene_scale and dr < 1.0
    for r, gt in zip(on[k + 1 :], world.gt_cam_from_world[k + 1 : n]):  # tracked on from it
        assert r.localized and r.matching is not Matching.GLOBAL, (r.status, r.message)
        assert pose_errors(r.cam_from_world, gt)[0] < limit
    for conf in (
        EngineConf(verified_min_inliers=strict, ambiguity_relocalize=False),
        EngineConf(verified_min_inliers=10**6),  # global matching not verified either
    ):
        res = run(conf)
        assert res[k].status is Status.LOST and res[k].cam_from_world is None
        assert res[k].message == "ambiguous: forced by the test"
        for r, gt in zip(res, world.gt_cam_from_world[:n]):
            assert r.cam_from_world is None or pose_errors(r.cam_from_world, gt)[0] < limit


def test_weak_relocalization_against_the_motion_is_rejected(world, bundle, cam):
    """Tracking frames 0-9, then a frame from far along the video: global matching finds it.
    Verified, it is RELOCALIZED; unverified, it contradicts the motion prediction and is LOST
    (no pose adopted) while the last pose is recent, UNVERIFIED once the prediction is stale."""
    far = len(world.gray) - 1
    gt_far = world.gt_cam_from_world[far]
    assert pose_errors(gt_far, world.gt_cam_from_world[9])[0] > 0.05 * bundle.scene_scale
    for conf, expected in (
        (EngineConf(), Status.RELOCALIZED),
        (EngineConf(verified_min_inliers=10_000), Status.LOST),
    ):
        loc = Localizer(bundle, cam, conf)
        for i in range(10):
            assert loc.localize(world.gray[i], i / 30).localized
        r = loc.localize(world.gray[far], 10 / 30)
        assert r.status is expected and r.matching == "global", (r.status, r.message)
        if expected is Status.LOST:
            assert (
                r.cam_from_world is None
                and r.covariance is None
                and "motion prediction" in r.message
            )
            assert loc.table.n_3d() == 0  # not adopted: the next frame relocalizes again
            # frames 0.6 s apart (no reset): rejected while the last pose (frame 9) is recent
            assert loc.localize(world.gray[far], 10 / 30 + 0.6).status is Status.LOST
            r = loc.localize(world.gray[far], 10 / 30 + 1.2)
            assert r.status is Status.UNVERIFIED and r.matching == "global"
        assert pose_errors(r.cam_from_world, gt_far)[0] < 0.05


def test_a_low_rate_weak_relocalization_off_the_prediction_is_rejected(world, bundle, cam):
    """A 3 Hz stream (frames 0, 10, 20, 30), then a frame whose tracks dropped (as when a faster
    camera's frame leaves the tracking window), 5 frames further along than the constant
    velocity predicts: its unverified relocalization, 0.08 scene scales from the prediction,
    is rejected at this interval as at 30 Hz: the limits do not grow with the interval
    (measured, not taken: docs/beyond-the-paper.md#rejected-contradiction-gap; grown by 0.3 x
    speed x interval they kept this pose, and on a thin map at 3 Hz published wrong ones).
    The pose rejected was right: the same frame in a new session (no prediction) is
    published within 1% of the scene scale."""
    frame = 35
    gt = world.gt_cam_from_world[frame]
    weak = {"verified_min_inliers": 10_000}
    loc = Localizer(bundle, cam, EngineConf())
    for k, i in enumerate((0, 10, 20, 30)):
        assert loc.localize(world.gray[i], k / 3).status is not Status.LOST
    assert loc.motion_published
    pred = loc.filter.predict(4 / 3)  # (the frame's own prediction: a second call adds 0 s)
    assert pred is not None
    off = pose_errors(pred, gt)[0] / bundle.scene_scale
    assert 0.05 < off < 0.15, off  # over the limit, within the jump rejection's reach
    loc.conf = EngineConf(**weak)
    loc.table = TrackTable.empty(loc.conf.max_hypotheses)  # the tracks dropped: relocalize
    r = loc.localize(world.gray[frame], 4 / 3)
    assert r.status is Status.LOST and r.matching is Matching.GLOBAL, (r.status, r.message)
    assert "motion prediction" in r.message and r.cam_from_world is None
    fresh = Localizer(bundle, cam, EngineConf(**weak)).localize(world.gray[frame], 4 / 3)
    assert fresh.status is Status.UNVERIFIED, (fresh.status, fresh.message)
    assert pose_errors(fresh.cam_from_world, gt)[0] < 0.01 * bundle.scene_scale


def test_a_wrong_weak_relocalization_at_a_short_gap_is_still_rejected(world, bundle, cam):
    """One frame after a published 30 Hz pose, a weak relocalization 0.08 scene scales from the
    prediction (the distance of the 3 Hz test above), or turned 15 deg from it, is rejected;
    the right pose (at the prediction) is kept. The poses are the truth moved (wrong by
    construction), judged by the check itself (``Localizer._contradiction``)."""
    from sfmloc.engine.certainty import Certainty

    loc = Localizer(bundle, cam, EngineConf())
    for i in range(10):
        assert loc.localize(world.gray[i], i / 30).localized
    assert loc.motion_published
    pred = loc.filter.predict(10 / 30)
    assert pred is not None
    gt = world.gt_cam_from_world[10]
    assert pose_errors(pred, gt)[0] < 0.01 * bundle.scene_scale
    weak = Certainty(np.eye(6) * 1e-4, 0.01, verified=False)
    away = np.array([0.08 * bundle.scene_scale, 0.0, 0.0])
    moved = Rigid3d(gt.rotation, gt.translation - gt.rotation @ away)  # centre + away
    turned = Rigid3d(rotmat_from_rotvec(np.radians([0.0, 15.0, 0.0])), np.zeros(3)) * gt
    assert abs(pose_errors(moved, gt)[0] - 0.08 * bundle.scene_scale) < 1e-9
    for pose, rejected in ((moved, True), (turned, True), (gt, False)):
        est = PoseEstimate(pose, np.ones(50, bool), 50, 1.0)
        message = loc._contradiction(est, weak, pred, 10 / 30)
        assert bool(message) is rejected, message


@pytest.fixture(scope="module")
def ambiguous_world(tmp_path_factory):
    """A square room whose four walls carry the same texture (``repeat_walls``), two boxes."""
    import cv2

    from server_helpers import room_scene
    from sfmloc.builder.build import BuildConf, assemble
    from sfmloc.io.colmap import read_model
    from sfmloc.io.poses import read_poses
    from sfmloc.map.bundle import write_bundle
    from sfmloc.synth import preset
    from sfmloc.synth.main import run

    root = tmp_path_factory.mktemp("ambiguous")
    conf = preset(
        "small",
        mapping_views=40,
        trajectory={"n_frames": 60},
        scene={"size": (5.0, 5.0, 3.0), "repeat_walls": True, "n_boxes": 2},
    )
    run(conf, root / "synth", scene=room_scene(conf.seed, conf.scene))
    data, timings, info = assemble(
        read_model(root / "synth" / "sparse"), root / "synth" / "images", BuildConf()
    )
    bundle = MapBundle(write_bundle(data, root / "maps", "amb", timings_s=timings, index_info=info))
    frames = sorted((root / "synth" / "video").glob("frame-*.png"))
    gt = read_poses(root / "synth" / "video_poses.txt").by_stem()
    gray = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in frames]
    return (
        bundle,
        Camera.from_json(root / "synth" / "camera.json"),
        gray,
        [gt[f.stem] for f in frames],
    )


def test_no_wrong_pose_on_a_scene_with_identical_walls(ambiguous_world):
    """Repeated texture on every wall: whatever the status, no pose beyond the wrong-pose limit
    (5% of the scene scale or 10 deg), and the video is still localized."""
    bundle, cam, gray, gt = ambiguous_world
    from server_helpers import room_scene

    walls = room_scene(0, SynthSceneConf(size=(5.0, 5.0, 3.0), repeat_walls=True, n_boxes=2))
    textures = [f.texture for f in walls.faces if f.recipe[0] == "wall"]
    assert len(textures) == 4 and all(np.array_equal(t, textures[0]) for t in textures)
    limit = 0.05 * bundle.scene_scale
    loc = Localizer(bundle, cam)
    res = [loc.localize(img, i / 30) for i, img in enumerate(gray)]
    wrong = [
        (i, r.status.value, *pose_errors(r.cam_from_world, g))
        for i, (r, g) in enumerate(zip(res, gt))
        if r.localized
        and (
            pose_errors(r.cam_from_world, g)[0] > limit or pose_errors(r.cam_from_world, g)[1] > 10
        )
    ]
    assert not wrong
    assert sum(r.localized for r in res) >= 0.8 * len(res)


def test_single_images_of_identical_walls_are_never_wrong(ambiguous_world):
    """Each frame relocalized alone (no motion to tell the walls apart): whatever the status,
    no pose beyond the wrong-pose limit (5% of the scene scale or 10 deg), the ambiguity said
    as such, and right poses still published."""
    bundle, cam, gray, gt = ambiguous_world
    limit = 0.05 * bundle.scene_scale
    res = [relocalize(img, cam, bundle) for img in gray]
    errors = [
        None if r.cam_from_world is None else pose_errors(r.cam_from_world, g)
        for r, g in zip(res, gt)
    ]
    wrong = [
        (i, r.status.value, r.inliers, e)
        for i, (r, e) in enumerate(zip(res, errors))
        if r.status is not Status.LOST and (e is None or e[0] > limit or e[1] > 10)
    ]
    assert not wrong
    assert sum(r.status is Status.RELOCALIZED for r in res) >= 12
    assert sum(r.message.startswith("ambiguous") for r in res) >= 10
    # Without the second-place and spread tests these frames come out wrong (a pose turned by
    # 90 deg onto a twin wall, with more inliers than the right one): the test bites. (Published
    # RELOCALIZED when verified by guided matching, UNVERIFIED when, strong enough to skip that,
    # it fails the strict test: a pose either way.) On these two frames a weak first-stage pose
    # (300 corners, ``relocalize_first_min_inliers``) finds the right wall: the twin wins on
    # every corner, so the demonstration runs without that path.
    off = EngineConf(second_place_ratio=0, min_inlier_spread=0, relocalize_first_min_inliers=0)
    for i in (40, 58):
        r = relocalize(gray[i], cam, bundle, off)
        assert r.status in (Status.RELOCALIZED, Status.UNVERIFIED)
        assert pose_errors(r.cam_from_world, gt[i])[0] > limit
        r = relocalize(
            gray[i], cam, bundle, off.model_copy(update={"global_verify_min_inliers": 0})
        )
        assert r.status is Status.RELOCALIZED
        assert pose_errors(r.cam_from_world, gt[i])[0] > limit


def test_an_unverified_recovered_pose_is_checked_by_global_matching(ambiguous_world, monkeypatch):
    """Robust walk at 3 Hz (main 2771732), frame 90: tracking found no pose after frame 80's
    12 cm off, and the recovery around the motion prediction agreed on a pose 1.43 m off (53%
    of the scene scale) on 173 inliers, unverified, withheld only by its centre sd 3.02%
    against the 3% limit, while the frame's global matching finds the right pose on 590
    (frame 130 since the wide tracking window: 1.80 m off, 122 inliers). A recovered pose
    failing the strict test is checked by the frame's global matching and replaced by its pose
    when that passes the strict test (``recovered_global_check``). Reproduced on the room of
    identical walls: frame 20's tracks lost and its motion prediction turned by 270 deg about
    the room's vertical axis (onto a twin wall), the recovery agrees on a pose 180 deg off on
    59 inliers (measured), unverified under the strict test of 100 inliers; global matching
    finds 171, the right pose. Without the check that wrong pose is published as TRACKING."""
    bundle, cam, gray, gt = ambiguous_world
    k = 20
    limit = 0.05 * bundle.scene_scale

    def frame_k(check: bool):
        conf = EngineConf(verified_min_inliers=100, recovered_global_check=check)
        return _recovered_from_a_turned_prediction(monkeypatch, ambiguous_world, k, 270.0, conf)

    assert EngineConf().recovered_global_check
    r = frame_k(True)
    assert r.status is Status.RELOCALIZED and r.matching is Matching.GLOBAL, r.message
    assert r.inliers >= 100
    dp, dr = pose_errors(r.cam_from_world, gt[k])
    assert dp < 0.01 * bundle.scene_scale and dr < 1.0, (dp, dr)
    # the check off: the recovered wrong pose is published (the test bites)
    r = frame_k(False)
    assert r.status is Status.TRACKING and r.matching is Matching.GUIDED, r.message
    dp, dr = pose_errors(r.cam_from_world, gt[k])
    assert dp > limit and dr > 10, (dp, dr)


def _recovered_from_a_turned_prediction(
    monkeypatch, world, k: int, degrees: float, conf: EngineConf, every_point: bool = False
):
    """Frame ``k`` of the room of identical walls (``world``) after frames k-4..k-1, with
    every track lost and the motion prediction the recovery starts from turned by
    ``degrees`` about the room's vertical axis (onto a twin wall); ``every_point``: the
    recovery searches every map point, not the last frame's scope. Returns its result."""
    bundle, cam, gray, _ = world
    turn = rotmat_from_rotvec(np.array([0.0, 0.0, np.deg2rad(degrees)]))
    centre = np.array([2.5, 2.5, 0.0])  # the 5 x 5 m room's vertical axis: walls onto walls
    original = Localizer._recover
    wrong_prediction = {"on": False}

    def turned(self, kps, image, pred, scope_points):
        if wrong_prediction["on"]:  # pred o T^-1, T(X) = turn (X - centre) + centre
            rot = pred.rotation @ turn.T
            pred = Rigid3d(rot, pred.translation + pred.rotation @ centre - rot @ centre)
            if every_point:
                scope_points = np.arange(len(self.bundle.points_xyz))
        return original(self, kps, image, pred, scope_points)

    with monkeypatch.context() as patch:  # (undone on return: the next call turns the original)
        patch.setattr(Localizer, "_recover", turned)
        loc = Localizer(bundle, cam, conf)
        for i in range(k - 4, k):
            loc.localize(gray[i], i / 30)
        loc.table = TrackTable.empty(loc.conf.max_hypotheses)  # every track lost
        wrong_prediction["on"] = True
        return loc.localize(gray[k], k / 30)


def test_a_recovered_pose_global_matching_places_elsewhere_is_not_published(
    ambiguous_world, monkeypatch
):
    """The check above, for a recovered pose that passes the strict test too
    (``recovered_verified_check``) and when global matching keeps no pose
    (``recovered_rivals``). On the room of identical walls with the motion prediction turned
    onto a twin wall, main (7eae836, default configuration) published 7 of 24 such frames (10,
    20, 25, 30 turned by 90, 180, 270 deg, the recovery given the last frame's scope or every
    map point) as TRACKING 0.69-1.25 scene scales off on 42-86 inliers, centre sd 0.1-0.4%:
    passing the strict test. Measured: frame 10 turned by 90 deg, every map point: recovered
    0.69 scene scales / 90 deg off on 51 inliers; the frame's global matching calls it
    ambiguous, 165 inliers for the right pose and 64 for a second place where the recovered
    pose is. Frame 20 turned by 270 deg: 86 inliers 0.80 scene scales off; global matching
    finds the right pose on 171, verified."""
    bundle, _, _, gt = ambiguous_world
    limit = 0.05 * bundle.scene_scale
    conf = EngineConf()
    assert conf.recovered_verified_check and conf.recovered_rivals

    def frame(k: int, degrees: float, every_point: bool, **changes):
        c = conf.model_copy(update=changes)
        r = _recovered_from_a_turned_prediction(
            monkeypatch, ambiguous_world, k, degrees, c, every_point
        )
        e = None if r.cam_from_world is None else pose_errors(r.cam_from_world, gt[k])
        return r, e

    # the global matching's right pose on more inliers (ambiguous): no pose
    r, e = frame(10, 90.0, True)
    assert r.status is Status.LOST and r.message.startswith("recovered pose withheld"), (r, e)
    # ... as for a recovered pose failing the strict test (the check's path)
    r, e = frame(10, 90.0, True, verified_min_inliers=100)
    assert r.status is Status.LOST and r.message.startswith("recovered pose withheld"), (r, e)
    # the global matching's right pose verified: it replaces the recovered one
    r, e = frame(20, 270.0, False)
    assert r.status is Status.RELOCALIZED and r.matching is Matching.GLOBAL, r.message
    assert e is not None and e[0] < 0.01 * bundle.scene_scale and e[1] < 1.0, e
    # a right recovered pose stays (frame 10's prediction not turned: global matching calls
    # the frame ambiguous too, its best pose is the recovered one)
    r, e = frame(10, 0.0, False)
    assert r.status is Status.TRACKING and r.matching is Matching.GUIDED, r.message
    assert e is not None and e[0] < 0.01 * bundle.scene_scale and e[1] < 1.0, e
    # without the rules these recovered wrong poses are published (the test bites)
    for k, degrees, every, changes in (
        (10, 90.0, True, {"recovered_verified_check": False}),
        (10, 90.0, True, {"verified_min_inliers": 100, "recovered_rivals": False}),
        (20, 270.0, False, {"recovered_verified_check": False}),
    ):
        r, e = frame(k, degrees, every, **changes)
        assert r.status is Status.TRACKING and r.matching is Matching.GUIDED, r.message
        assert e is not None and e[0] > limit and e[1] > 10, e


def test_replay_cli_writes_tum_and_covariance_side_file(world, tmp_path, capsys):
    from sfmloc.cli.main import main as cli
    from sfmloc.io.poses import read_poses

    traj = tmp_path / "t.tum"
    rc = cli(
        [
            "replay",
            str(world.maps_dir / "room"),
            str(world.frames[0].parent),
            "--camera",
            world.camera_spec,
            "--max-frames",
            "20",
            "--trajectory",
            str(traj),
        ]
    )
    assert rc == 0
    assert len(read_poses(traj, "tum")) >= 19  # a valid TUM file, untouched by the covariance
    tum = [line.split() for line in traj.read_text().splitlines() if not line.startswith("#")]
    cov = [
        line.split()
        for line in (tmp_path / "t.tum.cov").read_text().splitlines()
        if not line.startswith("#")
    ]
    assert [r[0] for r in cov] == [r[0] for r in tum]
    for r in cov:
        C = np.array([float(v) for v in r[2:]]).reshape(6, 6)
        assert r[1] != "LOST" and np.linalg.eigvalsh(C).min() > 0


# ----------------------------------------------------------------------------- bad input
def test_bad_frames_are_errors_or_lost_never_a_made_up_pose(world, bundle, cam):
    loc = Localizer(bundle, cam)
    assert loc.localize(world.gray[0], 0.0).status is Status.RELOCALIZED
    bad = [
        np.zeros((0, 0), np.uint8),
        np.zeros((240, 320), np.uint8),  # wrong size
        world.gray[1].astype(np.float32),  # wrong dtype
        np.zeros((480, 640, 2), np.uint8),  # wrong channels
        "not an image",
    ]
    for b in bad:
        with pytest.raises(ImageDecodeError):
            loc.localize(b, 1 / 30)
    # a constant frame has no keypoints: LOST, no pose
    r = loc.localize(np.full((480, 640), 128, np.uint8), 2 / 30)
    assert r.status is Status.LOST and r.cam_from_world is None and r.detected == 0
    r = relocalize(np.full((480, 640), 128, np.uint8), cam, bundle)
    assert r.status is Status.LOST and r.cam_from_world is None
    # noise: no made-up pose (LOST), or, if anything, not a confident one
    rng = np.random.default_rng(0)
    r = relocalize(rng.integers(0, 255, (480, 640), dtype=np.uint8), cam, bundle)
    assert r.status is Status.LOST
    # and the localizer keeps working on good frames afterwards
    ok = [loc.localize(world.gray[i], (3 + i) / 30) for i in range(3, 10)]
    assert ok[-1].status is not Status.LOST
    dp, _ = pose_errors(ok[-1].cam_from_world, world.gt_cam_from_world[9])
    assert dp < 0.1


def test_status_and_matching_are_enums_read_as_their_wire_strings():
    """Statuses and matching kinds are one pair of enums (the contract's, which the engine
    re-exports) and plain strings on every wire: equal to, printed, formatted, JSON- and
    msgpack-encoded as their values; every status has its gRPC enum value."""
    import json

    import msgpack

    import sfmloc_client.enums as contract
    from sfmloc_client.convert import STATUS_FROM_PB, STATUS_TO_PB
    from sfmloc_client.wire import STATUSES

    assert Status is contract.Status and Matching is contract.Matching
    assert STATUSES == ("TRACKING", "RELOCALIZED", "UNVERIFIED", "LOST")  # the wire's values
    assert [m.value for m in Matching] == ["none", "guided", "global", "odometry"]
    assert set(STATUS_TO_PB) == set(STATUSES) and set(STATUS_FROM_PB.values()) == set(STATUSES)
    for e in (*Status, *Matching):
        assert e == e.value and str(e) == f"{e}" == e.value
        assert json.dumps({e: e}) == f'{{"{e.value}": "{e.value}"}}'
        assert msgpack.unpackb(msgpack.packb(e)) == e.value
    assert Status("LOST") is Status.LOST and Matching("guided") is Matching.GUIDED


def test_engine_imports_no_transport():
    code = (
        "import sys, sfmloc.engine, sfmloc.features.daisy, sfmloc.map.bundle;"
        "bad = [m for m in ('zenoh', 'grpc') if m in sys.modules]; print(bad); sys.exit(1 if bad "
        "else 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_engine_config_has_the_paper_defaults_and_env_overrides():
    from sfmloc.config import load_config

    c = EngineConf()
    assert (c.k, c.sigma, c.beta, c.mu, c.rho, c.psi, c.kappa1, c.kappa2) == (
        50,
        2.0,
        0.8,
        32,
        48,
        0.8,
        25,
        10,
    )
    assert (c.batch_max, c.top_images, c.min_inliers, c.ratio, c.gamma) == (
        100,
        30,
        10,
        0.75,
        0.001,
    )
    c = load_config(
        EngineConf,
        environ={"SFMLOC_ENGINE__K": "64", "SFMLOC_ENGINE__VOTE": "sum"},
        prefix="SFMLOC_ENGINE__",
    )
    assert c.k == 64 and c.vote == "sum"


def test_a_removed_engine_setting_is_dropped_with_a_warning_that_says_why(tmp_path):
    """``batch_min`` was never read: an old config file or a saved bench conf naming it still
    loads (the batch's minimum is ``guided_min_pending``), with a warning saying so."""
    import json

    from sfmloc.config import load_config

    assert "batch_min" not in EngineConf.model_fields
    with pytest.warns(UserWarning, match="batch_min is ignored: it was never read; guided_min"):
        c = EngineConf.model_validate({**EngineConf().model_dump(), "batch_min": 150})
    assert c == EngineConf()
    old = tmp_path / "engine.json"
    old.write_text(json.dumps({"batch_min": 150, "batch_max": 120}))
    with pytest.warns(UserWarning, match="batch_min is ignored"):
        c = load_config(EngineConf, old, environ={}, prefix="SFMLOC_ENGINE__")
    assert c.batch_max == 120 and "batch_min" not in c.model_dump()


def test_frames_localize_keypoints_as_the_map_did(bundle, cam):
    from sfmloc.builder.build import BuildConf
    from sfmloc.engine.tracker import map_subpixel

    # The map's points were triangulated at its keypoints: frames must share their sub-pixel
    # method, read from the bundle (maps built before it was recorded used the quadratic fit).
    params = {"descriptors": BuildConf().descriptors.model_dump()}
    params["descriptors"]["subpixel"] = "forstner"
    assert map_subpixel(EngineConf(), params) == "forstner"
    assert map_subpixel(EngineConf(), {"descriptors": {"octaves": 2}}) == "quadratic"
    assert map_subpixel(EngineConf(subpixel="none"), params) == "none"
    # a bundle without build parameters: the builder's default
    assert Localizer(bundle, cam).subpixel == BuildConf().descriptors.subpixel == "quadratic"


@pytest.mark.parametrize(
    ("conf", "expected_searches"),
    [
        (EngineConf(recovery_search="global"), [True]),
        # scoped (the default): the recovery is judged hopeless on global matching's search,
        # so its own scoped search (a second one) never runs ...
        (EngineConf(), [True]),
        # ... which it does without that check (recover_precheck off): scoped, then global
        (EngineConf(recover_precheck=False), [False, True]),
    ],
    ids=["global", "scoped", "scoped-no-precheck"],
)
def test_a_failed_recovery_and_its_global_matching_describe_and_search_once(
    world, bundle, cam, monkeypatch, conf, expected_searches
):
    """Recovery around the prediction and the global matching that follows it describe the
    same keypoints: DAISY runs once for both, and so does the k-ANN search of the map; with
    the scoped recovery search, a recovery that cannot pass its first test on global
    matching's search (``recover_precheck``) makes no search of its own."""
    from sfmloc.engine.types import Matching
    from sfmloc.features.daisy import DaisyExtractor

    loc = Localizer(bundle, cam, conf)
    for i in range(4):
        loc.localize(world.gray[i], i / 30)
    assert len(loc.scope_points) > 0
    calls = []
    orig = DaisyExtractor.describe

    def counting(self, *a, **k):
        calls.append(len(a[1]))
        return orig(self, *a, **k)

    monkeypatch.setattr(DaisyExtractor, "describe", counting)
    searches = []
    search = bundle.index.search

    def counting_search(q, k, allowed=None, nprobe=None):
        searches.append(allowed is None)
        return search(q, k, allowed=allowed, nprobe=nprobe)

    monkeypatch.setattr(bundle.index, "search", counting_search)
    far = len(world.gray) - 1  # far from the prediction: recovery finds too few matches
    r = loc.localize(world.gray[far], 4 / 30)
    assert r.matching == Matching.GLOBAL and "reloc" in r.timings_ms
    assert len(calls) == 1, calls
    # ... and search the map once (recovery, global matching and its verification share it)
    assert searches == expected_searches, searches
    assert (
        pose_errors(r.cam_from_world, world.gt_cam_from_world[far])[0] < 0.05 * bundle.scene_scale
    )


@pytest.mark.parametrize(
    ("min_tracked", "second_estimates"), [(EngineConf().second_start_min_tracked, 0), (0.0, 1)]
)
def test_a_second_start_that_tracks_few_of_the_last_inliers_estimates_no_pose(
    world, bundle, cam, monkeypatch, min_tracked, second_estimates
):
    """The first start found no pose, and tracking from the last pose kept fewer than
    ``second_start_min_tracked`` of the last frame's inliers: the second start's estimate
    (RANSAC on a few mostly wrong tracks, its whole budget) is skipped; global matching takes
    the frame as before. Without the rule (0) it runs and fails."""
    from sfmloc.engine import localizer as engine

    loc = Localizer(bundle, cam, EngineConf(second_start_min_tracked=min_tracked))
    for i in range(4):
        loc.localize(world.gray[i], i / 30)
    priors = []
    orig = engine.estimate_pose

    def counting(*a, **k):
        priors.append(k.get("prior"))
        return orig(*a, **k)

    monkeypatch.setattr(engine, "estimate_pose", counting)
    tracked = []
    track = Localizer._track_2d

    def counting_track(self, *a, **k):
        out = track(self, *a, **k)
        tracked.append(out[0].n_3d())
        return out

    monkeypatch.setattr(Localizer, "_track_2d", counting_track)
    last, last_inliers = loc.last_pose, loc.last_inliers
    far = 20  # 16 frames on: both starts track a few of the last frame's ~100 inliers
    r = loc.localize(world.gray[far], 4 / 30)
    # (the case: two starts, the second's tracks above kappa2, under the share)
    assert len(tracked) == 2, tracked
    assert loc.conf.kappa2 < tracked[1] < 0.25 * last_inliers, (tracked, last_inliers)
    assert sum(p is last for p in priors) == second_estimates, priors
    assert r.matching == Matching.GLOBAL and r.status is Status.RELOCALIZED, r.message
    dp = pose_errors(r.cam_from_world, world.gt_cam_from_world[far])[0]
    assert dp < 0.02 * bundle.scene_scale, dp


def test_a_second_start_that_tracks_most_of_the_last_inliers_still_estimates(
    world, bundle, cam, monkeypatch
):
    """The early exit above does not fire where the second start succeeds: the camera stopped
    (the same frame again) after a stall, the prediction overshoots half a second of motion,
    the first start finds no pose and the second, from the last pose, tracks the frame."""
    starts = []
    second = Localizer._second_start

    def recording(self, prev, kps, table, est, *a, **k):
        out = second(self, prev, kps, table, est, *a, **k)
        starts.append((est is None, out[1] is not None))
        return out

    monkeypatch.setattr(Localizer, "_second_start", recording)
    for min_tracked in (EngineConf().second_start_min_tracked, 0.0):
        loc = Localizer(bundle, cam, EngineConf(second_start_min_tracked=min_tracked))
        for i in range(4):
            loc.localize(world.gray[i], i / 30)
        starts.clear()
        r = loc.localize(world.gray[3], 0.5)
        # the first start failed and the second gave the pose
        assert starts == [(True, True)], (min_tracked, starts)
        assert r.matching == Matching.GUIDED and r.status is Status.TRACKING, r.message
        dp, dr = pose_errors(r.cam_from_world, world.gt_cam_from_world[3])
        assert dp < 0.01 * bundle.scene_scale and dr < 0.5, (min_tracked, dp, dr)


def test_recovery_around_the_prediction_with_either_search(world, bundle, cam):
    """Tracks lost, motion known: the frame is recovered by guided matching of all its
    keypoints around the prediction (not global matching), whether the candidates come from
    the search over the whole map restricted to the scope or from a scoped search."""
    from sfmloc.engine.types import Matching

    for search in ("global", "scoped"):
        loc = Localizer(bundle, cam, EngineConf(recovery_search=search))
        for i in range(4):
            loc.localize(world.gray[i], i / 30)
        loc.table = TrackTable.empty(loc.conf.max_hypotheses)  # every track lost
        r = loc.localize(world.gray[4], 4 / 30)
        assert r.matching == Matching.GUIDED and r.status is Status.TRACKING, (search, r.message)
        assert "reloc" in r.timings_ms
        dp, dr = pose_errors(r.cam_from_world, world.gt_cam_from_world[4])
        assert dp < 0.02 * bundle.scene_scale and dr < 1.0, (search, dp, dr)


def _pending_table(conf: EngineConf, matched: int, pending: int) -> TrackTable:
    """A track table of ``matched`` rows with a 3D point and ``pending`` rows waiting for
    guided matching (the lazy-wait and spread-batch tests)."""
    t = TrackTable.empty(conf.max_hypotheses)
    n = matched + pending
    t.append(np.arange(n), np.zeros((n, 2)), np.zeros((n, 4), np.uint64))
    t.age[:] = 3
    t.point[:matched] = np.arange(matched)
    t.pending[:] = False
    t.pending[matched:] = True
    return t


def test_a_handful_of_pending_keypoints_waits_while_the_frame_has_matches(bundle, cam):
    """MATCHES-PENDING, lazily: fewer than ``guided_min_pending`` pending keypoints wait for
    more while the table holds at least ``refill_3d`` matches; with fewer matches every
    pending keypoint is tried at once; a full batch is capped at ``batch_max``."""

    conf = EngineConf()
    loc = Localizer(bundle, cam, conf)

    def table(matched: int, pending: int) -> TrackTable:
        return _pending_table(conf, matched, pending)

    few = conf.guided_min_pending - 1
    assert conf.guided_min_pending > 1 and conf.refill_3d > 1
    assert len(loc._pending_batch(table(conf.refill_3d, few))) == 0  # waits
    rows = loc._pending_batch(table(conf.refill_3d - 1, few))  # few matches: at once
    assert rows.tolist() == list(range(conf.refill_3d - 1, conf.refill_3d - 1 + few))
    assert len(loc._pending_batch(table(60, conf.guided_min_pending))) == conf.guided_min_pending
    assert len(loc._pending_batch(table(60, conf.batch_max + 7))) == conf.batch_max
    eager = Localizer(bundle, cam, EngineConf(guided_min_pending=1))
    assert len(eager._pending_batch(table(60, 1))) == 1


def test_guided_batches_spread_only_where_the_map_answers_readily(world, bundle, cam):
    """``batch_spread``: a frame takes at most ``batch_spread`` pending keypoints while the
    running share of guided matching's queries matched (updated by real guided matching) is
    at least ``spread_min_yield``; with a low share (a thin map), after a reset and with
    spreading off, or on a map whose median point is seen by fewer than
    ``batch_spread_min_track`` images, it takes ``batch_max`` at once. The lazy wait is
    unchanged."""
    from sfmloc.engine.scope import median_track_length

    track = median_track_length(bundle)
    conf = EngineConf(batch_spread=40, batch_spread_min_track=track)
    assert 0 < conf.batch_spread < conf.batch_max and 0 < conf.spread_min_yield < 1

    def table(matched: int, pending: int) -> TrackTable:
        return _pending_table(conf, matched, pending)

    loc = Localizer(bundle, cam, conf)
    assert loc.guided_yield == 0.0  # nothing known yet: full batches
    many = table(60, conf.batch_max + 7)
    assert len(loc._pending_batch(many)) == conf.batch_max
    res = run_sequence(loc, world.gray[:60], [i / 30 for i in range(60)])
    assert sum(r.matching == "guided" for r in res) >= 3
    # real guided matching updated the running share (on this scene few pending keypoints
    # match, ~0.05: its batches stay full)
    assert 0.0 < loc.guided_yield < 1.0
    assert all(r.cam_from_world is not None for r in res[1:])
    for r, g in zip(res, world.gt_cam_from_world[:60]):
        if r.cam_from_world is not None:
            assert pose_errors(r.cam_from_world, g)[0] < 0.05 * bundle.scene_scale
    # most queries matched (a map that answers readily) and no 3D match lost lately
    # (spread_keep_up, its own test): the first batch_spread pending rows
    loc.guided_yield, loc.loss_3d = conf.spread_min_yield, 0.0
    rows = loc._pending_batch(many)
    assert rows.tolist() == list(range(60, 60 + conf.batch_spread))
    assert len(loc._pending_batch(table(60, conf.guided_min_pending - 1))) == 0  # still lazy
    # few queries matched (a thin map): full batches at once
    loc.guided_yield = 0.5 * conf.spread_min_yield
    assert len(loc._pending_batch(many)) == conf.batch_max
    loc.reset()
    assert loc.guided_yield == 0.0 and len(loc._pending_batch(many)) == conf.batch_max
    # spreading off, or a map whose median point is seen by fewer images: full batches
    off = Localizer(bundle, cam, EngineConf(batch_spread=0, batch_spread_min_track=track))
    thinner = Localizer(
        bundle, cam, EngineConf(batch_spread=40, batch_spread_min_track=track + 0.5)
    )
    for other in (off, thinner):
        other.guided_yield = 1.0
        assert len(other._pending_batch(many)) == conf.batch_max


def test_guided_batches_spread_only_while_a_short_batch_keeps_up_with_lost_matches(
    world, bundle, cam
):
    """``spread_keep_up``: a frame spreads its batch only while the running number of 3D
    matches its tracked frames lose (``loss_3d``, from real tracking) is under spread_keep_up
    x batch_spread x the running yield, what a short batch brings back; where tracks die
    faster (an orbit at 3 Hz lost ~30 matches a frame against ~25 a short batch brings back;
    redkitchen ~1.3) a waiting keypoint is a lost match, and the batch stays full."""
    from sfmloc.engine.scope import median_track_length

    track = median_track_length(bundle)
    conf = EngineConf(batch_spread=40, batch_spread_min_track=track, spread_keep_up=0.25)
    many = _pending_table(conf, 60, conf.batch_max + 7)
    loc = Localizer(bundle, cam, conf)
    loc.guided_yield = 0.5
    brings = conf.spread_keep_up * conf.batch_spread * loc.guided_yield
    assert conf.spread_min_yield <= loc.guided_yield and brings > 0
    for loss, size in ((0.0, conf.batch_spread), (0.99 * brings, conf.batch_spread)):
        loc.loss_3d = loss
        assert len(loc._pending_batch(many)) == size, loss
    for loss in (brings, 3 * brings):
        loc.loss_3d = loss
        assert len(loc._pending_batch(many)) == conf.batch_max, loss
    loc.reset()
    assert loc.loss_3d == 0.0
    ungated = Localizer(bundle, cam, conf.model_copy(update={"spread_keep_up": 0.0}))
    ungated.guided_yield, ungated.loss_3d = 0.5, 3 * brings
    assert len(ungated._pending_batch(many)) == conf.batch_spread

    # the running loss comes from real tracking: the same video with its frames 5 apart
    # loses more 3D matches per tracked frame than at 30 Hz
    def losses(step: int) -> list[float]:
        run = Localizer(bundle, cam, conf)
        out = []
        for i in range(0, 60, step):
            run.localize(world.gray[i], i / 30)
            out.append(run.loss_3d)
        return out

    near, far = losses(1), losses(5)
    assert max(near) > 0 and np.mean(far) > np.mean(near), (np.mean(near), np.mean(far))


def test_a_1hz_camera_relocalizes_every_frame_whatever_the_noise_on_its_stamps(world, bundle, cam):
    """Frames 1 s apart sat on ``max_frame_gap_s`` when it was 1 s: stamps with float noise
    (every 30th frame of a 30 Hz clock, index / 30: 62/30 - 32/30 = 1.0000000000000002 s) or a
    few ms of jitter reset the tracker on some frames and not on others. At 0.9 s no common
    rate sits on the limit: every frame of a 1 Hz stream relocalizes (consecutive video
    frames, so that tracking could not have failed), and a 2 Hz stream tracks."""
    conf = EngineConf()
    assert conf.max_frame_gap_s == pytest.approx(0.9)
    stamps = [32 / 30, 62 / 30, 92 / 30]  # the float noise of a 30 Hz clock's every 30th
    for jitter in (0.004, -0.003, 0.02, 1e-9, -0.05, 0.0):
        stamps.append(stamps[-1] + 1.0 + jitter)
    over = [i for i in range(1, len(stamps)) if stamps[i] - stamps[i - 1] > 1.0]
    assert 1 in over and 0 < len(over) < len(stamps) - 1, over  # (a 1 s limit: some, not all)
    loc = Localizer(bundle, cam, conf)
    res = [loc.localize(world.gray[k], t) for k, t in enumerate(stamps)]
    assert all(r.matching is Matching.GLOBAL and r.status is not Status.LOST for r in res), [
        (r.status, r.matching) for r in res
    ]
    # 2 Hz, with the same jitter: every frame after the first tracks
    half = [0.0]
    for jitter in (0.004, -0.003, 0.02, 1e-9, -0.05, 0.0):
        half.append(half[-1] + 0.5 + jitter)
    loc = Localizer(bundle, cam, conf)
    res = [loc.localize(world.gray[k], t) for k, t in enumerate(half)]
    assert res[0].matching is Matching.GLOBAL
    assert [r.status for r in res[1:]] == [Status.TRACKING] * (len(half) - 1), [
        (r.status, r.matching) for r in res
    ]
    # with a 1 s limit exactly the gaps over 1 s by noise or jitter reset: frame by frame
    exact = Localizer(bundle, cam, EngineConf(max_frame_gap_s=1.0))
    res = [exact.localize(world.gray[k], t) for k, t in enumerate(stamps)]
    resets = [i for i, r in enumerate(res) if r.matching is Matching.GLOBAL]
    assert resets == [0, *over], [(r.status, r.matching) for r in res]
