"""What the engine returns for a frame."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from ..transforms import Rigid3d


class Status(str, enum.Enum):
    TRACKING = "TRACKING"  # pose from tracked keypoints with verified 2D-3D matches
    RELOCALIZED = "RELOCALIZED"  # pose from global matching this frame, verified
    # A pose from global matching this frame that is not verified yet (weak geometric support):
    # the following frames confirm it by tracking from it. Its covariance is inflated.
    UNVERIFIED = "UNVERIFIED"
    LOST = "LOST"  # no pose


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
    matching: str = "none"  # "none", "guided" or "global"
    timings_ms: dict[str, float] = field(default_factory=dict)
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
        return None if self.filtered_cam_from_world is None else self.filtered_cam_from_world.inverse()

    @property
    def localized(self) -> bool:
        return self.status is not Status.LOST

    @property
    def latency_ms(self) -> float:
        return self.timings_ms.get("total", 0.0)
