"""Algorithm 1 of the paper, LOCALIZE-FRAME(f, T, M), for one camera, and single-image
relocalization.

Per frame::

    KALMAN-FILTER-PREDICT
    K   <- EXTRACT-KEYPOINTS(f)                 Harris (gamma * previous max) + BRIEF
    eta <- TRACK-2D(f, K, T)                    windows around predicted positions
    if eta < kappa1: ADD-GOOD-FEATURES(f, K, T) pending keypoints where none are tracked
    C1  <- verified 2D-3D matches in T
    if |C1| > kappa2:
        P <- ESTIMATE-POSE(C1)                  P3P RANSAC + LM refinement
        if MATCHES-PENDING(T): GUIDED-MATCHING(f, T, P, M)   one batch of 100-150
    else:
        GLOBAL-MATCHING(f, T, M)                relocalize
    C2  <- verified matches in T
    if |C2| > kappa2 and C1 != C2: P <- ESTIMATE-POSE(C2)
    KALMAN-FILTER-UPDATE(P)

Two details the paper leaves open, decided here: when the pose from C1 fails (fewer than
``min_inliers`` inliers), its matches are discarded and the frame relocalizes at once (the
paper's rule "relocalize when fewer than kappa2 matches remain", applied after the failure);
matches that are outliers to the frame's pose lose their 3D point and become pending again.
Stored one-to-many hypotheses of tracked keypoints are re-verified against every new pose.
"""

from __future__ import annotations

import logging

import numpy as np

from ..cameras import Camera
from ..features.daisy import DaisyExtractor
from ..features.harris import detect_corners
from ..map.bundle import MapBundle
from ..transforms import Rigid3d, rotation_angle_deg
from .config import EngineConf
from .frame import to_gray, to_working, working_scale
from .matching import global_matching, guided_matching, verify_hypotheses
from .motion_filter import make_pose_filter
from .point_uncertainty import PointUncertainty
from .pose import PoseEstimate, estimate_pose, estimate_pose_one_to_many, pose_covariance, project
from .timing import StageTimer
from .track_table import TrackTable
from .tracker import Keypoints, extract_keypoints, free_candidates, map_subpixel, track_2d
from .types import FrameResult, Status

log = logging.getLogger(__name__)


def _working_scale(camera: Camera, bundle: MapBundle, conf: EngineConf) -> float:
    return working_scale(
        camera, bundle.native_focal_px, conf.working_scale, conf.max_working_pixels,
        bundle.coarsest_focal_px,
    )


def describe(extractor: DaisyExtractor, bundle: MapBundle, gray_prepared: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """PCA-32 DAISY at keypoints of a frame (same descriptor and projection as the bundle)."""
    theta = extractor.orientations(gray_prepared, xy)
    return bundle.pca.project(extractor.describe(gray_prepared, xy, theta))


class Localizer:
    """Per-client localization state: track table, Kalman filter, adaptive threshold.

    ``localize(frame, stamp)`` processes one video frame (uint8 gray or BGR of the camera's
    size; ``stamp`` in seconds) and returns a ``FrameResult``. Not thread-safe: one frame at a
    time per instance. The bundle is shared read-only between instances.

    Frames finer than the map (``working_scale``) are downscaled once on arrival: ``camera``
    is the working camera every pixel quantity refers to, ``input_camera`` the caller's.
    Poses are the same for both (scaling the intrinsics does not move the camera).
    """

    def __init__(self, bundle: MapBundle, camera: Camera, conf: EngineConf | None = None) -> None:
        self.bundle = bundle
        self.conf = conf or EngineConf()
        self.input_camera = camera
        self.scale = _working_scale(camera, bundle, self.conf)
        self.camera = camera if self.scale == 1.0 else camera.scaled(self.scale)
        self.K = self.camera.K
        self.subpixel = map_subpixel(self.conf, bundle.manifest.params)
        self.extractor = DaisyExtractor()
        self.reset()

    def reset(self) -> None:
        """Forget tracks and motion: the next frame relocalizes."""
        c = self.conf
        self.table = TrackTable.empty(c.max_hypotheses)
        self.filter = make_pose_filter(
            c.motion_model, c.accel_noise_scales_per_s2, c.angular_accel_noise_rad_s2,
            c.position_noise_scales, c.orientation_noise_rad, self.bundle.scene_scale,
        )
        self.prev_max_response: float | None = None
        self.next_track_id = 0
        self.last_stamp: float | None = None
        self.frames = 0
        self.scope_points = np.zeros(0, np.int64)  # 3D points matched in the last posed frame
        self.unverified = False  # tracking from a relocalization not verified yet
        self.last_posed_stamp: float | None = None

    # ------------------------------------------------------------------ helpers
    def _undistort(self, xy: np.ndarray) -> np.ndarray:
        return self.camera.undistort_points(xy) if self.camera.is_distorted else xy

    def _predict_positions(self, pred: Rigid3d | None) -> np.ndarray:
        """Where each tracked keypoint should be in the new frame."""
        T = self.table
        xy = T.xy.copy()
        if pred is None or len(T) == 0:
            return xy
        rows = np.nonzero(T.point >= 0)[0]
        if len(rows) == 0:
            return xy
        uv, z = self.camera.project(pred, self.bundle.points_xyz[T.point[rows]])
        ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
        rows, uv = rows[ok], uv[ok]
        if len(rows) == 0:
            return xy
        shift = np.median(uv - T.xy[rows], axis=0)
        xy += shift  # keypoints without a 3D point follow the median image motion
        xy[rows] = uv
        return xy

    def _new_ids(self, n: int) -> np.ndarray:
        ids = np.arange(self.next_track_id, self.next_track_id + n, dtype=np.int64)
        self.next_track_id += n
        return ids

    def _plausible(self, pose: Rigid3d, pred: Rigid3d | None, dt: float) -> bool:
        """A tracked pose may not jump farther from the prediction than the camera can move."""
        if pred is None:
            return True
        c = self.conf
        dpos = float(np.linalg.norm(pose.center - pred.center))
        drot = np.radians(rotation_angle_deg(pose.rotation, pred.rotation))
        slack = max(dt, 1.0 / 30.0)
        reach = (c.max_speed_scales_per_s * slack + c.jump_tolerance_scales) * self.bundle.scene_scale
        turn = c.max_angular_speed_rad_s * slack + np.radians(c.jump_tolerance_deg)
        return dpos <= reach and drot <= turn

    def _estimate_from_table(
        self, pred: Rigid3d | None = None, dt: float = 0.0, pred_is_estimate: bool = False
    ) -> PoseEstimate | None:
        rows, pts = self.table.matches()
        if len(rows) <= self.conf.kappa2:
            return None
        c = self.conf
        est = estimate_pose(
            self._undistort(self.table.xy[rows]), self.bundle.points_xyz[pts], self.K, c.ransac(), prior=pred,
            prior_threshold=c.prior_threshold_px, prior_is_estimate=pred_is_estimate,
        )
        if est is not None and not self._plausible(est.cam_from_world, pred, dt):
            log.debug("rejected a pose %.3g units / %.1f deg from the prediction",
                      np.linalg.norm(est.cam_from_world.center - pred.center),
                      rotation_angle_deg(est.cam_from_world.rotation, pred.rotation))
            est = None
        if est is None:
            # The tracked matches are no longer consistent: drop them (relocalize).
            self.table.point[rows] = -1
            self.table.pending[rows] = True
            return None
        outl = rows[~est.inlier_mask]
        self.table.point[outl] = -1
        self.table.pending[outl] = True
        return est

    # ------------------------------------------------------------------ algorithm 1
    def localize(self, frame: np.ndarray, stamp: float) -> FrameResult:
        c = self.conf
        timer = StageTimer()
        gray = to_gray(frame, self.input_camera)
        if self.last_stamp is not None and (stamp - self.last_stamp > c.max_frame_gap_s or stamp < self.last_stamp):
            self.reset()  # a long gap (or time going back): motion and tracks are stale
        dt = 0.0 if self.last_stamp is None else stamp - self.last_stamp
        pred = self.filter.predict(stamp)
        self.last_stamp = stamp
        self.frames += 1
        timer.lap("filter")

        gray = to_working(gray, self.scale)
        thr = c.gamma * self.prev_max_response if self.prev_max_response else None
        kps = extract_keypoints(gray, thr, c, self.subpixel)
        if kps.max_response > 0:
            self.prev_max_response = kps.max_response
        timer.lap("detect")

        # TRACK-2D
        T = self.table
        m = track_2d(T, self._predict_positions(pred), kps, c)
        tracked = m >= 0
        T.keep(tracked)
        m = m[tracked]
        T.xy = kps.xy[m]
        T.brief = kps.brief[m]
        T.age += 1
        eta = len(T)
        if eta < c.kappa1 or T.n_3d() < c.refill_3d:  # ADD-GOOD-FEATURES
            free = free_candidates(T.xy, kps, m, c.add_min_distance_px)
            room = max(0, c.max_tracks - len(T))
            if len(free) > room:
                free = free[np.argsort(-kps.response[free], kind="stable")[:room]]
                free.sort()
            T.append(self._new_ids(len(free)), kps.xy[free], kps.brief[free])
        timer.lap("track")

        n_c1 = T.n_3d()
        c1_ids = set(T.track_id[T.point >= 0].tolist())
        matching = "none"
        est: PoseEstimate | None = None
        relocalized = False
        prepared = None
        if n_c1 > c.kappa2:
            est = self._estimate_from_table(pred, dt)
            timer.lap("pose")
            if est is not None:
                self._reverify(est.cam_from_world)
                pending = np.nonzero(T.pending & (T.point < 0) & (T.age >= 1))[0][: c.batch_max]
                if len(pending):
                    prepared = self.extractor.prepare(gray)
                    self._guided(prepared, pending, est.cam_from_world)
                    matching = "guided"
                    timer.lap("match")
        if est is None and pred is not None and c.prior_recovery and len(self.scope_points):
            prepared = prepared if prepared is not None else self.extractor.prepare(gray)
            est = self._recover(prepared, kps, pred)
            if est is not None:
                matching = "guided"
            timer.lap("reloc")  # the whole frame around the prediction: a relocalization
        if est is None:
            prepared = prepared if prepared is not None else self.extractor.prepare(gray)
            est = self._global(prepared, kps)
            matching = "global"
            relocalized = est is not None
            timer.lap("reloc")
        T = self.table  # recovery and global matching restart the table
        c2_ids = set(T.track_id[T.point >= 0].tolist())
        if len(c2_ids) > c.kappa2 and c2_ids != c1_ids and not relocalized:
            # The new matches were verified against this frame's pose: it is the better prior.
            est2 = self._estimate_from_table(est.cam_from_world if est is not None else pred, dt,
                                             pred_is_estimate=est is not None)
            if est2 is not None:
                est = est2
            timer.lap("pose")

        # A pose is a promise: judge it by its covariance before anyone relies on it.
        cov = None if est is None else _covariance(est, self.K, self.bundle, c)
        sd = np.inf if cov is None else _position_sd(cov) / self.bundle.scene_scale
        verified = est is not None and _verified(est, sd, c)
        timer.lap("pose")
        message = ""
        recent = self.last_posed_stamp is not None and stamp - self.last_posed_stamp <= c.max_frame_gap_s
        if est is not None and relocalized and not verified and pred is not None and recent:
            dpos = np.linalg.norm(est.cam_from_world.center - pred.center) / self.bundle.scene_scale
            drot = rotation_angle_deg(est.cam_from_world.rotation, pred.rotation)
            if dpos > c.contradiction_position or drot > c.contradiction_deg:
                # weak and against the motion: not adopted; the next frame relocalizes again
                message = (f"weak relocalization ({est.num_inliers} inliers) {dpos:.2f} scene scales / "
                           f"{drot:.0f} deg from the motion prediction: rejected")
                T.point[:] = -1
                T.pending[:] = True
                est, cov = None, None

        # KALMAN-FILTER-UPDATE
        filtered = None
        if est is not None:
            self.last_posed_stamp = stamp
            self.scope_points = T.point[T.point >= 0].copy()
            if relocalized or not self.filter.initialized:
                keep = c.max_frame_gap_s if c.relocalize_keeps_motion else 0.0
                self.filter.reset(est.cam_from_world, stamp, keep,
                                  c.max_speed_scales_per_s * self.bundle.scene_scale, c.max_angular_speed_rad_s)
                filtered = est.cam_from_world
            else:
                filtered = self.filter.update(est.cam_from_world)
        timer.lap("filter")
        if est is None:
            status = Status.LOST
            message = message or "not enough 2D-3D matches for a pose"
        else:
            self.unverified = not verified if relocalized else self.unverified and not verified
            if sd > c.max_position_sd:
                # Too uncertain to promise: withheld (the tracker and filter still follow it).
                status = Status.LOST
                message = (f"pose withheld: centre sd {sd * 100:.1f}% of the scene scale "
                           f"(limit {c.max_position_sd * 100:.1f}%), {est.num_inliers} inliers")
            elif self.unverified:
                status = Status.UNVERIFIED
            else:
                status = Status.RELOCALIZED if relocalized else Status.TRACKING
        posed = status is not Status.LOST
        return FrameResult(
            status=status,
            stamp=stamp,
            cam_from_world=est.cam_from_world if posed else None,
            filtered_cam_from_world=filtered if posed else None,
            inliers=0 if est is None else est.num_inliers,
            detected=len(kps),
            tracked=eta,
            tracked_3d=T.n_3d(),
            matching=matching,
            timings_ms=timer.total(),
            message=message,
            covariance=cov if posed else None,
        )

    def _reverify(self, pose: Rigid3d) -> None:
        """Stored hypotheses of unmatched tracked keypoints, checked against the new pose."""
        T = self.table
        rows = np.nonzero((T.point < 0) & (T.hyp[:, 0] >= 0))[0]
        if len(rows) == 0:
            return
        out = T.point[rows].copy()
        verified = verify_hypotheses(
            T.hyp[rows], self._undistort(T.xy[rows]), self.bundle.points_xyz, pose, self.K,
            self.conf.guided_threshold_px, out,
        )
        T.point[rows] = out
        T.pending[rows[verified]] = False

    def _guided(self, prepared: np.ndarray, rows: np.ndarray, pose: Rigid3d) -> None:
        T = self.table
        desc = describe(self.extractor, self.bundle, prepared, T.xy[rows])
        gm = guided_matching(
            desc, self._undistort(T.xy[rows]), self.bundle, T.point[T.point >= 0], pose, self.K, self.conf
        )
        T.point[rows] = gm.point
        T.hyp[rows] = gm.hyp
        T.pending[rows] = False

    def _restart_table(self, kps: Keypoints) -> TrackTable:
        """A fresh track table from the frame's strongest keypoints (after tracking failed)."""
        c = self.conf
        sel = np.arange(len(kps))
        if len(sel) > c.global_max_keypoints:
            sel = np.sort(np.argsort(-kps.response, kind="stable")[: c.global_max_keypoints])
        T = TrackTable.empty(c.max_hypotheses)
        T.append(self._new_ids(len(sel)), kps.xy[sel], kps.brief[sel])
        T.pending[:] = False
        return T

    def _recover(self, prepared: np.ndarray, kps: Keypoints, pred: Rigid3d) -> PoseEstimate | None:
        """Tracking lost its 2D-3D matches but the motion filter still predicts the pose:
        guided matching of all the frame's keypoints, scoped by the images that saw the last
        matched points, and a pose from the hypotheses around the prediction (two passes, see
        ``_pose_from_hypotheses``). Much cheaper than global matching, the fallback."""
        c = self.conf
        T = self._restart_table(kps)
        if len(T) < c.min_inliers:
            return None
        xy_u = self._undistort(T.xy)
        desc = describe(self.extractor, self.bundle, prepared, T.xy)
        loose = c.model_copy(update={"guided_threshold_px": c.prior_threshold_px})
        gm = guided_matching(desc, xy_u, self.bundle, self.scope_points, pred, self.K, loose)
        res = _pose_from_hypotheses(gm.hyp, xy_u, self.bundle, self.K, c, pred)
        if res is None:
            return None
        est, point = res
        T.hyp = gm.hyp
        T.point = point
        T.pending = T.point < 0
        self.table = T
        self._reverify(est.cam_from_world)
        return est

    def _global(self, prepared: np.ndarray, kps: Keypoints) -> PoseEstimate | None:
        """GLOBAL-MATCHING on the frame's keypoints; the track table restarts from them."""
        c = self.conf
        T = self._restart_table(kps)
        self.table = T
        if len(T) < c.min_inliers:
            return None
        xy_u = self._undistort(T.xy)
        desc = describe(self.extractor, self.bundle, prepared, T.xy)
        res = _pose_from_global(desc, xy_u, self.bundle, self.K, c)
        if res is None:
            return None
        est, q, p, hyp = res
        T.hyp = hyp
        T.point[q] = p
        # Keypoints the global search could not match stay pending: guided matching, scoped by
        # the new pose, gets another try at them over the next frames.
        T.pending = T.point < 0
        return est


def _covariance(est: PoseEstimate, K: np.ndarray, bundle: MapBundle, conf: EngineConf) -> np.ndarray:
    """The pose's 6x6 covariance from its final refinement's inliers (``pose_covariance``),
    with the map points' own uncertainty (``point_uncertainty``) unless switched off."""
    if est.inlier_xy is None or est.inlier_X is None:
        return np.full((6, 6), np.inf)
    extra = None
    if conf.map_noise_px > 0:
        z = est.inlier_X @ est.cam_from_world.rotation[2] + est.cam_from_world.translation[2]
        extra = PointUncertainty.for_bundle(bundle).sigma_px(est.inlier_X, z, conf.map_noise_px)
    return pose_covariance(est.cam_from_world, K, est.inlier_xy, est.inlier_X, point_sigma_px=extra)


def _verified(est: PoseEstimate, sd: float, conf: EngineConf) -> bool:
    """The strict test: certain enough (centre sd, a fraction of the scene scale) on enough
    inliers."""
    return sd <= conf.verified_position_sd and est.num_inliers >= conf.verified_min_inliers


def _position_sd(cov: np.ndarray) -> float:
    """Standard deviation of the camera centre in its worst direction (map units)."""
    if not np.all(np.isfinite(cov)):
        return float("inf")
    return float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0)))


def _pose_from_global(
    desc: np.ndarray, xy_u: np.ndarray, bundle: MapBundle, K: np.ndarray, conf: EngineConf
) -> tuple[PoseEstimate, np.ndarray, np.ndarray, np.ndarray] | None:
    """Global matching + one-to-many RANSAC: (pose, inlier keypoints, their points, hypotheses)."""
    gm = global_matching(desc, bundle, conf)
    if len(gm.set1_q) < 3:
        return None
    H = conf.max_hypotheses
    hyp = np.full((len(desc), H), -1, np.int64)
    if len(gm.set2_q):
        rank = np.arange(len(gm.set2_q)) - np.searchsorted(gm.set2_q, gm.set2_q)
        hyp[gm.set2_q, rank] = gm.set2_p
    X = bundle.points_xyz
    res = estimate_pose_one_to_many(
        xy_u[gm.set1_q], X[gm.set1_p], gm.set2_q, xy_u[gm.set2_q], X[gm.set2_p], K, conf.ransac()
    )
    if res is None:
        return None
    est, chosen = res
    if conf.global_verify:
        # Guided matching of the whole frame around the RANSAC pose (scope: the map points it
        # makes visible). A right pose gathers the matches the ratio test dropped; a chance one
        # does not reach ``recover_min_inliers``. See ``EngineConf.global_verify``.
        ver = _match_near_prior(desc, xy_u, bundle, K, conf, est.cam_from_world)
        if ver is not None:
            vest, point = ver
            if vest.num_inliers >= est.num_inliers:
                q = np.nonzero(point >= 0)[0]
                return vest, q, point[q], hyp
            # Confirmed, and the RANSAC pose has the more inliers (the narrower covariance).
            return est, gm.set2_q[chosen], gm.set2_p[chosen], hyp
    # Among hundreds of candidate matches, ten that agree can be chance: demand a fraction too.
    if est.num_inliers < conf.global_min_inlier_ratio * len(gm.set1_q):
        return None
    return est, gm.set2_q[chosen], gm.set2_p[chosen], hyp


def relocalize(
    image: np.ndarray,
    camera: Camera,
    bundle: MapBundle,
    conf: EngineConf | None = None,
    prior: Rigid3d | None = None,
) -> FrameResult:
    """Localize a single image from scratch (stateless). With a ``prior`` (cam_from_world),
    the search is scoped to the database images that see the points the prior sees, and
    matches are verified against it, as in guided matching; without a pose from the scoped
    search it falls back to global matching."""
    conf = conf or EngineConf()
    timer = StageTimer()
    gray = to_gray(image, camera)
    # A fine image is described at about the map's resolution (see ``Localizer``); the pose
    # does not depend on the scaling of the intrinsics.
    scale = _working_scale(camera, bundle, conf)
    if scale != 1.0:
        gray, camera = to_working(gray, scale), camera.scaled(scale)
    corners = detect_corners(
        gray, rel_threshold=conf.gamma, max_corners=conf.global_max_keypoints, border=conf.mu // 2,
        subpixel=map_subpixel(conf, bundle.manifest.params),
    )
    timer.lap("detect")
    result = FrameResult(Status.LOST, 0.0, detected=len(corners), matching="global")
    if len(corners) < conf.min_inliers:
        result.timings_ms = timer.total()
        result.message = f"only {len(corners)} keypoints in the image"
        return result
    extractor = DaisyExtractor()
    prepared = extractor.prepare(gray)
    xy_u = camera.undistort_points(corners.xy) if camera.is_distorted else corners.xy
    desc = describe(extractor, bundle, prepared, corners.xy)
    K = camera.K
    est = None
    if prior is not None:
        est = _pose_near_prior(desc, xy_u, bundle, K, conf, prior)
    if est is None:
        res = _pose_from_global(desc, xy_u, bundle, K, conf)
        est = None if res is None else res[0]
    timer.lap("reloc")
    if est is not None:
        cov = _covariance(est, K, bundle, conf)
        sd = _position_sd(cov) / bundle.scene_scale
        timer.lap("pose")
        result.inliers = est.num_inliers
        if sd > conf.max_position_sd:
            result.message = (f"pose withheld: centre sd {sd * 100:.1f}% of the scene scale "
                              f"(limit {conf.max_position_sd * 100:.1f}%), {est.num_inliers} inliers")
        else:
            # a single image has no next frame to confirm it: only the strict test verifies
            result.status = Status.RELOCALIZED if _verified(est, sd, conf) else Status.UNVERIFIED
            result.cam_from_world = est.cam_from_world
            result.covariance = cov
    else:
        result.message = "no pose: too few consistent 2D-3D matches"
    result.timings_ms = timer.total()
    return result


def _pose_from_hypotheses(
    hyp: np.ndarray, xy_u: np.ndarray, bundle: MapBundle, K: np.ndarray, conf: EngineConf, prior: Rigid3d
) -> tuple[PoseEstimate, np.ndarray] | None:
    """A pose from one-to-many hypotheses around an approximate ``prior``, in two passes:
    verification within ``prior_threshold_px`` of the prior and a first pose, then every
    keypoint's hypotheses re-verified against that pose within ``guided_threshold_px`` and the
    pose re-estimated (wrong matches that fit the loose window drop out). Returns the pose and
    the verified point of every keypoint (-1: none)."""
    params = conf.ransac(conf.recover_min_inliers)
    est, point = None, None
    for threshold in (conf.prior_threshold_px, conf.guided_threshold_px):
        cur = np.full(len(hyp), -1, np.int64)
        verify_hypotheses(hyp, xy_u, bundle.points_xyz, prior, K, threshold, cur)
        q = np.nonzero(cur >= 0)[0]
        if len(q) < params.min_inliers:
            break
        nxt = estimate_pose(xy_u[q], bundle.points_xyz[cur[q]], K, params, prior=prior)
        if nxt is None:
            break
        est, prior = nxt, nxt.cam_from_world
        point = np.full(len(hyp), -1, np.int64)
        point[q[nxt.inlier_mask]] = cur[q[nxt.inlier_mask]]
    return None if est is None else (est, point)


def _pose_near_prior(desc, xy_u, bundle: MapBundle, K, conf: EngineConf, prior: Rigid3d) -> PoseEstimate | None:
    """Matches scoped by the points visible from the prior, verified against it with a loose
    threshold (the prior is approximate), then a pose with the prior as a hypothesis; the same
    rules as the tracker's recovery (``prior_threshold_px``, ``recover_min_inliers``)."""
    res = _match_near_prior(desc, xy_u, bundle, K, conf, prior)
    return None if res is None else res[0]


def _match_near_prior(
    desc: np.ndarray, xy_u: np.ndarray, bundle: MapBundle, K: np.ndarray, conf: EngineConf, prior: Rigid3d
) -> tuple[PoseEstimate, np.ndarray] | None:
    """``_pose_near_prior``'s pose and the verified point of every keypoint (-1: none)."""
    uv, z = project(prior, K, bundle.points_xyz)
    w, h = 2 * K[0, 2], 2 * K[1, 2]
    visible = np.nonzero((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h))[0]
    if len(visible) < conf.min_inliers:
        return None
    loose = conf.model_copy(update={"guided_threshold_px": conf.prior_threshold_px})
    gm = guided_matching(desc, xy_u, bundle, visible, prior, K, loose)
    return _pose_from_hypotheses(gm.hyp, xy_u, bundle, K, conf, prior)
