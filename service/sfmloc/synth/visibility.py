"""Which scene points a view observes, and where (exact projections).

A feature of ``scene.features`` is observed by a view when all of these hold:

1. it is in front of the camera and projects inside the image, ``margin_px`` from the border;
2. its face faces the camera and is at most ``max_obliquity_deg`` from frontal;
3. its clean neighbourhood (``Features.radius`` on the surface) spans at least
   ``min_feature_px`` pixels along both surface axes: smaller corners are not detectable;
4. the segment from the camera centre to it crosses no other face (exact ray casting);
5. every pixel within ``occlusion_margin_px`` of its projection shows its face in the
   z-buffer, so no occluding silhouette passes over its neighbourhood.

Public API::

    obs = visible_points(scene, camera, cam_from_world)   # Observations(point_idx, xy, depth)

``xy`` are COLMAP image coordinates (centre of the upper-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..cameras import Camera
from ..transforms import Rigid3d
from .config import RenderConf, VisibilityConf
from .renderer import render_geometry
from .scene import Scene, raycast


@dataclass
class Observations:
    point_idx: np.ndarray  # (N,) indices into scene.features, increasing
    xy: np.ndarray  # (N, 2) exact projections, COLMAP pixel convention
    depth: np.ndarray  # (N,) camera-frame z (m)

    def __len__(self) -> int:
        return len(self.point_idx)


def _face_axes(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cached = scene.cache.get("face_axes")
    if cached is None:
        u = np.stack([f.u_axis / np.linalg.norm(f.u_axis) for f in scene.faces])
        v = np.stack([f.v_axis / np.linalg.norm(f.v_axis) for f in scene.faces])
        n = np.stack([f.normal for f in scene.faces])
        cached = scene.cache["face_axes"] = (u, v, n)
    return cached


def visible_points(
    scene: Scene,
    camera: Camera,
    cam_from_world: Rigid3d,
    *,
    face_id: np.ndarray | None = None,
    conf: VisibilityConf | None = None,
    render_conf: RenderConf | None = None,
) -> Observations:
    """The features ``cam_from_world`` observes (see the module docstring for the rules).

    ``face_id`` is the z-buffer's face-id image of this view when the caller rendered it
    already (``render_full(...).face_id``); otherwise a geometry-only pass computes it.
    """
    conf = conf or VisibilityConf()
    F = scene.features
    empty = Observations(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0))
    if len(F) == 0:
        return empty
    near = (render_conf or RenderConf()).near
    xy, z = camera.project(cam_from_world, F.xyz)
    C = cam_from_world.center
    U, V, N = _face_axes(scene)
    fu, fv, fn = U[F.face], V[F.face], N[F.face]
    to_cam = C - F.xyz
    dist = np.linalg.norm(to_cam, axis=1)
    cos_obl = np.einsum("ij,ij->i", to_cam, fn) / np.maximum(dist, 1e-12)
    ok = (
        (z > near)
        & camera.in_image(xy, conf.margin_px)
        & (cos_obl >= np.cos(np.radians(conf.max_obliquity_deg)))
    )
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return empty
    # Detectable size: the clean neighbourhood's extent in pixels along both surface axes.
    X, r = F.xyz[idx], F.radius[idx][:, None]
    size = np.full(len(idx), np.inf)
    for axis in (fu[idx], fv[idx]):
        for sgn in (1.0, -1.0):
            p, zz = camera.project(cam_from_world, X + sgn * r * axis)
            d = np.where(zz > near, np.linalg.norm(p - xy[idx], axis=1), 0.0)
            size = np.minimum(size, d)
    idx = idx[size >= conf.min_feature_px]
    if len(idx) == 0:
        return empty
    # Exact occlusion: nothing between the camera and the point (its own face excluded).
    d = F.xyz[idx] - C
    L = np.linalg.norm(d, axis=1)
    _, hit = raycast(scene, C[None], d / L[:, None], t_max=L * (1 - 1e-9), exclude_face=F.face[idx])
    idx = idx[hit < 0]
    if len(idx) == 0:
        return empty
    # Clean neighbourhood in the z-buffer.
    if face_id is None:
        _, face_id = render_geometry(scene, camera, cam_from_world, render_conf)
    H, W = face_id.shape
    k = conf.occlusion_margin_px
    ci = np.floor(xy[idx, 0]).astype(np.int64)
    cj = np.floor(xy[idx, 1]).astype(np.int64)
    good = np.ones(len(idx), bool)
    own = F.face[idx]
    for dj in range(-k, k + 1):
        for di in range(-k, k + 1):
            jj, ii = cj + dj, ci + di
            inside = (jj >= 0) & (jj < H) & (ii >= 0) & (ii < W)
            good &= inside & (face_id[np.clip(jj, 0, H - 1), np.clip(ii, 0, W - 1)] == own)
    idx = idx[good]
    return Observations(idx, xy[idx], z[idx])
