"""The SfM front-end (sfmloc.builder.sfm) against exact ground truth and real frames.

A tiny synthetic scene, rendered here by ray casting: the inside corner of a room (floor
z=0, walls x=0 and y=0, random multi-scale texture), seen by 8 cameras on an arc with known
poses. Known-poses triangulation must put the points on those planes and keep the poses
exactly; images-only SfM must recover the poses up to a similarity. The furnished room of
``sfmloc.synth`` (when importable) checks the points against its surfaces. Plus the pycolmap <->
Reconstruction conversion, pose-to-image matching, the real redkitchen frames (skipped when
../shared/data is absent) and every kind of bad input.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from sfmloc.builder import sfm
from sfmloc.builder.sfm.stages import opencv_sift
from sfmloc.cameras import Camera
from sfmloc.errors import BuildCancelled, BuildError, CameraModelError, ImageDecodeError, InputError
from sfmloc.io.colmap import Reconstruction, read_model, write_model
from sfmloc.io.poses import read_poses, write_colmap_list, write_tum
from sfmloc.transforms import Rigid3d, align_umeyama

CAM = Camera.pinhole(320, 240, 250.0, 250.0, 160.0, 120.0)
N_VIEWS = 8


# --------------------------------------------------------------------------- synthetic scene
def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Blurred noise at three scales plus discs and squares: blobs and corners for SIFT."""
    acc = np.zeros((h, w), np.float32)
    for sigma, amp in ((1.5, 0.6), (4.0, 1.0), (10.0, 1.2)):
        b = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
        acc += amp * b / (b.std() + 1e-6)
    img = np.clip(128 + 40 * acc, 0, 255).astype(np.uint8)
    for _ in range(w * h // 1500):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        col = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.circle(img, c, int(rng.integers(3, 12)), col, -1, cv2.LINE_AA)
        else:
            s = rng.integers(4, 16, size=2)
            cv2.rectangle(img, c, (c[0] + int(s[0]), c[1] + int(s[1])), col, -1)
    return img


class Corner:
    """Floor and two walls of a room corner: planes ``origin + a*u + b*v``, ``a, b in [0, 1]``."""

    TEXELS_PER_M = 160

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.planes = []
        for o, u, v in (
            ((0, 0, 0), (3, 0, 0), (0, 3, 0)),  # floor z = 0
            ((0, 0, 2), (0, 3, 0), (0, 0, -2)),  # wall x = 0
            ((0, 0, 2), (3, 0, 0), (0, 0, -2)),  # wall y = 0
        ):
            o, u, v = (np.array(a, np.float64) for a in (o, u, v))
            n = np.cross(u, v)
            w, h = (
                int(np.linalg.norm(u) * self.TEXELS_PER_M),
                int(np.linalg.norm(v) * self.TEXELS_PER_M),
            )
            self.planes.append(
                {"o": o, "u": u, "v": v, "n": n / np.linalg.norm(n), "tex": _texture(rng, h, w)}
            )

    def render(self, cam: Camera, cam_from_world: Rigid3d, ss: int = 2) -> np.ndarray:
        """Ray cast (``ss`` x ``ss`` supersampled) in COLMAP's pixel convention."""
        w, h = cam.width * ss, cam.height * ss
        (fx, fy), (cx, cy) = cam.focal, cam.principal_point
        i, j = np.meshgrid((np.arange(w) + 0.5) / ss, (np.arange(h) + 0.5) / ss)
        rays = (
            np.stack([(i - cx) / fx, (j - cy) / fy, np.ones_like(i)], -1) @ cam_from_world.rotation
        )
        c = cam_from_world.center
        depth = np.full((h, w), np.inf)
        out = np.full((h, w), 128.0, np.float32)
        for p in self.planes:
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (p["n"] @ p["o"] - p["n"] @ c) / (rays @ p["n"])
            rel = c + t[..., None] * rays - p["o"]
            a = rel @ p["u"] / (p["u"] @ p["u"])
            b = rel @ p["v"] / (p["v"] @ p["v"])
            hit = (t > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1) & (t < depth)
            th, tw = p["tex"].shape
            val = cv2.remap(
                p["tex"].astype(np.float32),
                (a * tw - 0.5).astype(np.float32),
                (b * th - 0.5).astype(np.float32),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REFLECT,
            )
            out[hit], depth[hit] = val[hit], t[hit]
        img = cv2.resize(out, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)

    def distance(self, X: np.ndarray) -> np.ndarray:
        """Distance of points (N, 3) to the nearest of the three planes."""
        return np.min(np.stack([np.abs((X - p["o"]) @ p["n"]) for p in self.planes]), axis=0)


def look_at(center: np.ndarray, target, up=(0.0, 0.0, 1.0)) -> Rigid3d:
    """``cam_from_world`` of a camera at ``center`` looking at ``target`` (x right, y down)."""
    z = np.asarray(target, np.float64) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return Rigid3d(R, -R @ center)


def arc_poses(n: int = N_VIEWS) -> list[Rigid3d]:
    poses = []
    for a in np.radians(np.linspace(20, 70, n)):
        c = np.array([3.2 * np.cos(a), 3.2 * np.sin(a), 1.5 + 0.1 * np.sin(3 * a)])
        poses.append(look_at(c, (0.7, 0.7, 0.5)))
    return poses


@pytest.fixture(scope="module")
def corner_scene(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("corner")
    scene = Corner(seed=0)
    images = root / "images"
    images.mkdir()
    poses = arc_poses()
    names = [f"view-{k:03d}.png" for k in range(len(poses))]
    for name, T in zip(names, poses):
        assert cv2.imwrite(str(images / name), scene.render(CAM, T))
    pose_file = write_colmap_list(root / "poses.txt", names, poses)
    return {
        "root": root,
        "scene": scene,
        "images": images,
        "names": names,
        "poses": poses,
        "pose_file": pose_file,
    }


@pytest.fixture(scope="module")
def known_poses_rec(corner_scene) -> Reconstruction:
    return sfm.triangulate_known_poses(corner_scene["images"], corner_scene["pose_file"], CAM)


def _reproj_errors(rec: Reconstruction) -> np.ndarray:
    """Pixel distance between each observation and its point projected by our own Camera."""
    errs = []
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        ok = im.point3D_ids >= 0
        X = np.array([rec.points3D[int(i)].xyz for i in im.point3D_ids[ok]]).reshape(-1, 3)
        uv, z = cam.project(im.cam_from_world, X)
        assert np.all(z > 0)
        errs.append(np.linalg.norm(uv - im.points2D[ok], axis=1))
    return np.concatenate(errs)


# --------------------------------------------------------------------------- known poses
def test_known_poses_points_lie_on_the_true_planes(corner_scene, known_poses_rec):
    rec = known_poses_rec
    rec.check()
    assert len(rec.images) == N_VIEWS
    assert len(rec.points3D) > 500
    X = np.array([p.xyz for p in rec.points3D.values()])
    d = corner_scene["scene"].distance(X)
    # The scene is ~3 m across, seen from ~2.6 m with 10 mm pixels.
    assert np.median(d) < 0.005
    assert np.percentile(d, 90) < 0.02
    assert min(len(p.track_image_ids) for p in rec.points3D.values()) >= 3


def test_known_poses_are_kept_exactly(corner_scene, known_poses_rec):
    given = read_poses(corner_scene["pose_file"]).by_key()  # as written: 9 decimals
    for im in known_poses_rec.images.values():
        T = given[im.name]
        np.testing.assert_allclose(im.cam_from_world.rotation, T.rotation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(im.cam_from_world.translation, T.translation, rtol=0, atol=1e-12)
    cam = next(iter(known_poses_rec.cameras.values()))
    assert cam == CAM


def test_known_poses_observations_reproject_with_our_camera(known_poses_rec):
    """Keypoints, poses and points agree in COLMAP's pixel convention after conversion."""
    errs = _reproj_errors(known_poses_rec)
    assert errs.mean() < 0.5
    assert errs.max() < sfm.SfmConf().max_reproj_error + 1e-6
    mean_stored = np.mean([p.error for p in known_poses_rec.points3D.values()])
    assert abs(mean_stored - errs.mean()) < 0.1


def test_known_poses_progress_and_workdir_cleanup(corner_scene, tmp_path):
    events = []
    work = tmp_path / "work"
    rec = sfm.triangulate_known_poses(
        corner_scene["images"],
        corner_scene["pose_file"],
        CAM,
        sfm.sfm_conf("fast", min_track_length=2, sift_backend="pycolmap"),  # the chunked extractor
        workdir=work,
        progress=lambda st, f, msg: events.append((st, f, msg)),
        image_names=corner_scene["names"][:4],
    )
    assert len(rec.images) == 4
    stages = [e[0] for e in events]
    for st in ("input", "features", "matching", "triangulate"):
        assert st in stages
        fr = [f for s, f, _ in events if s == st]
        assert fr == sorted(fr) and fr[-1] == 1.0
    assert stages.index("features") < stages.index("matching") < stages.index("triangulate")
    assert all(0.0 <= f <= 1.0 for _, f, _ in events)
    assert work.is_dir() and not any(work.iterdir())
    # min_track_length=2 keeps two-view points
    assert min(len(p.track_image_ids) for p in rec.points3D.values()) == 2


def test_cancel_stops_the_build_and_cleans_up(corner_scene, tmp_path):
    work = tmp_path / "work"
    calls = {"n": 0}

    def should_cancel() -> bool:
        calls["n"] += 1
        return calls["n"] > 3

    with pytest.raises(BuildCancelled):
        sfm.triangulate_known_poses(
            corner_scene["images"],
            corner_scene["pose_file"],
            CAM,
            workdir=work,
            should_cancel=should_cancel,
        )
    assert not any(work.iterdir())


def test_cancel_interrupts_a_running_pycolmap_stage(corner_scene, tmp_path):
    """Cancelled while incremental mapping runs (in its worker thread): stops, cleans up."""
    work = tmp_path / "work"
    state = {"mapping": False, "calls": 0}

    def progress(stage: str, fraction: float, message: str) -> None:
        state["mapping"] |= stage == "mapping"

    def should_cancel() -> bool:
        if state["mapping"]:
            state["calls"] += 1
        return state["calls"] >= 2  # the 1st call is the check before the stage starts

    with pytest.raises(BuildCancelled) as err:
        sfm.reconstruct_images_only(
            corner_scene["images"],
            CAM,
            workdir=work,
            progress=progress,
            should_cancel=should_cancel,
        )
    assert err.value.stage == "mapping"
    assert not any(work.iterdir())


def test_keep_workdir_keeps_the_database(corner_scene, tmp_path):
    conf = sfm.sfm_conf("fast", keep_workdir=True, min_track_length=2)
    sfm.triangulate_known_poses(
        corner_scene["images"],
        corner_scene["pose_file"],
        CAM,
        conf,
        workdir=tmp_path,
        image_names=corner_scene["names"][:3],
    )
    kept = list(tmp_path.iterdir())
    assert len(kept) == 1 and (kept[0] / "database.db").is_file()


def test_known_poses_in_the_synthetic_room(tmp_path):
    """sfmloc.synth's furnished room along a walk: triangulated points lie on its surfaces
    (the distance along each point's first viewing ray matches a ray cast in the scene)."""
    synth = pytest.importorskip(
        "sfmloc.synth", reason="sfmloc.synth (the synthetic room) is not available"
    )
    from server_helpers import room_scene

    scene = room_scene(0)
    cam = Camera.pinhole(320, 240, 262.5, 262.5, 160.0, 120.0)
    poses = synth.make_trajectory("walk", 120, seed=0, scene=scene)[::8]
    (tmp_path / "img").mkdir()
    names = [f"f{k:03d}.png" for k in range(len(poses))]
    for name, T in zip(names, poses):
        bgr, _ = synth.render(scene, cam, T)
        cv2.imwrite(str(tmp_path / "img" / name), bgr)
    rec = sfm.triangulate_known_poses(
        tmp_path / "img", write_colmap_list(tmp_path / "p.txt", names, poses), cam
    )
    assert len(rec.images) == len(poses) and len(rec.points3D) > 300
    centers = np.array(
        [rec.images[int(p.track_image_ids[0])].cam_from_world.center for p in rec.points3D.values()]
    )
    X = np.array([p.xyz for p in rec.points3D.values()])
    dist = np.linalg.norm(X - centers, axis=1)
    t_hit, _ = synth.raycast(scene, centers, (X - centers) / dist[:, None])
    rel = np.abs(t_hit - dist) / dist
    assert np.median(rel) < 0.02  # ~0.5% measured: 2.5 cm at 4.5 m with 1.7 cm pixels
    assert np.mean(rel < 0.05) > 0.8


def _blobs(
    rng: np.random.Generator, w: int, h: int, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian blobs at known sub-pixel centres (COLMAP convention), sampled at pixel centres."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    img = np.full((h, w), 60.0)
    centres: list[tuple[float, float]] = []
    while len(centres) < 25:
        c = rng.uniform(20 * scale, [w - 20 * scale, h - 20 * scale])
        if all(np.hypot(*(c - o)) > 25 * scale for o in centres):
            centres.append((float(c[0]), float(c[1])))
            sigma = rng.uniform(2.0, 4.0) * scale
            img += 150 * np.exp(-((u - c[0]) ** 2 + (v - c[1]) ** 2) / (2 * sigma**2))
    return np.clip(img, 0, 255).astype(np.uint8), np.array(centres)


def _mean_offset(found: np.ndarray, centres: np.ndarray, radius: float) -> tuple[int, np.ndarray]:
    d = np.linalg.norm(found[None, :, :] - centres[:, None, :], axis=2)
    j = d.argmin(axis=1)
    ok = d[np.arange(len(centres)), j] < radius
    return int(ok.sum()), (found[j[ok]] - centres[ok]).mean(axis=0)


@pytest.mark.parametrize("backend", ["opencv", "pycolmap"])
def test_sift_keypoints_are_in_colmap_pixel_convention(backend):
    """Blob centres come back unbiased (a 0.25 or 0.5 px convention slip would show)."""
    gray, centres = _blobs(np.random.default_rng(1), 320, 240)
    conf = sfm.SfmConf()
    if backend == "opencv":
        kp, desc = opencv_sift(gray, conf)
        assert desc.dtype == np.uint8 and desc.shape == (len(kp), 128)
        norms = np.linalg.norm(desc.astype(np.float64), axis=1)
        assert np.all(np.abs(norms - 512) < 12)  # RootSIFT at COLMAP's uint8 scale
        xy = kp[:, :2]
    else:
        ex = pycolmap.FeatureExtractor.create(
            pycolmap.FeatureExtractionOptions(), pycolmap.Device.cpu
        )
        xy = pycolmap.keypoints_to_matrix(ex.extract_from_uint8_array(gray)[0])[:, :2]
    n, off = _mean_offset(xy.astype(np.float64), centres, 1.5)
    assert n >= 15
    assert np.all(np.abs(off) < 0.08), off


def test_opencv_sift_downscales_large_images_into_original_coordinates():
    gray, centres = _blobs(np.random.default_rng(2), 640, 480, scale=2.0)
    kp, _ = opencv_sift(gray, sfm.sfm_conf(max_image_size=320))
    n, off = _mean_offset(kp[:, :2].astype(np.float64), centres, 3.0)
    assert n >= 15
    assert np.all(np.abs(off) < 0.16), off


# --------------------------------------------------------------------------- images only
def test_images_only_recovers_poses_up_to_similarity(corner_scene):
    rec = sfm.reconstruct_images_only(corner_scene["images"], CAM)
    rec.check()
    assert len(rec.images) >= N_VIEWS - 1
    given = dict(zip(corner_scene["names"], corner_scene["poses"]))
    names = [im.name for im in rec.images.values()]
    est = np.array([im.cam_from_world.center for im in rec.images.values()])
    gt = np.array([given[n].center for n in names])
    s, R, t = align_umeyama(est, gt)
    assert np.max(np.linalg.norm((s * est @ R.T + t) - gt, axis=1)) < 0.03  # 3 cm on a 1.7 m arc
    for im in rec.images.values():  # rotations agree after the similarity too
        R_gt = given[im.name].rotation
        R_est = im.cam_from_world.rotation @ R.T
        assert np.degrees(np.arccos(np.clip((np.trace(R_est @ R_gt.T) - 1) / 2, -1, 1))) < 0.5
    X = np.array([p.xyz for p in rec.points3D.values()]) @ (s * R).T + t
    assert np.median(corner_scene["scene"].distance(X)) < 0.01
    # intrinsics of a given camera stay fixed
    assert next(iter(rec.cameras.values())) == CAM


def test_pair_generators():
    names = [f"{i}" for i in range(20)]
    seq = sfm.sequential_pairs(names, overlap=3, quadratic=True)
    assert ("0", "1") in seq and ("0", "3") in seq and ("0", "4") in seq and ("0", "5") not in seq
    assert len(set(seq)) == len(seq)
    assert len(sfm.exhaustive_pairs(names)) == 190
    # known poses: views that look away (> max angle) are not paired, even when close
    poses = arc_poses(6)
    away = look_at(poses[0].center + 0.01, poses[0].center * 2)
    pairs = sfm.pairs_from_poses(
        names[:7], poses + [away], neighbors=2, sequential=0, max_angle_deg=45
    )
    assert all("6" not in p for p in pairs)
    assert ("0", "1") in pairs and ("0", "5") not in pairs


# --------------------------------------------------------------------------- conversion
def test_pycolmap_round_trip_preserves_cameras_poses_tracks(known_poses_rec):
    prec = sfm.reconstruction_to_pycolmap(known_poses_rec)
    assert prec.num_reg_images() == len(known_poses_rec.images)
    assert prec.num_points3D() == len(known_poses_rec.points3D)
    back = sfm.reconstruction_from_pycolmap(prec)
    assert back.cameras == known_poses_rec.cameras
    for iid, im in known_poses_rec.images.items():
        b = back.images[iid]
        assert b.name == im.name and b.camera_id == im.camera_id
        np.testing.assert_allclose(
            b.cam_from_world.matrix(), im.cam_from_world.matrix(), rtol=0, atol=1e-12
        )
        np.testing.assert_array_equal(b.points2D, im.points2D)
        np.testing.assert_array_equal(b.point3D_ids, im.point3D_ids)
    for pid, p in known_poses_rec.points3D.items():
        q = back.points3D[pid]
        np.testing.assert_array_equal(q.xyz, p.xyz)
        np.testing.assert_array_equal(q.rgb, p.rgb)
        np.testing.assert_array_equal(q.track_image_ids, p.track_image_ids)
        np.testing.assert_array_equal(q.track_point2D_idxs, p.track_point2D_idxs)


def test_pycolmap_quaternions_are_xyzw_and_converted_through_matrices():
    rng = np.random.default_rng(3)
    for _ in range(20):
        q_xyzw = rng.standard_normal(4)
        q_xyzw /= np.linalg.norm(q_xyzw)  # w of either sign
        t = rng.standard_normal(3)
        T_py = pycolmap.Rigid3d(pycolmap.Rotation3d(q_xyzw), t)
        ours = sfm.rigid3d_from_pycolmap(T_py)
        expected = Rigid3d.from_quat_xyzw(q_xyzw, t)
        np.testing.assert_allclose(ours.rotation, expected.rotation, atol=1e-12)
        np.testing.assert_allclose(ours.translation, t, atol=0)
        back = sfm.rigid3d_to_pycolmap(ours)
        np.testing.assert_allclose(back.matrix(), T_py.matrix(), atol=1e-12)
        # a point maps the same way in both libraries
        x = rng.standard_normal(3)
        np.testing.assert_allclose(ours.apply(x), np.asarray(T_py * x), atol=1e-12)


def test_binary_model_written_by_pycolmap_reads_like_the_converter(known_poses_rec, tmp_path):
    prec = sfm.reconstruction_to_pycolmap(known_poses_rec)
    prec.write_binary(str(tmp_path))
    from_file = read_model(tmp_path)
    converted = sfm.reconstruction_from_pycolmap(pycolmap.Reconstruction(str(tmp_path)))
    assert from_file.cameras == converted.cameras
    for iid, im in from_file.images.items():
        np.testing.assert_allclose(
            im.cam_from_world.matrix(), converted.images[iid].cam_from_world.matrix(), atol=1e-12
        )
        np.testing.assert_array_equal(im.point3D_ids, converted.images[iid].point3D_ids)
    assert from_file.points3D.keys() == converted.points3D.keys()


def test_unsupported_pycolmap_camera_model_is_named():
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(
            model="OPENCV_FISHEYE",
            width=64,
            height=48,
            params=[50, 50, 32, 24, 0, 0, 0, 0],
            camera_id=1,
        )
    )
    with pytest.raises(CameraModelError, match="OPENCV_FISHEYE"):
        sfm.reconstruction_from_pycolmap(rec)


def test_filter_points_unlinks_observations(known_poses_rec):
    rec = sfm.reconstruction_from_pycolmap(sfm.reconstruction_to_pycolmap(known_poses_rec))
    longest = max(len(p.track_image_ids) for p in rec.points3D.values())
    n_before = len(rec.points3D)
    dropped = sfm.filter_points(rec, min_track_length=longest)
    assert dropped > 0 and len(rec.points3D) == n_before - dropped
    rec.check()
    linked = {int(i) for im in rec.images.values() for i in im.point3D_ids if i >= 0}
    assert linked == set(rec.points3D)


# --------------------------------------------------------------------------- poses <-> images
def test_pose_names_match_files_by_stem(tmp_path):
    T = [Rigid3d.from_rotvec([0, 0.1 * k, 0], [k, 0, 0]) for k in range(3)]
    f = write_colmap_list(
        tmp_path / "p.txt", [f"seq-01/frame-{k:06d}.color.png" for k in range(3)], T
    )
    names = ["frame-000000.color.jpg", "frame-000002.color.jpg", "frame-000009.color.jpg"]
    m = sfm.match_poses_to_images(read_poses(f), names)
    assert [n for n, _ in m] == ["frame-000000.color.jpg", "frame-000002.color.jpg"]
    assert m[1][1] is not None and np.allclose(m[1][1].translation, [2, 0, 0])
    # an exact relative name wins over stems
    f2 = write_colmap_list(tmp_path / "p2.txt", ["a/x.png", "b/x.png"], T[:2])
    m2 = sfm.match_poses_to_images(read_poses(f2), ["a/x.png", "b/x.png"])
    assert [n for n, _ in m2] == ["a/x.png", "b/x.png"]


def test_ambiguous_stems_are_an_error(tmp_path):
    T = [Rigid3d.identity()]
    f = write_colmap_list(tmp_path / "p.txt", ["seq/x.png"], T)
    with pytest.raises(InputError, match="ambiguous.*a/x.jpg"):
        sfm.match_poses_to_images(read_poses(f), ["a/x.jpg", "b/x.jpg"], f)
    f2 = write_colmap_list(tmp_path / "p2.txt", ["s1/x.png", "s2/x.png"], T * 2)
    with pytest.raises(InputError, match="both match image"):
        sfm.match_poses_to_images(read_poses(f2), ["x.jpg"], f2)


def test_tum_poses_match_numeric_stems_then_order(tmp_path):
    world_from_cam = [Rigid3d.from_rotvec([0, 0, 0.1 * k], [k, 1, 2]) for k in range(4)]
    stamps = [100.0, 100.033, 100.066, 100.1]
    f = write_tum(tmp_path / "t.txt", stamps, world_from_cam)
    poses = read_poses(f)
    # TUM RGB-D layout: timestamps as file names, nearest within 20 ms
    m = sfm.match_poses_to_images(poses, ["rgb/100.065000.png", "rgb/100.001.png", "rgb/105.0.png"])
    got = dict(m)
    assert set(got) == {"rgb/100.065000.png", "rgb/100.001.png"}
    np.testing.assert_allclose(
        got["rgb/100.065000.png"].inverse().translation, [2, 1, 2], atol=1e-6
    )
    # other names: by order when the counts are equal
    m = sfm.match_poses_to_images(poses, [f"f{k}.png" for k in (3, 1, 0, 2)])
    assert [n for n, _ in m] == ["f0.png", "f1.png", "f2.png", "f3.png"]
    np.testing.assert_allclose(m[3][1].center, [3, 1, 2], atol=1e-6)
    with pytest.raises(InputError, match="not timestamps"):
        sfm.match_poses_to_images(poses, ["a.png", "b.png"], f)


def test_known_poses_from_a_tum_trajectory(corner_scene, tmp_path):
    """TUM RGB-D layout end to end: timestamp file names, world_from_cam poses."""
    img = tmp_path / "rgb"
    img.mkdir()
    stamps = [1305031102.175304 + 0.1 * k for k in range(4)]
    for k, ts in enumerate(stamps):
        shutil.copy(corner_scene["images"] / corner_scene["names"][k], img / f"{ts:.6f}.png")
    world_from_cam = [T.inverse() for T in corner_scene["poses"][:4]]
    f = write_tum(tmp_path / "groundtruth.txt", [ts + 0.004 for ts in stamps], world_from_cam)
    rec = sfm.triangulate_known_poses(img, f, CAM, sfm.sfm_conf("fast", min_track_length=2))
    assert len(rec.images) == 4 and len(rec.points3D) > 100
    for im in rec.images.values():
        k = [f"{ts:.6f}.png" for ts in stamps].index(im.name)
        np.testing.assert_allclose(
            im.cam_from_world.center, corner_scene["poses"][k].center, atol=1e-6
        )
    d = corner_scene["scene"].distance(np.array([p.xyz for p in rec.points3D.values()]))
    assert np.median(d) < 0.01


# --------------------------------------------------------------------------- bad input
def _copy_images(corner_scene, dst: Path, k: int = 3) -> list[str]:
    dst.mkdir(parents=True, exist_ok=True)
    names = corner_scene["names"][:k]
    for n in names:
        shutil.copy(corner_scene["images"] / n, dst / n)
    return names


def test_poses_matching_no_image_is_named(corner_scene, tmp_path):
    f = write_colmap_list(
        tmp_path / "other.txt", ["elsewhere/a.png", "elsewhere/b.png"], corner_scene["poses"][:2]
    )
    with pytest.raises(InputError, match=r"no pose in .*other\.txt matches"):
        sfm.triangulate_known_poses(corner_scene["images"], f, CAM)


def test_unsupported_camera_model(corner_scene):
    with pytest.raises(CameraModelError, match="FOV"):
        sfm.triangulate_known_poses(
            corner_scene["images"], corner_scene["pose_file"], "FOV 320 240 250 160 120 0.1"
        )


def test_image_of_another_size_is_named(corner_scene, tmp_path):
    names = _copy_images(corner_scene, tmp_path / "img")
    cv2.imwrite(str(tmp_path / "img" / names[1]), np.zeros((100, 120), np.uint8))
    with pytest.raises(ImageDecodeError, match=f"{names[1]} is 120x100 but the camera is 320x240"):
        sfm.triangulate_known_poses(tmp_path / "img", corner_scene["pose_file"], CAM)
    with pytest.raises(ImageDecodeError, match=names[1]):
        sfm.reconstruct_images_only(tmp_path / "img")


def test_unreadable_image_is_named(corner_scene, tmp_path):
    names = _copy_images(corner_scene, tmp_path / "img")
    (tmp_path / "img" / names[2]).write_bytes(b"not a png at all")
    with pytest.raises(ImageDecodeError, match=f"cannot decode image .*{names[2]}"):
        sfm.triangulate_known_poses(tmp_path / "img", corner_scene["pose_file"], CAM)


def test_missing_folders_and_files(corner_scene, tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        sfm.triangulate_known_poses(tmp_path / "nope", corner_scene["pose_file"], CAM)
    with pytest.raises(InputError, match="pose file .* does not exist"):
        sfm.triangulate_known_poses(corner_scene["images"], tmp_path / "nope.txt", CAM)
    with pytest.raises(InputError, match="does not exist"):
        sfm.reconstruct_images_only(tmp_path / "nope")


def test_image_names_with_whitespace_are_refused(corner_scene, tmp_path):
    names = _copy_images(corner_scene, tmp_path / "img", k=2)
    (tmp_path / "img" / names[1]).rename(tmp_path / "img" / "view 001.png")
    # (a COLMAP list cannot even hold such a name; TUM poses match by order here)
    f = write_tum(tmp_path / "p.txt", [0.0, 1.0], [T.inverse() for T in corner_scene["poses"][:2]])
    with pytest.raises(InputError, match="whitespace.*'view 001.png'"):
        sfm.triangulate_known_poses(tmp_path / "img", f, CAM)
    with pytest.raises(InputError, match="whitespace"):
        sfm.reconstruct_images_only(tmp_path / "img", CAM)


def test_zero_triangulated_points_is_a_triangulate_error(corner_scene, tmp_path):
    """All images given the same pose: no baseline, nothing can be triangulated."""
    names = corner_scene["names"][:3]
    f = write_colmap_list(tmp_path / "same.txt", names, [corner_scene["poses"][0]] * 3)
    work = tmp_path / "work"
    with pytest.raises(BuildError) as err:
        sfm.triangulate_known_poses(
            corner_scene["images"], f, CAM, sfm.sfm_conf("fast"), workdir=work
        )
    assert err.value.stage == "triangulate"
    assert "same.txt" in str(err.value)
    assert not any(work.iterdir())  # cleaned up on failure too


def _model_for(corner_scene, rec: Reconstruction, tmp_path: Path) -> Path:
    return write_model(rec, tmp_path / "model", ".bin")


def test_colmap_input_is_checked_against_images(corner_scene, known_poses_rec, tmp_path):
    model = _model_for(corner_scene, known_poses_rec, tmp_path)
    rec = sfm.load_colmap_input(model, corner_scene["images"])
    assert len(rec.points3D) == len(known_poses_rec.points3D)
    # some images missing: count and names
    partial = tmp_path / "partial"
    _copy_images(corner_scene, partial, k=5)
    with pytest.raises(InputError, match=r"3 of the 8 images .* missing .*view-005\.png"):
        sfm.load_colmap_input(model, partial)
    # a folder of other images: the model and folder do not match
    other = tmp_path / "other"
    other.mkdir()
    cv2.imwrite(str(other / "unrelated.png"), np.zeros((240, 320), np.uint8))
    with pytest.raises(InputError, match="do not match.*unrelated.png"):
        sfm.load_colmap_input(model, other)


def test_colmap_input_bad_images_and_empty_model(corner_scene, known_poses_rec, tmp_path):
    model = _model_for(corner_scene, known_poses_rec, tmp_path)
    img = tmp_path / "img"
    shutil.copytree(corner_scene["images"], img)
    cv2.imwrite(str(img / "view-004.png"), np.zeros((240, 300), np.uint8))
    with pytest.raises(ImageDecodeError, match=r"view-004\.png is 300x240 but its camera"):
        sfm.load_colmap_input(model, img)
    (img / "view-004.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(ImageDecodeError, match=r"view-004\.png"):
        sfm.load_colmap_input(model, img)
    empty = Reconstruction(
        known_poses_rec.cameras,
        {
            iid: type(im)(im.image_id, im.name, im.camera_id, im.cam_from_world)
            for iid, im in known_poses_rec.images.items()
        },
    )
    with pytest.raises(InputError, match="no 3D points"):
        sfm.load_colmap_input(write_model(empty, tmp_path / "empty"), corner_scene["images"])


def test_colmap_input_unsupported_camera_model(corner_scene, known_poses_rec, tmp_path):
    model = write_model(known_poses_rec, tmp_path / "txt", ".txt")
    text = (model / "cameras.txt").read_text().replace("PINHOLE", "OPENCV_FISHEYE")
    (model / "cameras.txt").write_text(text)
    with pytest.raises(CameraModelError, match="OPENCV_FISHEYE"):
        sfm.load_colmap_input(model, corner_scene["images"])


# --------------------------------------------------------------------------- real frames
@pytest.mark.realdata
def test_known_poses_on_redkitchen_frames(redkitchen):
    """20 real frames (every 10th), read in place from ../shared/data (skipped when absent)."""
    names = [f"frame-{i:06d}.color.jpg" for i in range(0, 200, 10)]
    cam = "PINHOLE 640 480 525.505 525.505 320 240"
    rec = sfm.triangulate_known_poses(
        redkitchen, redkitchen / "pgt_sfm_seq01.txt", cam, image_names=names
    )
    rec.check()
    st = sfm.reconstruction_stats(rec)
    assert st["images"] == 20
    assert st["points3D"] > 500
    assert st["mean_track_length"] >= 3.0
    assert st["mean_reproj_error_px"] < 1.5
    assert np.median(_reproj_errors(rec)) < 1.5
    gt_by_key = read_poses(
        redkitchen / "pgt_sfm_seq01.txt"
    ).by_key()  # seq-01/frame-000000.color.png
    gt = {k.rsplit("/", 1)[-1].replace(".png", ".jpg"): T for k, T in gt_by_key.items()}
    for im in rec.images.values():
        np.testing.assert_allclose(im.cam_from_world.matrix(), gt[im.name].matrix(), atol=1e-12)
    # points are in front of the cameras that see them, at indoor distances (metres)
    depths = []
    for im in rec.images.values():
        ok = im.point3D_ids >= 0
        X = np.array([rec.points3D[int(i)].xyz for i in im.point3D_ids[ok]])
        depths.append(im.cam_from_world.apply(X)[:, 2])
    d = np.concatenate(depths)
    assert np.all(d > 0) and 0.3 < np.median(d) < 5.0


def test_token_cancelled_reads_the_installed_pycolmap_token():
    """pycolmap 4.2 made ``is_cancelled`` a property; calling it raised TypeError and turned
    every failure of an SfM stage (and Ctrl-C) into that TypeError."""
    from sfmloc.builder.sfm.run import token_cancelled

    token = pycolmap.CancellationToken()
    assert token_cancelled(token) is False
    token.cancel()
    assert token_cancelled(token) is True


@pytest.mark.parametrize("polling", [False, True])
def test_a_failing_pycolmap_stage_names_its_error(tmp_path, polling):
    """A real pycolmap call that fails (no such database folder) comes back as a BuildError
    naming the stage and pycolmap's own reason, with or without a cancel poller."""
    from sfmloc.builder.sfm.run import Reporter

    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "a.png"), np.zeros((32, 32), np.uint8))
    rep = Reporter(None, (lambda: False) if polling else None)
    with pytest.raises(BuildError) as err:
        rep.run(
            "features",
            pycolmap.extract_features,
            str(tmp_path / "no" / "such" / "db.db"),
            str(images),
        )
    assert err.value.stage == "features"
    assert "extract_features" in str(err.value)
