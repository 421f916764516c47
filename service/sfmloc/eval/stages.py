"""Where the milliseconds go: per-stage statistics of the engine's timers
(``FrameResult.timings_ms``, stages ``engine.timing.STAGES``) over a replayed sequence, as
printed by ``sfmloc replay`` and the bench report."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..engine.timing import STAGES

STAGE_COLUMNS = (
    "stage",
    "mean/frame",
    "share",
    "frames",
    "mean when run",
    "p95 when run",
    "p99 when run",
    "max",
)


def stage_stats(timings: Sequence[Mapping[str, float]]) -> dict[str, dict[str, float]]:
    """Per stage (pipeline order, then any other key, "total" last): ``mean`` ms per frame over
    all frames (a stage that did not run counts 0, so the means add up to the total's),
    ``share`` of the mean total, ``frames`` it ran in, and over those frames ``mean_run``,
    ``p95``, ``p99`` and ``max`` ms."""
    n = len(timings)
    if n == 0:
        return {}
    names = [k for k in STAGES if any(k in t for t in timings)]
    names += sorted({k for t in timings for k in t} - set(names) - {"total"})
    names += ["total"] if any("total" in t for t in timings) else []
    total_mean = float(np.mean([t.get("total", 0.0) for t in timings]))
    out = {}
    for k in names:
        ran = np.array([t[k] for t in timings if k in t], np.float64)
        mean = float(ran.sum() / n)
        out[k] = {
            "mean": mean,
            "share": mean / total_mean if total_mean > 0 else float("nan"),
            "frames": int(len(ran)),
            "mean_run": float(ran.mean()),
            "p95": float(np.percentile(ran, 95)),
            "p99": float(np.percentile(ran, 99)),
            "max": float(ran.max()),
        }
    return out


def stage_rows(stats: Mapping[str, Mapping[str, float]]) -> list[list[str]]:
    """The table's rows (``STAGE_COLUMNS``), milliseconds with one decimal."""
    return [
        [
            k,
            f"{s['mean']:.2f}",
            f"{100 * s['share']:.0f}%",
            str(s["frames"]),
            f"{s['mean_run']:.1f}",
            f"{s['p95']:.1f}",
            f"{s['p99']:.1f}",
            f"{s['max']:.1f}",
        ]
        for k, s in stats.items()
    ]


def format_stage_table(stats: Mapping[str, Mapping[str, float]]) -> str:
    """A plain-text table (ms), one line per stage."""
    rows = [list(STAGE_COLUMNS)] + stage_rows(stats)
    widths = [max(len(r[i]) for r in rows) for i in range(len(STAGE_COLUMNS))]
    return "\n".join(
        "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))
        for r in rows
    )
