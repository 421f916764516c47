"""Projected matches for a tracked frame's final refinement (engine/projected.py), against
exact synthetic ground truth: which map points are associated with which keypoints, and what
the refinement on them does to the pose."""

from __future__ import annotations

import numpy as np
import pytest

from sfmloc.engine import EngineConf
from sfmloc.engine.pose import RansacParams, estimate_pose, project
from sfmloc.engine.projected import projected_matches, refine_with_projections
from sfmloc.transforms import Rigid3d, pose_errors, rotmat_from_rotvec

K = np.array([[525.0, 0, 320.0], [0, 525.0, 240.0], [0, 0, 1]])
W, H = 640, 480


def _points(rng, n, cam_from_world, margin=20):
    uv = rng.uniform([margin, margin], [W - margin, H - margin], (n, 2))
    z = rng.uniform(1.5, 6.0, n)
    xc = np.hstack([(uv - K[:2, 2]) / K[0, 0] * z[:, None], z[:, None]])
    return cam_from_world.inverse().apply(xc)


def _spread(rng, n, min_dist):
    """n image positions at least ``min_dist`` apart (dart throwing)."""
    out: list[np.ndarray] = []
    while len(out) < n:
        p = rng.uniform([20, 20], [W - 20, H - 20])
        if all(np.hypot(*(p - q)) >= min_dist for q in out):
            out.append(p)
    return np.array(out)


def test_projected_matches_are_the_right_points_and_ambiguity_is_left_out():
    rng = np.random.default_rng(5)
    gt = Rigid3d(rotmat_from_rotvec([0.1, -0.2, 0.05]), [0.3, -0.1, 0.2])
    # 300 corners at least 8 px apart, each the projection of a map point at its own depth
    uv = _spread(rng, 300, 8.0)
    z = rng.uniform(1.5, 6.0, len(uv))
    X = gt.inverse().apply(np.hstack([(uv - K[:2, 2]) / K[0, 0] * z[:, None], z[:, None]]))
    kp = uv + rng.normal(0, 0.3, uv.shape)  # the frame's keypoints: noisy corners
    truth = np.arange(len(uv))
    # 0-9: a second keypoint 1.5 px away (which of the two is the corner?): not associated
    kp = np.vstack([kp, uv[:10] + [1.5, 0.0]])
    # 10-19: a second map point (the same corner triangulated twice, a little off) projecting
    # 0.8 px away: the closer of the two is taken
    X_dup = gt.inverse().apply(
        np.hstack([(uv[10:20] + [0.8, 0] - K[:2, 2]) / K[0, 0] * z[10:20, None], z[10:20, None]])
    )
    # a point behind the camera projecting onto corner 20's position is not a candidate
    behind = gt.inverse().apply(
        np.hstack([-(uv[20:21] - K[:2, 2]) / K[0, 0] * 2.0, np.array([[-2.0]])])
    )
    points = np.vstack([X, X_dup, behind])
    dup_ids = np.arange(len(X), len(X) + 10)
    # the pose the frame was tracked at: 0.3 px or so off
    pose = Rigid3d(rotmat_from_rotvec([0.1003, -0.2, 0.05]), [0.3, -0.1, 0.2005])
    assert np.abs(project(pose, K, X)[0] - uv).max() < 0.6
    kp_i, pt_i = projected_matches(
        pose, K, W, H, kp, points, np.arange(len(points)), radius_px=1.5, clear_px=3.0
    )
    assert len(np.unique(kp_i)) == len(kp_i)  # one point per keypoint
    right = {int(k): int(k) for k in truth[10:]}
    for k, p in zip(kp_i.tolist(), pt_i.tolist(), strict=True):
        assert k < len(uv), "an ambiguous second keypoint was associated"
        assert k >= 10, "a keypoint with another one 1.5 px away was associated"
        if 10 <= k < 20:
            assert p == k, "the farther of two projections was taken"
        else:
            assert p == right[k], (k, p)
    assert not np.isin(dup_ids, pt_i).any()
    assert len(points) - 1 not in pt_i.tolist()
    # every unambiguous corner is found (290), whatever the pose's 0.3 px error
    assert len(kp_i) == 290


def test_a_refinement_with_projected_matches_lowers_the_pose_error():
    """30 tracked matches and 300 projected ones, 0.7 px noise: the pose refined on all of them
    is more accurate; its inliers (and their count) stay the tracked matches'."""
    params = EngineConf().ransac()
    tracked_err, both_err = [], []
    for seed in range(10):
        rng = np.random.default_rng(20 + seed)
        gt = Rigid3d(rotmat_from_rotvec(rng.normal(0, 0.2, 3)), rng.normal(0, 0.5, 3))
        X = _points(rng, 330, gt)
        uv = project(gt, K, X)[0] + rng.normal(0, 0.7, (330, 2))
        est = estimate_pose(uv[:30], X[:30], K, params)
        assert est is not None
        out = refine_with_projections(est, K, uv[30:], X[30:], params)
        assert out.num_inliers == est.num_inliers and out.inlier_xy is est.inlier_xy
        assert np.array_equal(out.inlier_mask, est.inlier_mask)
        tracked_err.append(pose_errors(est.cam_from_world, gt)[0])
        both_err.append(pose_errors(out.cam_from_world, gt)[0])
    assert np.mean(both_err) < 0.5 * np.mean(tracked_err), (both_err, tracked_err)


def test_projected_matches_that_contradict_the_tracked_ones_leave_the_pose_alone():
    rng = np.random.default_rng(9)
    gt = Rigid3d(rotmat_from_rotvec([0.05, 0.1, -0.1]), [0.1, 0.2, -0.3])
    X = _points(rng, 330, gt)
    uv = project(gt, K, X)[0] + rng.normal(0, 0.3, (330, 2))
    params = RansacParams(loss_scale=1.0)
    est = estimate_pose(uv[:30], X[:30], K, params)
    assert est is not None
    # 300 "projected" matches of another pose, 8 px off for the tracked matches
    other = Rigid3d(gt.rotation, gt.translation + [0.05, 0.0, 0.0])
    wrong_uv = project(other, K, X[30:])[0]
    out = refine_with_projections(est, K, wrong_uv, X[30:], params)
    assert out is est


def test_pairs_the_tracked_matches_already_hold_are_dropped():
    from sfmloc.engine.projected import unmatched_only

    kp_xy = np.array([[10.0, 20.0], [30.5, 40.25], [50.0, 60.0], [70.0, 80.0]])
    kp_i, pt_i = np.array([0, 1, 2, 3]), np.array([100, 101, 102, 103])
    # keypoint 1 is tracked (with point 7); point 103 is tracked at another keypoint
    k, p = unmatched_only(kp_i, pt_i, kp_xy, kp_xy[[1]].copy(), np.array([7, 103]))
    assert k.tolist() == [0, 2] and p.tolist() == [100, 102]
    k, p = unmatched_only(kp_i, pt_i, kp_xy, np.zeros((0, 2)), np.zeros(0, np.int64))
    assert k.tolist() == [0, 1, 2, 3]


def test_scope_points_follow_the_matched_points(bundle):
    """The candidate points are those of the images seeing most of the matched points (each
    once, in the order of its first listing), with their coordinates; the answer is reused for
    the same images of the same bundle, and made again for other images (a relocalization
    elsewhere) or another bundle (a sub-map session swaps them)."""
    from sfmloc.engine.matching import scope_images
    from sfmloc.engine.projected import ScopePoints
    from sfmloc.map.bundle import MapBundle

    ptr, idx = bundle.image_points_ptr, bundle.image_points_idx

    def points_of(images):
        return np.unique(np.concatenate([idx[ptr[i] : ptr[i + 1]] for i in images]))

    scope = ScopePoints(top=3)
    first = np.asarray(idx[ptr[0] : ptr[0] + 40], np.int64)
    got = scope(bundle, first)
    images = np.sort(scope_images(bundle, first, 3))
    assert np.array_equal(np.sort(got), points_of(images))
    listed = np.concatenate([idx[ptr[i] : ptr[i + 1]] for i in images])
    assert len(listed) > len(got)  # the images share points: each is listed once
    first_listing = [int(np.nonzero(listed == p)[0][0]) for p in got]
    assert first_listing == sorted(first_listing)
    pts, xyz = scope.with_xyz(bundle, first)
    assert pts is got and np.array_equal(xyz, bundle.points_xyz[got])
    # stored axis by axis: projected_matches reads the (3, N) rows without a copy
    assert xyz.T.flags.c_contiguous and not xyz.T.flags.writeable
    assert scope(bundle, first[:39]) is got  # the same images: reused
    centers = np.array([T.center for T in bundle.image_cam_from_world])
    far = int(np.argmax(np.linalg.norm(centers - centers[0], axis=1)))
    other = np.asarray(idx[ptr[far] : ptr[far] + 40], np.int64)
    moved = scope(bundle, other)
    assert np.array_equal(np.sort(moved), points_of(scope_images(bundle, other, 3)))
    assert not np.array_equal(np.sort(moved), np.sort(got))
    assert scope(bundle, first) is got  # back to a recent scope: kept
    twin = MapBundle(bundle.path)  # the same map loaded again: another bundle
    assert scope(twin, other) is not moved
    assert scope(bundle, first) is not got  # (a swap starts afresh)


def test_scope_points_keep_the_most_recent_scopes(bundle):
    """The answers of the ``keep`` most recent scopes are kept (a scope that flips back to
    one of a few frames before costs no new deduplication), the least recently used dropped
    first; each equal to a fresh answer, and read only."""
    from sfmloc.engine.projected import ScopePoints

    ptr, idx = bundle.image_points_ptr, bundle.image_points_idx
    scope = ScopePoints(top=2, keep=2)
    seen: dict[bytes, np.ndarray] = {}
    queries = []
    for i in range(bundle.n_images):
        q = np.asarray(idx[ptr[i] : ptr[i] + 30], np.int64)
        got = scope(bundle, q)
        key = np.sort(got).tobytes()
        if key not in seen:
            seen[key] = got
            queries.append(q)
        if len(queries) == 3:
            break
    assert len(queries) == 3  # three distinct scopes
    a, b, c = queries
    pa = scope(bundle, a)  # recomputed: a was dropped when c came (keep 2)
    assert pa is not seen[np.sort(pa).tobytes()]
    assert np.array_equal(pa, seen[np.sort(pa).tobytes()])
    assert scope(bundle, c) is scope(bundle, c)  # c and a kept, b dropped
    assert scope(bundle, a) is pa
    assert not pa.flags.writeable
    fresh = ScopePoints(top=2)
    for q in (a, b, c):
        assert np.array_equal(scope(bundle, q), fresh(bundle, q))
        assert np.array_equal(scope.with_xyz(bundle, q)[1], bundle.points_xyz[scope(bundle, q)])


def test_first_listed_is_the_sorted_deduplication():
    """``_first_listed`` (a mask over the map's points) gives each point once in the order of
    its first listing, as the sort-based ``np.unique`` does, also when a part lists a point
    twice (its fallback) and for no parts."""
    from sfmloc.engine.projected import _first_listed

    rng = np.random.default_rng(3)
    for trial in range(200):
        n = int(rng.integers(1, 300))
        parts = [
            rng.permutation(n)[: int(rng.integers(0, n + 1))].astype(np.int32)
            for _ in range(int(rng.integers(1, 6)))
        ]
        if trial % 3 == 0:  # a part listing a point twice
            parts[-1] = np.concatenate([parts[-1], rng.integers(0, n, 2).astype(np.int32)])
        listed = np.concatenate(parts).astype(np.int64)
        _, first = np.unique(listed, return_index=True)
        got = _first_listed(n, parts)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, listed[np.sort(first)])
    dup = [np.array([3, 1], np.int32), np.array([1, 2, 2, 0], np.int32)]
    np.testing.assert_array_equal(_first_listed(5, dup), [3, 1, 2, 0])
    assert len(_first_listed(10, [])) == 0


def test_projected_matches_of_deduplicated_candidates_are_those_of_the_listing():
    """``ScopePoints`` lists each point once (with its coordinates): the pairs are those of
    the listing with repeats (a point seen by several scope images), ties included (two map
    points at the same place: the first listed wins either way)."""
    rng = np.random.default_rng(7)
    gt = Rigid3d(rotmat_from_rotvec([0.05, 0.1, -0.02]), [0.1, 0.2, -0.1])
    uv = _spread(rng, 200, 8.0)
    z = rng.uniform(1.5, 6.0, len(uv))
    X = gt.inverse().apply(np.hstack([(uv - K[:2, 2]) / K[0, 0] * z[:, None], z[:, None]]))
    points = np.vstack([X, X[:20]])  # 200-219: byte-identical twins of 0-19
    kp = uv + rng.normal(0, 0.3, uv.shape)
    listing = np.concatenate(
        [rng.permutation(len(points)), rng.choice(len(points), 150), np.arange(200, 220)]
    )
    _, first = np.unique(listing, return_index=True)
    once = listing[np.sort(first)]
    want = projected_matches(gt, K, W, H, kp, points, listing, radius_px=1.5, clear_px=3.0)
    got = projected_matches(
        gt, K, W, H, kp, points, once, 1.5, 3.0, np.ascontiguousarray(points[once])
    )
    assert len(want[0]) > 150
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    # of each pair of twins, the one listed first is taken
    pos = {int(p): i for i, p in enumerate(once)}
    for k, p in zip(*got, strict=True):
        if k < 20:
            twin = p + 200 if p < 200 else p - 200
            assert pos[int(p)] < pos[int(twin)]


def _reference_projected_matches(cam_from_world, K, width, height, kp_xy, X, radius_px, clear_px):
    """projected_matches as it was written before its neighbourhood sums were gathered at the
    projections' cells: two 3x3 box filters over the whole cell grid (cv2.boxFilter)."""
    import cv2

    pc = X @ cam_from_world.rotation.T + cam_from_world.translation
    z = pc[:, 2]
    front = z > 1e-9
    zs = np.where(front, z, 1.0)
    u = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    inside = np.nonzero(
        front & (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)
    )[0]
    u, v = u[inside], v[inside]
    gw, gh = int(width / clear_px) + 3, int(height / clear_px) + 3

    def cells(x, y):
        i = np.clip(np.floor(x / clear_px).astype(np.int64) + 1, 0, gw - 1)
        j = np.clip(np.floor(y / clear_px).astype(np.int64) + 1, 0, gh - 1)
        return j * gw + i

    def box(flat, weights=None):
        grid = np.bincount(flat, weights, minlength=gw * gh).astype(np.float64)
        out = cv2.boxFilter(
            grid.reshape(gh, gw), -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT
        )
        return out.ravel()

    kp_cell, p_cell = cells(kp_xy[:, 0], kp_xy[:, 1]), cells(u, v)
    kp_count = box(kp_cell)
    kp_sum = box(kp_cell, np.arange(1, len(kp_xy) + 1, dtype=np.float64))
    p_idx = np.nonzero(kp_count[p_cell] == 1)[0]
    kp = np.rint(kp_sum[p_cell[p_idx]]).astype(np.int64) - 1
    d2 = (kp_xy[kp, 0] - u[p_idx]) ** 2 + (kp_xy[kp, 1] - v[p_idx]) ** 2
    ok = d2 < radius_px * radius_px
    p_idx, kp, d2 = p_idx[ok], kp[ok], d2[ok]
    order = np.lexsort((d2, kp))
    first = np.ones(len(order), bool)
    first[1:] = kp[order[1:]] != kp[order[:-1]]
    sel = order[first]
    return kp[sel], inside[p_idx[sel]].astype(np.int64)


def test_projected_matches_are_those_of_the_box_filter_formulation():
    """The neighbourhood sums gathered at the projections' cells give the pairs of the two
    whole-grid box filters they replace, at the image's edges and corners too (cells clipped
    onto the border, keypoints and projections just outside the image) and in crowded cells."""
    rng = np.random.default_rng(11)
    pose = Rigid3d(rotmat_from_rotvec([0.05, -0.1, 0.02]), [0.1, 0.0, 0.3])
    for trial in range(20):
        n = 300 if trial % 2 else 1500  # sparse, then crowded (several keypoints per cell)
        kp = rng.uniform(-2.0, [W + 2.0, H + 2.0], (n, 2))
        kp[:40] = rng.choice([0.0, 0.4, W - 0.6, W - 0.1], 40)[:, None] * [1, 0] + rng.choice(
            [0.0, 0.3, H - 0.6, H - 0.2], 40
        )[:, None] * [0, 1]
        # map points projecting onto some keypoints (within a pixel), the rest anywhere
        uv = np.vstack(
            [kp[::2] + rng.normal(0, 0.6, kp[::2].shape), rng.uniform(-5, W + 5, (200, 2))]
        )
        z = rng.uniform(1.5, 6.0, len(uv))
        xc = np.hstack([(uv - K[:2, 2]) / K[0, 0] * z[:, None], z[:, None]])
        X = pose.inverse().apply(xc)
        for clear in (2.0, 3.0, 7.5):
            got = projected_matches(pose, K, W, H, kp, X, np.arange(len(X)), 1.5, clear)
            want = _reference_projected_matches(pose, K, W, H, kp, X, 1.5, clear)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
            assert len(got[0]) > 0


@pytest.mark.parametrize("n_kp", [100_000, 100_001])
def test_projected_matches_at_the_one_grid_limit_and_past_it(n_kp):
    """Up to ``_ONE_GRID_MAX_KEYPOINTS`` the count and the index sum share one float64 grid
    (exact below 2^53: the largest index sums); past it they are two grids. Both give the box
    filters' pairs, with 100,000 and 100,001 keypoints on a 4000 x 3000 image (crowded cells
    and ambiguous projections too)."""
    from sfmloc.engine import projected

    assert projected._ONE_GRID_MAX_KEYPOINTS == 100_000
    w, h = 4000, 3000
    k = np.array([[2000.0, 0, 2000.0], [0, 2000.0, 1500.0], [0, 0, 1]])
    rng = np.random.default_rng(5)
    pose = Rigid3d(rotmat_from_rotvec([0.02, 0.03, -0.01]), [0.05, 0.0, 0.1])
    kp = rng.uniform(-1.0, [w + 1.0, h + 1.0], (n_kp, 2))
    uv = np.vstack([kp[::3] + rng.normal(0, 0.6, kp[::3].shape), rng.uniform(0, w, (5000, 2))])
    z = rng.uniform(1.5, 6.0, len(uv))
    X = pose.inverse().apply(np.hstack([(uv - k[:2, 2]) / k[0, 0] * z[:, None], z[:, None]]))
    got = projected_matches(pose, k, w, h, kp, X, np.arange(len(X)), 1.5, 3.0)
    want = _reference_projected_matches(pose, k, w, h, kp, X, 1.5, 3.0)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    # the high keypoint indices are matched too (their index sums are the largest)
    assert len(got[0]) > 10_000 and got[0].max() > n_kp - 10


def test_the_scope_projected_axis_by_axis_is_the_row_major_product_bit_for_bit():
    """``projected_matches`` projects the scope as R @ X^T, (3, N), where it took X @ R^T,
    (N, 3): the same products summed in the same order, so the same bits (what its pairs, and
    the poses refined on them, rest on), for any count of points (BLAS takes other kernels for
    small and large products) and the coordinates' own layout or a copy of them."""
    from sfmloc.transforms import rotmat_from_rotvec as rot

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 7, 64, 255, 1000, 2274, 9000):
        for _ in range(4):
            R = rot(rng.normal(0, 1.5, 3))
            t = rng.normal(0, 3, 3)
            X = rng.normal(0, 1, (n, 3)) * 10.0 ** rng.uniform(-3, 3, (n, 1))
            row_major = X @ np.ascontiguousarray(R.T) + t
            by_axis = R @ np.ascontiguousarray(X.T)
            by_axis += t[:, None]
            if n > 1:  # (one point: matrix-vector products, projected_matches keeps X @ R^T)
                assert row_major.tobytes() == np.ascontiguousarray(by_axis.T).tobytes()
            # and so the pairs: each candidate alone (the one-point path) and all of them
            kp = (K[:2, :2] @ (row_major[:, :2] / row_major[:, 2:]).T).T + K[:2, 2]
            kp = np.vstack([kp + rng.normal(0, 0.3, kp.shape), [[-50.0, -50.0]]])
            pose = Rigid3d(R, t)
            want = _reference_projected_matches(pose, K, W, H, kp, X, 1.5, 3.0)
            got = projected_matches(pose, K, W, H, kp, X, np.arange(n), 1.5, 3.0)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
            for i in range(min(n, 3)):
                one = projected_matches(pose, K, W, H, kp, X, np.array([i]), 1.5, 3.0)
                ref = _reference_projected_matches(pose, K, W, H, kp, X[i : i + 1], 1.5, 3.0)
                np.testing.assert_array_equal(one[0], ref[0])
                np.testing.assert_array_equal(one[1], ref[1] + i)
