"""The server <-> worker messages (``sfmloc.server.protocol``): every message survives the
framing unchanged, a malformed one is a ``ProtocolError`` naming the problem, and a worker's
result becomes the ``PoseMessage`` clients get."""

from __future__ import annotations

import os
import socket
from multiprocessing.connection import Connection

import msgpack
import numpy as np
import pytest

from sfmloc.childproc import ProtocolError
from sfmloc.server import protocol as P
from sfmloc_client.wire import Transform

CAM = ("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
TF = Transform((0.0, 0.0, 0.6, 0.8), (1.0, -2.0, 3.5))
POSE = P.PoseResult(
    "TRACKING",
    TF,
    Transform((0.0, 0.0, -0.6, 0.8), (0.5, 0.25, -1.0)),
    TF,
    None,
    42,
    300,
    250,
    120,
    "guided",
    9.5,
    "",
    tuple(float(i) for i in range(36)),
)

MESSAGES = [
    (P.TO_WORKER, P.Load(7, "room", 3, "/maps/room", "b1")),
    (P.TO_WORKER, P.Drop("room", 3)),
    (
        P.TO_WORKER,
        P.LocalizeFrame(5, "room", 3, 11, 123456789, CAM, "png", 7, 12.5, 900.0, data=b"\x89PNG"),
    ),
    (
        P.TO_WORKER,
        P.LocalizeFrame(5, "room", 3, 12, 1, CAM, "png", 8, prior=TF, data=b"x"),
    ),
    (P.TO_WORKER, P.Relocalize(8, "room", 3, CAM, "gray8", TF, 12.5, 2000.0, bytes(range(256)))),
    (P.TO_WORKER, P.Relocalize(9, "room", 3, CAM, "jpeg", None, data=b"")),
    (P.TO_WORKER, P.Reset(5)),
    (P.TO_WORKER, P.Close(5)),
    (P.TO_WORKER, P.Stop()),
    (P.TO_SERVER, P.Ready(1, 4242)),
    (P.TO_SERVER, P.Loaded(7, P.MapSummary(10, 20, 3, 2, 1.5, "b1", True), None, 12.0)),
    (P.TO_SERVER, P.Loaded(7, None, P.WorkerError("BundleError", "corrupt"), 1.0)),
    (P.TO_SERVER, P.Result(5, 11, 123456789, 3, "b1", POSE, None, 1.0, 11.0, 7)),
    (
        P.TO_SERVER,
        P.Result(5, 12, 0, 3, "", None, P.WorkerError("ImageDecodeError", "bad png"), 0.0, 1.0),
    ),
    (P.TO_SERVER, P.RelocResult(8, POSE, None, 80.0)),
    (
        P.TO_SERVER,
        P.Result(
            5,
            13,
            7,
            3,
            "b1",
            None,
            None,
            1.0,
            11.0,
            9,
            P.PoseBrief("TRACKING", "guided", 9.5, TF),
            b"\xa6status\xa8TRACKING",
        ),
    ),
]


@pytest.mark.parametrize("proto,msg", MESSAGES, ids=lambda v: type(v).__name__)
def test_every_message_survives_a_socket_pair(proto, msg):
    a, b = socket.socketpair()
    with Connection(a.detach()) as ours, Connection(b.detach()) as theirs:
        proto.send(ours, msg)
        got = proto.recv(theirs)
    assert type(got) is type(msg)
    assert got == msg  # payload included (data is compared by the dataclass too)


def test_a_message_for_the_other_side_or_malformed_is_refused_by_name():
    with pytest.raises(ProtocolError, match="unknown message 'ready'"):
        P.TO_WORKER.decode(P.TO_SERVER.encode(P.Ready(0, 1)))
    with pytest.raises(ProtocolError, match="Drop: expected 2 fields"):
        P.TO_WORKER.decode(msgpack.packb(["drop", "room"]))
    with pytest.raises(ProtocolError, match="non-empty array"):
        P.TO_WORKER.decode(msgpack.packb({"op": "stop"}))
    with pytest.raises(ProtocolError, match="undecodable"):
        P.TO_WORKER.decode(b"\xc1")
    bad_tf = P.PoseResult.to_wire(POSE)
    bad_tf[1] = [0.0, 1.0]
    with pytest.raises(ProtocolError, match="7 values"):
        P.TO_SERVER.decode(msgpack.packb(["reloc_result", 1, bad_tf, None, 1.0]))
    bad_prior = P.TO_WORKER.encode(P.LocalizeFrame(5, "room", 3, 1, 1, CAM, "png", data=b"x"))
    fields = msgpack.unpackb(bad_prior)
    fields[11] = [0.0, 1.0]  # LocalizeFrame.prior: 2 values instead of 7
    with pytest.raises(ProtocolError, match="a transform has 7 values"):
        P.TO_WORKER.decode(msgpack.packb(fields))


def test_a_result_becomes_the_clients_pose_message():
    p = P.pose_message(
        POSE,
        None,
        seq=11,
        stamp_ns=5,
        map_name="room",
        client_id="c",
        build_id="b1",
        server_id="s",
        latency_ms=12.5,
        dropped=2,
    )
    assert (p.seq, p.stamp_ns, p.status, p.map, p.client_id, p.build_id, p.server_id) == (
        11,
        5,
        "TRACKING",
        "room",
        "c",
        "b1",
        "s",
    )
    assert p.cam_from_world == TF and p.filtered_cam_from_world == TF
    assert p.world_from_cam == POSE.world_from_cam and p.filtered_world_from_cam is None
    assert p.counts == {"detected": 300, "tracked": 250, "tracked_3d": 120}
    assert (p.inliers, p.matching, p.engine_ms, p.latency_ms, p.dropped) == (
        42,
        "guided",
        9.5,
        12.5,
        2,
    )
    assert p.covariance == tuple(float(i) for i in range(36)) and p.error is None


def test_a_worker_error_becomes_the_same_error_code_as_the_exception():
    from sfmloc.errors import ImageDecodeError, MapNotFoundError

    err = P.WorkerError.of(MapNotFoundError("map 'x' is not loaded"))
    assert isinstance(err.exception(), MapNotFoundError)
    p = P.pose_message(None, err, seq=3, stamp_ns=0, map_name="x")
    assert p.status == "LOST" and p.error.code == "NOT_FOUND" and "not loaded" in p.message
    p = P.pose_message(None, ImageDecodeError("bad"), seq=3, stamp_ns=0, map_name="x")
    assert p.error.code == "INVALID_ARGUMENT"
    # an unexpected exception type travels as InternalError, reported as INTERNAL
    err = P.WorkerError.of(ZeroDivisionError("oops"))
    assert err.type == "InternalError" and "ZeroDivisionError" in err.message
    assert P.pose_message(None, err, seq=1, stamp_ns=0, map_name="x").error.code == "INTERNAL"


def test_pose_result_of_an_engine_result():
    """``PoseResult.of`` (every frame, on the worker) gives the four transforms as the engine's
    own ``Rigid3d`` conversions do: the quaternion of the inverse is the conjugate, bit for
    bit, on rotations from every branch of the matrix-to-quaternion conversion (trace > 0 and
    each diagonal element largest), and the covariance's 36 values in row-major order."""
    import numpy as np

    from sfmloc.engine.types import FrameResult, Matching, Status
    from sfmloc.transforms import Rigid3d

    rng = np.random.default_rng(3)
    rotations = [np.eye(3), np.diag([1.0, -1.0, -1.0]) @ _rot([0.0, 0.01, 0.02])]
    for axis in np.eye(3):  # near half turns about each axis: the other three branches
        rotations.append(_rot(axis * 3.0 + rng.normal(0, 0.05, 3)))
    rotations += [_rot(rng.normal(0, 1.5, 3)) for _ in range(200)]
    for R in rotations:
        T = Rigid3d(R, rng.normal(0, 10, 3))
        F = Rigid3d(_rot(rng.normal(0, 1.5, 3)) @ R, rng.normal(0, 10, 3))
        cov = rng.normal(size=(6, 6))
        r = FrameResult(
            Status.TRACKING,
            1.0,
            cam_from_world=T,
            filtered_cam_from_world=F,
            inliers=40,
            matching=Matching.GUIDED,
            covariance=cov,
        )
        p = P.PoseResult.of(r)
        for got, want in (
            (p.cam_from_world, T),
            (p.world_from_cam, T.inverse()),
            (p.filtered_cam_from_world, F),
            (p.filtered_world_from_cam, F.inverse()),
        ):
            assert got is not None
            q = tuple(float(v) for v in want.quat_xyzw)
            if q[3] == 0.0:  # a half turn: q and -q, the same rotation, either may come out
                assert got.quat_xyzw in (q, tuple(-v for v in q))
            else:
                assert got.quat_xyzw == q
            assert got.t == tuple(float(v) for v in want.translation)
        assert p.covariance == tuple(float(v) for v in cov.ravel())
        assert p.status == "TRACKING" and p.inliers == 40 and p.matching == Matching.GUIDED.value
    lost = P.PoseResult.of(FrameResult(Status.LOST, 1.0, message="no corners"))
    assert lost.cam_from_world is None and lost.world_from_cam is None
    assert lost.filtered_world_from_cam is None and lost.covariance is None
    assert lost.message == "no corners"


def _rot(rotvec):
    from sfmloc.transforms import Rigid3d

    return Rigid3d.from_rotvec(rotvec, [0.0, 0.0, 0.0]).rotation


@pytest.mark.parametrize("sizes", [(90, None), (90, 0), (90, 16385), (20000, 3_000_000)])
def test_write_frames_sends_the_bytes_of_two_send_bytes_in_one_call(sizes):
    """``write_frames`` (the pool's sender: a frame's header and its image in one ``writev``)
    writes exactly what ``send_bytes(header); send_bytes(data)`` writes, so the other side
    reads it with ``recv_bytes``; past the socket's buffer (3 MB through a 64 kB one) the
    partial writes go on where they stopped."""
    import threading

    from sfmloc.childproc import write_frames

    rng = np.random.default_rng(sizes[0])
    header = rng.integers(0, 256, sizes[0], dtype=np.uint8).tobytes()
    data = None if sizes[1] is None else rng.integers(0, 256, sizes[1], dtype=np.uint8).tobytes()
    streams = []
    for use_writev in (False, True):
        a, b = socket.socketpair()
        a.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 65536)
        got: list[bytes] = []
        with Connection(a.detach()) as ours, Connection(b.detach()) as theirs:
            raw = socket.socket(fileno=os.dup(theirs.fileno()))  # the bytes as they are
            reader = threading.Thread(target=_read_all, args=(raw, got))
            reader.start()
            if use_writev:
                write_frames(ours, header, data)
            else:
                ours.send_bytes(header)
                if data is not None:
                    ours.send_bytes(data)
            ours.close()
            reader.join(30)
            raw.close()
        streams.append(got[0])
    assert streams[0] == streams[1]
    assert len(streams[1]) == 4 + len(header) + (0 if data is None else 4 + len(data))
    # ... and read back as two messages
    a, b = socket.socketpair()
    with Connection(a.detach()) as ours, Connection(b.detach()) as theirs:
        t = threading.Thread(target=write_frames, args=(ours, header, data))
        t.start()
        assert theirs.recv_bytes() == header
        if data is not None:
            assert theirs.recv_bytes() == data
        t.join(30)


def test_write_frames_to_a_closed_peer_raises_oserror():
    from sfmloc.childproc import write_frames

    a, b = socket.socketpair()
    b.close()
    with Connection(a.detach()) as ours:
        with pytest.raises(OSError):
            write_frames(ours, b"header", b"x" * 100_000)
        ours.close()
        with pytest.raises(OSError):
            write_frames(ours, b"header", None)


def _read_all(sock: socket.socket, out: list[bytes]) -> None:
    chunks = []
    while True:
        c = sock.recv(1 << 20)
        if not c:
            out.append(b"".join(chunks))
            return
        chunks.append(c)


def test_a_worker_encoded_pose_is_the_pose_message_encode_pose_writes():
    """A stream frame's pose travels from the worker as its brief and the pose message's
    engine entries already encoded (``stream_pose``); the server adds its own fields around
    those bytes (``encode_pose_entries``, ``SessionManager._send_encoded``). What a client
    receives is byte for byte ``encode_pose`` of the pose message the server built from the
    whole ``PoseResult`` (``pose_message``), for tracked, filtered-less and LOST poses."""
    import numpy as np

    from sfmloc.engine.types import FrameResult, Matching, Status
    from sfmloc.transforms import Rigid3d
    from sfmloc_client.wire import decode_pose, encode_pose, encode_pose_entries

    rng = np.random.default_rng(5)
    T = Rigid3d(_rot(rng.normal(0, 1.5, 3)), rng.normal(0, 10, 3))
    F = Rigid3d(_rot(rng.normal(0, 1.5, 3)), rng.normal(0, 10, 3))
    results = [
        FrameResult(
            Status.TRACKING,
            1.0,
            cam_from_world=T,
            filtered_cam_from_world=F,
            inliers=40,
            detected=900,
            tracked=300,
            tracked_3d=120,
            matching=Matching.GUIDED,
            covariance=rng.normal(size=(6, 6)),
            timings_ms={"total": 7.25},
            cpu_timings_ms={"total": 7.0},
        ),
        FrameResult(Status.RELOCALIZED, 1.0, cam_from_world=T, matching=Matching.GLOBAL),
        FrameResult(Status.LOST, 1.0, message="no corners: 'é' \u2013 kept"),
    ]
    for r in results:
        brief, wire = P.stream_pose(r)
        msg = P.Result(5, 11, 123, 3, "b1", None, None, 1.0, 11.0, 7, brief, wire)
        a, b = socket.socketpair()
        with Connection(a.detach()) as ours, Connection(b.detach()) as theirs:
            P.TO_SERVER.send(ours, msg)
            got = P.TO_SERVER.recv(theirs)
        assert isinstance(got, P.Result) and got.pose is None and got.posed == brief
        whole = P.PoseResult.of(r)
        assert (brief.status, brief.matching, brief.engine_ms, brief.cam_from_world) == (
            whole.status,
            whole.matching,
            whole.engine_ms,
            whole.cam_from_world,
        )
        server = {
            "seq": 11,
            "stamp_ns": 123,
            "map_name": "room",
            "client_id": "c",
            "build_id": "b1",
            "server_id": "s",
            "latency_ms": 12.5,
            "dropped": 2,
        }
        want = P.pose_message(whole, None, **server)
        data = encode_pose_entries(got.pose_wire, **server)
        assert data == encode_pose(want)
        assert decode_pose(data) == want
