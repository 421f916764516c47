"""Map points triangulated from Harris corners matched across posed images (a builder stage).

SfM puts its points at SIFT blobs; the engine observes a map point through a Harris corner. On
redkitchen (map from every 10th frame) only 8.7% of the SfM points' observations have an
online Harris corner within 1 px of their projection, and the corners the engine matches sit
1.34 px (median) from their points' projections at the ground-truth pose: every 2D-3D match
carries that offset. This stage replaces (or adds to) the SfM points with points triangulated
from the Harris corners themselves, with the image poses fixed:

- corners: full-resolution Harris of every image (the descriptor stage's detector settings),
  each with its oriented raw DAISY;
- pairs: each image with the ``neighbors`` images sharing most SfM points with it;
- matches: mutual best DAISY matches among the corners within ``epipolar_px`` of the epipolar
  line (both ways) whose triangulated depth lies in the image's SfM depth range, with a ratio
  test against the second best of those candidates;
- tracks: connected matches (union-find); a track seeing one image twice is dropped;
- points: multi-view Gauss-Newton triangulation; observations reprojecting over
  ``max_error_px`` are dropped once; a point needs ``min_track_length`` observations and a
  triangulation angle of ``min_angle_deg``.

The result is a ``Reconstruction`` with the same cameras and images whose observations are the
corners of the tracks, so the descriptor stage assigns each point the very corner it comes from.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np

from ..cameras import Camera
from ..config import StrictModel
from ..errors import BuildCancelled
from ..features.daisy import RAW_DIM, DaisyExtractor
from ..features.harris import detect_corners
from ..io.colmap import Image, Point3D, Reconstruction
from ..transforms import Rigid3d
from .desc_store import RawStore

Progress = Callable[[str, float, str], None]


# In mode "add" the Harris points' ids start here, apart from any id the SfM front end gives
# (its kept work folder holds points that filtering removed, with ids above the map's largest):
# an id below this names the same SfM point in the bundle and in that folder (the bench's SIFT
# peer relies on it).
HARRIS_POINT_ID_BASE = 1 << 32


class HarrisPointsConf(StrictModel):
    # On in the builder's default preset (mode "add"). Measured (2 cores at load 12-18; the
    # engine replayed in-process, errors against the ground truth; off -> add):
    # - redkitchen, map from every 10th frame (1000 frames): points 10971 -> 15561, descriptors
    #   110k -> 234k; median error 0.47 -> 0.34 cm, mean 0.68 -> 0.48 cm; within 5 cm / 5 deg
    #   96.7% -> 99.8%; localized 97.2% -> 100%; wrong poses 1 -> 0; median inliers 49 -> 65;
    #   matched corners' offset from their points' projections at the true pose 1.34 -> 0.84 px;
    #   CPU per frame x0.85 (300 frames, maps interleaved frame by frame, load 6).
    # - redkitchen every 60th frame (17 images, 300 frames): points 2471 -> 2949; median 0.68 ->
    #   0.55 cm, localized 89.7% -> 100%, within 5 cm / 5 deg 89.0% -> 100%; single-image
    #   relocalization of 40 non-map frames 35 -> 38, 0 wrong.
    # - synthetic walk (exact model, 120 views, 300 frames): median 0.40 -> 0.33 cm, within 5 cm
    #   / 5 deg 96.7% -> 98.7%; localized 100% -> 98.7% (4 poses withheld for their covariance,
    #   frames 80-83, where the off map's poses were 5-12 cm off); flight (same map) median
    #   0.26 -> 0.27 cm (a tie), mean 0.43 -> 0.35 cm, localized and within 99.7% -> 100%.
    # Mode "replace" (Harris points only): every 10th 4590 points, median 0.36 cm, within 99.8%;
    # synthetic walk 0.27 cm, within 100%; but every 60th 478 points, median 0.76 cm: a thin map
    # keeps few tracks of three views.
    # Remeasured with `sfmloc replay` at main 0dcd86a (the engine's covariance calibration and
    # recovery changes): redkitchen every 10th 0.49 -> 0.34 cm, within 97.7% -> 99.5%, localized
    # 97.7% -> 99.8%; every 60th 0.74 -> 0.55 cm, localized 94.3% -> 100%; synthetic walk 0.41
    # -> 0.34 cm, within 95.7% -> 99.0%; flight 0.26 -> 0.31 cm median (worse), mean 0.44 ->
    # 0.37 cm. The map's scene_scale (median depth) grows with the Harris points (synthetic 2.37
    # -> 2.71). min_angle_deg 2 instead of 1: redkitchen 0.37 cm, synthetic walk 0.37 cm (worse).
    # The stage adds about 30 s per 100 images of 640x480 (the pairwise matching).
    enabled: bool = False
    # "add": beside the SfM points (a corner goes to the nearest projection, so the Harris
    # point takes the descriptors at its corner); "replace": the Harris points only.
    mode: Literal["replace", "add"] = "add"
    neighbors: int = 8  # images matched with each image (most shared SfM points first)
    min_shared_points: int = 10  # a pair must share this many SfM points
    max_corners: int = 4000  # strongest corners per image
    epipolar_px: float = 1.5
    ratio: float = 0.8  # best / second-best DAISY distance among the epipolar candidates
    max_descriptor_distance: float = 0.7  # raw DAISY is unit length: 0 same, 1.41 orthogonal
    depth_margin: float = 1.5  # depths within [min / m, max * m] of the image's SfM points
    max_error_px: float = 1.0
    # Two-view tracks include wrong matches that lie on the epipolar line and so triangulate
    # exactly: on the synthetic room 12% of two-view points are off the surface by > 2% of
    # their depth, 0.3% of the longer ones. Redkitchen: 3 -> 2 gives as many points again
    # (8750) for the same accuracy (median 0.36 cm).
    min_track_length: int = 3
    # A thin map keeps two-view tracks too: when the median image would see fewer than this
    # many points (the SfM points in mode "add" and the Harris points of min_track_length
    # views), as the known-poses SfM does (SfmConf.two_view_below). 0: never. Robust
    # density-6x (synthetic room, 20 mapping views 6 apart; median 72 points per image): 777
    # -> 2287 points, replay of 300 frames: median error 0.0197 -> 0.0092 units, localized
    # 237 -> 242, 0 wrong both.
    two_view_below: int = 150
    # Keep two-view tracks whatever the count (set by the builder for known poses, below).
    keep_two_view: bool = False
    # Known poses: keep two-view tracks when the SfM stage kept two-view points (its median
    # image saw fewer than SfmConf.two_view_below points of 3+ views, or --min-track-length 2).
    # Robust redkitchen every 30th frame (34 images; SfM median 614 points per image, 3425 of
    # 5882 SfM points two-view): 6988 -> 8877 points, replay of 300 frames median 0.00520 ->
    # 0.00375 units, on the peer's 20 frames 0.00466 -> 0.00338 (peer 0.00276), 300/300
    # localized, 0 wrong both. The same on the synthetic walk's COLMAP model (120 views, median
    # 433) was mixed (medians on the peer's 20 frames: orbit 10 Hz 0.00227 -> 0.00159, walk
    # 3 Hz 0.00147 -> 0.00179, walk 30 Hz 0.00178 -> 0.00190): COLMAP inputs keep the
    # two_view_below rule only.
    follow_sfm_two_view: bool = True
    min_angle_deg: float = 1.0
    iterations: int = 6
    max_track_length: int = 48  # observations used per point (the first, by image)
    # Tracks extended to the other images where the point projects this close to a corner with
    # a matching DAISY (0: off). Mode replace, 1.0 px: redkitchen every 10th 4590 -> 6034 points,
    # median 0.36 -> 0.33 cm; but synthetic walk 0.27 -> 0.32 cm (within 5 cm / 5 deg 100 ->
    # 98%), redkitchen every 60th 0.76 -> 0.79 cm; mode add, every 60th 0.55 -> 0.60 cm.
    extend_px: float = 0.0


def _fundamental_normalized(pose_a: Rigid3d, pose_b: Rigid3d) -> np.ndarray:
    """Essential matrix E with ``x_b^T E x_a = 0`` for normalized coordinates."""
    R = pose_b.rotation @ pose_a.rotation.T
    t = pose_b.translation - R @ pose_a.translation
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ R


def _line_distances(E: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """(Na, Nb) distances (normalized units) of points b to the epipolar lines of points a."""
    ha = np.c_[xa, np.ones(len(xa))]
    lines = ha @ E.T  # (Na, 3): l = E x_a
    norm = np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-12)
    return np.abs(lines[:, :2] @ xb.T + lines[:, 2:3]) / norm[:, None]


def _midpoint_depths(pose_a: Rigid3d, pose_b: Rigid3d, xa: np.ndarray, xb: np.ndarray) -> tuple:
    """Depths in a and b of the closest points of the two rays (pairs of normalized points)."""
    Ra, Rb = pose_a.rotation, pose_b.rotation
    ca, cb = -Ra.T @ pose_a.translation, -Rb.T @ pose_b.translation
    da = np.c_[xa, np.ones(len(xa))] @ Ra  # world directions (rows: R^T x)
    db = np.c_[xb, np.ones(len(xb))] @ Rb
    w = ca - cb
    a, b, c = (da * da).sum(1), (da * db).sum(1), (db * db).sum(1)
    d, e = da @ w, db @ w
    den = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * e - c * d) / den  # along a (depth, since the direction's z is 1)
        u = (a * e - b * d) / den
    return s, u


def match_pair(
    pose_a: Rigid3d,
    pose_b: Rigid3d,
    xa: np.ndarray,
    xb: np.ndarray,
    da: np.ndarray,
    db: np.ndarray,
    focal: float,
    depth_a: tuple[float, float],
    depth_b: tuple[float, float],
    conf: HarrisPointsConf,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index pairs (ia, ib) of mutual best epipolar-consistent DAISY matches between the corners
    of two posed images (``xa``, ``xb``: undistorted normalized coordinates; ``da``, ``db``:
    unit raw DAISY), and their descriptor distances."""
    none = np.zeros(0, np.int64)
    if len(xa) == 0 or len(xb) == 0:
        return none, none, np.zeros(0)
    E = _fundamental_normalized(pose_a, pose_b)
    tol = conf.epipolar_px / focal
    ia_list, ib_list = [], []
    for s in range(0, len(xa), 1024):  # bounded (1024, Nb) temporaries
        d_ab = _line_distances(E, xa[s : s + 1024], xb)
        ia, ib = np.nonzero(d_ab < tol)
        ia_list.append(ia + s)
        ib_list.append(ib)
    ia, ib = np.concatenate(ia_list), np.concatenate(ib_list)
    if len(ia) == 0:
        return none, none, np.zeros(0)
    # Symmetric: a within the band of b's line too.
    lb = np.c_[xb[ib], np.ones(len(ib))] @ E  # l' = E^T x_b (rows)
    dist_ba = np.abs((lb[:, :2] * xa[ia]).sum(1) + lb[:, 2]) / np.maximum(
        np.hypot(lb[:, 0], lb[:, 1]), 1e-12
    )
    za, zb = _midpoint_depths(pose_a, pose_b, xa[ia], xb[ib])
    m = dist_ba < tol
    m &= (za > depth_a[0] / conf.depth_margin) & (za < depth_a[1] * conf.depth_margin)
    m &= (zb > depth_b[0] / conf.depth_margin) & (zb < depth_b[1] * conf.depth_margin)
    ia, ib = ia[m], ib[m]
    if len(ia) == 0:
        return none, none, np.zeros(0)
    dist = np.sqrt(
        np.maximum(
            2.0 - 2.0 * np.einsum("ij,ij->i", da[ia].astype(np.float32), db[ib].astype(np.float32)),
            0.0,
        )
    )
    best_a, ratio_a = _best_per_group(ia, dist, len(xa))
    best_b, ratio_b = _best_per_group(ib, dist, len(xb))
    # a candidate pair k is kept when it is the best of both its corners, passes both ratios
    k = np.arange(len(ia))
    keep = (best_a[ia] == k) & (best_b[ib] == k) & (dist < conf.max_descriptor_distance)
    keep &= (ratio_a[ia] < conf.ratio) & (ratio_b[ib] < conf.ratio)
    return ia[keep], ib[keep], dist[keep]


def _best_per_group(group: np.ndarray, dist: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per group id: the index (into ``dist``) of its smallest distance (-1 if none), and the
    ratio best / second best (0 with a single candidate)."""
    order = np.lexsort((dist, group))
    g = group[order]
    first = np.ones(len(g), bool)
    first[1:] = g[1:] != g[:-1]
    best = np.full(n, -1, np.int64)
    best[g[first]] = order[first]
    second = np.full(n, np.inf)
    has2 = np.zeros(len(g), bool)
    has2[1:] = first[:-1] & ~first[1:]  # the element right after a group's first
    second[g[has2]] = dist[order[has2]]
    d1 = np.full(n, np.inf)
    d1[g[first]] = dist[order[first]]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(np.isfinite(second), d1 / np.maximum(second, 1e-12), 0.0)
    return best, ratio


def _union_find_tracks(
    n_nodes: int, a: np.ndarray, b: np.ndarray, node_img: np.ndarray
) -> np.ndarray:
    """Track label per node from edges (a, b), taken in the given order (best first); an edge
    that would put two corners of one image in a track is skipped (a chain of matches through
    one wrong match would otherwise merge two physical points)."""
    parent = list(range(n_nodes))
    images: dict[int, set[int]] = {}

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    node_img_l = node_img.tolist()
    for u, v in zip(a.tolist(), b.tolist()):
        ru, rv = find(u), find(v)
        if ru == rv:
            continue
        iu = images.get(ru) or {node_img_l[u]}
        iv = images.get(rv) or {node_img_l[v]}
        if iu & iv:
            continue
        lo, hi = min(ru, rv), max(ru, rv)
        parent[hi] = lo
        images[lo] = iu | iv
        images.pop(hi, None)
    return np.array([find(i) for i in range(n_nodes)])


def triangulate_tracks(
    obs: np.ndarray, R: np.ndarray, t: np.ndarray, valid: np.ndarray, iterations: int = 6
) -> np.ndarray:
    """Points (C, 3) from padded observations: ``obs`` (C, M, 2) normalized coordinates in
    cameras ``R`` (C, M, 3, 3), ``t`` (C, M, 3); ``valid`` (C, M). Linear (DLT) start, then
    Gauss-Newton on the normalized reprojection error."""
    w = valid.astype(np.float64)
    P = np.concatenate([R, t[..., None]], axis=3)  # (C, M, 3, 4)
    A = np.concatenate(
        [obs[..., 0:1] * P[..., 2, :] - P[..., 0, :], obs[..., 1:2] * P[..., 2, :] - P[..., 1, :]],
        axis=1,
    )  # (C, 2M, 4)
    A = A * np.concatenate([w, w], axis=1)[..., None]
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1, :]
    X = Xh[:, :3] / np.where(np.abs(Xh[:, 3:4]) > 1e-12, Xh[:, 3:4], 1e-12)
    bad = ~np.all(np.isfinite(X), axis=1)
    X[bad] = 0.0
    for _ in range(iterations):
        pc = np.einsum("cmij,cj->cmi", R, X) + t
        z = np.where(np.abs(pc[..., 2]) > 1e-9, pc[..., 2], 1e-9)
        proj = pc[..., :2] / z[..., None]
        r = (proj - obs) * w[..., None]
        J = (R[..., :2, :] - proj[..., :, None] * R[..., 2:3, :]) / z[..., None, None]
        J = (J * w[..., None, None]).reshape(len(X), -1, 3)
        r = r.reshape(len(X), -1)
        H = np.einsum("cki,ckj->cij", J, J)
        # a small damping keeps near-degenerate (far, low-parallax) points solvable
        H = H + (1e-6 * np.trace(H, axis1=1, axis2=2) + 1e-12)[:, None, None] * np.eye(3)
        g = np.einsum("cki,ck->ci", J, r)
        step = np.linalg.solve(H, g[..., None])[..., 0]
        X = X - np.where(np.isfinite(step), step, 0.0)
    X[bad] = np.nan
    return X


def _errors_px(X, obs, R, t, focal):
    pc = np.einsum("cmij,cj->cmi", R, X) + t
    z = pc[..., 2]
    proj = pc[..., :2] / np.where(np.abs(z) > 1e-9, z, 1e-9)[..., None]
    return np.linalg.norm(proj - obs, axis=2) * focal, z


def harris_points(
    rec: Reconstruction,
    image_dir: Path,
    load_gray: Callable[[Path, Camera], np.ndarray],
    conf: HarrisPointsConf,
    detector: dict,
    progress: Progress | None = None,
    should_cancel: Callable[[], bool] | None = None,
    workdir: str | Path | None = None,
    chunk_tracks: int = 1024,
) -> tuple[Reconstruction, dict]:
    """A reconstruction with the same cameras and images and points triangulated from matched
    Harris corners (``mode`` "add": the SfM points too); and stats. ``detector``: keyword
    arguments of ``detect_corners`` (the descriptor stage's settings). The corners' DAISY
    descriptors wait in a file under ``workdir`` (None: in memory), read back per pair."""
    with RawStore(RAW_DIM, workdir, dtype=np.float16) as store:
        return _harris_points(
            rec, image_dir, load_gray, conf, detector, store, progress, should_cancel, chunk_tracks
        )


def _harris_points(
    rec: Reconstruction,
    image_dir: Path,
    load_gray: Callable[[Path, Camera], np.ndarray],
    conf: HarrisPointsConf,
    detector: dict,
    store: RawStore,
    progress: Progress | None,
    should_cancel: Callable[[], bool] | None,
    chunk_tracks: int,
) -> tuple[Reconstruction, dict]:
    images = sorted(rec.images.values(), key=lambda im: im.name)
    n_img = len(images)
    extractor = DaisyExtractor()
    # Per corner: pixel position, normalized position and gray level (the point's colour);
    # the 104-d descriptors (0.8 MB per image of 4000 corners) go to ``store`` (build memory).
    xy_px, xn, gray_at = [], [], []
    depth_range = []
    for i, im in enumerate(images):
        if should_cancel and should_cancel():
            raise BuildCancelled("cancelled", stage="harris_points")
        cam = rec.cameras[im.camera_id]
        gray = load_gray(image_dir / im.name, cam)
        c = detect_corners(gray, max_corners=conf.max_corners, **detector)
        _, d = extractor.compute(gray, c.xy)
        xy_px.append(c.xy)
        xn.append(cam.cam_from_img(c.xy))
        store.append(d.astype(np.float16))
        ix = np.minimum(c.xy[:, 0].astype(int), gray.shape[1] - 1)
        iy = np.minimum(c.xy[:, 1].astype(int), gray.shape[0] - 1)
        gray_at.append(gray[iy, ix])
        ids = im.point3D_ids[im.point3D_ids >= 0]
        pts = np.array([rec.points3D[int(p)].xyz for p in ids if int(p) in rec.points3D]).reshape(
            -1, 3
        )
        z = im.cam_from_world.apply(pts)[:, 2] if len(pts) else np.zeros(0)
        z = z[z > 0]
        depth_range.append(
            (float(np.percentile(z, 1)), float(np.percentile(z, 99))) if len(z) else (1e-6, 1e9)
        )
        if progress:
            progress("harris_points", 0.4 * (i + 1) / n_img, f"{im.name}: {len(c)} corners")
    pairs_sorted = _pairs_by_shared_points(rec, images, conf)
    offset = np.zeros(n_img + 1, np.int64)
    offset[1:] = np.cumsum([len(x) for x in xy_px])
    # Pairs come sorted by first image: a few images' descriptors are enough at a time.
    cache: OrderedDict[int, np.ndarray] = OrderedDict()

    def desc_of(k: int) -> np.ndarray:
        if k not in cache:
            cache[k] = store.read(offset[k], offset[k + 1])
            if len(cache) > 2 * conf.neighbors + 2:
                cache.popitem(last=False)
        cache.move_to_end(k)
        return cache[k]

    ea, eb, ed = [], [], []
    for k, (i, j) in enumerate(pairs_sorted):
        if should_cancel and should_cancel():
            raise BuildCancelled("cancelled", stage="harris_points")
        ci, cj = rec.cameras[images[i].camera_id], rec.cameras[images[j].camera_id]
        focal = 0.5 * (sum(ci.focal) + sum(cj.focal)) / 2
        ia, ib, dist = match_pair(
            images[i].cam_from_world,
            images[j].cam_from_world,
            xn[i],
            xn[j],
            desc_of(i),
            desc_of(j),
            focal,
            depth_range[i],
            depth_range[j],
            conf,
        )
        ea.append(ia + offset[i])
        eb.append(ib + offset[j])
        ed.append(dist)
        if progress and (k + 1) % 20 == 0:
            progress(
                "harris_points",
                0.4 + 0.4 * (k + 1) / len(pairs_sorted),
                f"{k + 1} of {len(pairs_sorted)} pairs",
            )
    a = np.concatenate(ea) if ea else np.zeros(0, np.int64)
    b = np.concatenate(eb) if eb else np.zeros(0, np.int64)
    order = np.argsort(np.concatenate(ed), kind="stable") if ed else np.zeros(0, np.int64)
    del ed
    cache.clear()
    a, b = a[order], b[order]
    node_img = np.repeat(np.arange(n_img, dtype=np.int32), np.diff(offset))
    # Only corners in some match take part (a small part of all corners): the union-find runs
    # over those, renumbered in order, so each track's label is still its smallest corner id.
    nodes, inv = np.unique(np.concatenate([a, b]), return_inverse=True)
    label = nodes[_union_find_tracks(len(nodes), inv[: len(a)], inv[len(a) :], node_img[nodes])]
    # Nodes in tracks of >= 2, grouped by track; drop tracks seeing an image twice.
    order = np.lexsort((node_img[nodes], label))
    nodes, lab = nodes[order], label[order]
    img = node_img[nodes]
    dup = np.zeros(len(nodes), bool)
    dup[1:] = (lab[1:] == lab[:-1]) & (img[1:] == img[:-1])
    bad = np.unique(lab[dup])
    keep = ~np.isin(lab, bad)
    nodes, lab, img = nodes[keep], lab[keep], img[keep]
    uniq, start, counts = np.unique(lab, return_index=True, return_counts=True)
    stats = {
        "corners": int(offset[-1]),
        "pairs": len(pairs_sorted),
        "matches": int(len(a)),
        "tracks": int(len(uniq)),
        "tracks_conflicting": int(len(bad)),
    }
    geo = {
        "R": np.stack([im.cam_from_world.rotation for im in images]),
        "t": np.stack([im.cam_from_world.translation for im in images]),
        "f": np.array([0.5 * sum(rec.cameras[im.camera_id].focal) for im in images]),
        "c": np.stack([im.cam_from_world.center for im in images]),
        "xn": np.concatenate(xn) if xn else np.zeros((0, 2)),
    }
    del xn
    tracks = np.split(nodes, start[1:]) if len(nodes) else []
    if conf.extend_px > 0:
        # two-view tracks too: extended, they may reach min_track_length
        pts_xyz, obs_nodes, _ = _solve(
            tracks, node_img, geo, conf.model_copy(update={"min_track_length": 2}), chunk_tracks
        )
        # what the points that already have min_track_length views observe
        stats["observations_before_extension"] = int(
            sum(len(o) for o in obs_nodes if len(o) >= max(2, conf.min_track_length))
        )
        desc_all = store.read(0, len(store))  # all corners' descriptors (extension only)
        obs_nodes = _extend(
            pts_xyz, obs_nodes, node_img, xy_px, offset, desc_all, images, rec, conf
        )
        del desc_all
    else:
        obs_nodes = tracks
    base = _sfm_points_per_image(rec, images) if conf.mode == "add" else np.zeros(n_img)
    pts_xyz, obs_nodes, thin_stats = _solve_kept(obs_nodes, node_img, geo, conf, base, chunk_tracks)
    stats.update(thin_stats)
    stats["points"] = len(pts_xyz)
    stats["observations"] = int(sum(len(o) for o in obs_nodes))
    if progress:
        progress(
            "harris_points", 1.0, f"{len(pts_xyz)} Harris points from {stats['tracks']} tracks"
        )
    return _reconstruction(
        rec, images, pts_xyz, obs_nodes, node_img, xy_px, offset, gray_at, conf
    ), stats


def _pairs_by_shared_points(
    rec: Reconstruction, images: list[Image], conf: HarrisPointsConf
) -> list[tuple[int, int]]:
    """Each image with its ``neighbors`` images sharing most SfM points (at least
    ``min_shared_points``), as sorted index pairs (i < j). The counts are a sparse
    image-by-image matrix (a dense one is 8 B * images^2: 800 MB at 10,000 images); each row is
    made dense only to rank it, as before."""
    from scipy import sparse

    n_img = len(images)
    index_of = {im.image_id: i for i, im in enumerate(images)}
    rows, cols = [], []
    for r, p in enumerate(rec.points3D.values()):
        ii = np.unique([index_of[int(x)] for x in p.track_image_ids if int(x) in index_of])
        rows.append(np.full(len(ii), r, np.int64))
        cols.append(ii.astype(np.int64))
    n_pts = len(rows)
    r_all = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    c_all = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    seen = sparse.csr_matrix((np.ones(len(r_all), np.int64), (r_all, c_all)), shape=(n_pts, n_img))
    shared = (seen.T @ seen).tocsr()
    shared.setdiag(0)
    pairs = set()
    for i in range(n_img):
        row = shared.getrow(i).toarray()[0]
        order = np.argsort(-row)[: conf.neighbors]
        for j in order:
            if row[j] >= conf.min_shared_points:
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _sfm_points_per_image(rec: Reconstruction, images: list[Image]) -> np.ndarray:
    """Per image, how many of its observations are points of ``rec``."""
    return np.array(
        [sum(1 for p in im.point3D_ids.tolist() if p >= 0 and p in rec.points3D) for im in images],
        np.float64,
    )


def _solve_kept(
    tracks: list[np.ndarray],
    node_img: np.ndarray,
    geo: dict,
    conf: HarrisPointsConf,
    per_image_base: np.ndarray,
    chunk_tracks: int = 1024,
) -> tuple[np.ndarray, list[np.ndarray], dict[str, int]]:
    """The points of ``tracks`` (in track order) and their observations: the points of
    ``min_track_length`` views, and the two-view ones too when the map is thin (the median
    image sees fewer than ``two_view_below`` of those and ``per_image_base``, its SfM points in
    mode "add") or ``keep_two_view``. Tracks of fewer views than ``min_track_length`` can only
    give such short points: they are solved only when those are kept (on redkitchen every 10th,
    not thin, most tracks are two-view). Each track's solve is its own (with the same padding
    M), so the points are those of solving all tracks and dropping the short ones after."""
    min_len = max(2, conf.min_track_length)
    conf2 = conf.model_copy(update={"min_track_length": 2})
    M = min(max((len(tr) for tr in tracks), default=0), conf.max_track_length)
    is_long = np.array([len(tr) >= min_len for tr in tracks], bool)
    long_in = np.nonzero(is_long)[0]
    pts_l, obs_l, src_l = _solve(
        [tracks[i] for i in long_in], node_img, geo, conf2, chunk_tracks, M
    )
    src_l = long_in[src_l]
    long = np.array([len(o) >= min_len for o in obs_l], bool)
    per_image = per_image_base.astype(np.float64, copy=True)
    for o in (o for o, k in zip(obs_l, long) if k):
        per_image[node_img[o]] += 1
    median = float(np.median(per_image)) if len(per_image) else 0.0
    kept = int(conf.keep_two_view or (len(per_image) > 0 and median < conf.two_view_below))
    stats = {"median_points_per_image_long": int(round(median)), "two_view_kept": kept}
    if not kept:
        return pts_l[long], [o for o, k in zip(obs_l, long) if k], stats
    short_in = np.nonzero(~is_long)[0]
    pts_s, obs_s, src_s = _solve(
        [tracks[i] for i in short_in], node_img, geo, conf2, chunk_tracks, M
    )
    # back to track order (the points' ids, so the bundle is what one solve of all gave)
    order = np.argsort(np.concatenate([src_l, short_in[src_s]]), kind="stable")
    obs_all = obs_l + obs_s
    return np.concatenate([pts_l, pts_s])[order], [obs_all[i] for i in order], stats


def _solve(
    tracks: list[np.ndarray],
    node_img: np.ndarray,
    geo: dict,
    conf: HarrisPointsConf,
    chunk_tracks: int = 1024,
    M: int | None = None,
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Triangulate tracks (arrays of corner node ids); drop observations over 3x then 1x
    ``max_error_px`` (re-solving after each); keep points with ``min_track_length``
    observations in front of their cameras and ``min_angle_deg``. Returns (P, 3) points, their
    kept node arrays and the indices of their tracks in ``tracks``. Tracks are solved
    ``chunk_tracks`` at a time: the padded arrays cost up to 70 KB per track (M = 48: rotations,
    the M x M ray angles, temporaries); each track's solve is its own and M (default: the
    longest track's length, at most ``max_track_length``) is the same for all chunks, so
    chunking changes no result."""
    if not tracks:
        return np.zeros((0, 3)), [], np.zeros(0, np.int64)
    if M is None:
        M = min(max(len(tr) for tr in tracks), conf.max_track_length)
    xs, kept, src = [], [], []
    for s in range(0, len(tracks), max(1, chunk_tracks)):
        X, nodes, idx = _solve_chunk(tracks[s : s + chunk_tracks], M, node_img, geo, conf)
        xs.append(X)
        kept.extend(nodes)
        src.append(idx + s)
    return np.concatenate(xs), kept, np.concatenate(src)


def _solve_chunk(
    tracks: list[np.ndarray], M: int, node_img: np.ndarray, geo: dict, conf: HarrisPointsConf
):
    n_obs = np.array([min(len(tr), M) for tr in tracks])
    valid = np.arange(M)[None, :] < n_obs[:, None]
    node = np.zeros((len(tracks), M), np.int64)
    for c, tr in enumerate(tracks):
        node[c, : n_obs[c]] = tr[:M]
        node[c, n_obs[c] :] = tr[0]
    im_i = node_img[node]
    R, t, f = geo["R"][im_i], geo["t"][im_i], geo["f"][im_i]
    obs = geo["xn"][node]
    min_len = max(2, conf.min_track_length)
    X = np.zeros((len(tracks), 3))
    src = np.arange(len(tracks))
    for limit in (3 * conf.max_error_px, conf.max_error_px, None):
        ok = valid.sum(1) >= min_len
        X, obs, R, t, f, valid, node, im_i, src = (
            a[ok] for a in (X, obs, R, t, f, valid, node, im_i, src)
        )
        if len(X) == 0:  # every track of the chunk too short
            return np.zeros((0, 3)), [], np.zeros(0, np.int64)
        X = triangulate_tracks(obs, R, t, valid, conf.iterations)
        err, z = _errors_px(X, obs, R, t, f)
        if limit is not None:
            valid = valid & (err < limit)
    valid = valid & (err < conf.max_error_px) & (z > 0)
    good = valid.sum(1) >= min_len
    rays = X[:, None, :] - geo["c"][im_i]
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-12)
    cos = np.einsum("cmi,cni->cmn", rays, rays)
    cos = np.where(valid[:, :, None] & valid[:, None, :], cos, 1.0)
    good &= np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1, 1))) >= conf.min_angle_deg
    good &= np.all(np.isfinite(X), axis=1)
    return X[good], [node[c][valid[c]] for c in np.nonzero(good)[0]], src[good]


def _extend(
    X: np.ndarray,
    tracks: list[np.ndarray],
    node_img: np.ndarray,
    xy_px: list[np.ndarray],
    offset: np.ndarray,
    desc: np.ndarray,
    images: list[Image],
    rec: Reconstruction,
    conf: HarrisPointsConf,
) -> list[np.ndarray]:
    """Tracks extended to every image where the point projects within ``extend_px`` of a free
    corner whose DAISY is within ``max_descriptor_distance`` of the track's mean descriptor
    (pairwise matching only links images chosen as neighbours, and a point's track decides its
    triangulation angle, descriptors and visibility). A corner claimed by several points goes
    to the nearest projection."""
    from scipy.spatial import cKDTree

    desc_all = desc.astype(np.float32)
    mean = (
        np.stack([desc_all[tr].mean(0) for tr in tracks])
        if tracks
        else np.zeros((0, desc_all.shape[1]))
    )
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    used = np.zeros(len(desc_all), bool)
    seen = [set(node_img[tr].tolist()) for tr in tracks]
    for tr in tracks:
        used[tr] = True
    cand_p, cand_n, cand_d = [], [], []
    for k, im in enumerate(images):
        if len(xy_px[k]) == 0:
            continue
        cam = rec.cameras[im.camera_id]
        uv, z = cam.project(im.cam_from_world, X)
        ok = np.nonzero((z > 0) & cam.in_image(uv))[0]
        ok = np.array([p for p in ok.tolist() if k not in seen[p]], np.int64)
        if len(ok) == 0:
            continue
        d, j = cKDTree(xy_px[k]).query(uv[ok], k=1, distance_upper_bound=conf.extend_px)
        hit = np.isfinite(d)
        p, n, d = ok[hit], j[hit] + offset[k], d[hit]
        free = ~used[n]
        p, n, d = p[free], n[free], d[free]
        dd = np.sqrt(np.maximum(2.0 - 2.0 * np.einsum("ij,ij->i", mean[p], desc_all[n]), 0.0))
        m = dd < conf.max_descriptor_distance
        cand_p.append(p[m])
        cand_n.append(n[m])
        cand_d.append(d[m])
    if not cand_p:
        return tracks
    p, n, d = np.concatenate(cand_p), np.concatenate(cand_n), np.concatenate(cand_d)
    order = np.argsort(d, kind="stable")
    p, n = p[order], n[order]
    _, first = np.unique(n, return_index=True)  # each corner to its nearest projection
    add: list[list[int]] = [[] for _ in tracks]
    for pp, nn in zip(p[first].tolist(), n[first].tolist()):
        add[pp].append(nn)
    return [
        np.concatenate([tr, np.array(ad, np.int64)]) if ad else tr for tr, ad in zip(tracks, add)
    ]


def _reconstruction(
    rec, images, pts_xyz, obs_nodes, node_img, xy_px, offset, gray_at, conf
) -> Reconstruction:
    """The new reconstruction: images keep their poses; their observations are the corners of
    the Harris points (and, in "add" mode, their SfM observations)."""
    first_id = 1
    if conf.mode == "add":
        first_id = max(HARRIS_POINT_ID_BASE, max(rec.points3D, default=0) + 1)
    per_img_xy: list[list[np.ndarray]] = [[] for _ in images]
    per_img_id: list[list[np.ndarray]] = [[] for _ in images]
    points: dict[int, Point3D] = {}
    if conf.mode == "add":
        points.update(rec.points3D)
        for k, im in enumerate(images):
            per_img_xy[k].append(im.points2D)
            per_img_id[k].append(im.point3D_ids)
    n_obs = [sum(len(a) for a in per_img_xy[k]) for k in range(len(images))]
    for p, nodes in enumerate(obs_nodes):
        pid = first_id + p
        imgs = node_img[nodes]
        tr_i, tr_k = [], []
        for n, k in zip(nodes.tolist(), imgs.tolist()):
            xy = xy_px[k][n - offset[k]]
            tr_i.append(images[k].image_id)
            tr_k.append(n_obs[k])
            n_obs[k] += 1
            per_img_xy[k].append(xy[None, :])
            per_img_id[k].append(np.array([pid]))
        k0, n0 = int(imgs[0]), int(nodes[0])
        g = int(gray_at[k0][n0 - offset[k0]])
        points[pid] = Point3D(
            pid, pts_xyz[p], np.array([g, g, g], np.uint8), 0.0, np.array(tr_i), np.array(tr_k)
        )
    new_images = {}
    for k, im in enumerate(images):
        xy = np.concatenate(per_img_xy[k]) if per_img_xy[k] else np.zeros((0, 2))
        ids = np.concatenate(per_img_id[k]) if per_img_id[k] else np.zeros(0, np.int64)
        new_images[im.image_id] = Image(
            im.image_id, im.name, im.camera_id, im.cam_from_world, xy, ids
        )
    return Reconstruction(cameras=dict(rec.cameras), images=new_images, points3D=points)
