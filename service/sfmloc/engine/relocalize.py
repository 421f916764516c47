"""Localizing an image from scratch: GLOBAL-MATCHING to a pose (the tracker's relocalization
step), the pose near an approximate prior (the tracker's recovery, a prior given with a
single image), and ``relocalize``, the stateless single-image query."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..cameras import Camera, as_camera
from ..features.daisy import DaisyExtractor
from ..features.harris import detect_corners
from ..map.bundle import MapBundle
from ..transforms import Rigid3d
from .certainty import is_verified, relocalization_certainty, rests_on_few, withheld
from .config import EngineConf
from .distinct import inlier_spread, occupied_cells, place_points, second_place
from .frame import to_gray, to_working, working_scale
from .matching import global_matching, guided_matching, verify_hypotheses
from .pose import (
    PoseEstimate,
    estimate_pose,
    estimate_pose_one_to_many,
    project,
    reprojection_errors,
    robust_refine,
)
from .timing import StageTimer
from .tracker import map_subpixel
from .types import FrameResult, Matching, Status


class _OutOfTime(Exception):
    """The time budget ran out after ``stage`` (caught in ``relocalize``: a LOST result)."""

    def __init__(self, stage: str) -> None:
        super().__init__(stage)
        self.stage = stage


def check_deadline(deadline: float | None, stage: str, cpu_deadline: float | None = None) -> None:
    """Between stages: past ``deadline`` (``time.monotonic()``) or ``cpu_deadline``
    (``time.thread_time()``: this thread's CPU, a budget of work that a busy machine does not
    shrink), stop after ``stage``."""
    if deadline is not None and time.monotonic() > deadline:
        raise _OutOfTime(stage)
    if cpu_deadline is not None and time.thread_time() > cpu_deadline:
        raise _OutOfTime(stage)


def map_working_scale(camera: Camera, bundle: MapBundle, conf: EngineConf) -> float:
    """The factor a frame of ``camera`` is resized by before it meets ``bundle``
    (``frame.working_scale`` with the map's focal lengths)."""
    return working_scale(
        camera,
        bundle.native_focal_px,
        conf.working_scale,
        conf.max_working_pixels,
        bundle.coarsest_focal_px,
    )


def describe(
    extractor: DaisyExtractor, bundle: MapBundle, gray_prepared: np.ndarray, xy: np.ndarray
) -> np.ndarray:
    """PCA-32 DAISY at keypoints of a frame (same descriptor and projection as the bundle)."""
    theta = extractor.orientations(gray_prepared, xy)
    return bundle.pca.project(extractor.describe(gray_prepared, xy, theta))


def spread_order(
    xy: np.ndarray, response: np.ndarray, width: int, height: int, grid: tuple[int, int] = (8, 6)
) -> np.ndarray:
    """Keypoint indices, strongest per cell of a ``grid`` over the image first: every cell's
    strongest (by decreasing response), then every cell's second, ... A prefix of it is the
    strongest corners spread over the image (a textured corner does not take them all)."""
    gx, gy = grid
    cx = np.clip((xy[:, 0] * gx / max(width, 1)).astype(np.int64), 0, gx - 1)
    cy = np.clip((xy[:, 1] * gy / max(height, 1)).astype(np.int64), 0, gy - 1)
    cell = cy * gx + cx
    by_cell = np.lexsort((-response, cell))
    cs = cell[by_cell]
    rank = np.arange(len(cs)) - np.searchsorted(cs, cs)  # rank within its cell
    return by_cell[np.lexsort((-response[by_cell], rank))]


def visible_points(camera: Camera, cam_from_world: Rigid3d, points_xyz: np.ndarray) -> np.ndarray:
    """Rows of the map points in front of the camera whose (undistorted) projection falls
    inside its ``width`` x ``height`` image."""
    uv, z = project(cam_from_world, camera.K, points_xyz)
    u, v = uv[:, 0], uv[:, 1]
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    return np.nonzero((z > 0) & inside)[0]


def pose_from_global(
    desc: np.ndarray,
    xy_u: np.ndarray,
    bundle: MapBundle,
    camera: Camera,
    conf: EngineConf,
    neighbours: tuple[np.ndarray, np.ndarray] | None = None,
    deadline: float | None = None,
    cpu_deadline: float | None = None,
) -> tuple[PoseEstimate, np.ndarray, np.ndarray, np.ndarray] | None:
    """GLOBAL-MATCHING + one-to-many RANSAC: (pose, inlier keypoints, their points, every
    keypoint's hypotheses), or None (``global_pose`` says why). ``neighbours``: the search of
    ``desc`` over the whole map, when already made (``matching.search_all``). ``deadline``:
    see ``relocalize``."""
    return global_pose(desc, xy_u, bundle, camera, conf, neighbours, deadline, cpu_deadline)[0]


def global_pose(
    desc: np.ndarray,
    xy_u: np.ndarray,
    bundle: MapBundle,
    camera: Camera,
    conf: EngineConf,
    neighbours: tuple[np.ndarray, np.ndarray] | None = None,
    deadline: float | None = None,
    cpu_deadline: float | None = None,
    strong_only: bool = False,
    first_min_inliers: int = 0,
    rivals: list[PoseEstimate] | None = None,
) -> tuple[tuple[PoseEstimate, np.ndarray, np.ndarray, np.ndarray] | None, str]:
    """``pose_from_global``'s answer and, when it is None, why. ``rivals``: when given, an
    ambiguous answer's two poses (the best, then the second place) are appended to it (a
    caller's own pose is judged against them). ``strong_only``: a pose only
    when RANSAC's is far above chance (``_needs_no_verification``, whatever
    ``global_verify``), with ``relocalize_first_iterations`` RANSAC iterations at most; no
    verification by guided matching (``relocalize``'s first stage). ``first_min_inliers``
    (with ``strong_only``; 0: off): a weaker RANSAC pose with at least that many inliers is
    verified and judged as a one-stage pose is, and kept only when it would be published
    RELOCALIZED (``EngineConf.relocalize_first_min_inliers``)."""
    if neighbours is None and conf.global_nprobe:
        neighbours = bundle.index.search(desc, conf.k, nprobe=conf.global_nprobe)
    gm = global_matching(desc, bundle, conf, neighbours)
    check_deadline(deadline, "search", cpu_deadline)
    none = "no pose: too few consistent 2D-3D matches"
    if len(gm.set1_q) < 3:
        return None, none
    if (
        strong_only
        and not _needs_no_verification(_at_most_inliers(gm.set2_q), len(gm.set1_q), conf)
        and (first_min_inliers <= 0 or _at_most_inliers(gm.set2_q) < first_min_inliers)
    ):
        # a RANSAC pose's inliers are distinct keypoints with a hypothesis: too few to be
        # strong whatever RANSAC finds (the same answer, without the RANSAC)
        return None, "no strong pose from the first keypoints"
    params = conf.ransac()
    if strong_only:
        params = replace(params, max_iterations=conf.relocalize_first_iterations)
    K = camera.K
    hyp = np.full((len(desc), conf.max_hypotheses), -1, np.int64)
    if len(gm.set2_q):
        rank = np.arange(len(gm.set2_q)) - np.searchsorted(gm.set2_q, gm.set2_q)
        hyp[gm.set2_q, rank] = gm.set2_p
    X = bundle.points_xyz
    res = estimate_pose_one_to_many(
        xy_u[gm.set1_q],
        X[gm.set1_p],
        gm.set2_q,
        xy_u[gm.set2_q],
        X[gm.set2_p],
        K,
        params,
        pool_stop=conf.global_pool_stop,
    )
    if res is None:
        return None, none
    est, chosen = res
    check_deadline(deadline, "RANSAC", cpu_deadline)
    out: tuple[PoseEstimate, np.ndarray, np.ndarray, np.ndarray] | None = None
    strong = (conf.global_verify or strong_only) and _needs_no_verification(
        est.num_inliers, len(gm.set1_q), conf
    )
    if (
        strong_only
        and not strong
        and (first_min_inliers <= 0 or est.num_inliers < first_min_inliers)
    ):
        return None, "no strong pose from the first keypoints"
    if conf.global_verify and not strong:
        # Guided matching of the whole frame around the RANSAC pose (scope: the map points it
        # makes visible). A right pose gathers the matches the ratio test dropped; a chance one
        # does not reach ``recover_min_inliers``. See ``EngineConf.global_verify``.
        reuse = gm.neighbours if conf.global_verify_search == "reuse" else None
        ver = match_near_prior(desc, xy_u, bundle, camera, conf, est.cam_from_world, reuse)
        if ver is not None:
            vest, point = ver
            if vest.num_inliers >= est.num_inliers:
                q = np.nonzero(point >= 0)[0]
                out = vest, q, point[q], hyp
            else:
                # Confirmed, and the RANSAC pose has the more inliers (the narrower covariance).
                out = est, gm.set2_q[chosen], gm.set2_p[chosen], hyp
    if out is None:
        # Among hundreds of candidate matches, ten that agree can be chance: demand a fraction.
        if est.num_inliers < conf.global_min_inlier_ratio * len(gm.set1_q):
            return None, none
        # Not verified for its strength: refined like a verified pose (a Cauchy loss on its
        # inliers), which the guided matching's pose would have been.
        fine = robust_final(est, K, conf) if strong else est
        out = fine, gm.set2_q[chosen], gm.set2_p[chosen], hyp
    if strong_only and not strong:
        # A weak first-stage pose is the answer only when it would be published as
        # RELOCALIZED: one that the other corners would make certain (a thin map's) is left
        # to them, before the distinctness tests' cost.
        cert = relocalization_certainty(out[0], K, bundle, conf)
        if not cert.verified or withheld(cert.position_sd, out[0].num_inliers, conf):
            return None, "no strong pose from the first keypoints"
    # Distinct: inliers over the image, and no other place nearly as good (``distinct``).
    if out[0].num_inliers < conf.spread_max_inliers:
        visible = None
        if conf.spread_cells == "visible":
            pose = out[0].cam_from_world
            visible = project(pose, K, X[visible_points(camera, pose, X)])[0]
        spread = inlier_spread(xy_u, xy_u[out[1]], camera.width, camera.height, visible)
        cells = occupied_cells(xy_u[out[1]], camera.width, camera.height)
        if cells < conf.min_inlier_cells:
            return None, (
                f"no pose: its {out[0].num_inliers} inliers lie in {cells} of the 16 image "
                f"cells (at least {conf.min_inlier_cells}): a narrow patch fits two poses"
            )
        if spread < conf.min_inlier_spread:
            where = "with keypoints" + (" and visible map points" if visible is not None else "")
            return None, (
                f"no pose: its {out[0].num_inliers} inliers cover {spread:.0%} of the image "
                f"cells {where} (at least {conf.min_inlier_spread:.0%})"
            )
    if conf.second_place_ratio > 0:
        other = second_place(
            est,
            (gm.set1_q, gm.set1_p),
            (gm.set2_q, gm.set2_p),
            xy_u,
            X,
            K,
            conf,
            bundle.scene_scale,
            place_points(bundle, gm.set2_p[chosen], conf.second_place_share),
        )
        check_deadline(deadline, "the second-place test", cpu_deadline)
        if other is not None:
            if rivals is not None:
                rivals += [out[0], other]
            dist = np.linalg.norm(other.cam_from_world.center - est.cam_from_world.center)
            return None, (
                f"ambiguous: another place {dist / bundle.scene_scale:.2f} scene scales away "
                f"fits {other.num_inliers} matches against {est.num_inliers} "
                "(repeated structure): no pose"
            )
    return out, ""


def robust_final(est: PoseEstimate, K: np.ndarray, conf: EngineConf) -> PoseEstimate:
    """``est`` refined on its inliers with the Cauchy loss of ``refine_loss_scale_px`` (the
    same inliers; as ``pose.final_refinement`` but without re-selecting them, which would mix
    several hypotheses of one keypoint)."""
    if conf.refine_loss_scale_px <= 0 or est.inlier_xy is None or est.inlier_X is None:
        return est
    xy, X = est.inlier_xy, est.inlier_X
    pose = robust_refine(est.cam_from_world, K, xy, X, conf.refine_loss_scale_px)
    err = reprojection_errors(pose, K, xy, X)
    return replace(est, cam_from_world=pose, mean_error_px=float(err.mean()))


def _at_most_inliers(set2_q: np.ndarray) -> int:
    """The most inliers a pose from these one-to-many matches can have: their distinct
    keypoints (``set2_q`` is grouped by keypoint)."""
    return int(np.count_nonzero(np.diff(set2_q))) + 1 if len(set2_q) else 0


def _needs_no_verification(inliers: int, candidates: int, conf: EngineConf) -> bool:
    """A RANSAC pose far above what chance gathers (``global_verify_min_inliers`` inliers and
    ``global_verify_min_ratio`` of the ratio-test matches) is not re-matched by guided matching:
    the verification rejects chance poses, which had 10-47 inliers (2-13%), and a pose on that
    many inliers gains no accuracy from it. The distinctness tests still judge it."""
    if conf.global_verify_min_inliers <= 0:
        return False
    return (
        inliers >= conf.global_verify_min_inliers
        and inliers >= conf.global_verify_min_ratio * candidates
    )


def pose_from_hypotheses(
    hyp: np.ndarray,
    xy_u: np.ndarray,
    bundle: MapBundle,
    K: np.ndarray,
    conf: EngineConf,
    prior: Rigid3d,
) -> tuple[PoseEstimate, np.ndarray] | None:
    """A pose from one-to-many hypotheses around an approximate ``prior``, in two passes:
    verification within ``prior_threshold_px`` of the prior and a first pose, then every
    keypoint's hypotheses re-verified against that pose within ``guided_threshold_px`` and the
    pose re-estimated (wrong matches that fit the loose window drop out). Returns the pose and
    the verified point of every keypoint (-1: none)."""
    params = conf.ransac(conf.recover_min_inliers)
    best: tuple[PoseEstimate, np.ndarray] | None = None
    for threshold in (conf.prior_threshold_px, conf.guided_threshold_px):
        cur = np.full(len(hyp), -1, np.int64)
        verify_hypotheses(hyp, xy_u, bundle.points_xyz, prior, K, threshold, cur)
        q = np.nonzero(cur >= 0)[0]
        if len(q) < params.min_inliers:
            break
        nxt = estimate_pose(xy_u[q], bundle.points_xyz[cur[q]], K, params, prior=prior)
        if nxt is None:
            break
        prior = nxt.cam_from_world
        point = np.full(len(hyp), -1, np.int64)
        point[q[nxt.inlier_mask]] = cur[q[nxt.inlier_mask]]
        best = (nxt, point)
    return best


def match_near_prior(
    desc: np.ndarray,
    xy_u: np.ndarray,
    bundle: MapBundle,
    camera: Camera,
    conf: EngineConf,
    prior: Rigid3d,
    neighbours: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[PoseEstimate, np.ndarray] | None:
    """Matches scoped by the points visible from the prior (in ``camera``'s image), verified
    against it with a loose threshold (the prior is approximate), then a pose with the prior as
    a hypothesis; the same rules as the tracker's recovery (``prior_threshold_px``,
    ``recover_min_inliers``). Returns the pose and the verified point of every keypoint (-1:
    none). ``neighbours``: global matching's search of ``desc``, restricted to the scope
    instead of a second search (``guided_matching``)."""
    visible = visible_points(camera, prior, bundle.points_xyz)
    if len(visible) < conf.min_inliers:
        return None
    K = camera.K
    loose = conf.model_copy(update={"guided_threshold_px": conf.prior_threshold_px})
    gm = guided_matching(desc, xy_u, bundle, visible, prior, K, loose, neighbours)
    return pose_from_hypotheses(gm.hyp, xy_u, bundle, K, conf, prior)


def relocalize(
    image: np.ndarray,
    camera: Camera | str | Path,
    bundle: MapBundle,
    conf: EngineConf | None = None,
    prior: Rigid3d | None = None,
    deadline: float | None = None,
    cpu_deadline: float | None = None,
) -> FrameResult:
    """Localize a single image from scratch (stateless). With a ``prior`` (cam_from_world),
    the search is scoped to the database images that see the points the prior sees, and
    matches are verified against it, as in guided matching; without a pose from the scoped
    search it falls back to global matching. The result's ``matching`` says which found the
    pose: ``guided`` (around the prior) or ``global``.

    ``deadline`` (``time.monotonic()``): checked between stages (image preparation, detection,
    description, search, RANSAC); past it the result is LOST, its message saying "time budget
    exceeded" and after which stage (a huge image or absurd intrinsics cannot hold a worker
    for seconds: issue 16). ``cpu_deadline`` (``time.thread_time()``) the same on this
    thread's CPU time."""
    camera = as_camera(camera)  # a camera.json path or "MODEL w h params..." too
    conf = conf or EngineConf()
    timer = StageTimer()
    try:
        return _relocalize(image, camera, bundle, conf, prior, deadline, cpu_deadline, timer)
    except _OutOfTime as exc:
        result = FrameResult(Status.LOST, 0.0, matching=Matching.GLOBAL)
        result.message = f"time budget exceeded after {exc.stage}"
        result.timings_ms, result.cpu_timings_ms = timer.total(), timer.cpu()
        return result


def _relocalize(
    image: np.ndarray,
    camera: Camera,
    bundle: MapBundle,
    conf: EngineConf,
    prior: Rigid3d | None,
    deadline: float | None,
    cpu_deadline: float | None,
    timer: StageTimer,
) -> FrameResult:
    check_deadline(deadline, "decoding", cpu_deadline)
    gray = to_gray(image, camera)
    # A fine image is described at about the map's resolution (see ``Localizer``); the pose
    # does not depend on the scaling of the intrinsics.
    scale = map_working_scale(camera, bundle, conf)
    if scale != 1.0:
        gray, camera = to_working(gray, scale), camera.scaled(scale)
    check_deadline(deadline, "image preparation", cpu_deadline)
    corners = detect_corners(
        gray,
        rel_threshold=conf.gamma,
        max_corners=conf.relocalize_max_keypoints or conf.global_max_keypoints,
        border=conf.mu // 2,
        subpixel=map_subpixel(conf, bundle.manifest.params),
    )
    timer.lap("detect")
    check_deadline(deadline, "detection", cpu_deadline)
    result = FrameResult(Status.LOST, 0.0, detected=len(corners), matching=Matching.GLOBAL)
    if len(corners) < conf.min_inliers:
        result.timings_ms, result.cpu_timings_ms = timer.total(), timer.cpu()
        result.message = f"only {len(corners)} keypoints in the image"
        return result
    extractor = DaisyExtractor()
    prepared = extractor.prepare(gray)
    xy_u = camera.undistort_points(corners.xy) if camera.is_distorted else corners.xy
    est = None
    neighbours: tuple[np.ndarray, np.ndarray] | None = None  # the search of desc, when made
    first = conf.relocalize_first_keypoints
    staged = (
        prior is None
        and conf.global_nprobe > 0
        and 0 < first < len(corners)
        and len(corners) >= conf.relocalize_staged_from
    )
    if staged:
        # First stage: the strongest corners spread over the image. A pose far above chance
        # from them is the answer; else the rest are described and searched, and global
        # matching runs on all of them as without the stage (``relocalize_first_keypoints``).
        sub = np.sort(
            spread_order(corners.xy, corners.response, camera.width, camera.height)[:first]
        )
        desc_1 = describe(extractor, bundle, prepared, corners.xy[sub])
        nb_1 = bundle.index.search(desc_1, conf.k, nprobe=conf.global_nprobe)
        check_deadline(deadline, "the first keypoints' search", cpu_deadline)
        res, _ = global_pose(
            desc_1,
            xy_u[sub],
            bundle,
            camera,
            conf,
            nb_1,
            deadline,
            cpu_deadline,
            True,
            conf.relocalize_first_min_inliers,
        )
        est = None if res is None else res[0]
        desc = desc_1  # (not used again when est is the answer)
        if est is None:
            rest = np.ones(len(corners), bool)
            rest[sub] = False
            desc_r = describe(extractor, bundle, prepared, corners.xy[rest])
            nb_r = bundle.index.search(desc_r, conf.k, nprobe=conf.global_nprobe)

            def joined(a: np.ndarray, b: np.ndarray) -> np.ndarray:
                # rows of the first keypoints' ``a`` and the rest's ``b`` in corner order
                out = np.empty((len(corners), a.shape[1]), a.dtype)
                out[sub], out[rest] = a, b
                return out

            desc = joined(desc_1, desc_r)
            neighbours = (joined(nb_1[0], nb_r[0]), joined(nb_1[1], nb_r[1]))
    else:
        desc = describe(extractor, bundle, prepared, corners.xy)
    check_deadline(deadline, "description", cpu_deadline)
    if prior is not None:
        near = match_near_prior(desc, xy_u, bundle, camera, conf, prior)
        est = None if near is None else near[0]
        if est is not None:
            # found by guided matching around the prior, not by global matching: reported so
            # (the status stays RELOCALIZED / UNVERIFIED: a single image is judged as one)
            result.matching = Matching.GUIDED
        check_deadline(deadline, "the search near the prior", cpu_deadline)
    why = "no pose: too few consistent 2D-3D matches"
    if est is None:
        res, why = global_pose(
            desc,
            xy_u,
            bundle,
            camera,
            conf,
            neighbours,
            deadline=deadline,
            cpu_deadline=cpu_deadline,
        )
        est = None if res is None else res[0]
    timer.lap("reloc")
    if est is not None:
        cert = relocalization_certainty(est, camera.K, bundle, conf)
        timer.lap("pose")
        result.inliers = est.num_inliers
        held = withheld(cert.position_sd, est.num_inliers, conf)
        if held is None:
            # a single image has no next frame to check the matches its certainty rests on
            # (its count by the strict test itself: one not verified for resting on one map
            # point, ``verified_without_one``, is left out as many points as a verified one)
            strict = is_verified(est, cert.position_sd, conf)
            held = rests_on_few(est, camera.K, bundle, conf, strict)
        if held is not None:
            result.message = held
        else:
            # a single image has no next frame to confirm it: only the strict test verifies
            result.status = Status.RELOCALIZED if cert.verified else Status.UNVERIFIED
            result.cam_from_world = est.cam_from_world
            result.covariance = cert.covariance
    else:
        result.message = why
    result.timings_ms, result.cpu_timings_ms = timer.total(), timer.cpu()
    return result
