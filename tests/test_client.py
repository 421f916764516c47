"""sfmloc_client: import hygiene, wire formats, images, cameras, TUM output, and the client
commands (sfmloc stream / relocalize / maps / sessions / servers) against a real server."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import msgpack
import numpy as np
import pytest
import zenoh

from server_helpers import (
    camera,
    client_zenoh,
    running_server,
    server_config,
    zenoh_endpoint,
)
from sfmloc_client import (
    CameraSpec,
    ErrorInfo,
    Frame,
    FrameStreamer,
    ImageDataError,
    MapAnnouncement,
    MessageTooLargeError,
    PoseMessage,
    PoseSubscriber,
    ServerInfo,
    Transform,
    TumWriter,
    WireError,
    decode_frame,
    decode_image,
    decode_map_announcement,
    decode_pose,
    encode_frame,
    encode_image,
    encode_map_announcement,
    encode_pose,
    make_zenoh_config,
)
from sfmloc_client.convert import pose_from_estimate_pb, pose_to_estimate_pb
from sfmloc_client.errors import CameraModelError
from sfmloc_client.wire import (
    FRAME_KEYEXPR,
    addressed_frame_keyexpr,
    decode_server_info,
    encode_server_info,
    frame_key,
    parse_frame_key,
    pose_key,
)

CAM = CameraSpec("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))


# ----------------------------------------------------------------------------- hygiene
def test_client_imports_nothing_of_the_server_or_heavy_libraries():
    code = (
        "import sys\n"
        "import sfmloc_client, sfmloc_client.wire, sfmloc_client.grpc_client, "
        "sfmloc_client.streamer\n"
        "import sfmloc_client.subscriber, sfmloc_client.sources, sfmloc_client.images, "
        "sfmloc_client.convert\n"
        "import sfmloc_client.discovery, sfmloc_client.trajectory, sfmloc_client.zconfig\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('sfmloc', 'scipy', 'faiss', "
        "'pycolmap', 'cv2'))\n"
        "print(','.join(bad))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "", f"sfmloc_client imported {r.stdout.strip()}"


def test_every_lazy_export_is_typed_for_type_checkers():
    """Each name the package exports lazily (``_EXPORTS``) is declared in its stub
    (``__init__.pyi``) as a re-export from the same module: otherwise mypy sees it as Any and
    checks none of its uses (a report once passed a PoseMessage where a Transform belongs,
    unnoticed)."""
    import ast
    from pathlib import Path

    import sfmloc_client

    stub = Path(sfmloc_client.__file__).with_suffix(".pyi")
    typed = {}
    for node in ast.parse(stub.read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            for a in node.names:
                assert a.asname == a.name  # an explicit re-export
                typed[a.name] = node.module
    assert typed == sfmloc_client._EXPORTS


# ----------------------------------------------------------------------------- wire
def test_frame_round_trip_and_unknown_keys_are_ignored():
    data = bytes(range(256)) * 12
    f = Frame(7, 123456789, CAM, "gray8", data[: 64 * 48])
    back = decode_frame(encode_frame(f))
    assert (back.seq, back.stamp_ns, back.camera, back.encoding, back.data) == (
        7,
        123456789,
        CAM,
        "gray8",
        data[:3072],
    )
    extended = msgpack.unpackb(encode_frame(f))
    extended["future_field"] = {"x": 1}
    assert decode_frame(msgpack.packb(extended)).seq == 7


def _env(**changes):
    d = {
        "seq": 1,
        "stamp_ns": 2,
        "camera": CAM.to_wire(),
        "encoding": "gray8",
        "data": b"\x00" * (64 * 48),
    }
    d.update(changes)
    return msgpack.packb({k: v for k, v in d.items() if v is not ...})


@pytest.mark.parametrize(
    "payload, words",
    [
        (b"\xc1", "not valid msgpack"),
        (msgpack.packb("a string"), "must be a msgpack map"),
        (_env(seq=-1), "seq must be a non-negative integer"),
        (_env(seq=True), "seq must be a non-negative integer"),
        (_env(stamp_ns=1.5), "stamp_ns"),
        (_env(camera=...), "missing key 'camera'"),
        (
            _env(camera={"model": "PINHOLE", "width": 64, "height": 48, "params": [1, 2, 3]}),
            "takes 4 parameters",
        ),
        (
            _env(camera={"model": "PINHOLE", "width": 0, "height": 48, "params": [1, 1, 1, 1]}),
            "out of range",
        ),
        (
            _env(camera={"model": "FISHEYE", "width": 64, "height": 48, "params": [1]}),
            "unsupported camera model",
        ),
        (
            _env(
                camera={
                    "model": "PINHOLE",
                    "width": 64,
                    "height": 48,
                    "params": [1, 1, float("nan"), 1],
                }
            ),
            "finite",
        ),
        (_env(encoding="webp"), "encoding must be one of"),
        (_env(data=b"\x00" * 100), "does not match the camera"),
        (_env(encoding="jpeg", data=b""), "non-empty"),
        (_env(data="text"), "non-empty bytes"),
    ],
)
def test_frame_validation_names_the_problem(payload, words):
    with pytest.raises(WireError) as e:
        decode_frame(payload)
    assert words in str(e.value) and e.value.code == "INVALID_ARGUMENT"


def test_a_camera_seen_before_is_its_validated_spec_and_only_the_same_values_are():
    """Frames carry their camera each time; one whose encoding was validated before is that
    spec (not validated again), and only exactly the same values and types are: 64 and 64.0,
    0.0 and -0.0, 1 and True are different cameras, as validation sees them."""
    cam = {"model": "PINHOLE", "width": 64, "height": 48, "params": [50.0, 50.0, 32.0, 24.0]}
    first = decode_frame(_env(camera=cam)).camera
    assert decode_frame(_env(camera=dict(cam))).camera is first
    assert first == CAM
    as_float = decode_frame(_env(camera={**cam, "width": 64.0})).camera
    assert as_float == first and as_float is not first  # validated: 64.0 is 64
    zero = decode_frame(_env(camera={**cam, "params": [50.0, 50.0, 0.0, 24.0]})).camera
    negzero = decode_frame(_env(camera={**cam, "params": [50.0, 50.0, -0.0, 24.0]})).camera
    assert math.copysign(1.0, zero.params[2]) == 1.0
    assert math.copysign(1.0, negzero.params[2]) == -1.0  # not the cached +0.0 camera
    one = {"model": "PINHOLE", "width": 1, "height": 1, "params": [1.0, 1.0, 0.5, 0.5]}
    data = {"encoding": "gray8", "data": b"\x00"}
    assert decode_frame(_env(camera=one, **data)).camera.width == 1
    with pytest.raises(WireError, match="width must be an integer"):
        decode_frame(_env(camera={**one, "width": True}, **data))
    bad = {**cam, "params": [50.0, 50.0, float("nan"), 24.0]}
    for _ in range(2):  # a refused camera is refused every time (never kept)
        with pytest.raises(WireError, match="finite"):
            decode_frame(_env(camera=bad))


def test_oversized_frames_are_refused_before_parsing():
    with pytest.raises(MessageTooLargeError) as e:
        decode_frame(_env(), max_bytes=1000)
    assert e.value.code == "RESOURCE_EXHAUSTED" and "exceeds the limit of 1000 bytes" in str(
        e.value
    )


def test_pose_round_trip_with_filtered_and_error():
    T = Transform((0.0, 0.0, math.sin(0.25), math.cos(0.25)), (1.0, 2.0, 3.0))
    p = PoseMessage(
        seq=5,
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
    )
    assert decode_pose(encode_pose(p)) == p
    # the covariance (36 values, row-major 6x6) survives the Zenoh wire and the protobuf form
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])
    cov[0, 3] = cov[3, 0] = 1e-6
    p.covariance = tuple(cov.ravel())
    p.status = "UNVERIFIED"
    back = decode_pose(encode_pose(p))
    assert back == p and np.array_equal(back.covariance_matrix, cov)
    assert (
        pose_from_estimate_pb(pose_to_estimate_pb(p), seq=5, stamp_ns=99).covariance == p.covariance
    )
    assert pose_from_estimate_pb(pose_to_estimate_pb(p), seq=5, stamp_ns=99).status == "UNVERIFIED"
    with pytest.raises(WireError, match="covariance must have 36"):
        decode_pose(msgpack.packb({"status": "TRACKING", "covariance": [1.0] * 35}))
    with pytest.raises(WireError, match="covariance"):
        decode_pose(msgpack.packb({"status": "TRACKING", "covariance": [float("nan")] * 36}))
    e = PoseMessage(
        seq=None, stamp_ns=0, status="LOST", error=ErrorInfo("NOT_FOUND", "map 'x' is not loaded")
    )
    back = decode_pose(encode_pose(e))
    assert back == e and not back.localized and back.error.code == "NOT_FOUND"
    with pytest.raises(WireError):
        decode_pose(msgpack.packb({"status": "HAPPY"}))
    # the engine's CPU: 0 from a server older than the field, a finite number else
    assert decode_pose(msgpack.packb({"status": "LOST"})).engine_cpu_ms == 0.0
    with pytest.raises(WireError, match="engine_cpu_ms"):
        decode_pose(msgpack.packb({"status": "LOST", "engine_cpu_ms": float("inf")}))


def test_transform_inverse_matches_the_server_convention():
    from sfmloc.transforms import Rigid3d

    R = Rigid3d.from_rotvec(np.array([0.3, -0.2, 0.5]), np.array([1.0, -2.0, 0.5]))
    T = Transform(tuple(R.quat_xyzw), tuple(R.translation))
    inv = T.inverse()
    Ri = R.inverse()
    np.testing.assert_allclose(inv.rotation_matrix(), Ri.rotation, atol=1e-9)
    np.testing.assert_allclose(inv.t, Ri.translation, atol=1e-9)
    np.testing.assert_allclose(T.matrix() @ inv.matrix(), np.eye(4), atol=1e-9)


def test_announcement_and_server_info_round_trip():
    a = MapAnnouncement("lab", "20260101T000000Z-abcd", "/maps/lab")
    assert decode_map_announcement(encode_map_announcement(a)) == a
    with pytest.raises(WireError):
        decode_map_announcement(msgpack.packb({"name": "bad name", "build_id": "x", "path": "/p"}))
    with pytest.raises(WireError):
        decode_map_announcement(msgpack.packb({"name": "lab", "build_id": "x"}))
    i = ServerInfo(
        "srv-1",
        "0.1.0",
        "host:50051",
        [{"name": "lab", "build_id": "b"}],
        3,
        2,
        {"busy": 0.5},
        True,
    )
    assert decode_server_info(encode_server_info(i)) == i


def test_keys():
    assert frame_key("lab", "drone-1") == "sfmloc/lab/drone-1/frame"
    assert pose_key("lab", "drone-1") == "sfmloc/lab/drone-1/pose"
    assert parse_frame_key("sfmloc/lab/drone-1/frame") == ("lab", "drone-1")
    # addressed to one server (one owner per session): no other server subscribes to it
    assert frame_key("lab", "drone-1", "srv-2") == "sfmloc/lab/drone-1/frame/srv-2"
    assert parse_frame_key("sfmloc/lab/drone-1/frame/srv-2") == ("lab", "drone-1")
    assert addressed_frame_keyexpr("srv-2") == "sfmloc/*/*/frame/srv-2"
    assert zenoh.KeyExpr(FRAME_KEYEXPR).intersects(zenoh.KeyExpr(frame_key("lab", "d")))
    assert not zenoh.KeyExpr(FRAME_KEYEXPR).intersects(zenoh.KeyExpr(frame_key("lab", "d", "s")))
    with pytest.raises(WireError):
        frame_key("lab", "drone-1", "no/slash")
    with pytest.raises(WireError):
        parse_frame_key("sfmloc/lab/drone-1/frame/srv-2/extra")
    for bad in ("a/b", "*", "", "x" * 65, "-lead", "sp ace"):
        with pytest.raises(WireError):
            frame_key(bad, "c")
    with pytest.raises(WireError):
        parse_frame_key("sfmloc/lab/pose")


# ----------------------------------------------------------------------------- images, cameras
def test_image_encodings_round_trip():
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    bgr = np.dstack([gray, gray // 2, 255 - gray])
    assert np.array_equal(decode_image("gray8", encode_image(gray, "gray8"), 64, 48), gray)
    assert np.array_equal(decode_image("bgr8", encode_image(bgr, "bgr8"), 64, 48, gray=False), bgr)
    assert np.array_equal(decode_image("png", encode_image(gray, "png"), 64, 48), gray)
    smooth = np.tile(np.linspace(0, 255, 64, dtype=np.uint8), (48, 1))
    assert (
        np.abs(
            decode_image("jpeg", encode_image(smooth, "jpeg"), 64, 48).astype(int) - smooth
        ).max()
        < 8
    )
    with pytest.raises(ImageDataError):
        decode_image("jpeg", b"\xff\xd8\xff" + b"\x00" * 100, 64, 48)
    with pytest.raises(ImageDataError) as e:
        decode_image("png", encode_image(gray, "png"), 32, 48)
    assert "64x48" in str(e.value)
    with pytest.raises(ImageDataError):
        encode_image(gray.astype(np.float32), "png")


def test_one_exception_hierarchy_with_one_status_table():
    """Client, server and builder raise the same classes (sfmloc.errors re-exports them); the
    client's older names are the same classes, not twins; every error knows its status code."""
    import sfmloc.errors as service_errors
    from sfmloc_client import errors as E

    assert service_errors.SfmlocError is E.SfmlocError is E.ClientError
    assert service_errors.MessageError is E.WireError and E.ImageDataError is E.ImageDecodeError
    assert all(issubclass(cls, E.SfmlocError) for cls, _ in E.STATUS_TABLE)
    assert E.WireError("x").code == E.CameraModelError("x").code == "INVALID_ARGUMENT"
    assert E.MessageTooLargeError("x").code == "RESOURCE_EXHAUSTED"
    assert E.JobNotFoundError("x").code == E.MapNotFoundError("x").code == "NOT_FOUND"
    assert E.code_of(KeyError("x")) == "INTERNAL" and "internal error" in E.message_of(KeyError(1))
    remote = E.RemoteError("UNAVAILABLE", "restarting")
    assert remote.code == E.code_of(remote) == "UNAVAILABLE" and remote.message == "restarting"
    assert E.error_class("BundleError") is E.BundleError
    assert E.error_class("os.system") is E.error_class("RemoteError") is E.InternalError


def test_camera_spec_parse(tmp_path):
    c = CameraSpec.parse("pinhole 640 480 525 525 320 240")
    assert c == CameraSpec("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))
    p = tmp_path / "camera.json"
    p.write_text(
        json.dumps(
            {
                "model": "OPENCV",
                "width": 10,
                "height": 8,
                "params": [1, 1, 5, 4, 0, 0, 0, 0],
                "param_names": ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"],
            }
        )
    )
    assert CameraSpec.parse(p).model == "OPENCV"
    for bad in ("PINHOLE 640", "PINHOLE a b 1 1 1 1", "PINHOLE 640 480 1 1 1"):
        with pytest.raises(CameraModelError):
            CameraSpec.parse(bad)


def test_tum_writer_writes_localized_world_from_cam(tmp_path):
    T = Transform((0.0, 0.0, 0.0, 1.0), (1.0, 2.0, 3.0))
    with TumWriter(tmp_path / "t.tum") as w:
        assert w.write(
            PoseMessage(1, 1_500_000_000, "TRACKING", cam_from_world=T.inverse(), world_from_cam=T)
        )
        assert not w.write(PoseMessage(2, 1_533_000_000, "LOST"))
    lines = (tmp_path / "t.tum").read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == 2
    assert [float(v) for v in lines[1].split()] == [1.5, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0]
    # the covariance side file: one line per pose line, timestamp, status, 36 values
    cov = tuple(float(v) for v in np.eye(6).ravel() * 1e-4)
    with TumWriter(tmp_path / "c.tum") as w:
        w.write(
            PoseMessage(
                1,
                1_500_000_000,
                "UNVERIFIED",
                cam_from_world=T.inverse(),
                world_from_cam=T,
                covariance=cov,
            )
        )
        w.write(
            PoseMessage(2, 1_533_000_000, "TRACKING", cam_from_world=T.inverse(), world_from_cam=T)
        )
    rows = [r.split() for r in (tmp_path / "c.tum.cov").read_text().splitlines()]
    assert rows[0][0] == "#" and "rx ry rz cx cy cz" in " ".join(rows[0])
    assert (
        rows[1][:2] == ["1.500000000", "UNVERIFIED"] and tuple(float(v) for v in rows[1][2:]) == cov
    )
    assert rows[2][1] == "TRACKING" and len(rows[2]) == 38 and all(v == "nan" for v in rows[2][2:])
    from sfmloc.io.poses import COVARIANCE_HEADER
    from sfmloc_client.trajectory import COVARIANCE_HEADER as CLIENT_HEADER

    assert COVARIANCE_HEADER == CLIENT_HEADER


def test_zenoh_config_builder():
    conf = make_zenoh_config("client", listen=[], connect=["tcp/10.0.0.1:7447"], multicast=False)
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/10.0.0.1:7447"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    with pytest.raises(ValueError):
        make_zenoh_config("satellite")


# ----------------------------------------------------------------------------- against a server
@pytest.fixture(scope="module")
def server(world):
    ep = zenoh_endpoint()
    with running_server(server_config(world, ep, server_id="client-tests")) as srv:
        yield srv, ep


def test_streamer_from_a_numpy_stack_and_the_pose_iterator(world, server):
    srv, ep = server
    stack = np.stack([np.dstack([g, g, g]) for g in world.gray[:8]])  # BGR frames, sent as JPEG
    with client_zenoh(ep) as z:
        with (
            PoseSubscriber(z, "room", "numpy") as poses,
            FrameStreamer(z, "room", "numpy", camera(world)) as fs,
        ):
            assert fs.wait_for_server(30)
            stats = fs.run(stack, lockstep=True, poses=poses)
            got = [poses.get(30) for _ in range(stats.sent)]
    assert stats.sent == 8 and [p.seq for p in got] == list(range(8))
    assert sum(p.localized for p in got) >= 7


def test_streamer_from_a_video_file_uses_its_clock(world, server, tmp_path):
    import cv2

    srv, ep = server
    video = tmp_path / "walk.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30, (640, 480))
    assert w.isOpened()
    for g in world.gray[:12]:
        w.write(np.dstack([g, g, g]))
    w.release()
    stamps: list[int] = []
    with client_zenoh(ep) as z:
        with (
            PoseSubscriber(
                z, "room", "video", callback=lambda p: stamps.append(p.stamp_ns)
            ) as poses,
            FrameStreamer(z, "room", "video", camera(world)) as fs,
        ):
            assert fs.wait_for_server(30)
            stats = fs.run(str(video), lockstep=True, poses=poses)
            assert poses.wait_for(stats.last_seq, 30)
    assert stats.sent == 12 and len(stamps) == 12
    np.testing.assert_allclose(np.diff(stamps), 1e9 / 30, rtol=0.01)  # the file's 30 Hz, from 0
    assert stamps[0] == 0


def _cli(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "sfmloc", *args], capture_output=True, text=True, timeout=timeout
    )


def test_cli_stream_writes_a_tum_trajectory(world, server, tmp_path):
    srv, ep = server
    out = tmp_path / "room.tum"
    r = _cli(
        "stream",
        "--map",
        "room",
        "--source",
        str(world.frames[0].parent),
        "--camera",
        str(world.root / "synth" / "camera.json"),
        "--fps",
        "20",
        "--max-frames",
        "30",
        "--zenoh-connect",
        ep,
        "--no-multicast",
        "--client-id",
        "cli-walker",
        "--encoding",
        "png",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    assert "poses received for 30 frames sent" in r.stdout
    n_received = int(r.stdout.split(" poses received")[0].split()[-1])
    assert 0 < n_received <= 30
    rows = [line.split() for line in out.read_text().splitlines() if not line.startswith("#")]
    assert 0.8 * n_received <= len(rows) <= n_received and all(len(row) == 8 for row in rows)
    stamps = [float(row[0]) for row in rows]
    assert stamps == sorted(stamps)
    q = np.array([[float(v) for v in row[4:]] for row in rows])
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    cov_rows = [line.split() for line in (tmp_path / "room.tum.cov").read_text().splitlines()[1:]]
    assert [row[0] for row in cov_rows] == [row[0] for row in rows]
    for row in cov_rows:
        C = np.array([float(v) for v in row[2:]]).reshape(6, 6)
        assert (
            row[1] in ("TRACKING", "RELOCALIZED", "UNVERIFIED") and np.linalg.eigvalsh(C).min() > 0
        )
    assert "sent 30 poses" in r.stderr  # the live status line


def test_cli_stream_without_a_server_fails_clearly(world, tmp_path):
    r = _cli(
        "stream",
        "--map",
        "room",
        "--source",
        str(world.frames[0].parent),
        "--camera",
        world.camera_spec,
        "--zenoh-connect",
        zenoh_endpoint(),
        "--no-multicast",
        "--wait-server",
        "1",
        "--max-frames",
        "2",
    )
    assert r.returncode == 1 and "no server" in r.stderr


def test_cli_relocalize_maps_sessions_servers(world, server):
    srv, ep = server
    target = f"127.0.0.1:{srv.grpc_port}"
    r = _cli(
        "relocalize",
        str(world.frames[15]),
        "--map",
        "room",
        "--camera",
        world.camera_spec,
        "--grpc",
        target,
        "--json",
    )
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    gt = world.gt_cam_from_world[15].inverse().translation
    assert (
        d["status"] == "RELOCALIZED"
        and np.linalg.norm(np.array(d["world_from_cam"]["t"]) - gt) < 0.1
    )
    r = _cli(
        "relocalize",
        str(world.frames[15]),
        "--map",
        "atlantis",
        "--camera",
        world.camera_spec,
        "--grpc",
        target,
    )
    assert r.returncode == 2 and "NOT_FOUND" in r.stderr
    r = _cli("maps", "list", "--grpc", target)
    assert r.returncode == 0 and "room2" in r.stdout
    r = _cli("maps", "show", "room2", "--grpc", target)  # labelled lines, not protobuf text
    assert r.returncode == 0 and "build id:" in r.stdout and "build_id:" not in r.stdout
    assert "name:         room2" in r.stdout.splitlines()[0]
    r = _cli("sessions", "list", "--grpc", target)
    assert r.returncode == 0 and "client" in r.stdout
    r = _cli("servers", "--zenoh-connect", ep, "--no-multicast", "--wait", "2")
    assert r.returncode == 0 and "client-tests: ready" in r.stdout and "room" in r.stdout


def test_cli_relocalize_with_a_prior(world, server):
    """README's `relocalize --prior 'qx qy qz qw tx ty tz'` (cam_from_world) ran in no test: a
    right prior reaches the engine (its search scoped around the prior verifies more matches:
    98 inliers against 32 for the whole-map search here), a wrong one costs time and not a
    wrong pose, and a malformed one is a clean exit 2 (words were a ValueError traceback)."""
    srv, _ = server
    k = 15
    gt = world.gt_cam_from_world[k].inverse().translation

    def reloc(*prior: str) -> subprocess.CompletedProcess:
        return _cli(
            "relocalize", str(world.frames[k]), "--map", "room", "--camera", world.camera_spec,
            "--grpc", f"127.0.0.1:{srv.grpc_port}", "--json", *prior,
        )  # fmt: skip

    without = json.loads(reloc().stdout)
    right = Transform.from_matrix(world.gt_cam_from_world[k].matrix4())
    r = reloc("--prior", " ".join(f"{v:.9f}" for v in (*right.quat_xyzw, *right.t)))
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["status"] == "RELOCALIZED", d
    assert np.linalg.norm(np.array(d["world_from_cam"]["t"]) - gt) < 0.1
    assert d["inliers"] > without["inliers"], (d, without)
    # how each was found, through the gRPC response into the JSON (the prior's said "global")
    assert (d["matching"], without["matching"]) == ("guided", "global"), (d, without)
    r = reloc("--prior", "0 0 0 1 100 100 100")  # nowhere near: found by global matching, or LOST
    d = json.loads(r.stdout)
    assert r.returncode in (0, 1) and (r.returncode == 0) == (d["world_from_cam"] is not None)
    if r.returncode == 0:
        assert np.linalg.norm(np.array(d["world_from_cam"]["t"]) - gt) < 0.1, d
    for bad in ("1 2 3", "a b c d e f g"):
        r = reloc("--prior", bad)
        assert r.returncode == 2 and "--prior takes 7 numbers" in r.stderr, r.stderr
        assert "Traceback" not in r.stderr


def test_cli_maps_unload_load_and_sessions_reset(world, server):
    """The map and session commands' other paths (README: map management): unload and load
    back by name, a reset of a client the server does not know."""
    srv, _ = server
    target = f"127.0.0.1:{srv.grpc_port}"
    r = _cli("maps", "unload", "room2", "--grpc", target)
    assert r.returncode == 0 and "unloaded room2" in r.stdout, r.stderr
    r = _cli("maps", "load", "room2", "--grpc", target)  # a name: from the maps folder
    assert r.returncode == 0 and r.stdout.startswith("loaded room2 (build "), r.stderr
    r = _cli("maps", "load", "/etc", "--grpc", target)
    assert r.returncode == 2 and "PERMISSION_DENIED" in r.stderr
    r = _cli("sessions", "reset", "nobody", "--grpc", target)
    assert r.returncode == 2 and "NOT_FOUND" in r.stderr


def test_every_command_has_help():
    for cmd in ("serve", "stream", "relocalize", "maps", "sessions", "servers"):
        r = _cli(cmd, "--help", timeout=60)
        assert r.returncode == 0 and "usage: sfmloc " + cmd in r.stdout and len(r.stdout) > 300, cmd
