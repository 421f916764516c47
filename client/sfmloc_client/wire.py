"""The Zenoh wire format of sfmloc: key expressions and msgpack messages, encoded and validated
by the same functions on both ends (the server imports this module).

Key expressions
===============

=====================================  ====  ==================================================
``sfmloc/<map>/<client>/frame``        in    a frame envelope (``Frame``), client -> server
``sfmloc/<map>/<client>/frame/<srv>``  in    the same, addressed to server ``<srv>`` only
``sfmloc/<map>/<client>/pose``         out   a pose message (``PoseMessage``), server -> client
``sfmloc/servers/<server-id>``               liveliness token of a running server
``sfmloc/servers/<server-id>/info``          queryable: ``ServerInfo`` (maps, sessions, load)
``sfmloc/maps/<name>``                       the builder announces a finished bundle
                                             (``MapAnnouncement``)
``sfmloc/bundles/<name>/<build-id>``         queryable of the builder: the bundle's files
                                             (``BundleFiles``), for servers without the path
``sfmloc/bundles/<name>/<build-id>/<file>``  queryable: ``?offset=N;size=M`` -> those bytes
=====================================  ====  ==================================================

``<map>`` and ``<client>`` are 1-64 characters of ``[A-Za-z0-9_.-]`` starting with a letter or
digit (they are single key-expression chunks and appear in file names).

Frame envelope (msgpack map; the image travels inside it, see "Why one envelope" below)::

    {"seq": uint, "stamp_ns": uint,
     "camera": {"model": "PINHOLE", "width": 640, "height": 480, "params": [fx, fy, cx, cy]},
     "encoding": "gray8" | "bgr8" | "jpeg" | "png",
     "data": bin,
     "source": str,            # optional: the sender's Zenoh session id (FrameStreamer sets it)
     "server": str,            # optional: the one server that answers it (see below)
     "prior": {"quat_xyzw": [x, y, z, w], "t": [tx, ty, tz]}}   # optional, see below

Raw encodings are row-major uint8, ``width*height`` (gray8) or ``width*height*3`` (bgr8) bytes.
A session belongs to the ``source`` of its first frame: frames under the same map and client id
from another source are refused (PERMISSION_DENIED) while the session is active, so two devices
given one id do not share (and corrupt) one track table; a source silent for a few seconds
(a device that restarted) is replaced by the new one, whose session starts afresh.
Unknown keys are ignored (newer clients may add some); missing or mistyped keys are errors.
``prior`` is an outside estimate of the frame's ``cam_from_world`` in the map's frame (the
client's last pose when it moves to another server, a GPS/IMU pose...). The server uses it only
when it has no motion prediction of its own for the session (its first frame, after a loss):
it looks for the frame around the prior (cheaper than global matching) before global matching;
a pose found so is a relocalization (``RELOCALIZED``/``UNVERIFIED``, judged like one). A wrong
prior costs time, not correctness. The quaternion need not be normalised (not zero).
With several servers hosting a map, a frame that names ``server`` is processed (and answered)
by that server only; the others ignore it silently. Without it every server hosting the map
answers. A frame naming a server is published on that server's key, ``.../frame/<srv>``, which
only that server subscribes to: the other servers never receive it (with N servers, N copies of
every image on the network and N decodes otherwise). ``FrameStreamer(server="auto")`` picks one
(``placement.py``: rendezvous hashing of the client id over the ready servers hosting the map)
and moves to another when its liveliness token drops.

Pose message (msgpack map), one per processed frame, and one per rejected frame::

    {"v": 1, "seq": uint | nil, "stamp_ns": uint,
     "status": "TRACKING" | "RELOCALIZED" | "UNVERIFIED" | "LOST",
     "cam_from_world": {"quat_xyzw": [4 floats], "t": [3 floats]} | nil,
     "covariance": [36 floats] | nil,
     "world_from_cam": {...} | nil,
     "filtered": {"cam_from_world": {...}, "world_from_cam": {...}} | nil,
     "inliers": uint, "latency_ms": float, "engine_ms": float, "engine_cpu_ms": float,
     "counts": {"detected": uint, "tracked": uint, "tracked_3d": uint},
     "matching": "none" | "guided" | "global" | "odometry", "dropped": uint,
     "map": str, "client_id": str, "build_id": str, "server_id": str,
     "message": str,
     "error": nil | {"code": "INVALID_ARGUMENT" | "NOT_FOUND" | "RESOURCE_EXHAUSTED" | ...,
                     "message": str}}

``latency_ms`` is the server's time from receiving the frame to publishing its pose (decode,
queueing, engine); ``engine_ms`` the engine's share, ``engine_cpu_ms`` the engine's CPU time
for the frame (0 from servers older than the field). ``dropped`` counts this client's frames the
server skipped so far because newer ones arrived while it was busy (latest-frame-only intake).
A frame the server cannot process gets a message with ``status: "LOST"`` and ``error`` set
(``seq`` is nil when the envelope was too broken to read it); ``error.code`` is a gRPC status
code name, the same the gRPC API would return for that failure. ``message`` says why a frame is
LOST when the engine knows.

``status``: ``TRACKING`` (tracked keypoints with verified 2D-3D matches), ``RELOCALIZED`` (global
matching this frame, verified by a strict geometric test), ``UNVERIFIED`` (global matching this
frame, not verified yet: the next frames confirm it by tracking from it, so treat it with care),
``LOST`` (no pose).

``covariance`` (every pose that is not LOST; nil otherwise): the 6x6 covariance of
``cam_from_world``, row-major, in this parameter order: ``[rx, ry, rz, cx, cy, cz]``, where
``r`` is a small rotation vector (radians) applied on the world side of the camera's rotation,
``R_world_from_cam' = exp([r]x) R_world_from_cam``, and ``c`` the camera centre in world
coordinates (map units). It comes from the final pose refinement (the reprojection residuals'
Gauss-Newton normal matrix, scaled by their variance). ``PoseMessage.covariance_matrix``
returns it as a numpy array.

Transforms are ``tgt_from_src`` (``x_tgt = R(quat_xyzw) x_src + t``), unit quaternions in
``x, y, z, w`` order with ``w >= 0``.

Why one envelope
================
The alternative (header as a Zenoh attachment, image as the payload) saves copying the image
into and out of the msgpack map. Measured on loopback at 640x480 (``sfmloc bench-transport
--only wire``): encode + decode 29 us (envelope) vs 6 us (attachment) for a raw gray8 frame
(307 kB), 12 vs 6 us for a JPEG (53 kB); publish -> decoded in the subscriber 0.17 vs 0.13 ms
(gray8) and 0.08 vs 0.08 ms (JPEG) at p50. Some 40 us against a ~10 ms engine step is not
worth two-part messages: one self-contained message is simpler to validate, record, replay
and bridge (storages keep payloads; other languages need only msgpack).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

from .cameras import CAMERA_MODELS, MAX_IMAGE_SIDE, camera_to_string, check_camera, parse_camera
from .enums import Status
from .errors import CameraModelError, MessageTooLargeError, WireError
from .keys import (
    BUNDLES_KEYEXPR,
    FRAME_KEYEXPR,
    MAPS_KEYEXPR,
    NAME_RE,
    ROOT,
    SERVER_INFO_KEYEXPR,
    SERVERS_KEYEXPR,
    addressed_frame_keyexpr,
    bundle_file_key,
    bundle_key,
    check_name,
    frame_key,
    map_announce_key,
    parse_frame_key,
    pose_key,
    server_info_key,
    server_token_key,
)

# The name rule, key expressions and camera table are defined in keys.py and cameras.py and
# re-exported here: this module is the specification of the Zenoh messages.
__all__ = [
    "BUNDLES_KEYEXPR",
    "CAMERA_MODELS",
    "COVARIANCE_ORDER",
    "DEFAULT_MAX_FRAME_BYTES",
    "ENCODINGS",
    "FRAME_KEYEXPR",
    "MAPS_KEYEXPR",
    "MAX_IMAGE_SIDE",
    "NAME_RE",
    "ROOT",
    "SERVERS_KEYEXPR",
    "SERVER_INFO_KEYEXPR",
    "STATUSES",
    "WIRE_VERSION",
    "BundleFiles",
    "CameraSpec",
    "ErrorInfo",
    "Frame",
    "MapAnnouncement",
    "PoseMessage",
    "ServerInfo",
    "Transform",
    "addressed_frame_keyexpr",
    "bundle_file_key",
    "bundle_key",
    "check_name",
    "decode_bundle_files",
    "decode_frame",
    "decode_map_announcement",
    "decode_pose",
    "decode_server_info",
    "encode_bundle_files",
    "encode_frame",
    "encode_map_announcement",
    "encode_pose",
    "encode_server_info",
    "frame_key",
    "map_announce_key",
    "parse_frame_key",
    "peek_seq",
    "pose_key",
    "raw_size",
    "server_info_key",
    "server_token_key",
    "transform_from_lists",
]

WIRE_VERSION = 1
ENCODINGS: tuple[str, ...] = ("gray8", "bgr8", "jpeg", "png")
STATUSES: tuple[str, ...] = tuple(s.value for s in Status)
# Order of the covariance's rows and columns (see the module docstring).
COVARIANCE_ORDER: tuple[str, ...] = ("rot_x", "rot_y", "rot_z", "center_x", "center_y", "center_z")
# Frames larger than this are rejected (RESOURCE_EXHAUSTED) unless the server is configured
# otherwise; 16 MiB holds a raw 4K BGR frame.
DEFAULT_MAX_FRAME_BYTES = 16 * 1024 * 1024


# ============================================================================ helpers
def _unpack(payload: bytes | bytearray | memoryview, max_bytes: int, what: str) -> dict[str, Any]:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise WireError(f"{what}: payload must be bytes, got {type(payload).__name__}")
    n = len(payload)
    if n > max_bytes:
        raise MessageTooLargeError(f"{what} of {n} bytes exceeds the limit of {max_bytes} bytes")
    try:
        obj = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            max_bin_len=max_bytes,
            max_str_len=1 << 20,
            max_array_len=1 << 16,
            max_map_len=1 << 10,
            max_ext_len=0,
        )
    except Exception as exc:  # noqa: BLE001 - msgpack raises many types on garbage
        raise WireError(f"{what} is not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict):
        raise WireError(f"{what} must be a msgpack map, got {type(obj).__name__}")
    return obj


def _pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _get(d: Mapping[str, Any], key: str, what: str) -> Any:
    if key not in d:
        raise WireError(f"{what}: missing key {key!r}")
    return d[key]


def _uint(v: Any, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise WireError(f"{name} must be a non-negative integer, got {v!r}")
    return int(v)


def _float(v: Any, name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise WireError(f"{name} must be a finite number, got {v!r}")
    return float(v)


# A list of only floats (not their subclasses) whose sum is finite has only finite values:
# ``_floats``' fast path. Every pose carries 64 such numbers (four transforms, the covariance):
# checked one by one they made decode_pose 23 us in a hot loop, 15.5 with this (issue 10: the
# client library's CPU per frame). Anything else (ints, bools, NaN, a sum that overflows) is
# checked one by one: the same values and errors.
_FLOAT_TYPE = {float}


def _plain_floats(v: Any, n: int | None) -> tuple[float, ...] | None:
    """``v`` as a tuple when it is a list of only floats (of length ``n`` if given) with a
    finite sum, else None (left to the value-by-value checks)."""
    if (
        type(v) is list
        and (n is None or len(v) == n)
        and set(map(type, v)) <= _FLOAT_TYPE
        and math.isfinite(sum(v))
    ):
        return tuple(v)
    return None


def _floats(v: Any, n: int | None, name: str) -> tuple[float, ...]:
    plain = _plain_floats(v, n)
    if plain is not None:
        return plain
    if not isinstance(v, (list, tuple)):
        raise WireError(f"{name} must be a list of numbers, got {type(v).__name__}")
    if n is not None and len(v) != n:
        raise WireError(f"{name} must have {n} numbers, got {len(v)}")
    return tuple(_float(x, name) for x in v)


def _str(v: Any, name: str) -> str:
    if not isinstance(v, str):
        raise WireError(f"{name} must be a string, got {type(v).__name__}")
    return v


# ============================================================================ camera
@dataclass(frozen=True)
class CameraSpec:
    """A COLMAP camera as it travels on the wire: model, size, parameters in COLMAP order."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        model, w, h, params = check_camera(self.model, self.width, self.height, self.params)
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "width", w)
        object.__setattr__(self, "height", h)
        object.__setattr__(self, "params", params)

    def to_wire(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "params": list(self.params),
        }

    @classmethod
    def from_wire(cls, d: Any) -> CameraSpec:
        """The camera of a message; a bad one makes the message malformed (``WireError``).
        A camera seen before (the same msgpack bytes) is the spec validated then."""
        if not isinstance(d, dict):
            raise WireError(
                f"camera must be a map with model, width, height, params; got {type(d).__name__}"
            )
        # Every frame carries its camera: validating it (check_camera, the frozen dataclass)
        # was ~16 us of the ~17 us decode_frame took in a hot loop, and several times that
        # in a live server (issue 10). The key is the camera's own encoding, so a hit is a
        # camera of exactly these values and types (640 and 640.0, 0.0 and -0.0, 1 and True
        # are different keys), which validates to the same spec; only valid ones are kept.
        try:
            key = _pack(d)
        except Exception:  # noqa: BLE001 - not encodable: validated (and refused) below
            key = None
        spec = _CAMERAS.get(key) if key is not None else None
        if spec is not None:
            return spec
        fields = [_get(d, k, "camera") for k in ("model", "width", "height", "params")]
        try:
            spec = cls(*fields)
        except CameraModelError as exc:
            raise WireError(str(exc)) from None
        if key is not None and len(key) <= _CAMERA_KEY_BYTES:
            if len(_CAMERAS) >= _CAMERAS_KEPT:
                _CAMERAS.clear()  # many cameras (or a client making up new ones): start over
            _CAMERAS[key] = spec
        return spec

    @classmethod
    def parse(cls, spec: str | Path) -> CameraSpec:
        """From a ``camera.json`` path or a ``"MODEL width height params..."`` string
        (``CameraModelError`` names the problem)."""
        return cls(*parse_camera(spec))

    def to_string(self) -> str:
        return camera_to_string(self.model, self.width, self.height, self.params)


# Validated cameras by their msgpack encoding (CameraSpec.from_wire): at most this many, of at
# most this many bytes each (a camera of a known model encodes in under 200 bytes).
_CAMERAS: dict[bytes, CameraSpec] = {}
_CAMERAS_KEPT = 256
_CAMERA_KEY_BYTES = 512


# ============================================================================ frames
def raw_size(encoding: str, width: int, height: int) -> int | None:
    """Bytes of a raw image, None for compressed encodings."""
    if encoding == "gray8":
        return width * height
    if encoding == "bgr8":
        return width * height * 3
    return None


@dataclass
class Frame:
    """One frame of a client's stream (the envelope)."""

    seq: int
    stamp_ns: int
    camera: CameraSpec
    encoding: str
    data: bytes
    source: str = ""  # the sender's Zenoh session id ("" : not given)
    server: str = ""  # the server id this frame is for ("" : every server hosting the map)
    prior: Transform | None = None  # an outside estimate of cam_from_world (see the module doc)

    def validate(self) -> Frame:
        _uint(self.seq, "seq")
        _uint(self.stamp_ns, "stamp_ns")
        if not isinstance(self.camera, CameraSpec):
            raise WireError("camera must be a CameraSpec")
        if self.encoding not in ENCODINGS:
            raise WireError(
                f"encoding must be one of {', '.join(ENCODINGS)}, got {self.encoding!r}"
            )
        if not isinstance(self.data, (bytes, bytearray, memoryview)) or len(self.data) == 0:
            raise WireError("data must be non-empty bytes")
        n = raw_size(self.encoding, self.camera.width, self.camera.height)
        if n is not None and len(self.data) != n:
            raise WireError(
                f"{self.encoding} data of {len(self.data)} bytes does not match the camera's "
                f"{self.camera.width}x{self.camera.height} ({n} bytes expected)"
            )
        if not isinstance(self.source, str) or len(self.source) > 64:
            raise WireError("source must be a string of at most 64 characters")
        if self.server:
            check_name(self.server, "server id")
        if self.prior is not None:
            if not isinstance(self.prior, Transform):
                raise WireError("prior must be a Transform (quat_xyzw, t)")
            q = _floats(self.prior.quat_xyzw, 4, "prior.quat_xyzw")
            _floats(self.prior.t, 3, "prior.t")
            if not 1e-6 < math.sqrt(sum(x * x for x in q)) < 1e6:
                raise WireError("prior.quat_xyzw must be a nonzero quaternion")
        return self


def encode_frame(frame: Frame) -> bytes:
    frame.validate()
    d = {
        "seq": frame.seq,
        "stamp_ns": frame.stamp_ns,
        "camera": frame.camera.to_wire(),
        "encoding": frame.encoding,
        "data": bytes(frame.data) if not isinstance(frame.data, bytes) else frame.data,
    }
    if frame.source:
        d["source"] = frame.source
    if frame.server:
        d["server"] = frame.server
    if frame.prior is not None:
        d["prior"] = frame.prior.to_wire()
    return _pack(d)


def decode_frame(
    payload: bytes | bytearray | memoryview, max_bytes: int = DEFAULT_MAX_FRAME_BYTES
) -> Frame:
    """Parse and validate a frame envelope; ``WireError`` (or a subclass) names the problem."""
    d = _unpack(payload, max_bytes, "frame envelope")
    what = "frame envelope"
    return Frame(
        seq=_uint(_get(d, "seq", what), "seq"),
        stamp_ns=_uint(_get(d, "stamp_ns", what), "stamp_ns"),
        camera=CameraSpec.from_wire(_get(d, "camera", what)),
        encoding=_str(_get(d, "encoding", what), "encoding"),
        data=_get(d, "data", what),
        source=_str(d.get("source", ""), "source"),
        server=_str(d.get("server", ""), "server"),
        prior=None if d.get("prior") is None else Transform.from_wire(d["prior"], "prior"),
    ).validate()


def peek_seq(payload: bytes | bytearray | memoryview) -> int | None:
    """The ``seq`` of a frame envelope that failed validation, when it can still be read (so an
    error reply can name the frame)."""
    try:
        d = msgpack.unpackb(payload, raw=False, max_bin_len=len(payload), max_ext_len=0)
        seq = d.get("seq") if isinstance(d, dict) else None
        return seq if isinstance(seq, int) and not isinstance(seq, bool) and seq >= 0 else None
    except Exception:  # noqa: BLE001
        return None


# ============================================================================ poses
@dataclass(frozen=True)
class Transform:
    """A rigid transform ``tgt_from_src`` as on the wire: unit quaternion (x, y, z, w) and t."""

    quat_xyzw: tuple[float, float, float, float]
    t: tuple[float, float, float]

    def to_wire(self) -> dict[str, Any]:
        return {"quat_xyzw": list(self.quat_xyzw), "t": list(self.t)}

    @classmethod
    def from_wire(cls, d: Any, name: str = "transform") -> Transform:
        if not isinstance(d, dict):
            raise WireError(f"{name} must be a map with quat_xyzw and t")
        q = _floats(_get(d, "quat_xyzw", name), 4, f"{name}.quat_xyzw")
        t = _floats(_get(d, "t", name), 3, f"{name}.t")
        return cls(q, t)  # type: ignore[arg-type]

    def rotation_matrix(self) -> Any:
        """3x3 numpy rotation matrix."""
        from .rotations import rotmat_from_quat_xyzw  # numpy, loaded when needed

        return rotmat_from_quat_xyzw(self.quat_xyzw)

    def matrix(self) -> Any:
        """4x4 homogeneous numpy matrix."""
        import numpy as np

        T = np.eye(4)
        T[:3, :3] = self.rotation_matrix()
        T[:3, 3] = self.t
        return T

    def inverse(self) -> Transform:
        import numpy as np

        R = self.rotation_matrix()
        t = -R.T @ np.asarray(self.t)
        x, y, z, w = self.quat_xyzw
        return Transform((-x, -y, -z, w), tuple(float(v) for v in t))  # type: ignore[arg-type]

    @property
    def position(self) -> tuple[float, float, float]:
        """``t`` of a ``world_from_cam`` transform is the camera centre in the world."""
        return self.t

    @classmethod
    def from_matrix(cls, T: Any) -> Transform:
        """From a 3x4 or 4x4 ``[R | t]`` (numpy), e.g. the engine's ``Rigid3d.matrix4()``:
        ``Transform.from_matrix(result.cam_from_world.matrix4())``."""
        import numpy as np

        from .rotations import quat_xyzw_from_rotmat

        M = np.asarray(T, dtype=np.float64)
        if M.shape not in ((3, 4), (4, 4)):
            raise WireError(f"expected a 3x4 or 4x4 matrix, got shape {M.shape}")
        q = quat_xyzw_from_rotmat(M[:3, :3])
        return cls(
            tuple(float(v) for v in q),  # type: ignore[arg-type]
            tuple(float(v) for v in M[:3, 3]),  # type: ignore[arg-type]
        )


@dataclass(frozen=True)
class ErrorInfo:
    code: str
    message: str

    def to_wire(self) -> dict[str, str]:
        return {"code": self.code, "message": self.message}


@dataclass
class PoseMessage:
    """The localization of one frame (Zenoh pose message, gRPC results are converted to it)."""

    seq: int | None
    stamp_ns: int
    status: str
    cam_from_world: Transform | None = None
    world_from_cam: Transform | None = None
    filtered_cam_from_world: Transform | None = None
    filtered_world_from_cam: Transform | None = None
    inliers: int = 0
    latency_ms: float = 0.0
    engine_ms: float = 0.0
    counts: dict[str, int] = field(default_factory=dict)
    matching: str = "none"
    dropped: int = 0
    map: str = ""
    client_id: str = ""
    build_id: str = ""
    server_id: str = ""
    message: str = ""
    error: ErrorInfo | None = None
    # 36 values, row-major 6x6 (order COVARIANCE_ORDER); None when LOST
    covariance: tuple[float, ...] | None = None
    engine_cpu_ms: float = 0.0  # the engine's CPU time for this frame (engine_ms is wall)

    @property
    def localized(self) -> bool:
        return self.status != Status.LOST and self.cam_from_world is not None

    @property
    def covariance_matrix(self) -> Any:
        """The covariance as a 6x6 numpy array (None when there is none)."""
        if self.covariance is None:
            return None
        import numpy as np

        return np.asarray(self.covariance, dtype=np.float64).reshape(6, 6)


def encode_pose(p: PoseMessage) -> bytes:
    return encode_pose_entries(
        pose_engine_entries(p),
        seq=p.seq,
        stamp_ns=p.stamp_ns,
        latency_ms=p.latency_ms,
        dropped=p.dropped,
        map_name=p.map,
        client_id=p.client_id,
        build_id=p.build_id,
        server_id=p.server_id,
        error=p.error,
    )


# A pose message is one msgpack map of 21 entries in two groups: the engine's result (11, below)
# and what the server adds (10, ``encode_pose_entries``). A server's engine worker packs the
# first group once (``pose_engine_entries``), and the server writes the map's header and its
# own entries before those bytes, without unpacking and repacking the transforms and the
# covariance (issue 10: ~19 us of Python per pose in a hot loop, ~10x that in the live server).
_POSE_ENGINE_ENTRIES = 11
_POSE_SERVER_ENTRIES = 10
_POSE_MAP_HEADER = b"\xde" + (_POSE_ENGINE_ENTRIES + _POSE_SERVER_ENTRIES).to_bytes(2, "big")


def pose_engine_entries(p: PoseMessage) -> bytes:
    """The msgpack map entries (no map header) of ``p``'s fields that come from the engine:
    status, the four transforms, inliers, engine_ms, engine_cpu_ms, counts, matching, message,
    covariance. ``encode_pose_entries`` makes the whole message of them."""
    filtered = None
    if p.filtered_cam_from_world is not None and p.filtered_world_from_cam is not None:
        filtered = {
            "cam_from_world": p.filtered_cam_from_world.to_wire(),
            "world_from_cam": p.filtered_world_from_cam.to_wire(),
        }
    # 11 entries: a fixmap, whose header is one byte (dropped)
    return _pack(
        {
            "status": p.status,
            "cam_from_world": None if p.cam_from_world is None else p.cam_from_world.to_wire(),
            "world_from_cam": None if p.world_from_cam is None else p.world_from_cam.to_wire(),
            "filtered": filtered,
            "inliers": p.inliers,
            "engine_ms": p.engine_ms,
            "engine_cpu_ms": p.engine_cpu_ms,
            "counts": dict(p.counts),
            "matching": p.matching,
            "message": p.message,
            "covariance": None if p.covariance is None else [float(v) for v in p.covariance],
        }
    )[1:]


def encode_pose_entries(
    engine: bytes,
    *,
    seq: int | None,
    stamp_ns: int,
    latency_ms: float,
    dropped: int,
    map_name: str,
    client_id: str,
    build_id: str,
    server_id: str,
    error: ErrorInfo | None = None,
) -> bytes:
    """The pose message of the engine's entries ``engine`` (``pose_engine_entries``) and the
    server's fields: byte for byte ``encode_pose`` of the same values."""
    return (
        _POSE_MAP_HEADER
        + _pack(
            {
                "v": WIRE_VERSION,
                "seq": seq,
                "stamp_ns": stamp_ns,
                "latency_ms": latency_ms,
                "dropped": dropped,
                "map": map_name,
                "client_id": client_id,
                "build_id": build_id,
                "server_id": server_id,
                "error": None if error is None else error.to_wire(),
            }
        )[1:]
        + engine
    )


def decode_pose(payload: bytes | bytearray | memoryview, max_bytes: int = 1 << 20) -> PoseMessage:
    d = _unpack(payload, max_bytes, "pose message")
    # Every client decodes a pose per frame: a message as servers write it (exact types, no
    # error) is read by ``_pose_as_written``, which accepts only what ``_pose_checked`` accepts
    # and gives the same values; anything else, and every refusal with its message, comes from
    # the field-by-field checks of ``_pose_checked``.
    try:
        return _pose_as_written(d)
    except _Unusual:
        return _pose_checked(d)


def _pose_checked(d: dict[str, Any]) -> PoseMessage:
    """The pose of a decoded message, every field checked (``WireError`` names the first
    problem)."""
    what = "pose message"
    status = _str(_get(d, "status", what), "status")
    if status not in STATUSES:
        raise WireError(f"status must be one of {', '.join(STATUSES)}, got {status!r}")
    seq = d.get("seq")
    seq = None if seq is None else _uint(seq, "seq")

    def tf(key: str, src: Any = d) -> Transform | None:
        v = src.get(key)
        return None if v is None else Transform.from_wire(v, key)

    filtered = d.get("filtered") or {}
    if not isinstance(filtered, dict):
        raise WireError("filtered must be a map or nil")
    err = d.get("error")
    if err is not None:
        if not isinstance(err, dict):
            raise WireError("error must be a map or nil")
        err = ErrorInfo(
            _str(err.get("code", ""), "error.code"), _str(err.get("message", ""), "error.message")
        )
    counts = d.get("counts") or {}
    if not isinstance(counts, dict):
        raise WireError("counts must be a map")
    cov = d.get("covariance")  # absent from servers older than the field: None
    cov = None if cov is None else _floats(cov, 36, "covariance")
    return PoseMessage(
        seq=seq,
        stamp_ns=_uint(d.get("stamp_ns", 0), "stamp_ns"),
        status=status,
        cam_from_world=tf("cam_from_world"),
        world_from_cam=tf("world_from_cam"),
        filtered_cam_from_world=tf("cam_from_world", filtered),
        filtered_world_from_cam=tf("world_from_cam", filtered),
        inliers=_uint(d.get("inliers", 0), "inliers"),
        latency_ms=_float(d.get("latency_ms", 0.0), "latency_ms"),
        engine_ms=_float(d.get("engine_ms", 0.0), "engine_ms"),
        engine_cpu_ms=_float(d.get("engine_cpu_ms", 0.0), "engine_cpu_ms"),
        counts={str(k): _uint(v, f"counts.{k}") for k, v in counts.items()},
        matching=_str(d.get("matching", "none"), "matching"),
        dropped=_uint(d.get("dropped", 0), "dropped"),
        map=_str(d.get("map", ""), "map"),
        client_id=_str(d.get("client_id", ""), "client_id"),
        build_id=_str(d.get("build_id", ""), "build_id"),
        server_id=_str(d.get("server_id", ""), "server_id"),
        message=_str(d.get("message", ""), "message"),
        error=err,
        covariance=cov,
    )


class _Unusual(Exception):
    """A message ``_pose_as_written`` leaves to ``decode_pose``'s field-by-field checks."""


_STATUS_SET = frozenset(STATUSES)


def _uint_as_written(v: Any) -> int:
    if type(v) is int and v >= 0:  # not a bool (its type is bool)
        return v
    raise _Unusual


def _float_as_written(v: Any) -> float:
    if type(v) is float and math.isfinite(v):
        return v
    raise _Unusual


def _str_as_written(v: Any) -> str:
    if type(v) is str:
        return v
    raise _Unusual


def _floats_as_written(v: Any, n: int) -> tuple[float, ...]:
    plain = _plain_floats(v, n)
    if plain is None:
        raise _Unusual
    return plain


def _transform_as_written(v: Any) -> Transform | None:
    if v is None:
        return None
    if type(v) is not dict:
        raise _Unusual
    return Transform(
        _floats_as_written(v.get("quat_xyzw"), 4),  # type: ignore[arg-type]
        _floats_as_written(v.get("t"), 3),  # type: ignore[arg-type]
    )


def _pose_as_written(d: dict[str, Any]) -> PoseMessage:
    """``decode_pose``'s pose of a message whose every field has the exact type a server
    writes (str, int, float, list, dict; no error): the same values the field-by-field checks
    give, without their per-field calls and messages (issue 10, the client's CPU per frame:
    decode_pose 16.3 -> 13.8 us in a hot loop, 4.1 of it msgpack's). Raises ``_Unusual`` for
    anything else."""
    status = d.get("status")
    if type(status) is not str or status not in _STATUS_SET or d.get("error") is not None:
        raise _Unusual
    seq = d.get("seq")
    filtered = d.get("filtered") or {}
    counts = d.get("counts") or {}
    cov = d.get("covariance")
    if type(filtered) is not dict or type(counts) is not dict:
        raise _Unusual
    counts_out = {k: v for k, v in counts.items() if type(k) is str and type(v) is int and v >= 0}
    if len(counts_out) != len(counts):
        raise _Unusual
    return PoseMessage(
        seq=None if seq is None else _uint_as_written(seq),
        stamp_ns=_uint_as_written(d.get("stamp_ns", 0)),
        status=status,
        cam_from_world=_transform_as_written(d.get("cam_from_world")),
        world_from_cam=_transform_as_written(d.get("world_from_cam")),
        filtered_cam_from_world=_transform_as_written(filtered.get("cam_from_world")),
        filtered_world_from_cam=_transform_as_written(filtered.get("world_from_cam")),
        inliers=_uint_as_written(d.get("inliers", 0)),
        latency_ms=_float_as_written(d.get("latency_ms", 0.0)),
        engine_ms=_float_as_written(d.get("engine_ms", 0.0)),
        engine_cpu_ms=_float_as_written(d.get("engine_cpu_ms", 0.0)),
        counts=counts_out,
        matching=_str_as_written(d.get("matching", "none")),
        dropped=_uint_as_written(d.get("dropped", 0)),
        map=_str_as_written(d.get("map", "")),
        client_id=_str_as_written(d.get("client_id", "")),
        build_id=_str_as_written(d.get("build_id", "")),
        server_id=_str_as_written(d.get("server_id", "")),
        message=_str_as_written(d.get("message", "")),
        error=None,
        covariance=None if cov is None else _floats_as_written(cov, 36),
    )


# ============================================================================ maps, servers
@dataclass(frozen=True)
class MapAnnouncement:
    """The builder's message on ``sfmloc/maps/<name>``: a bundle is ready at ``path`` (a folder
    on the builder's machine). A server that sees the same folder (shared storage) loads it
    there; one that does not fetches the bundle from the builder (``sfmloc/bundles/...``)."""

    name: str
    build_id: str
    path: str

    def __post_init__(self) -> None:
        check_name(self.name, "map name")
        _str(self.build_id, "build_id")
        if not _str(self.path, "path"):
            raise WireError("path must not be empty")


def encode_map_announcement(a: MapAnnouncement) -> bytes:
    return _pack({"name": a.name, "build_id": a.build_id, "path": a.path})


def decode_map_announcement(payload: bytes | bytearray | memoryview) -> MapAnnouncement:
    d = _unpack(payload, 1 << 16, "map announcement")
    w = "map announcement"
    return MapAnnouncement(_get(d, "name", w), _get(d, "build_id", w), _get(d, "path", w))


@dataclass(frozen=True)
class BundleFiles:
    """The builder's answer on ``sfmloc/bundles/<name>/<build-id>``: the bundle folder's files
    as ``(name, size in bytes)``. Integrity is the bundle's own: ``manifest.sha256`` covers the
    manifest, which holds every array file's SHA-256; the fetching server verifies both."""

    files: tuple[tuple[str, int], ...]

    def __post_init__(self) -> None:
        for name, size in self.files:
            check_name(name, "bundle file name")
            _uint(size, "file size")

    @property
    def total_bytes(self) -> int:
        return sum(size for _, size in self.files)


def encode_bundle_files(b: BundleFiles) -> bytes:
    return _pack({"files": [[n, s] for n, s in b.files]})


def decode_bundle_files(payload: bytes | bytearray | memoryview) -> BundleFiles:
    d = _unpack(payload, 1 << 20, "bundle file list")
    rows = _get(d, "files", "bundle file list")
    if not isinstance(rows, list) or not all(
        isinstance(r, list) and len(r) == 2 and isinstance(r[0], str) for r in rows
    ):
        raise WireError("bundle file list: 'files' must be a list of [name, size] pairs")
    return BundleFiles(tuple((r[0], r[1]) for r in rows))


@dataclass
class ServerInfo:
    """What ``sfmloc/servers/<id>/info`` answers."""

    server_id: str
    version: str = ""
    grpc: str = ""
    maps: list[dict[str, Any]] = field(default_factory=list)  # name, build_id, points, ...
    sessions: int = 0
    workers: int = 0
    load: dict[str, float] = field(default_factory=dict)  # frames_per_s, busy, ...
    ready: bool = False

    def to_wire(self) -> dict[str, Any]:
        return {
            "server_id": self.server_id,
            "version": self.version,
            "grpc": self.grpc,
            "maps": self.maps,
            "sessions": self.sessions,
            "workers": self.workers,
            "load": self.load,
            "ready": self.ready,
        }


def encode_server_info(info: ServerInfo) -> bytes:
    return _pack(info.to_wire())


def decode_server_info(payload: bytes | bytearray | memoryview) -> ServerInfo:
    d = _unpack(payload, 1 << 20, "server info")
    maps = d.get("maps", [])
    if not isinstance(maps, list) or not all(isinstance(m, dict) for m in maps):
        raise WireError("server info: maps must be a list of maps")
    load = d.get("load", {})
    if not isinstance(load, dict):
        raise WireError("server info: load must be a map")
    return ServerInfo(
        server_id=_str(_get(d, "server_id", "server info"), "server_id"),
        version=_str(d.get("version", ""), "version"),
        grpc=_str(d.get("grpc", ""), "grpc"),
        maps=maps,
        sessions=_uint(d.get("sessions", 0), "sessions"),
        workers=_uint(d.get("workers", 0), "workers"),
        load={str(k): _float(v, f"load.{k}") for k, v in load.items()},
        ready=bool(d.get("ready", False)),
    )


def transform_from_lists(quat_xyzw: Sequence[float], t: Sequence[float]) -> Transform:
    return Transform(tuple(float(v) for v in quat_xyzw), tuple(float(v) for v in t))  # type: ignore[arg-type]
