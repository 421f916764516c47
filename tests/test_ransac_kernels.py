"""The one-to-many RANSAC's kernels against the code they replace: the pool stop's log miss
probability summed incrementally (only the batches added since the last check) equals, bit for
bit, the sum over every batch recomputed at each check; the vectorized P3P finds OpenCV's
solutions, and a RANSAC presolved with it the same pose and inliers as with OpenCV's."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sfmloc.engine import pose
from sfmloc.engine.pose import RansacParams, estimate_pose_one_to_many, p3p_batch
from sfmloc.testing import one_to_many_matches, scene_points
from sfmloc.transforms import Rigid3d, rotmat_from_rotvec

K = np.array([[525.505, 0, 320.0], [0, 525.505, 240.0], [0, 0, 1]])


def reference_pool_miss_log(pools, in_best) -> float:
    """The sum over every pool, recomputed (before: quadratic in the batches)."""
    out = 0.0
    for pool, n in pools:
        w = float(in_best[pool - 1]) / pool
        if w >= 1.0:
            return -math.inf
        out += n * math.log(1.0 - w**3)
    return out


def test_incremental_pool_miss_log_equals_the_full_sum():
    rng = np.random.default_rng(0)
    checked = infinite = 0
    for trial in range(300):
        n1 = int(rng.integers(3, 700))
        pools: list[tuple[int, int]] = []
        out, done = 0.0, 0
        in_best = np.cumsum(rng.random(n1) < rng.uniform(0.05, 1.0))
        for it in range(0, 1000, 16):
            if rng.random() < 0.1:  # a new best pose: the sum starts again
                in_best = np.cumsum(rng.random(n1) < rng.uniform(0.05, 1.0))
                out, done = 0.0, 0
            if pools:
                out, done = pose._pool_miss_log(pools, in_best, out, done)
                want = reference_pool_miss_log(pools, in_best)
                assert out == want, (trial, it, out, want)  # bit for bit, -inf included
                assert done == len(pools)
                checked += 1
                infinite += out == -math.inf
            pools.append((min(n1, max(8, n1 // 5) + (n1 * it) // 200), 16))
    assert checked > 10000 and infinite > 100  # both branches taken
    # the whole sum at once, as before
    assert pose._pool_miss_log(pools, in_best) == (
        reference_pool_miss_log(pools, in_best),
        len(pools),
    )


def _scene(rng, n, gt):
    """``n`` points 1-6 units in front of ``gt``'s camera anywhere in the image, and their
    pixels."""
    return scene_points(rng, n, gt, K, depth=(1.0, 6.0), margin=0.0)


def test_p3p_batch_finds_opencvs_solutions():
    rng = np.random.default_rng(0)
    gt = Rigid3d(rotmat_from_rotvec([0.3, -0.5, 0.2]), [0.4, -0.2, 1.5])
    X, uv = _scene(rng, 400, gt)
    uv = uv + rng.normal(0, 2.0, uv.shape)  # noisy: the samples' solutions are not the truth
    S = rng.integers(0, 400, (2000, 3))
    S = S[(S[:, 0] != S[:, 1]) & (S[:, 0] != S[:, 2]) & (S[:, 1] != S[:, 2])]
    S[:5, 1] = S[:5, 0]  # degenerate: a point twice
    R, t, idx = p3p_batch(X[S], uv[S], K)
    assert np.all(np.diff(idx) >= 0) and not np.isin(np.arange(5), idx).any()
    found = total = 0
    cv_px = []  # OpenCV's reprojection errors of the samples' own points
    for s in range(5, len(S)):
        n, rv, tv = cv2.solveP3P(X[S[s]], uv[S[s]], K, None, flags=cv2.SOLVEPNP_P3P)
        mine = np.nonzero(idx == s)[0]
        for i in range(n):
            Rc, tc = cv2.Rodrigues(rv[i])[0], tv[i].ravel()
            if not (np.isfinite(Rc).all() and np.isfinite(tc).all()):
                continue  # OpenCV returns NaN poses for some samples
            total += 1
            pc = X[S[s]] @ Rc.T + tc
            cv_px.append(np.abs(pc[:, :2] / pc[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2] - uv[S[s]]))
            d = [np.abs(R[m] - Rc).max() + np.abs(t[m] - tc).max() / np.abs(tc).max() for m in mine]
            found += bool(d) and min(d) < 1e-6
    assert total > 3000 and found == total, (found, total)
    # every solution reprojects its three points exactly, in front of the camera
    pc = np.einsum("nij,nkj->nki", R, X[S[idx]]) + t[:, None, :]
    assert (pc[:, :, 2] > 0).all()
    px = pc[:, :, :2] / pc[:, :, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
    # OpenCV's worst here is 1.2e-7 px; the vectorized solver's 3.5e-5 px on one nearly
    # degenerate sample (not a root-polishing matter: a third Newton step leaves it), a
    # hundred thousandth of the 4 px RANSAC threshold, and refined before it is published
    err, cv_err = np.abs(px - uv[S[idx]]).max((1, 2)), np.max(cv_px, (1, 2))
    assert cv_err.max() < 1e-6
    assert np.median(err) < 1e-9 and np.percentile(err, 99) < 1e-6 and err.max() < 1e-4


def test_degenerate_samples_give_no_pose_to_score():
    """A sample naming one map point twice (two set-1 keypoints matched to one point) makes
    ``cv2.solveP3P`` return NaN translations: both kernels of the RANSAC drop them before
    scoring, and keep OpenCV's finite solutions of the other samples unchanged."""
    from sfmloc.engine.pose import p3p_opencv

    rng = np.random.default_rng(4)
    gt = Rigid3d(rotmat_from_rotvec([0.1, 0.2, -0.1]), [0.2, 0.1, 1.0])
    X, uv = _scene(rng, 50, gt)
    S = np.array([[0, 0, 2], [2, 3, 4], [5, 6, 6], [7, 8, 9]])
    n, _, tv = cv2.solveP3P(X[S[0]], uv[S[0]], K, None, flags=cv2.SOLVEPNP_P3P)
    assert n > 0 and not np.isfinite(np.asarray(tv[:n])).all()  # the NaN pose it returns
    R, t = p3p_opencv(X[S], uv[S], K)
    assert np.isfinite(R).all() and np.isfinite(t).all()
    want = []
    for s in (1, 3):
        n, rv, tv = cv2.solveP3P(X[S[s]], uv[S[s]], K, None, flags=cv2.SOLVEPNP_P3P)
        want += [(cv2.Rodrigues(rv[i])[0], tv[i].ravel()) for i in range(n)]
    assert len(R) == len(want) > 0
    for (Rc, tc), Rm, tm in zip(want, R, t):
        assert np.abs(Rm - Rc).max() < 1e-12 and np.abs(tm - tc).max() < 1e-12
    Rb, tb, idx = p3p_batch(X[S], uv[S], K)
    assert 0 not in idx and np.isfinite(Rb).all() and np.isfinite(tb).all()
    # a RANSAC whose best-ranked keypoints share map points: samples from them are degenerate
    n1 = 40
    s1 = np.r_[np.zeros(8, int), np.arange(1, n1 - 7)]
    ver = np.arange(n1)
    for presolve in (False, True):
        res = estimate_pose_one_to_many(
            uv[s1], X[s1], ver, uv[s1], X[s1], K, RansacParams(min_inliers=20),
            presolve=presolve,
        )  # fmt: skip
        assert res is not None
        Tm = res[0].cam_from_world
        assert np.abs(Tm.rotation - gt.rotation).max() < 1e-6
        assert np.abs(Tm.translation - gt.translation).max() < 1e-6


def test_presolved_ransac_equals_opencvs():
    """The same samples (one stream), OpenCV's solver against the vectorized one: the same
    iterations, inliers and chosen matches, the pose within 1e-7; on a scene whose best pose
    stops the run early and on one that uses the whole budget (no pose: None both)."""
    rng = np.random.default_rng(1)
    gt = Rigid3d(rotmat_from_rotvec([-0.2, 0.4, 0.0]), [1.0, 0.5, 2.0])
    X, uv = _scene(rng, 300, gt)
    uv = uv + rng.normal(0, 0.5, uv.shape)
    n1 = 120
    p1, q2, p2 = one_to_many_matches(rng, 300, n1, 0.6)
    p1_none = rng.integers(0, 300, n1)  # set 1 all wrong
    for s1, max_iterations, posed in ((p1, 1000, True), (p1_none, 300, False)):
        params = RansacParams(min_inliers=30, max_iterations=max_iterations)
        out = []
        for presolve in (False, True):
            stats: dict[str, int] = {}
            res = estimate_pose_one_to_many(
                uv[:n1], X[s1], q2, uv[q2], X[p2], K, params,
                pool_stop=True, presolve=presolve, stats=stats,
            )  # fmt: skip
            out.append((res, stats["iterations"]))
        (a, it_a), (b, it_b) = out
        assert it_a == it_b
        assert (a is not None) == posed and (b is not None) == posed
        if posed:
            assert a is not None and b is not None
            assert 16 <= it_a < max_iterations  # stopped early
            np.testing.assert_array_equal(a[1], b[1])
            assert a[0].num_inliers == b[0].num_inliers > 250
            Ta, Tb = a[0].cam_from_world, b[0].cam_from_world
            assert np.abs(Ta.rotation - Tb.rotation).max() < 1e-7
            assert np.abs(Ta.translation - Tb.translation).max() < 1e-7
        else:
            assert it_a >= max_iterations  # the whole budget
