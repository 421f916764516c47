"""What the engine returns for a frame."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from ..transforms import Rigid3d


class _WireEnum(str, enum.Enum):
    """An enum whose members are their wire strings: equal to them, and printed, formatted,
    JSON-encoded and msgpack-packed as them (``enum.StrEnum`` needs Python 3.11)."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, format_spec: str) -> str:
        return format(str(self.value), format_spec)


class Status(_WireEnum):
    """A frame's localization status; the value is the wire string."""

    TRACKING = "TRACKING"  # pose from tracked keypoints with verified 2D-3D matches
    RELOCALIZED = "RELOCALIZED"  # pose from global matching this frame, verified
    # A pose from global matching this frame that is not verified yet (weak geometric support):
    # the following frames confirm it by tracking from it. Its covariance is inflated.
    UNVERIFIED = "UNVERIFIED"
    LOST = "LOST"  # no pose


class Matching(_WireEnum):
    """How a frame's 2D-3D matches were found; the value is the wire string."""

    NONE = "none"  # only matches tracked from the previous frame
    GUIDED = "guided"  # guided matching around a pose (the tracked one, or the prediction)
    GLOBAL = "global"  # global matching: relocalization from scratch


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
