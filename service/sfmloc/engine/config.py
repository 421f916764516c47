"""Engine configuration: the paper's parameters are the defaults, every one overridable
(``SFMLOC_ENGINE__K=64`` in the environment, a config file, or code)."""

from __future__ import annotations

from typing import Literal

from ..config import StrictModel
from .pose import RansacParams


class EngineConf(StrictModel):
    # ---- the paper's parameters (Sections 2.1, 2.2, 3)
    k: int = 50  # neighbours per k-ANN query
    sigma: float = 2.0  # neighbours farther than sigma * nearest distance do not vote
    beta: float = 0.8  # clusters scoring >= beta * best are selected
    mu: int = 32  # BRIEF patch size (pixels)
    rho: int = 48  # tracking search window (pixels, square)
    psi: float = 0.8  # best / second-best Hamming ratio for a track match
    kappa1: int = 25  # add new keypoints when fewer are tracked
    kappa2: int = 10  # relocalize when at most this many 2D-3D matches remain
    gamma: float = 0.001  # Harris threshold: gamma * previous frame's maximum cornerness
    batch_min: int = 100  # guided matching batch (pending keypoints per frame)
    batch_max: int = 150
    top_images: int = 30  # guided matching scope
    ratio: float = 0.75  # ratio test on 3D point strengths
    min_inliers: int = 10  # a pose with fewer inliers is rejected
    # Global matching also needs this fraction of its ratio-test matches as inliers: 10 inliers
    # out of ~500 candidates is chance (a relocalization 3.7 m / 140 deg off had 1.9%; correct
    # ones on redkitchen have 12-63%).
    global_min_inlier_ratio: float = 0.05

    # ---- engineering choices the paper leaves open
    # Also ADD-GOOD-FEATURES when fewer tracked keypoints than this have a 3D match (0: only
    # the paper's kappa1 rule). Tracks with 3D matches decay faster than tracks overall, and
    # without refilling the engine falls back to costly global matching (kappa2) first.
    # Measured on redkitchen (300 frames): 0 -> 11 global frames, median 1.5 cm; 40 -> 3 global
    # frames, median 1.0 cm.
    refill_3d: int = 40
    # Cluster voting: "sum" adds the strength of every neighbour (the literal reading of the
    # paper); "max" lets each query vote once per cluster, with its strongest neighbour there.
    # With PCA-32 DAISY the 50th neighbour is typically only 1.5x farther than the first, so
    # sigma = 2 prunes little and "sum" mostly counts cluster sizes. Measured on 40 redkitchen
    # frames: relocalization succeeds on 39/40 with "max", 29/40 with "sum".
    vote: Literal["max", "sum"] = "max"
    # Before global matching, try guided matching of the whole frame around the motion
    # filter's prediction (scope: images of the last matched points; verification threshold
    # below). Off: the paper's behaviour (global matching whenever matches run out).
    prior_recovery: bool = True
    prior_threshold_px: float = 20.0
    # A recovered pose needs more inliers than a tracked one: verification within 20 px of a
    # prediction admits chance matches (an 11-inlier recovery on redkitchen was 0.65 m off).
    recover_min_inliers: int = 20
    # A tracked pose farther from the motion prediction than the camera can move in the frame
    # interval is rejected (the frame then recovers or relocalizes instead of reporting it).
    max_speed_mps: float = 5.0
    max_angular_speed_rps: float = 6.0  # ~340 deg/s: beyond a quadrotor's fast yaw
    jump_tolerance_m: float = 0.10
    jump_tolerance_deg: float = 5.0
    # Frames and queries finer than the map ("map"): processed at about the mapping images'
    # focal length (downscaled, never upsampled; see engine.frame.working_scale). "full": at
    # their own resolution, the paper's behaviour: Harris corners at 6 MP are fine detail no map
    # descriptor describes. Synthetic 3072x2048 queries of a map of 640x480 views: "full" 2/10
    # relocalized, both > 1 m off; "map" 10/10, median 0.5 cm (640x480 queries: 0.39 cm).
    working_scale: Literal["map", "full"] = "map"
    max_keypoints: int = 1500  # strongest Harris corners kept per frame (bounds the latency)
    max_tracks: int = 1000  # track table capacity
    max_hamming: int = 80  # a track match must also be this close (of 256 bits)
    global_max_keypoints: int = 1000  # keypoints described for global matching
    nprobe: int = 16  # inverted lists scanned per ANN query
    max_hypotheses: int = 8  # one-to-many 3D hypotheses kept per keypoint
    ransac_threshold_px: float = 4.0  # inlier reprojection error in RANSAC
    ransac_confidence: float = 0.999
    ransac_max_iterations: int = 1000
    refine_threshold_px: float = 3.0  # inliers kept for the final refinement
    guided_threshold_px: float = 6.0  # verification of guided hypotheses against the pose
    add_min_distance_px: float = 6.0  # new keypoints keep this far from tracked ones
    # Kalman filter (constant velocity, constant angular velocity)
    accel_noise: float = 4.0  # m/s^2 (white-noise acceleration)
    angular_accel_noise: float = 8.0  # rad/s^2
    position_noise: float = 0.02  # m, measurement
    orientation_noise: float = 0.01  # rad, measurement
    max_frame_gap_s: float = 1.0  # a longer gap between frames resets the filter

    def ransac(self, min_inliers: int | None = None) -> RansacParams:
        """The RANSAC settings of the pose estimators."""
        return RansacParams(
            threshold=self.ransac_threshold_px,
            refine_threshold=self.refine_threshold_px,
            min_inliers=self.min_inliers if min_inliers is None else min_inliers,
            confidence=self.ransac_confidence,
            max_iterations=self.ransac_max_iterations,
        )
