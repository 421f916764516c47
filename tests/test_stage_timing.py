"""The per-stage timing table (``eval.stages``): exact statistics of given timers, stages in
pipeline order, and the engine's timer charging each lap to its stage."""

from __future__ import annotations

import time

import pytest

from sfmloc.engine.timing import STAGES, StageTimer
from sfmloc.eval.stages import format_stage_table, stage_stats


def test_stage_stats_means_over_all_frames_percentiles_over_the_frames_run():
    timings = [{"detect": 4.0, "track": 2.0, "total": 6.0} for _ in range(19)]
    timings.append({"detect": 4.0, "reloc": 40.0, "total": 44.0})
    st = stage_stats(timings)
    assert list(st) == ["detect", "track", "reloc", "total"]  # pipeline order, total last
    assert st["detect"]["mean"] == pytest.approx(4.0) and st["detect"]["frames"] == 20
    assert st["track"]["mean"] == pytest.approx(19 * 2.0 / 20) and st["track"]["frames"] == 19
    assert st["reloc"]["mean"] == pytest.approx(2.0) and st["reloc"]["frames"] == 1
    assert st["reloc"]["mean_run"] == st["reloc"]["p95"] == st["reloc"]["max"] == 40.0
    total = (19 * 6.0 + 44.0) / 20
    assert st["total"]["mean"] == pytest.approx(total)
    assert st["detect"]["share"] + st["track"]["share"] + st["reloc"]["share"] == pytest.approx(1.0)
    assert st["total"]["p95"] == pytest.approx(6.0 + 0.05 * 38.0)  # numpy's linear percentile
    text = format_stage_table(st).splitlines()
    assert text[0].split()[0] == "stage" and [r.split()[0] for r in text[1:]] == list(st)
    assert stage_stats([]) == {}


def test_unknown_stages_follow_the_known_ones():
    st = stage_stats([{"zeta": 1.0, "alpha": 1.0, "pose": 1.0, "total": 3.0}])
    assert list(st) == ["pose", "alpha", "zeta", "total"]


def test_stage_timer_charges_each_lap_to_its_stage():
    assert STAGES == ("detect", "track", "match", "pose", "filter", "reloc")
    t = StageTimer()
    time.sleep(0.01)
    t.lap("detect")
    t.lap("pose")
    time.sleep(0.005)
    t.lap("detect")  # a stage run twice adds up
    ms = t.total()
    assert ms["detect"] >= 14.0 and ms["pose"] < 5.0
    assert ms["detect"] + ms["pose"] == pytest.approx(ms["total"], abs=0.5)


def test_stage_timer_charges_cpu_time_to_the_stage_that_spent_it():
    """A stage that waits costs wall time, not CPU; one that computes costs both."""
    t = StageTimer()
    time.sleep(0.05)
    t.lap("filter")
    end = time.thread_time() + 0.02
    while time.thread_time() < end:  # 20 ms of this thread's CPU
        pass
    t.lap("detect")
    ms, cpu = t.total(), t.cpu()
    assert set(cpu) == set(ms) == {"filter", "detect", "total"}
    assert ms["filter"] >= 49.0 and cpu["filter"] < 5.0
    # (the thread's CPU clock and the monotonic clock disagree by up to ~0.06 ms here)
    assert 20.0 <= cpu["detect"] <= ms["detect"] + 0.5
    assert cpu["filter"] + cpu["detect"] == pytest.approx(cpu["total"], abs=0.5)
