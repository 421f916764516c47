"""ROS 2 on Zenoh: poses as geometry_msgs, frames as sensor_msgs (``sfmloc_client.ros2``).

Checked against independent implementations: ``rosbags`` (a pure-Python ROS 2 CDR
(de)serializer that also computes RIHS01 type hashes from the message definitions) for the
messages and the type hashes of the key expressions, and Zenoh's own serializer (zenoh.ext) for
rmw_zenoh's attachment. A real server (real Zenoh sessions on loopback) publishes the poses.
"""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest

from sfmloc_client import ros2

rosbags = pytest.importorskip("rosbags", reason="rosbags (a dev dependency) decodes ROS 2 CDR")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from server_helpers import (  # noqa: E402
    client_zenoh,
    running_server,
    server_config,
    stream_lockstep,
    zenoh_endpoint,
)

TS = get_typestore(Stores.ROS2_JAZZY)


def rmw_key(topic: str, ros_type: str, domain: int = 0) -> str:
    """rmw_zenoh's documented topic key: <domain_id>/<topic>/<dds type>/<type hash>, built here
    from rosbags' hash, not ours."""
    pkg, kind, name = ros_type.split("/")
    return f"{domain}/{topic.strip('/')}/{pkg}::{kind}::dds_::{name}_/{TS.hash_rihs01(ros_type)}"


@pytest.mark.parametrize("ros_type", sorted(ros2.TYPE_HASHES))
def test_type_hashes_and_keys_match_the_definitions(ros_type):
    assert ros2.TYPE_HASHES[ros_type] == TS.hash_rihs01(ros_type)
    t = ros2.topic("lab-1", "7drone.a", "pose")
    assert t == "/sfmloc/lab_1/_7drone_a/pose"
    assert ros2.key_expr(t, ros_type, 5) == rmw_key(t, ros_type, 5)
    assert ros2.key_expr(t, ros_type, 5, "ros2dds") == "sfmloc/lab_1/_7drone_a/pose"


def test_pose_messages_decode_with_rosbags():
    rng = np.random.default_rng(0)
    pos, q = rng.normal(size=3), rng.normal(size=4)
    q /= np.linalg.norm(q)
    stamp = 1_700_000_123_456_789_012
    for frame_id in ("", "m", "sfmloc_room", "a" * 7):  # every string padding
        msg = TS.deserialize_cdr(
            ros2.encode_pose_stamped(stamp, frame_id, pos, q), "geometry_msgs/msg/PoseStamped"
        )
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(stamp, 10**9)
        assert msg.header.frame_id == frame_id
        p, o = msg.pose.position, msg.pose.orientation
        assert [p.x, p.y, p.z] == list(pos) and [o.x, o.y, o.z, o.w] == list(q)
    A = rng.normal(size=(6, 6))
    C = A @ A.T  # ours: [rx ry rz cx cy cz]
    msg = TS.deserialize_cdr(
        ros2.encode_pose_with_covariance(stamp, "f", pos, q, C.ravel()),
        "geometry_msgs/msg/PoseWithCovarianceStamped",
    )
    R = msg.pose.covariance.reshape(6, 6)  # ROS: [x y z rx ry rz]
    np.testing.assert_array_equal(R[:3, :3], C[3:, 3:])
    np.testing.assert_array_equal(R[3:, 3:], C[:3, :3])
    np.testing.assert_array_equal(R[:3, 3:], C[3:, :3])
    assert msg.pose.pose.position.x == pos[0]


def test_images_from_rosbags_decode():
    Image = TS.types["sensor_msgs/msg/Image"]
    Compressed = TS.types["sensor_msgs/msg/CompressedImage"]
    Header = TS.types["std_msgs/msg/Header"]
    Time = TS.types["builtin_interfaces/msg/Time"]
    hdr = Header(stamp=Time(sec=12, nanosec=34), frame_id="cam")
    rgb = np.arange(5 * 4 * 3, dtype=np.uint8).reshape(5, 4, 3)
    padded = np.zeros((5, 16), np.uint8)  # rows padded to a 16-byte step
    padded[:, :12] = rgb.reshape(5, 12)
    raw = TS.serialize_cdr(
        Image(
            header=hdr,
            height=5,
            width=4,
            encoding="rgb8",
            is_bigendian=0,
            step=16,
            data=padded.ravel(),
        ),
        "sensor_msgs/msg/Image",
    )
    img = ros2.decode_image(bytes(raw), 1 << 20)
    assert img.stamp_ns == 12 * 10**9 + 34 and img.frame_id == "cam"
    np.testing.assert_array_equal(img.image, rgb[:, :, ::-1])  # BGR
    assert ros2.decode_image(ros2.encode_image(1, "x", rgb[:, :, 0]), 1 << 20).image.shape == (5, 4)
    mine = TS.deserialize_cdr(ros2.encode_image(7, "x", rgb), "sensor_msgs/msg/Image")
    assert (mine.height, mine.width, mine.encoding, mine.step) == (5, 4, "bgr8", 12)
    comp = TS.serialize_cdr(
        Compressed(
            header=hdr,
            format="bgr8; jpeg compressed bgr8",
            data=np.frombuffer(b"\xff\xd8jpeg", np.uint8),
        ),
        "sensor_msgs/msg/CompressedImage",
    )
    c = ros2.decode_compressed_image(bytes(comp), 1 << 20)
    assert (c.encoding, c.data) == ("jpeg", b"\xff\xd8jpeg")
    from sfmloc_client.errors import WireError

    bad = TS.serialize_cdr(
        Image(
            header=hdr,
            height=5,
            width=4,
            encoding="32FC1",
            is_bigendian=0,
            step=16,
            data=padded.ravel(),
        ),
        "sensor_msgs/msg/Image",
    )
    with pytest.raises(WireError, match="32fc1"):
        ros2.decode_image(bytes(bad), 1 << 20)
    with pytest.raises(WireError, match="truncated"):
        ros2.decode_image(bytes(raw)[:40], 1 << 20)


def test_attachment_is_zenoh_ext_serialization():
    from zenoh import ZBytes
    from zenoh.ext import Int64, z_deserialize

    gid = bytes(range(16))
    att = ros2.rmw_attachment(42, 1_786_246_073_000_000, gid)
    seq, ts, g = z_deserialize(tuple[Int64, Int64, bytes], ZBytes(att))
    assert (seq, ts, g) == (42, 1_786_246_073_000_000, gid)


@pytest.fixture(scope="module")
def ros_server(world):
    ep = zenoh_endpoint()
    conf = server_config(world, ep, ros2={"enabled": True, "default_camera": world.camera_spec})
    with running_server(conf) as s:
        yield s, ep


class _Collector:
    def __init__(self, z, key: str) -> None:
        self.got: list[tuple[bytes, bytes | None]] = []
        self.cond = threading.Condition()
        self.sub = z.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        with self.cond:
            self.got.append((sample.payload.to_bytes(), att))
            self.cond.notify_all()

    def wait(self, n: int, timeout: float = 5.0) -> list:
        with self.cond:
            self.cond.wait_for(lambda: len(self.got) >= n, timeout)
            return list(self.got)


def test_server_publishes_ros2_poses(world, ros_server):
    from zenoh import ZBytes
    from zenoh.ext import Int64, z_deserialize

    _, ep = ros_server
    with client_zenoh(ep) as z:
        pose_c = _Collector(z, rmw_key("/sfmloc/room/rosbot/pose", "geometry_msgs/msg/PoseStamped"))
        cov_c = _Collector(
            z,
            rmw_key("/sfmloc/room/rosbot/pose_cov", "geometry_msgs/msg/PoseWithCovarianceStamped"),
        )
        poses = stream_lockstep(z, "room", "rosbot", world, n=20)
        localized = [p for p in poses if p.localized]
        assert len(localized) >= 15
        got = pose_c.wait(len(localized))
        got_cov = cov_c.wait(len(localized))
        tokens = [str(r.ok.key_expr) for r in z.liveliness().get("@ros2_lv/0/**", timeout=5)]
    # rmw_zenoh's graph (its design: @ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/
    # <enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>], '/' mangled to '%').
    node = r"@ros2_lv/0/(?P<zid>[0-9a-f]+)/0/0/NN/%/%/sfmloc_\w+"
    assert any(re.fullmatch(node, t) for t in tokens), tokens
    for topic, ros_type in (
        ("pose", "geometry_msgs/msg/PoseStamped"),
        ("pose_cov", "geometry_msgs/msg/PoseWithCovarianceStamped"),
    ):
        pkg, kind, name = ros_type.split("/")
        tail = (
            f"%sfmloc%room%rosbot%{topic}/{pkg}::{kind}::dds_::{name}_/"
            f"{TS.hash_rihs01(ros_type)}/::,1:,:,:,,"
        )
        assert any(
            re.fullmatch(r"@ros2_lv/0/[0-9a-f]+/0/\d+/MP/%/%/sfmloc_\w+/" + re.escape(tail), t)
            for t in tokens
        ), (tail, tokens)
    # Poses are published with congestion control DROP (the server never waits for a slow
    # subscriber), so a loaded machine may drop a few; every one that arrives must be exact.
    by_stamp = {p.stamp_ns: p for p in localized}
    assert len(got) >= 0.75 * len(localized) and len(got_cov) >= 0.75 * len(localized)
    seqs = []
    for payload, att in got:
        msg = TS.deserialize_cdr(payload, "geometry_msgs/msg/PoseStamped")
        assert msg.header.frame_id == "sfmloc_room"
        p = by_stamp[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec]  # LOST: none
        pos = msg.pose.position
        np.testing.assert_allclose([pos.x, pos.y, pos.z], p.world_from_cam.t, atol=1e-12)
        o = msg.pose.orientation
        np.testing.assert_allclose([o.x, o.y, o.z, o.w], p.world_from_cam.quat_xyzw, atol=1e-12)
        assert att is not None
        seqs.append(z_deserialize(tuple[Int64, Int64, bytes], ZBytes(att))[0])
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    for payload, _ in got_cov:
        cmsg = TS.deserialize_cdr(payload, "geometry_msgs/msg/PoseWithCovarianceStamped")
        assert cmsg.header.frame_id == "sfmloc_room"
        p = by_stamp[cmsg.header.stamp.sec * 10**9 + cmsg.header.stamp.nanosec]
        C = np.asarray(p.covariance).reshape(6, 6)
        R = cmsg.pose.covariance.reshape(6, 6)
        np.testing.assert_allclose(R[:3, :3], C[3:, 3:])
        np.testing.assert_allclose(R[3:, 3:], C[:3, :3])
        pos = cmsg.pose.pose.position
        np.testing.assert_allclose([pos.x, pos.y, pos.z], p.world_from_cam.t, atol=1e-12)


def test_frames_as_ros2_images_are_localized(world, ros_server):
    """CompressedImage (PNG) and Image (mono8) samples serialized by rosbags, on rmw_zenoh
    keys, come back as poses (msgpack and ROS) at the ground truth."""
    import zenoh

    from sfmloc_client import PoseSubscriber

    _, ep = ros_server
    Compressed = TS.types["sensor_msgs/msg/CompressedImage"]
    Image = TS.types["sensor_msgs/msg/Image"]
    Header = TS.types["std_msgs/msg/Header"]
    Time = TS.types["builtin_interfaces/msg/Time"]
    n = 12
    for client, kind in (("rospng", "compressed"), ("rosraw", "raw")):
        got: list = []
        with client_zenoh(ep) as z, PoseSubscriber(z, "room", client, callback=got.append) as ps:
            ros_poses = _Collector(
                z, rmw_key(f"/sfmloc/room/{client}/pose", "geometry_msgs/msg/PoseStamped")
            )
            topic = f"/sfmloc/room/{client}/image" + ("/compressed" if kind == "compressed" else "")
            ros_type = "sensor_msgs/msg/" + ("CompressedImage" if kind == "compressed" else "Image")
            # BLOCK, as FrameStreamer's frames: a frame of 300-560 kB is 5-9 of Zenoh's 64 kB
            # batches through a queue of 2, and with the default (DROP) Zenoh discards the whole
            # frame when its tx thread falls 50 ms behind. Under load the server then never got
            # a frame, and the test waited 20 s for its pose (2 of 45 runs; 0 of 30 with BLOCK).
            pub = z.declare_publisher(
                rmw_key(topic, ros_type), congestion_control=zenoh.CongestionControl.BLOCK
            )
            deadline = time.monotonic() + 20
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.01)
            for k in range(n):
                stamp = Time(sec=100 + k // 30, nanosec=int((k % 30) * 1e9 / 30))
                hdr = Header(stamp=stamp, frame_id="cam")
                if kind == "compressed":
                    msg = Compressed(
                        header=hdr, format="png", data=np.frombuffer(world.png[k], np.uint8)
                    )
                else:
                    g = world.gray[k]
                    msg = Image(
                        header=hdr,
                        height=g.shape[0],
                        width=g.shape[1],
                        encoding="mono8",
                        is_bigendian=0,
                        step=g.shape[1],
                        data=g.ravel(),
                    )
                pub.put(bytes(TS.serialize_cdr(msg, ros_type)))
                assert ps.wait_for(k, 20.0), f"no pose for {kind} frame {k}"
            ros_got = ros_poses.wait(sum(p.localized for p in got))
            pub.undeclare()
        assert [p.seq for p in got] == list(range(n))
        assert all(p.error is None for p in got), [p.error for p in got]
        loc = [p for p in got if p.localized]
        assert len(loc) >= n - 2 and len(ros_got) >= 0.75 * len(loc)
        for p in loc:
            gt = world.gt_cam_from_world[p.seq].inverse().translation
            assert np.linalg.norm(np.asarray(p.world_from_cam.t) - gt) < 0.05
            assert p.stamp_ns == (100 + p.seq // 30) * 10**9 + int((p.seq % 30) * 1e9 / 30)
