from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ImageEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    IMAGE_ENCODING_UNSPECIFIED: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_GRAY8: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_BGR8: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_JPEG: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_PNG: _ClassVar[ImageEncoding]

class LocalizationStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    LOCALIZATION_STATUS_UNSPECIFIED: _ClassVar[LocalizationStatus]
    LOCALIZATION_STATUS_TRACKING: _ClassVar[LocalizationStatus]
    LOCALIZATION_STATUS_RELOCALIZED: _ClassVar[LocalizationStatus]
    LOCALIZATION_STATUS_LOST: _ClassVar[LocalizationStatus]
    LOCALIZATION_STATUS_UNVERIFIED: _ClassVar[LocalizationStatus]
IMAGE_ENCODING_UNSPECIFIED: ImageEncoding
IMAGE_ENCODING_GRAY8: ImageEncoding
IMAGE_ENCODING_BGR8: ImageEncoding
IMAGE_ENCODING_JPEG: ImageEncoding
IMAGE_ENCODING_PNG: ImageEncoding
LOCALIZATION_STATUS_UNSPECIFIED: LocalizationStatus
LOCALIZATION_STATUS_TRACKING: LocalizationStatus
LOCALIZATION_STATUS_RELOCALIZED: LocalizationStatus
LOCALIZATION_STATUS_LOST: LocalizationStatus
LOCALIZATION_STATUS_UNVERIFIED: LocalizationStatus

class Camera(_message.Message):
    __slots__ = ("model", "width", "height", "params")
    MODEL_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    PARAMS_FIELD_NUMBER: _ClassVar[int]
    model: str
    width: int
    height: int
    params: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, model: _Optional[str] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., params: _Optional[_Iterable[float]] = ...) -> None: ...

class Rigid3d(_message.Message):
    __slots__ = ("quat_xyzw", "t")
    QUAT_XYZW_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    quat_xyzw: _containers.RepeatedScalarFieldContainer[float]
    t: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, quat_xyzw: _Optional[_Iterable[float]] = ..., t: _Optional[_Iterable[float]] = ...) -> None: ...

class Image(_message.Message):
    __slots__ = ("encoding", "data", "width", "height")
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    encoding: ImageEncoding
    data: bytes
    width: int
    height: int
    def __init__(self, encoding: _Optional[_Union[ImageEncoding, str]] = ..., data: _Optional[bytes] = ..., width: _Optional[int] = ..., height: _Optional[int] = ...) -> None: ...

class FrameCounts(_message.Message):
    __slots__ = ("detected", "tracked", "tracked_3d")
    DETECTED_FIELD_NUMBER: _ClassVar[int]
    TRACKED_FIELD_NUMBER: _ClassVar[int]
    TRACKED_3D_FIELD_NUMBER: _ClassVar[int]
    detected: int
    tracked: int
    tracked_3d: int
    def __init__(self, detected: _Optional[int] = ..., tracked: _Optional[int] = ..., tracked_3d: _Optional[int] = ...) -> None: ...

class PoseEstimate(_message.Message):
    __slots__ = ("status", "cam_from_world", "world_from_cam", "filtered_cam_from_world", "filtered_world_from_cam", "inliers", "latency_ms", "counts", "matching", "message", "covariance")
    STATUS_FIELD_NUMBER: _ClassVar[int]
    CAM_FROM_WORLD_FIELD_NUMBER: _ClassVar[int]
    WORLD_FROM_CAM_FIELD_NUMBER: _ClassVar[int]
    FILTERED_CAM_FROM_WORLD_FIELD_NUMBER: _ClassVar[int]
    FILTERED_WORLD_FROM_CAM_FIELD_NUMBER: _ClassVar[int]
    INLIERS_FIELD_NUMBER: _ClassVar[int]
    LATENCY_MS_FIELD_NUMBER: _ClassVar[int]
    COUNTS_FIELD_NUMBER: _ClassVar[int]
    MATCHING_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    status: LocalizationStatus
    cam_from_world: Rigid3d
    world_from_cam: Rigid3d
    filtered_cam_from_world: Rigid3d
    filtered_world_from_cam: Rigid3d
    inliers: int
    latency_ms: float
    counts: FrameCounts
    matching: str
    message: str
    covariance: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, status: _Optional[_Union[LocalizationStatus, str]] = ..., cam_from_world: _Optional[_Union[Rigid3d, _Mapping]] = ..., world_from_cam: _Optional[_Union[Rigid3d, _Mapping]] = ..., filtered_cam_from_world: _Optional[_Union[Rigid3d, _Mapping]] = ..., filtered_world_from_cam: _Optional[_Union[Rigid3d, _Mapping]] = ..., inliers: _Optional[int] = ..., latency_ms: _Optional[float] = ..., counts: _Optional[_Union[FrameCounts, _Mapping]] = ..., matching: _Optional[str] = ..., message: _Optional[str] = ..., covariance: _Optional[_Iterable[float]] = ...) -> None: ...
