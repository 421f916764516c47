"""How uncertain each map point is, for the pose covariance.

A point triangulated from mapping views that saw it under a small angle is poorly placed along
its viewing rays: its depth error is about ``sigma_px / f * d / sin(theta)`` (``d`` the distance
to the nearest mapping view, ``theta`` the largest angle between its rays). A pose computed from
such points inherits their errors, and since the same points serve many frames the per-frame
pixel noise alone makes the covariance optimistic (redkitchen, a map from every 10th video
frame: median half-angle 3.3 deg). Each correspondence's variance therefore gets the point's
error projected into the query, treated as isotropic (an upper bound: a depth error along the
query's own ray does not move the projection).

The frame's own residuals already hold each point's independent error; this term stands for
what they do not show (errors shared by neighbouring points, the map's poses). Its scale,
``EngineConf.map_noise_px``, is fitted on exact synthetic ground truth
(``sfmloc.eval.calibration``).

``PointUncertainty.for_bundle(bundle)`` computes ``kappa = d / sin(theta)`` per point once per
bundle (cached); ``sigma_px(X, z)`` gives the extra pixel standard deviation of correspondences
with world points ``X`` at depths ``z`` in the query.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np

from ..map.bundle import MapBundle

# Pixel noise of the mapping views' keypoints (the map points' triangulation inputs).
MAP_NOISE_PX = 1.0
# A point seen under a smaller angle is treated as seen under this one (keeps kappa finite;
# such a point then weighs almost nothing).
MIN_ANGLE_DEG = 0.5

_lock = threading.Lock()
_cache: weakref.WeakKeyDictionary[MapBundle, PointUncertainty] = weakref.WeakKeyDictionary()


class PointUncertainty:
    def __init__(self, bundle: MapBundle) -> None:
        X = np.asarray(bundle.points_xyz, np.float64)
        centers = np.array([T.center for T in bundle.image_cam_from_world]).reshape(-1, 3)
        ptr = np.asarray(bundle.image_points_ptr)
        pts = np.asarray(bundle.image_points_idx, np.int64)
        img = np.repeat(np.arange(len(centers)), np.diff(ptr))
        rays = X[pts] - centers[img]
        dist = np.linalg.norm(rays, axis=1)
        rays /= np.maximum(dist, 1e-12)[:, None]
        n = len(X)
        # per-point sums of the rays (bincount: the same sums as np.add.at, x4 faster)
        mean = np.stack(
            [np.bincount(pts, rays[:, i], minlength=n) for i in range(3)], axis=1
        ).astype(np.float64, copy=False)
        mean /= np.maximum(np.linalg.norm(mean, axis=1), 1e-12)[:, None]
        # the largest angle to the mean ray, doubled: about the widest pair of rays
        half = np.arccos(np.clip(np.sum(rays * mean[pts], axis=1), -1.0, 1.0))
        theta = np.zeros(n)
        np.maximum.at(theta, pts, 2.0 * half)
        d_min = np.full(n, np.inf)
        np.minimum.at(d_min, pts, dist)
        d_min[~np.isfinite(d_min)] = 0.0  # a point no image lists: no information, no term
        theta = np.maximum(theta, np.radians(MIN_ANGLE_DEG))
        self.kappa = d_min / np.sin(np.minimum(theta, np.pi / 2))
        self._index = {X[i].tobytes(): i for i in range(n)}
        # The same lookup vectorized: rows sorted by a hash of their bytes (then by row, so the
        # last of byte-identical rows is found, as the dict keeps it); a row whose hash matches
        # but whose bytes do not (a collision) is looked up in the dict. The per-row dict
        # lookups cost ~0.2 ms per frame.
        self._rows = np.ascontiguousarray(X).view(np.uint64).reshape(n, 3)
        keys = _row_keys(self._rows)
        self._order = np.lexsort((np.arange(n), keys))
        self._sorted_keys = keys[self._order]

    def lookup(self, X: np.ndarray) -> np.ndarray:
        """The map row of each of the world points ``X`` (bytes equal), -1 for none."""
        X = np.ascontiguousarray(X, np.float64).reshape(-1, 3)
        if len(self._order) == 0 or len(X) == 0:
            return np.full(len(X), -1, np.int64)
        q = X.view(np.uint64).reshape(-1, 3)
        kq = _row_keys(q)
        pos = np.maximum(np.searchsorted(self._sorted_keys, kq, side="right") - 1, 0)
        row = self._order[pos]
        hit = self._sorted_keys[pos] == kq
        same = hit & np.all(self._rows[row] == q, axis=1)
        idx = np.where(same, row, -1)
        for i in np.nonzero(hit & ~same)[0]:
            idx[i] = self._index.get(X[i].tobytes(), -1)
        return idx

    @classmethod
    def for_bundle(cls, bundle: MapBundle) -> PointUncertainty:
        with _lock:
            pu = _cache.get(bundle)
            if pu is None:
                pu = _cache[bundle] = cls(bundle)
            return pu

    def sigma_px(
        self, X: np.ndarray, z: np.ndarray, map_noise_px: float = MAP_NOISE_PX
    ) -> np.ndarray:
        """Extra pixel standard deviation per correspondence (0 for points not in the map)."""
        idx = self.lookup(X)
        k = np.where(idx >= 0, self.kappa[np.maximum(idx, 0)], 0.0)
        return map_noise_px * k / np.maximum(z, 1e-9)

    def sigma_px_of(
        self, points: np.ndarray, z: np.ndarray, map_noise_px: float = MAP_NOISE_PX
    ) -> np.ndarray:
        """``sigma_px`` of the map points with indices ``points`` (no lookup by coordinates)."""
        return map_noise_px * self.kappa[points] / np.maximum(z, 1e-9)


def _row_keys(rows: np.ndarray) -> np.ndarray:
    """A 64-bit hash of each row of three uint64 words (the bytes of a float64 point)."""
    with np.errstate(over="ignore"):
        k = rows[:, 0] * np.uint64(0x9E3779B97F4A7C15)
        k ^= rows[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
        k ^= rows[:, 2] * np.uint64(0x165667B19E3779F9)
        k ^= k >> np.uint64(29)
    return k
