"""Algorithm 1 of the paper, LOCALIZE-FRAME(f, T, M), for one camera.

Per frame, ``Localizer.localize`` runs these steps (each a method that takes what it needs,
the track table T included, and returns what it produces)::

    KALMAN-FILTER-PREDICT                       _kalman_filter_predict
    K   <- EXTRACT-KEYPOINTS(f)                 _extract_keypoints: Harris (gamma * previous max)
                                                + BRIEF
    eta <- TRACK-2D(f, K, T)                    _track_2d: windows around predicted positions
    if eta < kappa1: ADD-GOOD-FEATURES(f, K, T) _add_good_features: pending keypoints where none
                                                are tracked
    C1  <- FETCH-2D-3D-MATCHES-FROM-TABLE(T)    _match_ids
    if |C1| > kappa2:
        P <- ESTIMATE-POSE(C1)                  _estimate_pose: P3P RANSAC + LM refinement
        if MATCHES-PENDING(T):                  _reverify, _pending_batch
            GUIDED-MATCHING(f, T, P, M)         _guided_matching: one batch of 100-150
    else:
        GLOBAL-MATCHING(f, T, M)                _global_matching: relocalize
    C2  <- FETCH-2D-3D-MATCHES-FROM-TABLE(T)
    if |C2| > kappa2 and C1 != C2: P <- ESTIMATE-POSE(C2)
    KALMAN-FILTER-UPDATE(P)                     _kalman_filter_update

Details the paper leaves open, decided here: when the pose from C1 fails (fewer than
``min_inliers`` inliers), its matches are discarded and the frame relocalizes at once (the
paper's rule "relocalize when fewer than kappa2 matches remain", applied after the failure),
first by guided matching around the motion prediction (``_recover``), then globally; matches
that are outliers to the frame's pose lose their 3D point and become pending again; stored
one-to-many hypotheses of tracked keypoints are re-verified against every new pose; and a pose
is judged by its covariance (``certainty``) before it is published (``_status``).

The track table is state across frames: ``localize`` reads ``self.table`` once, the previous
frame's, and TRACK-2D makes this frame's table from it (a new object: the previous one is never
modified). Later steps may fill in or replace this frame's table and return the one they
produced; ``localize`` stores it back once, at the end.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

from ..cameras import Camera, as_camera
from ..features.daisy import DaisyExtractor
from ..map.bundle import MapBundle
from ..transforms import Rigid3d, rotation_angle_deg
from .certainty import (
    Certainty,
    certainty,
    is_verified,
    position_sd,
    relocalization_certainty,
    rests_on_few,
    verified_without_one,
    with_disagreement,
    withheld,
)
from .config import EngineConf
from .frame import to_gray, to_working
from .matching import guided_matching, search_all, verify_hypotheses
from .motion_filter import make_pose_filter
from .point_uncertainty import PointUncertainty
from .pose import PoseEstimate, RansacParams, estimate_pose, final_refinement
from .projected import ScopePoints, projected_matches, refine_with_projections, unmatched_only
from .relocalize import (
    describe,
    global_pose,
    map_working_scale,
    pose_from_hypotheses,
    visible_points,
)
from .scope import image_weights, median_track_length
from .session_points import SessionPoints, odometry_covariance
from .timing import StageTimer
from .track_table import TrackTable
from .tracker import (
    Keypoints,
    edge_keypoints,
    extract_keypoints,
    free_candidates,
    map_subpixel,
    track_2d,
    with_keypoints,
)
from .types import FrameResult, Matching, Status

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Prediction:
    """KALMAN-FILTER-PREDICT's output for a frame."""

    cam_from_world: Rigid3d | None  # the predicted pose (None: no motion known yet)
    dt: float  # seconds since the previous frame (0 on the first)


class _FrameImage:
    """A frame at the working scale, and its DAISY preparation, made on first use (only
    frames that describe keypoints pay for it)."""

    def __init__(self, gray: np.ndarray, extractor: DaisyExtractor) -> None:
        self.gray = gray
        self._extractor = extractor
        self._prepared: np.ndarray | None = None
        self._described: tuple[np.ndarray, np.ndarray] | None = None
        self._searched: tuple[np.ndarray, tuple[np.ndarray, np.ndarray]] | None = None

    @property
    def prepared(self) -> np.ndarray:
        if self._prepared is None:
            self._prepared = self._extractor.prepare(self.gray)
        return self._prepared

    def describe_all(self, bundle: MapBundle, xy: np.ndarray) -> np.ndarray:
        """``describe`` of the frame's keypoints ``xy``, once: a recovery that fails is followed
        by global matching of the same keypoints (a second DAISY pass was ~10 ms)."""
        if self._described is None or not np.array_equal(self._described[0], xy):
            self._described = (xy.copy(), describe(self._extractor, bundle, self.prepared, xy))
        return self._described[1]

    def search_all(
        self, bundle: MapBundle, conf: EngineConf, xy: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The k-ANN search over the whole map of those keypoints' descriptors, once: recovery
        restricts it to its scope and global matching uses it as is (``recovery_search``)."""
        desc = self.describe_all(bundle, xy)
        if self._searched is None or self._searched[0] is not desc:
            self._searched = (desc, search_all(desc, bundle, conf))
        return self._searched[1]


def _match_ids(table: TrackTable) -> np.ndarray:
    """FETCH-2D-3D-MATCHES-FROM-TABLE, as the track ids of the verified matches (C1, C2),
    sorted (a table's track ids are distinct: equal arrays are equal sets; a Python set of
    them cost 3x, 2-3 times a frame)."""
    return np.sort(table.track_id[table.point >= 0])


def _median_rows(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=0)`` of a finite (N, 2) array, N > 0, by one partition (the same
    numbers: the middle element, or the mean of the middle two; np.median's checks and
    dispatch cost 4x the partition, once a frame)."""
    n = len(a)
    k = n // 2
    if n % 2:
        return np.partition(a, k, axis=0)[k]
    part = np.partition(a, (k - 1, k), axis=0)
    return (part[k - 1] + part[k]) / 2


def _keep_track_ids(table: TrackTable, tracked: TrackTable) -> None:
    """Rows of ``table`` (restarted from this frame's keypoints) at the position of a row of
    ``tracked`` (this frame's tracked table: its rows sit on the same keypoints) take that
    row's track id and age."""
    if len(table) == 0 or len(tracked) == 0:
        return
    at = {(float(x), float(y)): i for i, (x, y) in enumerate(tracked.xy)}
    for r, (x, y) in enumerate(table.xy):
        i = at.get((float(x), float(y)))
        if i is not None:
            table.track_id[r] = tracked.track_id[i]
            table.age[r] = tracked.age[i]


def _unmatch(table: TrackTable, rows: np.ndarray | slice) -> None:
    """The rows lose their 3D point and become pending for guided matching again."""
    table.point[rows] = -1
    table.pending[rows] = True


def _status(
    est: PoseEstimate | None,
    cert: Certainty | None,
    relocalized: bool,
    message: str,
    unverified: bool,
    conf: EngineConf,
    rests_on: Callable[[], str | None] | None = None,
) -> tuple[Status, str, bool]:
    """The frame's status and message, and whether tracking now continues from an unverified
    relocalization (``unverified``: it did before this frame): the frames tracked from one
    are UNVERIFIED until one passes the strict test. ``rests_on``: why the pose rests on a
    few matches (``Localizer._rests_on_few``), asked of a tracked UNVERIFIED pose."""
    if est is None or cert is None:
        return Status.LOST, message or "not enough 2D-3D matches for a pose", unverified
    if relocalized:
        unverified = not cert.verified
    else:
        unverified = unverified and not cert.verified
    why = withheld(cert.position_sd, est.num_inliers, conf)
    if why is not None:
        # Too uncertain to promise: withheld (the tracker and filter still follow it).
        return Status.LOST, why, unverified
    if unverified and est.num_inliers < conf.unverified_min_inliers:
        # A consistent set of wrong matches passes the covariance test: few inliers, no check.
        why = (
            f"pose withheld: unverified on {est.num_inliers} inliers "
            f"(fewer than {conf.unverified_min_inliers})"
        )
        return Status.LOST, why, unverified
    if unverified and not relocalized and rests_on is not None:
        # Tracked on from an unverified (or withheld) relocalization: its tracks carry the
        # same matches, no independent check of them (robust density-6x, a session reset
        # every 10 frames: a withheld relocalization 50-80% of the scene scale off, followed,
        # gathered guided matches around itself and was published UNVERIFIED 46-80% off
        # with sd 1.4-1.8%, 13-16% without its 2 most influential points).
        why = rests_on()
        if why is not None:
            return Status.LOST, why, unverified
    if unverified:
        return Status.UNVERIFIED, message, unverified
    return (Status.RELOCALIZED if relocalized else Status.TRACKING), message, unverified


def prepare(bundle: MapBundle, conf: EngineConf) -> None:
    """The per-bundle tables a tracked frame reads (cached per bundle), computed now, at
    load, rather than by the first frame: the points' triangulation uncertainty (the
    covariance) and the scope's image weights. On redkitchen from every frame (70,534
    points, 1.03 M observations) the point uncertainty took 0.5 s of the first frame's CPU
    (the every-10th map: 0.03 s), 0.47 ms of its 1,000-frame mean."""
    if conf.map_noise_px > 0:
        PointUncertainty.for_bundle(bundle)
    if conf.scope_radius > 0:
        image_weights(bundle, conf.scope_radius, conf.scope_min_duplicates)


class Localizer:
    """Per-client localization state: track table, Kalman filter, adaptive threshold.

    ``localize(frame, stamp)`` processes one video frame (uint8 gray or BGR of the camera's
    size; ``stamp`` in seconds) and returns a ``FrameResult``. Not thread-safe: one frame at a
    time per instance. The bundle is shared read-only between instances.

    Frames finer than the map (``working_scale``) are downscaled once on arrival: ``camera``
    is the working camera every pixel quantity refers to, ``input_camera`` the caller's.
    Poses are the same for both (scaling the intrinsics does not move the camera).
    """

    def __init__(
        self, bundle: MapBundle, camera: Camera | str | Path, conf: EngineConf | None = None
    ) -> None:
        """``camera``: a ``Camera``, a ``camera.json`` path or ``"MODEL w h params..."``."""
        camera = as_camera(camera)
        self.bundle = bundle
        self.conf = conf or EngineConf()
        self.input_camera = camera
        self.scale = map_working_scale(camera, bundle, self.conf)
        self.camera = camera if self.scale == 1.0 else camera.scaled(self.scale)
        self._ransac_of: EngineConf | None = None  # the configuration of _ransac_params
        self._ransac_params = self.conf.ransac()
        self.K = self.camera.K
        # (``Camera.is_distorted`` builds the distortion coefficients: ~5 calls a frame)
        self._distorted = self.camera.is_distorted
        self._cell_scale = 4.0 / np.array([self.camera.width, self.camera.height], np.float64)
        self.subpixel = map_subpixel(self.conf, bundle.manifest.params)
        self.extractor = DaisyExtractor()
        self._scope_points = ScopePoints(self.conf.projected_top_images)
        # Called (no arguments) when a frame found no pose by tracking and is about to be
        # matched globally against the whole bundle (its costliest step, ~200 ms CPU when the
        # bundle does not hold the frame): a sub-map session starts loading the parts the
        # frame's place-recognition vote prefers then, so they are resident by the time its
        # search needs them (``engine/submaps.py``). None: nothing.
        self.before_global_matching: Callable[[], None] | None = None
        prepare(bundle, self.conf)
        c = self.conf
        # (scope_nprobe: on maps whose points are seen by enough images, None elsewhere)
        self.scope_nprobe: int | None = None
        if c.scope_nprobe > 0 and median_track_length(bundle) >= c.scope_nprobe_min_track:
            self.scope_nprobe = c.scope_nprobe
        self.spread_batches = median_track_length(bundle) >= c.batch_spread_min_track
        self.session = SessionPoints(
            self.K,
            bundle.scene_scale,
            c.odometry_min_parallax_deg,
            c.odometry_max_reprojection_px,
            c.odometry_max_depth_scales,
            c.odometry_noise_px,
            c.odometry_window,
            # the camera's own function, not ``self._undistort``: a bound method would make a
            # reference cycle (localizer -> session -> localizer) that keeps a replaced map's
            # bundle, and its mapped index, alive until the cyclic GC happens to run
            self.camera.undistort_points if self._distorted else None,
        )
        self.reset()

    def reset(self) -> None:
        """Forget tracks and motion: the next frame relocalizes."""
        c = self.conf
        self.table = TrackTable.empty(c.max_hypotheses)
        self.session.reset()  # session points are the tracks': they go with them
        self.filter = make_pose_filter(
            c.motion_model,
            c.accel_noise_scales_per_s2,
            c.angular_accel_noise_rad_s2,
            c.position_noise_scales,
            c.orientation_noise_rad,
            self.bundle.scene_scale,
        )
        self.prev_max_response: float | None = None
        self.next_track_id = 0
        self.last_stamp: float | None = None
        self.frames = 0
        self.scope_points = np.zeros(0, np.int64)  # 3D points matched in the last posed frame
        self.unverified = False  # tracking from a relocalization not verified yet
        self.last_posed_stamp: float | None = None
        self.last_inliers = 0  # of the last posed frame
        self.guided_yield = 0.0  # running share of guided matching's queries matched
        self.loss_3d = 0.0  # running 3D matches lost per tracked frame (_note_3d_loss)
        self.last_pose: Rigid3d | None = None  # cam_from_world of the last posed frame
        self.interval = 0.0  # seconds from the frame before the last to the last
        self.last_interval = 0.0  # the same one frame earlier
        self.motion_published = False  # the last posed frame's pose was published (not withheld)
        # this frame's pose and covariance as judged (published or withheld), None without one
        self.judged: tuple[PoseEstimate, np.ndarray] | None = None
        self._odo_map_inliers = 0  # map inliers of the last odometry pose
        self._odo_outliers = np.zeros(0, np.int64)  # its table rows of map-match outliers
        self._odo_why = ""  # why this frame's odometry pose was no pose (or "")

    def swap_bundle(
        self, bundle: MapBundle, point_rows: Callable[[np.ndarray], np.ndarray]
    ) -> None:
        """Run on ``bundle``, another part of the same map, from the next frame on (a sub-map
        switch, ``engine/submaps.py``), keeping tracks and motion: ``point_rows`` maps point
        rows of the current bundle to rows of ``bundle`` (-1 where it lacks the point, and for
        -1). Matches to points the new bundle holds stay matches, the others become pending
        (guided matching tries them again there). Nothing keeps the old bundle referenced:
        its mapped pages would stay resident beyond a sub-map budget."""
        t = self.table
        new_point = point_rows(t.point)
        t.pending = t.pending | ((t.point >= 0) & (new_point < 0))
        t.point = new_point
        t.hyp = point_rows(t.hyp)
        sp = point_rows(self.scope_points)
        self.scope_points = sp[sp >= 0]
        self.bundle = bundle
        self._scope_points = ScopePoints(self.conf.projected_top_images)  # held the old bundle

    def detach_bundle(self) -> None:
        """Let the bundle go before the next ``swap_bundle`` (which does not read the old
        one): a sub-map session whose budget holds one part drops its part before the next
        one loads, since the kernel keeps a part's pages resident while anything maps it
        (``engine/submaps.py``). The localizer must not run until ``swap_bundle``."""
        self.bundle = None  # type: ignore[assignment]
        self._scope_points = ScopePoints(self.conf.projected_top_images)

    # ------------------------------------------------------------------ algorithm 1
    def localize(
        self, frame: np.ndarray, stamp: float, prior: Rigid3d | None = None
    ) -> FrameResult:
        """LOCALIZE-FRAME(f, T, M): one frame through the steps of Algorithm 1 (module
        docstring). ``prior``: an outside estimate of the frame's ``cam_from_world`` (the
        client's last pose from another server after a failover, GPS/IMU), used only when the
        engine has no motion prediction of its own (first frame, after a loss): the prior
        recovery around it is tried before global matching, and a pose found so counts as a
        relocalization (judged, and reported, like one)."""
        c = self.conf
        timer = StageTimer()
        gray = to_gray(frame, self.input_camera)
        if self._stale(stamp):
            self.reset()  # a long gap (or time going back): motion and tracks are stale
        pred = self._kalman_filter_predict(stamp)
        prev = self.table  # the previous frame's track table, read once
        self._odo_why = ""
        timer.lap("filter")

        image = _FrameImage(to_working(gray, self.scale), self.extractor)
        kp_threshold = self.prev_max_response  # this frame's detection threshold's basis
        kps = self._extract_keypoints(image.gray, kp_threshold)
        if kps.max_response > 0:
            self.prev_max_response = kps.max_response
        timer.lap("detect")

        table, used = self._track_2d(prev, kps, pred.cam_from_world, pred.dt)
        eta = len(table)
        if eta < c.kappa1 or table.n_3d() < c.refill_3d or self._uncovered(table, kps, used):
            table = self._add_good_features(table, kps, used)
        timer.lap("track")

        c1 = _match_ids(table)
        matching = Matching.NONE
        est: PoseEstimate | None = None
        unrefined = False  # est is the first estimate, before its robust final refinement
        relocalized = False
        ambiguous = ""  # why the frame's tracked poses were not trusted
        weak = False  # the tracked pose explains too few of its tracked matches
        from_recovery = False  # est was recovered around the prediction (tracking found none)
        global_unverified = False  # this frame's global matching ran and verified no pose
        if len(c1) > c.kappa2:
            # Without the robust final refinement where the frame holds many matches: the
            # second estimate below is that refinement, on the matches this pose then
            # verifies as well (``first_unrefined_from``).
            final = c.first_unrefined_from <= 0 or len(c1) < c.first_unrefined_from
            table, est = self._estimate_pose(table, pred.cam_from_world, pred.dt, final=final)
            timer.lap("pose")
            if self._doubtful(pred, est):
                table, est, eta, ambiguous = self._second_start(
                    prev, kps, table, est, eta, pred.dt, final
                )
                c1 = _match_ids(table)
                timer.lap("pose")
            unrefined = est is not None and not final and c.refine_loss_scale_px > 0
            weak = est is not None and est.num_inliers < c.track_consensus * len(c1)
            if est is not None:
                table = self._reverify(table, est.cam_from_world)
                self._note_3d_loss(prev.n_3d() - table.n_3d())
                batch = self._pending_batch(table)
                if len(batch):
                    table = self._guided_matching(table, batch, image, est.cam_from_world)
                    matching = Matching.GUIDED
                    timer.lap("match")
        # the tracked table (before a recovery or relocalization restarts it): its tracks
        # carry the session points visual odometry poses a frame on
        tracked_table = table
        odo_cert: Certainty | None = None  # the odometry pose's certainty, when it has one
        loo_cert: Certainty | None = None  # a suspect pose's, judged without its one match
        if est is None and not ambiguous and self._odometry_ready():
            # Tracking found no map pose after a published one: odometry on the session points
            # first (the recovery's and global matching's poses on a thin map are the ones
            # that go wrong, and they cost 10-100x more), kept when publishable.
            vo = self._odometry(table, pred)
            timer.lap("pose")
            if vo is not None and withheld(vo[1].position_sd, vo[0].num_inliers, c) is None:
                table, est, back, matching = self._adopt_odometry(kps, image, vo[0], table)
                odo_cert = vo[1] if back is None else None  # a map pose again: judged below
                timer.lap("match")
        # (not around a prediction the frame contradicts: global matching decides)
        can_recover = c.prior_recovery and len(self.scope_points) > 0 and not ambiguous
        if est is None and pred.cam_from_world is not None and can_recover:
            recovered = (
                None
                if self._recovery_fails(kps, image, pred.cam_from_world)
                else self._recover(kps, image, pred.cam_from_world, self.scope_points)
            )
            if recovered is not None:
                table, est = recovered
                matching = Matching.GUIDED
                from_recovery = True
            timer.lap("reloc")  # the whole frame around the prediction: a relocalization
        elif est is None and pred.cam_from_world is None and prior is not None:
            if c.prior_recovery and prior.is_finite():
                near = visible_points(self.camera, prior, self.bundle.points_xyz)
                recovered = self._recover(kps, image, prior, near) if len(near) else None
                if recovered is not None:
                    table, est = recovered
                    matching, relocalized = Matching.GUIDED, True
            timer.lap("reloc")
        lost_why = ambiguous  # why the frame has no pose, when it has none
        if est is None:
            if self.before_global_matching is not None:
                self.before_global_matching()
            table, est, why = self._global_matching(kps, image)
            matching = Matching.GLOBAL
            relocalized = est is not None
            lost_why = lost_why or why
            timer.lap("reloc")
        c2 = _match_ids(table)
        odo = odo_cert is not None  # (an odometry pose: tracking gave none, so not unrefined)
        new_matches = len(c2) > c.kappa2 and not np.array_equal(c2, c1) and not relocalized
        if (new_matches and not odo) or unrefined:
            # The new matches were verified against this frame's pose: it is the better prior.
            # The first estimate stopped before its robust final refinement: this is it, on
            # C2 (issue 10: one Cauchy refinement per frame fewer; on redkitchen C2 differs
            # from C1 on 995 of 999 tracked frames, so the second estimate ran anyway).
            own = est is not None
            prior = est.cam_from_world if est is not None else pred.cam_from_world
            table, est2 = self._estimate_pose(table, prior, pred.dt, prior_is_estimate=own)
            if est2 is not None:
                est = est2
            elif unrefined and est is not None:
                est = self._refined(est)
            timer.lap("pose")

        # A pose is a promise: judge it by its covariance before anyone relies on it.
        cert = odo_cert if odo else None if est is None else certainty(est, self.K, self.bundle, c)
        if relocalized and est is not None and cert is not None:
            # (no earlier frame checked a relocalization's matches: its strict test must not
            # rest on one map point, ``verified_without_one``)
            cert = verified_without_one(cert, est, self.K, self.bundle, c)
        timer.lap("pose")
        tracked = not (relocalized or odo)  # tracked on the map this frame
        if est is not None and cert is not None and tracked and c.densify_uncertain:
            uncertain = withheld(cert.position_sd, est.num_inliers, c) is not None
            # A pose resting on its most influential match (that one may be wrong and fitted)
            # or on a weak consensus of its tracked matches is replaced only by a re-matched
            # pose that passes the strict test: replaced by a merely more certain one,
            # redkitchen frame 466 (3.5% of the scene scale off -> 2.9%) restarted the tracks
            # and frame 468 came out 6.0% off (main: 2.0%).
            suspect = weak or withheld(cert.position_sd_loo, est.num_inliers, c) is not None
            if uncertain or suspect:
                # Only a pose about to be withheld is re-matched also from the prediction and
                # with the corners near the edge (it is lost otherwise): a suspect one's extra
                # re-match, more certain but not verified, only widens its covariance
                # (rematch_disagreement): redkitchen frame 466, a right pose 3.5% off, withheld.
                wider = (pred.cam_from_world, kp_threshold) if uncertain else None
                dense = self._densify(kps, image, est, cert, wider)
                unchecked_rule = c.suspect_leave_out and c.suspect_leave_out_unchecked
                if dense is not None and (uncertain or dense[2].verified):
                    table, est, cert = dense
                    matching = Matching.GUIDED
                    # The re-match of a pose too uncertain to publish, itself resting on its
                    # most influential match: nothing checked that one either (robust
                    # density-6x walk at 3 Hz, frame 191: 48 tracked inliers, sd 3.05%; its
                    # re-match 13.1% of the scene scale off on 63 with sd 2.36%, one wrong
                    # match 7 px off at the true pose; 19.3% without it). (One withheld
                    # anyway keeps its own sd and message.)
                    without_one = (
                        unchecked_rule
                        and not cert.verified
                        and withheld(cert.position_sd, est.num_inliers, c) is None
                    )
                elif dense is not None:
                    if c.rematch_disagreement:
                        # Not replaced, but the frame's own matches also place it elsewhere:
                        # the tracked pose is that uncertain at least (redkitchen --extend
                        # map, frame 466: TRACKING 17 cm off with sd 4.4 cm; its re-match
                        # 9.4 cm from it).
                        cert = with_disagreement(cert, est, dense[1], self.bundle, c)
                    # (suspect, not replaced: the re-match started from this pose and cannot
                    # check the match it rests on)
                    without_one = c.suspect_leave_out
                else:
                    # Suspect, and its re-match found no pose more certain than its own sd
                    # (the one in doubt) or none at all: that match is unchecked as when the
                    # re-match agrees (robust density-6x walk at 3 Hz, frame 213: 45 right
                    # tracked matches on a far patch put it 10% off; guided matching added one
                    # wrong match, 15 px off at the true pose, that fixed it 13.4% off at sd
                    # 1.61%, 13.5% without it; its re-match 11.7% off at sd 13.8%).
                    without_one = suspect and not uncertain and unchecked_rule
                if without_one:  # judged at its sd without its most influential match
                    judged = self._judged_without_one(cert)
                    if judged is not cert:
                        cert = loo_cert = judged
                timer.lap("match")
        message = lost_why if est is None else ""
        if est is None and self._odo_why:
            # (odometry had a pose and it was not kept: said first, then what else failed)
            message = f"{self._odo_why}; {message}" if message else self._odo_why
        if from_recovery and est is not None and cert is not None and cert.verified:
            if c.recovered_verified_check:
                # Recovered around the prediction and passing the strict test: guided matching
                # around a prediction turned onto a twin wall agrees on a wrong pose as
                # certain as a right one (``recovered_verified_check``). The frame's global
                # matching replaces it (its pose passes the strict test) or withholds it when
                # it places the frame elsewhere on at least its inliers.
                rivals: list[PoseEstimate] = []
                table_g, est_g, cert_g = self._verified_global(kps, image, rivals)
                why = self._rivalled(est, rivals if est_g is None else [est_g])
                if why and est_g is not None:
                    table, est, cert = table_g, est_g, cert_g
                    relocalized, matching = True, Matching.GLOBAL
                elif why:
                    _unmatch(table, slice(None))
                    est, cert, message = None, None, why
                global_unverified = est_g is None
                timer.lap("reloc")
        if est is not None and cert is not None and not (relocalized or odo or cert.verified):
            if est.num_inliers < self.conf.collapse_ratio * self.last_inliers:
                table, est, cert, message = self._verify_collapse(kps, image, est, table)
                if est is not None:
                    relocalized, matching = True, Matching.GLOBAL
                timer.lap("reloc")
            elif from_recovery and c.recovered_global_check:
                # Recovered around the prediction after tracking found no pose, and not
                # verified: this frame's global matching decides when it passes the strict
                # test (guided matching around a wrong prediction can agree on a wrong pose,
                # robust walk at 3 Hz: frame 130, 122 inliers 1.80 m off, 67% of the scene
                # scale; its global matching: the right pose on 404). Not verified by global
                # matching: withheld when a pose global matching found and did not keep
                # places the frame elsewhere on more inliers (``recovered_rivals``), else it
                # goes on to the checks below unchanged.
                rivals = []
                table_g, est_g, cert_g = self._verified_global(kps, image, rivals)
                if est_g is not None:
                    table, est, cert = table_g, est_g, cert_g
                    relocalized, matching = True, Matching.GLOBAL
                elif c.recovered_rivals and (why := self._rivalled(est, rivals)):
                    _unmatch(table, slice(None))
                    est, cert, message = None, None, why
                global_unverified = est_g is None
                timer.lap("reloc")
        if est is not None and cert is not None and not (relocalized or odo or cert.verified):
            message = self._other_solution(table, est, pred.cam_from_world)
            # (not when this frame's global matching already found no verified pose: the same
            # keypoints give the same answer)
            if message and c.ambiguity_relocalize and not global_unverified:
                # the matches do not decide between two poses: this frame's global matching
                # does, when it passes the strict test (as a collapsed pose is checked)
                table_g, est_g, cert_g = self._verified_global(kps, image)
                if est_g is not None:
                    table, est, cert, message = table_g, est_g, cert_g, ""
                    relocalized, matching = True, Matching.GLOBAL
                timer.lap("reloc")
            if message:
                # the matches do not decide between two poses: none; the next frame relocalizes
                _unmatch(table, slice(None))
                est, cert = None, None
            timer.lap("pose")
        if est is not None and cert is not None and relocalized:
            message = self._contradiction(est, cert, pred.cam_from_world, stamp)
            message = message or self._rests_on_few(est, cert) or ""
            if message:
                # weak and against the motion, or resting on a few matches: not adopted; the
                # next frame relocalizes again
                _unmatch(table, slice(None))
                est, cert = None, None

        if not odo and est is not None and cert is not None and self._odometry_ready():
            if withheld(cert.position_sd, est.num_inliers, c) is not None:
                # A map pose too uncertain to publish (thin map): odometry instead, when it is
                # more certain (its own status rules judge it below).
                vo = self._odometry(tracked_table, pred)
                timer.lap("pose")
                if vo is not None and vo[1].position_sd < cert.position_sd:
                    table, est, back, matching = self._adopt_odometry(
                        kps, image, vo[0], tracked_table
                    )
                    cert = vo[1] if back is None else back
                    relocalized, message = False, ""
                    timer.lap("match")

        if est is not None and cert is not None and not relocalized and c.projected_refine:
            est, cert = self._projected_refinement(est, cert, kps, table)
            timer.lap("pose")

        filtered = None
        if est is not None:
            filtered = self._kalman_filter_update(est.cam_from_world, relocalized, stamp)
            self.last_posed_stamp = stamp
            # (an odometry pose's map inliers: the collapse test compares map matches)
            self.last_inliers = (
                self._odo_map_inliers if matching is Matching.ODOMETRY else est.num_inliers
            )
            self.last_pose = est.cam_from_world
            self.scope_points = table.point[table.point >= 0]  # (a boolean index copies)
        timer.lap("filter")
        self.table = table  # the one place the track table is stored for the next frame

        # The pose and covariance the status rules judge, published or withheld (LOST): what
        # eval.calibration measures, withheld poses included.
        self.judged = (est, cert.covariance) if est is not None and cert is not None else None

        status, message, self.unverified = _status(
            est,
            cert,
            relocalized,
            message,
            self.unverified,
            c,
            # (an odometry pose's certainty is its own: session points, not map points)
            None
            if est is None or cert is None or matching is Matching.ODOMETRY
            else partial(self._rests_on_few, est, cert),
        )
        if status is Status.LOST and cert is not None and cert is loo_cert:
            # (the sd quoted is the one without that match: say so, and why)
            message += (
                "; judged without its most influential match, which the whole-frame re-match"
                " (started from this pose) could not check"
            )
        if est is not None:  # the motion filter now rests on this pose: published or withheld
            self.motion_published = status is not Status.LOST
        if c.odometry:
            self._session_points(table, est, cert, status, matching)
        pose = est.cam_from_world if est is not None and status is not Status.LOST else None
        return FrameResult(
            status=status,
            stamp=stamp,
            cam_from_world=pose,
            filtered_cam_from_world=filtered if pose is not None else None,
            inliers=0 if est is None else est.num_inliers,
            detected=len(kps),
            tracked=eta,
            tracked_3d=table.n_3d(),
            matching=matching,
            timings_ms=timer.total(),
            cpu_timings_ms=timer.cpu(),
            message=message,
            covariance=cert.covariance if pose is not None and cert is not None else None,
        )

    # ------------------------------------------------------------------ the steps
    def _stale(self, stamp: float) -> bool:
        """Whether the frame at ``stamp`` comes after too long a gap (or before the last)."""
        last = self.last_stamp
        return last is not None and (stamp - last > self.conf.max_frame_gap_s or stamp < last)

    def _kalman_filter_predict(self, stamp: float) -> Prediction:
        """KALMAN-FILTER-PREDICT: the pose expected at ``stamp`` (the filter and the clock
        move to ``stamp``)."""
        dt = 0.0 if self.last_stamp is None else stamp - self.last_stamp
        self.last_interval, self.interval = self.interval, dt
        pred = self.filter.predict(stamp)
        self.last_stamp = stamp
        self.frames += 1
        return Prediction(pred, dt)

    def _extract_keypoints(self, gray: np.ndarray, prev_max_response: float | None) -> Keypoints:
        """EXTRACT-KEYPOINTS: Harris above gamma times the previous frame's maximum response,
        with BRIEF."""
        return extract_keypoints(gray, self._threshold(prev_max_response), self.conf, self.subpixel)

    def _threshold(self, prev_max_response: float | None) -> float | None:
        """The Harris threshold of a frame: gamma times the previous frame's maximum response
        (None on the first frame: gamma times the frame's own)."""
        return self.conf.gamma * prev_max_response if prev_max_response else None

    def _track_2d(
        self, prev: TrackTable, kps: Keypoints, pred: Rigid3d | None, dt: float
    ) -> tuple[TrackTable, np.ndarray]:
        """TRACK-2D: this frame's table, the rows of ``prev`` tracked into ``kps`` (moved to
        their keypoint, BRIEF updated, one frame older), and the keypoint of each row;
        ``dt``: the frame interval (the window widens with it)."""
        m = track_2d(prev, self._predict_positions(prev, pred), kps, self.conf, dt)
        rows = np.flatnonzero(m >= 0)
        used = m[rows]
        # (take, not ``kps.xy[used]``: the same rows; numpy 2.4 gathers rows of an (M, 2) or
        # (M, 4) array by integer indexing at x3-8 take's CPU, issue 10)
        return prev.tracked(rows, kps.xy.take(used, 0), kps.brief.take(used, 0)), used

    def _uncovered(self, table: TrackTable, kps: Keypoints, used: np.ndarray) -> bool:
        """Whether the 3D matches cover fewer than ``refill_coverage`` of the image cells (a
        4x4 grid) that have keypoints: a pose from points bunched in one part of the image is
        poorly constrained, however many they are. ``table``: ``_track_2d``'s, each row on
        its keypoint ``kps[used[row]]``."""
        c = self.conf
        if c.refill_coverage <= 0 or len(kps) == 0:
            return False

        def cells(xy: np.ndarray) -> np.ndarray:
            ij = np.minimum(np.maximum((xy * self._cell_scale).astype(np.int64), 0), 3)
            return ij[:, 1] * 4 + ij[:, 0]

        # (a row's cell is its keypoint's: the row's position is the keypoint's, bit for bit)
        covered = int(
            np.count_nonzero(np.bincount(cells(kps.xy[used[table.point >= 0]]), minlength=16))
        )
        if covered >= c.refill_coverage * 16:
            # Enough whatever cells the keypoints have (16 at most; the product rounds
            # monotonically): the frame's ~650 keypoints' cells are not needed (issue 10)
            return False
        return covered < c.refill_coverage * int(
            np.count_nonzero(np.bincount(cells(kps.xy), minlength=16))
        )

    def _add_good_features(self, table: TrackTable, kps: Keypoints, used: np.ndarray) -> TrackTable:
        """ADD-GOOD-FEATURES: keypoints away from every tracked one join the table, pending,
        the strongest first while there is room."""
        c = self.conf
        free = free_candidates(table.xy, kps, used, c.add_min_distance_px)
        room = max(0, c.max_tracks - len(table))
        if len(free) > room:
            free = free[np.argsort(-kps.response[free], kind="stable")[:room]]
            free.sort()
        # (take: row gathers, as in ``_track_2d``)
        table.append(self._new_ids(len(free)), kps.xy.take(free, 0), kps.brief.take(free, 0))
        return table

    def _estimate_pose(
        self,
        table: TrackTable,
        prior: Rigid3d | None,
        dt: float,
        prior_is_estimate: bool = False,
        final: bool = True,
    ) -> tuple[TrackTable, PoseEstimate | None]:
        """ESTIMATE-POSE from the table's verified matches (None with at most kappa2 of
        them). Outliers to the pose lose their match; with no (plausible) pose, all do.
        ``prior_is_estimate``: the prior is this frame's own pose; ``final`` False: without
        the robust final refinement (see ``estimate_pose``)."""
        rows, pts = table.matches()
        if len(rows) <= self.conf.kappa2:
            return table, None
        c = self.conf
        # (the rows by ``take``: numpy 2.4's integer indexing of (n, 2) / (n, 3) arrays costs
        # x5-9 as much, 5-6 us a selection on ~150 matches; the same rows, an ndarray)
        est = estimate_pose(
            self._undistort(table.xy.take(rows, 0)),
            np.asarray(self.bundle.points_xyz).take(pts, 0),
            self.K,
            self._ransac(),
            prior=prior,
            prior_threshold=c.prior_threshold_px,
            prior_is_estimate=prior_is_estimate,
            final=final,
        )
        pose = None if est is None else est.cam_from_world
        if pose is not None and prior is not None and not self._plausible(pose, prior, dt):
            log.debug(
                "rejected a pose %.3g units / %.1f deg from the prediction",
                np.linalg.norm(pose.center - prior.center),
                rotation_angle_deg(pose.rotation, prior.rotation),
            )
            est = None
        if est is None:
            # The tracked matches are no longer consistent: drop them (relocalize).
            _unmatch(table, rows)
            return table, None
        _unmatch(table, rows[~est.inlier_mask])
        est.inlier_points = pts[est.inlier_mask]
        return table, est

    def _refined(self, est: PoseEstimate) -> PoseEstimate:
        """The robust final refinement of an estimate made without it, on its own inliers
        (when the second estimate that would have been it found no pose)."""
        assert est.inlier_xy is not None and est.inlier_X is not None
        own = replace(est, inlier_mask=np.ones(est.num_inliers, bool))
        out = final_refinement(own, self.K, est.inlier_xy, est.inlier_X, self._ransac())
        if out is None or out is own:
            return est
        if est.inlier_points is not None:
            out.inlier_points = est.inlier_points[out.inlier_mask]
        return out

    def _doubtful(self, pred: Prediction, est: PoseEstimate | None) -> bool:
        """Whether the frame's tracked pose may rest on a wrong motion prediction: the
        prediction extrapolates over a longer interval than the motion was measured on, or the
        tracked pose kept too few of the last posed frame's inliers (or failed)."""
        c = self.conf
        if c.second_start_dt_ratio <= 0 or self.last_pose is None or pred.cam_from_world is None:
            return False
        longer = self.last_interval > 0 and pred.dt > c.second_start_dt_ratio * self.last_interval
        dropped = est is None or est.num_inliers < c.second_start_inliers * self.last_inliers
        return longer or dropped

    def _second_start(
        self,
        prev: TrackTable,
        kps: Keypoints,
        table: TrackTable,
        est: PoseEstimate | None,
        eta: int,
        dt: float,
        final: bool = True,
    ) -> tuple[TrackTable, PoseEstimate | None, int, str]:
        """TRACK-2D and ESTIMATE-POSE once more, started from the last posed frame's pose
        instead of the prediction (no motion). A prediction that overshoots puts the tracking
        windows on wrong corners and seeds the pose in the wrong one of the two solutions that
        near-planar matches allow; its pose then explains fewer matches. The start whose pose
        has more inliers wins (the prediction's on a tie). Two poses farther apart than a
        wrong pose (``contradiction_position``, ``contradiction_deg``) on similar support
        (``second_start_tie``) are no pose: the frame cannot tell which is right.
        ``final``: as the first estimate (with its robust final refinement or without).
        Returns the table, pose and tracked count chosen, and why there is no pose."""
        assert self.last_pose is not None
        c = self.conf
        table_b, used = self._track_2d(prev, kps, self.last_pose, dt)
        eta_b = len(table_b)
        if eta_b < c.kappa1 or table_b.n_3d() < c.refill_3d or self._uncovered(table_b, kps, used):
            table_b = self._add_good_features(table_b, kps, used)
        if table_b.n_3d() <= c.kappa2:
            return table, est, eta, ""
        if est is None and table_b.n_3d() < c.second_start_min_tracked * self.last_inliers:
            # the windows around the last pose missed too: RANSAC would spend its whole
            # budget on a few, mostly wrong, tracks (``second_start_min_tracked``)
            return table, est, eta, ""
        table_b, est_b = self._estimate_pose(table_b, self.last_pose, dt, final=final)
        if est_b is None:
            return table, est, eta, ""
        if est is None:
            return table_b, est_b, eta_b, ""
        dpos, drot = self._apart(est.cam_from_world, est_b.cam_from_world)
        few, many = sorted((est.num_inliers, est_b.num_inliers))
        apart = dpos > c.contradiction_position or drot > c.contradiction_deg
        if apart and few >= c.second_start_tie * many:
            _unmatch(table, slice(None))
            why = (
                f"ambiguous: {est.num_inliers} inliers from the motion prediction and "
                f"{est_b.num_inliers} from the last pose, {dpos:.2f} scene scales / "
                f"{drot:.0f} deg apart"
            )
            return table, None, eta, why
        if est_b.num_inliers > est.num_inliers:
            return table_b, est_b, eta_b, ""
        return table, est, eta, ""

    def _apart(self, a: Rigid3d, b: Rigid3d) -> tuple[float, float]:
        """How far apart two poses are: centres in scene scales, rotation in degrees."""
        dpos = float(np.linalg.norm(a.center - b.center)) / self.bundle.scene_scale
        return dpos, rotation_angle_deg(a.rotation, b.rotation)

    def _other_solution(self, table: TrackTable, est: PoseEstimate, pred: Rigid3d | None) -> str:
        """Why an unverified tracked pose is not published (or ""): RANSAC on its matches,
        without the prior, finds a pose farther from it than a wrong pose
        (``contradiction_position``, ``contradiction_deg``) on at least ``second_start_tie``
        of its inliers, and nearer the motion prediction than it. Near-planar matches admit
        two solutions; the motion decides between them, and here it does not side with ours."""
        c = self.conf
        rows, pts = table.matches()
        if not c.ambiguity_check or len(rows) <= c.kappa2:
            return ""
        xy, X = self._undistort(table.xy[rows]), self.bundle.points_xyz[pts]
        other = estimate_pose(xy, X, self.K, c.ransac())
        if other is None or other.num_inliers < c.second_start_tie * est.num_inliers:
            return ""
        dpos, drot = self._apart(est.cam_from_world, other.cam_from_world)
        if dpos <= c.contradiction_position and drot <= c.contradiction_deg:
            return ""
        if pred is not None:
            ours = self._apart(est.cam_from_world, pred)
            theirs = self._apart(other.cam_from_world, pred)
            if ours[0] <= theirs[0] and ours[1] <= theirs[1]:
                return ""  # the other solution is farther from the motion: ours stands
        return (
            f"ambiguous: {est.num_inliers} inliers from the motion prior, {other.num_inliers} "
            f"for a pose {dpos:.2f} scene scales / {drot:.0f} deg away"
        )

    def _projected_refinement(
        self, est: PoseEstimate, cert: Certainty, kps: Keypoints, table: TrackTable
    ) -> tuple[PoseEstimate, Certainty]:
        """A verified tracked pose refined once more with the map points projecting onto the
        frame's unmatched keypoints (``engine.projected``). The status rules judged the
        tracked matches, and the covariance stays theirs (``refine_with_projections``)."""
        c = self.conf
        if not cert.verified:
            return est, cert
        rows, pts = table.matches()
        kp_u = self._undistort(kps.xy)
        scope, scope_xyz = self._scope_points.with_xyz(self.bundle, pts)
        kp_i, pt_i = projected_matches(
            est.cam_from_world,
            self.K,
            self.camera.width,
            self.camera.height,
            kp_u,
            self.bundle.points_xyz,
            scope,
            c.projected_radius_px,
            c.projected_clear_px,
            scope_xyz,
        )
        # the table's positions are its keypoints' own
        kp_i, pt_i = unmatched_only(kp_i, pt_i, kps.xy, table.xy.take(rows, 0), pts)
        if len(kp_i) == 0:
            return est, cert
        est = refine_with_projections(
            est,
            self.K,
            kp_u.take(kp_i, 0),
            self.bundle.points_xyz.take(pt_i, 0),
            self._ransac(),
            iterations=c.projected_iterations,
        )
        return est, cert

    def _reverify(self, table: TrackTable, pose: Rigid3d) -> TrackTable:
        """Stored hypotheses of unmatched tracked keypoints, checked against the new pose."""
        rows = np.nonzero((table.point < 0) & (table.hyp[:, 0] >= 0))[0]
        if len(rows) == 0:
            return table
        out = table.point[rows]  # (a copy: an index array's gather)
        verified = verify_hypotheses(
            table.hyp.take(rows, 0),  # (take: row gathers, as in ``_track_2d``)
            self._undistort(table.xy.take(rows, 0)),
            self.bundle.points_xyz,
            pose,
            self.K,
            self.conf.guided_threshold_px,
            out,
        )
        table.point[rows] = out
        table.pending[rows[verified]] = False
        return table

    def _pending_batch(self, table: TrackTable) -> np.ndarray:
        """MATCHES-PENDING: the rows guided matching takes this frame (at most ``batch_max``
        of the keypoints tracked for at least a frame, not matched, not tried yet)."""
        pending = table.pending & (table.point < 0) & (table.age >= 1)
        rows = np.nonzero(pending)[0]
        c = self.conf
        if len(rows) < c.guided_min_pending and table.n_3d() >= c.refill_3d:
            # Lazy (the paper's lazy evaluation, one step further): a handful of pending
            # keypoints waits for more while the frame rests on enough matches; a batch pays
            # the DAISY preparation of the whole frame and the search's fixed cost whatever
            # its size. Most such keypoints are dropped by the tracker before their turn.
            return rows[:0]
        n = min(c.batch_spread, c.batch_max)
        if (
            n > 0
            and self.spread_batches
            and self.guided_yield >= c.spread_min_yield
            and (c.spread_keep_up <= 0 or self.loss_3d < c.spread_keep_up * n * self.guided_yield)
        ):
            # The map answers readily here and a short batch brings (n x the yield) more
            # matches than tracking loses a frame: the rest wait for the next frames
            # (spread_keep_up: where tracks die faster, a waiting keypoint is a lost match)
            return rows[:n]
        return rows[: c.batch_max]

    def _many_3d(self, table: TrackTable) -> bool:
        """The frame holds scope_nprobe_max_3d or more 3D matches: the scoped search keeps
        its full nprobe lists (``scope_nprobe_max_3d``)."""
        m = self.conf.scope_nprobe_max_3d
        return m > 0 and table.n_3d() >= m

    def _note_3d_loss(self, lost: int) -> None:
        """The running number of 3D matches a tracked frame loses (tracking, re-verification)
        against the previous frame's, the weight of the guided yield's (``spread_keep_up``)."""
        w = self.conf.spread_yield_weight
        self.loss_3d = w * max(0, lost) + (1.0 - w) * self.loss_3d

    def _guided_matching(
        self, table: TrackTable, rows: np.ndarray, image: _FrameImage, pose: Rigid3d
    ) -> TrackTable:
        """GUIDED-MATCHING of the table's ``rows`` around this frame's pose; on a frame holding
        fewer than ``few_matches_below`` matches, with the looser ``few_matches_ratio``
        hypotheses."""
        c = self.conf
        few = table.n_3d() < c.few_matches_below
        # (take: row gathers, as in ``_track_2d``; two copies, as the two gathers were)
        desc = describe(self.extractor, self.bundle, image.prepared, table.xy.take(rows, 0))
        gm = guided_matching(
            desc,
            self._undistort(table.xy.take(rows, 0)),
            self.bundle,
            table.point[table.point >= 0],
            pose,
            self.K,
            c,
            ratio=c.few_matches_ratio if few else None,
            nprobe=None if few or self._many_3d(table) else self.scope_nprobe,
        )
        table.point[rows] = gm.point
        table.hyp[rows] = gm.hyp
        table.pending[rows] = False
        if len(rows):
            share = np.count_nonzero(gm.point >= 0) / len(rows)
            w = self.conf.spread_yield_weight
            self.guided_yield = w * share + (1.0 - w) * self.guided_yield
        return table

    def _recover(
        self, kps: Keypoints, image: _FrameImage, pred: Rigid3d, scope_points: np.ndarray
    ) -> tuple[TrackTable, PoseEstimate] | None:
        """Tracking lost its 2D-3D matches but the motion filter still predicts the pose:
        guided matching of all the frame's keypoints, scoped by the images that saw the last
        matched points (``scope_points``), and a pose from the hypotheses around the
        prediction (two passes, see ``pose_from_hypotheses``). Much cheaper than global
        matching, the fallback. Returns a new table restarted from the keypoints, and the pose."""
        c = self.conf
        table = self._restart_table(kps)
        if len(table) < c.min_inliers:
            return None
        xy_u = self._undistort(table.xy)
        desc = image.describe_all(self.bundle, table.xy)
        loose = c.model_copy(update={"guided_threshold_px": c.prior_threshold_px})
        reuse = (
            image.search_all(self.bundle, c, table.xy) if c.recovery_search == "global" else None
        )
        gm = guided_matching(desc, xy_u, self.bundle, scope_points, pred, self.K, loose, reuse)
        res = pose_from_hypotheses(gm.hyp, xy_u, self.bundle, self.K, c, pred)
        if res is None:
            return None
        est, point = res
        table.hyp = gm.hyp
        table.point = point
        table.pending = table.point < 0
        return self._reverify(table, est.cam_from_world), est

    def _recovery_fails(self, kps: Keypoints, image: _FrameImage, pred: Rigid3d) -> bool:
        """Whether ``_recover`` around ``pred`` is bound to fail its first test (fewer than
        ``recover_min_inliers`` keypoints with a hypothesis within ``prior_threshold_px`` of the
        prediction), judged on the hypotheses of the whole-map search global matching makes
        (restricted to the recovery's scope) instead of the recovery's own scoped search:
        global matching follows a failed recovery and reuses that search, so a recovery that
        cannot succeed costs no search of its own (``recover_precheck``)."""
        c = self.conf
        if not c.recover_precheck or c.recovery_search != "scoped":
            return False
        xy = kps.xy[self._restart_rows(kps)]  # (the keypoints of ``_recover``'s table)
        if len(xy) < c.min_inliers:
            return False  # (``_recover`` returns at once)
        desc = image.describe_all(self.bundle, xy)
        loose = c.model_copy(update={"guided_threshold_px": c.prior_threshold_px})
        reuse = image.search_all(self.bundle, c, xy)
        gm = guided_matching(
            desc, self._undistort(xy), self.bundle, self.scope_points, pred, self.K, loose, reuse
        )
        return int(np.count_nonzero(gm.point >= 0)) < c.recover_min_inliers

    def _densify(
        self,
        kps: Keypoints,
        image: _FrameImage,
        est: PoseEstimate,
        cert: Certainty,
        wider: tuple[Rigid3d | None, float | None] | None = None,
    ) -> tuple[TrackTable, PoseEstimate, Certainty] | None:
        """A pose about to be withheld as too uncertain, re-matched on the whole frame: guided
        matching of all the frame's keypoints around it, scoped by the map points it makes
        visible, as in ``_recover`` (``densify_uncertain``). The tracks that survive on a thin
        map are often bunched on one far plane; the frame sees more map points than they do.
        With ``wider`` (the motion prediction and the frame's detection threshold's basis, the
        previous maximum response), the keypoints include the corners from
        ``densify_edge_px`` from the image edge on (inside the tracker's border), and with
        ``densify_from_prediction`` the re-match also starts from the prediction when the
        last posed frame was published. Returns the
        restarted table, the pose and its certainty of the most certain re-match when it is
        more certain (smaller centre sd) than ``cert``, else None."""
        c = self.conf
        starts = [est.cam_from_world]
        if wider is not None:
            pred, kp_threshold = wider
            if 0 < c.densify_edge_px < c.mu // 2:
                thr = self._threshold(kp_threshold)
                edge = edge_keypoints(image.gray, thr, c, c.densify_edge_px, self.subpixel)
                kps = with_keypoints(kps, edge)
            if c.densify_from_prediction and pred is not None and self.motion_published:
                starts.append(pred)
        best: tuple[TrackTable, PoseEstimate, Certainty] | None = None
        for start in starts:
            visible = visible_points(self.camera, start, self.bundle.points_xyz)
            if len(visible) < c.min_inliers:
                continue
            dense = self._recover(kps, image, start, visible)
            if dense is None:
                continue
            table, est_d = dense
            cert_d = certainty(est_d, self.K, self.bundle, c)
            if cert_d.position_sd < (cert if best is None else best[2]).position_sd:
                best = (table, est_d, cert_d)
        return best

    def _global_matching(
        self, kps: Keypoints, image: _FrameImage, rivals: list[PoseEstimate] | None = None
    ) -> tuple[TrackTable, PoseEstimate | None, str]:
        """GLOBAL-MATCHING on the frame's keypoints: a new table restarted from them (with
        their matches when a pose was found), the pose, and why there is none (the frame's
        message: a LOST says which test it failed). ``rivals``: see ``global_pose``."""
        c = self.conf
        table = self._restart_table(kps)
        if len(table) < c.min_inliers:
            return table, None, f"only {len(table)} keypoints in the frame"
        xy_u = self._undistort(table.xy)
        desc = image.describe_all(self.bundle, table.xy)
        search = image.search_all(self.bundle, c, table.xy)
        res, why = global_pose(desc, xy_u, self.bundle, self.camera, c, search, rivals=rivals)
        if res is None:
            return table, None, why
        est, q, p, hyp = res
        table.hyp = hyp
        table.point[q] = p
        # Keypoints the global search could not match stay pending: guided matching, scoped by
        # the new pose, gets another try at them over the next frames.
        table.pending = table.point < 0
        return table, est, ""

    def _rivalled(self, est: PoseEstimate, rivals: list[PoseEstimate]) -> str:
        """Why a recovered pose is withheld (or ""): the strongest of the poses the frame's
        global matching found and did not keep (``rivals``) has at least its inliers and lies
        farther from it than a wrong pose (``contradiction_position``, ``contradiction_deg``).
        One near it (an ambiguous answer whose best is the recovered pose) supports it."""
        if not rivals:
            return ""
        c = self.conf
        rival = max(rivals, key=lambda r: r.num_inliers)
        if rival.num_inliers < est.num_inliers:
            return ""
        dpos, drot = self._apart(est.cam_from_world, rival.cam_from_world)
        if dpos <= c.contradiction_position and drot <= c.contradiction_deg:
            return ""
        return (
            f"recovered pose withheld: {est.num_inliers} inliers around the motion prediction, "
            f"global matching {rival.num_inliers} for a pose {dpos:.2f} scene scales / "
            f"{drot:.0f} deg away"
        )

    def _verify_collapse(
        self, kps: Keypoints, image: _FrameImage, est: PoseEstimate, table: TrackTable
    ) -> tuple[TrackTable, PoseEstimate | None, Certainty | None, str]:
        """A tracked pose failing the strict test on a small fraction of the last frame's
        inliers (the tracks were lost; guided matching around the prediction found few
        matches) is checked as a relocalization: global matching on this frame, adopted when
        it passes the strict test; else no pose (withheld, not adopted: the next frame
        relocalizes)."""
        table_g, est_g, cert_g = self._verified_global(kps, image)
        if est_g is not None and cert_g is not None:
            return table_g, est_g, cert_g, ""
        _unmatch(table, slice(None))
        why = (
            f"tracked pose withheld: {est.num_inliers} inliers after {self.last_inliers}, "
            "not verified, and no verified relocalization"
        )
        return table, None, None, why

    def _verified_global(
        self, kps: Keypoints, image: _FrameImage, rivals: list[PoseEstimate] | None = None
    ) -> tuple[TrackTable, PoseEstimate | None, Certainty | None]:
        """Global matching on this frame, kept only when its pose passes the strict test (a
        check of a doubtful tracked pose: an unverified relocalization would not settle it).
        Returns the restarted table, the pose and its certainty, or (table, None, None).
        ``rivals``: when given, the poses it found and did not keep are appended to it (one
        that fails the strict test, or an ambiguous answer's two)."""
        table_g, est_g, _ = self._global_matching(kps, image, rivals)
        cert_g = (
            None
            if est_g is None
            else relocalization_certainty(est_g, self.K, self.bundle, self.conf)
        )
        if est_g is None or cert_g is None or not cert_g.verified:
            if est_g is not None and rivals is not None:
                rivals.append(est_g)
            return table_g, None, None
        return table_g, est_g, cert_g

    def _contradiction(
        self, est: PoseEstimate, cert: Certainty, pred: Rigid3d | None, stamp: float
    ) -> str:
        """Why a relocalization is not adopted (weak, and far from a recent motion
        prediction), or "" when it is."""
        c = self.conf
        last = self.last_posed_stamp
        recent = last is not None and stamp - last <= c.max_frame_gap_s
        # A prediction extrapolated from a withheld pose (too uncertain, or unverified on few
        # inliers: ``contradiction_published_only``) is no evidence against a relocalization.
        trusted = self.motion_published or not c.contradiction_published_only
        if cert.verified or pred is None or not recent or not trusted:
            return ""
        dpos = np.linalg.norm(est.cam_from_world.center - pred.center) / self.bundle.scene_scale
        drot = rotation_angle_deg(est.cam_from_world.rotation, pred.rotation)
        if dpos > c.contradiction_position or drot > c.contradiction_deg:
            return (
                f"weak relocalization ({est.num_inliers} inliers) {dpos:.2f} scene scales / "
                f"{drot:.0f} deg from the motion prediction: rejected"
            )
        return ""

    def _judged_without_one(self, cert: Certainty) -> Certainty:
        """A suspect tracked pose that its re-match did not replace, judged at its centre sd
        without its most influential match when that is over ``relocalize_leave_out_sd``
        (``suspect_leave_out``): the covariance scaled to that sd. Nothing checked that match
        (the re-match started from the pose it fixed), and it alone can put the pose a wrong
        pose away. Over the withholding limit (a fraction of it), the pose is withheld."""
        limit = self.conf.relocalize_leave_out_sd
        sd, loo = cert.position_sd, cert.position_sd_loo
        if limit <= 0 or not loo > limit or not loo > sd:
            return cert
        # (over the withholding limit the leave-one-out sd is exact, not its upper bound)
        scale = (loo / sd) ** 2 if sd > 0 else math.inf
        return Certainty(cert.covariance * scale, loo, False, loo)

    def _rests_on_few(self, est: PoseEstimate, cert: Certainty) -> str | None:
        """Why a pose the status rules would publish rests on a few matches
        (``certainty.rests_on_few``, the single-image rule), or None when it does not
        (``track_relocalize_leave_out``). Asked of a relocalization (not adopted when it does:
        the frames tracked from it would keep those matches, their tracks, and be published
        too; the next frame relocalizes) and of the frames tracked on from an unverified one
        (withheld)."""
        c = self.conf
        if not c.track_relocalize_leave_out:
            return None
        if withheld(cert.position_sd, est.num_inliers, c) is not None:
            return None  # withheld anyway (LOST); followed as any withheld pose
        # (its count by the strict test itself: a pose not verified for resting on one map
        # point, ``verified_without_one``, is left out as many points as a verified one)
        return rests_on_few(est, self.K, self.bundle, c, is_verified(est, cert.position_sd, c))

    def _kalman_filter_update(self, pose: Rigid3d, relocalized: bool, stamp: float) -> Rigid3d:
        """KALMAN-FILTER-UPDATE with the frame's pose: the filtered pose. A relocalization
        (or the first pose) restarts the filter at the pose."""
        c = self.conf
        if relocalized or not self.filter.initialized:
            keep = c.max_frame_gap_s if c.relocalize_keeps_motion else 0.0
            self.filter.reset(
                pose,
                stamp,
                keep,
                c.max_speed_scales_per_s * self.bundle.scene_scale,
                c.max_angular_speed_rad_s,
            )
            return pose
        return self.filter.update(pose)

    def _odometry(
        self, table: TrackTable, pred: Prediction
    ) -> tuple[PoseEstimate, Certainty] | None:
        """Visual odometry beyond the map: the pose from the table's session points and its map
        matches together, around the motion prediction, with an honest covariance: the
        relative fit's (pixel noise, each point's own triangulation or map uncertainty) plus
        the anchor frames' carried rigidly to this camera (``SessionPoints``). Not verified
        (it is not the map's pose). None without ``odometry_min_points`` session inliers or
        a plausible pose. The map matches it finds outliers are ``_odo_outliers`` (they lose
        their match when the pose is adopted)."""
        c = self.conf
        if pred.cam_from_world is None:
            return None
        self.session.activate()
        sm = self.session.matches(table.track_id)
        if len(sm.rows) < c.odometry_min_points:
            return None
        mrows, mpts = table.matches()
        rows = np.concatenate([sm.rows, mrows])
        X = np.concatenate([sm.xyz, self.bundle.points_xyz[mpts]])
        xy = self._undistort(table.xy[rows])
        est = estimate_pose(
            xy,
            X,
            self.K,
            self._ransac(),
            prior=pred.cam_from_world,
            prior_threshold=c.prior_threshold_px,
        )
        if est is None or not self._plausible(est.cam_from_world, pred.cam_from_world, pred.dt):
            return None
        if est.num_inliers < c.odometry_min_consensus * len(rows):
            # Most of the frame's tracks disagree with the pose: they jumped to other corners
            # (``odometry_min_consensus``), and a consensus of the rest is no check.
            self._odo_why = (
                f"odometry pose withheld: {est.num_inliers} of its {len(rows)} matches "
                f"agree (fewer than {c.odometry_min_consensus:.0%})"
            )
            return None
        ns = len(sm.rows)
        inl = est.inlier_mask
        if np.count_nonzero(inl[:ns]) < c.odometry_min_points:
            return None
        pose = est.cam_from_world
        z = X[inl] @ pose.rotation[2] + pose.translation[2]
        if not np.all(z > 0):
            return None
        sigma = np.empty(len(z))
        s_in = inl[:ns]
        k = int(np.count_nonzero(s_in))
        sigma[:k] = sm.sigma_px(s_in, pose, self.K)
        m_in = np.nonzero(inl[ns:])[0]
        if len(m_in):
            pu = PointUncertainty.for_bundle(self.bundle)
            sigma[k:] = pu.sigma_px_of(mpts[m_in], z[k:], c.map_noise_px)
        cov = odometry_covariance(
            self.session,
            pose,
            self.K,
            xy[inl],
            X[inl],
            sigma,
            sm.anchor[s_in],
            c.refine_loss_scale_px,
        )
        sd = position_sd(cov) / self.bundle.scene_scale
        est.inlier_points = None
        self._odo_map_inliers = len(m_in)
        self._odo_outliers = mrows[~inl[ns:]]
        return est, Certainty(cov, sd, False, sd)

    def _adopt_odometry(
        self, kps: Keypoints, image: _FrameImage, odo: PoseEstimate, tracked: TrackTable
    ) -> tuple[TrackTable, PoseEstimate, Certainty | None, Matching]:
        """An odometry pose taken for the frame: the map matches it found outliers lose their
        match in ``tracked`` (the frame's tracked table), then the whole frame is re-matched
        around it (``_map_again``). Returns the table, the pose, the map pose's certainty when
        back on the map (None: still the odometry pose) and how the matches were found."""
        _unmatch(tracked, self._odo_outliers)
        back = self._map_again(kps, image, odo, tracked)
        if back is None:
            return tracked, odo, None, Matching.ODOMETRY
        table, est, cert = back
        return table, est, cert, Matching.GUIDED

    def _odometry_ready(self) -> bool:
        """Whether a frame may be posed by odometry: on, with session points, after a
        published pose."""
        return self.conf.odometry and self.session.ready() and self.motion_published

    def _map_again(
        self, kps: Keypoints, image: _FrameImage, odo: PoseEstimate, tracked: TrackTable
    ) -> tuple[TrackTable, PoseEstimate, Certainty] | None:
        """Back on the map from an odometry pose: the whole frame re-matched around it, scoped
        by the map points it makes visible (``_recover``, as ``_densify``). Returns the
        restarted table, the map pose and its certainty when that pose is publishable (not
        withheld) and agrees with the odometry pose (within the wrong-pose limits,
        ``contradiction_position``, ``contradiction_deg``), else None (odometry goes on).
        Only frames posed by odometry pay it (a thin map; they would otherwise relocalize).
        The restarted table's rows at a keypoint of the ``tracked`` table keep that row's track
        id and age: the session points stay theirs (robust density-6x, rebuilt map: back on the
        map at frame 273 on 25-27 inliers, frames 276-277 then withheld at sd 2.7-2.9% with no
        session point left to pose them)."""
        c = self.conf
        visible = visible_points(self.camera, odo.cam_from_world, self.bundle.points_xyz)
        if len(visible) < c.min_inliers:
            return None
        dense = self._recover(kps, image, odo.cam_from_world, visible)
        if dense is None:
            return None
        table, est = dense
        cert = certainty(est, self.K, self.bundle, c)
        if withheld(cert.position_sd, est.num_inliers, c) is not None:
            return None
        dpos, drot = self._apart(est.cam_from_world, odo.cam_from_world)
        if dpos > c.contradiction_position or drot > c.contradiction_deg:
            return None
        _keep_track_ids(table, tracked)
        return table, est, cert

    def _session_points(
        self,
        table: TrackTable,
        est: PoseEstimate | None,
        cert: Certainty | None,
        status: Status,
        matching: Matching,
    ) -> None:
        """The session points after a frame: a published map pose (TRACKING or RELOCALIZED)
        adds its unmatched tracks' rays and triangulates; a LOST frame drops them (the next
        published frame starts over); an odometry or unverified pose leaves them."""
        if status is Status.LOST or est is None or cert is None:
            if self.session.active or self.session.recent:
                self.session.reset()
            return
        if status is Status.UNVERIFIED:
            return
        self.session.record(
            table.track_id,
            table.xy,
            table.point < 0,
            est.cam_from_world,
            cert.covariance,
            odometry=matching is Matching.ODOMETRY,
        )

    # ------------------------------------------------------------------ helpers
    def _ransac(self) -> RansacParams:
        """``conf.ransac()``, made once per configuration (~15 us a call, 3 a frame)."""
        if self._ransac_of is not self.conf:
            self._ransac_params, self._ransac_of = self.conf.ransac(), self.conf
        return self._ransac_params

    def _undistort(self, xy: np.ndarray) -> np.ndarray:
        return self.camera.undistort_points(xy) if self._distorted else xy

    def _predict_positions(self, table: TrackTable, pred: Rigid3d | None) -> np.ndarray:
        """Where each tracked keypoint of ``table`` should be in the new frame."""
        xy = table.xy.copy()
        if pred is None or len(table) == 0:
            return xy
        rows = np.flatnonzero(table.point >= 0)
        if len(rows) == 0:
            return xy
        # (take: row gathers, as in ``_track_2d``)
        uv, z = self.camera.project(pred, self.bundle.points_xyz.take(table.point[rows], 0))
        # (both coordinates finite: a (N, 2) bool row read as one uint16, not .all(axis=1))
        ok = np.isfinite(uv).view(np.uint16).ravel() == 257
        ok &= z > 0
        if not ok.all():
            rows, uv = rows[ok], uv[ok]
            if len(rows) == 0:
                return xy
        shift = _median_rows(uv - table.xy.take(rows, 0))
        xy += shift  # keypoints without a 3D point follow the median image motion
        xy[rows] = uv
        return xy

    def _restart_rows(self, kps: Keypoints) -> np.ndarray:
        """The keypoints a restarted table holds: the ``global_max_keypoints`` strongest."""
        sel = np.arange(len(kps))
        if len(sel) > self.conf.global_max_keypoints:
            top = np.argsort(-kps.response, kind="stable")[: self.conf.global_max_keypoints]
            sel = np.sort(top)
        return sel

    def _new_ids(self, n: int) -> np.ndarray:
        ids = np.arange(self.next_track_id, self.next_track_id + n, dtype=np.int64)
        self.next_track_id += n
        return ids

    def _plausible(self, pose: Rigid3d, pred: Rigid3d, dt: float) -> bool:
        """A tracked pose may not jump farther from the prediction than the camera can move."""
        c = self.conf
        R, R_pred = pose.rotation, pred.rotation
        # (the centres' difference -R' t - (-R_pred' t_pred), bit for bit, without the two
        # Rigid3d.center calls; the angle of R R_pred' from its trace, the sum of the two
        # matrices' entrywise products, in radians: half of this test's CPU, twice a frame)
        d = R_pred.T @ pred.translation - R.T @ pose.translation
        dpos = math.sqrt(d @ d)  # np.linalg.norm's arithmetic, without its dispatch
        drot = math.acos(min(max((float(np.vdot(R, R_pred)) - 1.0) / 2.0, -1.0), 1.0))
        slack = max(dt, 1.0 / 30.0)
        # Bounded: far from the prediction is implausible however long the frame interval.
        reach_scales = min(c.max_speed_scales_per_s * slack, c.max_jump_scales)
        reach_scales += c.jump_tolerance_scales
        reach = reach_scales * self.bundle.scene_scale
        turn = c.max_angular_speed_rad_s * slack + math.radians(c.jump_tolerance_deg)
        return dpos <= reach and drot <= turn

    def _restart_table(self, kps: Keypoints) -> TrackTable:
        """A fresh track table from the frame's strongest keypoints (after tracking failed)."""
        c = self.conf
        sel = self._restart_rows(kps)
        table = TrackTable.empty(c.max_hypotheses)
        table.append(self._new_ids(len(sel)), kps.xy[sel], kps.brief[sel])
        table.pending[:] = False
        return table
