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

    def __call__(self, stage: str, fraction: float, message: str = "") -> None:
        fraction = min(max(float(fraction), 0.0), 1.0)
        if stage != self.stage:
            if self.stage is not None and self.tty:
                self.stream.write("\n")
            self.stage = stage
            self.t_stage = time.perf_counter()
            self.last_decile = -1
        elapsed = time.perf_counter() - self.t_stage
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

    def close(self) -> None:
        if self.tty and self.stage is not None:
            self.stream.write("\n")
            self.stream.flush()
