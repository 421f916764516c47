"""Error and latency statistics of a replayed sequence (the keys ``sfmloc replay --json``
writes, and the paper's Table 2 columns)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..transforms import Rigid3d, pose_errors

# A TRACKING frame this wrong is "confident wrong".
WRONG_POSITION_M = 0.5
WRONG_ROTATION_DEG = 10.0


@dataclass
class FrameRecord:
    index: int
    name: str
    stamp: float
    status: str
    matching: str
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
    # CPU time of the process for the frame (ms): unlike latency_ms, it does not grow when
    # other processes load the machine (the engine runs on one thread).
    cpu_ms: float | None = None


def attach_errors(rec: FrameRecord, est: Rigid3d | None, gt: Rigid3d | None) -> None:
    rec.cam_from_world = est
    rec.gt_cam_from_world = gt
    if est is not None and gt is not None:
        rec.position_error_m, rec.rotation_error_deg = pose_errors(est, gt)


def _stats(x: np.ndarray) -> dict[str, float]:
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


def summarize(records: list[FrameRecord]) -> dict:
    """The replay summary (keys fixed by the CLI contract, plus a few extras)."""
    n = len(records)
    localized = np.array([r.status != "LOST" for r in records], bool)
    lat = np.array([r.latency_ms for r in records], np.float64)
    with_gt = [r for r in records if r.position_error_m is not None]
    pe = np.array([r.position_error_m for r in with_gt], np.float64)
    re_ = np.array([r.rotation_error_deg for r in with_gt], np.float64)
    wrong = [
        r for r in with_gt
        if r.status == "TRACKING" and (r.position_error_m > WRONG_POSITION_M or r.rotation_error_deg > WRONG_ROTATION_DEG)
    ]
    guided = [r for r in records if r.matching == "guided"]
    glob = [r for r in records if r.matching == "global"]
    frames_with_gt = sum(1 for r in records if r.gt_cam_from_world is not None)

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
        "latency_ms": _stats(lat),
        "guided_frames": len(guided),
        "global_frames": len(glob),
        # extras
        "localized_frames": int(localized.sum()),
        "frames_with_groundtruth": frames_with_gt,
        "evaluated_frames": len(with_gt),
        "guided_latency_ms_mean": float(np.mean([r.latency_ms for r in guided])) if guided else float("nan"),
        "global_latency_ms_mean": float(np.mean([r.latency_ms for r in glob])) if glob else float("nan"),
        "status_counts": {s: sum(1 for r in records if r.status == s) for s in ("TRACKING", "RELOCALIZED", "LOST")},
        "confident_wrong_frames": [r.name for r in wrong][:50],
    }


def align_umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimizing ||dst - (R src + t)|| (SE(3), no scale)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    C = (dst - mu_d).T @ (src - mu_s) / len(src)
    U, _, Vt = np.linalg.svd(C)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    return R, mu_d - R @ mu_s


def absolute_trajectory_error(records: list[FrameRecord]) -> float:
    """RMSE of camera centres after SE(3) alignment of estimate to ground truth (ATE)."""
    pairs = [(r.cam_from_world.center, r.gt_cam_from_world.center) for r in records
             if r.cam_from_world is not None and r.gt_cam_from_world is not None]
    if len(pairs) < 3:
        return float("nan")
    est = np.array([p[0] for p in pairs])
    gt = np.array([p[1] for p in pairs])
    R, t = align_umeyama(est, gt)
    return float(np.sqrt(np.mean(np.sum((est @ R.T + t - gt) ** 2, axis=1))))
