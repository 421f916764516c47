"""A localization suite's speed, repeated: our engine and ``global-every-frame`` replayed
``BenchConf.reps`` times, interleaved, ``pycolmap-sift`` once; the timing numbers are the median
over the reps, with their spread (min-max) and the load average at the start of each rep. The
stage tables are one rep's, the median rep's (``median_rep``), so their rows sum to their total.

Why: on a shared machine one replay is one sample. The same code read 5.4 and 5.8 ms per frame
in two back-to-back quiet replays (x1.07), and the published redkitchen mean moved 5.78 -> 6.21
-> 6.09 across three benches of nearly the same code. A ratio to a peer is fairest when both
run next to each other, so every rep runs ours and ``global-every-frame`` back to back (the
order alternates from rep to rep, as ``bench.ab`` does) and the ratio is taken rep by rep.

``pycolmap-sift`` runs once (about 75 s of the redkitchen suite's ~100 s, ~150 ms a frame,
against ~10 s for each of the two others), after the last rep: the bench runs every suite's
reps first, then the peer's tuning and its runs (``main``), so that the process that times our
engine has done nothing but load maps, as a server worker (a map build in the same process
slows its replays: docs/development.md#bench-isolation). Its ratio is its one run against
each rep of ours (so its median is its mean time over the median of ours).

Accuracy comes from rep 1. The engine is repeatable (the same frames give the same poses, bit
for bit), so every later rep must give rep 1's poses, frame by frame: the check is recorded in
``reps.repeatable`` and is a target; a difference is reported, not raised (the run's other
numbers stay good).
"""

from __future__ import annotations

import copy
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..eval.metrics import FrameRecord
from .config import OURS, BenchConf
from .suites import Prepared, peer_indices, replay_ours, run_sift_peer

log = logging.getLogger(__name__)

Progress = Callable[[str, float, str], None]

GEF = "global-every-frame"
SIFT = "pycolmap-sift"
# The repeated methods, and the timing fields of a ``stats.method_summary`` that vary from rep
# to rep (the median is published); every other field is accuracy and comes from rep 1.
REPEATED = (OURS, GEF)
TIMING_KEYS = (
    "T_ms_mean",
    "T_ms_std",
    "T_ms_p50",
    "T_ms_p99",
    "T_ms_max",
    "T_M_ms_mean",
    "T_M_ms_std",
    "cpu_ms_mean",
)
# The per-rep numbers kept in results.json (flat keys: report tables and spreads read them).
REP_KEYS = (
    "load_average",
    "ours_T_ms_mean",
    "ours_T_ms_p99",
    "ours_cpu_ms_mean",
    "ours_same_frames_T_ms_mean",
    "gef_T_ms_mean",
    "rate_ratio_gef",
    "cpu_ratio_gef",
    "rate_ratio_sift",
    "cpu_ratio_sift",
    "relocalization_p95_ms",
)


@dataclass
class SuiteRuns:
    """Every rep's records of a suite: ``ours[k]`` and ``gef[k]`` of rep k+1, ``sift`` once."""

    ours: list[list[FrameRecord]]
    gef: list[list[FrameRecord]]
    sift: list[FrameRecord] = field(default_factory=list)
    load_average: list[float] = field(default_factory=list)  # 1-min load at each rep's start
    order: list[list[str]] = field(default_factory=list)  # the methods in the order they ran

    def first(self) -> dict[str, list[FrameRecord]]:
        """Rep 1's records of all three methods (per-frame files, figures, accuracy)."""
        return {OURS: self.ours[0], GEF: self.gef[0], SIFT: self.sift}


def run_reps(
    prep: Prepared, conf: BenchConf, progress: Progress, reps: int | None = None
) -> SuiteRuns:
    """Ours and global-every-frame, ``reps`` (default ``conf.reps``) times on the same frames,
    in alternating order (rep 1: ours first), in this process (a fresh ``Localizer`` per
    replay); ``sift`` is left empty for ``run_sift`` (after every suite's reps)."""
    from ..engine import EngineConf
    from ..io.frames import FrameSource
    from ..map.bundle import MapBundle
    from .peers import global_every_frame, run_peer

    n = conf.reps if reps is None else reps
    runs = SuiteRuns([], [], [])
    bundle = MapBundle(prep.bundle_path)
    source = FrameSource(prep.frames_dir, fps=prep.fps)
    gef_fn = global_every_frame(bundle, prep.camera, EngineConf())
    idx, stride = peer_indices(prep, conf.peer_frames)
    log.info(
        "%s: our engine on %d frames, global-every-frame on %d (every %d), %d reps",
        prep.name,
        prep.count,
        len(idx),
        stride,
        n,
    )
    for k in range(n):
        label = f"rep {k + 1}/{n}"
        order = [GEF, OURS] if k % 2 else [OURS, GEF]
        runs.load_average.append(os.getloadavg()[0])
        runs.order.append(order)
        for method in order:
            log.info("%s: %s, %s", prep.name, method, label)
            if method == OURS:
                stage = f"{prep.name}:{OURS}" + (f" {label}" if k else "")
                runs.ours.append(replay_ours(prep, bundle, source, progress, stage))
            else:
                runs.gef.append(
                    run_peer(
                        GEF,
                        gef_fn,
                        source,
                        idx,
                        prep.groundtruth,
                        progress=_peer_progress(progress, prep.name, f" {label}" if k else ""),
                    )
                )
    return runs


def run_sift(
    runs: SuiteRuns, prep: Prepared, conf: BenchConf, sift_conf, progress: Progress
) -> None:
    """``pycolmap-sift`` once, after the last rep (``runs.order``'s last entry says so)."""
    runs.sift = run_sift_peer(prep, conf, sift_conf, progress)
    runs.order[-1].append(SIFT)


def _peer_progress(progress: Progress, suite: str, label: str) -> Progress:
    def on_peer(stage: str, fraction: float, message: str) -> None:
        progress(f"{suite}:{stage}{label}", fraction, message)

    return on_peer


# --------------------------------------------------------------------------- repeatability
def _pose_key(r: FrameRecord) -> tuple:
    """What must not change from rep to rep: the frame's outcome and its pose, bit for bit."""
    pose = r.cam_from_world
    arr = None if pose is None else np.concatenate([pose.rotation.ravel(), pose.translation])
    return (
        r.index,
        str(r.status),
        str(r.matching),
        r.inliers,
        r.detected,
        r.tracked,
        r.tracked_3d,
        None if arr is None else arr.tobytes(),
    )


def differing_frames(a: Sequence[FrameRecord], b: Sequence[FrameRecord]) -> list[int]:
    """Indices of the frames whose outcome or pose differs between two runs (a frame missing
    from one counts)."""
    ka = {r.index: _pose_key(r) for r in a}
    kb = {r.index: _pose_key(r) for r in b}
    return sorted(i for i in ka.keys() | kb.keys() if ka.get(i) != kb.get(i))


def repeatability(runs: SuiteRuns) -> dict:
    """Every later rep against rep 1, per repeated method: the frames that differ."""
    out: dict = {"identical": True, "methods": {}}
    for name, per_rep in ((OURS, runs.ours), (GEF, runs.gef)):
        diffs = [differing_frames(per_rep[0], recs) for recs in per_rep[1:]]
        worst = max(diffs, key=len, default=[])
        out["methods"][name] = {
            "frames": len(per_rep[0]),
            "frames_differing_per_rep": [len(d) for d in diffs],
            "first_differing": worst[:10],
        }
        if any(diffs):
            out["identical"] = False
    return out


# --------------------------------------------------------------------------- medians
def _median(xs: Sequence[float]) -> float:
    return float(np.median(np.asarray(xs, np.float64))) if len(xs) else float("nan")


def _median_fields(dicts: Sequence[dict], keys: Sequence[str]) -> dict:
    """``dicts[0]`` with each of ``keys`` replaced by its median over ``dicts``."""
    out = copy.deepcopy(dicts[0])
    for k in keys:
        if k in out:
            out[k] = _median([d[k] for d in dicts])
    return out


def _median_method(summaries: Sequence[dict]) -> dict:
    m = _median_fields(summaries, TIMING_KEYS)
    t = m["T_ms_mean"]
    m["rate_hz"] = 1000.0 / t if t and t == t else float("nan")
    return m


def median_rep(values: Sequence[float]) -> int:
    """The index of the rep whose value is the median of ``values`` (for an even count the
    lower of the two middle ones; ties: the earliest rep; NaNs sort last).

    Why one rep and not a median per cell: a stage table (or a peer's stage line) is read
    down its rows, which add up to the frame's total only within one run; per-cell medians
    mix reps, and their rows need not sum to their total."""
    v = np.asarray(values, np.float64)
    mid = v[np.argsort(v, kind="stable")[(len(v) - 1) // 2]]
    same = np.flatnonzero(v == mid)  # ties: the earliest (rep 1's when it is among them)
    return int(same[0]) if len(same) else 0


def rep_numbers(s: dict, load: float) -> dict:
    """The headline numbers of one rep's ``summarize_suite`` (flat, ``REP_KEYS``)."""
    o, same = s["methods"][OURS], s["same_frames"][OURS]
    r = s["ratios"]
    rl = s.get("relocalization_ms") or {}
    return {
        "load_average": load,
        "ours_T_ms_mean": o["T_ms_mean"],
        "ours_T_ms_p99": o["T_ms_p99"],
        "ours_cpu_ms_mean": o["cpu_ms_mean"],
        "ours_same_frames_T_ms_mean": same["T_ms_mean"],
        "gef_T_ms_mean": s["methods"][GEF]["T_ms_mean"],
        "rate_ratio_gef": r[GEF]["rate_ratio"],
        "cpu_ratio_gef": r[GEF]["cpu_ratio"],
        "rate_ratio_sift": r[SIFT]["rate_ratio"],
        "cpu_ratio_sift": r[SIFT]["cpu_ratio"],
        "relocalization_p95_ms": rl.get("wall", {}).get("p95", float("nan")),
    }


def summarize_repeated(
    runs: SuiteRuns,
    summarize: Callable[[dict[str, list[FrameRecord]]], dict],
) -> dict:
    """``summarize`` (``main.summarize_suite`` on the suite's frames) of every rep, combined:
    accuracy and counts from rep 1, every timing number (our engine's and global-every-frame's
    means, percentiles and CPU, the ratios, the relocalization times) the median over the
    reps, the stage tables those of the median rep (``median_rep``); ``reps`` holds each rep's
    headline numbers, their min-max, the loads, which rep gave the stage tables and the
    repeatability check."""
    per = [
        summarize({OURS: ours, GEF: gef, SIFT: runs.sift})
        for ours, gef in zip(runs.ours, runs.gef, strict=True)
    ]
    out = copy.deepcopy(per[0])
    for m in REPEATED:
        out["methods"][m] = _median_method([s["methods"][m] for s in per])
    out["same_frames"][OURS] = _median_method([s["same_frames"][OURS] for s in per])
    out["ratios"] = {
        m: _median_fields([s["ratios"][m] for s in per], list(per[0]["ratios"][m]))
        for m in per[0]["ratios"]
    }
    # The stage tables are one rep's each: ours the rep whose mean per frame is the median
    # (its total row is the published median for an odd count of reps; a frame's latency is
    # its timers' "total"), global-every-frame's stage line likewise from its median rep.
    stage_rep = median_rep([s["methods"][OURS]["T_ms_mean"] for s in per])
    gef_stage_rep = median_rep([s["methods"][GEF]["T_ms_mean"] for s in per])
    out["stages_ms"] = copy.deepcopy(per[stage_rep]["stages_ms"])
    out["peer_stages_ms"][GEF] = copy.deepcopy(per[gef_stage_rep]["peer_stages_ms"][GEF])
    if "relocalization_ms" in out:
        rl = out["relocalization_ms"]
        for kind in ("wall", "cpu"):
            rl[kind] = _median_fields([s["relocalization_ms"][kind] for s in per], list(rl[kind]))
    numbers = [rep_numbers(s, load) for s, load in zip(per, runs.load_average, strict=True)]
    out["reps"] = {
        "count": len(per),
        "statistic": "median",
        "repeated": list(REPEATED),
        "once": [SIFT],
        "order": runs.order,
        "per_rep": numbers,
        # 1-based: the rep whose stage table ("stages_ms") and global-every-frame stage line
        # ("peer_stages_ms") are published
        "stage_table_rep": stage_rep + 1,
        "peer_stage_rep": {GEF: gef_stage_rep + 1},
        "spread": {
            k: {
                "median": _median([n[k] for n in numbers]),
                "min": float(np.nanmin([n[k] for n in numbers])),
                "max": float(np.nanmax([n[k] for n in numbers])),
            }
            for k in REP_KEYS
        },
        "repeatable": repeatability(runs),
    }
    return out
