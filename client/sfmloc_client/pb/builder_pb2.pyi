from . import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class BuildState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    BUILD_STATE_UNSPECIFIED: _ClassVar[BuildState]
    BUILD_STATE_QUEUED: _ClassVar[BuildState]
    BUILD_STATE_RUNNING: _ClassVar[BuildState]
    BUILD_STATE_SUCCEEDED: _ClassVar[BuildState]
    BUILD_STATE_FAILED: _ClassVar[BuildState]
    BUILD_STATE_CANCELLED: _ClassVar[BuildState]
BUILD_STATE_UNSPECIFIED: BuildState
BUILD_STATE_QUEUED: BuildState
BUILD_STATE_RUNNING: BuildState
BUILD_STATE_SUCCEEDED: BuildState
BUILD_STATE_FAILED: BuildState
BUILD_STATE_CANCELLED: BuildState

class ColmapInput(_message.Message):
    __slots__ = ("model_dir", "image_dir")
    MODEL_DIR_FIELD_NUMBER: _ClassVar[int]
    IMAGE_DIR_FIELD_NUMBER: _ClassVar[int]
    model_dir: str
    image_dir: str
    def __init__(self, model_dir: _Optional[str] = ..., image_dir: _Optional[str] = ...) -> None: ...

class PosedImagesInput(_message.Message):
    __slots__ = ("image_dir", "poses_file", "camera")
    IMAGE_DIR_FIELD_NUMBER: _ClassVar[int]
    POSES_FILE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    image_dir: str
    poses_file: str
    camera: _common_pb2.Camera
    def __init__(self, image_dir: _Optional[str] = ..., poses_file: _Optional[str] = ..., camera: _Optional[_Union[_common_pb2.Camera, _Mapping]] = ...) -> None: ...

class ImagesOnlyInput(_message.Message):
    __slots__ = ("image_dir", "camera", "matching")
    IMAGE_DIR_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    MATCHING_FIELD_NUMBER: _ClassVar[int]
    image_dir: str
    camera: _common_pb2.Camera
    matching: str
    def __init__(self, image_dir: _Optional[str] = ..., camera: _Optional[_Union[_common_pb2.Camera, _Mapping]] = ..., matching: _Optional[str] = ...) -> None: ...

class SubmitBuildRequest(_message.Message):
    __slots__ = ("name", "out_dir", "colmap", "posed_images", "images_only", "preset", "config_json", "stride")
    NAME_FIELD_NUMBER: _ClassVar[int]
    OUT_DIR_FIELD_NUMBER: _ClassVar[int]
    COLMAP_FIELD_NUMBER: _ClassVar[int]
    POSED_IMAGES_FIELD_NUMBER: _ClassVar[int]
    IMAGES_ONLY_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    CONFIG_JSON_FIELD_NUMBER: _ClassVar[int]
    STRIDE_FIELD_NUMBER: _ClassVar[int]
    name: str
    out_dir: str
    colmap: ColmapInput
    posed_images: PosedImagesInput
    images_only: ImagesOnlyInput
    preset: str
    config_json: str
    stride: int
    def __init__(self, name: _Optional[str] = ..., out_dir: _Optional[str] = ..., colmap: _Optional[_Union[ColmapInput, _Mapping]] = ..., posed_images: _Optional[_Union[PosedImagesInput, _Mapping]] = ..., images_only: _Optional[_Union[ImagesOnlyInput, _Mapping]] = ..., preset: _Optional[str] = ..., config_json: _Optional[str] = ..., stride: _Optional[int] = ...) -> None: ...

class SubmitBuildResponse(_message.Message):
    __slots__ = ("job_id",)
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    def __init__(self, job_id: _Optional[str] = ...) -> None: ...

class BuildEvent(_message.Message):
    __slots__ = ("job_id", "state", "stage", "fraction", "message", "elapsed_s", "bundle_path", "error")
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    STAGE_FIELD_NUMBER: _ClassVar[int]
    FRACTION_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    ELAPSED_S_FIELD_NUMBER: _ClassVar[int]
    BUNDLE_PATH_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    state: BuildState
    stage: str
    fraction: float
    message: str
    elapsed_s: float
    bundle_path: str
    error: str
    def __init__(self, job_id: _Optional[str] = ..., state: _Optional[_Union[BuildState, str]] = ..., stage: _Optional[str] = ..., fraction: _Optional[float] = ..., message: _Optional[str] = ..., elapsed_s: _Optional[float] = ..., bundle_path: _Optional[str] = ..., error: _Optional[str] = ...) -> None: ...

class BuildJob(_message.Message):
    __slots__ = ("job_id", "name", "state", "stage", "fraction", "message", "elapsed_s", "bundle_path", "error", "input_kind", "submitted_utc", "ended_utc")
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    STAGE_FIELD_NUMBER: _ClassVar[int]
    FRACTION_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    ELAPSED_S_FIELD_NUMBER: _ClassVar[int]
    BUNDLE_PATH_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    INPUT_KIND_FIELD_NUMBER: _ClassVar[int]
    SUBMITTED_UTC_FIELD_NUMBER: _ClassVar[int]
    ENDED_UTC_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    name: str
    state: BuildState
    stage: str
    fraction: float
    message: str
    elapsed_s: float
    bundle_path: str
    error: str
    input_kind: str
    submitted_utc: str
    ended_utc: str
    def __init__(self, job_id: _Optional[str] = ..., name: _Optional[str] = ..., state: _Optional[_Union[BuildState, str]] = ..., stage: _Optional[str] = ..., fraction: _Optional[float] = ..., message: _Optional[str] = ..., elapsed_s: _Optional[float] = ..., bundle_path: _Optional[str] = ..., error: _Optional[str] = ..., input_kind: _Optional[str] = ..., submitted_utc: _Optional[str] = ..., ended_utc: _Optional[str] = ...) -> None: ...

class WatchBuildRequest(_message.Message):
    __slots__ = ("job_id",)
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    def __init__(self, job_id: _Optional[str] = ...) -> None: ...

class ListBuildsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListBuildsResponse(_message.Message):
    __slots__ = ("jobs",)
    JOBS_FIELD_NUMBER: _ClassVar[int]
    jobs: _containers.RepeatedCompositeFieldContainer[BuildJob]
    def __init__(self, jobs: _Optional[_Iterable[_Union[BuildJob, _Mapping]]] = ...) -> None: ...

class GetBuildRequest(_message.Message):
    __slots__ = ("job_id",)
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    def __init__(self, job_id: _Optional[str] = ...) -> None: ...

class CancelBuildRequest(_message.Message):
    __slots__ = ("job_id",)
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    def __init__(self, job_id: _Optional[str] = ...) -> None: ...

class CancelBuildResponse(_message.Message):
    __slots__ = ("cancelled",)
    CANCELLED_FIELD_NUMBER: _ClassVar[int]
    cancelled: bool
    def __init__(self, cancelled: _Optional[bool] = ...) -> None: ...
