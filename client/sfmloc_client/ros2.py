"""ROS 2 messages on Zenoh: poses out as ``geometry_msgs``, frames in as ``sensor_msgs``.

No ROS installation is needed: the few message types are written and read here in CDR (XCDR1,
little endian, the 4-byte encapsulation header ``00 01 00 00``, as ROS 2 serializes them), on
the key expressions ROS 2's Zenoh middleware uses:

- ``rmw_zenoh`` (``rmw_zenoh_cpp``, ROS 2 Jazzy and later): ``<domain_id>/<topic>/<dds type
  name>/<type hash>``, e.g. ``0/sfmloc/lab/drone1/pose/geometry_msgs::msg::dds_::PoseStamped_/
  RIHS01_10f3...``, each sample with rmw_zenoh's attachment (sequence number, source timestamp,
  publisher gid: without it rmw_zenoh drops the sample);
- ``ros2dds`` (``zenoh-bridge-ros2dds``): the topic name without its leading ``/``.

Topics, for map M and client C (names outside ``[A-Za-z0-9_]`` become ``_``, a token starting
with a digit gets a leading ``_``; ROS names allow nothing else):

- ``/sfmloc/M/C/pose`` ``geometry_msgs/msg/PoseStamped``, ``/sfmloc/M/C/pose_cov``
  ``geometry_msgs/msg/PoseWithCovarianceStamped``: the camera's optical frame (x right, y down,
  z forward, as REP 103's ``*_optical_frame``) in the map's frame (``header.frame_id``, one per
  map), stamped with the frame's own time; only localized frames (a LOST frame has no pose).
  Covariance in ROS order (x, y, z, rotation about x, y, z; the rotation a small one on the
  map side), i.e. our ``[rx ry rz cx cy cz]`` blocks swapped.
- ``/sfmloc/M/C/image`` ``sensor_msgs/msg/Image`` (mono8, bgr8, rgb8) and
  ``/sfmloc/M/C/image/compressed`` ``sensor_msgs/msg/CompressedImage`` (jpeg, png): frames in.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import WireError

# RIHS01 type hashes (ROS 2 Jazzy), checked in the tests against the hashes rosbags computes
# from the message definitions.
TYPE_HASHES = {
    "geometry_msgs/msg/PoseStamped": (
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
    ),
    "geometry_msgs/msg/PoseWithCovarianceStamped": (
        "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e"
    ),
    "sensor_msgs/msg/Image": (
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
    ),
    "sensor_msgs/msg/CompressedImage": (
        "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a"
    ),
}
POSE = "geometry_msgs/msg/PoseStamped"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
KEY_FORMATS = ("rmw_zenoh", "ros2dds")
_CDR_LE = b"\x00\x01\x00\x00"
_BAD = re.compile(r"[^A-Za-z0-9_]")
# Our covariance order [rx ry rz cx cy cz] -> ROS's [x y z rx ry rz].
_ROS_ORDER = np.array([3, 4, 5, 0, 1, 2])


def ros_name(token: str) -> str:
    """A map name or client id as a ROS name token."""
    t = _BAD.sub("_", token)
    return "_" + t if t[:1].isdigit() else t


def topic(map_name: str, client_id: str, leaf: str, prefix: str = "sfmloc") -> str:
    """``/prefix/<map>/<client>/<leaf>`` with the names made ROS tokens."""
    return f"/{prefix}/{ros_name(map_name)}/{ros_name(client_id)}/{leaf}"


def dds_type_name(ros_type: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` -> ``geometry_msgs::msg::dds_::PoseStamped_``."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def key_expr(ros_topic: str, ros_type: str, domain_id: int = 0, fmt: str = "rmw_zenoh") -> str:
    """The Zenoh key expression of a ROS 2 topic (see the module docstring)."""
    name = ros_topic.strip("/")
    if fmt == "ros2dds":
        return name
    if fmt != "rmw_zenoh":
        raise WireError(f"ROS 2 key format must be one of {', '.join(KEY_FORMATS)}, got {fmt!r}")
    return f"{int(domain_id)}/{name}/{dds_type_name(ros_type)}/{TYPE_HASHES[ros_type]}"


# rmw_zenoh's QoS field of a liveliness token: reliability:durability:history,depth:deadline
# s,ns:lifespan s,ns:liveliness,lease s,ns, empty where the default; ours: keep last 1.
QOS_KEEP_LAST_1 = "::,1:,:,:,,"


def mangle(name: str) -> str:
    """rmw_zenoh's mangling of a name inside a liveliness token: ``/`` becomes ``%``."""
    return name.replace("/", "%")


def liveliness_key(
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    kind: str,
    node_name: str,
    ros_topic: str | None = None,
    ros_type: str | None = None,
    qos: str = QOS_KEEP_LAST_1,
) -> str:
    """rmw_zenoh's graph token: ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/
    <enclave>/<namespace>/<node>[/<topic>/<dds type>/<type hash>/<qos>]`` (kind ``NN`` a
    node, ``MP`` a publisher, ``MS`` a subscription; enclave and namespace ``/``, mangled)."""
    key = f"@ros2_lv/{int(domain_id)}/{zid}/{node_id}/{entity_id}/{kind}/%/%/{mangle(node_name)}"
    if ros_topic is None or ros_type is None:
        return key
    return f"{key}/{mangle(ros_topic)}/{dds_type_name(ros_type)}/{TYPE_HASHES[ros_type]}/{qos}"


def rmw_attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's sample attachment: int64 sequence number, int64 source timestamp (ns), the
    16-byte publisher gid as a sequence (LEB128 length, then the bytes) - zenoh-ext's
    serialization of ``(int64, int64, std::array<uint8_t, 16>)``."""
    if len(gid) != 16:
        raise ValueError("a gid is 16 bytes")
    return struct.pack("<qqB", seq, stamp_ns, 16) + bytes(gid)


# ---------------------------------------------------------------------------- writing
class _Writer:
    def __init__(self) -> None:
        self.buf = bytearray()

    def align(self, n: int) -> None:
        self.buf += b"\x00" * (-len(self.buf) % n)

    def pack(self, fmt: str, *vals: float | int, align: int) -> None:
        self.align(align)
        self.buf += struct.pack("<" + fmt, *vals)

    def string(self, s: str) -> None:
        b = s.encode() + b"\x00"
        self.pack("I", len(b), align=4)
        self.buf += b

    def header(self, stamp_ns: int, frame_id: str) -> None:
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        self.pack("iI", sec, nsec, align=4)
        self.string(frame_id)

    def pose(
        self, position: Sequence[float] | np.ndarray, quat_xyzw: Sequence[float] | np.ndarray
    ) -> None:
        self.pack("3d", *map(float, position), align=8)
        self.pack("4d", *map(float, quat_xyzw), align=8)

    def payload(self) -> bytes:
        return _CDR_LE + bytes(self.buf)


def encode_pose_stamped(
    stamp_ns: int,
    frame_id: str,
    position: Sequence[float] | np.ndarray,
    quat_xyzw: Sequence[float] | np.ndarray,
) -> bytes:
    """``geometry_msgs/msg/PoseStamped`` in CDR."""
    w = _Writer()
    w.header(stamp_ns, frame_id)
    w.pose(position, quat_xyzw)
    return w.payload()


def ros_covariance(covariance: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """Our 6x6 ``[rx ry rz cx cy cz]`` covariance in ROS's ``[x y z rx ry rz]`` order."""
    C = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
    return C[np.ix_(_ROS_ORDER, _ROS_ORDER)]


def encode_pose_with_covariance(
    stamp_ns: int,
    frame_id: str,
    position: Sequence[float] | np.ndarray,
    quat_xyzw: Sequence[float] | np.ndarray,
    covariance: np.ndarray | tuple[float, ...],
) -> bytes:
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` in CDR (covariance in our order, 36
    values row-major; reordered here)."""
    w = _Writer()
    w.header(stamp_ns, frame_id)
    w.pose(position, quat_xyzw)
    w.pack("36d", *ros_covariance(covariance).ravel(), align=8)
    return w.payload()


def encode_image(
    stamp_ns: int, frame_id: str, image: np.ndarray, encoding: str | None = None
) -> bytes:
    """``sensor_msgs/msg/Image`` in CDR (mono8 for HxW, bgr8 for HxWx3 unless given)."""
    img = np.ascontiguousarray(image, dtype=np.uint8)
    enc = encoding or ("mono8" if img.ndim == 2 else "bgr8")
    h, w = img.shape[:2]
    wr = _Writer()
    wr.header(stamp_ns, frame_id)
    wr.pack("II", h, w, align=4)
    wr.string(enc)
    wr.pack("B", 0, align=1)  # is_bigendian
    wr.pack("I", img.strides[0], align=4)  # step
    wr.pack("I", img.nbytes, align=4)
    wr.buf += img.tobytes()
    return wr.payload()


def encode_compressed_image(stamp_ns: int, frame_id: str, fmt: str, data: bytes) -> bytes:
    """``sensor_msgs/msg/CompressedImage`` in CDR (``fmt``: "jpeg" or "png")."""
    w = _Writer()
    w.header(stamp_ns, frame_id)
    w.string(fmt)
    w.pack("I", len(data), align=4)
    w.buf += data
    return w.payload()


# ---------------------------------------------------------------------------- reading
class _Reader:
    def __init__(self, payload: bytes, what: str) -> None:
        if len(payload) < 4 or payload[:4] not in (_CDR_LE, b"\x00\x00\x00\x00"):
            raise WireError(f"{what}: not a little-endian CDR payload")
        self.buf = memoryview(payload)[4:]
        self.pos = 0
        self.what = what

    def _need(self, n: int) -> None:
        if self.pos + n > len(self.buf):
            raise WireError(f"{self.what}: truncated CDR payload")

    def unpack(self, fmt: str, align: int) -> tuple:
        self.pos += -self.pos % align
        size = struct.calcsize("<" + fmt)
        self._need(size)
        vals = struct.unpack_from("<" + fmt, self.buf, self.pos)
        self.pos += size
        return vals

    def octets(self, limit: int) -> bytes:
        (n,) = self.unpack("I", 4)
        if n > limit:
            raise WireError(f"{self.what}: {n} bytes, more than the {limit} allowed")
        self._need(n)
        b = bytes(self.buf[self.pos : self.pos + n])
        self.pos += n
        return b

    def string(self) -> str:
        b = self.octets(4096)
        try:
            return b.rstrip(b"\x00").decode()
        except UnicodeDecodeError:
            raise WireError(f"{self.what}: a string is not UTF-8") from None

    def header(self) -> tuple[int, str]:
        sec, nsec = self.unpack("iI", 4)
        if sec < 0 or nsec >= 1_000_000_000:
            raise WireError(f"{self.what}: invalid stamp {sec} s {nsec} ns")
        return sec * 1_000_000_000 + nsec, self.string()


@dataclass
class RosImage:
    """A decoded ``sensor_msgs`` image: raw pixels (``image``) or compressed ``data``."""

    stamp_ns: int
    frame_id: str
    encoding: str  # ROS encoding (mono8, bgr8, rgb8) or compressed format (jpeg, png)
    image: np.ndarray | None = None
    data: bytes | None = None


RAW_ENCODINGS = {"mono8": 1, "8uc1": 1, "bgr8": 3, "rgb8": 3, "8uc3": 3}


def decode_image(payload: bytes, max_bytes: int) -> RosImage:
    """A ``sensor_msgs/msg/Image`` (8-bit mono or 3-channel); ``WireError`` naming the problem
    otherwise."""
    r = _Reader(payload, "sensor_msgs/Image")
    stamp, frame_id = r.header()
    h, w = r.unpack("II", 4)
    enc = r.string().lower()
    (big,) = r.unpack("B", 1)
    (step,) = r.unpack("I", 4)
    data = r.octets(max_bytes)
    ch = RAW_ENCODINGS.get(enc)
    if ch is None:
        raise WireError(
            f"sensor_msgs/Image encoding {enc!r} is not supported (use mono8, bgr8 or rgb8)"
        )
    if h == 0 or w == 0 or step < w * ch or len(data) < step * h:
        raise WireError(
            f"sensor_msgs/Image {w}x{h} {enc}: step {step} and {len(data)} data bytes do not fit"
        )
    rows = np.frombuffer(data, np.uint8, count=step * h).reshape(h, step)[:, : w * ch]
    img = rows.reshape(h, w, ch) if ch == 3 else rows.reshape(h, w)
    if enc == "rgb8":
        img = img[:, :, ::-1]
    del big  # 8-bit data has no byte order
    return RosImage(stamp, frame_id, enc, image=np.ascontiguousarray(img))


def decode_compressed_image(payload: bytes, max_bytes: int) -> RosImage:
    """A ``sensor_msgs/msg/CompressedImage`` (jpeg or png, as image_transport's ``format``
    field names them, e.g. ``"bgr8; jpeg compressed bgr8"``)."""
    r = _Reader(payload, "sensor_msgs/CompressedImage")
    stamp, frame_id = r.header()
    fmt = r.string().lower()
    data = r.octets(max_bytes)
    kind = "png" if "png" in fmt else "jpeg" if ("jpeg" in fmt or "jpg" in fmt) else None
    if kind is None:
        raise WireError(f"sensor_msgs/CompressedImage format {fmt!r} is not jpeg or png")
    if not data:
        raise WireError("sensor_msgs/CompressedImage carries no data")
    return RosImage(stamp, frame_id, kind, data=data)
