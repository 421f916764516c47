"""Distinct relocalizations (engine/distinct.py) against exact ground truth: the inlier spread
over the image, and the second-place test on a scene with a twin (repeated structure)."""

from __future__ import annotations

import numpy as np

from sfmloc.engine import EngineConf
from sfmloc.engine.distinct import inlier_spread, occupied_cells, second_place
from sfmloc.engine.pose import estimate_pose_one_to_many
from sfmloc.testing import scene_points
from sfmloc.transforms import Rigid3d, pose_errors, rotmat_from_rotvec

K = np.array([[525.0, 0, 320.0], [0, 525.0, 240.0], [0, 0, 1]])


def test_inlier_spread_counts_cells_with_keypoints():
    rng = np.random.default_rng(0)
    xy = rng.uniform([0, 0], [640, 480], (400, 2))
    assert occupied_cells(xy, 640, 480) == 16
    assert inlier_spread(xy, xy, 640, 480) == 1.0
    corner = xy[(xy[:, 0] < 160) & (xy[:, 1] < 120)]
    assert inlier_spread(xy, corner, 640, 480) == 1 / 16
    # cells without keypoints do not count against the pose (a half-blank image)
    left = xy[xy[:, 0] < 320]
    assert inlier_spread(left, left[left[:, 1] < 240], 640, 480) == 0.5
    assert inlier_spread(xy, xy[:0], 640, 480) == 0.0
    # points on the far border fall in the last cell, not outside the grid
    assert occupied_cells(np.array([[640.0, 480.0]]), 640, 480) == 1


def test_inlier_spread_over_the_cells_the_map_reaches():
    """With the projections of the map points the pose makes visible, only the cells holding
    keypoints and such a projection count: a map reaching the left quarter of the view."""
    rng = np.random.default_rng(1)
    xy = rng.uniform([0, 0], [640, 480], (400, 2))
    left = xy[xy[:, 0] < 160]  # the 4 cells of the first column
    assert inlier_spread(xy, left, 640, 480) == 4 / 16
    assert inlier_spread(xy, left, 640, 480, xy_visible=left) == 1.0
    assert inlier_spread(xy, left[left[:, 1] < 240], 640, 480, xy_visible=left) == 0.5
    # a visible point where no keypoint is does not count, nor an inlier outside those cells
    blank = xy[xy[:, 1] < 360]  # no keypoints in the bottom row
    visible = np.vstack([left, [[600.0, 470.0]]])
    assert inlier_spread(blank, visible, 640, 480, xy_visible=visible) == 1.0
    assert inlier_spread(xy, xy, 640, 480, xy_visible=left) == 1.0
    assert inlier_spread(xy, left, 640, 480, xy_visible=np.zeros((0, 2))) == 0.0


def _twin_scene(n_twin: int, seed: int = 3):
    """150 points seen by ``gt``; the first ``n_twin`` also exist as a twin, moved by a
    90 deg turn about the vertical axis (a square room's identical walls), seen at the same
    pixels from ``twin_cam``. Every keypoint's hypotheses: its point and, where there is one,
    its twin; set 1 holds one of them per keypoint (the twin for half the twinned ones)."""
    rng = np.random.default_rng(seed)
    gt = Rigid3d(rotmat_from_rotvec([0.05, 0.3, 0.0]), [0.2, -0.1, 0.5])
    X, uv = scene_points(rng, 150, gt, K)
    turn = Rigid3d(rotmat_from_rotvec([0.0, np.pi / 2, 0.0]), [3.0, 0.0, 1.0])  # world -> twin
    points = np.vstack([X, turn.apply(X[:n_twin])])
    twin_cam = Rigid3d(
        gt.rotation @ turn.rotation.T,
        gt.translation - gt.rotation @ turn.rotation.T @ turn.translation,
    )
    uv = uv + rng.normal(0, 0.3, uv.shape)
    q2 = np.concatenate([np.arange(150), np.arange(n_twin)])
    p2 = np.concatenate([np.arange(150), 150 + np.arange(n_twin)])
    order = np.argsort(q2, kind="stable")
    q2, p2 = q2[order], p2[order]
    p1 = np.arange(150)
    flip = np.arange(n_twin)[::2]
    p1[flip] = 150 + flip
    return gt, twin_cam, uv, points, (np.arange(150), p1), (q2, p2)


def _best(uv, points, set1, set2, conf):
    (q1, p1), (q2, p2) = set1, set2
    res = estimate_pose_one_to_many(uv[q1], points[p1], q2, uv[q2], points[p2], K, conf.ransac())
    assert res is not None
    return res[0]


def test_second_place_finds_the_twin_of_a_repeated_scene():
    conf = EngineConf()
    gt, twin_cam, uv, points, set1, set2 = _twin_scene(n_twin=90)
    best = _best(uv, points, set1, set2, conf)
    # the whole scene has more support (150 points against 90): RANSAC finds the truth ...
    assert pose_errors(best.cam_from_world, gt)[0] < 0.01
    other = second_place(best, set1, set2, uv, points, K, conf, scene_scale=3.0)
    # ... and the twin explains 90 of its 150 matches: a second place, exactly the twin's pose
    assert other is not None and other.num_inliers >= 85
    dp, dr = pose_errors(other.cam_from_world, twin_cam)
    assert dp < 0.01 and dr < 0.1, (dp, dr)


def test_no_second_place_without_a_twin_or_below_the_ratio():
    conf = EngineConf()
    gt, _, uv, points, set1, set2 = _twin_scene(n_twin=0)
    best = _best(uv, points, set1, set2, conf)
    assert second_place(best, set1, set2, uv, points, K, conf, scene_scale=3.0) is None
    # a twin of 30 points explains 20% of the 150 inliers: under the 0.3 ratio, not ambiguous
    gt, _, uv, points, set1, set2 = _twin_scene(n_twin=30)
    best = _best(uv, points, set1, set2, conf)
    assert pose_errors(best.cam_from_world, gt)[0] < 0.01
    assert second_place(best, set1, set2, uv, points, K, conf, scene_scale=3.0) is None
    lower = conf.model_copy(update={"second_place_ratio": 0.15})
    other = second_place(best, set1, set2, uv, points, K, lower, scene_scale=3.0)
    assert other is not None and other.num_inliers >= 25


def _ranked_scene(seed: int, ranked: bool, n: int = 300, right: int = 110):
    """``n`` keypoints of a camera at ``gt``; ``right`` of them matched to their point, the
    others to a random one (set 1, one match per keypoint), each keypoint with two more wrong
    hypotheses (set 2). ``ranked``: the right matches first in set 1, as global matching's
    ratio ranking puts most of them (else in random order)."""
    rng = np.random.default_rng(seed)
    gt = Rigid3d(rotmat_from_rotvec([0.1, -0.2, 0.05]), [0.3, 0.1, 0.4])
    X, uv = scene_points(rng, n, gt, K)
    points = np.vstack([X, rng.uniform(-3, 3, (2 * n, 3))])
    uv = uv + rng.normal(0, 0.3, uv.shape)
    good = np.arange(n) < right if ranked else rng.permutation(n) < right
    p1 = np.where(good, np.arange(n), n + rng.integers(0, 2 * n, n))
    q2 = np.repeat(np.arange(n), 3)
    p2 = np.stack([p1, n + rng.integers(0, 2 * n, n), n + rng.integers(0, 2 * n, n)], 1).ravel()
    return gt, uv, points, (np.arange(n), p1), (q2, p2)


def _ranked_ransac(seed: int, ranked: bool, pool_stop: bool):
    """Global RANSAC (default conf) on ``_ranked_scene``: (true pose, result, stats)."""
    gt, uv, points, (q1, p1), (q2, p2) = _ranked_scene(seed, ranked=ranked)
    stats: dict[str, int] = {}
    res = estimate_pose_one_to_many(
        uv[q1],
        points[p1],
        q2,
        uv[q2],
        points[p2],
        K,
        EngineConf().ransac(),
        pool_stop=pool_stop,
        stats=stats,
    )
    return gt, res, stats


def test_prosac_stop_ends_ranked_ransac_sooner_on_the_same_pose():
    """With the right matches ranked first, the pool rule stops within two batches where the
    whole-set rule (37% inliers) runs on; both find the true pose on the same inliers."""
    runs = {}
    for pool_stop in (False, True):
        gt, res, stats = _ranked_ransac(7, ranked=True, pool_stop=pool_stop)
        assert res is not None
        dp, dr = pose_errors(res[0].cam_from_world, gt)
        assert dp < 0.005 and dr < 0.1, (pool_stop, dp, dr)
        runs[pool_stop] = (stats["iterations"], res[0].num_inliers)
    assert runs[True][0] <= 32, runs
    assert runs[False][0] >= 4 * runs[True][0], runs
    assert abs(runs[True][1] - runs[False][1]) <= 2 and runs[True][1] >= 105, runs


def test_prosac_stop_does_not_cut_short_an_unranked_search():
    """Right matches spread through the ranking: the pools are no richer than the whole set,
    so the pool rule stops no sooner than half the whole-set rule's iterations."""
    iters = {}
    for pool_stop in (False, True):
        gt, res, stats = _ranked_ransac(8, ranked=False, pool_stop=pool_stop)
        assert res is not None and pose_errors(res[0].cam_from_world, gt)[0] < 0.005
        iters[pool_stop] = stats["iterations"]
    assert iters[True] >= 0.5 * iters[False] and iters[False] >= 64, iters


def test_minimal_samples_are_three_distinct_indices_in_the_pool():
    from sfmloc.engine.pose import _minimal_samples

    rng = np.random.default_rng(0)
    for pool in (3, 4, 8, 500):
        s = _minimal_samples(rng, pool, 200)
        assert s.shape == (200, 3) and s.min() >= 0 and s.max() < pool
        assert np.all((s[:, 0] != s[:, 1]) & (s[:, 0] != s[:, 2]) & (s[:, 1] != s[:, 2]))
    # every index of a small pool is drawn (no bias to the front)
    assert set(_minimal_samples(rng, 8, 200).ravel()) == set(range(8))
