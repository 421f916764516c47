from . import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class RelocalizeRequest(_message.Message):
    __slots__ = ("map", "image", "camera", "prior_cam_from_world")
    MAP_FIELD_NUMBER: _ClassVar[int]
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    PRIOR_CAM_FROM_WORLD_FIELD_NUMBER: _ClassVar[int]
    map: str
    image: _common_pb2.Image
    camera: _common_pb2.Camera
    prior_cam_from_world: _common_pb2.Rigid3d
    def __init__(self, map: _Optional[str] = ..., image: _Optional[_Union[_common_pb2.Image, _Mapping]] = ..., camera: _Optional[_Union[_common_pb2.Camera, _Mapping]] = ..., prior_cam_from_world: _Optional[_Union[_common_pb2.Rigid3d, _Mapping]] = ...) -> None: ...

class RelocalizeResponse(_message.Message):
    __slots__ = ("pose",)
    POSE_FIELD_NUMBER: _ClassVar[int]
    pose: _common_pb2.PoseEstimate
    def __init__(self, pose: _Optional[_Union[_common_pb2.PoseEstimate, _Mapping]] = ...) -> None: ...

class StreamFrame(_message.Message):
    __slots__ = ("map", "client_id", "seq", "stamp_ns", "camera", "image", "prior_cam_from_world")
    MAP_FIELD_NUMBER: _ClassVar[int]
    CLIENT_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    PRIOR_CAM_FROM_WORLD_FIELD_NUMBER: _ClassVar[int]
    map: str
    client_id: str
    seq: int
    stamp_ns: int
    camera: _common_pb2.Camera
    image: _common_pb2.Image
    prior_cam_from_world: _common_pb2.Rigid3d
    def __init__(self, map: _Optional[str] = ..., client_id: _Optional[str] = ..., seq: _Optional[int] = ..., stamp_ns: _Optional[int] = ..., camera: _Optional[_Union[_common_pb2.Camera, _Mapping]] = ..., image: _Optional[_Union[_common_pb2.Image, _Mapping]] = ..., prior_cam_from_world: _Optional[_Union[_common_pb2.Rigid3d, _Mapping]] = ...) -> None: ...

class PoseUpdate(_message.Message):
    __slots__ = ("seq", "stamp_ns", "pose", "dropped", "client_id", "error_code", "error_message")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    DROPPED_FIELD_NUMBER: _ClassVar[int]
    CLIENT_ID_FIELD_NUMBER: _ClassVar[int]
    ERROR_CODE_FIELD_NUMBER: _ClassVar[int]
    ERROR_MESSAGE_FIELD_NUMBER: _ClassVar[int]
    seq: int
    stamp_ns: int
    pose: _common_pb2.PoseEstimate
    dropped: int
    client_id: str
    error_code: str
    error_message: str
    def __init__(self, seq: _Optional[int] = ..., stamp_ns: _Optional[int] = ..., pose: _Optional[_Union[_common_pb2.PoseEstimate, _Mapping]] = ..., dropped: _Optional[int] = ..., client_id: _Optional[str] = ..., error_code: _Optional[str] = ..., error_message: _Optional[str] = ...) -> None: ...

class MapInfo(_message.Message):
    __slots__ = ("name", "path", "build_id", "points", "descriptors", "images", "clusters", "memory_mb", "sessions", "loaded_utc", "submaps", "map_memory_mb", "resident_mb")
    NAME_FIELD_NUMBER: _ClassVar[int]
    PATH_FIELD_NUMBER: _ClassVar[int]
    BUILD_ID_FIELD_NUMBER: _ClassVar[int]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTORS_FIELD_NUMBER: _ClassVar[int]
    IMAGES_FIELD_NUMBER: _ClassVar[int]
    CLUSTERS_FIELD_NUMBER: _ClassVar[int]
    MEMORY_MB_FIELD_NUMBER: _ClassVar[int]
    SESSIONS_FIELD_NUMBER: _ClassVar[int]
    LOADED_UTC_FIELD_NUMBER: _ClassVar[int]
    SUBMAPS_FIELD_NUMBER: _ClassVar[int]
    MAP_MEMORY_MB_FIELD_NUMBER: _ClassVar[int]
    RESIDENT_MB_FIELD_NUMBER: _ClassVar[int]
    name: str
    path: str
    build_id: str
    points: int
    descriptors: int
    images: int
    clusters: int
    memory_mb: float
    sessions: int
    loaded_utc: str
    submaps: int
    map_memory_mb: float
    resident_mb: float
    def __init__(self, name: _Optional[str] = ..., path: _Optional[str] = ..., build_id: _Optional[str] = ..., points: _Optional[int] = ..., descriptors: _Optional[int] = ..., images: _Optional[int] = ..., clusters: _Optional[int] = ..., memory_mb: _Optional[float] = ..., sessions: _Optional[int] = ..., loaded_utc: _Optional[str] = ..., submaps: _Optional[int] = ..., map_memory_mb: _Optional[float] = ..., resident_mb: _Optional[float] = ...) -> None: ...

class ListMapsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListMapsResponse(_message.Message):
    __slots__ = ("maps",)
    MAPS_FIELD_NUMBER: _ClassVar[int]
    maps: _containers.RepeatedCompositeFieldContainer[MapInfo]
    def __init__(self, maps: _Optional[_Iterable[_Union[MapInfo, _Mapping]]] = ...) -> None: ...

class GetMapRequest(_message.Message):
    __slots__ = ("name",)
    NAME_FIELD_NUMBER: _ClassVar[int]
    name: str
    def __init__(self, name: _Optional[str] = ...) -> None: ...

class LoadMapRequest(_message.Message):
    __slots__ = ("path", "name")
    PATH_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    path: str
    name: str
    def __init__(self, path: _Optional[str] = ..., name: _Optional[str] = ...) -> None: ...

class UnloadMapRequest(_message.Message):
    __slots__ = ("name",)
    NAME_FIELD_NUMBER: _ClassVar[int]
    name: str
    def __init__(self, name: _Optional[str] = ...) -> None: ...

class UnloadMapResponse(_message.Message):
    __slots__ = ("unloaded", "sessions_closed")
    UNLOADED_FIELD_NUMBER: _ClassVar[int]
    SESSIONS_CLOSED_FIELD_NUMBER: _ClassVar[int]
    unloaded: bool
    sessions_closed: int
    def __init__(self, unloaded: _Optional[bool] = ..., sessions_closed: _Optional[int] = ...) -> None: ...

class SessionInfo(_message.Message):
    __slots__ = ("client_id", "map", "transport", "frames", "localized", "dropped", "last_latency_ms", "mean_latency_ms", "status", "idle_s")
    CLIENT_ID_FIELD_NUMBER: _ClassVar[int]
    MAP_FIELD_NUMBER: _ClassVar[int]
    TRANSPORT_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    LOCALIZED_FIELD_NUMBER: _ClassVar[int]
    DROPPED_FIELD_NUMBER: _ClassVar[int]
    LAST_LATENCY_MS_FIELD_NUMBER: _ClassVar[int]
    MEAN_LATENCY_MS_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    IDLE_S_FIELD_NUMBER: _ClassVar[int]
    client_id: str
    map: str
    transport: str
    frames: int
    localized: int
    dropped: int
    last_latency_ms: float
    mean_latency_ms: float
    status: _common_pb2.LocalizationStatus
    idle_s: float
    def __init__(self, client_id: _Optional[str] = ..., map: _Optional[str] = ..., transport: _Optional[str] = ..., frames: _Optional[int] = ..., localized: _Optional[int] = ..., dropped: _Optional[int] = ..., last_latency_ms: _Optional[float] = ..., mean_latency_ms: _Optional[float] = ..., status: _Optional[_Union[_common_pb2.LocalizationStatus, str]] = ..., idle_s: _Optional[float] = ...) -> None: ...

class ListSessionsRequest(_message.Message):
    __slots__ = ("map",)
    MAP_FIELD_NUMBER: _ClassVar[int]
    map: str
    def __init__(self, map: _Optional[str] = ...) -> None: ...

class ListSessionsResponse(_message.Message):
    __slots__ = ("sessions",)
    SESSIONS_FIELD_NUMBER: _ClassVar[int]
    sessions: _containers.RepeatedCompositeFieldContainer[SessionInfo]
    def __init__(self, sessions: _Optional[_Iterable[_Union[SessionInfo, _Mapping]]] = ...) -> None: ...

class ResetSessionRequest(_message.Message):
    __slots__ = ("client_id", "map")
    CLIENT_ID_FIELD_NUMBER: _ClassVar[int]
    MAP_FIELD_NUMBER: _ClassVar[int]
    client_id: str
    map: str
    def __init__(self, client_id: _Optional[str] = ..., map: _Optional[str] = ...) -> None: ...

class ResetSessionResponse(_message.Message):
    __slots__ = ("reset",)
    RESET_FIELD_NUMBER: _ClassVar[int]
    reset: bool
    def __init__(self, reset: _Optional[bool] = ...) -> None: ...
