"""The enumerations of the contract: a frame's localization status and how its 2D-3D matches
were found. One definition for the engine (``sfmloc.engine.types`` re-exports them), the
server and the client; on every wire (Zenoh msgpack, gRPC strings, JSON) they are their
string values, and they compare equal to them."""

from __future__ import annotations

import enum


class WireEnum(str, enum.Enum):
    """An enum whose members are their wire strings: equal to them, and printed, formatted,
    JSON-encoded and msgpack-packed as them (``enum.StrEnum`` needs Python 3.11)."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, format_spec: str) -> str:
        return format(str(self.value), format_spec)


class Status(WireEnum):
    """A frame's localization status."""

    TRACKING = "TRACKING"  # pose from tracked keypoints with verified 2D-3D matches
    RELOCALIZED = "RELOCALIZED"  # pose from global matching this frame, verified
    # A pose from global matching this frame that is not verified yet (weak geometric support):
    # the following frames confirm it by tracking from it. Its covariance is inflated.
    UNVERIFIED = "UNVERIFIED"
    LOST = "LOST"  # no pose


class Matching(WireEnum):
    """How a frame's 2D-3D matches were found."""

    NONE = "none"  # only matches tracked from the previous frame
    # guided matching around a pose: the tracked one, the prediction, or a client's prior (a
    # relocalization found around it, in a stream or a single image's Relocalize)
    GUIDED = "guided"
    GLOBAL = "global"  # global matching: relocalization from scratch
    # visual odometry beyond the map: the pose rests on session points the engine triangulated
    # from its own tracks in earlier map-posed frames (never map-verified; its covariance
    # carries those frames' uncertainty and grows with the distance from them)
    ODOMETRY = "odometry"
