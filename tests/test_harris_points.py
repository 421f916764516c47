"""Map points triangulated from Harris corners (builder/harris_points.py), against exact ground
truth: matching and triangulation on exact projections, and on the rendered synthetic room the
points must lie on the scene's surfaces where the corners are."""

from __future__ import annotations

import json

import numpy as np

from sfmloc.cameras import Camera
from sfmloc.transforms import Rigid3d, rotmat_from_rotvec


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def test_epipolar_matching_and_triangulation_recover_exact_points():
    """Corners at the exact projections of 200 points (distorted camera) among 150 distractors
    per image; each point's descriptor is the same up to noise in every view. Every match must
    be right, and the triangulated points exact."""
    from sfmloc.builder.harris_points import HarrisPointsConf, match_pair, triangulate_tracks

    rng = np.random.default_rng(1)
    cam = Camera("OPENCV", 640, 480, [500, 500, 320, 240, -0.05, 0.01, 0.0, 0.0])
    poses = [
        Rigid3d(rotmat_from_rotvec([0, 0.08 * k, 0]), [-0.25 * k, 0.02 * k, 0]) for k in range(3)
    ]
    n = 200
    truth = np.column_stack(
        [rng.uniform(-1, 1, n), rng.uniform(-0.7, 0.7, n), rng.uniform(3, 5, n)]
    )
    base = rng.normal(size=(n, 104))
    xn, desc, idx_of_point = [], [], []
    for T in poses:
        uv, _ = cam.project(T, truth)
        ok = cam.in_image(uv, margin=5)
        dist_xy = rng.uniform([0, 0], [640, 480], (150, 2))
        xy = np.vstack([uv[ok], dist_xy])
        d = np.vstack(
            [base[ok] + rng.normal(0, 0.05, (ok.sum(), 104)), rng.normal(size=(150, 104))]
        )
        perm = rng.permutation(len(xy))
        xn.append(cam.cam_from_img(xy[perm]))
        desc.append(_unit(d[perm]))
        idx = np.full(len(xy), -1)
        idx[: ok.sum()] = np.nonzero(ok)[0]
        idx_of_point.append(idx[perm])
    conf = HarrisPointsConf()
    depth = (2.5, 5.5)
    n_right = 0
    for a, b in ((0, 1), (1, 2), (0, 2)):
        ia, ib, dist = match_pair(
            poses[a], poses[b], xn[a], xn[b], desc[a], desc[b], 500.0, depth, depth, conf
        )
        pa, pb = idx_of_point[a][ia], idx_of_point[b][ib]
        assert np.all(pa >= 0) and np.array_equal(pa, pb), "a wrong match"
        assert np.all(dist < conf.max_descriptor_distance)
        n_right += len(ia)
    assert n_right > 0.8 * 3 * n * 0.8  # most visible points are matched in every pair
    # three-view triangulation of every point seen in all views, from normalized observations
    obs = np.stack([cam.cam_from_img(cam.project(T, truth)[0]) for T in poses], axis=1)  # (n, 3, 2)
    R = np.broadcast_to(np.stack([T.rotation for T in poses]), (n, 3, 3, 3))
    t = np.broadcast_to(np.stack([T.translation for T in poses]), (n, 3, 3))
    valid = np.ones((n, 3), bool)
    valid[:10, 2] = False  # two views are enough
    X = triangulate_tracks(obs, R, t, valid)
    assert np.abs(X - truth).max() < 1e-6


def test_harris_points_lie_on_the_scene_surfaces(world):
    """On the rendered room (exact poses), every Harris point reprojects onto its corners and
    lies on the surface the rendered depth map shows at those corners."""
    from server_helpers import room_scene
    from sfmloc.builder.build import BuildConf, load_gray
    from sfmloc.builder.harris_points import HarrisPointsConf, harris_points
    from sfmloc.io.colmap import read_model
    from sfmloc.synth import SynthConf, render_geometry

    rec = read_model(world.root / "synth" / "sparse")
    dc = BuildConf().descriptors
    conf = HarrisPointsConf(enabled=True, mode="replace", extend_px=1.0)
    detector = {
        "rel_threshold": dc.harris_rel_threshold,
        "border": dc.border,
        "subpixel": dc.subpixel,
    }
    new, stats = harris_points(rec, world.root / "synth" / "images", load_gray, conf, detector)
    assert stats["points"] == len(new.points3D) > 1000, stats
    # tracks are extended beyond the matched image pairs (checked against the depth maps below)
    assert stats["observations"] > stats["observations_before_extension"], stats
    assert set(new.images) == set(rec.images)
    sconf = SynthConf.model_validate(
        json.loads((world.root / "synth" / "scene.json").read_text())["config"]
    )
    scene = room_scene(sconf.seed, sconf.scene)
    cam = rec.cameras[1]
    rel_err, reproj = [], []
    for im in list(new.images.values())[::5]:
        depth, _ = render_geometry(scene, cam, im.cam_from_world)
        sel = im.point3D_ids >= 0
        if not sel.any():
            continue
        xy, ids = im.points2D[sel], im.point3D_ids[sel]
        X = np.stack([new.points3D[int(p)].xyz for p in ids])
        uv, z = cam.project(im.cam_from_world, X)
        reproj.append(np.linalg.norm(uv - xy, axis=1))
        # the corner's pixel may read the far side of an occluding edge: the closest depth of
        # its 5x5 neighbourhood
        xi, yi = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)
        err = np.full(len(z), np.inf)
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                zr = depth[np.clip(yi + dy, 0, cam.height - 1), np.clip(xi + dx, 0, cam.width - 1)]
                err = np.minimum(err, np.abs(z - zr) / zr)
        rel_err.append(err)
    reproj, rel_err = np.concatenate(reproj), np.concatenate(rel_err)
    assert reproj.max() < conf.max_error_px
    assert np.median(rel_err) < 0.002, np.median(rel_err)
    # a wrong match along the epipolar line triangulates exactly, off the surface: tracks of
    # three or more views make that rare (two-view tracks: 12% of points off by > 2%)
    assert np.mean(rel_err < 0.02) > 0.98, np.mean(rel_err < 0.02)


def test_harris_points_switch_builds_a_map_of_harris_points(world):
    """The builder option end to end: "replace" keeps the Harris points only, "add" keeps the
    SfM points (same ids, same positions before refinement) beside them; each point has
    descriptors, and the build info records the stage's counts."""
    from sfmloc.builder.build import BuildConf, assemble, preset
    from sfmloc.config import merge_presets
    from sfmloc.io.colmap import read_model

    assert preset("default").harris_points.enabled and not preset("paper").harris_points.enabled
    rec = read_model(world.root / "synth" / "sparse")
    images = world.root / "synth" / "images"
    conf = merge_presets(BuildConf(), harris_points={"enabled": True, "mode": "replace"})
    data, timings, info = assemble(rec, images, conf)
    assert info["harris_points"] == len(data.points_xyz) > 1000
    assert "harris_points" in timings
    assert len(np.unique(data.desc_point)) > 0.9 * len(data.points_xyz)
    conf = merge_presets(conf, harris_points={"mode": "add"}, refine={"enabled": False})
    both, _, info_add = assemble(rec, images, conf)
    assert len(both.points_xyz) == len(rec.points3D) + info_add["harris_points"]
    sfm_ids = np.array(sorted(rec.points3D))
    rows = np.searchsorted(both.point_ids, sfm_ids)
    assert np.array_equal(both.point_ids[rows], sfm_ids)
    assert np.allclose(both.points_xyz[rows], np.stack([rec.points3D[int(p)].xyz for p in sfm_ids]))
    # The Harris points' ids never name an SfM point, not even one the front end's filtering
    # removed (its kept work folder still holds those: the bench's SIFT peer reads it).
    from sfmloc.builder.harris_points import HARRIS_POINT_ID_BASE

    new = np.setdiff1d(both.point_ids, sfm_ids)
    assert len(new) == info_add["harris_points"] and new.min() >= HARRIS_POINT_ID_BASE


def _surface_errors(rec, new, scene, cam) -> np.ndarray:
    """Per observation of ``new``'s points: the relative depth error against the rendered depth
    (the closest of the corner's 5x5 neighbourhood: it may read the far side of an edge)."""
    from sfmloc.synth import render_geometry

    out = []
    for im in new.images.values():
        sel = im.point3D_ids >= 0
        if not sel.any():
            continue
        depth, _ = render_geometry(scene, cam, im.cam_from_world)
        xy, ids = im.points2D[sel], im.point3D_ids[sel]
        _, z = cam.project(im.cam_from_world, np.stack([new.points3D[int(p)].xyz for p in ids]))
        xi, yi = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)
        err = np.full(len(z), np.inf)
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                zr = depth[np.clip(yi + dy, 0, cam.height - 1), np.clip(xi + dx, 0, cam.width - 1)]
                err = np.minimum(err, np.abs(z - zr) / zr)
        out.append(err)
    return np.concatenate(out)


def test_a_thin_map_keeps_two_view_harris_points_on_the_surfaces(world):
    """Every 3rd mapping view of the rendered room (a thin map: its median image sees fewer
    than ``two_view_below`` points) keeps two-view Harris tracks: more points than with
    ``two_view_below`` 0, the same points for the longer tracks, and the two-view points on the
    scene's surfaces (exact depth maps). The full 40 views are not thin: no two-view track."""
    from server_helpers import room_scene
    from sfmloc.bench.robust_data import every_kth_image, subset_model
    from sfmloc.builder.build import BuildConf, load_gray
    from sfmloc.builder.harris_points import HarrisPointsConf, harris_points
    from sfmloc.io.colmap import read_model
    from sfmloc.synth import SynthConf

    full = read_model(world.root / "synth" / "sparse")
    thin = subset_model(full, every_kth_image(full, 3))
    images = world.root / "synth" / "images"
    dc = BuildConf().descriptors
    det = {"rel_threshold": dc.harris_rel_threshold, "border": dc.border, "subpixel": dc.subpixel}
    conf = HarrisPointsConf(enabled=True, mode="add")
    kept, st_kept = harris_points(thin, images, load_gray, conf, det)
    off, st_off = harris_points(
        thin, images, load_gray, conf.model_copy(update={"two_view_below": 0}), det
    )
    assert st_kept["two_view_kept"] == 1 and st_off["two_view_kept"] == 0
    assert st_kept["median_points_per_image_long"] < conf.two_view_below
    harris = [p for pid, p in kept.points3D.items() if pid not in thin.points3D]
    long = [p for p in harris if len(p.track_image_ids) >= conf.min_track_length]
    two = [p for p in harris if len(p.track_image_ids) == 2]
    assert len(two) > len(long) and len(kept.points3D) == len(off.points3D) + len(two), (
        len(two),
        len(long),
    )
    # the longer tracks' points are those of the map without two-view tracks
    xyz_long = np.sort(np.stack([p.xyz for p in long]), axis=0)
    xyz_off = np.sort(
        np.stack([p.xyz for pid, p in off.points3D.items() if pid not in thin.points3D]), axis=0
    )
    assert np.allclose(xyz_long, xyz_off)
    sconf = SynthConf.model_validate(
        json.loads((world.root / "synth" / "scene.json").read_text())["config"]
    )
    scene = room_scene(sconf.seed, sconf.scene)
    ids_two = {pid for pid, p in kept.points3D.items() if pid not in thin.points3D}
    ids_two &= {pid for pid, p in kept.points3D.items() if len(p.track_image_ids) == 2}
    only_two = type(kept)(
        cameras=kept.cameras,
        images={
            k: type(im)(
                im.image_id,
                im.name,
                im.camera_id,
                im.cam_from_world,
                im.points2D[np.isin(im.point3D_ids, list(ids_two))],
                im.point3D_ids[np.isin(im.point3D_ids, list(ids_two))],
            )
            for k, im in kept.images.items()
        },
        points3D={pid: kept.points3D[pid] for pid in ids_two},
    )
    err = _surface_errors(thin, only_two, scene, thin.cameras[1])
    # measured: 904 two-view points, median 0.06% of the depth, 83% within 2% (a wrong match
    # along the epipolar line triangulates exactly, off the surface; the engine's RANSAC and
    # Cauchy refinement take them as outliers)
    assert np.median(err) < 0.003, np.median(err)
    assert np.mean(err < 0.02) > 0.8, np.mean(err < 0.02)
    # the full map is not thin
    _, st_full = harris_points(full, images, load_gray, conf, det)
    assert st_full["two_view_kept"] == 0, st_full
    assert st_full["median_points_per_image_long"] >= conf.two_view_below


def _solve_all_then_drop(tracks, node_img, geo, conf, per_image_base, chunk_tracks):
    """The stage before 3+-view tracks were solved first: every track solved, the short points
    dropped afterwards unless the map is thin (the reference ``_solve_kept`` must equal)."""
    from sfmloc.builder.harris_points import _solve

    conf2 = conf.model_copy(update={"min_track_length": 2})
    pts, obs, _ = _solve(tracks, node_img, geo, conf2, chunk_tracks)
    long = np.array([len(o) >= conf.min_track_length for o in obs], bool)
    per_image = per_image_base.astype(np.float64, copy=True)
    for o in (o for o, k in zip(obs, long) if k):
        per_image[node_img[o]] += 1
    median = float(np.median(per_image))
    kept = int(conf.keep_two_view or median < conf.two_view_below)
    if not kept:
        pts, obs = pts[long], [o for o, k in zip(obs, long) if k]
    return pts, obs, {"median_points_per_image_long": int(round(median)), "two_view_kept": kept}


def test_two_view_tracks_solved_only_when_kept_give_the_same_points():
    """``_solve_kept`` solves the tracks of 3+ views first and the two-view ones only on a thin
    map: the points (positions, observations, order) must be exactly those of solving every
    track and dropping the short ones after, on a thin and on a non-thin map. Tracks of 2-6
    noisy views, some with an outlier observation (a 3-view track can end with 2), some far
    points below the minimum triangulation angle; chunks of 7 tracks."""
    from sfmloc.builder.harris_points import HarrisPointsConf, _solve_kept

    rng = np.random.default_rng(3)
    n_img, f = 8, 500.0
    poses = [Rigid3d(rotmat_from_rotvec([0, 0.03 * k, 0]), [-0.2 * k, 0, 0]) for k in range(n_img)]
    cam = Camera("PINHOLE", 640, 480, [f, f, 320, 240])
    xn, node_img, tracks = [], [], []
    n = 0
    for p in range(400):
        depth = rng.uniform(3, 6) if p % 10 else rng.uniform(200, 400)  # far: angle < 1 deg
        X = np.array([rng.uniform(-1, 1), rng.uniform(-0.7, 0.7), depth])
        k = int(rng.choice([2, 2, 2, 3, 4, 6]))
        imgs = np.sort(rng.choice(n_img, k, replace=False))
        for j, i in enumerate(imgs):
            x = cam.cam_from_img(cam.project(poses[i], X[None])[0])[0]
            x = x + rng.normal(0, 0.2 / f, 2)
            if p % 5 == 1 and j == 0:
                x = x + [0, 8.0 / f]  # off its epipolar lines: dropped, the track shortens
            xn.append(x)
            node_img.append(i)
        tracks.append(np.arange(n, n + k))
        n += k
    node_img = np.array(node_img)
    geo = {
        "R": np.stack([T.rotation for T in poses]),
        "t": np.stack([T.translation for T in poses]),
        "f": np.full(n_img, f),
        "c": np.stack([T.center for T in poses]),
        "xn": np.array(xn),
    }
    track_len = np.repeat([len(tr) for tr in tracks], [len(tr) for tr in tracks])
    base = np.zeros(n_img)
    for below, keep in ((0, False), (10**6, False), (0, True)):
        conf = HarrisPointsConf(two_view_below=below, keep_two_view=keep)
        pts, obs, st = _solve_kept(tracks, node_img, geo, conf, base, chunk_tracks=7)
        ref_pts, ref_obs, ref_st = _solve_all_then_drop(tracks, node_img, geo, conf, base, 7)
        assert st == ref_st
        assert st["two_view_kept"] == int(below > 0 or keep)
        assert np.array_equal(pts, ref_pts)
        assert len(obs) == len(ref_obs) and all(np.array_equal(a, b) for a, b in zip(obs, ref_obs))
        # the cases meant: two-view points from two-view tracks and from longer tracks that
        # lost an observation (kept on a thin map only), and tracks rejected for their angle
        short = [o for o in obs if len(o) < conf.min_track_length]
        from_long = sum(track_len[o[0]] >= conf.min_track_length for o in short)
        if st["two_view_kept"]:
            assert len(short) > 100 and from_long > 5, (len(short), from_long)
            assert len(pts) < len(tracks) - 20, len(pts)
        else:
            assert not short
