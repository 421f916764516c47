"""The server <-> worker messages (``sfmloc.server.protocol``): every message survives the
framing unchanged, a malformed one is a ``ProtocolError`` naming the problem, and a worker's
result becomes the ``PoseMessage`` clients get."""

from __future__ import annotations

import socket
from multiprocessing.connection import Connection

import msgpack
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
