"""Camera pose from 2D-3D matches (paper Section 3.3): P3P inside RANSAC, then nonlinear
least-squares refinement on the inliers, and a final refinement with a robust (Cauchy) loss
on every match within the refinement threshold (``final_refinement``); rejected under
``min_inliers`` inliers.

Image points here are *undistorted* pixel coordinates (the camera's pinhole part ``K``), so
the geometry is the same for every camera model.

Two estimators, both returning None or a ``PoseEstimate`` with inlier statistics:

- ``estimate_pose``: one 3D point per keypoint (the track table's verified matches). OpenCV's
  RANSAC with P3P minimal solutions, then Levenberg-Marquardt on the inliers.
- ``estimate_pose_one_to_many``: the global-matching case. Hypotheses are generated from the
  ratio-test matches (set 1) and verified against the one-to-many matches (set 2): a keypoint
  counts as an inlier when any of its 3D hypotheses reprojects within the threshold (paper
  Section 2.1). Hypotheses are scored in batches, vectorized.
"""

from __future__ import annotations

import functools
import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from ..transforms import Rigid3d


def _symmetric_eigensolvers() -> tuple[
    Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], Callable[[np.ndarray], np.ndarray]
]:
    """``np.linalg.eigh`` and ``np.linalg.eigvalsh`` of a float64 matrix without their Python
    wrapper: the LAPACK gufuncs (dsyevd) the wrapper calls, called as it calls them on float64
    input, so the same bits. Issue 10: on a frame's 6x6 and 3x3 covariance blocks the wrapper's
    argument checks, type resolution and errstate block cost twice the LAPACK call (eigh 23 ->
    10 us, eigvalsh 11 -> 3.5 us; four calls a tracked frame). Callers pass finite matrices
    (checked before), where the wrapper's error on non-convergence cannot arise.
    ``numpy.linalg._umath_linalg`` is private: where it is missing, the public functions."""
    try:
        gufuncs = importlib.import_module("numpy.linalg._umath_linalg")
        eigh_lo, eigvalsh_lo = gufuncs.eigh_lo, gufuncs.eigvalsh_lo
    except (ImportError, AttributeError):
        return np.linalg.eigh, np.linalg.eigvalsh
    return (
        functools.partial(eigh_lo, signature="d->dd"),
        functools.partial(eigvalsh_lo, signature="d->d"),
    )


eigh_sym, eigvalsh_sym = _symmetric_eigensolvers()


def _einsum_kernel() -> Callable[..., np.ndarray]:
    """``np.einsum`` without its Python layer: the C function it calls itself when not asked
    to optimize (numpy 2's ``einsum``: ``return c_einsum(*operands, **kwargs)``), so the same
    bits. Issue 10: the layer (its dispatcher and keyword checks) was a third of the call on
    the leave-one-out's (n, 6) rows, three calls a tracked frame. Private: where it is
    missing, the public function."""
    try:
        return importlib.import_module("numpy._core._multiarray_umath").c_einsum
    except (ImportError, AttributeError):
        return np.einsum


_c_einsum = _einsum_kernel()


@dataclass(frozen=True)
class RansacParams:
    threshold: float = 4.0  # inlier reprojection error (px) while hypothesizing
    refine_threshold: float = 3.0  # inliers kept for the final refinement (px)
    min_inliers: int = 10  # fewer: no pose
    confidence: float = 0.999
    max_iterations: int = 1000
    # Final refinement on every match within ``refine_threshold`` with a Cauchy loss of this
    # scale (px); 0: plain least squares on them (see ``robust_refine``).
    loss_scale: float = 0.0
    # The least-squares round from a prior (``least_squares``) stops after a step shorter than
    # this many of the pose's own standard deviations (0: only at ``least_squares``' tol).
    converged_sd: float = 0.0


@dataclass
class PoseEstimate:
    cam_from_world: Rigid3d
    inlier_mask: np.ndarray  # over the correspondences given to the estimator
    num_inliers: int
    mean_error_px: float
    # The inlier correspondences of the final refinement (undistorted px, world points): the
    # input of ``pose_covariance``.
    inlier_xy: np.ndarray | None = None
    inlier_X: np.ndarray | None = None
    # Their map point indices when the caller knows them (the covariance then finds each
    # point's uncertainty by index instead of by its coordinates).
    inlier_points: np.ndarray | None = None


# The covariance's parameterization, in this order (the same on every interface):
#   [0:3] rotation: a small rotation vector d applied on the world side of world_from_cam,
#         R_world_from_cam' = exp([d]x) R_world_from_cam (radians, world axes);
#   [3:6] camera centre in world coordinates (map units).
COVARIANCE_ORDER = ("rot_x", "rot_y", "rot_z", "center_x", "center_y", "center_z")
# The pixel noise is estimated from the residuals, never below this (px): with exact matches
# (or a handful of inliers that happen to agree) the residuals alone would claim certainty.
MIN_NOISE_PX = 0.3


def pose_covariance(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    min_noise_px: float = MIN_NOISE_PX,
    point_sigma_px: np.ndarray | None = None,
    loss_scale: float = 0.0,
) -> np.ndarray:
    """``pose_covariances``' plain covariance (without the leave-one-out work)."""
    return pose_covariances(
        cam_from_world, K, xy, X, min_noise_px, point_sigma_px, loss_scale, leave_one_out=False
    )[0]


def pose_covariances(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    min_noise_px: float = MIN_NOISE_PX,
    point_sigma_px: np.ndarray | None = None,
    loss_scale: float = 0.0,
    leave_one_out: bool = True,
    loo_sd_over: float = 0.0,
    removed: list[int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """6x6 covariance of a refined pose (order ``COVARIANCE_ORDER``) from its inlier
    correspondences (undistorted pixels ``xy`` (N,2), world points ``X`` (N,3)): the
    Gauss-Newton normal matrix J^T J of the reprojection residuals, inverted and scaled by the
    residual variance (sum of squared residuals over 2N - 6 degrees of freedom). With
    ``point_sigma_px`` (N,), each correspondence's variance is the residual variance plus that
    term squared (the map point's own error, projected: ``point_uncertainty``), and the normal
    matrix is weighted accordingly. All-infinite when the geometry does not constrain the pose
    (fewer than 4 points, degenerate).

    Returns that covariance and, with ``leave_one_out`` (else the same matrix twice), the
    covariance without the one correspondence whose removal widens the centre's standard
    deviation most (``_without_most_influential``): a pose whose certainty rests on a single
    match cannot check that match (its residual is small whatever the pose: the pose is fitted
    to it), and a wrong one moves the pose unseen. Synthetic room after a 0.8 s gap: 20 right
    matches on a far wall (centre sd 8.6% of the scene scale) and one wrong on a near point:
    sd 0.6% with it, the pose 5.1% off. ``loo_sd_over`` > 0 (map units): a caller that only
    asks whether that covariance's centre sd is over it may get an upper bound instead, when
    the bound is not over it (``_without_most_influential``'s ``sd_over``). ``removed``: the
    index of the correspondence left out is appended to it (when one was)."""
    n = len(xy)
    if n < 4:
        inf = np.full((6, 6), np.inf)
        return inf, inf
    R_cw = cam_from_world.rotation
    fx, fy = K[0, 0], K[1, 1]
    B, rw, r2, var, w = _weighted_terms(
        cam_from_world, K, xy, X, min_noise_px, point_sigma_px, loss_scale
    )
    inverted = _camera_covariance(B, w, float(fx), float(fy), 1e12)
    if inverted is None:
        inf = np.full((6, 6), np.inf)
        return inf, inf
    _, cov, Cu, Cv = inverted
    G = np.zeros((6, 6))
    G[:3, :3] = G[3:, 3:] = -R_cw

    def to_world(C: np.ndarray) -> np.ndarray:
        C = G.T @ C @ G
        return 0.5 * (C + C.T)

    if not leave_one_out:
        cov = to_world(cov)
        return cov, cov
    loo = _without_most_influential(cov, B.T @ Cu, B.T @ Cv, w, loo_sd_over, removed)
    cov_w = to_world(cov)
    if isinstance(loo, float):
        # the bound cov / (1 - h): turned with cov, not turned again (issue 10: the second
        # turn and its finiteness test were ~10% of a tracked frame's covariance)
        return cov_w, cov_w * loo
    return cov_w, (to_world(loo) if np.isfinite(loo).all() else loo)


def _weighted_terms(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    min_noise_px: float,
    point_sigma_px: np.ndarray | None,
    loss_scale: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """``pose_covariances``' per-match quantities: the terms b (9, n), the Cauchy weights
    ``rw`` (ones without a loss), the squared residuals ``r2`` (px^2), the pixel noise variance
    ``var`` and the information weights ``w``.

    The normal matrix comes from the weighted moments of the nine per-match terms b = [1, x,
    y, iz, x^2, xy, x iz, y^2, y iz] (as ``robust_refine``; every Jacobian entry is +-fx or
    +-fy times one of them or a sum of two), in robust_refine's parameters (a rotation w and
    a shift v on the camera side: x_cam = exp(w) (R X + t) + v), then turned into the
    covariance's: with R_wc' = exp([d]x) R_wc and the centre c' = c + e, to first order
    w = -R_cw d and v = -R_cw e, so cov = G' cov_cam G with G = diag(-R_cw, -R_cw)
    (orthogonal: the same eigenvalues, the same centre-block spectrum). Issue 10: the (2N, 6)
    Jacobian written out per entry cost x2 the CPU (the same matrix to rounding,
    ``tests/test_pose_kernels.py``)."""
    n = len(xy)
    pc = np.asarray(X, np.float64) @ cam_from_world.rotation.T + cam_from_world.translation
    fx, fy = K[0, 0], K[1, 1]
    B = np.empty((9, n))
    B[0] = 1.0
    np.divide(1.0, np.maximum(pc[:, 2], 1e-9), out=B[3])  # iz
    np.multiply(pc[:, :2].T, B[3], out=B[1:3])  # x, y
    np.multiply(B[1:4], B[1], out=B[4:7])  # x^2, xy, x iz
    np.multiply(B[2:4], B[2], out=B[7:9])  # y^2, y iz
    du = fx * B[1] + K[0, 2] - xy[:, 0]
    dv = fy * B[2] + K[1, 2] - xy[:, 1]
    r2 = du * du + dv * dv
    if loss_scale > 0:
        # The robust refinement's Cauchy weights: the noise is what its weighted residuals say,
        # not inflated by the near-outliers (2-3 px) it down-weights.
        rw = 1.0 / (1.0 + r2 / loss_scale**2)
    else:
        rw = np.ones(n)
    # (np.add.reduce: the sums .sum() and np.sum take, without their Python layers)
    dof = max(2 * float(np.add.reduce(rw)) - 6, 1.0)
    var = max(float(np.add.reduce(rw * r2)) / dof, min_noise_px**2)
    if point_sigma_px is None:
        w = rw / var
    else:
        w = rw / (var + np.asarray(point_sigma_px, np.float64) ** 2)
    return B, rw, r2, var, w


def _camera_covariance(
    B: np.ndarray, w: np.ndarray, fx: float, fy: float, max_cond: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The pose covariance in ``robust_refine``'s camera-side parameters from the per-match
    terms ``B`` and weights ``w`` (``_weighted_terms``): the normal matrix's eigenvalues
    (ascending), its inverse, and the Jacobian maps ``Cu``, ``Cv`` (``_cov_map``); None where
    the normal matrix is not finite or its condition number is over ``max_cond``."""
    QH, Cu, Cv = _cov_map(fx, fy)
    Bs = B * np.sqrt(w)
    H = ((Bs @ Bs.T).reshape(81) @ QH).reshape(6, 6)
    if not np.isfinite(H).all():  # (the array's own .all(): np.all's dispatch costs 3 us)
        return None
    # H is symmetric: one eigendecomposition gives its condition number and its inverse
    # (np.linalg.cond's SVD and np.linalg.inv cost twice as much)
    ev, V = eigh_sym(H)
    if not ev[0] > 0 or ev[-1] > max_cond * ev[0]:
        return None
    cov = (V / ev) @ V.T
    return ev, 0.5 * (cov + cov.T), Cu, Cv


def leave_out_sd_bound(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    k: int,
    min_noise_px: float = MIN_NOISE_PX,
    point_sigma_px: np.ndarray | None = None,
    loss_scale: float = 0.0,
) -> float:
    """An upper bound of the centre sd (map units, worst direction) that ``k`` greedy
    leave-one-out steps reach (``certainty.position_sd_without``: ``pose_covariances`` on
    the matches left, its most influential one removed, ``k`` times), valid for any ``k``
    matches removed; inf where it cannot be bounded so, including wherever those steps might
    end at an infinite covariance (too few matches, a match the pose cannot do without).

    Issue 10: the greedy steps were ~6% of a relocalization's CPU, to answer whether the sd
    without them exceeds ``relocalize_leave_out_sd``; where this bound is within it, so is
    the exact value (the same decision). Why it bounds, with H the information of all ``n``
    matches, h_i = max eig(w_i J_i H^-1 J_i^T) each match's leverage (w_i J_i^T J_i <= h_i H)
    and var the noise variance they give: a step's set T (at most k - 1 removed) re-estimates
    the variance from its own residuals, between var_lo (the k - 1 largest weighted squared
    residuals gone, the same degrees of freedom) and var_hi (all residuals, k - 1 matches'
    degrees of freedom gone: each Cauchy weight is at most 1); a weight rw / (var_T + s^2)
    is then at least var / var_hi and at most var / var_lo times its weight at var. So the
    information of any set without k matches is at least shrink H, shrink = var / var_hi x
    (1 - the k largest h_i summed), its covariance at most H^-1 / shrink, and a match's
    leverage in a step at most (var / var_lo) h_i / shrink: under 0.999, no step meets a
    singular downdate, and the condition number stays far under ``pose_covariances``' 1e12.
    """
    n = len(xy)
    if k < 1 or n < k + 6:
        return float("inf")
    B, rw, r2, var, w = _weighted_terms(
        cam_from_world, K, xy, X, min_noise_px, point_sigma_px, loss_scale
    )
    inverted = _camera_covariance(B, w, float(K[0, 0]), float(K[1, 1]), 1e10)
    if inverted is None:
        return float("inf")
    ev, cov, Cu, Cv = inverted
    _, _, l00, l11, l01 = _leverage_rows(cov, B.T @ Cu, B.T @ Cv)
    h = _leverages(w, l00, l11, l01)
    top = np.sort(h)[-k:]
    s_rw, rr = float(rw.sum()), rw * r2
    s_rr = float(rr.sum())
    var_hi = max(s_rr / max(2 * s_rw - 6 - 2 * (k - 1), 1.0), min_noise_px**2)
    gone = float(np.sort(rr)[len(rr) - (k - 1) :].sum()) if k > 1 else 0.0
    var_lo = max((s_rr - gone) / max(2 * s_rw - 6, 1.0), min_noise_px**2)
    shrink = var / var_hi * (1.0 - float(top.sum()))
    if not shrink > 0:
        return float("inf")
    grow = var / var_lo
    if grow * float(h.max()) / shrink >= 0.999 or ev[-1] / ev[0] * grow / shrink > 1e11:
        return float("inf")
    lam = float(eigvalsh_sym(cov[3:, 3:])[-1])
    return math.sqrt(max(lam, 0.0) / shrink)


@functools.lru_cache(maxsize=8)
def _cov_map(fx: float, fy: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``pose_covariances``' constant maps: from the second moments S (9x9) of the per-match
    terms b to the normal matrix H = Cu' S Cu + Cv' S Cv (81 -> 36, undamped), and ``Cu``,
    ``Cv`` (9, 6): a match's Jacobian rows J_u = b Cu, J_v = b Cv (``_gn_map``'s, without the
    residual rows). Read-only (shared)."""
    Cu, Cv = _jacobian_maps(fx, fy)
    QH = (np.einsum("ia,jb->ijab", Cu, Cu) + np.einsum("ia,jb->ijab", Cv, Cv)).reshape(81, 36)
    for a in (QH, Cu, Cv):
        a.flags.writeable = False
    return QH, Cu, Cv


def _leverage_rows(
    cov: np.ndarray, Ju: np.ndarray, Jv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per correspondence (its Jacobian rows ``Ju``, ``Jv``, (n, 6)): A_i's rows ``Au``,
    ``Av`` (J_i cov) and J_i cov J_i^T's entries ``l00``, ``l11``, ``l01``."""
    Au, Av = Ju @ cov, Jv @ cov  # (n, 6) each: the rows of A_i
    l00 = _c_einsum("ij,ij->i", Au, Ju)  # J_i cov J_i^T
    l11 = _c_einsum("ij,ij->i", Av, Jv)
    l01 = _c_einsum("ij,ij->i", Au, Jv)
    return Au, Av, l00, l11, l01


def _leverages(w: np.ndarray, l00: np.ndarray, l11: np.ndarray, l01: np.ndarray) -> np.ndarray:
    """Each correspondence's leverage: the largest eigenvalue of W_i^1/2 J_i cov J_i^T
    W_i^1/2 (its 2x2 entries from ``_leverage_rows``, weight ``w``), in closed form."""
    half = 0.5 * (l00 + l11)
    return w * (half + np.sqrt(np.maximum(half * half - (l00 * l11 - l01 * l01), 0.0)))


def _without_most_influential(
    cov: np.ndarray,
    Ju: np.ndarray,
    Jv: np.ndarray,
    w: np.ndarray,
    sd_over: float = 0.0,
    removed: list[int] | None = None,
) -> np.ndarray | float:
    """The covariance ``cov`` (of the information sum of the Jacobian rows ``Ju``, ``Jv``
    (n, 6), a correspondence's u and v rows, weighted by its ``w``) without the correspondence
    whose removal widens the camera centre's standard deviation most (its worst direction).
    Each removal is a rank-2 downdate (Woodbury): cov_-i = cov + A_i^T (W_i^-1 - J_i cov
    J_i^T)^-1 A_i, A_i = J_i cov. A correspondence the pose cannot do without (leverage 1: the
    downdated information is singular) gives an all-infinite covariance.

    ``sd_over`` > 0: where the bound cov / (1 - h), h the largest leverage (the largest
    eigenvalue of W_i^1/2 J_i cov J_i^T W_i^1/2 over all i; every downdate is within it:
    H_-i >= (1 - h_i) H), puts the centre's standard deviation at most ``sd_over``, that
    bound instead (the caller only asks whether the exact one is over ``sd_over``: the same
    answer, without the per-match 3x3 algebra), as its factor 1 / (1 - h) (a float: the
    caller scales the covariance it already has)."""
    n = len(Ju)
    if n <= 4:
        return np.full((6, 6), np.inf)
    # Each correspondence's two rows (u, v) as separate (n, 6) blocks: A_i's rows are two
    # GEMMs, and the 2x2 and 3x3 algebra below is written out per entry over all n at once
    # (the batched (n, 2, 6) products, three-operand einsum and n LAPACK 3x3 eigensolves cost
    # x4 the CPU on ~150 matches; the same quantities up to rounding).
    Au, Av, l00, l11, l01 = _leverage_rows(cov, Ju, Jv)
    grow = 0.0  # the bound's factor 1 / (1 - h), where it answers
    if sd_over > 0:
        h = float(_leverages(w, l00, l11, l01).max())
        if h < 1.0 and eigvalsh_sym(cov[3:, 3:])[-1] * (1.0 / (1.0 - h)) <= sd_over * sd_over:
            grow = 1.0 / (1.0 - h)
            # Every leverage under 1 - 1e-4 (the usual case): each downdate's (1 - l1)(1 - l2)
            # exceeds 1e-8, so the positive-definiteness test below passes, and the bound is
            # answered without it (issue 10: ~8 operations over all matches a tracked frame).
            if h < 1.0 - 1e-4:
                return grow
    # S_i = W_i^-1 - J_i cov J_i^T (symmetric: its off-diagonal from one side)
    iw = 1.0 / w
    s00, s11, s01 = iw - l00, iw - l11, -l01
    det = s00 * s11 - s01 * s01
    # W_i^-1 - J_i cov J_i^T is positive definite exactly when the downdate leaves the
    # information positive definite; relative tolerance: leverage within 1e-9 of 1 is 1
    scale = iw * iw
    ok = (det > 1e-9 * scale) & (s00 > 0)
    if not ok.all():
        return np.full((6, 6), np.inf)
    if grow:  # (a leverage within 1e-4 of 1: the bound once every downdate passed)
        return grow
    i00, i11, i01 = s11 / det, s00 / det, -s01 / det  # S_i^-1
    # centre block of cov_-i: cov_c + sum_kl Sinv_kl a_k a_l^T, a_0 / a_1 = A_i's rows' centre
    # parts (the centre block alone decides which removal is worst; in ``robust_refine``'s
    # parameters the shift's block, the centre's turned by R_cw: the same spectrum)
    u, v = Au[:, 3:], Av[:, 3:]
    pu = i00[:, None] * u + i01[:, None] * v
    pv = i01[:, None] * u + i11[:, None] * v
    c = cov[3:, 3:]

    def entry(a: int, b: int) -> np.ndarray:
        return c[a, b] + u[:, a] * pu[:, b] + v[:, a] * pv[:, b]

    worst = int(
        np.argmax(
            _largest_eigenvalues_3x3(
                entry(0, 0), entry(1, 1), entry(2, 2), entry(0, 1), entry(0, 2), entry(1, 2)
            )
        )
    )
    if removed is not None:
        removed.append(worst)
    A = np.stack([Au[worst], Av[worst]])
    Sinv = np.array([[i00[worst], i01[worst]], [i01[worst], i11[worst]]])
    out = cov + A.T @ Sinv @ A
    return 0.5 * (out + out.T)


def _largest_eigenvalues_3x3(
    a00: np.ndarray,
    a11: np.ndarray,
    a22: np.ndarray,
    a01: np.ndarray,
    a02: np.ndarray,
    a12: np.ndarray,
) -> np.ndarray:
    """The largest eigenvalue of each symmetric 3x3 matrix given by its six entries (arrays),
    in closed form (Smith 1961: the eigenvalues of a symmetric 3x3 are q + 2 p cos(phi + 2 pi
    k / 3), q the mean of the diagonal)."""
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0
    p = np.sqrt(p2)
    safe = np.where(p > 0, p, 1.0)
    # det(B) / 2 with B = (A - q I) / p
    det = (
        b00 * (b11 * b22 - a12 * a12)
        - a01 * (a01 * b22 - a12 * a02)
        + a02 * (a01 * a12 - b11 * a02)
    )
    # (np.minimum / np.maximum: np.clip's Python wrapper costs ~10 us per call)
    r = np.minimum(np.maximum(det / (2.0 * safe * safe * safe), -1.0), 1.0)
    return np.where(p > 0, q + 2.0 * p * np.cos(np.arccos(r) / 3.0), q)


def pose_error_vector(est_cam_from_world: Rigid3d, gt_cam_from_world: Rigid3d) -> np.ndarray:
    """The error of an estimate in the covariance's parameterization (``COVARIANCE_ORDER``):
    rotation vector of R_wc_est R_wc_gt^T (world axes, rad) and centre difference."""
    R = est_cam_from_world.rotation.T @ gt_cam_from_world.rotation
    rot = cv2.Rodrigues(R)[0].reshape(3)
    return np.concatenate([rot, est_cam_from_world.center - gt_cam_from_world.center])


def project(cam_from_world: Rigid3d, K: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted pixel projections (N, 2) and depths (N,)."""
    pc = X @ cam_from_world.rotation.T + cam_from_world.translation
    z = pc[:, 2]
    zs = np.where(z > 1e-9, z, 1e-9)
    u = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    return np.stack([u, v], axis=1), z


def reprojection_errors(
    cam_from_world: Rigid3d, K: np.ndarray, xy: np.ndarray, X: np.ndarray
) -> np.ndarray:
    """Pixel errors; points behind the camera get infinity."""
    # ``project`` and a row norm, written out: the same operations in the same order (the
    # norm of a row of two is sqrt(du * du + dv * dv)), bit-identical, without the stacked
    # (N, 2) temporaries (called ~14 times per frame; x0.5 CPU).
    pc = X @ cam_from_world.rotation.T + cam_from_world.translation
    z = pc[:, 2]
    # (np.fmax: z where z > 1e-9, else 1e-9, NaN included: np.where's values, without its mask)
    zs = np.fmax(z, 1e-9)
    du = K[0, 0] * pc[:, 0] / zs + K[0, 2] - xy[:, 0]
    dv = K[1, 1] * pc[:, 1] / zs + K[1, 2] - xy[:, 1]
    err = np.sqrt(du * du + dv * dv)
    err[z <= 1e-6] = np.inf
    return err


def _rigid(rvec: np.ndarray, tvec: np.ndarray) -> Rigid3d:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return Rigid3d(R, np.asarray(tvec, dtype=np.float64).reshape(3))


def refine(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    threshold: float,
    rounds: int = 2,
) -> tuple[Rigid3d, np.ndarray]:
    """Levenberg-Marquardt on the inliers (reprojection error < threshold), re-selecting
    inliers after each round. Returns the pose and the final inlier mask."""
    pose, mask, _ = _refine(cam_from_world, K, xy, X, threshold, rounds)
    return pose, mask


def _refine(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    threshold: float,
    rounds: int = 2,
    gauss_newton: bool = False,
    converged_sd: float = 0.0,
) -> tuple[Rigid3d, np.ndarray, np.ndarray]:
    """``refine``, and the reprojection errors of every match at the returned pose (callers
    select other inlier sets from them instead of projecting again). ``gauss_newton``: each
    round by ``least_squares`` (falling back to OpenCV's Levenberg-Marquardt where it does
    not lower the squared error) instead, stopped as ``least_squares``' ``converged_sd``
    says."""
    pose = cam_from_world
    err = reprojection_errors(pose, K, xy, X)
    mask = err < threshold
    for _ in range(rounds):
        n_in = np.count_nonzero(mask)
        if n_in < 4:
            break
        if gauss_newton:
            # every match within the threshold (the tracker's first estimate, usually): the
            # matches and errors as they are, not four fancy-indexed copies
            every = n_in == len(mask)
            idx = None if every else mask.nonzero()[0]
            xs, Xs = (xy, X) if idx is None else (_take_rows(xy, idx), _take_rows(X, idx))
            gn = least_squares(pose, K, xs, Xs, converged_sd=converged_sd)
            gn_err = reprojection_errors(gn, K, xy, X)
            e0, e1 = (err, gn_err) if idx is None else (err.take(idx), gn_err.take(idx))
            if float(e1 @ e1) < float(e0 @ e0):
                pose, err = gn, gn_err
                new_mask = err < threshold
                if (new_mask == mask).all():  # (the same shape: np.array_equal's checks cost 1 us)
                    break
                mask = new_mask
                continue
        rvec, _ = cv2.Rodrigues(pose.rotation)
        idx = mask.nonzero()[0]
        rvec, tvec = cv2.solvePnPRefineLM(
            # (float64 copies: of the taken rows, not copied again when already float64)
            _take_rows(X, idx).astype(np.float64, copy=False),
            _take_rows(xy, idx).astype(np.float64, copy=False),
            K,
            None,
            rvec,
            pose.translation.reshape(3, 1).copy(),
        )
        pose = _rigid(rvec, tvec)
        err = reprojection_errors(pose, K, xy, X)
        new_mask = err < threshold
        if (new_mask == mask).all():
            break
        mask = new_mask
    return pose, mask, err


_EYE6 = np.eye(6)
_EYE6.flags.writeable = False


def least_squares(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    iterations: int = 5,
    tol: float = 1e-8,
    converged_sd: float = 0.0,
) -> Rigid3d:
    """Gauss-Newton on the squared reprojection error (``robust_refine``'s steps without the
    loss), stopped once a step moves the rotation and the translation by less than ``tol``
    (radians; relative to the translation's length), or, with ``converged_sd`` > 0, once a
    step is shorter than that many of the pose's standard deviations (``_gauss_newton``):
    the minimum OpenCV's
    ``solvePnPRefineLM`` reaches (within 1e-5, its own stopping tolerance, and lower, on
    synthetic scenes started 3-17 px off, ``tests/test_pose_kernels.py``) at ~x0.5 its CPU on ~120
    matches (issue 10: its setup dominates whatever its iteration cap). No damping beyond
    ``robust_refine``'s 1e-9: a caller checks that the squared error went down
    (``_refine``)."""
    return _gauss_newton(cam_from_world, K, xy, X, 0.0, iterations, tol, converged_sd)


# Measured for issue 10 and left as they are (redkitchen, map every 10th frame): a tracked frame
# runs no RANSAC (the prediction's refinement explains 80% of the matches: 25 solvePnPRansac
# calls in 600 frames); cv2.solvePnPRefineLM costs ~140 us per call whatever its iteration
# cap (2, 3, 5, 10 or 20: the same CPU; its setup dominates), and a numpy Gauss-Newton to the
# same minimum costs as much; the robust refinements are not converged when they stop (steps
# of the third iteration median 0.05 px, p90 0.2 px, in the first estimate's; 0.02 / 0.09 px
# in the second's), so fewer iterations would move the poses, not only save time.


def robust_refine(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    scale: float,
    iterations: int = 3,
) -> Rigid3d:
    """Gauss-Newton on the reprojection error with a Cauchy loss of ``scale`` pixels
    (iteratively reweighted): a match ``scale`` off counts half, one 3 ``scale`` off a tenth.
    The pose is perturbed on the left: ``x_cam = exp(w) (R X + t) + v``.

    Each step is a dozen array operations (issue 10: on the ~120 matches of a redkitchen
    refinement a step's cost is numpy's per-call overhead, not arithmetic). With x, y the
    normalized coordinates and iz the inverse depth, every Jacobian entry is a constant (+-fx,
    +-fy) times one of the per-match terms b = [1, x, y, iz, x^2, xy, x iz, y^2, y iz] or a sum
    of two (fx (1 + x^2), -fy (1 + y^2)). So the normal equations H = J' W J, g = J' W r are
    linear in the weighted second moments of the rows [b; r_u; r_v]: one symmetric product of
    those (11, n) rows scaled by sqrt(w), then one product with the constant map of
    ``_gn_map`` gives H (damped) and g. The same steps as the Jacobian written out per match
    up to rounding (poses within 1e-12 relative, ``tests/test_pose_kernels.py``).
    """
    return _gauss_newton(cam_from_world, K, xy, X, scale, iterations)


def _gauss_newton(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    scale: float,
    iterations: int,
    tol: float = 0.0,
    converged_sd: float = 0.0,
) -> Rigid3d:
    """``robust_refine``'s steps; ``scale`` 0: without the loss (``least_squares``). ``tol``
    > 0: stop after a step below it (radians, and relative to the translation's length).
    ``converged_sd`` > 0: stop after a step whose Mahalanobis length is below it, in the
    standard deviations of a pose whose pixel noise is ``MIN_NOISE_PX`` (the least any
    covariance here claims, so at least as strict as the pose's own: outliers inflate a
    least-squares residual's variance): delta' H delta, with H delta = g, is delta' g.
    Issue 10: the tracker's first estimate (from the motion prediction, ~10 sd off) took
    3.9 steps a frame to reach ``tol`` on redkitchen (1000 frames); in its own residuals'
    sd its second step was a median 0.08 (p90 0.27, at most 1.0) and its third 3.5e-5 (at
    most 1.5e-3): Gauss-Newton on a least-squares pose converges about quadratically, and a
    step under 0.5 sd leaves it ~1e-4 sd from where the further steps would take it."""
    n = len(xy)
    if n < 4:
        return cam_from_world
    P = np.empty((3, 4))  # [R | t]
    P[:, :3] = cam_from_world.rotation
    P[:, 3] = cam_from_world.translation
    Xh = np.empty((4, n))
    Xh[:3] = X.T
    Xh[3] = 1.0
    f = K.diagonal()[:2, None]  # (fx, fy)
    obs = xy.T - K[:2, 2:3]  # the observations relative to the principal point
    A = np.empty((11, n))  # rows: b (9), then the residuals u, v
    A[0] = 1.0
    r = A[9:]
    As = np.empty((11, n))
    r2 = np.empty((2, n))
    w = np.empty(n)
    s2 = scale * scale
    Q = _gn_map(float(K[0, 0]), float(K[1, 1]))
    for _ in range(iterations):
        pc = P @ Xh
        if np.minimum.reduce(pc[2]) <= 1e-9:  # (ndarray.min's Python layer: 0.3 us)
            break
        np.divide(1.0, pc[2], out=A[3])  # iz
        np.multiply(pc[:2], A[3], out=A[1:3])  # x, y
        np.multiply(A[1:4], A[1], out=A[4:7])  # x^2, xy, x iz
        np.multiply(A[2:4], A[2], out=A[7:9])  # y^2, y iz
        np.multiply(f, A[1:3], out=r)
        r -= obs
        if s2 > 0:
            # square roots of the Cauchy weights s^2 / (s^2 + |r|^2), applied to both sides
            np.multiply(r, r, out=r2)
            np.add(r2[0], r2[1], out=w)
            w += s2
            np.divide(s2, w, out=w)
            np.sqrt(w, out=w)
            np.multiply(A, w, out=As)
        else:
            As = A
        Hg = (As @ As.T).reshape(121) @ Q  # H (6x6, damped) and g
        ok, delta = cv2.solve(
            Hg[:36].reshape(6, 6), Hg[36:].reshape(6, 1), flags=cv2.DECOMP_CHOLESKY
        )
        if not ok:
            break
        dR, _ = cv2.Rodrigues(-delta[:3])
        P = dR @ P
        P[:, 3] -= delta[3:, 0]
        if converged_sd > 0 and float(Hg[36:] @ delta[:, 0]) < converged_sd**2 * MIN_NOISE_PX**2:
            break  # (delta' g = delta' H delta)
        if tol > 0 and np.abs(delta[:3]).max() < tol:
            if np.abs(delta[3:]).max() < tol * max(float(np.linalg.norm(P[:, 3])), 1e-12):
                break
    if not np.isfinite(P).all():  # (P holds the pose: one test, not Rigid3d.is_finite's two)
        return cam_from_world
    return Rigid3d(P[:, :3].copy(), P[:, 3].copy())


def _jacobian_maps(fx: float, fy: float) -> tuple[np.ndarray, np.ndarray]:
    """(9, 6) each: a match's Jacobian rows J_u = b Cu, J_v = b Cv in ``robust_refine``'s
    parameters, b = [1, x, y, iz, x^2, xy, x iz, y^2, y iz]."""
    Cu, Cv = np.zeros((9, 6)), np.zeros((9, 6))
    # J_u = fx (-xy, 1 + x^2, -y, iz, 0, -x iz)
    Cu[[5, 0, 4, 2, 3, 6], [0, 1, 1, 2, 3, 5]] = [-fx, fx, fx, -fx, fx, -fx]
    # J_v = fy (-(1 + y^2), xy, x, 0, iz, -y iz)
    Cv[[0, 7, 5, 1, 3, 8], [0, 0, 1, 2, 4, 5]] = [-fy, -fy, fy, fy, fy, -fy]
    return Cu, Cv


@functools.lru_cache(maxsize=8)
def _gn_map(fx: float, fy: float) -> np.ndarray:
    """``robust_refine``'s constant (121, 42) map from the second moments S (11x11) of the rows
    [b; r_u; r_v], b = [1, x, y, iz, x^2, xy, x iz, y^2, y iz], to the damped normal matrix
    H + 1e-9 trace(H) I (36 entries) and the gradient g (6): with J_u = b Cu, J_v = b Cv,
    H = Cu' S Cu + Cv' S Cv and g = Cu' S e_u + Cv' S e_v, each entry linear in S. Read-only
    (shared)."""
    Cu, Cv = np.zeros((11, 6)), np.zeros((11, 6))
    Cu[:9], Cv[:9] = _jacobian_maps(fx, fy)
    QH = np.einsum("ia,jb->ijab", Cu, Cu) + np.einsum("ia,jb->ijab", Cv, Cv)
    QH += 1e-9 * np.einsum("ijaa->ij", QH)[:, :, None, None] * np.eye(6)
    Qg = np.zeros((11, 11, 6))
    Qg[:, 9], Qg[:, 10] = Cu, Cv
    Q = np.concatenate([QH.reshape(121, 36), Qg.reshape(121, 6)], axis=1)
    Q.flags.writeable = False
    return Q


def estimate_pose(
    xy: np.ndarray,
    X: np.ndarray,
    K: np.ndarray,
    params: RansacParams = RansacParams(),
    *,
    prior: Rigid3d | None = None,
    prior_tie: float = 0.9,
    prior_accept: float = 0.8,
    prior_threshold: float | None = None,
    prior_is_estimate: bool = False,
    final: bool = True,
) -> PoseEstimate | None:
    """Pose from one-to-one matches (undistorted pixels ``xy`` (N,2), world points ``X`` (N,3)).

    With a ``prior`` (the motion filter's prediction), LM refinement started from the prior is
    a second hypothesis beside RANSAC's: when the matches lie on one distant plane the pose has
    a two-fold (mirror) ambiguity that no minimal solver resolves, and both solutions explain
    the points almost equally well. The prior's solution wins unless RANSAC's has clearly more
    inliers (``prior_tie``: the prior's count must reach that fraction of RANSAC's). When the
    prior's solution already explains ``prior_accept`` of all matches, RANSAC is skipped: the
    common tracking case, where matches were verified against the previous pose.

    ``prior_is_estimate``: the prior is already this frame's pose and every match was verified
    against it (the tracker's second estimate, after guided matching): it is refined alone,
    without RANSAC (None under ``min_inliers``), which could only propose a pose its own
    matches contradict.

    ``final`` False: the estimate before the robust final refinement (``final_refinement``),
    for a caller that refines it robustly itself afterwards (the tracker's first estimate:
    its second one, on the matches guided matching and the re-verification added, starts
    from it).
    """
    threshold, refine_threshold, min_inliers = (
        params.threshold,
        params.refine_threshold,
        params.min_inliers,
    )
    n = len(xy)
    if n < max(4, min_inliers):
        return None
    from_prior = None
    # (the prior's finiteness tested once)
    finite_prior = prior is not None and prior.is_finite()
    if prior_is_estimate and not finite_prior:
        return None
    if prior is not None and finite_prior:
        # Select inliers with the looser RANSAC threshold first: the prior is a prediction. A
        # prediction can be farther off than that (15-30 px at 3 Hz): then a first round within
        # ``prior_threshold`` px. Without it, a walk at 3 Hz lost the prior's hypothesis and took
        # RANSAC's mirror pose, 2.5 m off, from 62 correct matches (worst pose there 2.5 -> 0.6 m;
        # redkitchen, 250 frames: worst 7.9 -> 2.5 cm, median unchanged).
        pose = prior
        loose = prior_threshold is not None and prior_threshold > threshold
        if prior_is_estimate and loose and params.loss_scale > 0:
            return _refine_own_estimate(prior, K, xy, X, params, prior_threshold)
        err = None  # the errors of every match at ``pose`` once known (not projected twice)
        if loose and prior_threshold is not None:  # (`loose` implies it; mypy needs it said)
            pose, _, err = _refine(
                pose,
                K,
                xy,
                X,
                prior_threshold,
                rounds=1,
                gauss_newton=True,
                converged_sd=params.converged_sd,
            )
        if params.loss_scale > 0 and loose:
            # The robust final refinement follows: a least-squares round at the tighter
            # thresholds first only changes where it starts, and for the worse (redkitchen,
            # 1000 frames, the same 2004 calls: the second estimate of a frame median 0.481 ->
            # 0.473 cm, mean 0.841 -> 0.835 cm, CPU x0.49 with its RANSAC gone; the first
            # 0.541 -> 0.538 cm, mean 0.930 -> 0.932 cm, CPU x0.85).
            if err is None:
                err = reprojection_errors(pose, K, xy, X)
            mask = err < refine_threshold
        elif params.loss_scale > 0:
            pose, _, err = _refine(pose, K, xy, X, threshold, rounds=1)
            mask = err < refine_threshold
        else:
            pose, _ = refine(pose, K, xy, X, threshold, rounds=1)
            pose, mask, err = _refine(pose, K, xy, X, refine_threshold)
        from_prior = _finish(pose, mask, K, xy, X, min_inliers, err)
        accepted = from_prior is not None and from_prior.num_inliers >= prior_accept * n
        if accepted or prior_is_estimate:
            return final_refinement(from_prior, K, xy, X, params) if final else from_prior
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X.astype(np.float64),
        xy.astype(np.float64),
        K,
        None,
        iterationsCount=params.max_iterations,
        reprojectionError=threshold,
        confidence=params.confidence,
        flags=cv2.SOLVEPNP_AP3P,
    )
    ransac = None
    if ok and inl is not None and len(inl) >= min_inliers:
        pose, mask, err = _refine(_rigid(rvec, tvec), K, xy, X, refine_threshold)
        ransac = _finish(pose, mask, K, xy, X, min_inliers, err)
    if ransac is None or from_prior is None:
        best = ransac if ransac is not None else from_prior
    else:
        best = from_prior if from_prior.num_inliers >= prior_tie * ransac.num_inliers else ransac
    return final_refinement(best, K, xy, X, params) if final else best


def _refine_own_estimate(
    pose: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    params: RansacParams,
    prior_threshold: float | None,
) -> PoseEstimate | None:
    """The robust refinement alone of the frame's own pose on every match within
    ``prior_threshold`` (the tracker's second estimate: each match was verified against the
    pose, which was itself refined robustly; a least-squares round first, pulled by the
    near-outliers the Cauchy loss then down-weights, only moved where it started)."""
    err = reprojection_errors(pose, K, xy, X)
    sel = err < (prior_threshold if prior_threshold is not None else params.threshold)
    n_sel = np.count_nonzero(sel)
    if n_sel < max(4, params.min_inliers):
        return None
    # (every match verified within the guided threshold of this pose is within it: on a
    # tracked frame all are, and the matches go in as they are, not copied)
    if n_sel < len(sel):
        idx = sel.nonzero()[0]
        xy_sel, X_sel = _take_rows(xy, idx), _take_rows(X, idx)
    else:
        xy_sel, X_sel = xy, X
    pose = robust_refine(pose, K, xy_sel, X_sel, params.loss_scale)
    err = reprojection_errors(pose, K, xy, X)
    return _finish(pose, err < params.refine_threshold, K, xy, X, params.min_inliers, err)


def final_refinement(
    est: PoseEstimate | None, K: np.ndarray, xy: np.ndarray, X: np.ndarray, params: RansacParams
) -> PoseEstimate | None:
    """The estimate refined once more on its inliers with the robust loss (``params.loss_scale``;
    nothing to do when 0); the inliers are then every match within ``refine_threshold``. The
    returned ``inlier_mask`` is the set the final refinement used."""
    if est is None or params.loss_scale <= 0:
        return est
    sel = est.inlier_mask
    idx = sel.nonzero()[0]
    pose = robust_refine(
        est.cam_from_world, K, _take_rows(xy, idx), _take_rows(X, idx), params.loss_scale
    )
    err = reprojection_errors(pose, K, xy, X)
    mask = err < params.refine_threshold
    if np.count_nonzero(mask) < params.min_inliers:
        return est
    out = _finish(pose, mask, K, xy, X, params.min_inliers, err)
    return out if out is not None else est


def _finish(
    pose: Rigid3d, mask: np.ndarray, K, xy, X, min_inliers: int, err: np.ndarray | None = None
) -> PoseEstimate | None:
    """The estimate of ``pose`` on the matches in ``mask``; ``err``: every match's error at
    ``pose`` when already computed."""
    n_in = int(np.count_nonzero(mask))  # (a Python int: num_inliers goes into JSON)
    if n_in < min_inliers or not pose.is_finite():
        return None
    idx = mask.nonzero()[0]  # (the rows once, for the three ``_take_rows``)
    xy_in, X_in = _take_rows(xy, idx), _take_rows(X, idx)
    err = reprojection_errors(pose, K, xy_in, X_in) if err is None else err.take(idx)
    # (the mean as np.mean takes it, np.add.reduce over n_in, without its Python layer: 2 us)
    mean = float(np.add.reduce(err)) / n_in if n_in else float("inf")
    return PoseEstimate(pose, mask, n_in, mean, xy_in, X_in)


def _take_rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[idx]`` for integer indices ``idx`` of any shape (``a[mask]`` for ``idx =
    mask.nonzero()[0]``): the same rows, copied, C-ordered. Issue 10: on the (n, 2) and (n, 3)
    match arrays numpy's boolean and integer indexing cost x3-9 ``take``'s (n 100-400:
    3.7-10.1 us for the three of ``_finish``, 1.2-2.0 us taken), five to eight such
    selections a tracked frame, a few hundred in a relocalization's RANSAC."""
    return a.take(idx, 0)


def estimate_pose_one_to_many(
    hyp_xy: np.ndarray,
    hyp_X: np.ndarray,
    ver_kp: np.ndarray,
    ver_xy: np.ndarray,
    ver_X: np.ndarray,
    K: np.ndarray,
    params: RansacParams = RansacParams(),
    *,
    batch: int = 16,
    seed: int = 0,
    growth: int = 200,
    lo_per_batch: int = 2,
    pool_stop: bool = False,
    presolve: bool = False,
    stats: dict[str, int] | None = None,
) -> tuple[PoseEstimate, np.ndarray] | None:
    """RANSAC over set 1 (``hyp_xy``, ``hyp_X``: one match per keypoint, best first) verified
    on set 2 (``ver_kp``: keypoint id of each one-to-many pair, ``ver_xy``, ``ver_X``).

    Sampling is progressive (PROSAC-like): minimal samples come from the best-ranked matches
    first, the pool growing to all of set 1 over ``growth`` iterations; the ``lo_per_batch``
    best hypotheses of each batch are locally optimized (refined on their inliers) before
    scoring; the adaptive stop uses the best pose's inlier ratio over all of set 1.

    ``pool_stop``: also stop once an all-inlier sample of the best pose would have been drawn,
    at ``confidence``, from the pools actually sampled (PROSAC's stopping rule): each
    iteration missed with probability ``1 - w^3``, ``w`` the best pose's inlier ratio within
    that iteration's pool, not within all of set 1. Set 1 is ranked by distinctiveness, so
    the pools are richer in inliers than the whole set: on redkitchen the best pose was found
    within 32 iterations in nearly every relocalization, and the whole-set rule still ran to
    250-1000 of them. ``stats`` (a dict), when given, receives the ``iterations`` run.

    ``presolve``: draw the samples of all ``max_iterations`` at once and solve them with the
    vectorized ``p3p_batch`` instead of one OpenCV call each (~20 us a call, most of an
    iteration): for a run expected to use its whole budget (the second-place test's), where
    the samples an early stop leaves unused cost less than the calls saved. The same samples;
    the solutions equal OpenCV's within 1e-8. Neither kernel hands a non-finite pose to the
    scoring (``p3p_opencv``, ``p3p_batch``).

    Returns the pose and, per set-2 pair, whether it is the inlier chosen for its keypoint
    (at most one per keypoint: the closest reprojection)."""
    threshold, refine_threshold, min_inliers = (
        params.threshold,
        params.refine_threshold,
        params.min_inliers,
    )
    confidence, max_iterations = params.confidence, params.max_iterations
    n1 = len(hyp_xy)
    if n1 < 3 or len(ver_kp) < min_inliers:
        return None
    rng = np.random.default_rng(seed)
    _, kp_dense = np.unique(ver_kp, return_inverse=True)
    obj = hyp_X.astype(np.float64)
    img = hyp_xy.astype(np.float64)
    # Scoring as one GEMM per batch: with P = [R | t] and Xh = [X, 1], a pair's pixel error
    # times its depth is linear in P: z (u - x) = (fx p1 + (cx - x) p3) . Xh, likewise for v,
    # and z = p3 . Xh; so the rows kron((fx, 0, cx - x), Xh), kron((0, fy, cy - y), Xh) and
    # kron((0, 0, 1), Xh) against the stacked vec(P) give all three for every hypothesis at
    # once, without dividing (the same inliers: |error| < threshold with z > 0).
    # The rows in keypoint order (``by_kp``), so that a keypoint's pairs are consecutive and
    # "any inlier hypothesis" is a difference of cumulative sums at each keypoint's last row.
    by_kp = np.argsort(kp_dense, kind="stable")
    kp_last = np.flatnonzero(np.r_[np.diff(kp_dense[by_kp]) != 0, True])
    Xh = np.hstack([_take_rows(ver_X, by_kp).astype(np.float64), np.ones((len(ver_X), 1))])
    sxy = _take_rows(ver_xy, by_kp)
    zero, one = np.zeros(len(Xh)), np.ones(len(Xh))
    rows_u = np.stack([np.full(len(Xh), K[0, 0]), zero, K[0, 2] - sxy[:, 0]], 1)
    rows_v = np.stack([zero, np.full(len(Xh), K[1, 1]), K[1, 2] - sxy[:, 1]], 1)
    rows_z = np.stack([zero, zero, one], 1)
    F = np.concatenate(
        [(r[:, :, None] * Xh[:, None, :]).reshape(-1, 12) for r in (rows_u, rows_v, rows_z)]
    )
    n_ver = len(Xh)
    best_score, best_pose = 0, None
    needed = max_iterations
    thr2 = threshold * threshold
    it = 0
    pools: list[tuple[int, int]] = []  # (pool size, iterations drawn from it) per batch
    in_best = np.zeros(n1, np.int64)  # the best pose's set-1 inliers, counted by rank
    # The pool stop's log miss probability, summed over ``pools[:miss_n]`` in order (the same
    # additions as summing them all at each check: bit-identical, without the quadratic cost
    # over up to 63 batches); reset when the best pose changes.
    miss_log, miss_n = 0.0, 0
    log_fail = math.log(1.0 - confidence)

    def pool_size(drawn: int) -> int:
        # the best-ranked matches a batch samples from, after ``drawn`` iterations
        return min(n1, max(8, n1 // 5) + (n1 * drawn) // growth)

    pre = None
    if presolve:
        # Every batch's samples drawn up front (the same draws from the same stream: a batch's
        # pool depends on its index only) and solved in one vectorized call.
        n_b = -(-max_iterations // batch)
        S_all = np.concatenate(
            [_minimal_samples(rng, pool_size(b * batch), batch) for b in range(n_b)]
        )
        R_all, T_all, s_all = p3p_batch(_take_rows(obj, S_all), _take_rows(img, S_all), K)
        pre = (R_all, T_all, np.searchsorted(s_all, np.arange(n_b + 1) * batch))
    n_batch = 0
    while it < min(needed, max_iterations):
        if pool_stop and best_pose is not None and pools:
            miss_log, miss_n = _pool_miss_log(pools, in_best, miss_log, miss_n)
            if miss_log < log_fail:
                break
        pool = pool_size(it)
        pools.append((pool, batch))
        if pre is not None:
            lo, hi = pre[2][n_batch], pre[2][n_batch + 1]
            n_batch += 1
            it += batch
            if hi == lo:
                continue
            R, T = pre[0][lo:hi], pre[1][lo:hi]
            B = len(R)
        else:
            S = _minimal_samples(rng, pool, batch)
            it += len(S)
            # The batch's sample points gathered at once: a view per sample instead of two
            # fancy indexings (the same contiguous (3, 3) and (3, 2) arrays for the solver).
            R, T = p3p_opencv(_take_rows(obj, S), _take_rows(img, S), K)
            B = len(R)
            if B == 0:
                continue
        # One GEMM for all hypotheses: (3M, 12) @ (12, B) -> z*du, z*dv, z, each (M, B)
        P = np.concatenate([R, T[:, :, None]], 2).reshape(B, 12)
        E = F @ P.T
        E2 = E * E  # the three squares in one pass (the same products as squaring each)
        z = E[2 * n_ver :]
        inl = (E2[:n_ver] + E2[n_ver : 2 * n_ver] < thr2 * E2[2 * n_ver :]) & (z > 1e-6)  # (M, B)
        # distinct keypoints with at least one inlier hypothesis
        per_kp = np.cumsum(inl, axis=0, dtype=np.int32)[kp_last]  # (keypoints, B)
        per_kp[1:] -= per_kp[:-1].copy()
        scores = (per_kp > 0).sum(axis=0)
        # Local optimization (LO-RANSAC): a minimal solution from correct matches is itself off
        # by centimetres and a degree or two, so its raw support can lose to a wrong pose built
        # on repeated structure; the batch's strongest hypotheses are refined on their inliers
        # and scored again.
        for b in np.argsort(-scores, kind="stable")[:lo_per_batch]:
            if scores[b] < max(0.5 * best_score, 0.5 * min_inliers):
                break  # not competitive even before refinement
            cand = Rigid3d(R[b], T[b])
            chosen = _closest_per_keypoint(cand, K, kp_dense, ver_xy, ver_X, threshold)
            if chosen.sum() >= 4:
                idx = chosen.nonzero()[0]
                xy_c, X_c = _take_rows(ver_xy, idx), _take_rows(ver_X, idx)
                cand, _ = refine(cand, K, xy_c, X_c, threshold, rounds=2)
            score = int(_closest_per_keypoint(cand, K, kp_dense, ver_xy, ver_X, threshold).sum())
            if score > best_score:
                best_score, best_pose = score, cand
                # Adaptive stop from the inlier ratio of the whole set, as for uniform
                # sampling: the ratio within the best-ranked pool can be high for a wrong pose
                # when repeated structure puts a consistent cluster of wrong matches at the top
                # of the ranking. Sampling the best-ranked first still stops sooner.
                e1 = reprojection_errors(best_pose, K, hyp_xy, hyp_X)
                in_best = np.cumsum(e1 < threshold)
                miss_log, miss_n = 0.0, 0
                w = float(in_best[-1]) / n1
                if w >= 1.0:
                    needed = it
                elif w > 0:
                    needed = int(math.ceil(math.log(1.0 - confidence) / math.log(1.0 - w**3)))
    if stats is not None:
        stats["iterations"] = it
    if best_pose is None or best_score < min_inliers:
        return None
    # One-to-one correspondences: for each keypoint its closest inlier hypothesis; refine on
    # them, re-choosing the closest hypothesis after refinement.
    pose = best_pose
    for _ in range(2):
        chosen = _closest_per_keypoint(pose, K, kp_dense, ver_xy, ver_X, threshold)
        if chosen.sum() < 4:
            return None
        idx = chosen.nonzero()[0]
        xy_c, X_c = _take_rows(ver_xy, idx), _take_rows(ver_X, idx)
        pose, mask = refine(pose, K, xy_c, X_c, refine_threshold)
    chosen = _closest_per_keypoint(pose, K, kp_dense, ver_xy, ver_X, refine_threshold)
    idx = chosen.nonzero()[0]
    xy_c, X_c = _take_rows(ver_xy, idx), _take_rows(ver_X, idx)
    est = _finish(pose, chosen[chosen], K, xy_c, X_c, min_inliers)
    if est is None:
        return None
    est.inlier_mask = chosen
    return est, chosen


def p3p_opencv(objS: np.ndarray, imgS: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, ...]:
    """OpenCV's P3P solutions of samples ``objS`` (S, 3, 3) world points, ``imgS`` (S, 3, 2)
    pixels: rotations (B, 3, 3) and translations (B, 3). A degenerate sample (two coincident
    points or pixels: two set-1 keypoints matched to one map point) gives solutions with NaN
    translations from ``cv2.solveP3P``: dropped here, before scoring, as ``p3p_batch`` drops
    them (a NaN pose scored 0 inliers, but by accident of NaN comparisons)."""
    p3p = cv2.solveP3P
    Rs: list[np.ndarray] = []  # rotation vectors of the solutions
    ts: list[np.ndarray] = []
    for j in range(len(objS)):
        try:
            n_sol, rvecs, tvecs = p3p(objS[j], imgS[j], K, None, flags=cv2.SOLVEPNP_P3P)
        except cv2.error:
            continue
        Rs += rvecs[:n_sol]
        ts += tvecs[:n_sol]
    B = len(Rs)
    r = np.asarray(Rs, np.float64).reshape(B, 3)
    T = np.asarray(ts, np.float64).reshape(B, 3)
    fin = np.isfinite(r).all(1) & np.isfinite(T).all(1)
    if not fin.all():
        r, T = r[fin], T[fin]
    return _rotations_from_rotvecs(r), T


def p3p_batch(X: np.ndarray, x: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every P3P solution of N samples at once (Grunert's quartic as in Haralick et al. 1994,
    its roots from the companion matrices' eigenvalues, polished by two Newton steps; the pose
    from the two triangles' orthonormal frames). ``X`` (N, 3, 3) world points, ``x`` (N, 3, 2)
    pixels. Returns rotations (M, 3, 3), translations (M, 3) and each solution's sample index
    (M,), ascending. Degenerate samples (coincident points) give no solution."""
    N = len(X)
    with np.errstate(all="ignore"):
        xh = np.concatenate([x, np.ones((N, 3, 1))], 2) @ np.linalg.inv(K).T
        j = xh / np.linalg.norm(xh, axis=2, keepdims=True)  # unit bearings
        ca = (j[:, 1] * j[:, 2]).sum(1)  # cos of the angle opposite a = |X2 - X3|
        cb = (j[:, 0] * j[:, 2]).sum(1)
        cg = (j[:, 0] * j[:, 1]).sum(1)
        a2 = ((X[:, 1] - X[:, 2]) ** 2).sum(1)
        b2 = ((X[:, 0] - X[:, 2]) ** 2).sum(1)
        c2 = ((X[:, 0] - X[:, 1]) ** 2).sum(1)
        q, p = (a2 - c2) / b2, (a2 + c2) / b2
        A4 = (q - 1) ** 2 - 4 * c2 / b2 * ca**2
        A3 = 4 * (q * (1 - q) * cb - (1 - p) * ca * cg + 2 * c2 / b2 * ca**2 * cb)
        A2 = 2 * (
            q**2
            - 1
            + 2 * q**2 * cb**2
            + 2 * (b2 - c2) / b2 * ca**2
            - 4 * p * ca * cb * cg
            + 2 * (b2 - a2) / b2 * cg**2
        )
        A1 = 4 * (-q * (1 + q) * cb + 2 * a2 / b2 * cg**2 * cb - (1 - p) * ca * cg)
        A0 = (1 + q) ** 2 - 4 * a2 / b2 * cg**2
        C = np.zeros((N, 4, 4))
        C[:, 1, 0] = C[:, 2, 1] = C[:, 3, 2] = 1
        C[:, 0, 3], C[:, 1, 3], C[:, 2, 3], C[:, 3, 3] = -A0 / A4, -A1 / A4, -A2 / A4, -A3 / A4
        ok = np.asarray(np.isfinite(C).all((1, 2)))
        C[~ok] = 0
        # The quartic's roots v = s3 / s1 by companion eigenvalues. A closed-form (Ferrari)
        # solver with eigvals as fallback was measured and reverted (1c71011, issue 10):
        # x0.51 at 1008 samples, x0.80 on 171 recorded real calls (median 64 samples; under
        # 64 rows its ~80 array operations are slower), but relocalization CPU per call
        # mean x0.993, p95 x0.996 on the bench's 500 frames (this runs 0.34 times a frame,
        # in the second-place test): ~0.13 ms of ~29, not worth 100 lines of numerics.
        r = np.linalg.eigvals(C)
        real = (np.abs(r.imag) <= 1e-6 * np.maximum(1, np.abs(r.real))) & ok[:, None]
        n_idx, k_idx = np.nonzero(real)
        v = r.real[n_idx, k_idx]
        A = np.stack([A4, A3, A2, A1, A0], 1)[n_idx]
        for _ in range(2):
            f = (((A[:, 0] * v + A[:, 1]) * v + A[:, 2]) * v + A[:, 3]) * v + A[:, 4]
            df = ((4 * A[:, 0] * v + 3 * A[:, 1]) * v + 2 * A[:, 2]) * v + A[:, 3]
            v = v - np.where(df != 0, f / np.where(df != 0, df, 1), 0)
        qq, cai, cbi, cgi = q[n_idx], ca[n_idx], cb[n_idx], cg[n_idx]
        u = ((qq - 1) * v**2 - 2 * qq * cbi * v + 1 + qq) / (2 * (cgi - v * cai))  # s2 / s1
        s1sq = b2[n_idx] / (1 + v**2 - 2 * v * cbi)
        good = (v > 0) & (u > 0) & (s1sq > 0) & np.isfinite(u) & np.isfinite(s1sq)
        n_idx, u, v, s1 = n_idx[good], u[good], v[good], np.sqrt(s1sq[good])
        Pc = j[n_idx] * np.stack([s1, u * s1, v * s1], 1)[:, :, None]  # camera points
        Xw = X[n_idx]

        def frame(P: np.ndarray) -> np.ndarray:
            e1 = P[:, 1] - P[:, 0]
            e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
            e3 = _cross_rows(e1, P[:, 2] - P[:, 0])
            e3 /= np.linalg.norm(e3, axis=1, keepdims=True)
            return np.stack([e1, _cross_rows(e3, e1), e3], 2)

        R = frame(Pc) @ frame(Xw).transpose(0, 2, 1)
        t = Pc[:, 0] - np.einsum("nij,nj->ni", R, Xw[:, 0])
        fin = np.isfinite(R).all((1, 2)) & np.isfinite(t).all(1)
    return R[fin], t[fin], n_idx[fin]


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of (N, 3) rows, the same products and differences in the same order
    (a1 b2 - a2 b1, a2 b0 - a0 b2, a0 b1 - a1 b0: bit for bit), without its axis handling
    (issue 10: four calls per ``p3p_batch``, ~0.1 ms of Python each)."""
    out = np.empty(a.shape)
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    np.subtract(a1 * b2, a2 * b1, out=out[:, 0])
    np.subtract(a2 * b0, a0 * b2, out=out[:, 1])
    np.subtract(a0 * b1, a1 * b0, out=out[:, 2])
    return out


def _minimal_samples(rng: np.random.Generator, pool: int, n: int) -> np.ndarray:
    """``n`` samples of 3 distinct indices below ``pool`` (``pool`` >= 3), drawn at once (one
    ``Generator.choice`` per sample cost as much as the P3P solve)."""
    s = rng.integers(0, pool, (n, 3))
    while True:
        dup = (s[:, 0] == s[:, 1]) | (s[:, 0] == s[:, 2]) | (s[:, 1] == s[:, 2])
        if not dup.any():
            return s
        s[dup] = rng.integers(0, pool, (int(dup.sum()), 3))


def _pool_miss_log(
    pools: list[tuple[int, int]], in_best: np.ndarray, out: float = 0.0, done: int = 0
) -> tuple[float, int]:
    """log of the probability that no minimal sample drawn from ``pools`` ((pool size,
    iterations) per batch) was all inliers of the best pose (``in_best``: its set-1 inliers
    among the first i + 1 ranked matches), and how many pools it covers. ``out``: the value
    for ``pools[:done]`` at the same ``in_best`` (0.0 and 0 to sum them all); the rest are
    added to it in order."""
    if out == -math.inf:
        return out, len(pools)
    for pool, n in pools[done:]:
        w = float(in_best[pool - 1]) / pool
        if w >= 1.0:
            return -math.inf, len(pools)
        out += n * math.log(1.0 - w**3)
    return out, len(pools)


def _rotations_from_rotvecs(r: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for a batch of rotation vectors (B, 3) -> (B, 3, 3) (one
    ``cv2.Rodrigues`` call per RANSAC solution cost as much as the P3P solve)."""
    theta = np.linalg.norm(r, axis=1)
    small = theta < 1e-12
    k = r / np.where(small, 1.0, theta)[:, None]
    Kx = np.zeros((len(r), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    R = np.eye(3) + s * Kx + (1.0 - c) * (Kx @ Kx)
    R[small] = np.eye(3)
    return R


def _closest_per_keypoint(pose, K, kp_dense, xy, X, threshold) -> np.ndarray:
    err = reprojection_errors(pose, K, xy, X)
    ok = err < threshold
    chosen = np.zeros(len(xy), bool)
    if not ok.any():
        return chosen
    idx = np.nonzero(ok)[0]
    order = idx[np.lexsort((err[idx], kp_dense[idx]))]
    first = np.ones(len(order), bool)
    first[1:] = kp_dense[order[1:]] != kp_dense[order[:-1]]
    chosen[order[first]] = True
    return chosen
