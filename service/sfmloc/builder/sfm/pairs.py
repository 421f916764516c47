"""Image pairs for known poses, chosen by geometry: baseline, viewing angle and frustum overlap.

Why: in 30 Hz video each image's nearest cameras are a few millimetres to centimetres away
(redkitchen: 7.5 mm per frame, scene depth ~1.5 m). Matching only those (the old rule: 5
nearest plus the next 2 in sequence) gave pairs whose triangulation angle is almost always
under the 1.5 deg filter (99% of the every-frame pairs), so adding frames *removed* points.

The geometric selector gives every image a fixed budget of partners, whatever the frame rate:

- ``near`` partners: the nearest cameras (centre distance) that look the same way (within
  ``max_angle_deg``): robust matching that links the image into tracks.
- one partner per target triangulation angle (``angles_deg``, e.g. 2.5, 5, 10, 20 deg): among
  cameras that look the same way and whose frustum covers at least ``min_overlap`` of this
  image's view at its scene depth, the one whose angle at that depth is nearest the target
  (within a factor sqrt(2)). Wide pairs give the triangulation angle; near pairs keep the
  tracks that join them, so redundant frames add observations to points instead of splitting
  them.

The angle and the overlap need each image's scene depth, which the poses alone do not give:
``depths_from_matches`` estimates it from the verified matches of the near pairs (matched
first), as the median inverse depth of their rays triangulated at the known poses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pycolmap

from ...cameras import Camera
from ...transforms import Rigid3d

# Grid of image points (per side) whose frustum points are tested in the other camera.
OVERLAP_GRID = 6
# A per-image depth needs this many matched rays, mostly in front (else the median is used).
MIN_DEPTH_SAMPLES = 20
MIN_FRONT_FRACTION = 0.7


def _stack(cam_from_worlds: Sequence[Rigid3d]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotations (n, 3, 3), translations (n, 3), centres (n, 3)."""
    R = np.array([T.rotation for T in cam_from_worlds], dtype=np.float64).reshape(-1, 3, 3)
    t = np.array([T.translation for T in cam_from_worlds], dtype=np.float64).reshape(-1, 3)
    C = -np.einsum("nji,nj->ni", R, t)
    return R, t, C


def near_pairs(
    cam_from_worlds: Sequence[Rigid3d], near: int, max_angle_deg: float
) -> set[tuple[int, int]]:
    """Each image with its ``near`` nearest cameras (centre distance) whose viewing direction
    is within ``max_angle_deg``; index pairs (a < b)."""
    R, _, C = _stack(cam_from_worlds)
    V = R[:, 2, :]  # optical axes in world
    cos_max = math.cos(math.radians(max_angle_deg))
    n = len(C)
    pairs: set[tuple[int, int]] = set()
    if near <= 0:
        return pairs
    for i in range(n):
        d = np.linalg.norm(C - C[i], axis=1)
        ok = V @ V[i] >= cos_max
        ok[i] = False
        cand = np.flatnonzero(ok)
        for j in cand[np.argsort(d[cand], kind="stable")][:near]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return pairs


def frustum_overlap(
    camera: Camera,
    cam_from_worlds: Sequence[Rigid3d],
    i: int,
    depth: float,
    grid: int = OVERLAP_GRID,
) -> np.ndarray:
    """For every camera j: the fraction of image ``i``'s view at ``depth`` (a grid of image
    points lifted to that depth) that projects inside camera j's image in front of it. (n,)"""
    R, t, _ = _stack(cam_from_worlds)
    w, h = camera.size
    u, v = np.meshgrid((np.arange(grid) + 0.5) * w / grid, (np.arange(grid) + 0.5) * h / grid)
    xy = camera.cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1))
    Xc = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) * depth  # z = depth in camera i
    Xw = (Xc - t[i]) @ R[i]  # world_from_cam: R^T (x - t)
    pc = np.einsum("nij,mj->nmi", R, Xw) + t[:, None, :]  # (n, m, 3)
    z = pc[..., 2]
    fx, fy = camera.focal
    cx, cy = camera.principal_point
    zs = np.where(z > 1e-9, z, 1.0)
    px = fx * pc[..., 0] / zs + cx
    py = fy * pc[..., 1] / zs + cy
    inside = (z > 1e-9) & (px >= 0) & (px <= w) & (py >= 0) & (py <= h)
    return inside.mean(axis=1)


def triangulation_angles_deg(
    cam_from_worlds: Sequence[Rigid3d], i: int, depth: float
) -> np.ndarray:
    """For every camera j: the angle (deg) between the rays from image ``i``'s and j's centres
    to the point on ``i``'s optical axis at ``depth``. (n,)"""
    R, _, C = _stack(cam_from_worlds)
    X = C[i] + depth * R[i, 2]
    a = X - C[i]
    b = X - C
    cos = (b @ a) / np.maximum(np.linalg.norm(b, axis=1) * np.linalg.norm(a), 1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def wide_pairs(
    camera: Camera,
    cam_from_worlds: Sequence[Rigid3d],
    depths: Sequence[float] | np.ndarray,
    angles_deg: Sequence[float],
    min_overlap: float,
    max_angle_deg: float,
) -> set[tuple[int, int]]:
    """Each image with one partner per target triangulation angle (see the module docstring);
    index pairs (a < b)."""
    R, _, C = _stack(cam_from_worlds)
    V = R[:, 2, :]
    cos_max = math.cos(math.radians(max_angle_deg))
    pairs: set[tuple[int, int]] = set()
    band = math.sqrt(2.0)
    # An image chosen by others stops being a candidate at twice the budget: at the ends of a
    # walk every view would otherwise pick the same farthest one.
    degree = np.zeros(len(C), dtype=np.int64)
    cap = 2 * len(angles_deg)
    for i in range(len(C)):
        d = float(depths[i])
        if not (math.isfinite(d) and d > 0):
            continue
        ok = V @ V[i] >= cos_max
        ok[i] = False
        if not ok.any():
            continue
        overlap = frustum_overlap(camera, cam_from_worlds, i, d)
        angle = triangulation_angles_deg(cam_from_worlds, i, d)
        ok &= overlap >= min_overlap
        mine = np.zeros(len(C), dtype=bool)  # partners i already has (chosen by them)
        for a, b in pairs:
            if i in (a, b):
                mine[a + b - i] = True
        for target in angles_deg:
            in_band = ok & (angle >= target / band) & (angle < target * band)
            if (in_band & mine).any():
                continue  # a partner at this angle already (it chose i)
            sel = np.flatnonzero(in_band & (degree < cap))
            if len(sel) == 0:
                continue
            # the angle nearest the target (ranking by overlap instead made hubs of the
            # ends of a walk, where many views tie at the grid's coarse overlap steps)
            j = int(sel[np.argmin(np.abs(np.log(angle[sel] / target)))])
            pairs.add((min(i, j), max(i, j)))
            degree[[i, j]] += 1
            mine[j] = True
    return pairs


def depths_from_matches(
    db_path: str | Path,
    names: Sequence[str],
    cam_from_worlds: Sequence[Rigid3d],
    camera: Camera,
    pairs: Sequence[tuple[int, int]],
) -> np.ndarray:
    """Per image, the scene depth (along its optical axis, in pose units) from the verified
    matches of ``pairs`` (indices into ``names``) in the COLMAP database, triangulated at the
    given poses: 1 / median inverse depth, which is unbiased by the noise of short baselines.
    Images without enough matched rays get the median of the others; NaN when none has any."""
    R, _, C = _stack(cam_from_worlds)
    samples: list[list[np.ndarray]] = [[] for _ in names]
    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {im.name: int(im.image_id) for im in db.read_all_images()}
        kps: dict[int, np.ndarray] = {}

        def rays(k: int, idx: np.ndarray) -> np.ndarray:
            if k not in kps:
                xy = np.asarray(db.read_keypoints(ids[names[k]]), dtype=np.float64)[:, :2]
                uv = camera.cam_from_img(xy)
                kps[k] = np.concatenate([uv, np.ones((len(uv), 1))], axis=1)
            return kps[k][idx]

        for a, b in pairs:
            ia, ib = ids.get(names[a]), ids.get(names[b])
            if ia is None or ib is None or not db.exists_two_view_geometry(ia, ib):
                continue
            m = np.asarray(db.read_two_view_geometry(ia, ib).inlier_matches, dtype=np.int64)
            if len(m) == 0:
                continue
            ra, rb = rays(a, m[:, 0]), rays(b, m[:, 1])
            samples[a].append(_inverse_depths(ra, rb, R[a], R[b], C[a], C[b]))
            samples[b].append(_inverse_depths(rb, ra, R[b], R[a], C[b], C[a]))
    finally:
        db.close()
    out = np.full(len(names), np.nan)
    for k, s in enumerate(samples):
        if not s:
            continue
        inv = np.concatenate(s)
        inv = inv[np.isfinite(inv)]
        if len(inv) >= MIN_DEPTH_SAMPLES and np.mean(inv > 0) >= MIN_FRONT_FRACTION:
            out[k] = 1.0 / float(np.median(inv))
    good = np.isfinite(out)
    if good.any():
        out[~good] = float(np.median(out[good]))
    return out


def _inverse_depths(
    ra: np.ndarray, rb: np.ndarray, Ra: np.ndarray, Rb: np.ndarray, Ca: np.ndarray, Cb: np.ndarray
) -> np.ndarray:
    """Inverse z-depths in camera a of the points seen along rays ``ra`` (camera a,
    normalized (x, y, 1)) and ``rb`` (camera b). With unit world directions u, w and baseline
    b, w x u = rho (w x b) for rho = 1/distance along u: least squares in rho is linear in the
    rays' noise, so the median is unbiased even for millimetre baselines."""
    u = ra @ Ra  # world directions R^T r
    w = rb @ Rb
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    wxb = np.cross(w, Cb - Ca)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.sum(np.cross(w, u) * wxb, axis=1) / np.sum(wxb * wxb, axis=1)
    return rho * np.linalg.norm(ra, axis=1)  # z = distance / |ra|
