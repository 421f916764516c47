"""A frame's pose prior (an outside estimate of its cam_from_world: the client's last pose when
it moves to another server, GPS/IMU): the engine searches around it before global matching when
it has no prediction of its own; it travels in the Zenoh frame envelope; a wrong prior costs
time, never a wrong pose. Exact synthetic ground truth."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import zenoh

from server_helpers import Collected, camera, running_server, server_config, zenoh_endpoint
from sfmloc.cameras import Camera
from sfmloc.engine import Localizer
from sfmloc.map.bundle import MapBundle
from sfmloc.transforms import Rigid3d, pose_errors, rotmat_from_rotvec
from sfmloc_client import FrameStreamer, PoseSubscriber, make_zenoh_config
from sfmloc_client.errors import WireError
from sfmloc_client.wire import CameraSpec, Frame, PoseMessage, Transform, decode_frame, encode_frame

K = 7  # a frame of the walk (not the first: nothing special about it)


def _perturbed(T: Rigid3d, dpos: float, deg: float) -> Rigid3d:
    """``T`` with its centre moved by ``dpos`` (map units) and turned by ``deg``."""
    R = rotmat_from_rotvec(np.radians(deg) * np.array([0.0, 1.0, 0.0])) @ T.rotation
    c = T.center + np.array([dpos, 0.0, 0.0])
    return Rigid3d(R, -R @ c)


def _wire(T: Rigid3d) -> Transform:
    q, t = T.quat_xyzw, T.translation
    return Transform(tuple(float(x) for x in q), tuple(float(x) for x in t))  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def engine(world):
    return MapBundle(world.maps_dir / "room"), Camera.parse(world.camera_spec)


def test_a_new_session_with_a_prior_is_found_around_it(world, engine):
    bundle, cam = engine
    gt = world.gt_cam_from_world[K]
    near = _perturbed(gt, 0.02 * bundle.scene_scale, 2.0)
    r = Localizer(bundle, cam).localize(world.gray[K], 0.0, prior=near)
    assert r.matching == "guided", r.message  # no global matching ran
    assert r.status.value in ("RELOCALIZED", "UNVERIFIED")
    dp, dr = pose_errors(r.cam_from_world, gt)
    assert dp < 0.01 * bundle.scene_scale and dr < 0.5, (dp, dr)
    # without it: global matching, the same place
    r0 = Localizer(bundle, cam).localize(world.gray[K], 0.0)
    assert r0.matching == "global"
    assert np.linalg.norm(r0.cam_from_world.center - r.cam_from_world.center) < (
        0.01 * bundle.scene_scale
    )


@pytest.mark.parametrize(
    "dpos, deg",
    [(1.0, 0.0), (0.0, 90.0), (0.0, 180.0), (0.3, 30.0)],  # scene scales, degrees
)
def test_a_wrong_prior_costs_time_not_a_wrong_pose(world, engine, dpos, deg):
    bundle, cam = engine
    gt = world.gt_cam_from_world[K]
    far = _perturbed(gt, dpos * bundle.scene_scale, deg)
    r = Localizer(bundle, cam).localize(world.gray[K], 0.0, prior=far)
    assert r.cam_from_world is not None, r.message
    dp, dr = pose_errors(r.cam_from_world, gt)
    assert dp < 0.05 * bundle.scene_scale and dr < 10.0, (r.matching, dp, dr)


def test_the_prior_is_ignored_while_the_engine_has_its_own_prediction(world, engine):
    bundle, cam = engine
    loc = Localizer(bundle, cam)
    loc.localize(world.gray[0], 0.0)
    far = _perturbed(world.gt_cam_from_world[1], bundle.scene_scale, 180.0)
    r = loc.localize(world.gray[1], 1 / 30, prior=far)
    assert r.status.value == "TRACKING"
    dp, _ = pose_errors(r.cam_from_world, world.gt_cam_from_world[1])
    assert dp < 0.01 * bundle.scene_scale


def test_the_prior_travels_in_the_frame_envelope():
    cam = CameraSpec("PINHOLE", 4, 3, (5.0, 5.0, 2.0, 1.5))
    prior = Transform((0.0, 0.0, math.sin(0.2), math.cos(0.2)), (1.0, -2.0, 3.5))
    f = Frame(1, 2, cam, "gray8", bytes(12), prior=prior)
    assert decode_frame(encode_frame(f)).prior == prior
    assert decode_frame(encode_frame(Frame(1, 2, cam, "gray8", bytes(12)))).prior is None
    for bad in (
        Transform((0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),  # no rotation
        Transform((0.0, 0.0, 0.0, 1.0), (math.nan, 0.0, 0.0)),
        Transform((0.0, 0.0, 1.0), (0.0, 0.0, 0.0)),  # type: ignore[arg-type]
    ):
        with pytest.raises(WireError, match="prior"):
            encode_frame(Frame(1, 2, cam, "gray8", bytes(12), prior=bad))


def test_a_server_uses_the_prior_and_a_streamer_hands_over_the_last_pose(world):
    """A real server: a new session's first frame with a prior is found around it (guided),
    without one by global matching. A ``FrameStreamer`` that moved to a server which has not
    localized it yet sends the last pose another server gave it."""
    ep = zenoh_endpoint()
    with (
        running_server(server_config(world, ep, server_id="s1")),
        zenoh.open(make_zenoh_config("peer", connect=[ep], multicast=False)) as z,
    ):
        for client, prior in (("with-prior", _wire(world.gt_cam_from_world[K])), ("none", None)):
            got = Collected()
            with (
                PoseSubscriber(z, "room", client, callback=got.append),
                FrameStreamer(z, "room", client, camera(world), encoding="png") as fs,
            ):
                assert fs.wait_for_server(20)
                fs.publish(data=world.png[K], encoding="png", prior=prior)
                assert got.has_seq(0, 30)
            (p,) = list(got)
            assert p.localized and p.matching == ("guided" if prior else "global"), p

        # The handover: the last pose came from "s0" (gone); frames now go to s1.
        got = Collected()
        with (
            PoseSubscriber(z, "room", "mover", callback=got.append),
            FrameStreamer(z, "room", "mover", camera(world), encoding="png", server="s1") as fs,
        ):
            assert fs.wait_for_server(20)
            old = PoseMessage(41, 0, "TRACKING", _wire(world.gt_cam_from_world[K]), server_id="s0")
            fs.note_pose(old)
            assert fs._handover_prior("s1") == old.cam_from_world
            fs.publish(data=world.png[K], encoding="png")
            assert got.has_seq(0, 30)
            first = list(got)[0]
            assert first.localized and first.matching == "guided", first
            fs.note_pose(first)  # s1 localized us: no more prior
            assert fs._handover_prior("s1") is None


def test_a_grpc_stream_frame_carries_a_prior(world):
    """StreamLocalize: a SourceFrame's prior goes as prior_cam_from_world; the first frame is
    found around it; a malformed prior is that frame's INVALID_ARGUMENT, the stream goes on."""
    from sfmloc_client import LocalizationClient, SourceFrame

    bad = Transform((0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # no rotation: refused
    frames = [
        SourceFrame(data=world.png[K], encoding="png", prior=_wire(world.gt_cam_from_world[K])),
        SourceFrame(data=world.png[K + 1], encoding="png", prior=bad),
        SourceFrame(data=world.png[K + 2], encoding="png"),
    ]

    def paced():  # one at a time: no frame dropped as stale
        for k, f in enumerate(frames):
            yield f
            deadline = time.monotonic() + 60
            while len(poses) <= k and time.monotonic() < deadline:
                time.sleep(0.01)

    ep = zenoh_endpoint()
    poses: list = []
    with (
        running_server(server_config(world, ep)) as srv,
        LocalizationClient(f"127.0.0.1:{srv.grpc_port}") as gc,
    ):
        for p in gc.stream(paced(), "room", camera(world), encoding="png", timeout=60):
            poses.append(p)
    assert [p.seq for p in poses] == [0, 1, 2]
    assert poses[0].localized and poses[0].matching == "guided", poses[0]
    assert poses[1].error is not None and poses[1].error.code == "INVALID_ARGUMENT"
    assert "quaternion" in poses[1].error.message
    assert poses[2].localized
