"""How far a pose can be trusted: its covariance, the strict "verified" test, and the rule
that withholds a pose too uncertain to publish (a pose is a promise). Shared by the tracker's
Algorithm 1 (``localizer``) and single-image relocalization (``relocalize``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..map.bundle import MapBundle
from .config import EngineConf
from .point_uncertainty import PointUncertainty
from .pose import (
    PoseEstimate,
    eigvalsh_sym,
    leave_out_sd_bound,
    pose_covariances,
    pose_error_vector,
)


@dataclass(frozen=True)
class Certainty:
    covariance: np.ndarray  # 6x6 of cam_from_world (``engine.pose.COVARIANCE_ORDER``)
    position_sd: float  # centre sd in its worst direction, in scene scales (inf: unknown)
    verified: bool  # passes the strict test (``EngineConf.verified_position_sd``)
    # ``position_sd`` without the pose's most influential match
    # (``EngineConf.covariance_leave_one_out``; else the same): what it would be if that match
    # were wrong. The tracker re-matches a frame whose pose would be withheld by it. Where an
    # upper bound of it would not withhold the pose, that bound (the same decision; issue 10:
    # the exact one's per-match algebra was a fifth of the covariance's CPU).
    position_sd_loo: float = float("nan")


def certainty(est: PoseEstimate, K: np.ndarray, bundle: MapBundle, conf: EngineConf) -> Certainty:
    """The covariance of ``est`` and what it says about the pose."""
    cov, loo = covariances(est, K, bundle, conf)
    sd = position_sd(cov) / bundle.scene_scale
    sd_loo = position_sd(loo) / bundle.scene_scale
    return Certainty(cov, sd, is_verified(est, sd, conf), sd_loo)


def covariance(est: PoseEstimate, K: np.ndarray, bundle: MapBundle, conf: EngineConf) -> np.ndarray:
    """The pose's 6x6 covariance from its final refinement's inliers (``pose_covariance``),
    with the map points' own uncertainty (``point_uncertainty``) unless switched off."""
    return covariances(est, K, bundle, conf)[0]


def covariances(
    est: PoseEstimate, K: np.ndarray, bundle: MapBundle, conf: EngineConf
) -> tuple[np.ndarray, np.ndarray]:
    """``covariance``, and the same without the most influential match when
    ``covariance_leave_one_out`` (else the same matrix)."""
    if est.inlier_xy is None or est.inlier_X is None:
        inf = np.full((6, 6), np.inf)
        return inf, inf
    extra = _point_sigma_px(est, bundle, conf)
    # The pixel noise is measured with the final refinement's own Cauchy weights
    # (``refine_loss_scale_px``), as the pose was estimated.
    # the leave-one-out is only asked whether it would withhold the pose (``withheld``)
    limit = conf.max_position_sd / small_sample_factor(est.num_inliers, conf.withhold_noise_z)
    return pose_covariances(
        est.cam_from_world,
        K,
        est.inlier_xy,
        est.inlier_X,
        point_sigma_px=extra,
        loss_scale=conf.refine_loss_scale_px,
        leave_one_out=conf.covariance_leave_one_out,
        loo_sd_over=limit * bundle.scene_scale,
    )


def _point_sigma_px(est: PoseEstimate, bundle: MapBundle, conf: EngineConf) -> np.ndarray | None:
    """The inliers' map points' own error in pixels (``point_uncertainty``), None when off."""
    if conf.map_noise_px <= 0 or est.inlier_X is None:
        return None
    z = est.inlier_X @ est.cam_from_world.rotation[2] + est.cam_from_world.translation[2]
    pu = PointUncertainty.for_bundle(bundle)
    if est.inlier_points is not None:
        return pu.sigma_px_of(est.inlier_points, z, conf.map_noise_px)
    return pu.sigma_px(est.inlier_X, z, conf.map_noise_px)


def position_sd_without(
    est: PoseEstimate,
    K: np.ndarray,
    bundle: MapBundle,
    conf: EngineConf,
    k: int,
    sd_over: float = 0.0,
) -> float:
    """The centre sd (scene scales, worst direction) without the ``k`` map points whose removal
    widens it most (greedily: the most influential, then the most influential of the rest, ...).
    A map point is one piece of evidence: its matches (two keypoints a pixel apart, one per
    detection scale, can both match it) are counted once. What the pose would be worth if ``k``
    of its matches were wrong (``EngineConf.relocalize_leave_out_sd``). ``sd_over`` > 0
    (scene scales): a caller that only asks whether it is over that value may get an upper
    bound instead, when the bound is not over it (``pose.leave_out_sd_bound``)."""
    if est.inlier_xy is None or est.inlier_X is None:
        return float("inf")
    _, first = np.unique(est.inlier_X, axis=0, return_index=True)
    keep = np.sort(first)
    extra = _point_sigma_px(est, bundle, conf)
    if sd_over > 0:
        bound = leave_out_sd_bound(
            est.cam_from_world,
            K,
            est.inlier_xy[keep],
            est.inlier_X[keep],
            k,
            point_sigma_px=None if extra is None else extra[keep],
            loss_scale=conf.refine_loss_scale_px,
        )
        if bound / bundle.scene_scale <= sd_over:
            return bound / bundle.scene_scale
    for _ in range(k):
        removed: list[int] = []
        _, loo = pose_covariances(
            est.cam_from_world,
            K,
            est.inlier_xy[keep],
            est.inlier_X[keep],
            point_sigma_px=None if extra is None else extra[keep],
            loss_scale=conf.refine_loss_scale_px,
            removed=removed,
        )
        if not removed:  # too few points, or one the pose cannot do without
            return float("inf")
        keep = np.delete(keep, removed[0])
    return position_sd(loo) / bundle.scene_scale


def rests_on_few(
    est: PoseEstimate, K: np.ndarray, bundle: MapBundle, conf: EngineConf, verified: bool
) -> str | None:
    """Why a single-image pose is withheld for resting on a few matches (its centre sd without
    its ``relocalize_leave_out`` most influential map points, ``relocalize_leave_out_verified``
    for a pose passing the strict test, over ``relocalize_leave_out_sd``), or None."""
    k = conf.relocalize_leave_out_verified if verified else conf.relocalize_leave_out
    if conf.relocalize_leave_out_sd <= 0 or k <= 0:
        return None
    sd = position_sd_without(est, K, bundle, conf, k, sd_over=conf.relocalize_leave_out_sd)
    if sd <= conf.relocalize_leave_out_sd:
        return None
    return (
        f"pose withheld: it rests on {k} matches (centre sd {sd * 100:.1f}% of the scene "
        f"scale without them, limit {conf.relocalize_leave_out_sd * 100:.1f}%), "
        f"{est.num_inliers} inliers"
    )


def relocalization_certainty(
    est: PoseEstimate, K: np.ndarray, bundle: MapBundle, conf: EngineConf
) -> Certainty:
    """``certainty`` of a relocalization (a pose with no tracks behind it: global matching, a
    prior's recovery), with ``verified_without_one`` applied."""
    return verified_without_one(certainty(est, K, bundle, conf), est, K, bundle, conf)


def verified_without_one(
    cert: Certainty, est: PoseEstimate, K: np.ndarray, bundle: MapBundle, conf: EngineConf
) -> Certainty:
    """``cert`` not verified when it passes the strict test on one map point: its centre sd
    without its most influential map point (``position_sd_without``: a point matched by two
    keypoints counts once) would be withheld (``withheld``). A relocalization has no earlier
    frame to check that point's match, so its strictly tested certainty cannot rest on it
    (``EngineConf.verified_without_one``)."""
    if not (cert.verified and conf.verified_without_one):
        return cert
    # (an upper bound may answer where it is within the limit: the same decision)
    limit = conf.max_position_sd / small_sample_factor(est.num_inliers, conf.withhold_noise_z)
    sd = position_sd_without(est, K, bundle, conf, 1, sd_over=limit)
    if withheld(sd, est.num_inliers, conf) is None:
        return cert
    return replace(cert, verified=False)


def is_verified(est: PoseEstimate, sd: float, conf: EngineConf) -> bool:
    """The strict test: certain enough (centre sd, a fraction of the scene scale) on enough
    inliers."""
    return sd <= conf.verified_position_sd and est.num_inliers >= conf.verified_min_inliers


def position_sd(cov: np.ndarray) -> float:
    """Standard deviation of the camera centre in its worst direction (map units)."""
    if not np.isfinite(cov).all():  # (the array's own .all(): np.all's dispatch costs 3 us)
        return float("inf")
    # (the largest eigenvalue: LAPACK returns them ascending; math.sqrt: the same correctly
    # rounded root as np.sqrt, without its dispatch on a scalar)
    return math.sqrt(max(float(eigvalsh_sym(cov[3:, 3:])[-1]), 0.0))


def small_sample_factor(inliers: int, z: float) -> float:
    """How much larger the centre sd may be, at one-sided normal quantile ``z`` (1.645: 95%),
    given that the pixel noise was estimated from only ``2 * inliers - 6`` residual degrees of
    freedom: sqrt(dof / chi2 quantile), the quantile by Wilson-Hilferty. 1 for ``z`` = 0."""
    dof = max(2 * inliers - 6, 1)
    a = 2.0 / (9.0 * dof)
    # (math.sqrt: np.sqrt's correctly rounded root without its dispatch on a scalar; 5 calls a
    # frame)
    q = dof * max(1.0 - a - z * math.sqrt(a), 1e-3) ** 3
    return math.sqrt(dof / q) if z > 0 else 1.0


def withheld(sd: float, inliers: int, conf: EngineConf) -> str | None:
    """Why a pose is too uncertain to publish (centre sd, at the upper bound of its noise
    estimate, over ``max_position_sd`` scene scales), or None when it may be published."""
    bound = sd * small_sample_factor(inliers, conf.withhold_noise_z)
    if not bound > conf.max_position_sd:
        return None
    return (
        f"pose withheld: centre sd {sd * 100:.1f}% of the scene scale (upper bound "
        f"{bound * 100:.1f}%, limit {conf.max_position_sd * 100:.1f}%), {inliers} inliers"
    )


def with_disagreement(
    cert: Certainty, est: PoseEstimate, other: PoseEstimate, bundle: MapBundle, conf: EngineConf
) -> Certainty:
    """``cert`` of ``est`` widened by its difference from ``other``, a second pose of the same
    frame from its own matches (the whole-frame re-match): covariance ``C + e e^T`` with ``e``
    the difference in the covariance's parameterization (``pose_error_vector``). Each pose's
    covariance assumes independent pixel noise; drifted tracks on one plane in a blurred frame
    move a pose along the plane's translation-rotation ambiguity with small residuals, and the
    other pose's distance is the evidence of how far (``EngineConf.rematch_disagreement``)."""
    e = pose_error_vector(est.cam_from_world, other.cam_from_world)
    cov = cert.covariance + np.outer(e, e)
    sd = position_sd(cov) / bundle.scene_scale
    return Certainty(cov, sd, is_verified(est, sd, conf), float(np.fmax(cert.position_sd_loo, sd)))
