"""What the engine returns for a frame."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sfmloc_client.enums import Matching, Status

from ..transforms import Rigid3d

__all__ = ["FrameResult", "Matching", "Status"]  # the enums are the contract's (sfmloc_client)


@dataclass
class FrameResult:
    status: Status
    stamp: float
    cam_from_world: Rigid3d | None = None  # raw estimate of this frame
    filtered_cam_from_world: Rigid3d | None = None  # Kalman-filtered
    inliers: int = 0
    detected: int = 0  # Harris keypoints this frame
    tracked: int = 0  # keypoints tracked from the previous frame
    tracked_3d: int = 0  # tracked keypoints with a verified 2D-3D match
    matching: Matching = Matching.NONE
    timings_ms: dict[str, float] = field(default_factory=dict)
    # the same stages in the engine thread's CPU time (``StageTimer.cpu``)
    cpu_timings_ms: dict[str, float] = field(default_factory=dict)
    message: str = ""  # why a frame is LOST, when known
    # 6x6 covariance of ``cam_from_world`` (None when LOST), order [rotation (rad, a small
    # rotation on the world side of world_from_cam), camera centre in world (map units)]:
    # see ``engine.pose.COVARIANCE_ORDER``.
    covariance: np.ndarray | None = None

    @property
    def world_from_cam(self) -> Rigid3d | None:
        return None if self.cam_from_world is None else self.cam_from_world.inverse()

    @property
    def filtered_world_from_cam(self) -> Rigid3d | None:
        fcfw = self.filtered_cam_from_world
        return None if fcfw is None else fcfw.inverse()

    @property
    def localized(self) -> bool:
        return self.status is not Status.LOST

    @property
    def latency_ms(self) -> float:
        return self.timings_ms.get("total", 0.0)
