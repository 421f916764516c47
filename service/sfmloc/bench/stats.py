"""Per-method numbers of a localization suite: the paper's Table 2 columns and the accuracy
figures users compare, computed from ``FrameRecord``s with ``sfmloc.eval.metrics``."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..engine.types import Matching
from ..eval.metrics import (
    FrameRecord,
    absolute_trajectory_error,
    distribution,
    is_pose,
    summarize,
)
from ..eval.stages import stage_stats


def _ms(x: Sequence[float]) -> tuple[float, float]:
    return (float(np.mean(x)), float(np.std(x))) if len(x) else (math.nan, math.nan)


def method_summary(records: list[FrameRecord], scene_scale: float) -> dict:
    """Table 2 (F, F_loc, T, M, T_M), errors, latency tail, wrong poses, ATE, CPU time.
    ``scene_scale`` (the map's median depth) sets the wrong-pose and relative-recall limits."""
    s = summarize(records, scene_scale)
    n = len(records)
    lat = [r.latency_ms for r in records]
    cpu = [r.cpu_ms for r in records if r.cpu_ms is not None]
    matched = [r.latency_ms for r in records if r.matching in (Matching.GUIDED, Matching.GLOBAL)]
    t_mean, t_std = _ms(lat)
    tm_mean, tm_std = _ms(matched)
    with_gt = s["frames_with_groundtruth"]
    return {
        "F": n,
        "F_loc": s["localized_frames"],
        "F_loc_pct": 100.0 * s["localized_fraction"],
        "T_ms_mean": t_mean,
        "T_ms_std": t_std,
        "rate_hz": 1000.0 / t_mean if t_mean and t_mean == t_mean else math.nan,
        "M": len(matched),
        "M_pct": 100.0 * len(matched) / n if n else math.nan,
        "T_M_ms_mean": tm_mean,
        "T_M_ms_std": tm_std,
        "guided_frames": s["guided_frames"],
        "global_frames": s["global_frames"],
        "T_ms_p50": s["latency_ms"]["p50"],
        "T_ms_p99": s["latency_ms"]["p99"],
        "T_ms_max": s["latency_ms"]["max"],
        "cpu_ms_mean": float(np.mean(cpu)) if cpu else math.nan,
        "median_position_error_m": s["median_position_error_m"],
        "median_position_error_rel": s["median_position_error_m"] / s["scene_scale"],
        "mean_position_error_m": s["mean_position_error_m"],
        "median_rotation_error_deg": s["median_rotation_error_deg"],
        "mean_rotation_error_deg": s["mean_rotation_error_deg"],
        # Poses under any status but LOST beyond the wrong-pose limits (eval.metrics).
        "wrong_poses": s["confident_wrong"],
        "wrong_statuses": s["wrong_statuses"],
        "scene_scale": s["scene_scale"],
        "wrong_position_limit": s["wrong_position_limit"],
        "recall_5cm_5deg_pct": 100.0 * s["within_5cm_5deg_fraction"],
        "recall_relative_pct": 100.0 * s["within_relative_fraction"],
        "recall_relative_position_limit": s["within_relative_position_limit"],
        "ate_m": absolute_trajectory_error(records),
        "inliers_median": float(np.median([r.inliers for r in records if is_pose(r.status)]))
        if s["localized_frames"]
        else math.nan,
        "frames_with_groundtruth": with_gt,
        "status_counts": s["status_counts"],
    }


def stage_times(records: list[FrameRecord]) -> dict[str, dict[str, float]]:
    """Per stage of the engine's timers (``eval.stages.stage_stats``): mean ms per frame over
    all frames, share of the total, and mean / p95 / p99 / max over the frames it ran in."""
    return stage_stats([r.timings_ms for r in records])


def relocalization_times(records: list[FrameRecord]) -> dict:
    """The time distribution of single-image relocalization calls (issue 10's target is on its
    p95): ``eval.metrics.distribution`` of the wall clock and of the process's CPU time, ms."""
    return {
        "calls": len(records),
        "wall": distribution([r.latency_ms for r in records]),
        "cpu": distribution([r.cpu_ms for r in records if r.cpu_ms is not None]),
    }


def ratios(ours: dict, peer: dict) -> dict:
    """Ours against a peer on the same frames: frame-rate ratio (peer mean time / ours), the
    same on CPU time, and the accuracy ratio (peer median position error / ours)."""

    def div(a: float, b: float) -> float:
        return a / b if b and b == b and a == a else math.nan

    return {
        "rate_ratio": div(peer["T_ms_mean"], ours["T_ms_mean"]),
        "cpu_ratio": div(peer["cpu_ms_mean"], ours["cpu_ms_mean"]),
        "p99_ratio": div(peer["T_ms_p99"], ours["T_ms_p99"]),
        "median_position_error_ratio": div(
            peer["median_position_error_m"], ours["median_position_error_m"]
        ),
    }
