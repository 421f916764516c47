"""Protobuf (gRPC API) <-> the library's dataclasses, used by the client and the server alike."""

from __future__ import annotations

import math
from typing import Any

from .enums import Matching, Status
from .errors import WireError
from .pb import common_pb2, localization_pb2
from .wire import ENCODINGS, CameraSpec, ErrorInfo, PoseMessage, Transform, raw_size

STATUS_TO_PB = {
    Status.TRACKING.value: common_pb2.LOCALIZATION_STATUS_TRACKING,
    Status.RELOCALIZED.value: common_pb2.LOCALIZATION_STATUS_RELOCALIZED,
    Status.UNVERIFIED.value: common_pb2.LOCALIZATION_STATUS_UNVERIFIED,
    Status.LOST.value: common_pb2.LOCALIZATION_STATUS_LOST,
}
STATUS_FROM_PB = {v: k for k, v in STATUS_TO_PB.items()}
ENCODING_TO_PB = {
    "gray8": common_pb2.IMAGE_ENCODING_GRAY8,
    "bgr8": common_pb2.IMAGE_ENCODING_BGR8,
    "jpeg": common_pb2.IMAGE_ENCODING_JPEG,
    "png": common_pb2.IMAGE_ENCODING_PNG,
}
ENCODING_FROM_PB = {v: k for k, v in ENCODING_TO_PB.items()}


def camera_to_pb(cam: CameraSpec) -> common_pb2.Camera:
    return common_pb2.Camera(
        model=cam.model, width=cam.width, height=cam.height, params=list(cam.params)
    )


def camera_from_pb(pb: common_pb2.Camera) -> CameraSpec:
    if not pb.model:
        raise WireError("camera is missing (model, width, height, params)")
    return CameraSpec(pb.model, pb.width, pb.height, tuple(pb.params))


def image_to_pb(encoding: str, data: bytes, width: int = 0, height: int = 0) -> common_pb2.Image:
    if encoding not in ENCODING_TO_PB:
        raise WireError(f"encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    return common_pb2.Image(
        encoding=ENCODING_TO_PB[encoding], data=data, width=width, height=height
    )


def image_from_pb(pb: common_pb2.Image, camera: CameraSpec) -> tuple[str, bytes]:
    """``(encoding, data)`` of an image message, checked against the camera."""
    enc = ENCODING_FROM_PB.get(pb.encoding)
    if enc is None:
        raise WireError(
            f"image encoding is unset or unknown ({pb.encoding}); use GRAY8, BGR8, JPEG or PNG"
        )
    if not pb.data:
        raise WireError("image data is empty")
    if (pb.width or pb.height) and (pb.width, pb.height) != (camera.width, camera.height):
        raise WireError(
            f"image is {pb.width}x{pb.height}, the camera is {camera.width}x{camera.height}"
        )
    n = raw_size(enc, camera.width, camera.height)
    if n is not None and len(pb.data) != n:
        raise WireError(
            f"{enc} data of {len(pb.data)} bytes does not match {camera.width}x{camera.height} "
            f"({n} bytes expected)"
        )
    return enc, pb.data


def transform_to_pb(t: Transform | None) -> common_pb2.Rigid3d | None:
    return None if t is None else common_pb2.Rigid3d(quat_xyzw=list(t.quat_xyzw), t=list(t.t))


def transform_from_pb(pb: common_pb2.Rigid3d, present: bool) -> Transform | None:
    if not present:
        return None
    if len(pb.quat_xyzw) != 4 or len(pb.t) != 3:
        raise WireError("a Rigid3d needs 4 quaternion values and 3 translation values")
    q, t = tuple(float(v) for v in pb.quat_xyzw), tuple(float(v) for v in pb.t)
    if not all(math.isfinite(v) for v in q + t):
        raise WireError(f"a Rigid3d must be finite: quat_xyzw={list(q)}, t={list(t)}")
    if math.sqrt(sum(v * v for v in q)) < 1e-6:
        raise WireError(f"a Rigid3d quaternion must not be zero: quat_xyzw={list(q)}")
    return Transform(q, t)  # type: ignore[arg-type]


def pose_to_estimate_pb(p: PoseMessage) -> common_pb2.PoseEstimate:
    est = common_pb2.PoseEstimate(
        status=STATUS_TO_PB.get(p.status, common_pb2.LOCALIZATION_STATUS_UNSPECIFIED),
        inliers=p.inliers,
        latency_ms=p.latency_ms,
        counts=common_pb2.FrameCounts(
            detected=p.counts.get("detected", 0),
            tracked=p.counts.get("tracked", 0),
            tracked_3d=p.counts.get("tracked_3d", 0),
        ),
        matching=p.matching,
        message=p.message,
        covariance=list(p.covariance) if p.covariance is not None else [],
    )
    for field, value in (
        ("cam_from_world", p.cam_from_world),
        ("world_from_cam", p.world_from_cam),
        ("filtered_cam_from_world", p.filtered_cam_from_world),
        ("filtered_world_from_cam", p.filtered_world_from_cam),
    ):
        if value is not None:
            getattr(est, field).CopyFrom(transform_to_pb(value))
    return est


def pose_from_estimate_pb(
    est: common_pb2.PoseEstimate, seq: int | None = None, stamp_ns: int = 0
) -> PoseMessage:
    def tf(name: str) -> Transform | None:
        return transform_from_pb(getattr(est, name), est.HasField(name))

    return PoseMessage(
        seq=seq,
        stamp_ns=stamp_ns,
        status=STATUS_FROM_PB.get(est.status, Status.LOST.value),
        cam_from_world=tf("cam_from_world"),
        world_from_cam=tf("world_from_cam"),
        filtered_cam_from_world=tf("filtered_cam_from_world"),
        filtered_world_from_cam=tf("filtered_world_from_cam"),
        inliers=est.inliers,
        latency_ms=est.latency_ms,
        counts={
            "detected": est.counts.detected,
            "tracked": est.counts.tracked,
            "tracked_3d": est.counts.tracked_3d,
        },
        matching=est.matching or Matching.NONE.value,
        message=est.message,
        covariance=_covariance_from_pb(est.covariance),
    )


def _covariance_from_pb(values: Any) -> tuple[float, ...] | None:
    if len(values) == 0:
        return None
    if len(values) != 36:
        raise WireError(f"covariance must have 36 values (6x6, row-major), got {len(values)}")
    return tuple(float(v) for v in values)


def pose_to_update_pb(p: PoseMessage) -> localization_pb2.PoseUpdate:
    return localization_pb2.PoseUpdate(
        seq=p.seq or 0,
        stamp_ns=p.stamp_ns,
        pose=pose_to_estimate_pb(p),
        dropped=p.dropped,
        client_id=p.client_id,
        error_code="" if p.error is None else p.error.code,
        error_message="" if p.error is None else p.error.message,
    )


def pose_from_update_pb(u: localization_pb2.PoseUpdate) -> PoseMessage:
    p = pose_from_estimate_pb(u.pose, seq=u.seq, stamp_ns=u.stamp_ns)
    p.dropped = u.dropped
    p.client_id = u.client_id
    if u.error_code:
        p.error = ErrorInfo(u.error_code, u.error_message)
    return p
