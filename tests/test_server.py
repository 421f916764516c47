"""The localization server end to end: real Zenoh sessions (peer mode, loopback, multicast
scouting off), real gRPC on loopback, real worker processes, a synthetic world with exact
ground truth (see server_helpers). No mocks; no assertion on how long anything takes."""

from __future__ import annotations

import asyncio
import queue
import threading
import urllib.request
from pathlib import Path

import grpc
import msgpack
import numpy as np
import pytest
import zenoh

from server_helpers import (
    Collected,
    camera,
    client_zenoh,
    free_port,
    position_errors,
    running_server,
    server_config,
    stream_lockstep,
    wait_until,
    zenoh_endpoint,
)
from sfmloc_client import (
    CameraSpec,
    Frame,
    FrameStreamer,
    LocalizationClient,
    MapAnnouncement,
    PoseSubscriber,
    RemoteError,
    SourceFrame,
    encode_frame,
    encode_image,
    encode_map_announcement,
    query_servers,
)
from sfmloc_client.discovery import list_server_ids
from sfmloc_client.errors import CameraModelError
from sfmloc_client.wire import frame_key, map_announce_key


@pytest.fixture(scope="module")
def zep():
    return zenoh_endpoint()


@pytest.fixture(scope="module")
def srv(world, zep):
    """The server most tests share: two worker processes, both maps, following the builder."""
    conf = server_config(
        world,
        zep,
        workers=2,
        worker_kind="process",
        follow_builder=True,
        metrics_port=free_port(),
        server_id="test-server",
        map_roots=[str(world.spare_dir)],
    )
    with running_server(conf) as s:
        yield s


@pytest.fixture(scope="module")
def grpc_client(srv):
    with LocalizationClient(f"127.0.0.1:{srv.grpc_port}", timeout=60) as c:
        yield c


@pytest.fixture()
def z(zep, srv):
    with client_zenoh(zep) as session:
        yield session


# ----------------------------------------------------------------------------- streaming
def test_stream_receives_a_pose_for_every_frame_with_its_seq(world, z):
    poses = stream_lockstep(z, "room", "walker", world)
    assert [p.seq for p in poses] == list(range(len(world.png)))
    assert all(p.error is None and p.map == "room" and p.client_id == "walker" for p in poses)
    localized = [p for p in poses if p.localized]
    assert len(localized) >= 0.9 * len(poses)
    assert np.median(position_errors(world, poses)) < 0.05  # metres, exact ground truth
    assert (
        poses[0].status == "RELOCALIZED" or not poses[0].localized
    )  # a new session starts from scratch
    assert any(p.status == "TRACKING" for p in poses)
    assert all(p.latency_ms >= p.engine_ms > 0 for p in localized)
    # the engine's CPU for the frame (its thread's), about its wall time on a free core
    assert all(0 < p.engine_cpu_ms <= p.engine_ms * 1.05 + 1.0 for p in localized)
    # every pose carries its 6x6 covariance (positive definite); LOST ones none
    for p in poses:
        C = p.covariance_matrix
        assert (C is None) == (not p.localized)
        assert C is None or (np.allclose(C, C.T) and np.linalg.eigvalsh(C).min() > 0)


def test_two_clients_on_two_maps_at_once(world, z):
    results: dict[str, list] = {}

    def client(map_name: str, cid: str) -> None:
        results[map_name] = stream_lockstep(z, map_name, cid, world, n=40)

    threads = [
        threading.Thread(target=client, args=("room", "a")),
        threading.Thread(target=client, args=("room2", "b")),
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    for map_name, cid in (("room", "a"), ("room2", "b")):
        poses = results[map_name]
        assert [p.seq for p in poses] == list(range(40)), map_name
        assert {(p.map, p.client_id) for p in poses} == {(map_name, cid)}
        assert sum(p.localized for p in poses) >= 36
        assert np.median(position_errors(world, poses)) < 0.05


def test_sessions_sharing_workers_get_the_poses_of_a_session_alone(world):
    """The engine is repeatable (README, Conventions): three sessions on one map streamed at
    once, lockstep (no frame stale), on two workers (two of them share one, frame by frame),
    get bit for bit the poses, covariances and statuses of a session streamed alone.

    Its own server, with no wall-clock frame budget: the promise is about frames the engine
    works on, and with the budget (2 s) a frame that waits longer for its worker is answered
    DEADLINE_EXCEEDED without being worked on, as promised (config.py, frame_budget_ms): at
    load ~14 the shared server so answered s3's first frame, waiting behind s1's
    relocalization, and s3's poses then differed from the first (2 of 3 suite runs)."""
    zep = zenoh_endpoint()
    conf = server_config(world, zep, workers=2, worker_kind="process", frame_budget_ms=0)
    with running_server(conf), client_zenoh(zep) as z:
        _sessions_sharing_workers_get_the_poses_of_a_session_alone(world, z)


def _sessions_sharing_workers_get_the_poses_of_a_session_alone(world, z) -> None:

    def answers(poses: list) -> list:
        return [
            (
                p.seq,
                p.status,
                p.matching,
                p.inliers,
                p.cam_from_world,
                p.filtered_cam_from_world,
                p.covariance,
                p.message,
            )
            for p in poses
        ]

    alone = answers(stream_lockstep(z, "room", "alone", world, n=40))
    assert [a[0] for a in alone] == list(range(40))
    results: dict[str, list] = {}

    def client(cid: str) -> None:
        results[cid] = answers(stream_lockstep(z, "room", cid, world, n=40))

    threads = [threading.Thread(target=client, args=(c,)) for c in ("s1", "s2", "s3")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(180)
    for cid in ("s1", "s2", "s3"):
        assert results[cid] == alone, cid


def test_latest_frame_only_intake_drops_and_counts_stale_frames(world, z, grpc_client):
    """A burst far faster than the engine: stale frames are dropped (never queued), counted,
    reported in the poses and in ListSessions, and the newest frame is always processed."""
    got: list = []
    n = 40
    with (
        PoseSubscriber(z, "room", "burst", callback=got.append) as poses,
        FrameStreamer(z, "room", "burst", camera(world), congestion="block") as fs,
    ):
        assert fs.wait_for_server(30)
        for k in range(n):  # back to back: ~microseconds apart, each frame takes milliseconds
            fs.publish(data=world.png[k], encoding="png", stamp_ns=int(k * 1e9 / 30))
        assert poses.wait_for(n - 1, 60)
    seqs = [p.seq for p in got]
    assert seqs == sorted(seqs) and seqs[-1] == n - 1  # in order, and the newest frame made it
    dropped = got[-1].dropped
    assert dropped > 0
    assert len(got) + dropped == n  # every frame either processed or counted as dropped
    session = next(s for s in grpc_client.list_sessions("room") if s.client_id == "burst")
    assert session.dropped == dropped and session.frames == n


def test_grpc_stream_localize_with_a_corrupt_frame_in_the_middle(world, grpc_client):
    """StreamLocalize in lockstep (each frame after the previous pose): every frame gets its
    pose; the corrupt one a LOST update with an error code, and the stream goes on."""
    frames = [SourceFrame(data=d, encoding="png") for d in world.png[:20]]
    frames[10] = SourceFrame(
        data=b"\x89PNG\r\n\x1a\n" + b"garbage" * 50, encoding="png"
    )  # corrupt PNG
    frames[15] = SourceFrame(data=b"\x00" * 1000, encoding="gray8")  # not 640x480
    acks: queue.Queue = queue.Queue()

    def requests():
        for f in frames:
            yield f
            acks.get(timeout=60)

    poses = []
    for p in grpc_client.stream(
        requests(), "room", camera(world), client_id="grpc-walker", encoding="png"
    ):
        poses.append(p)
        acks.put(p.seq)
    assert [p.seq for p in poses] == list(range(20))
    bad = poses[10]
    assert bad.status == "LOST" and bad.error is not None and bad.error.code == "INVALID_ARGUMENT"
    assert "cannot be decoded" in bad.error.message
    assert poses[15].error.code == "INVALID_ARGUMENT" and "1000 bytes" in poses[15].error.message
    assert all(
        p.error is None and p.client_id == "grpc-walker" for p in poses if p.seq not in (10, 15)
    )
    assert sum(p.localized for p in poses) >= 17
    assert np.median(position_errors(world, poses)) < 0.05
    assert all((p.covariance is not None) == p.localized for p in poses)  # StreamLocalize


def test_grpc_stream_burst_drops_stale_frames_and_ends_with_the_last(world, grpc_client):
    poses = list(
        grpc_client.stream(
            (SourceFrame(data=d, encoding="png") for d in world.png[:30]),
            "room",
            camera(world),
            encoding="png",
        )
    )
    seqs = [p.seq for p in poses]
    assert seqs == sorted(seqs) and seqs[-1] == 29
    assert len(poses) + poses[-1].dropped == 30
    assert poses[0].client_id.startswith("grpc-")  # assigned by the server


def test_grpc_stream_on_an_unknown_map_or_without_camera_ends_with_its_status(world, grpc_client):
    with pytest.raises(RemoteError) as e:
        list(grpc_client.stream(iter(world.png[:2]), "no-such-map", camera(world), encoding="png"))
    assert e.value.code == "NOT_FOUND" and "no-such-map" in e.value.message
    # The client refuses a bad camera before sending (the same rule as the server's), so the
    # server's answer is checked with raw requests.
    with pytest.raises(CameraModelError, match="focal"):
        CameraSpec("PINHOLE", 640, 480, (-1.0, 525.0, 320.0, 240.0))
    from sfmloc_client.convert import image_to_pb
    from sfmloc_client.pb import common_pb2
    from sfmloc_client.pb import localization_pb2 as lpb

    bad_cam = common_pb2.Camera(
        model="PINHOLE", width=640, height=480, params=[-1.0, 525.0, 320.0, 240.0]
    )
    reqs = [
        lpb.StreamFrame(
            map="room", seq=k, camera=bad_cam, image=image_to_pb("png", world.png[k], 640, 480)
        )
        for k in range(2)
    ]
    with pytest.raises(grpc.RpcError) as err:
        list(grpc_client.stub.StreamLocalize(iter(reqs), timeout=60))
    assert err.value.code().name == "INVALID_ARGUMENT" and "focal" in err.value.details()


# ----------------------------------------------------------------------------- bad input
def _raw_put(z: zenoh.Session, key: str, payload: bytes) -> None:
    z.put(key, payload)


def test_bad_frames_get_clear_errors_while_a_good_client_keeps_getting_poses(world, z, srv):
    good: list = []
    errors: dict[str, list] = {}
    cam = camera(world)
    cases = {
        "garbage": b"\x00\x01not msgpack at all",
        "not-a-map": msgpack.packb([1, 2, 3]),
        "missing-key": msgpack.packb({"seq": 3, "stamp_ns": 0, "encoding": "png", "data": b"x"}),
        "bad-encoding": msgpack.packb(
            {"seq": 4, "stamp_ns": 0, "camera": cam.to_wire(), "encoding": "webp", "data": b"x"}
        ),
        "wrong-size": msgpack.packb(
            {
                "seq": 5,
                "stamp_ns": 0,
                "camera": cam.to_wire(),
                "encoding": "gray8",
                "data": b"\x00" * 10000,
            }
        ),
        "corrupt-jpeg": encode_frame(
            Frame(6, 0, cam, "jpeg", b"\xff\xd8\xff\xe0" + bytes(range(256)) * 8)
        ),
        "other-size-png": encode_frame(
            Frame(
                7, 0, CameraSpec("PINHOLE", 320, 240, (262.5, 262.5, 160, 120)), "png", world.png[0]
            )
        ),
        "bad-camera": msgpack.packb(
            {
                "seq": 8,
                "stamp_ns": 0,
                "camera": {
                    "model": "PINHOLE",
                    "width": 640,
                    "height": 480,
                    "params": [-5.0, 525.0, 320.0, 240.0],
                },
                "encoding": "png",
                "data": world.png[0],
            }
        ),
        "oversized": msgpack.packb(
            {
                "seq": 9,
                "stamp_ns": 0,
                "camera": cam.to_wire(),
                "encoding": "png",
                "data": b"\x00" * (srv.conf.max_frame_bytes + 10),
            }
        ),
        "huge-camera": encode_frame(
            Frame(
                10, 0, CameraSpec("PINHOLE", 8000, 8000, (5e3, 5e3, 4e3, 4e3)), "png", world.png[0]
            )
        ),
        # a decompression bomb: 14 kB of PNG that would decode to 9000 x 9000 pixels
        "bomb": encode_frame(
            Frame(11, 0, cam, "png", encode_image(np.zeros((9000, 9000), np.uint8), "png"))
        ),
    }
    expected = {
        "garbage": ("INVALID_ARGUMENT", None, "msgpack"),
        "not-a-map": ("INVALID_ARGUMENT", None, "map"),
        "missing-key": ("INVALID_ARGUMENT", 3, "camera"),
        "bad-encoding": ("INVALID_ARGUMENT", 4, "encoding"),
        "wrong-size": ("INVALID_ARGUMENT", 5, "bytes"),
        "corrupt-jpeg": ("INVALID_ARGUMENT", 6, "cannot be decoded"),
        "other-size-png": ("INVALID_ARGUMENT", 7, "320x240"),
        "bad-camera": ("INVALID_ARGUMENT", 8, "focal"),
        "oversized": ("RESOURCE_EXHAUSTED", None, "exceeds the limit"),
        "huge-camera": ("RESOURCE_EXHAUSTED", 10, "exceeds this server's limit"),
        "bomb": ("INVALID_ARGUMENT", 11, "larger than the decoder allows"),
    }
    subs = []
    for cid in cases:
        errors[cid] = []
        subs.append(PoseSubscriber(z, "room", cid, callback=errors[cid].append))
    unknown: list = []
    subs.append(PoseSubscriber(z, "atlantis", "lost", callback=unknown.append))
    stop = threading.Event()

    def good_client() -> None:
        good.extend(stream_lockstep(z, "room", "good", world, n=30))
        stop.set()

    t = threading.Thread(target=good_client)
    t.start()
    try:
        with FrameStreamer(z, "room", "probe", cam) as probe:
            assert probe.wait_for_server(30)

        def send_unanswered() -> bool:
            # Re-send until answered: the server may learn of a pose subscriber declared just
            # now after its frame (declarations and express data travel separately).
            for cid, payload in cases.items():
                if not errors[cid]:
                    _raw_put(z, frame_key("room", cid), payload)
            if not unknown:
                _raw_put(
                    z,
                    frame_key("atlantis", "lost"),
                    encode_frame(Frame(0, 0, cam, "png", world.png[0])),
                )
            return wait_until(lambda: all(errors[c] for c in cases) and bool(unknown), 1.0)

        assert wait_until(send_unanswered, 60, every=0.0), [c for c in cases if not errors[c]]
        t.join(120)
    finally:
        stop.set()
        for s in subs:
            s.close()
    for cid, (code, seq, words) in expected.items():
        p = errors[cid][0]
        assert p.status == "LOST" and p.error is not None, cid
        assert p.error.code == code, (cid, p.error)
        assert p.seq == seq, (cid, p.seq)
        assert words in p.error.message, (cid, p.error.message)
    assert unknown[0].error.code == "NOT_FOUND" and "atlantis" in unknown[0].error.message
    assert [p.seq for p in good] == list(range(30)) and all(p.error is None for p in good)
    assert sum(p.localized for p in good) >= 27


# ----------------------------------------------------------------------------- gRPC
def test_relocalize_single_images(world, grpc_client):
    cam = camera(world)
    errs = []
    for k in (5, 25, 45):
        pose = grpc_client.relocalize(world.png[k], "room", cam, encoding="png")
        assert pose.status == "RELOCALIZED" and pose.inliers >= 10
        C = pose.covariance_matrix  # through the gRPC response
        assert C.shape == (6, 6) and np.linalg.eigvalsh(C).min() > 0 and np.sqrt(C[3, 3]) < 0.05
        gt = world.gt_cam_from_world[k].inverse().translation
        errs.append(np.linalg.norm(np.asarray(pose.world_from_cam.t) - gt))
    assert np.median(errs) < 0.05
    # raw gray8 works too, and a prior is accepted
    pose = grpc_client.relocalize(world.gray[30], "room", cam, encoding="gray8")
    assert pose.localized
    near = grpc_client.relocalize(
        world.png[30], "room", cam, encoding="png", prior=pose.cam_from_world
    )
    assert near.localized
    # found around the prior: the response says guided matching (it said global)
    assert (pose.matching, near.matching) == ("global", "guided")


@pytest.mark.parametrize(
    "case, code",
    [
        ("unknown-map", "NOT_FOUND"),
        ("corrupt-jpeg", "INVALID_ARGUMENT"),
        ("bad-camera", "INVALID_ARGUMENT"),
        ("wrong-raw-size", "INVALID_ARGUMENT"),
        ("no-encoding", "INVALID_ARGUMENT"),
        ("oversized", "RESOURCE_EXHAUSTED"),
        ("nan-prior", "INVALID_ARGUMENT"),
        ("zero-prior", "INVALID_ARGUMENT"),
        ("short-prior", "INVALID_ARGUMENT"),
    ],
)
def test_relocalize_errors_map_to_status_codes(world, grpc_client, case, code):
    from sfmloc_client.grpc_client import relocalize_request
    from sfmloc_client.pb import common_pb2

    cam = camera(world)
    req = relocalize_request(world.png[0], "room", cam, encoding="png")
    if case == "unknown-map":
        req.map = "atlantis"
    elif case == "corrupt-jpeg":
        req.image.encoding, req.image.data = (
            common_pb2.IMAGE_ENCODING_JPEG,
            b"\xff\xd8\xff" + b"\x17" * 5000,
        )
    elif case == "bad-camera":
        req.camera.model = "FISHEYE_9000"
    elif case == "wrong-raw-size":
        req.image.encoding, req.image.data = common_pb2.IMAGE_ENCODING_GRAY8, b"\x00" * 1234
    elif case == "no-encoding":
        req.image.encoding = common_pb2.IMAGE_ENCODING_UNSPECIFIED
    elif case == "oversized":
        req.image.data = b"\x00" * (5 * 1024 * 1024)  # the test server takes 4 MB
    elif case.endswith("-prior"):
        q = {"nan": [float("nan"), 0, 0, 1], "zero": [0, 0, 0, 0], "short": [0, 0, 1]}[case[:-6]]
        req.prior_cam_from_world.CopyFrom(common_pb2.Rigid3d(quat_xyzw=q, t=[0, 0, 0]))
    with pytest.raises(grpc.RpcError) as e:
        grpc_client.stub.Relocalize(req, timeout=60)
    assert e.value.code().name == code
    assert e.value.details()  # a message that says what is wrong
    if case == "oversized":
        assert "larger than max" in e.value.details() or "exceeds" in e.value.details()


@pytest.mark.parametrize(
    "method, kind",
    [
        ("/sfmloc.v1.Localization/Relocalize", "unary"),
        ("/sfmloc.v1.Localization/ListMaps", "unary"),
        ("/sfmloc.v1.Localization/StreamLocalize", "stream"),
        ("/grpc.health.v1.Health/Check", "unary"),
    ],
)
def test_unparsable_request_bytes_are_invalid_argument(srv, method, kind, caplog):
    """Bytes that are no protobuf message of the method's type: INVALID_ARGUMENT with a
    message (grpc's own answer would be UNKNOWN or INTERNAL), and no error logged for it."""
    import logging

    caplog.set_level(logging.WARNING)
    garbage = [b"\xff\xff\xff\xff", b"\x0a\xff\x01", bytes(range(256))]
    with grpc.insecure_channel(f"127.0.0.1:{srv.grpc_port}") as ch:
        for data in garbage:
            with pytest.raises(grpc.RpcError) as e:
                if kind == "unary":
                    ch.unary_unary(method)(data, timeout=30)
                else:
                    list(ch.stream_stream(method)(iter([data]), timeout=30))
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, (
                method,
                data,
                e.value.details(),
            )
            assert "malformed request" in e.value.details()
    errors = [r.getMessage()[:200] for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors == []  # e.g. not "Abort already called!" with a traceback per message


def test_async_client(world, srv):
    from sfmloc_client import AsyncLocalizationClient

    async def main() -> tuple:
        async with AsyncLocalizationClient(f"127.0.0.1:{srv.grpc_port}") as c:
            maps = await c.list_maps()
            pose = await c.relocalize(world.png[12], "room", camera(world), encoding="png")
            health = await c.health()
            return maps, pose, health

    maps, pose, health = asyncio.run(main())
    assert {m.name for m in maps} >= {"room", "room2"}
    assert pose.localized and health == "SERVING"


# ----------------------------------------------------------------------------- maps
def test_map_replaced_under_a_live_stream(world, z, grpc_client):
    old = grpc_client.get_map("room").build_id
    poses: list = []
    cam = camera(world)
    with (
        PoseSubscriber(z, "room", "replace", callback=poses.append) as sub,
        FrameStreamer(z, "room", "replace", cam) as fs,
    ):
        assert fs.wait_for_server(30)
        for k in range(50):
            seq = fs.publish(data=world.png[k], encoding="png", stamp_ns=int(k * 1e9 / 30))
            assert sub.wait_for(seq, 60)
            if k == 20:
                info = grpc_client.load_map(str(world.room_rebuilt), "room")  # replaces "room"
                assert info.build_id != old
    new = grpc_client.get_map("room").build_id
    assert new != old and new == info.build_id
    assert [p.seq for p in poses] == list(range(50)) and all(p.error is None for p in poses)
    builds = [p.build_id for p in poses]
    switch = builds.index(new)
    assert (
        switch == 21 and set(builds[:switch]) == {old} and set(builds[switch:]) == {new}
    )  # one clean switch
    assert poses[switch].status in ("RELOCALIZED", "LOST")  # a fresh Localizer on the new map
    assert sum(p.localized for p in poses[switch:]) >= len(poses[switch:]) - 3


def _index_mapping_kb(pid: int, bundle: Path) -> tuple[int, int, int]:
    """(mappings, Rss kB, Pss kB) of process ``pid``'s mappings of ``bundle``'s index file:
    the map's index pages that live in the shared file mapping (Pss < Rss: shared with
    another process)."""
    target = str(bundle.resolve() / "index_faiss.npy")
    n = rss = pss = 0
    hit = False
    with open(f"/proc/{pid}/smaps") as f:
        for line in f:
            parts = line.split()
            if parts and "-" in parts[0] and len(parts) >= 5:  # a mapping's header line
                hit = parts[-1] == target
                n += hit
            elif hit and parts[0] == "Rss:":
                rss += int(parts[1])
            elif hit and parts[0] == "Pss:":
                pss += int(parts[1])
    return n, rss, pss


def test_workers_share_one_mapped_index_and_all_see_a_replacement_under_load(
    world, z, grpc_client, srv
):
    """Every worker process reads a map's index in place from the bundle's file (one copy in
    the page cache, shared), and a map replaced while clients on every worker stream is seen
    by all of them: one clean switch per client, the new file mapped by every worker, the old
    one released."""
    import shutil

    base = world.spare_dir / "share-test"  # inside the server's map_roots
    shutil.rmtree(base, ignore_errors=True)
    old_dir, new_dir = base / "a" / "shared", base / "b" / "shared"
    shutil.copytree(world.maps_dir / "room", old_dir)  # files no other map of this server maps
    shutil.copytree(world.room_rebuilt, new_dir)
    pool = srv.server.pool
    probe = pool.load_map("probe", 10**6, str(old_dir), "")  # each worker: how it holds the index
    pool.drop_map("probe", 10**6)
    assert probe.index_in_place is True
    old = grpc_client.load_map(str(old_dir), "shared")
    pids = [h.pid for h in pool.workers]  # stream workers and the relocalization lane
    assert len(pids) == pool.n + pool.reloc_workers == 3
    for pid in pids:  # each worker searched the index at load (warm-up): the same pages
        n, rss, pss = _index_mapping_kb(pid, old_dir)
        assert n >= 1 and rss > 0 and pss < rss, (pid, n, rss, pss)

    # Clients until every worker hosts one (sessions go to the least busy worker).
    sessions = srv.server.sessions
    clients: list[str] = []
    while {s.worker for s in sessions.list("shared")} != set(range(pool.n)) and len(clients) < 8:
        cid = f"sharer-{len(clients)}"
        stream_lockstep(z, "shared", cid, world, n=1)
        clients.append(cid)
    assert {s.worker for s in sessions.list("shared")} == set(range(pool.n))

    n, switch_at = 40, 12
    half, swapped = threading.Event(), threading.Event()
    results: dict[str, list] = {}

    def client(cid: str) -> None:
        got: list = []
        with (
            PoseSubscriber(z, "shared", cid, callback=got.append) as sub,
            FrameStreamer(z, "shared", cid, camera(world)) as fs,
        ):
            for k in range(n):
                seq = fs.publish(
                    data=world.png[k], encoding="png", seq=k, stamp_ns=int((k + 1) * 1e9 / 30)
                )
                assert sub.wait_for(seq, 60)
                if k == switch_at:
                    half.set()
                    assert swapped.wait(120)  # LoadMap returned: the registry has swapped
        results[cid] = got

    threads = [threading.Thread(target=client, args=(c,)) for c in clients]
    for t in threads:
        t.start()
    assert half.wait(120)
    new = grpc_client.load_map(str(new_dir), "shared")  # replaces "shared" while they stream
    swapped.set()
    for t in threads:
        t.join(180)
    assert new.build_id != old.build_id
    for cid in clients:
        poses = results[cid]
        assert [p.seq for p in poses] == list(range(n)) and all(p.error is None for p in poses), cid
        builds = [p.build_id for p in poses]
        k = builds.index(new.build_id)
        assert 0 < k and set(builds[:k]) == {old.build_id}, cid
        assert set(builds[k:]) == {new.build_id}, cid
        assert sum(p.localized for p in poses[k:]) >= len(poses[k:]) - 3, cid
    for pid in pids:
        n, rss, pss = _index_mapping_kb(pid, new_dir)
        assert n >= 1 and rss > 0 and pss < rss, (pid, n, rss, pss)
    # The old generation is dropped everywhere: its file is no longer mapped by any worker.
    assert wait_until(lambda: all(_index_mapping_kb(pid, old_dir)[0] == 0 for pid in pids), 30)
    grpc_client.unload_map("shared")
    shutil.rmtree(base, ignore_errors=True)


def test_unload_load_and_corrupt_bundles(world, z, grpc_client):
    r = grpc_client.unload_map("room2")
    assert r.unloaded
    assert "room2" not in {m.name for m in grpc_client.list_maps()}
    with pytest.raises(RemoteError) as e:
        grpc_client.get_map("room2")
    assert e.value.code == "NOT_FOUND"
    with pytest.raises(RemoteError) as e:
        grpc_client.unload_map("room2")
    assert e.value.code == "NOT_FOUND"
    with pytest.raises(RemoteError) as e:
        grpc_client.load_map(str(world.corrupt), "room2")
    assert e.value.code == "FAILED_PRECONDITION" and "corrupt" in e.value.message
    with pytest.raises(RemoteError) as e:
        grpc_client.load_map(str(world.maps_dir / "nothing-here"))
    assert e.value.code == "FAILED_PRECONDITION"
    with pytest.raises(RemoteError) as e:
        grpc_client.load_map(str(world.maps_dir / "room2"), "bad name!")
    assert e.value.code == "INVALID_ARGUMENT"
    assert wait_until(
        lambda: grpc_client.health("sfmloc.v1.Localization/room2") == "NOT_SERVING", 10
    )
    assert grpc_client.health() == "SERVING"  # room is still loaded
    m = grpc_client.load_map(str(world.maps_dir / "room2"))
    assert m.name == "room2" and m.points > 0 and m.memory_mb > 0
    assert wait_until(lambda: grpc_client.health("sfmloc.v1.Localization/room2") == "SERVING", 10)
    assert [p.seq for p in stream_lockstep(z, "room2", "after-reload", world, n=5)] == list(
        range(5)
    )


def test_load_map_only_from_the_maps_folders(world, z, grpc_client):
    """LoadMap takes a map name or a path inside the maps folders (--maps, map_roots);
    anything else, a bundle included, is PERMISSION_DENIED before it is read, and the
    message does not tell whether the outside path exists."""
    outside = world.root / "synth"  # exists, outside both roots
    link_in_maps = world.maps_dir / "link-out"
    link_in_maps.symlink_to(world.root, target_is_directory=True)
    try:
        for path in (
            str(outside),
            str(world.root / "nothing-here"),
            "/etc",
            "/dev/zero",
            "/",
            str(world.maps_dir / ".." / "synth"),
            str(link_in_maps / "synth"),
            "../synth",
            str(world.maps_dir),
        ):
            with pytest.raises(RemoteError) as e:
                grpc_client.load_map(path, "denied")
            assert e.value.code == "PERMISSION_DENIED", path
            assert "outside the server's maps folders" in e.value.message
            assert "No such file" not in e.value.message
        # an announcement pointing outside is refused the same way (logged, nothing loaded)
        ann = MapAnnouncement("denied", "some-build", str(outside))
        z.put(map_announce_key("denied"), encode_map_announcement(ann))
        # a name resolves inside the maps folder; a relative path from it
        assert grpc_client.load_map("room2", "by-name").points > 0
        assert grpc_client.load_map("./room2", "by-rel").points > 0
        assert "denied" not in {m.name for m in grpc_client.list_maps()}
    finally:
        link_in_maps.unlink()
        for m in grpc_client.list_maps():
            if m.name in ("by-name", "by-rel"):
                grpc_client.unload_map(m.name)


def test_follow_builder_announcement_loads_the_map(world, z, grpc_client):
    # The announced build id is the folder's: a folder of another build at that path would be
    # fetched from the builder instead (bundles over the network), not loaded in its place.
    from sfmloc.map.bundle import MapBundle

    build_id = MapBundle(world.maps_dir / "room2", verify=False).build_id
    ann = MapAnnouncement("room3", build_id, str(world.maps_dir / "room2"))
    z.put(map_announce_key("room3"), encode_map_announcement(ann))
    assert wait_until(lambda: "room3" in {m.name for m in grpc_client.list_maps()}, 60)
    assert grpc_client.get_map("room3").points == grpc_client.get_map("room2").points
    z.put(map_announce_key("bad"), b"\x00garbage")  # ignored, logged
    grpc_client.unload_map("room3")


# ----------------------------------------------------------------------------- sessions
def test_a_second_device_under_the_same_client_id_is_refused(world, zep, srv):
    """Two Zenoh sessions (two devices) streaming under one client id: the second is refused
    with PERMISSION_DENIED and the first keeps its session (its poses stay correct); once the
    first has been silent for a few seconds, the second takes over with a fresh session."""
    from sfmloc.server.sessions import SOURCE_TAKEOVER_S

    cam = camera(world)
    with client_zenoh(zep) as za, client_zenoh(zep) as zb:
        got = Collected()

        def answered(k: int) -> bool:  # wait_for(seq) means "up to seq": the seqs interleave here
            return got.has_seq(k)

        with (
            PoseSubscriber(za, "room", "twin", callback=got.append),
            FrameStreamer(za, "room", "twin", cam) as a,
            FrameStreamer(zb, "room", "twin", cam) as b,
        ):
            assert a.source != b.source
            assert a.wait_for_server(30) and b.wait_for_server(30)
            for k in range(20):
                a.publish(data=world.png[k], encoding="png", seq=k, stamp_ns=int(k * 1e9 / 30))
                assert answered(k)
                if k in (5, 10, 15):
                    b.publish(
                        data=world.png[k], encoding="png", seq=1000 + k, stamp_ns=int(k * 1e9 / 30)
                    )
                    assert answered(1000 + k)
            mine = [p for p in got if p.seq is not None and p.seq < 1000]
            theirs = [p for p in got if p.seq is not None and p.seq >= 1000]
            assert [p.seq for p in mine] == list(range(20))
            assert len(theirs) == 3 and all(
                p.error is not None and p.error.code == "PERMISSION_DENIED" for p in theirs
            )
            assert "in use by another sender" in theirs[0].error.message
            assert (
                position_errors(world, mine[3:]).max() < 0.05
            )  # A's track table was not disturbed
            assert mine[-1].status == "TRACKING"
            # A goes quiet: B's frames are refused until A has been silent SOURCE_TAKEOVER_S,
            # then B takes the id over, from a fresh session
            seq = iter(range(3000, 4000))

            def b_accepted() -> bool:
                k = next(seq)
                b.publish(data=world.png[20], encoding="png", seq=k, stamp_ns=int(20 * 1e9 / 30))
                assert answered(k)
                return next(p for p in got if p.seq == k).error is None

            assert not b_accepted()  # right after A's last frame: still A's
            assert wait_until(b_accepted, SOURCE_TAKEOVER_S + 30, every=0.25)
            for k in range(20, 25):
                b.publish(
                    data=world.png[k], encoding="png", seq=2000 + k, stamp_ns=int(k * 1e9 / 30)
                )
                assert answered(2000 + k)
            taken = [p for p in got if p.seq is not None and 2000 <= p.seq < 3000]
            assert all(p.error is None for p in taken) and sum(p.localized for p in taken) >= 3
    assert srv.server.metrics.sessions_closed.get("room", "replaced") >= 1


def test_list_and_reset_sessions(world, z, grpc_client):
    poses = stream_lockstep(z, "room", "resettable", world, n=10)
    assert poses[-1].status == "TRACKING"
    s = [s for s in grpc_client.list_sessions("room") if s.client_id == "resettable"]
    assert len(s) == 1 and s[0].transport == "zenoh" and s[0].frames == 10 and s[0].localized >= 9
    assert grpc_client.reset_session("resettable", "room")
    got: list = []
    with (
        PoseSubscriber(z, "room", "resettable", callback=got.append) as sub,
        FrameStreamer(z, "room", "resettable", camera(world)) as fs,
    ):
        fs.publish(data=world.png[10], encoding="png", seq=10, stamp_ns=int(10 * 1e9 / 30))
        assert sub.wait_for(10, 60)
    assert got[0].status in ("RELOCALIZED", "LOST")  # forgot its tracks: global matching again
    with pytest.raises(RemoteError) as e:
        grpc_client.reset_session("nobody")
    assert e.value.code == "NOT_FOUND"


# ----------------------------------------------------------------------------- discovery, metrics
def test_discovery_token_and_info(z, srv):
    assert "test-server" in list_server_ids(z)
    infos = query_servers(z, timeout=5)
    info = next(i for i in infos if i.server_id == "test-server")
    assert info.ready and info.workers == 2 and info.grpc.endswith(str(srv.grpc_port))
    assert {"room", "room2"} <= {m["name"] for m in info.maps}


def test_metrics_endpoint(world, z, srv):
    stream_lockstep(z, "room", "metered", world, n=5)
    port = srv.conf.metrics_port
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
    assert 'sfmloc_frames_received_total{map="room",transport="zenoh"}' in text
    assert 'sfmloc_frame_latency_seconds_bucket{map="room",le="+Inf"}' in text
    assert "# TYPE sfmloc_frame_latency_seconds histogram" in text
    assert 'sfmloc_sessions{map="room",transport="zenoh"}' in text
    assert 'sfmloc_maps_loaded{map="room"' in text
    count = next(
        float(line.split()[-1])
        for line in text.splitlines()
        if line.startswith('sfmloc_frame_latency_seconds_count{map="room"}')
    )
    assert count >= 5
    assert urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=10).status == 200


def test_health_and_reflection(srv, grpc_client):
    from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

    assert grpc_client.health() == "SERVING"
    assert grpc_client.health("sfmloc.v1.Localization") == "SERVING"
    assert grpc_client.health("sfmloc.v1.Localization/room") == "SERVING"  # per map
    with pytest.raises(RemoteError) as e:
        grpc_client.health("sfmloc.v1.Localization/no-such-map")
    assert e.value.code == "NOT_FOUND"
    stub = reflection_pb2_grpc.ServerReflectionStub(grpc_client.channel)
    resp = next(
        stub.ServerReflectionInfo(
            iter([reflection_pb2.ServerReflectionRequest(list_services="")]), timeout=10
        )
    )
    names = {s.name for s in resp.list_services_response.service}
    assert {"sfmloc.v1.Localization", "grpc.health.v1.Health"} <= names
    # The stable v1 name answers too (same messages; grpcurl and Postman ask v1 first), and
    # serves the descriptors a client needs to call us.
    v1 = grpc_client.channel.stream_stream(
        "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
        request_serializer=reflection_pb2.ServerReflectionRequest.SerializeToString,
        response_deserializer=reflection_pb2.ServerReflectionResponse.FromString,
    )
    asks = [
        reflection_pb2.ServerReflectionRequest(list_services=""),
        reflection_pb2.ServerReflectionRequest(file_containing_symbol="sfmloc.v1.Localization"),
    ]
    listed, described = list(v1(iter(asks), timeout=10))
    assert names == {s.name for s in listed.list_services_response.service}
    assert "grpc.reflection.v1.ServerReflection" in names
    assert described.file_descriptor_response.file_descriptor_proto


def test_a_crashed_worker_is_restarted_and_other_clients_carry_on(world, z, srv):
    import os
    import signal

    before = stream_lockstep(z, "room", "survivor", world, n=5)
    assert before[-1].localized
    pool = srv.server.pool
    victim = pool.workers[0]
    pid = victim.pid
    os.kill(pid, signal.SIGKILL)
    assert pool.wait_for(lambda: pool.workers[0].pid not in (0, pid) and pool.is_alive(0), 120)
    after = stream_lockstep(z, "room", "survivor", world, n=10)
    assert [p.seq for p in after] == list(range(10))
    assert sum(p.localized for p in after) >= 8


def test_a_worker_killed_under_streams_answers_every_frame(world, z, srv):
    """kill -9 of the worker two streams are on, while their frames are in it: every frame
    gets an answer (a pose, or UNAVAILABLE for the frames the dead worker had), and the
    sessions go on at once on the surviving worker, before the replacement is ready."""
    import os
    import signal

    pool = srv.server.pool
    assert pool.wait_for(
        lambda: all(h.alive and h.serving and h.ready.is_set() for h in pool.workers), 120
    )
    cam = camera(world)
    got = {"k1": Collected(), "k2": Collected()}
    with (
        PoseSubscriber(z, "room", "k1", callback=got["k1"].append),
        PoseSubscriber(z, "room", "k2", callback=got["k2"].append),
        FrameStreamer(z, "room", "k1", cam) as f1,
        FrameStreamer(z, "room", "k2", cam) as f2,
    ):
        streams = [(f1, "k1"), (f2, "k2")]
        assert f1.wait_for_server(30) and f2.wait_for_server(30)
        for f, cid in streams:  # open both sessions
            f.publish(data=world.png[0], encoding="png", seq=0, stamp_ns=0)
            assert got[cid].has_seq(0)
        workers = {
            s.worker for s in srv.server.sessions.list("room") if s.client_id in ("k1", "k2")
        }
        victim = pool.workers[sorted(workers)[0]]
        restarts = pool.restarts
        for k in range(1, 40):
            for f, _ in streams:
                f.publish(data=world.png[k], encoding="png", seq=k, stamp_ns=int(k * 1e9 / 30))
            if k == 5:
                os.kill(victim.pid, signal.SIGKILL)
            for _, cid in streams:
                assert got[cid].has_seq(k), (cid, k)
        moved = {s.worker for s in srv.server.sessions.list("room") if s.client_id in ("k1", "k2")}
    for cid in ("k1", "k2"):
        seqs = sorted({p.seq for p in got[cid]})
        assert seqs == list(range(40)), cid  # nothing silent
        errors = [p for p in got[cid] if p.error is not None]
        assert all(p.error.code == "UNAVAILABLE" for p in errors) and len(errors) <= 2
        assert sum(p.localized for p in got[cid] if p.seq >= 30) >= 8  # it went on
    assert pool.restarts >= restarts + 1
    assert victim.index not in moved  # the sessions left the dead worker and stayed away
    assert pool.wait_for(
        lambda: pool.is_alive(victim.index) and pool.workers[victim.index].ready.is_set(), 120
    )


def test_load_map_while_a_worker_restarts(world, z, srv, grpc_client):
    """LoadMap right after a worker died answers without waiting for the dead worker, and the
    replacement comes up with that map too (it reloads the maps current when it is ready)."""
    import os
    import signal

    pool = srv.server.pool
    assert pool.wait_for(
        lambda: all(h.alive and h.serving and h.ready.is_set() for h in pool.workers), 120
    )
    victim = pool.workers[0]
    restarts = pool.restarts
    os.kill(victim.pid, signal.SIGKILL)
    assert pool.wait_for(lambda: not pool.is_alive(0), 60)
    info = grpc_client.load_map("room2", "window", timeout=60)  # answered by the live worker
    assert info.name == "window"
    assert pool.wait_for(
        lambda: pool.restarts > restarts and pool.is_alive(0) and pool.workers[0].ready.is_set(),
        120,
    )
    # two new sessions: one lands on the replacement, which must hold "window"
    for cid in ("win-a", "win-b"):
        poses = stream_lockstep(z, "window", cid, world, n=4)
        assert all(p.error is None for p in poses) and poses[-1].localized, (
            cid,
            [(p.seq, p.status, p.error) for p in poses],
        )
    assert {s.worker for s in srv.server.sessions.list("window")} >= {0}
    grpc_client.unload_map("window")


def test_a_stream_reports_an_outage_and_resumes_by_itself(world, z, srv):
    """The server stops answering for a while (its frame intake withdrawn from frame 15 to
    40): the streamer counts the outage (frames without an answer), keeps sending, and gets
    poses again afterwards without being restarted."""
    cam = camera(world)
    got: list = []
    fe = srv.server.zenoh

    def on_sent(seq, _fr, _t):
        if seq == 15:
            fe.stop_intake()
        elif seq == 40:
            fe.start_intake()

    try:
        with (
            PoseSubscriber(z, "room", "outage", callback=got.append) as poses,
            FrameStreamer(z, "room", "outage", cam) as fs,
        ):
            assert fs.wait_for_server(30)
            src = [
                SourceFrame(data=d, encoding="png", stamp_ns=int(k * 1e9 / 30))
                for k, d in enumerate(world.png[:70])
            ]
            stats = fs.run(src, fps=15, poses=poses, on_sent=on_sent)
            # answers come back (the server keeps the newest frame of a busy session)
            assert poses.wait_for(45, 60)
    finally:
        if fe._frame_sub is None:
            fe.start_intake()
    assert stats.outages >= 1 and stats.max_unanswered >= 20  # frames 16-39 had no answer
    assert not {p.seq for p in got} & set(range(20, 38))  # nothing was answered in the outage


def test_a_grpc_stream_survives_unload_and_resumes_when_the_map_is_back(world, grpc_client):
    """UnloadMap under a live StreamLocalize: the frames get NOT_FOUND (none is silent, the
    stream stays open), and once the map is loaded again the same stream localizes again."""
    grpc_client.load_map("room2", "blinky")
    acks: queue.Queue = queue.Queue()

    def requests():
        for k, d in enumerate(world.png[:24]):
            if k == 8:
                grpc_client.unload_map("blinky")
            elif k == 14:
                grpc_client.load_map("room2", "blinky")
            yield SourceFrame(data=d, encoding="png", stamp_ns=int(k * 1e9 / 30))
            acks.get(timeout=60)

    poses = []
    try:
        for p in grpc_client.stream(
            requests(), "blinky", camera(world), client_id="blinker", encoding="png"
        ):
            poses.append(p)
            acks.put(p.seq)
    finally:
        if "blinky" in {m.name for m in grpc_client.list_maps()}:
            grpc_client.unload_map("blinky")
    assert [p.seq for p in poses] == list(range(24))  # every frame answered, stream not ended
    gone = [p for p in poses if 8 <= p.seq < 14]
    assert all(p.error is not None and p.error.code == "NOT_FOUND" for p in gone)
    assert all(p.error is None for p in poses if p.seq < 8 or p.seq >= 14)
    assert sum(p.localized for p in poses if p.seq >= 14) >= 8  # resumed on the reloaded map
