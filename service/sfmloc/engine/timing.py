"""Where a frame's milliseconds go: a per-frame stage timer, returned in
``FrameResult.timings_ms`` (no global state: each call of the engine owns its timer)."""

from __future__ import annotations

import time

# The engine's stages, in pipeline order (the keys of ``FrameResult.timings_ms`` besides
# "total"): Harris + BRIEF (and the downscale to the working size); TRACK-2D and
# ADD-GOOD-FEATURES; guided matching (DAISY of the pending keypoints, the scoped k-ANN
# search, verification); pose estimation with its covariance; the motion filter (prediction,
# input checks and the update); relocalization (recovery around the prediction and global
# matching with its RANSAC and verification).
STAGES = ("detect", "track", "match", "pose", "filter", "reloc")


class StageTimer:
    """Laps of one frame: ``lap(stage)`` charges the time since the previous lap (or the
    start) to ``stage``; ``total()`` adds "total" and returns the milliseconds per stage (wall
    clock: the frame's latency). ``cpu()`` returns the same laps in this thread's CPU time:
    on a loaded machine wall laps also count the time other processes held the core (~3x the
    CPU at load 8 on 2 cores), CPU laps say where this frame's work went."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.c0 = time.thread_time()
        self.last = self.t0
        self.clast = self.c0
        self.ms: dict[str, float] = {}
        self.cpu_ms: dict[str, float] = {}

    def lap(self, stage: str) -> None:
        now, cnow = time.perf_counter(), time.thread_time()
        self.ms[stage] = self.ms.get(stage, 0.0) + (now - self.last) * 1e3
        self.cpu_ms[stage] = self.cpu_ms.get(stage, 0.0) + (cnow - self.clast) * 1e3
        self.last, self.clast = now, cnow

    def total(self) -> dict[str, float]:
        self.ms["total"] = (time.perf_counter() - self.t0) * 1e3
        return self.ms

    def cpu(self) -> dict[str, float]:
        self.cpu_ms["total"] = (time.thread_time() - self.c0) * 1e3
        return self.cpu_ms
