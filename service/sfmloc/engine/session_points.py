"""Session points: visual odometry on the tracker's own tracks, beyond the map.

Where the map is thin (synthetic room, mapping views at 6x the default spacing: frames 218-274
see one mapping view over half of the image), a frame's map matches alone leave its pose too
uncertain to publish, while the tracker still follows hundreds of Harris+BRIEF keypoints that
have no map point. While the camera is posed on the map, those tracks are triangulated from
two posed frames with enough parallax into session-local 3D points, kept per session (only the
tracks alive in the track table: bounded by it; dropped on LOST and reset). A frame that the
map alone cannot pose is posed on them beside its map matches (``Localizer._odometry``).

Honest covariance: a session point is only as right as the posed frames it was triangulated
from. Their errors are shared by every session point triangulated from them (one rigid error
of the anchor frame moves them all), so they are not averaged away over the points: the pose's
covariance is the relative fit's (pixel noise and each point's triangulation error, which are
independent) plus the anchor frame's covariance carried rigidly to the new camera
(``compound``). It grows with the distance from the anchor, and the status rules withhold the
pose once it exceeds their limit. Points are triangulated only from map-posed frames (never
from odometry poses: those rest on the points themselves).

Plain numpy; no state beyond the session's tracks.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..transforms import Rigid3d
from .certainty import position_sd
from .pose import pose_covariance


def compound(anchor_cov: np.ndarray, anchor_center: np.ndarray, center: np.ndarray) -> np.ndarray:
    """The anchor frame's 6x6 covariance (``engine.pose.COVARIANCE_ORDER``) carried to a camera
    at ``center`` posed on points triangulated from the anchor: an anchor error (rotation
    ``d`` on the world side, centre shift ``e``) moves the points, and with them the new
    camera, rigidly about the anchor's centre: the new camera's rotation error is ``d`` and its
    centre error ``e + d x (center - anchor_center)``."""
    r = np.asarray(center, np.float64) - np.asarray(anchor_center, np.float64)
    J = np.eye(6)
    # d x r = -[r]x d
    J[3:, :3] = -np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    out = J @ anchor_cov @ J.T
    return 0.5 * (out + out.T)


@dataclass
class SessionMatches:
    """The session points of a track table's rows."""

    rows: np.ndarray  # (N,) table rows
    xyz: np.ndarray  # (N, 3) world points
    axis: np.ndarray  # (N, 3) unit direction of the point's depth error (the rays' bisector)
    lat: np.ndarray  # (N,) its triangulation sd across that direction (map units)
    depth: np.ndarray  # (N,) and along it
    anchor: np.ndarray  # (N,) anchor frame of each point (``SessionPoints.frames``)

    def sigma_px(self, sel: np.ndarray, pose: Rigid3d, K: np.ndarray) -> np.ndarray:
        """The selected points' triangulation error projected into a camera at ``pose``: the
        sd in pixels of its worst image direction (their 3D covariance, lateral ``lat`` and
        ``depth`` along ``axis``, through the projection's Jacobian). A point seen along its
        depth direction projects its large depth error to little image motion."""
        X = self.xyz[sel]
        R = pose.rotation
        pc = X @ R.T + pose.translation
        z = pc[:, 2]
        u, v = pc[:, 0] / z, pc[:, 1] / z
        f = 0.5 * (K[0, 0] + K[1, 1])
        g = (f / z) ** 2
        a = self.lat[sel] ** 2
        dd = self.depth[sel] ** 2 - a
        bc = self.axis[sel] @ R.T  # the axis in camera coordinates
        jb0 = bc[:, 0] - u * bc[:, 2]
        jb1 = bc[:, 1] - v * bc[:, 2]
        # P = g * (a (J0 J0^T) + dd (Jb Jb^T)), J0 J0^T = [[1 + u^2, u v], [u v, 1 + v^2]]
        p00 = g * (a * (1 + u * u) + dd * jb0 * jb0)
        p01 = g * (a * u * v + dd * jb0 * jb1)
        p11 = g * (a * (1 + v * v) + dd * jb1 * jb1)
        half = 0.5 * (p00 + p11)
        disc = np.sqrt(np.maximum(0.25 * (p00 - p11) ** 2 + p01 * p01, 0.0))
        return np.sqrt(half + disc)


class SessionPoints:
    """Per-session triangulated points of the tracker's tracks, keyed by track id.

    ``observe`` records a map-posed, published frame's unmatched tracks (their first ray, then
    a point once a later ray sees them from far enough); ``matches`` returns the points of a
    table's rows. Thresholds are relative: parallax in degrees, reprojection in pixels, depth
    in scene scales."""

    def __init__(
        self,
        K: np.ndarray,
        scene_scale: float,
        min_parallax_deg: float,
        max_reprojection_px: float,
        max_depth_scales: float,
        noise_px: float,
        window: int = 60,
        undistort: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        self.K = np.asarray(K, np.float64)
        self.Kinv = np.linalg.inv(self.K)
        self.f = float(0.5 * (self.K[0, 0] + self.K[1, 1]))
        self.scene_scale = float(scene_scale)
        self.cos_min = float(np.cos(np.radians(min_parallax_deg)))
        self.max_reprojection_px = float(max_reprojection_px)
        self.max_depth = float(max_depth_scales) * self.scene_scale
        self.noise_px = float(noise_px)
        self.window = int(window)
        self.undistort = undistort
        self.reset()

    def reset(self) -> None:
        # Lazy: while the map poses every frame, a published frame only appends its track ids,
        # positions and pose here (references, no work: the incremental triangulation cost
        # 0.62 ms of redkitchen's 10.4 ms a frame); the first frame that needs odometry
        # replays them (``activate``), and from then on ``record`` triangulates as it goes.
        self.recent: deque[tuple[np.ndarray, np.ndarray, np.ndarray, Rigid3d, np.ndarray]] = deque(
            maxlen=self.window
        )
        self.active = False
        self.idle = 0  # map-posed frames recorded since odometry last posed one
        # first observation of each unmatched track: centre, unit ray (world), frame
        self.obs_id = np.zeros(0, np.int64)  # sorted
        self.obs_c = np.zeros((0, 3))
        self.obs_d = np.zeros((0, 3))
        self.obs_frame = np.zeros(0, np.int64)
        # triangulated points
        self.pt_id = np.zeros(0, np.int64)  # sorted
        self.pt_xyz = np.zeros((0, 3))
        self.pt_axis = np.zeros((0, 3))
        self.pt_lat = np.zeros(0)
        self.pt_depth = np.zeros(0)
        self.pt_anchor = np.zeros(0, np.int64)
        # anchor frames: number -> (centre, 6x6 covariance, centre sd)
        self.frames: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}
        self.frame_no = 0

    def ready(self) -> bool:
        """Whether odometry may have points: recorded frames or points."""
        return len(self.recent) > 1 or len(self.pt_id) > 0

    def record(
        self,
        track_id: np.ndarray,
        xy: np.ndarray,
        unmatched: np.ndarray,
        pose: Rigid3d,
        cov: np.ndarray,
        odometry: bool = False,
    ) -> None:
        """A published frame (``observe``'s arguments, ``xy`` as detected: undistorted when
        used): kept for later while inactive; triangulated now while active. After
        ``window`` map-posed frames without odometry the points go and recording is lazy
        again."""
        if not self.active:
            self.recent.append((track_id, xy, unmatched, pose, cov))
            return
        self.idle = 0 if odometry else self.idle + 1
        if self.idle > self.window:
            self.reset()
            self.recent.append((track_id, xy, unmatched, pose, cov))
            return
        self.observe(track_id, self._undistorted(xy), unmatched, pose, cov, odometry)

    def activate(self) -> None:
        """Triangulate the recorded frames (in order, as ``observe`` would have as they came)
        and triangulate each published frame from now on."""
        if self.active:
            return
        for track_id, xy, unmatched, pose, cov in self.recent:
            self.observe(track_id, self._undistorted(xy), unmatched, pose, cov)
        self.recent.clear()
        self.active = True
        self.idle = 0

    def _undistorted(self, xy: np.ndarray) -> np.ndarray:
        return xy if self.undistort is None else self.undistort(xy)

    def __len__(self) -> int:
        return len(self.pt_id)

    def observe(
        self,
        track_id: np.ndarray,
        xy_u: np.ndarray,
        unmatched: np.ndarray,
        pose: Rigid3d,
        cov: np.ndarray,
        odometry: bool = False,
    ) -> None:
        """A published frame: ``track_id`` and undistorted ``xy_u`` of all the table's rows,
        ``unmatched`` the rows without a map point. Tracks no longer in the table are
        forgotten (they never come back). ``odometry``: the frame was posed on session points;
        it only adds points of tracks that have none (anchored at it, with its covariance),
        never re-triangulates the points it was posed on."""
        self.frame_no += 1
        fno = self.frame_no
        c = pose.center
        R_wc = pose.rotation.T
        self.frames[fno] = (c.copy(), np.asarray(cov, np.float64), position_sd(cov))
        ids = track_id[unmatched]
        ones = np.ones((len(ids), 1))
        rays = np.hstack([xy_u[unmatched], ones]) @ self.Kinv.T @ R_wc.T
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        # forget tracks that left the table (and points of tracks now matched to the map)
        keep = np.isin(self.obs_id, ids, assume_unique=True)
        self._keep_obs(keep)
        keep = np.isin(self.pt_id, ids, assume_unique=True)
        self._keep_pts(keep)
        if len(self.obs_id):
            pos_c = np.minimum(np.searchsorted(self.obs_id, ids), len(self.obs_id) - 1)
            known = self.obs_id[pos_c] == ids
        else:
            pos_c = np.zeros(len(ids), np.int64)
            known = np.zeros(len(ids), bool)
        new = ~known
        if np.any(new):
            n = int(np.count_nonzero(new))
            self.obs_id = np.concatenate([self.obs_id, ids[new]])
            self.obs_c = np.concatenate([self.obs_c, np.repeat(c[None], n, axis=0)])
            self.obs_d = np.concatenate([self.obs_d, rays[new]])
            self.obs_frame = np.concatenate([self.obs_frame, np.full(n, fno, np.int64)])
            order = np.argsort(self.obs_id, kind="stable")
            self._keep_obs(order)
            # (the known tracks' first observations moved: new ids sort among them, e.g. a
            # track that was matched to the map and is unmatched again keeps its old id; the
            # positions found before would pair a track's ray with another track's first ray)
            pos_c = np.searchsorted(self.obs_id, ids)
        if odometry and len(self.pt_id):
            known &= ~np.isin(ids, self.pt_id, assume_unique=True)
        self._triangulate(ids[known], rays[known], c, fno, pos_c[known])
        # frames no point or observation refers to are dropped
        used = set(self.obs_frame.tolist()) | set(self.pt_anchor.tolist())
        for k in [k for k in self.frames if k not in used]:
            del self.frames[k]

    def _triangulate(
        self, ids: np.ndarray, d1: np.ndarray, c1: np.ndarray, fno: int, at: np.ndarray
    ) -> None:
        if len(ids) == 0:
            return
        c0, d0 = self.obs_c[at], self.obs_d[at]
        cosang = np.einsum("ij,ij->i", d0, d1)
        ok = cosang < self.cos_min
        if not np.any(ok):
            return
        ids, d0, d1, c0, cosang = ids[ok], d0[ok], d1[ok], c0[ok], cosang[ok]
        f0 = self.obs_frame[at[ok]]
        # midpoint of the closest points of the two rays c0 + s d0 and c1 + t d1
        w = c0 - c1
        b = cosang
        dd = np.einsum("ij,ij->i", d0, w)
        ee = np.einsum("ij,ij->i", d1, w)
        den = 1.0 - b * b
        s = (b * ee - dd) / den
        t = (ee - b * dd) / den
        X = 0.5 * ((c0 + s[:, None] * d0) + (c1 + t[:, None] * d1))
        # reprojection error of X on each ray, as an angle turned into pixels
        v0 = X - c0
        v1 = X - c1
        z0 = np.linalg.norm(v0, axis=1)
        z1 = np.linalg.norm(v1, axis=1)
        sin0 = np.linalg.norm(np.cross(v0, d0), axis=1) / np.maximum(z0, 1e-12)
        sin1 = np.linalg.norm(np.cross(v1, d1), axis=1) / np.maximum(z1, 1e-12)
        err = self.f * np.maximum(sin0, sin1)
        good = (
            (s > 0)
            & (t > 0)
            & (err <= self.max_reprojection_px)
            & (np.maximum(z0, z1) <= self.max_depth)
            & np.isfinite(X).all(axis=1)
        )
        if not np.any(good):
            return
        ids, X, f0 = ids[good], X[good], f0[good]
        sin_par = np.sqrt(np.maximum(den[good], 1e-12))
        # a two-ray triangulation with each ray off by noise_px: across the rays about the
        # farther ray's lateral error, along their bisector that over the parallax's sine
        zmax = np.maximum(z0[good], z1[good])
        lat = zmax * (self.noise_px / self.f)
        depth = np.sqrt(2.0) * lat / sin_par
        axis = d0[good] + d1[good]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        # the anchor: the less certain of the two frames (their errors move the point)
        anchor = np.where(
            np.array([self.frames[int(k)][2] for k in f0]) >= self.frames[fno][2], f0, fno
        )
        # (re)triangulated from the widest baseline so far: replace, then keep sorted
        old = np.isin(self.pt_id, ids, assume_unique=True)
        self._keep_pts(~old)
        self.pt_id = np.concatenate([self.pt_id, ids])
        self.pt_xyz = np.concatenate([self.pt_xyz, X])
        self.pt_axis = np.concatenate([self.pt_axis, axis])
        self.pt_lat = np.concatenate([self.pt_lat, lat])
        self.pt_depth = np.concatenate([self.pt_depth, depth])
        self.pt_anchor = np.concatenate([self.pt_anchor, anchor.astype(np.int64)])
        self._keep_pts(np.argsort(self.pt_id, kind="stable"))

    def _keep_obs(self, sel: np.ndarray) -> None:
        self.obs_id, self.obs_c = self.obs_id[sel], self.obs_c[sel]
        self.obs_d, self.obs_frame = self.obs_d[sel], self.obs_frame[sel]

    def _keep_pts(self, sel: np.ndarray) -> None:
        self.pt_id, self.pt_xyz = self.pt_id[sel], self.pt_xyz[sel]
        self.pt_axis, self.pt_lat = self.pt_axis[sel], self.pt_lat[sel]
        self.pt_depth, self.pt_anchor = self.pt_depth[sel], self.pt_anchor[sel]

    def matches(self, track_id: np.ndarray) -> SessionMatches:
        """The session points of the rows whose track ids are ``track_id``."""
        if len(self.pt_id) == 0 or len(track_id) == 0:
            z = np.zeros(0, np.int64)
            e = np.zeros(0)
            return SessionMatches(z, np.zeros((0, 3)), np.zeros((0, 3)), e, e, z)
        pos = np.minimum(np.searchsorted(self.pt_id, track_id), len(self.pt_id) - 1)
        rows = np.nonzero(self.pt_id[pos] == track_id)[0]
        p = pos[rows]
        return SessionMatches(
            rows,
            self.pt_xyz[p],
            self.pt_axis[p],
            self.pt_lat[p],
            self.pt_depth[p],
            self.pt_anchor[p],
        )

    def anchor_covariance(
        self, anchors: np.ndarray, weights: np.ndarray, center: np.ndarray
    ) -> np.ndarray:
        """The anchors' error carried to a camera at ``center`` posed on points anchored at
        ``anchors`` with fit ``weights``: the weighted mean (weights summing to 1) of the
        anchor frames' compounded covariances. The pose's anchor error is the weighted sum of
        the points' anchor errors, which are correlated (the same map points posed the anchor
        frames): whatever their correlation, var(sum w e) <= (sum w sd)^2 <= sum w sd^2, so the
        mean of the covariances (never divided by the number of points, as independent errors
        would be) bounds it."""
        out = np.zeros((6, 6))
        w = np.asarray(weights, np.float64)
        w = w / w.sum()
        ks, inv = np.unique(anchors, return_inverse=True)
        wk = np.bincount(inv.reshape(-1), weights=w, minlength=len(ks))
        for k, wt in zip(ks, wk, strict=True):
            ca, cov, _ = self.frames[int(k)]
            out += wt * compound(cov, ca, center)
        return out


def odometry_covariance(
    session: SessionPoints,
    pose: Rigid3d,
    K: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    sigma_px: np.ndarray,
    anchors: np.ndarray,
    loss_scale: float = 0.0,
) -> np.ndarray:
    """The 6x6 covariance of a pose fitted to undistorted ``xy`` of world points ``X``, the
    first ``len(anchors)`` of them session points anchored at ``anchors`` (the rest map
    points): the relative fit's covariance (``pose_covariance``, each point's own error
    ``sigma_px`` in its pixel variance) plus the anchor frames' error carried to the camera
    (``SessionPoints.anchor_covariance``, weighted by each session point's weight in that
    fit)."""
    rel = pose_covariance(pose, K, xy, X, point_sigma_px=sigma_px, loss_scale=loss_scale)
    k = len(anchors)
    share = 1.0 / (session.noise_px**2 + np.asarray(sigma_px[:k], np.float64) ** 2)
    return rel + session.anchor_covariance(anchors, share, pose.center)
