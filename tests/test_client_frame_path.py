"""The client library's per-frame path (issue 10: its CPU per frame), with real Zenoh and a real
server: a pose as servers write it is read by ``decode_pose``'s as-written path with exactly the
values of the field-by-field checks, any other message by those checks (refusals unchanged);
the streamer learns whether a server receives its frames from Zenoh's matching reports instead
of asking per frame, and still counts every frame no server could receive."""

from __future__ import annotations

import math
import threading

import msgpack
import pytest

from server_helpers import camera, client_zenoh, running_server, server_config, zenoh_endpoint
from sfmloc_client import (
    FrameStreamer,
    PoseMessage,
    PoseSubscriber,
    SourceFrame,
    Transform,
    WireError,
    decode_pose,
    encode_pose,
    wire,
)
from sfmloc_client.wire import pose_key


def _checked(payload: bytes) -> PoseMessage | str:
    """The field-by-field decoding alone: its pose, or its refusal's message."""
    try:
        return wire._pose_checked(wire._unpack(payload, 1 << 20, "pose message"))
    except WireError as exc:
        return f"{type(exc).__name__}: {exc}"


def _decoded(payload: bytes) -> PoseMessage | str:
    try:
        return decode_pose(payload)
    except WireError as exc:
        return f"{type(exc).__name__}: {exc}"


def _as_written(payload: bytes) -> PoseMessage:
    return wire._pose_as_written(msgpack.unpackb(payload, raw=False))


@pytest.fixture(scope="module")
def server(world):
    ep = zenoh_endpoint()
    with running_server(server_config(world, ep, server_id="frame-path")) as srv:
        yield srv, ep


def test_poses_a_server_sends_are_read_as_written_with_the_checked_values(world, server):
    """Every pose message of a real stream (and the error answer to a frame for a map the
    server does not host) decodes to what the field-by-field checks give; the server's poses
    take the as-written path (a message it refuses would fall back, silently costing ~2x)."""
    _, ep = server
    raw: list[bytes] = []
    lock = threading.Lock()

    def keep(sample) -> None:
        with lock:
            raw.append(sample.payload.to_bytes())

    frames = [SourceFrame(data=world.png[k], encoding="png") for k in range(6)]
    with client_zenoh(ep) as z:
        sub = z.declare_subscriber(pose_key("room", "as-written"), keep)
        with (
            PoseSubscriber(z, "room", "as-written") as poses,
            FrameStreamer(z, "room", "as-written", camera(world), encoding="png") as fs,
        ):
            assert fs.wait_for_server(30)
            stats = fs.run(frames, lockstep=True, poses=poses, pose_timeout=30)
            got = [poses.get(30) for _ in range(stats.sent)]
        with PoseSubscriber(z, "nosuchmap", "as-written") as lost:
            with FrameStreamer(z, "nosuchmap", "as-written", camera(world), encoding="png") as fs:
                assert fs.wait_for_server(30)
                fs.publish(data=world.png[0], encoding="png")
                error = lost.get(30)
        sub.undeclare()
    assert [p.seq for p in got] == list(range(6)) and sum(p.localized for p in got) >= 5
    with lock:
        payloads = list(raw)
    assert len(payloads) == 6
    for payload, pose in zip(payloads, got):
        assert _as_written(payload) == _checked(payload) == pose
        assert pose.covariance is not None and len(pose.covariance) == 36
    assert error is not None and error.error is not None and error.error.code == "NOT_FOUND"
    assert _checked(encode_pose(error)) == error == decode_pose(encode_pose(error))
    with pytest.raises(wire._Unusual):  # an error answer is read by the checks
        _as_written(encode_pose(error))


def _pose() -> PoseMessage:
    T = Transform((0.0, 0.0, math.sin(0.25), math.cos(0.25)), (1.0, 2.0, 3.0))
    return PoseMessage(
        seq=7,
        stamp_ns=99,
        status="TRACKING",
        cam_from_world=T,
        world_from_cam=T.inverse(),
        filtered_cam_from_world=T,
        filtered_world_from_cam=T.inverse(),
        inliers=42,
        latency_ms=9.5,
        engine_ms=8.0,
        engine_cpu_ms=7.25,
        counts={"detected": 500, "tracked": 300, "tracked_3d": 120},
        matching="guided",
        dropped=3,
        map="lab",
        client_id="drone",
        build_id="b1",
        server_id="s1",
        covariance=tuple(float(i) * 1e-6 for i in range(36)),
    )


def _variants() -> list[tuple[str, object]]:
    """(path in the message, value): types and values a server does not write (ints for
    floats, bools, NaN, bytes, ...; some valid, most not), and an error answer's fields."""
    bad = [
        None,
        True,
        False,
        -1,
        1,
        2**64 - 1,
        1.5,
        float("nan"),
        float("inf"),
        -float("inf"),
        "x",
        b"x",
        [],
        {},
        [1.0] * 3,
        [1.0] * 4,
        [1, 2, 3],
        [True] * 3,
        [1e308] * 36,
        [0] * 36,
    ]
    keys = [
        "seq",
        "stamp_ns",
        "status",
        "inliers",
        "latency_ms",
        "engine_ms",
        "engine_cpu_ms",
        "matching",
        "dropped",
        "map",
        "client_id",
        "build_id",
        "server_id",
        "message",
        "covariance",
        "counts",
        "filtered",
        "error",
        "cam_from_world",
        "world_from_cam",
        "cam_from_world.quat_xyzw",
        "cam_from_world.t",
        "filtered.world_from_cam",
        "filtered.cam_from_world.t",
        "counts.detected",
        "error.code",
    ]
    out: list[tuple[str, object]] = [(k, v) for k in keys for v in bad]
    out += [
        ("counts", {b"detected": 1}),
        ("counts", {"detected": -1}),
        ("status", "LOST"),
        ("error", {"code": "NOT_FOUND", "message": "gone"}),
        ("error", {"code": 5}),
        ("filtered", None),
        ("covariance", None),
        ("cam_from_world", None),
    ]
    return out


def test_every_other_message_decodes_or_is_refused_exactly_as_the_checks_say():
    base = msgpack.unpackb(encode_pose(_pose()), raw=False)
    assert _as_written(encode_pose(_pose())) == _pose() == decode_pose(encode_pose(_pose()))
    for path, value in _variants():
        d = msgpack.unpackb(encode_pose(_pose()), raw=False)
        *parents, last = path.split(".")
        node = d
        for k in parents:
            if not isinstance(node.get(k), dict):
                node[k] = {}
            node = node[k]
        node[last] = value
        payload = msgpack.packb(d, use_bin_type=True)
        assert _decoded(payload) == _checked(payload), (path, value)
        del node[last]  # and the field missing
        payload = msgpack.packb(d, use_bin_type=True)
        assert _decoded(payload) == _checked(payload), (path, "missing")
    assert base == msgpack.unpackb(encode_pose(_pose()), raw=False)


def _reported(fs: FrameStreamer) -> bool:
    return fs._reported[id(fs._pub)][0][0]


def _until(cond, timeout: float = 30.0) -> bool:
    event = threading.Event()
    for _ in range(int(timeout / 0.01)):
        if cond():
            return True
        event.wait(0.01)
    return cond()


def test_the_streamer_follows_its_server_from_zenoh_reports_and_counts_frames_lost(world):
    """A frame is counted undelivered exactly when no server subscribes: before the server,
    while it serves (Zenoh's report: no question per frame), and after it stopped."""
    ep = zenoh_endpoint()
    with client_zenoh(ep) as z:
        got: list = []
        with (
            PoseSubscriber(z, "room", "reports", callback=got.append) as poses,
            FrameStreamer(z, "room", "reports", camera(world), encoding="png") as fs,
        ):
            assert not _reported(fs) and not fs.server_present()
            fs.publish(data=world.png[0], encoding="png")
            assert fs.undelivered == 1
            with running_server(server_config(world, ep)):
                assert fs.wait_for_server(60)
                assert _until(lambda: _reported(fs))  # Zenoh reported the match
                for k in range(1, 4):  # in lockstep: the server keeps only a newest frame
                    fs.publish(data=world.png[k], encoding="png")
                    assert poses.wait_for(k, 30)
                assert fs.undelivered == 1
            assert _until(lambda: not fs.server_present())
            assert _until(lambda: not _reported(fs))  # ... and that it is gone
            fs.publish(data=world.png[4], encoding="png")
            assert fs.undelivered == 2
        assert sorted(p.seq for p in got) == [1, 2, 3]
    assert fs._reported == {}  # the listener went with its publisher
