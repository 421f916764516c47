"""Conventions: rigid transforms and quaternions, camera models (projection round trips,
undistortion), pose files, configuration from files and the environment."""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest

from sfmloc.cameras import Camera
from sfmloc.config import StrictModel, load_config, merge_presets
from sfmloc.errors import CameraModelError, ConfigError, ModelFormatError, SfmlocError
from sfmloc.io.poses import detect_pose_format, name_stem, read_poses, write_colmap_list, write_tum
from sfmloc.transforms import (
    Rigid3d,
    align_umeyama,
    pose_errors,
    quat_wxyz_from_rotmat,
    quat_xyzw_from_rotmat,
    rotation_angle_deg,
    rotmat_from_quat_wxyz,
    rotmat_from_quat_xyzw,
    rotmat_from_rotvec,
    rotvec_from_rotmat,
)

rng = np.random.default_rng(0)


def random_rotation():
    q = rng.standard_normal(4)
    return rotmat_from_quat_wxyz(q / np.linalg.norm(q))


# ----------------------------------------------------------------------------- transforms
def test_quaternion_round_trips_and_orders():
    for _ in range(200):
        R = random_rotation()
        qw = quat_wxyz_from_rotmat(R)
        qx = quat_xyzw_from_rotmat(R)
        assert qw[0] >= 0 and np.isclose(np.linalg.norm(qw), 1)
        assert np.allclose(qx, [qw[1], qw[2], qw[3], qw[0]])
        assert np.allclose(rotmat_from_quat_wxyz(qw), R, atol=1e-12)
        assert np.allclose(rotmat_from_quat_xyzw(qx), R, atol=1e-12)
        assert np.allclose(rotmat_from_rotvec(rotvec_from_rotmat(R)), R, atol=1e-10)
    # a known rotation: 90 degrees about z
    Rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    assert np.allclose(quat_wxyz_from_rotmat(Rz), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)])
    assert np.isclose(rotation_angle_deg(Rz, np.eye(3)), 90.0)
    # near-180-degree rotations (Shepperd's branches)
    for axis in np.eye(3):
        R = rotmat_from_rotvec(axis * (np.pi - 1e-9))
        assert np.allclose(rotmat_from_quat_wxyz(quat_wxyz_from_rotmat(R)), R, atol=1e-8)


def test_rigid3d_compose_inverse_apply_center():
    a_from_b = Rigid3d(random_rotation(), rng.standard_normal(3))
    b_from_c = Rigid3d(random_rotation(), rng.standard_normal(3))
    x_c = rng.standard_normal((10, 3))
    a_from_c = a_from_b * b_from_c
    assert np.allclose(a_from_c.apply(x_c), a_from_b.apply(b_from_c.apply(x_c)))
    ident = a_from_b * a_from_b.inverse()
    assert np.allclose(ident.rotation, np.eye(3)) and np.allclose(ident.translation, 0)
    cam_from_world = a_from_b
    assert np.allclose(cam_from_world.apply(cam_from_world.center), 0, atol=1e-12)
    assert np.allclose(cam_from_world.inverse().translation, cam_from_world.center)
    T = Rigid3d.from_matrix(cam_from_world.matrix4())
    assert np.allclose(T.rotation, cam_from_world.rotation) and np.allclose(
        T.translation, cam_from_world.translation
    )
    with pytest.raises(ValueError):
        Rigid3d.from_matrix(np.eye(2))


def test_rigid3d_takes_and_checks_its_arrays_as_numpy_converts_them():
    """``Rigid3d``'s construction keeps float64 arrays of the right shape as they are and
    converts anything else as ``np.asarray(x, float64).reshape`` did (issue 10: the fast path
    skips that for the engine's own arrays): the same values, dtype, shape and memory (a view
    of the caller's array either way), and the same errors, message for message, for a wrong
    size or type; ``is_finite`` (on Python floats) answers as np.isfinite for a NaN, +inf or
    -inf in each of the twelve numbers."""

    def reference(x, shape):
        return np.asarray(x, dtype=np.float64).reshape(shape)

    R, t = random_rotation(), rng.standard_normal(3)
    goods = [
        (R, t),
        (R.tolist(), t.tolist()),
        (R.astype(np.float32), t.astype(np.float32)),
        (R.reshape(9), t.reshape(3, 1)),
        (np.asfortranarray(R), t[::-1].copy()[::-1]),  # non-contiguous / strided: viewed
        (R.astype(">f8"), np.array([1, 2, 3])),  # big-endian, integers: converted
    ]
    for Rin, tin in goods:
        p = Rigid3d(Rin, tin)
        for got, x, shape in ((p.rotation, Rin, (3, 3)), (p.translation, tin, (3,))):
            want = reference(x, shape)
            assert type(got) is np.ndarray and got.dtype == np.float64 and got.shape == shape
            assert got.tobytes() == want.tobytes() and got.strides == want.strides
            if isinstance(x, np.ndarray) and x.dtype == np.float64 and type(x) is np.ndarray:
                assert np.shares_memory(got, x)  # a view of the caller's array, as before
    bads = [np.eye(2), np.zeros(10), "abc", None, [[1, 2], [3]], np.zeros(3, "U1")]
    for bad in bads:
        with pytest.raises(Exception) as want_err:
            reference(bad, (3, 3))
        with pytest.raises(type(want_err.value)) as got_err:
            Rigid3d(bad, t)
        assert str(got_err.value) == str(want_err.value)
        with pytest.raises(Exception) as want_err:
            reference(bad, (3,))
        with pytest.raises(type(want_err.value)) as got_err:
            Rigid3d(R, bad)
        assert str(got_err.value) == str(want_err.value)
    p = Rigid3d(R, t)
    assert p.is_finite() is True
    for i in range(12):
        for bad in (np.nan, np.inf, -np.inf):
            Rb, tb = R.copy(), t.copy()
            if i < 9:
                Rb.reshape(9)[i] = bad
            else:
                tb[i - 9] = bad
            assert Rigid3d(Rb, tb).is_finite() is False
    assert Rigid3d(np.full((3, 3), 1e308), np.full(3, -1e308)).is_finite() is True


def test_pose_errors():
    gt = Rigid3d(random_rotation(), [1.0, 2.0, 3.0])
    R_off = rotmat_from_rotvec([0, 0, np.radians(2.0)])
    # rotate the camera by 2 degrees about its centre and move the centre 10 cm
    world_from_cam = gt.inverse()
    est_world_from_cam = Rigid3d(
        world_from_cam.rotation @ R_off, world_from_cam.translation + [0.1, 0, 0]
    )
    dp, dr = pose_errors(est_world_from_cam.inverse(), gt)
    assert np.isclose(dp, 0.1) and np.isclose(dr, 2.0)


# ----------------------------------------------------------------------------- cameras
CAMERAS = [
    Camera("SIMPLE_PINHOLE", 640, 480, [500, 320, 240]),
    Camera("PINHOLE", 640, 480, [500, 510, 321, 239]),
    Camera("SIMPLE_RADIAL", 640, 480, [500, 320, 240, -0.08]),
    Camera("RADIAL", 640, 480, [500, 320, 240, -0.1, 0.02]),
    Camera("OPENCV", 640, 480, [500, 505, 320, 240, -0.12, 0.03, 0.001, -0.002]),
    Camera(
        "FULL_OPENCV",
        640,
        480,
        [500, 505, 320, 240, -0.1, 0.02, 0.001, -0.001, 0.001, 0.01, 0.0, 0.0],
    ),
]


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.model)
def test_projection_round_trip(cam):
    pts2d = rng.uniform([5, 5], [635, 475], (500, 2))
    uv = cam.cam_from_img(pts2d)
    back = cam.img_from_normalized(uv)
    assert np.abs(back - pts2d).max() < 1e-6
    # 3D: points at random depths project back where they came from
    X = np.hstack([uv, np.ones((len(uv), 1))]) * rng.uniform(0.5, 10, (len(uv), 1))
    assert np.abs(cam.img_from_cam(X) - pts2d).max() < 1e-6


def test_distortion_matches_opencv():
    import cv2

    cam = CAMERAS[4]
    X = np.hstack([rng.uniform(-0.5, 0.5, (100, 2)), np.ones((100, 1))]) * 3
    ours = cam.img_from_cam(X)
    cv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    assert np.abs(ours - cv.reshape(-1, 2)).max() < 1e-9


def test_camera_project_world_points_and_depth():
    cam = CAMERAS[1]
    cam_from_world = Rigid3d(random_rotation(), [0.2, -0.1, 3.0])
    X_cam = np.array([[0.1, 0.2, 2.0], [0.0, 0.0, -1.0]])
    X_world = cam_from_world.inverse().apply(X_cam)
    uv, z = cam.project(cam_from_world, X_world)
    assert np.allclose(z, [2.0, -1.0])
    assert np.allclose(uv[0], [500 * 0.05 + 321, 510 * 0.1 + 239])


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.model)
def test_camera_project_is_the_transform_then_the_image_mapping_bit_for_bit(cam):
    """``Camera.project`` writes the transform out (R^T contiguous) and, for a pinhole
    model, applies K in place: the bits of ``Rigid3d.apply`` followed by the division and
    ``img_from_normalized`` (what the tracker's predicted positions were), every model, one
    point and many, points behind and on the camera plane too."""
    for n in (1, 2, 5, 100, 1000):
        T = Rigid3d(random_rotation(), rng.normal(0, 1, 3))
        X = rng.normal(0, 3, (n, 3))
        X[: n // 3] = T.inverse().apply(np.c_[rng.normal(0, 1, (n // 3, 2)), np.zeros(n // 3)])
        pc = T.apply(X)
        z = pc[:, 2]
        want = cam.img_from_normalized(pc[:, :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)[:, None])
        uv, depth = cam.project(T, X)
        assert uv.tobytes() == want.tobytes() and depth.tobytes() == z.tobytes()


def test_camera_parse_forms_and_errors(tmp_path):
    c = Camera.parse("PINHOLE 640 480 525.505 525.505 320 240")
    assert c.model == "PINHOLE" and c.size == (640, 480) and np.allclose(c.K[0], [525.505, 0, 320])
    c.to_json(tmp_path / "camera.json")
    assert Camera.parse(tmp_path / "camera.json") == c
    assert Camera.parse(c.to_string()) == c
    scaled = c.scaled(0.5)
    assert scaled.size == (320, 240) and np.allclose(scaled.params, [262.7525, 262.7525, 160, 120])
    with pytest.raises(CameraModelError, match="unsupported camera model"):
        Camera.parse("FISHEYE_X 640 480 1 2 3")
    with pytest.raises(CameraModelError, match="takes 4 parameters"):
        Camera.parse("PINHOLE 640 480 525 320 240")
    with pytest.raises(CameraModelError):
        Camera.parse("PINHOLE 0 480 525 525 320 240")
    with pytest.raises(CameraModelError, match="cannot read camera file"):
        Camera.parse(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(CameraModelError, match="needs 'model'"):
        Camera.parse(tmp_path / "bad.json")
    assert issubclass(CameraModelError, SfmlocError)


@pytest.mark.parametrize(
    "spec",
    [
        "PINHOLE 640 480 525 525 320 240",
        "simple_radial 64 48 50 32 24 0.01",
        "FISHEYE 64 48 1 2 3",
        "PINHOLE 64 48 1 1 1",
        "PINHOLE 0 48 1 1 1 1",
        "PINHOLE 99999 48 1 1 1 1",
        "PINHOLE 64 48 -5 5 32 24",
        "RADIAL 64 48 50 32 24 nan 0",
    ],
)
def test_client_and_service_cameras_share_one_rule(spec):
    """One table and one validation (sfmloc_client.cameras): the client's CameraSpec and the
    service's Camera accept the same cameras and refuse the others with the same message."""
    from sfmloc_client import CameraSpec

    try:
        spec_client = CameraSpec.parse(spec)
    except CameraModelError as exc:
        with pytest.raises(CameraModelError) as e:
            Camera.parse(spec)
        assert str(e.value) == str(exc)
        return
    cam = Camera.parse(spec)
    assert (cam.model, cam.width, cam.height, tuple(cam.params)) == (
        spec_client.model,
        spec_client.width,
        spec_client.height,
        spec_client.params,
    )
    assert cam.to_string() == spec_client.to_string()
    assert Camera.parse(spec_client.to_string()) == cam


def test_umeyama_recovers_a_similarity_exactly():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(20, 3))
    R = Rigid3d.from_rotvec([0.3, -1.2, 0.5], [0, 0, 0]).rotation
    t = np.array([1.0, -2.0, 0.5])
    s, R_est, t_est = align_umeyama(src, 2.5 * src @ R.T + t)
    assert np.isclose(s, 2.5) and np.allclose(R_est, R) and np.allclose(t_est, t)
    s, R_est, t_est = align_umeyama(src, src @ R.T + t, with_scale=False)
    assert s == 1.0 and np.allclose(R_est, R) and np.allclose(t_est, t)


# ----------------------------------------------------------------------------- pose files
def test_tum_and_colmap_pose_files_round_trip(tmp_path):
    poses = [Rigid3d(random_rotation(), rng.standard_normal(3)) for _ in range(5)]
    write_tum(tmp_path / "t.tum", [i / 30 for i in range(5)], [p.inverse() for p in poses])
    write_colmap_list(tmp_path / "c.txt", [f"seq/f{i}.png" for i in range(5)], poses)
    assert detect_pose_format(tmp_path / "t.tum") == "tum"
    assert detect_pose_format(tmp_path / "c.txt") == "colmap"
    t = read_poses(tmp_path / "t.tum")
    c = read_poses(tmp_path / "c.txt")
    for p, et, ec in zip(poses, t.entries, c.entries):
        assert np.allclose(et.cam_from_world.rotation, p.rotation, atol=1e-8)
        assert np.allclose(et.cam_from_world.translation, p.translation, atol=1e-8)
        assert np.allclose(ec.cam_from_world.matrix(), p.matrix(), atol=1e-8)
    assert t.entries[2].timestamp == pytest.approx(2 / 30, abs=1e-6)  # TUM files keep microseconds
    assert set(c.by_stem()) == {f"f{i}" for i in range(5)}
    assert name_stem("seq-01/frame-000001.color.png") == "frame-000001.color"
    (tmp_path / "bad.txt").write_text("a b c\n")
    with pytest.raises(ModelFormatError):
        read_poses(tmp_path / "bad.txt")
    (tmp_path / "bad2.txt").write_text("img.png 1 0 0 0 x 0 0\n")
    with pytest.raises(ModelFormatError, match="bad2.txt:1"):
        read_poses(tmp_path / "bad2.txt")


def test_redkitchen_pose_list_reads(redkitchen):
    p = read_poses(redkitchen / "pgt_sfm_seq01.txt")
    assert len(p) == 1000 and p.format == "colmap"
    # the file's first line, converted: its quaternion is wxyz and normalized
    q = p.entries[0].cam_from_world.quat_wxyz
    assert np.allclose(q, [0.981975, 0.0120587, 0.128058, 0.138496], atol=1e-5)


# ----------------------------------------------------------------------------- config
class Inner(StrictModel):
    k: int = 50
    sigma: float = 2.0


class Outer(StrictModel):
    name: str = "x"
    inner: Inner = Inner()
    items: list[int] = [1]


def test_config_precedence_file_env_overrides(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"name": "file", "inner": {"k": 10}}))
    env = {"SFMLOC_INNER__SIGMA": "3.5", "SFMLOC_NAME": "env", "SFMLOC_ITEMS": "[4, 5]"}
    c = load_config(Outer, f, environ=env)
    assert c.name == "env" and c.inner.k == 10 and c.inner.sigma == 3.5 and c.items == [4, 5]
    c = load_config(Outer, f, environ=env, overrides={"name": "flag", "items": None})
    assert c.name == "flag" and c.items == [4, 5]
    assert load_config(Outer, environ={}).inner.k == 50


def test_config_errors_name_the_problem(tmp_path):
    with pytest.raises(ConfigError, match="SFMLOC_"):
        load_config(Outer, environ={"SFMLOC_INNER__K": "lots"})
    (tmp_path / "c.json").write_text(json.dumps({"typo": 1}))
    with pytest.raises(ConfigError, match="typo"):
        load_config(Outer, tmp_path / "c.json", environ={})
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(ConfigError, match="cannot parse config file"):
        load_config(Outer, tmp_path / "broken.json", environ={})


def test_merge_presets():
    c = merge_presets(Outer(), inner={"k": 7})
    assert c.inner.k == 7 and c.inner.sigma == 2.0 and c.name == "x"


def test_library_logging_has_null_handler():
    import logging

    import sfmloc
    import sfmloc_client

    assert any(isinstance(h, logging.NullHandler) for h in logging.getLogger("sfmloc").handlers)
    assert any(
        isinstance(h, logging.NullHandler) for h in logging.getLogger("sfmloc_client").handlers
    )
    assert sfmloc.__version__ == sfmloc_client.__version__


def test_one_thread_pinning_helper(monkeypatch):
    """Commands, workers and build jobs pin the same variables; a user's value wins unless a
    measurement forces one thread."""
    import os

    from sfmloc.threads import THREAD_VARS, pin_threads_env, single_thread_env

    monkeypatch.setenv("OMP_NUM_THREADS", "4")
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    pin_threads_env()
    assert os.environ["OMP_NUM_THREADS"] == "4" and os.environ["MKL_NUM_THREADS"] == "1"
    pin_threads_env(force=True)
    assert all(os.environ[v] == "1" for v in THREAD_VARS)
    env = single_thread_env({"PATH": "/bin", "OPENBLAS_NUM_THREADS": "8"})
    assert env["PATH"] == "/bin" and all(env[v] == "1" for v in THREAD_VARS)


_FAULTS_SCRIPT = """
import resource, sys
import numpy as np
from sfmloc.threads import pin_allocator
if sys.argv[1] == "pinned":
    assert pin_allocator()
faults = []
for _ in range(6):
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(1 << 18)  # 2, 6 and 6 MB: a frame's temporaries, freed
    b = np.ones(3 << 18)
    c = np.ones(3 << 18)
    del a, b, c
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
print(sum(faults[2:]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt (Linux)")
def test_allocator_keeps_a_frames_temporaries(tmp_path):
    """Issue 10: with ``pin_allocator`` (called by ``pin_threads_runtime``) blocks of a few MB
    allocated and freed again and again reuse the heap; without it glibc maps a block as
    large as the largest freed so far afresh (its adaptive threshold) and every round faults
    its pages in (counted, not timed: 4 rounds after 2 of warm-up, each way in a fresh
    process, numpy's huge-page advice off so that pages are 4 KB)."""
    import subprocess

    from sfmloc.threads import pin_allocator

    if not pin_allocator():
        pytest.skip("this C library has no mallopt")
    env = {**os.environ, "NUMPY_MADVISE_HUGEPAGE": "0"}
    out = {}
    for mode in ("pinned", "default"):
        run = subprocess.run(
            [sys.executable, "-c", _FAULTS_SCRIPT, mode],
            capture_output=True,
            text=True,
            env=env,
            check=True,
            timeout=120,
        )
        out[mode] = int(run.stdout.strip())
    # the two 6 MB blocks are 3,072 pages a round: 12,288 in the 4 rounds when mapped afresh
    assert out["pinned"] < 500 < 10000 < out["default"], out


def test_pose_types_convert_both_ways():
    """The engine's Rigid3d (quat_wxyz inside) and the client's Transform (quat_xyzw) carry the
    same transform through the explicit converters."""
    from sfmloc.transforms import Rigid3d, rotmat_from_rotvec
    from sfmloc_client import Transform

    r = Rigid3d(rotmat_from_rotvec([0.4, -2.9, 1.0]), np.array([1.5, -2.0, 30.0]))
    t = Transform.from_matrix(r.matrix4())
    assert t.quat_xyzw[3] >= 0 and abs(np.linalg.norm(t.quat_xyzw) - 1) < 1e-12
    np.testing.assert_allclose(t.quat_xyzw, r.quat_xyzw, atol=1e-12)
    np.testing.assert_allclose(t.t, r.translation, atol=1e-12)
    back = Rigid3d.from_transform(t)
    np.testing.assert_allclose(back.rotation, r.rotation, atol=1e-12)
    np.testing.assert_allclose(t.inverse().t, r.inverse().translation, atol=1e-9)
    np.testing.assert_allclose(Transform.from_matrix(r.matrix()).matrix(), r.matrix4(), atol=1e-12)
