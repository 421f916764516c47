"""Every message between the server and its engine workers (framing: ``sfmloc.childproc``).

Server -> worker: ``Load``, ``Drop``, ``LocalizeFrame`` (+ image), ``Relocalize`` (+ image),
``Reset``, ``Close``, ``Stop``. Worker -> server: ``Ready``, ``Loaded``, ``Result`` (a stream
frame), ``RelocResult`` (a single image). A failure travels as a ``WorkerError`` inside
``Loaded``/``Result``/``RelocResult`` and is rebuilt by class name from a fixed list
(``status.error_from_wire``), never unpickled.

Poses travel as ``PoseResult`` with the client's ``Transform`` (quat_xyzw, t), so the server
turns a result into a ``PoseMessage`` by copying fields, without another conversion.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from sfmloc_client.wire import CameraSpec, PoseMessage, Transform, pose_engine_entries

from ..childproc import Message, Part, Protocol, ProtocolError, payload
from ..engine.types import Status
from .status import error_from_wire, error_info, error_to_wire

# A camera as the worker needs it: (model, width, height, params). Hashable: the worker caches
# its ``Camera`` by it. Validated once by the server (``sessions.validate_camera``).
CameraTuple = tuple[str, int, int, tuple[float, ...]]


def camera_tuple(cam: CameraSpec) -> CameraTuple:
    return (cam.model, int(cam.width), int(cam.height), tuple(float(p) for p in cam.params))


def _camera_from_wire(v: Any) -> CameraTuple:
    model, width, height, params = v
    return (str(model), int(width), int(height), tuple(float(p) for p in params))


def _tf_to_wire(t: Transform | None) -> list[float] | None:
    return None if t is None else [*t.quat_xyzw, *t.t]


def _tf_from_wire(v: Any) -> Transform | None:
    if v is None:
        return None
    if len(v) != 7:
        raise ProtocolError(f"a transform has 7 values (quat_xyzw, t), got {len(v)}")
    return Transform(tuple(v[:4]), tuple(v[4:]))


def transform_of(T: Any) -> Transform | None:
    """An engine ``Rigid3d`` (or None) as the wire's ``Transform``."""
    if T is None:
        return None
    q, t = T.quat_xyzw, T.translation
    return Transform(
        (float(q[0]), float(q[1]), float(q[2]), float(q[3])),
        (float(t[0]), float(t[1]), float(t[2])),
    )


def transforms_of(T: Any) -> tuple[Transform | None, Transform | None]:
    """An engine ``Rigid3d`` ``tgt_from_src`` (or None) and its inverse as wire
    ``Transform``s, from one quaternion: the inverse's is the conjugate (x, y, z negated, the
    same w >= 0), which is what ``quat_xyzw_from_rotmat`` of the transposed matrix computes,
    bit for bit (Shepperd's branches see the same diagonal; only a rotation of exactly 180
    degrees, w = 0, may come out as the other of its two equal quaternions). Per frame on the
    worker: ``transform_of`` twice plus ``Rigid3d.inverse`` cost 4 quaternion conversions of
    numpy scalars, ~0.15 ms of the worker's CPU per pose (load ~13)."""
    if T is None:
        return None, None
    x, y, z, w = T.quat_xyzw.tolist()
    R, t = T.rotation, T.translation
    inv_t = (-(R.T @ t)).tolist()  # Rigid3d.inverse's translation, the same arithmetic
    return Transform((x, y, z, w), tuple(t.tolist())), Transform((-x, -y, -z, w), tuple(inv_t))


# ============================================================================ parts
@dataclass
class WorkerError(Part):
    """A failure on the worker: the exception's class name (from ``status``'s fixed list,
    else ``InternalError``) and its message."""

    type: str
    message: str

    @classmethod
    def of(cls, exc: BaseException) -> WorkerError:
        d = error_to_wire(exc)
        return cls(d["type"], d["message"])

    def exception(self) -> Exception:
        return error_from_wire({"type": self.type, "message": self.message})


@dataclass
class MapSummary(Part):
    points: int
    descriptors: int
    images: int
    clusters: int
    memory_mb: float
    build_id: str
    index_in_place: bool  # the faiss index reads the bundle's mapped file (shared by workers)


@dataclass
class PoseResult(Part):
    """An engine ``FrameResult`` as the server needs it (all four transforms: the inverses are
    computed on the worker rather than in the server's intake thread)."""

    status: str
    cam_from_world: Transform | None
    world_from_cam: Transform | None
    filtered_cam_from_world: Transform | None
    filtered_world_from_cam: Transform | None
    inliers: int
    detected: int
    tracked: int
    tracked_3d: int
    matching: str
    engine_ms: float
    message: str
    covariance: tuple[float, ...] | None  # 36 values, row-major 6x6; None when LOST
    # The engine's CPU time for the frame (its thread's, not wall): the server's CPU per pose
    # beyond it is the server's own cost (decoding, transport, scheduling).
    engine_cpu_ms: float = 0.0

    @classmethod
    def of(cls, r: Any) -> PoseResult:
        """From an engine ``FrameResult``."""
        cfw, wfc = transforms_of(r.cam_from_world)
        fcfw, fwfc = transforms_of(r.filtered_cam_from_world)
        return cls(
            status=r.status.value,
            cam_from_world=cfw,
            world_from_cam=wfc,
            filtered_cam_from_world=fcfw,
            filtered_world_from_cam=fwfc,
            inliers=int(r.inliers),
            detected=int(r.detected),
            tracked=int(r.tracked),
            tracked_3d=int(r.tracked_3d),
            matching=r.matching.value,
            engine_ms=float(r.latency_ms),
            message=r.message,
            covariance=None
            if r.covariance is None
            else tuple(np.asarray(r.covariance, dtype=np.float64).ravel().tolist()),
            engine_cpu_ms=float(r.cpu_timings_ms.get("total", 0.0)),
        )

    def to_wire(self) -> list[Any]:
        v = super().to_wire()
        for i in range(1, 5):
            v[i] = _tf_to_wire(getattr(self, _POSE_TFS[i - 1]))
        return v

    @classmethod
    def from_wire(cls, values: Any) -> PoseResult:
        p = super().from_wire(values)
        for name in _POSE_TFS:
            setattr(p, name, _tf_from_wire(getattr(p, name)))
        if p.covariance is not None:
            p.covariance = tuple(p.covariance)
        return p

    @property
    def counts(self) -> dict[str, int]:
        return {"detected": self.detected, "tracked": self.tracked, "tracked_3d": self.tracked_3d}


_POSE_TFS = (
    "cam_from_world",
    "world_from_cam",
    "filtered_cam_from_world",
    "filtered_world_from_cam",
)


@dataclass
class PoseBrief(Part):
    """What the server itself reads of a stream frame's pose (its turns, the session's state,
    metrics); the pose message's engine fields travel beside it already encoded
    (``Result.pose_wire``)."""

    status: str
    matching: str
    engine_ms: float
    cam_from_world: Transform | None

    def to_wire(self) -> list[Any]:
        return [self.status, self.matching, self.engine_ms, _tf_to_wire(self.cam_from_world)]

    @classmethod
    def from_wire(cls, values: Any) -> PoseBrief:
        b = super().from_wire(values)
        b.cam_from_world = _tf_from_wire(b.cam_from_world)
        return b


def stream_pose(r: Any) -> tuple[PoseBrief, bytes]:
    """An engine ``FrameResult`` as a stream frame's ``Result`` carries it: the brief the
    server reads, and the pose message's engine entries (``wire.pose_engine_entries``), which
    the server publishes as they are (the same bytes ``encode_pose`` writes)."""
    pose = PoseResult.of(r)
    msg = pose_message(pose, None, seq=None, stamp_ns=0, map_name="")
    return (
        PoseBrief(pose.status, pose.matching, pose.engine_ms, pose.cam_from_world),
        pose_engine_entries(msg),
    )


# ============================================================================ server -> worker
@dataclass
class Load(Message):
    OP = "load"
    req: int
    name: str
    gen: int
    path: str
    build_id: str


@dataclass
class Drop(Message):
    OP = "drop"
    name: str
    gen: int


@dataclass
class LocalizeFrame(Message):
    """One frame of a session (its image follows as the payload)."""

    OP = "frame"
    HAS_DATA = True
    sid: int
    map: str
    gen: int
    seq: int
    stamp_ns: int
    camera: CameraTuple
    encoding: str
    # The server's number for this dispatch, echoed in its Result: a result that comes back
    # after its frame was answered otherwise (time budget, worker death) is told from the
    # answer to a newer frame of the session, even when clients repeat seqs (gRPC's default 0).
    ticket: int = 0
    # The frame's time budget: ``deadline`` (time.monotonic(), one clock for the machine's
    # processes; 0: none): a frame not started by then is answered DEADLINE_EXCEEDED without
    # any work; ``cpu_budget_ms``: the most CPU it may use once started (0: no limit).
    deadline: float = 0.0
    cpu_budget_ms: float = 0.0
    # The client's outside estimate of cam_from_world (wire.Frame's ``prior``), None: none.
    prior: Transform | None = None
    data: bytes = payload()

    def to_wire(self) -> list[Any]:
        v = super().to_wire()
        v[10] = _tf_to_wire(self.prior)
        return v

    @classmethod
    def from_wire(cls, values: Any) -> LocalizeFrame:
        m = super().from_wire(values)
        m.camera = _camera_from_wire(m.camera)
        m.prior = _tf_from_wire(m.prior)
        return m


@dataclass
class Relocalize(Message):
    """One image, no session (its image follows as the payload)."""

    OP = "reloc"
    HAS_DATA = True
    req: int
    map: str
    gen: int
    camera: CameraTuple
    encoding: str
    prior: Transform | None  # cam_from_world prior, or None
    # The caller's deadline (time.monotonic(), one clock for every process of the machine; 0:
    # none): past it the work is dropped before it starts. budget_ms: the most time the work
    # may take once started (0: no limit), checked between the engine's stages.
    deadline: float = 0.0
    budget_ms: float = 0.0
    data: bytes = payload()

    def to_wire(self) -> list[Any]:
        v = super().to_wire()
        v[5] = _tf_to_wire(self.prior)
        return v

    @classmethod
    def from_wire(cls, values: Any) -> Relocalize:
        m = super().from_wire(values)
        m.camera = _camera_from_wire(m.camera)
        m.prior = _tf_from_wire(m.prior)
        return m


@dataclass
class Reset(Message):
    OP = "reset"
    sid: int


@dataclass
class Close(Message):
    OP = "close"
    sid: int


@dataclass
class Stop(Message):
    OP = "stop"


# ============================================================================ worker -> server
@dataclass
class Ready(Message):
    OP = "ready"
    index: int
    pid: int


@dataclass
class Loaded(Message):
    OP = "loaded"
    req: int
    summary: MapSummary | None
    error: WorkerError | None
    ms: float

    @classmethod
    def from_wire(cls, values: Any) -> Loaded:
        m = super().from_wire(values)
        m.summary = None if m.summary is None else MapSummary.from_wire(m.summary)
        m.error = None if m.error is None else WorkerError.from_wire(m.error)
        return m


@dataclass
class Result(Message):
    """The answer to a ``LocalizeFrame``: a pose, or an error."""

    OP = "result"
    sid: int
    seq: int
    stamp_ns: int
    gen: int
    build_id: str  # of the map the frame ran on ("" when it was not loaded)
    pose: PoseResult | None
    error: WorkerError | None
    decode_ms: float
    worker_ms: float
    ticket: int = 0  # the LocalizeFrame's
    # A pose as the engine worker sends it (``stream_pose``): ``pose`` is None, ``brief`` what
    # the server reads of it and ``pose_wire`` the pose message's engine entries, published as
    # they are. (``pose`` is the whole pose as values, for other senders: test workers.)
    brief: PoseBrief | None = None
    pose_wire: bytes = b""

    @property
    def posed(self) -> PoseResult | PoseBrief | None:
        """The pose's status, matching, engine_ms and cam_from_world (None: an error)."""
        return self.pose if self.pose is not None else self.brief

    @classmethod
    def from_wire(cls, values: Any) -> Result:
        m = super().from_wire(values)
        m.pose = None if m.pose is None else PoseResult.from_wire(m.pose)
        m.error = None if m.error is None else WorkerError.from_wire(m.error)
        m.brief = None if m.brief is None else PoseBrief.from_wire(m.brief)
        return m


@dataclass
class RelocResult(Message):
    """The answer to a ``Relocalize``."""

    OP = "reloc_result"
    req: int
    pose: PoseResult | None
    error: WorkerError | None
    worker_ms: float

    @classmethod
    def from_wire(cls, values: Any) -> RelocResult:
        m = super().from_wire(values)
        m.pose = None if m.pose is None else PoseResult.from_wire(m.pose)
        m.error = None if m.error is None else WorkerError.from_wire(m.error)
        return m


TO_WORKER = Protocol(Load, Drop, LocalizeFrame, Relocalize, Reset, Close, Stop)
TO_SERVER = Protocol(Ready, Loaded, Result, RelocResult)


def pose_message(
    pose: PoseResult | None,
    error: WorkerError | BaseException | None,
    *,
    seq: int | None,
    stamp_ns: int,
    map_name: str,
    client_id: str = "",
    build_id: str = "",
    server_id: str = "",
    latency_ms: float = 0.0,
    dropped: int = 0,
) -> PoseMessage:
    """A worker's pose (or error) for one frame or image as the ``PoseMessage`` clients get."""
    p = PoseMessage(
        seq=seq,
        stamp_ns=stamp_ns,
        status=Status.LOST.value,
        latency_ms=latency_ms,
        dropped=dropped,
        map=map_name,
        client_id=client_id,
        build_id=build_id,
        server_id=server_id,
    )
    if pose is None:
        exc = error.exception() if isinstance(error, WorkerError) else error
        p.error = error_info(exc if exc is not None else ProtocolError("no pose and no error"))
        p.message = p.error.message
        return p
    p.status = pose.status
    p.cam_from_world, p.world_from_cam = pose.cam_from_world, pose.world_from_cam
    p.filtered_cam_from_world = pose.filtered_cam_from_world
    p.filtered_world_from_cam = pose.filtered_world_from_cam
    p.inliers = pose.inliers
    p.engine_ms = pose.engine_ms
    p.engine_cpu_ms = pose.engine_cpu_ms
    p.counts = pose.counts
    p.matching = pose.matching
    p.message = pose.message
    p.covariance = pose.covariance
    return p
