"""Re-triangulate map points at the keypoints the engine will see (a builder stage).

SfM places a 3D point where its SfM features were (SIFT blobs); the paper then assigns every
Harris corner within tau = 2 px of the point's projection to it. Online, the engine's 2D
observation of that point is a Harris corner, not the SIFT blob, so every 2D-3D match carries a
systematic offset of up to tau (and Harris' own inward bias at corners), which limits pose
accuracy. This stage moves each point to where its own level-0 (full-resolution) Harris
keypoints triangulate, with the image poses fixed, so map and online detector agree:

- a point needs observations in at least two images and a triangulation angle of at least
  ``min_angle_deg``;
- Gauss-Newton on the reprojection error, all points at once (padded, masked);
- the new position is kept only when every observation reprojects within ``max_error_px`` and
  no projection moves more than ``max_shift_px`` (it must stay the same point); else the SfM
  position stays.

Measured: synthetic walk (exact ground truth) median error 0.96 -> 0.48 cm, 0.17 -> 0.10 deg;
redkitchen median 0.68 -> 0.53 cm, mean 1.36 -> 1.01 cm.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from ..cameras import Camera
from ..config import StrictModel
from ..transforms import Rigid3d


class RefineConf(StrictModel):
    enabled: bool = True
    # Pyramid levels whose keypoints are used, relative to the full-resolution level (0;
    # positive: downsampled, negative: upsampled).
    levels: list[int] = [0]
    max_observations: int = 16  # per point
    # Which ones a point seen in more images uses: "first": the first by image order (on a
    # video map the start of its track, a narrow baseline); "spread": the most spread viewing
    # rays (``spread_observations``). Measured on the captured inputs of this stage (the same
    # points, keypoints and poses; only the choice differs), synthetic room with 360 mapping
    # views built from its exact model (2,341 of 19,940 points in more than 16 images):
    # distance to the room's surfaces (exact) of the 2,198 such points both moved, median
    # 0.865 -> 0.780 mm, mean 1.411 -> 1.343, p90 3.32 -> 3.17 (all observations, no cap:
    # 0.760 mm, x4 the stage's CPU); the exact model points among them (276), distance to
    # their true position median 5.53 -> 5.33 mm, mean 5.86 -> 5.64 (the rest of the ~4.6 mm is
    # the Harris corners' own offset, the same for every choice). Redkitchen every 10th frame
    # (168 of 13,327 points in more than 16 images, 159 moved by ~1.2 mm): bench.ab, 1000
    # frames, 2 interleaved runs (nice 19, load 17): 1000/1000 both, median 0.279 -> 0.269 cm,
    # within 5 cm / 5 deg 99.8% both, 0 wrong.
    select: Literal["first", "spread"] = "spread"
    iterations: int = 6
    max_error_px: float = 1.5
    max_shift_px: float = 2.5
    min_angle_deg: float = 1.5


def refine_points(
    points_xyz: np.ndarray,
    desc_point: np.ndarray,
    desc_image: np.ndarray,
    desc_level: np.ndarray,
    desc_xy: np.ndarray,
    image_cameras: list[Camera],
    image_poses: list[Rigid3d],
    conf: RefineConf | None = None,
    full_resolution_level: int = 0,
    chunk_points: int = 1024,
) -> tuple[np.ndarray, np.ndarray]:
    """New point positions (P, 3) and which points moved (P,) bool. ``desc_level`` holds
    pyramid level indices; ``full_resolution_level`` is the index of scale 1 (the builder's
    number of upsampled levels). Points are solved ``chunk_points`` at a time."""
    conf = conf or RefineConf()
    n_pts = len(points_xyz)
    out = np.array(points_xyz, dtype=np.float64, copy=True)
    moved = np.zeros(n_pts, bool)
    sel = np.isin(desc_level, [full_resolution_level + lv for lv in conf.levels])
    if not conf.enabled or not sel.any():
        return out, moved
    P, I, XY = (
        desc_point[sel].astype(np.int64),
        desc_image[sel].astype(np.int64),
        desc_xy[sel].astype(np.float64),
    )
    # Observations in undistorted normalized coordinates; residuals are scaled back to pixels
    # by the focal length.
    uvn = np.empty_like(XY)
    focal = np.empty(len(XY))
    for cam in {id(c): c for c in image_cameras}.values():
        m = np.array([image_cameras[i] is cam for i in I])
        if m.any():
            uvn[m] = cam.cam_from_img(XY[m])
            focal[m] = 0.5 * sum(cam.focal)
    order = np.lexsort((I, P))
    P, I, uvn, focal = P[order], I[order], uvn[order], focal[order]
    # At most one observation per (point, image): the first.
    first = np.ones(len(P), bool)
    first[1:] = (P[1:] != P[:-1]) | (I[1:] != I[:-1])
    P, I, uvn, focal = P[first], I[first], uvn[first], focal[first]
    counts = np.bincount(P, minlength=n_pts)
    geo = (
        np.stack([T.rotation for T in image_poses]),
        np.stack([T.translation for T in image_poses]),
        np.stack([T.center for T in image_poses]),
    )
    if conf.select == "spread" and np.any(counts > conf.max_observations):
        keep = spread_observations(P, I, counts, out, geo[2], conf.max_observations, chunk_points)
        P, I, uvn, focal = P[keep], I[keep], uvn[keep], focal[keep]
        counts = np.bincount(P, minlength=n_pts)
    cand = np.nonzero(counts >= 2)[0]
    if len(cand) == 0:
        return out, moved
    # Points in chunks: the padded (C, M, ...) arrays cost about 4 KB per point (build memory,
    # issue 17); every point's solve is its own, so chunking changes no result.
    start_all = np.searchsorted(P, cand)
    n_obs_all = np.minimum(counts[cand], conf.max_observations)
    step = max(1, int(chunk_points))
    for s in range(0, len(cand), step):
        part = cand[s : s + step]
        keep, X = _refine_chunk(
            out[part], start_all[s : s + step], n_obs_all[s : s + step], I, uvn, focal, geo, conf
        )
        out[part[keep]] = X[keep]
        moved[part[keep]] = True
    return out, moved


def spread_observations(
    P: np.ndarray,
    I: np.ndarray,
    counts: np.ndarray,
    X: np.ndarray,
    centers: np.ndarray,
    m: int,
    chunk_points: int = 1024,
) -> np.ndarray:
    """Which observations (``P``, ``I`` sorted by point, one per image) a point with more
    than ``m`` of them keeps: ``m`` whose viewing rays (from the point at ``X`` to the image
    centres) are spread widest, chosen greedily (the ray farthest from the mean ray, then
    each time the ray farthest from every one chosen). Points with at most ``m`` keep all."""
    keep = np.ones(len(P), bool)
    long_pts = np.nonzero(counts > m)[0]
    starts = np.searchsorted(P, long_pts)
    for s in range(0, len(long_pts), max(1, int(chunk_points))):
        pts, st = long_pts[s : s + chunk_points], starts[s : s + chunk_points]
        n = counts[pts]
        width = int(n.max())
        valid = np.arange(width)[None, :] < n[:, None]  # (L, N)
        idx = np.where(valid, st[:, None] + np.arange(width)[None, :], st[:, None])
        rays = centers[I[idx]] - X[pts][:, None, :]
        rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-12)
        rows = np.arange(len(pts))
        mean = np.einsum("lni,ln->li", rays, valid.astype(np.float64))
        # cosine to the closest chosen ray; invalid slots never win (+inf)
        first = np.argmin(np.where(valid, np.einsum("lni,li->ln", rays, mean), np.inf), axis=1)
        chosen = np.zeros_like(valid)
        chosen[rows, first] = True
        closest = np.einsum("lni,li->ln", rays, rays[rows, first])
        for _ in range(m - 1):
            nxt = np.argmin(np.where(valid & ~chosen, closest, np.inf), axis=1)
            chosen[rows, nxt] = True
            closest = np.maximum(closest, np.einsum("lni,li->ln", rays, rays[rows, nxt]))
        keep[idx[valid]] = chosen[valid]
    return keep


def _refine_chunk(
    X0: np.ndarray,
    start: np.ndarray,
    n_obs: np.ndarray,
    I: np.ndarray,
    uvn: np.ndarray,
    focal: np.ndarray,
    geo: tuple[np.ndarray, np.ndarray, np.ndarray],
    conf: RefineConf,
) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton for points at ``X0`` (their observations from ``start``, ``n_obs`` of
    them; ``geo``: the images' rotations, translations, centres); which pass the checks, and
    the new positions."""
    M = conf.max_observations
    idx = start[:, None] + np.arange(M)[None, :]
    valid = np.arange(M)[None, :] < n_obs[:, None]
    idx = np.where(valid, idx, start[:, None])
    R = geo[0][I[idx]]  # (C, M, 3, 3)
    t = geo[1][I[idx]]  # (C, M, 3)
    obs = uvn[idx]  # (C, M, 2)
    f = focal[idx]  # (C, M)
    X = X0.copy()
    w = valid.astype(np.float64)
    for _ in range(conf.iterations):
        pc = np.einsum("cmij,cj->cmi", R, X) + t
        z = np.where(np.abs(pc[..., 2]) > 1e-9, pc[..., 2], 1e-9)
        proj = pc[..., :2] / z[..., None]
        r = (proj - obs) * (f * w)[..., None]  # (C, M, 2) pixels
        # d(proj)/dX = (R[:2] - proj * R[2]) / z
        J = (R[..., :2, :] - proj[..., :, None] * R[..., 2:3, :]) / z[..., None, None]
        J = J * (f * w)[..., None, None]  # (C, M, 2, 3)
        J = J.reshape(len(X), -1, 3)
        r = r.reshape(len(X), -1)
        H = np.einsum("cki,ckj->cij", J, J) + 1e-9 * np.eye(3)
        g = np.einsum("cki,ck->ci", J, r)
        X = X - np.linalg.solve(H, g[..., None])[..., 0]
    # acceptance
    pc = np.einsum("cmij,cj->cmi", R, X) + t
    pc0 = np.einsum("cmij,cj->cmi", R, X0) + t
    z, z0 = pc[..., 2], pc0[..., 2]
    ok_depth = np.all((z > 1e-6) | ~valid, axis=1)
    zs, z0s = np.where(np.abs(z) > 1e-9, z, 1e-9), np.where(np.abs(z0) > 1e-9, z0, 1e-9)
    proj, proj0 = pc[..., :2] / zs[..., None], pc0[..., :2] / z0s[..., None]
    err = np.linalg.norm(proj - obs, axis=2) * f
    shift = np.linalg.norm(proj - proj0, axis=2) * f
    err_ok = np.all((err < conf.max_error_px) | ~valid, axis=1)
    shift_ok = np.all((shift < conf.max_shift_px) | ~valid, axis=1)
    # triangulation angle: widest pair of viewing rays
    centers = geo[2][I[idx]]  # (C, M, 3)
    rays = X[:, None, :] - centers
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-12)
    cos = np.einsum("cmi,cni->cmn", rays, rays)
    cos = np.where(valid[:, :, None] & valid[:, None, :], cos, 1.0)
    angle_ok = np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1, 1))) >= conf.min_angle_deg
    keep = ok_depth & err_ok & shift_ok & angle_ok & np.all(np.isfinite(X), axis=1)
    return keep, X
