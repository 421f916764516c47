"""The pose estimator's faster kernels against the code they replace: reprojection errors
without stacked temporaries and errors reused instead of projected again (bit for bit), and
Gauss-Newton from the weighted moments of the Jacobian's nine per-match terms (the same steps
up to rounding: poses within 1e-10, the same inliers), on synthetic scenes with noise,
outliers and points behind the camera, and on the estimator's inputs from real redkitchen
frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from sfmloc.engine import pose
from sfmloc.engine.pose import RansacParams, estimate_pose, reprojection_errors, robust_refine
from sfmloc.transforms import Rigid3d, rotmat_from_rotvec

K = np.array([[525.0, 0, 320.0], [0, 525.0, 240.0], [0, 0, 1]])


# ----------------------------------------------------------------------------- references
def reference_reprojection_errors(cam_from_world, K, xy, X):
    """``project`` and ``np.linalg.norm`` as before."""
    uv, z = pose.project(cam_from_world, K, X)
    err = np.linalg.norm(uv - xy, axis=1)
    err[z <= 1e-6] = np.inf
    return err


def reference_robust_refine(cam_from_world, K, xy, X, scale, iterations=3):
    """Gauss-Newton with a Cauchy loss as before (the Jacobian from temporaries)."""
    R, t = cam_from_world.rotation, cam_from_world.translation
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    n = len(xy)
    if n < 4:
        return cam_from_world
    inv_s2 = 1.0 / (scale * scale)
    J = np.zeros((2, n, 6))
    r = np.empty((2, n))
    for _ in range(iterations):
        pc = X @ R.T + t
        px, py, pz = pc[:, 0], pc[:, 1], pc[:, 2]
        if np.any(pz <= 1e-9):
            break
        iz = 1.0 / pz
        x, y = px * iz, py * iz
        r[0] = fx * x + cx - xy[:, 0]
        r[1] = fy * y + cy - xy[:, 1]
        w = 1.0 / (1.0 + (r[0] * r[0] + r[1] * r[1]) * inv_s2)
        fu, fv = fx * iz, fy * iz
        J[0, :, 0], J[0, :, 1], J[0, :, 2] = -fu * x * py, fu * (pz + x * px), -fu * py
        J[0, :, 3], J[0, :, 5] = fu, -fu * x
        J[1, :, 0], J[1, :, 1], J[1, :, 2] = -fv * (pz + y * py), fv * y * px, fv * px
        J[1, :, 4], J[1, :, 5] = fv, -fv * y
        Jf = J.reshape(2 * n, 6)
        Jw = Jf * np.tile(w, 2)[:, None]
        H = Jw.T @ Jf
        g = Jw.T @ r.reshape(-1)
        try:
            delta = -np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        dR, _ = cv2.Rodrigues(delta[:3].reshape(3, 1))
        R, t = dR @ R, dR @ t + delta[3:]
    out = Rigid3d(R, t)
    return out if out.is_finite() else cam_from_world


# ----------------------------------------------------------------------------- scenes
def noisy_scene(seed: int, n: int):
    """A pose, world points (a few behind the camera) and their pixels with noise and gross
    outliers, and a start pose off by a few centimetres and a degree."""
    rng = np.random.default_rng(seed)
    gt = Rigid3d(rotmat_from_rotvec(rng.normal(0, 0.3, 3)), rng.normal(0, 0.5, 3))
    uv = rng.uniform([0, 0], [640, 480], (n, 2))
    z = rng.uniform(1.5, 8.0, n)
    z[: n // 20] *= -1  # behind the camera
    xc = np.hstack([(uv - K[:2, 2]) / K[0, 0] * z[:, None], z[:, None]])
    X = gt.inverse().apply(xc)
    xy = uv + rng.normal(0, 0.7, uv.shape)
    bad = rng.random(n) < 0.25
    xy[bad] += rng.uniform(-30, 30, (int(bad.sum()), 2))
    start = Rigid3d(
        rotmat_from_rotvec(rng.normal(0, 0.004, 3)) @ gt.rotation,
        gt.translation + rng.normal(0, 0.01, 3),
    )
    return gt, start, xy, X


def assert_same_estimate(a, b):
    assert (a is None) == (b is None)
    if a is None:
        return
    np.testing.assert_array_equal(a.cam_from_world.rotation, b.cam_from_world.rotation)
    np.testing.assert_array_equal(a.cam_from_world.translation, b.cam_from_world.translation)
    np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)
    assert a.num_inliers == b.num_inliers and a.mean_error_px == b.mean_error_px


# ----------------------------------------------------------------------------- tests
@pytest.mark.parametrize("n", [0, 1, 4, 37, 300, 2000])
def test_reprojection_errors_equal_project_and_norm(n):
    for seed in range(3):
        gt, start, xy, X = noisy_scene(seed, max(n, 1))
        xy, X = xy[:n], X[:n]
        for p in (gt, start):
            got = reprojection_errors(p, K, xy, X)
            np.testing.assert_array_equal(got, reference_reprojection_errors(p, K, xy, X))
        if n >= 20:
            assert np.isinf(got).any() and np.isfinite(got).any()


def assert_same_pose(got, want, tol=1e-10):
    """Poses equal up to rounding: rotation entries within ``tol``, translations within
    ``tol`` of their size (the moments-based Gauss-Newton sums the same products in another
    order: 4e-13 at most on these scenes)."""
    np.testing.assert_allclose(got.rotation, want.rotation, rtol=0, atol=tol)
    size = max(1.0, float(np.abs(want.translation).max()))
    np.testing.assert_allclose(got.translation, want.translation, rtol=0, atol=tol * size)


@pytest.mark.parametrize("n", [3, 4, 12, 80, 600])
def test_robust_refine_equals_the_temporaries_version(n):
    for seed in range(4):
        gt, start, xy, X = noisy_scene(10 + seed, n)
        front = (X @ gt.rotation.T + gt.translation)[:, 2] > 0
        for scale, its in ((1.0, 3), (0.5, 1), (2.0, 6)):
            got = robust_refine(start, K, xy[front], X[front], scale, its)
            want = reference_robust_refine(start, K, xy[front], X[front], scale, its)
            assert_same_pose(got, want)
            if its and front.sum() >= 4:
                assert not np.array_equal(got.translation, start.translation)
        # a point behind the camera stops it where the reference stops
        got = robust_refine(start, K, xy, X, 1.0)
        want = reference_robust_refine(start, K, xy, X, 1.0)
        assert_same_pose(got, want)


def test_estimates_with_the_moments_gauss_newton_equal_the_reference(monkeypatch):
    """The estimator's robust paths (final refinement, the frame's own estimate) give the same
    inliers, counts and poses (to rounding) as with the reference Gauss-Newton."""
    for seed in range(6):
        gt, start, xy, X = noisy_scene(50 + seed, 300)
        front = (X @ gt.rotation.T + gt.translation)[:, 2] > 0
        xy, X = xy[front], X[front]
        params = RansacParams(loss_scale=1.0)
        for kw in (
            {},
            dict(prior=start),
            dict(prior=start, prior_threshold=20.0),
            dict(prior=start, prior_threshold=20.0, prior_is_estimate=True),
        ):
            got = estimate_pose(xy, X, K, params, **kw)
            with monkeypatch.context() as m:
                m.setattr(pose, "robust_refine", reference_robust_refine)
                want = estimate_pose(xy, X, K, params, **kw)
            assert got is not None and want is not None
            assert_same_pose(got.cam_from_world, want.cam_from_world)
            np.testing.assert_array_equal(got.inlier_mask, want.inlier_mask)
            assert got.num_inliers == want.num_inliers
            assert got.mean_error_px == pytest.approx(want.mean_error_px, rel=1e-9)


def test_refine_errors_are_those_of_its_pose_and_finish_reuses_them():
    for seed in range(6):
        gt, start, xy, X = noisy_scene(20 + seed, 250)
        for thr, rounds in ((20.0, 1), (20.0, 2), (4.0, 2)):
            p, mask, err = pose._refine(start, K, xy, X, thr, rounds)
            np.testing.assert_array_equal(err, reference_reprojection_errors(p, K, xy, X))
            np.testing.assert_array_equal(mask, err < thr)
            assert pose.refine(start, K, xy, X, thr, rounds)[1].tolist() == mask.tolist()
            mask = err < 4.0
            # the estimate from reused errors is the one from projecting its inliers again
            a = pose._finish(p, mask, K, xy, X, 10, err)
            b = pose._finish(p, mask, K, xy, X, 10)
            assert_same_estimate(a, b)
            assert a is not None and a.mean_error_px < 4.0


def test_estimate_pose_paths_recover_the_pose():
    """Every branch that now reuses errors (prior with and without the loose first round,
    plain least squares, RANSAC) still finds the true pose and its inliers, counted as a
    Python int."""
    for seed in range(3):
        gt, start, xy, X = noisy_scene(30 + seed, 300)
        front = (X @ gt.rotation.T + gt.translation)[:, 2] > 0
        xy, X = xy[front], X[front]
        good = reference_reprojection_errors(gt, K, xy, X) < 3.0
        for loss in (0.0, 1.0):
            params = RansacParams(loss_scale=loss)
            for kw in (
                {},
                dict(prior=start),
                dict(prior=start, prior_threshold=20.0),
                dict(prior=start, prior_threshold=20.0, prior_is_estimate=True),
            ):
                est = estimate_pose(xy, X, K, params, **kw)
                assert est is not None
                c = est.cam_from_world
                assert np.linalg.norm(c.center - gt.center) < 0.02
                assert (est.inlier_mask == good).mean() > 0.97
                # a Python int and float (the replay's JSON takes them as they are)
                assert type(est.num_inliers) is int and type(est.mean_error_px) is float


def test_kernels_on_redkitchen_corners_equal_the_references(redkitchen: Path):
    """Real keypoint layouts: Harris corners of redkitchen frames, with world points along
    their rays at random depths seen from a random pose, and noise; the errors bit for bit,
    the robust refinement to rounding."""
    from sfmloc.features.harris import detect_corners

    rng = np.random.default_rng(0)
    for i in (0, 300, 600, 900):
        gray = cv2.imread(str(redkitchen / f"frame-{i:06d}.color.jpg"), cv2.IMREAD_GRAYSCALE)
        xy = detect_corners(gray, rel_threshold=0.001, max_corners=400, border=16).xy
        gt = Rigid3d(rotmat_from_rotvec(rng.normal(0, 0.5, 3)), rng.normal(0, 1.0, 3))
        z = rng.uniform(1.0, 4.0, len(xy))
        X = gt.inverse().apply(np.hstack([(xy - K[:2, 2]) / K[0, 0] * z[:, None], z[:, None]]))
        xy_n = xy + rng.normal(0, 0.8, xy.shape)
        start = Rigid3d(rotmat_from_rotvec(rng.normal(0, 0.005, 3)) @ gt.rotation, gt.translation)
        np.testing.assert_array_equal(
            reprojection_errors(start, K, xy_n, X),
            reference_reprojection_errors(start, K, xy_n, X),
        )
        got = robust_refine(start, K, xy_n, X, 1.0)
        want = reference_robust_refine(start, K, xy_n, X, 1.0)
        assert_same_pose(got, want)
        assert np.linalg.norm(got.center - gt.center) < 0.01


def reference_without_most_influential(cov, J, w):
    """The leave-one-out covariance as before: batched (n, 2, 6) products, a three-operand
    einsum and one LAPACK eigensolve per correspondence."""
    n = len(J) // 2
    if n <= 4:
        return np.full((6, 6), np.inf)
    Ji = J.reshape(n, 2, 6)
    A = Ji @ cov
    S = -np.einsum("nij,nkj->nik", A, Ji)
    S[:, 0, 0] += 1.0 / w[0::2]
    S[:, 1, 1] += 1.0 / w[1::2]
    det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
    scale = (1.0 / w[0::2]) * (1.0 / w[1::2])
    if not ((det > 1e-9 * scale) & (S[:, 0, 0] > 0)).all():
        return np.full((6, 6), np.inf)
    Sinv = np.empty_like(S)
    Sinv[:, 0, 0], Sinv[:, 1, 1] = S[:, 1, 1] / det, S[:, 0, 0] / det
    Sinv[:, 0, 1], Sinv[:, 1, 0] = -S[:, 0, 1] / det, -S[:, 1, 0] / det
    Ap = A[:, :, 3:]
    pos = cov[3:, 3:] + np.einsum("nki,nkl,nlj->nij", Ap, Sinv, Ap)
    worst = int(np.argmax(np.linalg.eigvalsh(pos)[:, -1]))
    out = cov + A[worst].T @ Sinv[worst] @ A[worst]
    return 0.5 * (out + out.T)


def test_symmetric_eigensolvers_equal_numpy_linalg_bit_for_bit():
    """``eigh_sym`` / ``eigvalsh_sym`` (the LAPACK gufuncs without numpy.linalg's wrapper)
    against ``np.linalg.eigh`` / ``eigvalsh``, bytes equal: the 6x6 normal matrices and 3x3
    centre blocks (views, as ``position_sd`` passes them) of random, near-singular and diagonal
    symmetric matrices."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(300, 6, 6)) * rng.uniform(1e-4, 1e4, (300, 1, 1))
    mats = list(A @ A.transpose(0, 2, 1)) + list(A + A.transpose(0, 2, 1))
    mats += [np.diag(rng.uniform(0, 1, 6)), np.outer(*rng.normal(size=(2, 6))) + np.eye(6)]
    for H in mats:
        H = 0.5 * (H + H.T)
        w, V = pose.eigh_sym(H)
        w0, V0 = np.linalg.eigh(H)
        assert w.tobytes() == w0.tobytes() and V.tobytes() == V0.tobytes()
        for block in (H, H[3:, 3:]):
            assert pose.eigvalsh_sym(block).tobytes() == np.linalg.eigvalsh(block).tobytes()


def test_largest_eigenvalues_3x3_equal_lapack():
    """The closed form against ``np.linalg.eigvalsh`` on random, near-degenerate (a double and
    a triple eigenvalue), rank-deficient and diagonal symmetric matrices: within 1e-12 of the
    spectrum's scale, but 5e-8 where the largest eigenvalue is double (the cosine is taken at
    arccos(-1), where a rounding of r moves the angle by sqrt(eps))."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(500, 3, 3))
    mats = [A @ A.transpose(0, 2, 1), A + A.transpose(0, 2, 1)]
    Q = np.linalg.qr(rng.normal(size=(200, 3, 3)))[0]
    for ev in ([1.0, 1.0, 2.0], [2.0, 2.0, 1.0], [3.0, 3.0, 3.0], [0.0, 0.0, 1e-6]):
        mats.append(Q @ (np.asarray(ev)[:, None] * Q.transpose(0, 2, 1)))
    mats.append(np.einsum("ni,ij->nij", rng.uniform(0, 1e-4, (50, 3)), np.eye(3)))
    M = np.concatenate(mats)
    got = pose._largest_eigenvalues_3x3(
        M[:, 0, 0], M[:, 1, 1], M[:, 2, 2], M[:, 0, 1], M[:, 0, 2], M[:, 1, 2]
    )
    want = np.linalg.eigvalsh(M)[:, -1]
    ev = np.linalg.eigvalsh(M)
    scale = np.abs(ev).max(axis=1)
    double_top = ev[:, 2] - ev[:, 1] < 1e-6 * scale
    assert 150 < double_top.sum() < 500  # the [2, 2, 1] and [3, 3, 3] sets (and no other)
    err = np.abs(got - want) / scale
    assert err[~double_top].max() < 1e-12
    assert err[double_top].max() < 5e-8


def reference_pose_covariances(
    cam_from_world,
    K,
    xy,
    X,
    min_noise_px=pose.MIN_NOISE_PX,
    point_sigma_px=None,
    loss_scale=0.0,
    leave_one_out=True,
):
    """``pose_covariances`` as before: the (2N, 6) Jacobian in the covariance's parameters
    written out per entry, and the batched leave-one-out above."""
    n = len(xy)
    inf = np.full((6, 6), np.inf)
    if n < 4:
        return inf, inf
    R_cw = cam_from_world.rotation
    c = cam_from_world.center
    d = np.asarray(X, np.float64) - c
    pc = d @ R_cw.T
    x, y, z = pc[:, 0], pc[:, 1], np.maximum(pc[:, 2], 1e-9)
    fx, fy = K[0, 0], K[1, 1]
    J = np.empty((2 * n, 6))
    a_u = (fx / z)[:, None] * (R_cw[0] - (x / z)[:, None] * R_cw[2])
    a_v = (fy / z)[:, None] * (R_cw[1] - (y / z)[:, None] * R_cw[2])
    for a, rows in ((a_u, slice(0, 2 * n, 2)), (a_v, slice(1, 2 * n, 2))):
        J[rows, 0] = a[:, 1] * d[:, 2] - a[:, 2] * d[:, 1]
        J[rows, 1] = a[:, 2] * d[:, 0] - a[:, 0] * d[:, 2]
        J[rows, 2] = a[:, 0] * d[:, 1] - a[:, 1] * d[:, 0]
        J[rows, 3:] = -a
    uv = np.stack([fx * x / z + K[0, 2], fy * y / z + K[1, 2]], 1)
    r2 = np.sum((uv - xy) ** 2, axis=1)
    rw = 1.0 / (1.0 + r2 / loss_scale**2) if loss_scale > 0 else np.ones(n)
    dof = max(2 * float(rw.sum()) - 6, 1.0)
    var = max(float(np.sum(rw * r2)) / dof, min_noise_px**2)
    if point_sigma_px is None:
        w = np.repeat(rw / var, 2)
    else:
        w = np.repeat(rw / (var + np.asarray(point_sigma_px, np.float64) ** 2), 2)
    H = (J * w[:, None]).T @ J
    if not np.all(np.isfinite(H)):
        return inf, inf
    ev, V = np.linalg.eigh(H)
    if not ev[0] > 0 or ev[-1] > 1e12 * ev[0]:
        return inf, inf
    cov = (V / ev) @ V.T
    cov = 0.5 * (cov + cov.T)
    return cov, (reference_without_most_influential(cov, J, w) if leave_one_out else cov)


def _covariance_case(base: int, seed: int, n: int):
    """A covariance test case: ``n`` matches in front of the camera of ``noisy_scene(base +
    seed)``; odd seeds put the points bunched on a far plane (depth 9, pixels 0.5 px noisy),
    seeds not divisible by 3 give per-point uncertainties (px). (gt, xy, X, sigma or None)"""
    gt, _, xy, X = noisy_scene(base + seed, n + n // 10 + 2)
    front = (X @ gt.rotation.T + gt.translation)[:, 2] > 0
    xy, X = xy[front][:n], X[front][:n]
    rng = np.random.default_rng(seed)
    if seed % 2:
        depth = np.full((len(xy), 1), 9.0)
        X = gt.inverse().apply(np.hstack([(xy - K[:2, 2]) / K[0, 0] * depth, depth]))
        xy = xy + rng.normal(0, 0.5, xy.shape)
    sig = rng.uniform(0, 1.5, len(xy)) if seed % 3 else None
    return gt, xy, X, sig


@pytest.mark.parametrize("n", [4, 5, 6, 30, 150, 600])
def test_covariances_equal_the_jacobian_written_out(n):
    """The covariance from the weighted moments in ``robust_refine``'s parameters, turned into
    the covariance's, against the (2N, 6) Jacobian in the covariance's parameters and the
    batched leave-one-out: the same matrices to rounding (1e-9 of their largest entry), both
    infinite together, with and without point uncertainties, the Cauchy weights, the
    leave-one-out, and on points bunched on a far plane."""
    for seed in range(6):
        gt, xy, X, sig = _covariance_case(40, seed, n)
        for loss, loo_on in ((1.0, True), (0.0, True), (1.0, False)):
            kw = dict(point_sigma_px=sig, loss_scale=loss, leave_one_out=loo_on)
            got = pose.pose_covariances(gt, K, xy, X, **kw)
            want = reference_pose_covariances(gt, K, xy, X, **kw)
            for g, w in zip(got, want):
                assert np.isfinite(g).all() == np.isfinite(w).all()
                if np.isfinite(w).all():
                    # rounding grows with the condition number (up to 3e6 on 5 matches: 1.3e-9)
                    ev = np.linalg.eigvalsh(w)
                    tol = max(1e-10, 1e-14 * ev[-1] / ev[0]) * np.abs(w).max()
                    np.testing.assert_allclose(g, w, rtol=0, atol=tol)
            if n >= 30:  # a pose the matches constrain: both matrices finite
                assert np.isfinite(got[0]).all() and np.isfinite(got[1]).all()
            if not loo_on:
                assert got[1] is got[0]


def reference_refine_lm(cam_from_world, K, xy, X, threshold):
    """``_refine``'s one round with OpenCV's Levenberg-Marquardt, as before."""
    err = reprojection_errors(cam_from_world, K, xy, X)
    mask = err < threshold
    rvec, _ = cv2.Rodrigues(cam_from_world.rotation)
    rvec, tvec = cv2.solvePnPRefineLM(
        X[mask], xy[mask], K, None, rvec, cam_from_world.translation.reshape(3, 1).copy()
    )
    pose_ = pose._rigid(rvec, tvec)
    return pose_, reprojection_errors(pose_, K, xy, X)


def _scene_and_prediction(
    seed: int, n: int, rng: np.random.Generator
) -> tuple[Rigid3d, np.ndarray, np.ndarray, Rigid3d]:
    """A noisy scene's pose, its first ``n`` matches in front of the camera, and a prediction
    ~1.5 deg and ~5 cm off (10-20 px on these scenes), as the tracker's first estimate starts."""
    gt, _, xy, X = noisy_scene(seed, n + n // 10 + 2)
    front = (X @ gt.rotation.T + gt.translation)[:, 2] > 0
    start = Rigid3d(
        rotmat_from_rotvec(rng.normal(0, 0.015, 3)) @ gt.rotation,
        gt.translation + rng.normal(0, 0.03, 3),
    )
    return gt, xy[front][:n], X[front][:n], start


@pytest.mark.parametrize("n", [12, 40, 120, 600])
def test_least_squares_reaches_the_levenberg_marquardt_minimum(n):
    """The tracker's first refinement (one round on the matches within 20 px of a prediction)
    by Gauss-Newton lands where OpenCV's Levenberg-Marquardt did: poses within 1e-5 (rotation
    entries; translations relative to their size), from predictions 3-17 px off, with noise
    and outliers among the matches; the same matches within 3 px, and a squared error no
    larger. Where they differ by more than 1e-7 (8 of 32 scenes, 2.7e-6 at most, on 8
    matches), Levenberg-Marquardt stopped first (its tolerance is float epsilon): its squared
    error is the larger, by 1e-11 to 6e-10."""
    rng = np.random.default_rng(n)
    for seed in range(8):
        gt, xy, X, start = _scene_and_prediction(100 + seed, n, rng)
        got, _, err = pose._refine(start, K, xy, X, 20.0, rounds=1, gauss_newton=True)
        want, want_err = reference_refine_lm(start, K, xy, X, 20.0)
        assert_same_pose(got, want, tol=1e-5)
        np.testing.assert_array_equal(err < 3.0, want_err < 3.0)
        sel = reprojection_errors(start, K, xy, X) < 20.0
        assert err[sel] @ err[sel] <= want_err[sel] @ want_err[sel] * (1 + 1e-12)
        off = np.linalg.norm(got.center - gt.center)
        assert off <= np.linalg.norm(want.center - gt.center) + 1e-5
        if n >= 40:  # (on 12 matches a quarter of them outliers, both are off)
            assert off < 0.05


def test_least_squares_falls_back_where_gauss_newton_does_not_descend():
    """Starts Gauss-Newton cannot take (the prediction 45 deg and 2 scene units off, points
    crossing the camera's plane): ``_refine`` keeps OpenCV's Levenberg-Marquardt result
    there (8 of 70 such starts), and elsewhere a pose with a smaller squared error than the
    start's."""
    rng = np.random.default_rng(3)
    gt, _, xy, X = noisy_scene(7, 80)
    front = (X @ gt.rotation.T + gt.translation)[:, 2] > 0
    xy, X = xy[front], X[front]
    fallbacks = 0
    for _ in range(100):
        start = Rigid3d(
            rotmat_from_rotvec(rng.normal(0, 0.8, 3)) @ gt.rotation,
            gt.translation + rng.normal(0, 2.0, 3),
        )
        sel = reprojection_errors(start, K, xy, X) < 1000.0
        if sel.sum() < 6:
            continue
        gn = pose.least_squares(start, K, xy[sel], X[sel])
        e0 = reprojection_errors(start, K, xy[sel], X[sel])
        e_gn = reprojection_errors(gn, K, xy[sel], X[sel])
        got, _, err = pose._refine(start, K, xy, X, 1000.0, rounds=1, gauss_newton=True)
        want, want_err = reference_refine_lm(start, K, xy, X, 1000.0)
        if not e_gn @ e_gn < e0 @ e0:
            fallbacks += 1
            np.testing.assert_array_equal(got.rotation, want.rotation)
            np.testing.assert_array_equal(got.translation, want.translation)
            np.testing.assert_array_equal(err, want_err)
        else:
            assert err[sel] @ err[sel] < e0 @ e0
    assert fallbacks == 8


def test_leave_one_out_bound_gives_the_same_answer():
    """With ``loo_sd_over`` the leave-one-out may be an upper bound (the covariance over one
    minus the largest leverage): never below the exact one (the difference is positive
    semidefinite), and over ``loo_sd_over`` exactly when the exact one is (the only question
    the tracker asks of it), on scenes with 6-600 matches, point uncertainties and bunched
    points; the bound is taken where the limit is loose, the exact one where it is tight."""
    took_bound = took_exact = 0
    for n in (6, 30, 150, 600):
        for seed in range(6):
            gt, xy, X, sig = _covariance_case(70, seed, n)
            kw = dict(point_sigma_px=sig, loss_scale=1.0)
            cov, exact = pose.pose_covariances(gt, K, xy, X, **kw)
            if not np.isfinite(exact).all():
                continue
            sd = np.sqrt(np.linalg.eigvalsh(exact[3:, 3:])[-1])
            for over in sd * np.array([0.5, 0.99, 1.01, 1.2, 2.0, 10.0]):
                got_cov, got = pose.pose_covariances(gt, K, xy, X, loo_sd_over=over, **kw)
                np.testing.assert_array_equal(got_cov, cov)
                got_sd = np.sqrt(np.linalg.eigvalsh(got[3:, 3:])[-1])
                assert (got_sd > over) == (sd > over)
                assert np.linalg.eigvalsh(got - exact)[0] >= -1e-9 * np.abs(exact).max()
                if np.array_equal(got, exact):
                    took_exact += 1
                else:
                    took_bound += 1
    assert took_bound > 20 and took_exact > 20


def greedy_leave_out_sd(gt, K, xy, X, k, sig, loss):
    """``certainty.position_sd_without``'s greedy steps at the pose level (map units): ``k``
    times the covariance of the matches left without its most influential one."""
    keep = np.arange(len(xy))
    loo = np.full((6, 6), np.inf)
    for _ in range(k):
        removed: list[int] = []
        _, loo = pose.pose_covariances(
            gt,
            K,
            xy[keep],
            X[keep],
            point_sigma_px=None if sig is None else sig[keep],
            loss_scale=loss,
            removed=removed,
        )
        if not removed:
            return np.inf
        keep = np.delete(keep, removed[0])
    if not np.isfinite(loo).all():
        return np.inf
    return float(np.sqrt(max(np.linalg.eigvalsh(loo[3:, 3:])[-1], 0.0)))


def test_leave_out_bound_is_never_below_the_greedy_steps():
    """Issue 10: ``leave_out_sd_bound`` stands for the k greedy leave-one-out steps where it
    is within a caller's limit: it is never below them (with point uncertainties, the Cauchy
    weights and without, points bunched on a far plane, noise and outliers in the residuals,
    k 1-4), it is finite where the matches constrain the pose well (150+ matches over a range
    of depths), and it is infinite where a step could end infinite (fewer than k + 6
    matches)."""
    finite = 0
    for n in (6, 8, 12, 30, 150, 600):
        for seed in range(6):
            gt, xy, X, sig = _covariance_case(90, seed, n)
            for k in (1, 2, 4):
                for loss in (1.0, 0.0):
                    bound = pose.leave_out_sd_bound(
                        gt, K, xy, X, k, point_sigma_px=sig, loss_scale=loss
                    )
                    exact = greedy_leave_out_sd(gt, K, xy, X, k, sig, loss)
                    if n < k + 6:
                        assert bound == np.inf
                    if np.isfinite(bound):
                        finite += 1
                        assert np.isfinite(exact), (n, seed, k, loss)
                        assert bound >= exact * (1 - 1e-9), (n, seed, k, loss, bound, exact)
                    if n >= 150 and seed % 2 == 0:  # points over the depth range
                        assert np.isfinite(bound), (n, seed, k, loss)
    assert finite > 50


def test_cross_rows_equals_numpy_cross_and_p3p_batch_is_unchanged(monkeypatch):
    """Issue 10: ``p3p_batch``'s row cross products without ``np.cross``'s axis handling: the
    same values bit for bit (random rows with zeros, signed zeros, infinities and NaNs), and
    ``p3p_batch`` with ``np.cross`` in their place gives the very same solutions on 2,000
    random samples."""
    rng = np.random.default_rng(7)
    a, b = rng.normal(0, 10, (500, 3)), rng.normal(0, 10, (500, 3))
    a[:20] = 0.0
    b[10:30] = -0.0
    a[40:45, 1] = np.inf
    b[50:55, 2] = np.nan
    got, want = pose._cross_rows(a, b), np.cross(a, b)
    assert np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(np.signbit(got), np.signbit(want))
    X = rng.uniform(-3, 3, (2000, 3, 3)) + [0.0, 0.0, 6.0]
    uv = rng.uniform(0, 640, (2000, 3, 2))
    new = pose.p3p_batch(X, uv, K)
    monkeypatch.setattr(pose, "_cross_rows", np.cross)
    old = pose.p3p_batch(X, uv, K)
    assert len(new[0]) > 1000
    for n, o in zip(new, old):
        np.testing.assert_array_equal(n, o)


@pytest.mark.parametrize("n", [40, 120, 600])
def test_least_squares_stops_once_a_step_is_under_its_sd(n):
    """``converged_sd``: the least-squares round from a prediction (the tracker's first
    estimate, ~10 of the pose's sd off) stops after the first step shorter than 0.5 sd (at
    0.3 px noise) instead of running on to 1e-8 rad: after 2-3 steps here where the tolerance
    took 4-5 (the same pose, bit for bit, as that many steps), within 1e-3 sd (the centre's,
    from the pose's covariance) of where the further steps went, with the same matches within
    3 px; through ``estimate_pose`` (``RansacParams.converged_sd``) as well."""
    rng = np.random.default_rng(n)
    checked = 0
    for seed in range(8):
        gt, xy, X, start = _scene_and_prediction(200 + seed, n, rng)
        sel = reprojection_errors(start, K, xy, X) < 20.0
        xs, Xs = xy[sel], X[sel]
        full = pose.least_squares(start, K, xs, Xs)
        inl = reprojection_errors(full, K, xy, X) < 3.0
        if inl.sum() < 0.5 * sel.sum():
            continue  # (the start too far for this scene: no tracker would accept it)
        checked += 1
        early = pose.least_squares(start, K, xs, Xs, converged_sd=0.5)
        steps = [pose.least_squares(start, K, xs, Xs, iterations=k, tol=0.0) for k in range(6)]

        def took(p: Rigid3d, steps: list[Rigid3d] = steps) -> int:  # steps that gave p
            return next(k for k, q in enumerate(steps) if np.array_equal(q.rotation, p.rotation))

        assert 2 <= took(early) < took(full)
        cov = pose.pose_covariance(full, K, xy[inl], X[inl])
        sd = np.sqrt(np.linalg.eigvalsh(cov[3:, 3:])[-1])
        assert np.linalg.norm(early.center - full.center) < 1e-3 * sd
        np.testing.assert_array_equal(reprojection_errors(early, K, xy, X) < 3.0, inl)
        got = estimate_pose(
            xy,
            X,
            K,
            RansacParams(loss_scale=1.0, converged_sd=0.5),
            prior=start,
            prior_threshold=20.0,
            final=False,
        )
        ref = estimate_pose(
            xy, X, K, RansacParams(loss_scale=1.0), prior=start, prior_threshold=20.0, final=False
        )
        assert got is not None and ref is not None
        assert np.linalg.norm(got.cam_from_world.center - ref.cam_from_world.center) < 1e-3 * sd
        np.testing.assert_array_equal(got.inlier_mask, ref.inlier_mask)
    assert checked >= 6


def test_row_selection_and_finite_test_equal_numpy():
    """The selections by ``take`` (``_take_rows``) and the finiteness test on Python floats
    (``Rigid3d.is_finite``) against the numpy calls they replace: the same bytes, dtypes and
    shapes; the same answer for a NaN, +inf or -inf in each of a pose's twelve numbers."""

    def numpy_finite(p: Rigid3d) -> bool:
        return bool(np.isfinite(p.rotation).all() and np.isfinite(p.translation).all())

    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 150):
        for mask in (rng.random(n) < 0.7, np.ones(n, bool), np.zeros(n, bool)):
            idx = mask.nonzero()[0]
            for a in (rng.random((n, 2)), rng.random((n, 3)).astype(np.float32), rng.random(n)):
                got, want = pose._take_rows(a, idx), a[mask]
                assert got.dtype == want.dtype and got.shape == want.shape
                assert got.flags.c_contiguous and got.tobytes() == want.tobytes()
                if n:  # integer indices of any shape (RANSAC's (samples, 3) gathers)
                    S = rng.integers(0, n, (5, 3))
                    got, want = pose._take_rows(a, S), a[S]
                    assert got.dtype == want.dtype and got.shape == want.shape
                    assert got.flags.c_contiguous and got.tobytes() == want.tobytes()
    p = Rigid3d(rotmat_from_rotvec(np.array([0.1, -0.2, 0.3])), np.array([1.0, -2.0, 3.0]))
    assert numpy_finite(p) and p.is_finite() is True
    for i in range(12):
        for bad in (np.nan, np.inf, -np.inf):
            R, t = p.rotation.copy(), p.translation.copy()
            if i < 9:
                R.reshape(9)[i] = bad
            else:
                t[i - 9] = bad
            q = Rigid3d(R, t)
            assert numpy_finite(q) is False and q.is_finite() is False


def test_einsum_kernel_equals_numpy_einsum():
    """``np.einsum``'s C kernel called directly (``_c_einsum``, the leverages' row products)
    against ``np.einsum``: the same bytes."""
    rng = np.random.default_rng(4)
    for n in (1, 5, 150, 600):
        A, B = rng.normal(size=(2, n, 6)) * rng.uniform(1e-3, 1e3)
        assert pose._c_einsum("ij,ij->i", A, B).tobytes() == np.einsum("ij,ij->i", A, B).tobytes()
