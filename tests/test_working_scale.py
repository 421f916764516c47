"""The scale-aware front end against exact ground truth: frames and queries finer than the map
(here 3072x2048 and 1280x960 renders of a room mapped from 640x480 views) are processed at
the map's resolution with scaled intrinsics, and poses come back for the original camera.
Also: the map's recorded keypoint scales, and bundles written before they were recorded."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from server_helpers import WIDTH
from sfmloc.cameras import Camera
from sfmloc.engine import EngineConf, Localizer, Status, relocalize
from sfmloc.engine.frame import to_working, working_scale
from sfmloc.errors import BundleError
from sfmloc.features.harris import detect_corners
from sfmloc.map.bundle import MANIFEST, MANIFEST_SHA256, MapBundle
from sfmloc.transforms import pose_errors

F640 = 525.0  # the world's focal length at 640x480


@pytest.fixture(scope="module")
def scene(world):
    from server_helpers import room_scene, world_synth_conf
    from sfmloc.synth.renderer import prepare

    conf = world_synth_conf()
    sc = room_scene(conf.seed, conf.scene)
    prepare(sc)
    return sc, conf


def big_camera(w: int, h: int) -> Camera:
    """The world's horizontal field of view at another resolution (principal point centred)."""
    f = F640 * w / WIDTH
    return Camera.pinhole(w, h, f, f, w / 2, h / 2)


def render_gray(scene, camera: Camera, pose, seed: int) -> np.ndarray:
    from sfmloc.synth.renderer import render_full

    sc, conf = scene
    bgr = render_full(sc, camera, pose, noise_seed=(seed, 5), conf=conf.render).bgr
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)


@pytest.fixture(scope="module")
def big(world, scene):
    """Frame 30 of the video rendered at 3072x2048 (exact pose)."""
    cam = big_camera(3072, 2048)
    return cam, render_gray(scene, cam, world.gt_cam_from_world[30], 30)


def test_working_scale_selection_and_scaled_intrinsics():
    # 3072x2048 at f = 2520 against a map of f = 525 images: exactly 640 px wide, f = 525.
    cam = big_camera(3072, 2048)
    s = working_scale(cam, F640)
    assert s == pytest.approx(640 / 3072)
    w = cam.scaled(s)
    assert (w.width, w.height) == (640, 427)
    np.testing.assert_allclose(w.params, [525.0, 525.0, 320.0, 1024 * 640 / 3072], rtol=1e-12)
    assert to_working(np.zeros((2048, 3072), np.uint8), s).shape == (427, 640)
    assert working_scale(big_camera(1280, 960), F640) == 0.5
    # At or below the map's resolution, or within half a sub-octave of it: as it is.
    assert working_scale(big_camera(640, 480), F640) == 1.0
    assert working_scale(Camera.pinhole(640, 480, 560, 560, 320, 240), F640) == 1.0
    assert working_scale(big_camera(320, 240), F640) == 1.0  # never upsampled
    assert working_scale(cam, F640, "full") == 1.0  # the paper's behaviour, on request
    # A map of 3072x2048 images (f = 2520, pyramid down to 630): a frame of the same camera
    # runs within the engine's pixel budget (640x480 pixels) but not below the map's coarsest
    # level: 768x512, f = 630.
    assert working_scale(cam, 2520.0, "map", 640 * 480, 630.0) == 768 / 3072
    # A 1920x1080 camera mapped with itself: the budget alone (pyramid down to f / 4).
    hd = Camera.pinhole(1920, 1080, 1400, 1400, 960, 540)
    budget = np.sqrt(640 * 480 / (1920 * 1080))
    assert working_scale(hd, 1400.0, "map", 640 * 480, 350.0) == round(1920 * budget) / 1920
    # The budget never makes a frame finer than the map, and a VGA frame is left alone.
    assert working_scale(cam, F640, "map", 640 * 480, F640 / 4) == pytest.approx(640 / 3072)
    assert working_scale(big_camera(640, 480), F640, "map", 640 * 480, F640 / 4) == 1.0
    # Other models: distortion is in normalized coordinates and stays.
    rad = Camera("SIMPLE_RADIAL", 2000, 1500, np.array([1640.0, 1000.0, 750.0, -0.05]))
    r = rad.scaled(working_scale(rad, 410.0))
    assert (r.width, r.height) == (500, 375)
    np.testing.assert_allclose(r.params, [410.0, 250.0, 187.5, -0.05], rtol=1e-12)


def corner_offset(a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
    """Matched Harris corners of two images of one view: how many, and their median shift."""
    from scipy.spatial import cKDTree

    ca = detect_corners(a, rel_threshold=0.01, border=10)
    cb = detect_corners(b, rel_threshold=0.01, border=10)
    d, nn = cKDTree(cb.xy).query(ca.xy, distance_upper_bound=1.5)
    hit = np.isfinite(d)
    return int(hit.sum()), np.median(cb.xy[nn[hit]] - ca.xy[hit], axis=0)


def test_working_image_is_the_view_of_the_scaled_camera(world, scene, big):
    """The 3072x2048 render downscaled to the working scale equals, corner for corner, the
    same view rendered directly through ``Camera.scaled``: pixels are COLMAP's (corner
    origin), so the principal point scales as c * s. (Scaled as for pixel centres at integers,
    (c + 0.5) * s - 0.5, every corner would be 0.37 px off.)"""
    cam, gray = big
    s = working_scale(cam, F640)
    wcam = cam.scaled(s)
    working = to_working(gray, s)
    direct = render_gray(scene, wcam, world.gt_cam_from_world[30], 30)
    n, offset = corner_offset(working, direct)
    assert n >= 200, n
    assert np.all(np.abs(offset) < 0.08), offset
    fx, fy, cx, cy = wcam.params
    centred = Camera.pinhole(
        wcam.width, wcam.height, fx, fy, (1536 + 0.5) * s - 0.5, (1024 + 0.5) * s - 0.5
    )
    n, offset = corner_offset(working, render_gray(scene, centred, world.gt_cam_from_world[30], 30))
    assert np.all(np.abs(offset) > 0.25), offset


def test_large_query_relocalizes_with_the_pose_of_the_small_one(world, bundle, big):
    cam, gray = big
    gt = world.gt_cam_from_world[30]
    r = relocalize(gray, cam, bundle)
    assert r.status is Status.RELOCALIZED, r.message
    dp, dr = pose_errors(r.cam_from_world, gt)
    assert dp < 0.05 and dr < 1.0, (dp, dr)
    small = relocalize(world.gray[30], Camera.parse(world.camera_spec), bundle)
    assert small.status is Status.RELOCALIZED
    dp, dr = pose_errors(r.cam_from_world, small.cam_from_world)
    assert dp < 0.05 and dr < 1.0, (dp, dr)
    # With a prior, the same scale (the prior's scoped search uses the working camera).
    near = relocalize(gray, cam, bundle, prior=small.cam_from_world)
    assert near.status is Status.RELOCALIZED
    dp, dr = pose_errors(near.cam_from_world, gt)
    assert dp < 0.05 and dr < 1.0, (dp, dr)


def test_localizer_streams_1280x960_frames_at_the_map_scale(world, bundle, scene):
    cam = big_camera(1280, 960)
    loc = Localizer(bundle, cam)
    assert loc.scale == 0.5 and loc.input_camera == cam
    assert loc.camera == cam.scaled(0.5) and (loc.camera.width, loc.camera.height) == (640, 480)
    n = 6
    res = [
        loc.localize(render_gray(scene, cam, world.gt_cam_from_world[i], i), i / 30)
        for i in range(n)
    ]
    assert res[0].status is Status.RELOCALIZED
    assert all(r.status is not Status.LOST for r in res)
    for r, gt in zip(res, world.gt_cam_from_world[:n]):
        dp, dr = pose_errors(r.cam_from_world, gt)
        assert dp < 0.05 and dr < 1.0, (dp, dr)
    with pytest.raises(Exception, match="camera is 1280x960"):
        loc.localize(world.gray[0], n / 30)  # frames are the caller's camera's size


def write_manifest(bundle_dir, manifest: dict) -> None:
    """Replace a bundle's manifest, with its checksum file (as an older writer would have)."""
    import hashlib

    text = json.dumps(manifest).encode()
    (bundle_dir / MANIFEST).write_bytes(text)
    (bundle_dir / MANIFEST_SHA256).write_text(f"{hashlib.sha256(text).hexdigest()}  {MANIFEST}\n")


def test_bundle_records_keypoint_scales_and_old_bundles_still_load(world, bundle, tmp_path):
    ks = bundle.keypoint_scales
    assert bundle.native_focal_px == pytest.approx(F640)
    assert bundle.coarsest_focal_px == pytest.approx(F640 / 4)  # two octaves down
    assert ks["native_focal_px"] == pytest.approx(F640)
    # An old bundle: no keypoint_scales in its manifest (checksums cover the arrays only).
    old = tmp_path / "old"
    shutil.copytree(world.maps_dir / "room", old)
    m = json.loads((old / MANIFEST).read_text())
    m.pop("keypoint_scales")
    m["params"] = {"descriptors": {"octaves": 2, "per_octave": 4, "up_levels": 2}}
    write_manifest(old, m)
    b = MapBundle(old)
    assert b.native_focal_px == pytest.approx(F640)
    # From desc_level and the recorded pyramid: the levels span 2^0.5 .. 2^-2 of 525 px.
    pct = b.keypoint_scales["descriptor_focal_px"]
    assert F640 / 4 - 1e-6 <= pct["p05"] <= pct["p50"] <= pct["p95"] <= F640 * 2**0.5 + 1e-6
    levels = np.asarray(b.array("desc_level"))
    expect = np.median(F640 * 2.0 ** ((2 - levels.astype(float)) / 4))
    assert pct["p50"] == pytest.approx(expect)
    # ... and the engine uses it exactly as for a new bundle.
    assert Localizer(b, big_camera(3072, 2048)).scale == pytest.approx(640 / 3072)
    # A manifest with a nonsensical value is an error naming it.
    m["keypoint_scales"] = {"native_focal_px": -3}
    write_manifest(old, m)
    with pytest.raises(BundleError, match="native_focal_px"):
        MapBundle(old)


def test_full_resolution_mode_is_the_papers_front_end(world, bundle):
    """The switch off: a 640x480 camera is unaffected either way, and "full" keeps a large
    camera at its own resolution."""
    cam = Camera.parse(world.camera_spec)
    assert Localizer(bundle, cam).scale == 1.0
    assert Localizer(bundle, big_camera(1280, 960), EngineConf(working_scale="full")).scale == 1.0


def test_large_query_over_grpc(world, big):
    """The server path: a 3072x2048 JPEG through gRPC's Relocalize is processed at the
    working scale and the pose comes back for the original camera."""
    from server_helpers import free_port, running_server, server_config, zenoh_endpoint
    from sfmloc_client import CameraSpec, LocalizationClient

    cam, gray = big
    spec = CameraSpec.parse("PINHOLE 3072 2048 " + " ".join(repr(float(p)) for p in cam.params))
    conf = server_config(world, zenoh_endpoint(), metrics_port=free_port())
    with (
        running_server(conf) as srv,
        LocalizationClient(f"127.0.0.1:{srv.grpc_port}", timeout=120) as c,
    ):
        pose = c.relocalize(gray, "room", spec, encoding="jpeg")
    assert pose.status == "RELOCALIZED", pose
    gt = world.gt_cam_from_world[30].inverse().translation
    assert np.linalg.norm(np.asarray(pose.world_from_cam.t) - gt) < 0.05
