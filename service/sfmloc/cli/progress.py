"""Progress display for long commands: a bar per stage on a terminal, a log line every 10% (and
at the end of each stage) otherwise. Matches the builder's ``progress(stage, fraction, message)``
callback."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class ProgressPrinter:
    def __init__(self, stream: TextIO | None = None, width: int = 30) -> None:
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.width = width
        self.stage: str | None = None
        self.t_stage = time.perf_counter()
        self.last_decile = -1
        # (stage, time of its first event) in order, and the time of the last event: stage
        # durations for stage_times().
        self._starts: list[tuple[str, float]] = []
        self._t_last = self.t_stage

    def __call__(
        self, stage: str, fraction: float, message: str = "", t: float | None = None
    ) -> None:
        """One progress event. ``t``: when it happened, in seconds on the caller's clock (a
        builder job's events carry their time since the job started: a finished job's
        progress, replayed at once, still shows how long each stage took); default now."""
        fraction = min(max(float(fraction), 0.0), 1.0)
        now = time.perf_counter() if t is None else float(t)
        self._t_last = now
        if not self._starts or self._starts[-1][0] != stage:
            self._starts.append((stage, now))
        if stage != self.stage:
            if self.stage is not None and self.tty:
                self.stream.write("\n")
            self.stage = stage
            self.t_stage = now
            self.last_decile = -1
        elapsed = now - self.t_stage
        if self.tty:
            filled = int(round(fraction * self.width))
            bar = "#" * filled + "-" * (self.width - filled)
            msg = message if len(message) < 60 else message[:57] + "..."
            self.stream.write(
                f"\r{stage:>12s} [{bar}] {fraction * 100:5.1f}% {elapsed:6.1f}s {msg:<60s}"
            )
            if fraction >= 1.0:
                self.stream.write("\n")
                self.stage = None
            self.stream.flush()
            return
        decile = int(fraction * 10)
        if decile != self.last_decile or fraction >= 1.0:
            self.last_decile = decile
            self.stream.write(f"{stage:>12s} {fraction * 100:5.1f}% {elapsed:6.1f}s {message}\n")
            self.stream.flush()

    def stage_times(self) -> dict[str, float]:
        """Seconds per stage, in order: from a stage's first event to the next stage's first
        (the last stage: to the last event); a stage seen twice adds up."""
        out: dict[str, float] = {}
        ends = [t for _, t in self._starts[1:]] + [self._t_last]
        for (stage, t0), t1 in zip(self._starts, ends):
            out[stage] = out.get(stage, 0.0) + (t1 - t0)
        return out

    def close(self) -> None:
        if self.tty and self.stage is not None:
            self.stream.write("\n")
            self.stream.flush()
