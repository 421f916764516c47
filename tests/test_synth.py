"""The synthetic test bed must be exact: renderer, visibility, model, trajectories, CLI layout.

Checks use independent means where possible: corner positions are measured in the rendered
pixels (edge-line fits), occlusion by a ray caster written here, depth by ray-plane algebra.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from sfmloc.cameras import Camera
from sfmloc.errors import CameraModelError
from sfmloc.io.colmap import read_model
from sfmloc.io.poses import read_poses
from sfmloc.synth import (
    Scene,
    build_reconstruction,
    check_trajectory,
    look_at,
    make_trajectory,
    mapping_views,
    render,
    render_full,
    render_geometry,
    visible_points,
)
from sfmloc.synth.config import SceneConf, VisibilityConf
from sfmloc.synth.model import feature_index_of_points
from sfmloc.synth.scene import room_layout
from sfmloc.transforms import Rigid3d

N_MAP = 20


@pytest.fixture(scope="module")
def scene() -> Scene:
    """The world's room, shared (server_helpers.room_scene); the determinism test below builds
    its own again to compare."""
    from server_helpers import room_scene

    return room_scene(0)


def test_run_refuses_a_scene_of_another_seed_or_conf(scene, tmp_path):
    """``run(scene=...)`` takes a prebuilt room only for the seed and scene it was built for."""
    from sfmloc.synth import preset
    from sfmloc.synth.main import run

    for conf in (preset("small", seed=1), preset("small", scene={"n_boxes": 3})):
        with pytest.raises(ValueError, match="given for seed"):
            run(conf, tmp_path / "out", scene=scene)
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def camera() -> Camera:
    return Camera.pinhole(640, 480, 525.0, 525.0, 320.0, 240.0)


@pytest.fixture(scope="module")
def mapping(scene, camera):
    """Mapping views rendered as ``sfmloc synth`` does (default noise), and their model."""
    poses = mapping_views(scene, N_MAP, seed=0)
    renders = [render_full(scene, camera, T, noise_seed=(0, 1, i)) for i, T in enumerate(poses)]
    names = [f"map-{i:04d}.png" for i in range(N_MAP)]
    rec = build_reconstruction(scene, camera, poses, names, face_ids=[r.face_id for r in renders])
    return poses, renders, rec


# --------------------------------------------------------------------------- helpers
def _sample(gray: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples at COLMAP image coordinates (pixel centres at +0.5)."""
    pts = np.atleast_2d(pts)
    return map_coordinates(gray, [pts[:, 1] - 0.5, pts[:, 0] - 0.5], order=1, mode="nearest")


def fit_corner(gray, camera, T, X, u, v, r, min_step=30.0):
    """Where the junction at world point X lies in the image, measured from the pixels.

    The model gives the edge directions (the image lines of the texture axes u, v through X)
    and where the four uniform quadrants are (r/2 inside each); the pixels give, along
    profiles across each edge 3 px and more from the corner (blur rounds the tip), the 50 %
    crossings between its two quadrants' intensities. Each edge line is placed at the mean
    perpendicular offset of its crossings and the corner is where the two lines meet.
    Symmetric blur of any width keeps 50 % crossings on the edge, so this is unbiased for L,
    T and X corners, and the measured position owes nothing to the model's position of X.
    """
    q = {}
    g = np.array([0.25, 0.45, 0.65, 0.85])
    for a in (1, -1):
        for b in (1, -1):
            P = np.array([X + r * (a * x * u + b * y * v) for x in g for y in g])
            q[a, b] = _sample(gray, camera.project(T, P)[0]).mean()
    xy0 = camera.project(T, X[None])[0][0]
    normals, offsets = [], []
    for axis, other in ((u, v), (v, u)):
        crossings = []
        oth = camera.project(T, np.stack([X + 0.5 * r * other, X - 0.5 * r * other]))[0]
        tips = camera.project(T, np.stack([X + r * axis, X - r * axis]))[0]
        d = tips[0] - tips[1]
        d /= np.linalg.norm(d)
        n = np.array([-d[1], d[0]])
        for sgn, tip in zip((1, -1), tips):
            length = np.linalg.norm(tip - xy0)
            e = (tip - xy0) / length
            qa, qb = (q[sgn, 1], q[sgn, -1]) if axis is u else (q[1, sgn], q[-1, sgn])
            if abs(qa - qb) < min_step:
                continue
            level = (qa + qb) / 2
            s_min = min(
                abs(e[0] * (o - xy0)[1] - e[1] * (o - xy0)[0]) / np.linalg.norm(o - xy0)
                for o in oth
            )
            for a in np.arange(3.0, 0.8 * length, 0.5):
                h = min(3.0, a * s_min - 1.0, 0.8 * length - a)  # stay clear of the other edge
                if h < 1.0:
                    continue
                offs = np.arange(-h, h + 1e-9, 0.05)
                prof = _sample(gray, xy0 + a * e + offs[:, None] * n) - level
                k = np.flatnonzero(np.sign(prof[:-1]) * np.sign(prof[1:]) < 0)
                if len(k) != 1:
                    continue
                k = k[0]
                t = prof[k] / (prof[k] - prof[k + 1])
                crossings.append(n @ (xy0 + a * e) + offs[k] + t * (offs[k + 1] - offs[k]))
        if len(crossings) < 4:
            return None
        normals.append(n)
        offsets.append(np.mean(crossings))
    A = np.array(normals)
    if abs(np.linalg.det(A)) < 0.3:
        return None
    return np.linalg.solve(A, np.array(offsets))


def measurable(scene, camera, T, face_id, fi, min_reach=8.0):
    """(u, v, r) when feature ``fi``'s clean square is big, unoccluded and not too skewed."""
    F = scene.features
    f = scene.faces[F.face[fi]]
    X, r = F.xyz[fi], F.radius[fi]
    u = f.u_axis / np.linalg.norm(f.u_axis)
    v = f.v_axis / np.linalg.norm(f.v_axis)
    pp, z = camera.project(
        T,
        np.stack(
            [
                X + r * u,
                X - r * u,
                X + r * v,
                X - r * v,
                X + r * (u + v),
                X + r * (u - v),
                X - r * (u + v),
                X - r * (u - v),
            ]
        ),
    )
    xy = camera.project(T, X[None])[0][0]
    if np.any(z <= 0) or np.min(np.linalg.norm(pp[:4] - xy, axis=1)) < min_reach:
        return None
    du, dv = pp[0] - pp[1], pp[2] - pp[3]
    if abs(du[0] * dv[1] - du[1] * dv[0]) / (np.linalg.norm(du) * np.linalg.norm(dv)) < 0.7:
        return None  # edges closer than 45 deg in the image: profiles would cross both
    H, W = face_id.shape
    if (
        pp[4:, 0].min() < 1
        or pp[4:, 1].min() < 1
        or pp[4:, 0].max() > W - 1
        or pp[4:, 1].max() > H - 1
    ):
        return None
    mask = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(mask, np.round(pp[[4, 5, 6, 7]] - 0.5).astype(np.int32), 1)
    if np.any(face_id[mask > 0] != f.index):
        return None
    return u, v, r


def raycast_independent(scene, origin, dirs, t_max):
    """First face hit strictly before ``t_max`` along each ray (-1 if none): plain algebra."""
    dirs = np.atleast_2d(dirs)
    hit = np.full(len(dirs), -1)
    best = np.array(t_max, np.float64, copy=True).reshape(-1) * np.ones(len(dirs))
    for f in scene.faces:
        c = f.corners
        n = np.cross(c[1] - c[0], c[3] - c[0])
        n /= np.linalg.norm(n)
        den = dirs @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((c[0] - origin) @ n) / den
        P = origin + t[:, None] * dirs
        e1, e2 = c[1] - c[0], c[3] - c[0]
        a = (P - c[0]) @ e1 / (e1 @ e1)
        b = (P - c[0]) @ e2 / (e2 @ e2)
        inside = (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        ok = (np.abs(den) > 1e-12) & (t > 1e-9) & (t < best * (1 - 1e-9)) & inside
        best[ok] = t[ok]
        hit[ok] = f.index
    return hit, best


# --------------------------------------------------------------------------- renderer geometry
def test_track_points_are_where_the_rendered_corners_are(scene, camera, mapping):
    poses, renders, rec = mapping
    fidx = feature_index_of_points(scene, rec)
    errs, obliq, kinds = [], [], set()
    for iid, im in rec.images.items():
        T = poses[iid - 1]
        r = renders[iid - 1]
        gray = cv2.cvtColor(r.bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
        for xy, pid in zip(im.points2D, im.point3D_ids):
            fi = fidx[int(pid)]
            m = measurable(scene, camera, T, r.face_id, fi)
            if m is None:
                continue
            est = fit_corner(gray, camera, T, scene.features.xyz[fi], *m)
            if est is None:
                continue
            errs.append(np.linalg.norm(est - xy))
            f = scene.faces[scene.features.face[fi]]
            to_cam = T.center - scene.features.xyz[fi]
            obliq.append(np.degrees(np.arccos(to_cam @ f.normal / np.linalg.norm(to_cam))))
            kinds.add(f.recipe[0])
    errs, obliq = np.array(errs), np.array(obliq)
    assert len(errs) >= 120, f"only {len(errs)} measurable track points"
    assert (obliq > 45).sum() >= 15, "the sample must include oblique views of surfaces"
    assert {"wall", "floor", "box"} <= kinds
    assert errs.max() < 0.5, f"worst track point is {errs.max():.3f} px from its corner"
    assert np.median(errs) < 0.1


def test_corner_measurement_sees_a_half_pixel_shift(scene, camera, mapping):
    """The check above has the power to catch the classic 0.5 px convention bug."""
    poses, renders, rec = mapping
    fidx = feature_index_of_points(scene, rec)
    d = []
    for im in sorted(rec.images.values(), key=lambda i: -len(i.point3D_ids))[:4]:
        T, r = poses[im.image_id - 1], renders[im.image_id - 1]
        shifted = cv2.warpAffine(
            r.bgr,
            np.float32([[1, 0, 0.5], [0, 1, 0.5]]),
            (640, 480),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        gray = cv2.cvtColor(shifted, cv2.COLOR_BGR2GRAY).astype(np.float32)
        for xy, pid in zip(im.points2D, im.point3D_ids):
            fi = fidx[int(pid)]
            m = measurable(scene, camera, T, r.face_id, fi)
            est = None if m is None else fit_corner(gray, camera, T, scene.features.xyz[fi], *m)
            if est is not None:
                d.append(est - xy)
    d = np.array(d)
    assert len(d) >= 20
    assert np.allclose(np.median(d, axis=0), [0.5, 0.5], atol=0.1)
    assert np.min(np.linalg.norm(d, axis=1)) > 0.3


def test_depth_map_is_the_analytic_plane_depth(scene, camera, mapping):
    poses, renders, _ = mapping
    K_inv = np.linalg.inv(camera.K)
    us, vs = np.meshgrid(np.arange(640) + 0.5, np.arange(480) + 0.5)
    rays = np.stack([us, vs, np.ones_like(us)], -1) @ K_inv.T  # camera frame, z = 1
    for i in (0, 5, 11):
        T, r = poses[i], renders[i]
        assert np.all(r.face_id >= 0), "a closed room shows a surface at every pixel"
        expected = np.empty((480, 640))
        for fid in np.unique(r.face_id):
            f = scene.faces[fid]
            n_c = T.rotation @ f.normal
            d_c = f.plane_d - f.normal @ T.center
            m = r.face_id == fid
            expected[m] = d_c / (rays[m] @ n_c)
        np.testing.assert_allclose(r.depth, expected, rtol=2e-6)
        # Independent ray casting through pixel centres agrees on face and depth, away from edges.
        rng = np.random.default_rng(i)
        j, k = rng.integers(0, 480, 400), rng.integers(0, 640, 400)
        d_world = rays[j, k] @ T.rotation  # R^T d
        hit, t = raycast_independent(scene, T.center, d_world, np.inf)
        ok = np.ones(400, bool)
        for dj in (-1, 0, 1):
            for dk in (-1, 0, 1):
                ok &= r.face_id[np.clip(j + dj, 0, 479), np.clip(k + dk, 0, 639)] == r.face_id[j, k]
        assert ok.sum() > 300
        assert np.array_equal(hit[ok], r.face_id[j, k][ok])
        np.testing.assert_allclose(t[ok] * rays[j, k, 2][ok], r.depth[j, k][ok], rtol=2e-6)


def test_track_points_show_their_face_and_texture(scene, camera, mapping):
    poses, renders, rec = mapping
    fidx = feature_index_of_points(scene, rec)
    F = scene.features
    n_checked = 0
    for iid, im in rec.images.items():
        T, r = poses[iid - 1], renders[iid - 1]
        smooth = cv2.GaussianBlur(r.bgr, (0, 0), 1.0).astype(np.float64)  # average the noise
        for xy, pid in zip(im.points2D, im.point3D_ids):
            fi = fidx[int(pid)]
            i, j = int(np.floor(xy[0])), int(np.floor(xy[1]))
            assert r.face_id[j, i] == F.face[fi]
            # Depth at the pixel centre vs the point's own depth: same plane, a fraction of a
            # pixel away.
            z = (T.apply(F.xyz[fi]))[2]
            assert abs(r.depth[j, i] - z) < 0.02 * z
            if F.radius[fi] * camera.K[0, 0] / z < 12:
                continue
            f = scene.faces[F.face[fi]]
            s, t = F.st[fi]
            rad = F.radius[fi] / min(f.texel_size)
            for a, b in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                # The middle of each quadrant shows that quadrant's texture colour, shaded.
                st = np.array([s + a * rad / 2, t + b * rad / 2])
                ts, tt = int(st[0]), int(st[1])
                tex = f.texture[tt - 1 : tt + 1, ts - 1 : ts + 1].reshape(-1, 3).mean(0)
                p = camera.project(T, f.world_from_tex(st[None]))[0][0]
                pi, pj = int(p[0]), int(p[1])
                if not (2 <= pi < 638 and 2 <= pj < 478):
                    continue
                if np.any(r.face_id[pj - 2 : pj + 3, pi - 2 : pi + 3] != f.index):
                    continue
                seen = smooth[pj, pi]
                assert np.all(np.abs(seen - tex * f.shade) < 12), (seen, tex * f.shade)
                n_checked += 1
    assert n_checked >= 100


# --------------------------------------------------------------------------- visibility
def test_no_occluded_point_in_a_track_and_visible_points_present(scene, camera, mapping):
    poses, renders, _ = mapping
    F = scene.features
    conf = VisibilityConf()
    normals = np.stack([f.normal for f in scene.faces])[F.face]
    n_occluded = n_required = 0
    # The mapping views plus one that looks past the table and a box at the wall behind.
    table = next(b for b in scene.layout.boxes if b.kind == "table_top")
    eye = np.array([table.center[0] - 2.0, table.center[1] - 0.2, 1.1])
    extra = look_at(eye, [table.center[0] + 1.0, table.center[1], 0.5])
    views = [(T, r.face_id) for T, r in zip(poses, renders)] + [(extra, None)]
    for T, face_id in views:
        obs = visible_points(scene, camera, T, face_id=face_id)
        in_track = np.zeros(len(F), bool)
        in_track[obs.point_idx] = True
        xy, z = camera.project(T, F.xyz)
        to_cam = T.center - F.xyz
        dist = np.linalg.norm(to_cam, axis=1)
        facing = np.einsum("ij,ij->i", to_cam, normals) > 0
        cand = np.flatnonzero((z > 0.05) & camera.in_image(xy, 0) & facing)
        hit, _ = raycast_independent(
            scene, T.center, -to_cam[cand] / dist[cand, None], dist[cand] * (1 - 1e-9)
        )
        occluded = cand[hit >= 0]
        n_occluded += len(occluded)
        assert not in_track[occluded].any(), "an occluded point is in a track"
        assert np.all(np.isin(obs.point_idx, cand[hit < 0])), (
            "a track point is occluded, off-image or back-facing"
        )
        # Around a track point, every pixel centre within the margin sees the point's face.
        k = conf.occlusion_margin_px
        grid = np.array([[di, dj] for dj in range(-k, k + 1) for di in range(-k, k + 1)]) + 0.5

        def first_faces(idx, xy=xy, grid=grid, T=T):
            px = (np.floor(xy[idx])[:, None, :] + grid[None]).reshape(-1, 2)
            d = (
                np.column_stack([(px - camera.K[:2, 2]) / camera.K[0, 0], np.ones(len(px))])
                @ T.rotation
            )
            return raycast_independent(scene, T.center, d, np.inf)[0].reshape(len(idx), -1)

        def sizes_of(idx, xy=xy, T=T):
            faces = [scene.faces[i] for i in F.face[idx]]
            u = np.stack([f.u_axis / np.linalg.norm(f.u_axis) for f in faces])
            v = np.stack([f.v_axis / np.linalg.norm(f.v_axis) for f in faces])
            ends = np.stack([F.xyz[idx] + F.radius[idx, None] * w for w in (u, -u, v, -v)], axis=1)
            p = camera.project(T, ends.reshape(-1, 3))[0].reshape(-1, 4, 2)
            return np.min(np.linalg.norm(p - xy[idx, None], axis=2), axis=1)

        tp = obs.point_idx
        assert len(tp) > 0
        assert np.all(first_faces(tp) == F.face[tp, None]), "a silhouette crosses a track point"
        assert np.all(camera.in_image(xy[tp], conf.margin_px))
        cos_t = np.einsum("ij,ij->i", to_cam[tp], normals[tp]) / dist[tp]
        assert np.all(cos_t >= np.cos(np.radians(conf.max_obliquity_deg)) - 1e-12)
        assert np.all(sizes_of(tp) >= conf.min_feature_px - 1e-9)
        np.testing.assert_allclose(obs.xy, xy[tp], atol=1e-9)
        # Clearly visible points (independent test, margins on every threshold) must be present.
        clear = cand[hit < 0]
        cos_o = np.einsum("ij,ij->i", to_cam[clear], normals[clear]) / dist[clear]
        keep = cos_o > np.cos(np.radians(conf.max_obliquity_deg - 3))
        keep &= camera.in_image(xy[clear], conf.margin_px + 1)
        clear = clear[keep]
        if len(clear) == 0:
            continue
        clear = clear[sizes_of(clear) > conf.min_feature_px + 0.5]
        # Every pixel centre around the projection must see the point's face first.
        required = clear[np.all(first_faces(clear) == F.face[clear, None], axis=1)]
        n_required += len(required)
        missing = required[~in_track[required]]
        assert len(missing) == 0, f"clearly visible points {missing[:5]} are missing"
    assert n_occluded >= 200 and n_required >= 200


def test_tracks_reference_exact_projections(scene, camera, mapping):
    poses, _, rec = mapping
    rec.check()
    n_obs = 0
    for pid, p in rec.points3D.items():
        assert len(p.track_image_ids) >= 2
        for iid, idx in zip(p.track_image_ids, p.track_point2D_idxs):
            im = rec.images[int(iid)]
            assert im.point3D_ids[idx] == pid
            expected = camera.project(poses[iid - 1], p.xyz[None])[0][0]
            np.testing.assert_allclose(im.points2D[idx], expected, atol=1e-9)
            n_obs += 1
    assert n_obs == sum(len(im.point3D_ids) for im in rec.images.values())
    assert len(rec.points3D) > 300


# --------------------------------------------------------------------------- scene and images
def test_walls_have_hundreds_of_harris_corners(scene, camera):
    L, W, _ = scene.size
    for eye, target in (
        ((L / 2, 1.5, 1.5), (L / 2, 0.0, 1.4)),
        ((5.5, W / 2, 1.5), (L, W / 2, 1.4)),
    ):
        bgr, _ = render(scene, camera, look_at(eye, target))
        c = cv2.goodFeaturesToTrack(
            cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), 3000, 0.01, 5, useHarrisDetector=True
        )
        assert len(c) >= 200


def test_deterministic_for_a_seed_and_different_across_seeds(scene, camera):
    again = Scene.room(0)
    assert all(np.array_equal(a.texture, b.texture) for a, b in zip(scene.faces, again.faces))
    np.testing.assert_array_equal(scene.features.xyz, again.features.xyz)
    T = mapping_views(scene, 2, seed=0)[1]
    pairs = zip(mapping_views(again, 2, 0), mapping_views(scene, 2, 0))
    assert all(np.array_equal(a.matrix(), b.matrix()) for a, b in pairs)
    b1, d1 = render(scene, camera, T, noise_seed=7)
    b2, d2 = render(again, camera, T, noise_seed=7)
    assert np.array_equal(b1, b2) and np.array_equal(d1, d2)
    b3, _ = render(scene, camera, T, noise_seed=8)
    assert not np.array_equal(b1, b3)
    assert 1.0 < np.std(b1.astype(float) - b3) < 4.0  # two draws of sigma-2 noise
    other = Scene.room(1, SceneConf())
    assert len(other.features) != len(scene.features) or not np.array_equal(
        other.features.xyz, scene.features.xyz
    )
    b4, _ = render(other, camera, T, noise_seed=7)
    assert np.mean(np.abs(b4.astype(float) - b1)) > 10


def test_noise_free_render_and_camera_checks(scene, camera):
    T = look_at((4.0, 2.5, 1.5), (8.0, 2.5, 1.4))
    a, _ = render(scene, camera, T, noise_sigma=0.0, noise_seed=1)
    b, _ = render(scene, camera, T, noise_sigma=0.0, noise_seed=2)
    assert np.array_equal(a, b)
    with pytest.raises(CameraModelError):
        render(scene, Camera("OPENCV", 640, 480, [525, 525, 320, 240, 0.1, 0, 0, 0]), T)


# --------------------------------------------------------------------------- trajectories
@pytest.mark.parametrize("seed", [0, 3])
def test_trajectories_stay_in_free_space(seed):
    layout = room_layout(seed)
    L, W, H = layout.size
    for kind, extra in (
        ("walk", {}),
        ("flight", {}),
        ("orbit", {}),
        ("orbit", {"look": "outward"}),
    ):
        poses = make_trajectory(kind, 600, seed, layout, **extra)
        assert len(poses) == 600
        assert check_trajectory(layout, poses) == []
        C = np.stack([p.center for p in poses])
        assert np.all((C[:, 0] > 0.5) & (C[:, 0] < L - 0.5) & (C[:, 1] > 0.5) & (C[:, 1] < W - 0.5))
        assert np.all((C[:, 2] > 0.5) & (C[:, 2] < H - 0.5))
        for b in layout.boxes:
            assert np.all(b.distance_xy(C[:, :2]) > 0.3), (kind, b.name)
        v = np.linalg.norm(np.diff(C, axis=0), axis=1) * 30
        a = np.linalg.norm(np.diff(C, 2, axis=0), axis=1) * 900
        assert a.max() < 6.0, f"{kind} is not smooth"
        if kind == "walk":
            assert 1.0 <= v.min() and v.max() <= 1.45
            assert (
                np.all(np.abs(C[:, 2] - np.median(C[:, 2])) < 0.1)
                and 1.35 < np.median(C[:, 2]) < 1.7
            )
        if kind == "orbit":
            r = np.linalg.norm(C[:, :2] - layout.track.center, axis=1)
            assert np.ptp(r) < 1e-9
        if kind == "flight":
            fwd = np.stack([p.rotation[2] for p in poses])
            yaw = np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))
            rate = np.degrees(np.abs(np.diff(yaw))) * 30
            assert rate.max() >= 90 and rate.max() <= 130
            assert np.ptp(C[:, 2]) > 0.3  # altitude changes
            up = np.stack([-p.rotation[1] for p in poses])  # camera -y in world
            tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1, 1)))
            assert tilt.max() < 25  # small roll and pitch (camera mounted 8 deg down)


def test_mapping_views_cover_every_wall_and_box(scene, camera):
    poses = mapping_views(scene, 120, seed=0)
    assert len(poses) == 120 and check_trajectory(scene, poses, min_view_depth=0.8) == []
    C = np.stack([p.center for p in poses])
    assert np.ptp(C[:, 2]) > 1.0
    owner = [f.name if f.name.startswith("wall") else f.name.split("_")[0] for f in scene.faces]
    views: dict[str, int] = {}
    for T in poses:
        _, face_id = render_geometry(scene, camera, T)
        ids, counts = np.unique(face_id, return_counts=True)
        for name in {owner[i] for i, c in zip(ids, counts) if c >= 2000}:
            views[name] = views.get(name, 0) + 1
    boxes = {b.name for b in scene.layout.boxes if b.kind != "table_leg"}
    walls = {f.name for f in scene.faces if f.name.startswith("wall")}
    assert all(views.get(b, 0) >= 4 for b in boxes), views
    assert all(views.get(w, 0) >= 15 for w in walls), views


# --------------------------------------------------------------------------- command line
def test_cli_writes_the_full_layout(tmp_path, scene, camera, capsys):
    from sfmloc.cli.main import main as cli

    out = tmp_path / "ds"
    assert (
        cli(
            [
                "-q",
                "synth",
                str(out),
                "--frames",
                "20",
                "--mapping-views",
                "8",
                "--trajectory",
                "flight",
            ]
        )
        == 0
    )
    summary = capsys.readouterr().out
    assert "20 frames" in summary and "frames/s" in summary
    assert sorted(p.name for p in out.iterdir()) == [
        "camera.json",
        "groundtruth.tum",
        "images",
        "scene.json",
        "sparse",
        "video",
        "video_poses.txt",
    ]
    assert sorted(p.name for p in (out / "video").iterdir()) == [
        f"frame-{i:06d}.png" for i in range(20)
    ]
    assert len(list((out / "images").iterdir())) == 8
    assert not list(tmp_path.glob(".ds.*")), "temporary folders are cleaned up"
    img = cv2.imread(str(out / "video" / "frame-000000.png"))
    assert img.shape == (480, 640, 3) and img.dtype == np.uint8
    assert Camera.from_json(out / "camera.json") == camera
    info = json.loads((out / "scene.json").read_text())
    assert info["seed"] == 0 and info["trajectory"] == "flight" and info["frames"] == 20

    # The model on disk is the in-memory model of the same views.
    poses = mapping_views(scene, 8, seed=0)
    names = [f"map-{i:04d}.png" for i in range(8)]
    mem = build_reconstruction(scene, camera, poses, names)
    disk = read_model(out / "sparse")
    assert disk.cameras == mem.cameras
    assert sorted(disk.images) == sorted(mem.images) and sorted(disk.points3D) == sorted(
        mem.points3D
    )
    for iid, im in mem.images.items():
        d = disk.images[iid]
        assert d.name == im.name and (out / "images" / d.name).is_file()
        np.testing.assert_allclose(
            d.cam_from_world.matrix(), im.cam_from_world.matrix(), atol=1e-12
        )
        np.testing.assert_array_equal(d.points2D, im.points2D)
        np.testing.assert_array_equal(d.point3D_ids, im.point3D_ids)
    for pid, p in mem.points3D.items():
        d = disk.points3D[pid]
        np.testing.assert_array_equal(d.xyz, p.xyz)
        np.testing.assert_array_equal(d.track_image_ids, p.track_image_ids)
        np.testing.assert_array_equal(d.track_point2D_idxs, p.track_point2D_idxs)

    # Video poses: TUM (world_from_cam) and the COLMAP list (cam_from_world) match the trajectory.
    traj = make_trajectory("flight", 20, 0, scene)
    tum = read_poses(out / "groundtruth.tum")
    assert tum.format == "tum" and len(tum) == 20
    lst = read_poses(out / "video_poses.txt").by_key()
    for i, (e, T) in enumerate(zip(tum, traj)):
        assert e.timestamp == pytest.approx(i / 30, abs=1e-6)
        for got in (e.cam_from_world, lst[f"frame-{i:06d}.png"]):
            np.testing.assert_allclose(got.rotation, T.rotation, atol=1e-8)
            np.testing.assert_allclose(got.center, T.center, atol=1e-8)

    # A second run does not clobber a finished data set unless asked to.
    assert cli(["-q", "synth", str(out), "--frames", "2", "--mapping-views", "2"]) == 2
    assert len(list((out / "video").iterdir())) == 20


def test_cli_help_explains_layout_and_conventions(capsys):
    from sfmloc.cli.main import main as cli

    with pytest.raises(SystemExit):
        cli(["synth", "--help"])
    text = capsys.readouterr().out
    for word in (
        "--trajectory",
        "--frames",
        "--seed",
        "--mapping-views",
        "--noise",
        "groundtruth.tum",
        "world_from_cam",
        "cam_from_world",
        "z up",
        "(0.5, 0.5)",
        "video_poses.txt",
        "sparse/",
    ):
        assert word in text, word


def test_rigid_pose_helpers_follow_colmap_axes():
    T = look_at((1.0, 2.0, 1.5), (5.0, 2.0, 1.5))
    # Looking along +x with z up: camera z = +x, camera x (right) = -y, camera y (down) = -z.
    np.testing.assert_allclose(T.rotation, [[0, -1, 0], [0, 0, -1], [1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(T.center, [1.0, 2.0, 1.5])
    assert isinstance(T, Rigid3d)
