"""Input 2: images with known poses -> 3D points triangulated with pycolmap, poses fixed.

For a user whose poses come from motion capture or a dataset's ground truth: the map is
metric and in their world frame. Steps: match pose entries to image files; SIFT (OpenCV's by
default, ``sift_backend``) into a COLMAP database;
choose pairs from the poses (``pair_selection="geometric"``, ``sfm.pairs``: each image with its
``pair_near`` nearest cameras, matched first to estimate its scene depth, then one partner per
target triangulation angle among the cameras whose frustum overlaps its view; ``"nearest"``:
its ``pair_neighbors`` nearest cameras that look within ``pair_max_angle_deg`` of the same
direction, plus its ``pair_sequential`` next images in pose-file order); match and verify
them; ``pycolmap.triangulate_points`` with the given
poses and intrinsics held fixed (it triangulates, merges and completes tracks, and refines the
points only by bundle adjustment, filtering by reprojection error and triangulation angle);
drop points seen in fewer than ``min_track_length`` images (where that would leave the median
image fewer than ``two_view_below`` points, triangulate again keeping two-view tracks).

Matching pose entries to files:

- COLMAP list (``name qw qx qy qz tx ty tz``): by relative file name; entries whose name is not
  a file are matched by ``name_stem`` (``seq-01/frame-000000.color.png`` ->
  ``frame-000000.color``, so ``frame-000000.color.jpg`` matches). Two files with one stem, or
  two entries for one file, are an error naming them.
- TUM (``timestamp tx ty tz qx qy qz qw``): when every file stem is a number (the TUM RGB-D
  layout ``rgb/1305031102.175304.png``), each image takes the pose with the nearest timestamp
  within ``max_time_diff`` seconds; otherwise, when there are exactly as many images as poses,
  by order (images sorted by name, poses in file order); otherwise an error.

Images without a pose are skipped with a warning; poses without an image are ignored.

Measured on 100 redkitchen frames (every 10th of seq-01, 640x480, 2 cores): see the table
above ``SFM_PRESETS`` in ``sfm.conf``; reproduce with ``python -m sfmloc.bench.sfm``.
Nearest pairs: k=3 gave 5% fewer points and shorter tracks (5.3), k=8 3% more points at 2x
the matching time; min track 2 adds ~7k two-view points whose depth is the least reliable (on the
synthetic scenes their surface error is ~1.5x that of longer tracks).
"""

from __future__ import annotations

import bisect
import logging
import math
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pycolmap

from ...cameras import Camera
from ...errors import BuildError, InputError
from ...io.colmap import Reconstruction
from ...io.poses import PoseList, name_stem, read_poses
from ...transforms import Rigid3d
from .conf import SfmConf, incremental_options
from .convert import (
    filter_points,
    reconstruction_from_pycolmap,
    reconstruction_stats,
    rigid3d_to_pycolmap,
)
from .inputs import check_images, check_names, list_images, select_images
from .pairs import depths_from_matches, near_pairs, wide_pairs
from .run import CancelCheck, Progress, Reporter, quiet_colmap, work_directory
from .stages import extract_features, match_pairs, to_pycolmap_camera

log = logging.getLogger(__name__)

MAX_TIME_DIFF_S = 0.02  # TUM RGB-D's associate.py default


# --------------------------------------------------------------------------- poses <-> files
def match_poses_to_images(
    poses: PoseList,
    names: Sequence[str],
    poses_file: str | Path = "poses",
    image_dir: str | Path = "images",
    max_time_diff: float = MAX_TIME_DIFF_S,
) -> list[tuple[str, Rigid3d]]:
    """``(image name, cam_from_world)`` for every image that has a pose, in pose-file order
    (TUM by order: image order). See the module docstring for the rules."""
    if not names:
        raise InputError(f"[input] no images in {image_dir}")
    if poses.format == "tum":
        matched = _match_tum(poses, names, poses_file, image_dir, max_time_diff)
    else:
        matched = _match_by_name(poses, names, poses_file)
    if not matched:
        raise InputError(
            f"[input] no pose in {poses_file} matches an image in {image_dir} "
            f"({len(poses)} poses, e.g. {poses.entries[0].key!r}; {len(names)} images, e.g. "
            f"{names[0]!r})"
        )
    n_skipped = len(names) - len(matched)
    if n_skipped:
        have = {n for n, _ in matched}
        examples = [n for n in names if n not in have][:3]
        log.warning(
            "%d of %d images in %s have no pose in %s and are skipped (e.g. %s)",
            n_skipped,
            len(names),
            image_dir,
            poses_file,
            ", ".join(examples),
        )
    n_unused = len(poses) - len(matched)
    if n_unused:
        log.info(
            "%d of %d poses in %s have no image in %s (ignored)",
            n_unused,
            len(poses),
            poses_file,
            image_dir,
        )
    return matched


def _match_by_name(poses: PoseList, names: Sequence[str], poses_file) -> list[tuple[str, Rigid3d]]:
    exact = set(names)
    by_stem: dict[str, list[str]] = {}
    for n in names:
        by_stem.setdefault(name_stem(n), []).append(n)
    out: list[tuple[str, Rigid3d]] = []
    owner: dict[str, str] = {}  # image name -> pose key that took it
    for e in poses.entries:
        key = e.key.replace("\\", "/")
        if key in exact:
            name = key
        else:
            cands = by_stem.get(name_stem(key), [])
            if not cands:
                continue
            if len(cands) > 1:
                raise InputError(
                    f"[input] pose {e.key!r} in {poses_file} is ambiguous: images "
                    f"{', '.join(cands[:4])} "
                    "share its name stem; give poses with the images' relative names"
                )
            name = cands[0]
        if name in owner:
            raise InputError(
                f"[input] poses {owner[name]!r} and {e.key!r} in {poses_file} both match image "
                f"{name!r}"
            )
        owner[name] = e.key
        out.append((name, e.cam_from_world))
    return out


def _numeric_stem(name: str) -> float | None:
    try:
        v = float(name_stem(name))
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def _match_tum(
    poses: PoseList, names: Sequence[str], poses_file, image_dir, max_dt: float
) -> list[tuple[str, Rigid3d]]:
    named = [_numeric_stem(n) for n in names]
    stamps = [s for s in named if s is not None]
    if len(stamps) == len(named):
        order = sorted(range(len(poses.entries)), key=lambda i: poses.entries[i].stamp)
        ts = [poses.entries[i].stamp for i in order]
        out = []
        used: dict[int, str] = {}
        for name, s in sorted(zip(names, stamps), key=lambda x: x[1]):
            k = bisect.bisect_left(ts, s)
            best = min((j for j in (k - 1, k) if 0 <= j < len(ts)), key=lambda j: abs(ts[j] - s))
            if abs(ts[best] - s) > max_dt:
                continue
            if best in used:
                raise InputError(
                    f"[input] images {used[best]!r} and {name!r} both match the pose at "
                    f"t={ts[best]} in "
                    f"{poses_file} (within {max_dt} s)"
                )
            used[best] = name
            out.append((name, poses.entries[order[best]].cam_from_world))
        return out
    if len(names) == len(poses):
        log.info(
            "TUM poses %s matched to the %d images of %s by order (file names are not timestamps)",
            poses_file,
            len(names),
            image_dir,
        )
        return [(n, e.cam_from_world) for n, e in zip(sorted(names), poses.entries)]
    raise InputError(
        f"[input] cannot match the {len(poses)} TUM poses of {poses_file} to the {len(names)} "
        "images of "
        f"{image_dir}: image names are not timestamps (e.g. {names[0]!r}) and the counts differ"
    )


# --------------------------------------------------------------------------- pairs
def pairs_from_poses(
    names: Sequence[str],
    cam_from_worlds: Sequence[Rigid3d],
    neighbors: int,
    sequential: int,
    max_angle_deg: float,
) -> list[tuple[str, str]]:
    """Image pairs likely to overlap: each image with its ``neighbors`` nearest cameras (by
    centre distance) whose viewing directions differ by less than ``max_angle_deg``, and with
    its next ``sequential`` images in the given order. Unique, in a stable order."""
    n = len(names)
    C = np.array([T.center for T in cam_from_worlds]).reshape(n, 3)
    V = np.array([T.rotation[2] for T in cam_from_worlds]).reshape(n, 3)  # optical axes in world
    cos_max = math.cos(math.radians(max_angle_deg))
    pairs: set[tuple[int, int]] = set()
    for i in range(n):
        for s in range(1, sequential + 1):
            if i + s < n:
                pairs.add((i, i + s))
        if neighbors > 0:
            d = np.linalg.norm(C - C[i], axis=1)
            ok = (V @ V[i] >= cos_max) & (np.arange(n) != i)
            cand = np.flatnonzero(ok)
            for j in cand[np.argsort(d[cand], kind="stable")][:neighbors]:
                pairs.add((min(i, int(j)), max(i, int(j))))
    return [(names[a], names[b]) for a, b in sorted(pairs)]


def match_geometric_pairs(
    db_path: Path,
    work: Path,
    names: Sequence[str],
    cam_from_worlds: Sequence[Rigid3d],
    camera: Camera,
    conf: SfmConf,
    rep: Reporter,
) -> list[tuple[str, str]]:
    """``sfm.pairs``' selection, matched in two rounds: the near pairs first (their matches
    give each image's scene depth), then the wide pairs that depth implies. Returns all pairs."""
    near = sorted(near_pairs(cam_from_worlds, conf.pair_near, conf.pair_max_angle_deg))
    if not near:  # pair_near=0: still need depths, from each image's nearest view
        near = sorted(near_pairs(cam_from_worlds, 1, conf.pair_max_angle_deg))
    log.info("matching %d near image pairs", len(near))
    match_pairs(db_path, work, [(names[a], names[b]) for a, b in near], conf, rep)
    depths = depths_from_matches(db_path, names, cam_from_worlds, camera, near)
    if not np.isfinite(depths).any():
        log.warning("no scene depth from the near pairs' matches: matching near pairs only")
        return [(names[a], names[b]) for a, b in near]
    wide = wide_pairs(
        camera,
        cam_from_worlds,
        depths,
        conf.pair_angles_deg,
        conf.pair_min_overlap,
        conf.pair_max_angle_deg,
    )
    extra = sorted(wide - set(near))
    log.info(
        "scene depth median %.3g (per image %.3g-%.3g); matching %d wide pairs (angles %s deg)",
        float(np.median(depths)),
        float(np.min(depths)),
        float(np.max(depths)),
        len(extra),
        "/".join(f"{a:g}" for a in conf.pair_angles_deg),
    )
    if extra:
        rep.report("matching", 0.0, f"matching {len(extra)} wide pairs")
        match_pairs(db_path, work, [(names[a], names[b]) for a, b in extra], conf, rep)
    return [(names[a], names[b]) for a, b in sorted(set(near) | wide)]


# --------------------------------------------------------------------------- pipeline
def triangulate_known_poses(
    image_dir: str | Path,
    poses_file: str | Path,
    camera: Camera | str | Path,
    conf: SfmConf | None = None,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    should_cancel: CancelCheck | None = None,
    *,
    image_names: Sequence[str] | None = None,
    stride: int = 1,
    poses_format: str | None = None,
    max_time_diff: float = MAX_TIME_DIFF_S,
) -> Reconstruction:
    """Triangulate a map from images with known ``cam_from_world`` poses (kept exactly).

    ``camera``: a ``Camera``, a ``camera.json`` path or ``"PINHOLE w h fx fy cx cy"``; all
    images share it. ``image_names`` restricts to those relative names; ``stride`` then keeps
    every n-th image with a pose (in pose-file order). ``workdir``: parent of the temporary
    work directory (COLMAP database, pair lists), removed afterwards unless
    ``conf.keep_workdir``. Progress stages: input, features, matching, triangulate.
    """
    conf = conf or SfmConf()
    rep = Reporter(progress, should_cancel)
    image_dir, poses_file = Path(image_dir), Path(poses_file)
    cam = camera if isinstance(camera, Camera) else Camera.parse(camera)
    if not poses_file.is_file():
        raise InputError(f"[input] pose file {poses_file} does not exist")
    poses = read_poses(poses_file, poses_format)
    files = select_images(list_images(image_dir), image_names, 1, image_dir)
    matched = match_poses_to_images(poses, files, poses_file, image_dir, max_time_diff)
    if stride < 1:
        raise InputError(f"[input] stride must be >= 1, got {stride}")
    matched = matched[::stride]
    if len(matched) < 2:
        raise InputError(
            f"[input] need at least two posed images to triangulate, got {len(matched)} from "
            f"{image_dir}"
        )
    names = [n for n, _ in matched]
    check_names(names, image_dir)
    pose_of = dict(matched)
    rep.report("input", 0.0, f"{len(names)} posed images, camera {cam.to_string()}")
    with quiet_colmap():
        check_images(image_dir, names, lambda _n: cam.size, conf, rep)
        pycolmap.set_random_seed(conf.seed)
        with work_directory(workdir, conf.keep_workdir) as work:
            db_path = work / "database.db"
            extract_features(db_path, image_dir, names, to_pycolmap_camera(cam), conf, rep)
            rep.check("matching")
            poses_in_order = [pose_of[n] for n in names]
            if conf.pair_selection == "nearest":
                pairs = pairs_from_poses(
                    names,
                    poses_in_order,
                    conf.pair_neighbors,
                    conf.pair_sequential,
                    conf.pair_max_angle_deg,
                )
                log.info("matching %d image pairs chosen from the poses", len(pairs))
                match_pairs(db_path, work, pairs, conf, rep)
            else:
                match_geometric_pairs(db_path, work, names, poses_in_order, cam, conf, rep)
            rep.check("triangulate")
            rep.report("triangulate", 0.0, "triangulating with fixed poses")
            min_track = conf.min_track_length
            rec, dropped = _triangulate(db_path, image_dir, work, pose_of, conf, min_track, rep)
            ppi = _median_points_per_image(rec)
            if min_track > 2 and ppi < conf.two_view_below:
                rep.report(
                    "triangulate",
                    0.5,
                    f"median image sees {ppi:.0f} points (< {conf.two_view_below}): keeping "
                    "two-view points",
                )
                log.info(
                    "known poses: median %.0f points per image with tracks >= %d; re-triangulating "
                    "with "
                    "two-view tracks (SfmConf.two_view_below)",
                    ppi,
                    min_track,
                )
                min_track = 2
                rec, dropped = _triangulate(db_path, image_dir, work, pose_of, conf, min_track, rep)
    st = reconstruction_stats(rec)
    if st["points3D"] == 0:
        raise BuildError(
            f"no 3D point could be triangulated from {len(names)} images of {image_dir} with the "
            "poses of "
            f"{poses_file} (do the poses match the images? are they cam_from_world?)",
            stage="triangulate",
        )
    msg = (
        f"{st['points3D']} points (dropped {dropped}: track < {min_track} or error > "
        f"{conf.max_reproj_error:g} px), mean track {st['mean_track_length']:.2f}, mean error "
        f"{st['mean_reproj_error_px']:.2f} px"
    )
    log.info("known-poses triangulation: %s", msg)
    rep.report("triangulate", 1.0, msg)
    return rec


def _triangulate(
    db_path: Path,
    image_dir: Path,
    work: Path,
    pose_of: dict[str, Rigid3d],
    conf: SfmConf,
    min_track: int,
    rep: Reporter,
) -> tuple[Reconstruction, int]:
    """pycolmap triangulation at the fixed poses into ``work/sparse`` (replaced), points with
    shorter tracks or larger errors dropped: (reconstruction, points dropped)."""
    out_dir = work / "sparse"
    shutil.rmtree(out_dir, ignore_errors=True)
    out_dir.mkdir()
    tri = rep.run(
        "triangulate",
        pycolmap.triangulate_points,
        _posed_reconstruction(db_path, pose_of),
        db_path,
        image_dir,
        out_dir,
        clear_points=True,
        # One thread: the bundle adjustments' Ceres sums its cost over threads in the order
        # they finish, so with more a rebuild could differ in the last bits and a point near
        # a filter's threshold go either way; here they take ~1.5 s of a 30 s build.
        options=incremental_options(
            conf.model_copy(update={"min_track_length": min_track, "num_threads": 1})
        ),
        refine_intrinsics=False,
    )
    rec = reconstruction_from_pycolmap(tri)
    return rec, filter_points(rec, min_track, conf.max_reproj_error)


def _median_points_per_image(rec: Reconstruction) -> float:
    n = [int(np.count_nonzero(im.point3D_ids >= 0)) for im in rec.images.values()]
    return float(np.median(n)) if n else 0.0


def _posed_reconstruction(db_path: Path, pose_of: dict[str, Rigid3d]) -> pycolmap.Reconstruction:
    """A pycolmap reconstruction with the database's camera, rig and image ids and our poses."""
    db = pycolmap.Database.open(db_path)
    try:
        cameras = db.read_all_cameras()
        images = db.read_all_images()
    finally:
        db.close()
    rec = pycolmap.Reconstruction()
    for cam in cameras:
        rec.add_camera_with_trivial_rig(cam)
    for im in images:
        if im.name not in pose_of:
            continue
        if int(im.frame_id) != int(im.image_id):
            raise BuildError(
                f"unexpected database layout: image {im.name} in frame {im.frame_id}",
                stage="triangulate",
            )
        pim = pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id)
        rec.add_image_with_trivial_frame(pim, rigid3d_to_pycolmap(pose_of[im.name]))
    return rec
