"""Error and latency statistics of a replayed sequence (the keys ``sfmloc replay --json``
writes, and the paper's Table 2 columns)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..engine.types import Matching, Status
from ..transforms import Rigid3d, align_umeyama, pose_errors

# A wrong pose: any status but LOST (a client acts on every pose it receives, whatever the
# status says) off by more than this fraction of the scene's scale (MapBundle.scene_scale,
# the median camera-to-point depth of the map, in map units) or by more than this angle.
WRONG_POSITION_FRACTION = 0.05
WRONG_ROTATION_DEG = 10.0
# Accuracy bounds: the usual 7-Scenes recall (5 cm and 5 deg, for maps in metres) and a
# scene-relative one for maps in any unit: 2.5% of the scene scale is 5 cm at a 2 m median
# depth (the order of redkitchen's and the synthetic room's).
RECALL_POSITION_M = 0.05
RECALL_ROTATION_DEG = 5.0
RECALL_POSITION_FRACTION = 0.025
WRONG_POSE_RULE = (
    f"any status but LOST, position error > {WRONG_POSITION_FRACTION:.0%} of the scene scale "
    f"(median camera-to-point depth) or rotation error > {WRONG_ROTATION_DEG:g} deg"
)


@dataclass
class FrameRecord:
    index: int
    name: str
    stamp: float
    status: Status
    matching: Matching
    latency_ms: float
    inliers: int
    detected: int
    tracked: int
    tracked_3d: int
    position_error_m: float | None = None
    rotation_error_deg: float | None = None
    cam_from_world: Rigid3d | None = None
    gt_cam_from_world: Rigid3d | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    cpu_timings_ms: dict[str, float] = field(default_factory=dict)  # the stages' CPU time
    # CPU time of the process for the frame (ms): unlike latency_ms, it does not grow when
    # other processes load the machine (the engine runs on one thread).
    cpu_ms: float | None = None
    covariance: np.ndarray | None = None  # 6x6 of cam_from_world (engine.pose.COVARIANCE_ORDER)
    message: str = ""  # why the frame is LOST (or a pose withheld), when the method says


def attach_errors(rec: FrameRecord, est: Rigid3d | None, gt: Rigid3d | None) -> None:
    rec.cam_from_world = est
    rec.gt_cam_from_world = gt
    if est is not None and gt is not None:
        rec.position_error_m, rec.rotation_error_deg = pose_errors(est, gt)


def is_pose(status: Status | str) -> bool:
    """Every status but LOST reports a pose (TRACKING, RELOCALIZED and any status added later)."""
    return status != Status.LOST


def wrong_position_limit(scene_scale: float) -> float:
    """The position error (map units) above which a pose is wrong."""
    return WRONG_POSITION_FRACTION * _checked_scale(scene_scale)


def _checked_scale(scene_scale: float) -> float:
    if not (isinstance(scene_scale, (int, float)) and np.isfinite(scene_scale) and scene_scale > 0):
        raise ValueError(f"scene_scale must be a positive number (map units), got {scene_scale!r}")
    return float(scene_scale)


def wrong_poses(records: list[FrameRecord], scene_scale: float) -> list[FrameRecord]:
    """Frames with a pose (any status but LOST) and an error over the wrong-pose limits."""
    limit = wrong_position_limit(scene_scale)
    return [
        r
        for r in records
        if is_pose(r.status)
        and r.position_error_m is not None
        and r.rotation_error_deg is not None
        and (r.position_error_m > limit or r.rotation_error_deg > WRONG_ROTATION_DEG)
    ]


def within(records: list[FrameRecord], position: float, rotation_deg: float) -> int:
    """Frames with a pose within ``position`` (map units) and ``rotation_deg`` of ground truth."""
    return sum(
        1
        for r in records
        if is_pose(r.status)
        and r.position_error_m is not None
        and r.rotation_error_deg is not None
        and r.position_error_m <= position
        and r.rotation_error_deg <= rotation_deg
    )


def _counts(first: list[str], records: list[FrameRecord]) -> dict[str, int]:
    """Frames per status: ``first`` (even when 0), then any other status in order of appearance."""
    keys = dict.fromkeys([*first, *(r.status for r in records)])
    return {s: sum(1 for r in records if r.status == s) for s in keys}


def distribution(x: Sequence[float] | np.ndarray) -> dict[str, float]:
    """Mean, std, p50, p95, p99 and max of ``x`` (NaN each when empty)."""
    if len(x) == 0:
        return {k: float("nan") for k in ("mean", "std", "p50", "p95", "p99", "max")}
    return {
        "mean": float(np.mean(x)),
        "std": float(np.std(x)),
        "p50": float(np.percentile(x, 50)),
        "p95": float(np.percentile(x, 95)),
        "p99": float(np.percentile(x, 99)),
        "max": float(np.max(x)),
    }


def summarize(records: list[FrameRecord], scene_scale: float) -> dict:
    """The replay summary (keys fixed by the CLI contract, plus a few extras). ``scene_scale``
    (``MapBundle.scene_scale``) sets the wrong-pose and scene-relative accuracy limits;
    ``confident_wrong`` counts wrong poses under any status but LOST."""
    scale = _checked_scale(scene_scale)
    n = len(records)
    localized = np.array([is_pose(r.status) for r in records], bool)
    lat = np.array([r.latency_ms for r in records], np.float64)
    with_gt = [r for r in records if r.position_error_m is not None]
    pe = np.array([r.position_error_m for r in with_gt], np.float64)
    re_ = np.array([r.rotation_error_deg for r in with_gt], np.float64)
    wrong = wrong_poses(records, scale)
    guided = [r for r in records if r.matching == Matching.GUIDED]
    glob = [r for r in records if r.matching == Matching.GLOBAL]
    frames_with_gt = sum(1 for r in records if r.gt_cam_from_world is not None)

    def share(k: int) -> float:
        return k / frames_with_gt if frames_with_gt else float("nan")

    def nanstat(f, x):
        return float(f(x)) if len(x) else float("nan")

    return {
        "frames": n,
        "localized_fraction": float(localized.mean()) if n else 0.0,
        "median_position_error_m": nanstat(np.median, pe),
        "median_rotation_error_deg": nanstat(np.median, re_),
        "mean_position_error_m": nanstat(np.mean, pe),
        "mean_rotation_error_deg": nanstat(np.mean, re_),
        "confident_wrong": len(wrong),
        "latency_ms": distribution(lat),
        "guided_frames": len(guided),
        "global_frames": len(glob),
        # extras
        "localized_frames": int(localized.sum()),
        "frames_with_groundtruth": frames_with_gt,
        "evaluated_frames": len(with_gt),
        "guided_latency_ms_mean": float(np.mean([r.latency_ms for r in guided]))
        if guided
        else float("nan"),
        "global_latency_ms_mean": float(np.mean([r.latency_ms for r in glob]))
        if glob
        else float("nan"),
        # The usual three first, then any other status seen, in order of appearance.
        "status_counts": _counts([Status.TRACKING, Status.RELOCALIZED, Status.LOST], records),
        "confident_wrong_frames": [r.name for r in wrong][:50],
        "wrong_statuses": _counts([], wrong),
        "scene_scale": scale,
        "wrong_position_limit": wrong_position_limit(scale),
        "wrong_rotation_limit_deg": WRONG_ROTATION_DEG,
        # Fractions of the frames with ground truth (a LOST frame counts as a miss).
        "within_5cm_5deg_fraction": share(within(records, RECALL_POSITION_M, RECALL_ROTATION_DEG)),
        "within_relative_fraction": share(
            within(records, RECALL_POSITION_FRACTION * scale, RECALL_ROTATION_DEG)
        ),
        "within_relative_position_limit": RECALL_POSITION_FRACTION * scale,
    }


def absolute_trajectory_error(records: list[FrameRecord]) -> float:
    """RMSE of camera centres after SE(3) alignment of estimate to ground truth (ATE)."""
    pairs = [
        (r.cam_from_world.center, r.gt_cam_from_world.center)
        for r in records
        if r.cam_from_world is not None and r.gt_cam_from_world is not None
    ]
    if len(pairs) < 3:
        return float("nan")
    est = np.array([p[0] for p in pairs])
    gt = np.array([p[1] for p in pairs])
    _, R, t = align_umeyama(est, gt, with_scale=False)  # SE(3): no scale
    return float(np.sqrt(np.mean(np.sum((est @ R.T + t - gt) ** 2, axis=1))))
