"""Is a relocalization distinct? Two tests of a global-matching pose beyond its inlier count
(a pose is a promise): its inliers must spread over the image, and no other place may
explain the frame nearly as well (repeated texture: identical walls, rooms that look alike).
See ``EngineConf.min_inlier_spread`` and ``EngineConf.second_place_ratio``."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..map.bundle import MapBundle
from ..transforms import rotation_angle_deg
from .config import EngineConf
from .pose import PoseEstimate, estimate_pose_one_to_many, reprojection_errors


def occupied_cells(xy: np.ndarray, width: int, height: int, grid: int = 4) -> int:
    """How many cells of a ``grid`` x ``grid`` partition of the image hold a point of ``xy``."""
    return len(cell_ids(xy, width, height, grid))


def cell_ids(xy: np.ndarray, width: int, height: int, grid: int = 4) -> np.ndarray:
    """The cells of a ``grid`` x ``grid`` partition of the image that hold a point of ``xy``."""
    if len(xy) == 0:
        return np.zeros(0, np.int64)
    size = np.array([width, height], np.float64)
    ij = np.clip((xy * (grid / size)).astype(np.int64), 0, grid - 1)
    return np.unique(ij[:, 1] * grid + ij[:, 0])


def inlier_spread(
    xy_all: np.ndarray,
    xy_inliers: np.ndarray,
    width: int,
    height: int,
    xy_visible: np.ndarray | None = None,
) -> float:
    """The fraction of the image cells (4x4) with keypoints that hold an inlier. With
    ``xy_visible`` (where the map points the pose makes visible project), only the cells
    with keypoints and a visible map point count: a cell the map has no point in cannot hold
    an inlier at any pose, so a thin map's right pose is not judged by it (robust density-6x:
    right relocalizations on 26-62 inliers covered 3 of 4 and 4 of 7 such cells, 20-27% of
    the cells with keypoints)."""
    cells = cell_ids(xy_all, width, height)
    if xy_visible is not None:
        cells = np.intersect1d(cells, cell_ids(xy_visible, width, height))
    inl = np.intersect1d(cell_ids(xy_inliers, width, height), cells)
    return len(inl) / max(1, len(cells))


def second_place(
    best: PoseEstimate,
    set1: tuple[np.ndarray, np.ndarray],
    set2: tuple[np.ndarray, np.ndarray],
    xy_u: np.ndarray,
    points_xyz: np.ndarray,
    K: np.ndarray,
    conf: EngineConf,
    scene_scale: float,
    place_points: np.ndarray | None = None,
) -> PoseEstimate | None:
    """A pose at another place (farther from ``best`` than a wrong pose:
    ``contradiction_position`` scene scales or ``contradiction_deg``) with at least
    ``second_place_ratio`` x ``best``'s inliers, found by RANSAC among the candidate matches
    that ``best`` does not explain; else None. A place RANSAC finds below that bar (or at
    ``best``'s place) has its matches set aside too and the search goes on, for
    ``second_place_rounds`` searches in all (several look-alike places: the one found first
    can hide a better one). ``set1``/``set2``: (keypoint, point) pairs of global matching.
    ``place_points`` (bool per map point): the points of ``best``'s place (``place_points``),
    set aside as well: a twin's matches are then most of what RANSAC samples."""
    # A place by chance gathers 12-16 inliers (the synthetic room): the bar is at least what
    # a recovery needs.
    need = max(conf.recover_min_inliers, math.ceil(conf.second_place_ratio * best.num_inliers))
    T = best.cam_from_world
    (q1, p1), (q2, p2) = set1, set2
    X1, X2, xy1, xy2 = points_xyz[p1], points_xyz[p2], xy_u[q1], xy_u[q2]
    # Explained: within twice the RANSAC threshold (a pose a little off the same place does
    # not count as a second place).
    near = 2 * conf.ransac_threshold_px
    k1 = ~(reprojection_errors(T, K, xy1, X1) < near)
    k2 = ~(reprojection_errors(T, K, xy2, X2) < near)
    if place_points is not None:
        k1 &= ~place_points[p1]
        k2 &= ~place_points[p2]
    for _ in range(conf.second_place_rounds):
        # Too few keypoints left to reach the bar: no second place, without a RANSAC.
        n_kp = len(np.unique(q2[k2]))
        if n_kp < need or k1.sum() < 3:
            return None
        # No good hypothesis, no adaptive stop: the budget finds, at RANSAC's confidence, a
        # place holding ``need`` of the remaining keypoints (few iterations when such a place
        # would be most of what remains).
        w = need / n_kp
        budget = conf.second_place_iterations
        if w < 1.0:
            lg = math.log(1 - conf.ransac_confidence) / math.log(1 - w**3)
            budget = min(budget, math.ceil(lg))
        params = replace(conf.ransac(need), max_iterations=max(16, budget))
        res = estimate_pose_one_to_many(
            xy1[k1],
            X1[k1],
            q2[k2],
            xy2[k2],
            X2[k2],
            K,
            params,
            pool_stop=conf.global_pool_stop,
            presolve=True,  # no good hypothesis: the run uses its whole budget
        )
        if res is None:
            return None
        other = res[0]
        O = other.cam_from_world
        far = np.linalg.norm(O.center - T.center) > conf.contradiction_position * scene_scale
        turned = rotation_angle_deg(O.rotation, T.rotation) > conf.contradiction_deg
        if other.num_inliers >= need and (far or turned):
            return other
        k1 &= ~(reprojection_errors(O, K, xy1, X1) < near)
        k2 &= ~(reprojection_errors(O, K, xy2, X2) < near)
    return None


def place_points(bundle: MapBundle, inlier_points: np.ndarray, share: float) -> np.ndarray:
    """The map points seen by the database images that see at least ``share`` of
    ``inlier_points`` (a pose's place; bool per map point)."""
    ptr, idx = bundle.point_images()
    p = inlier_points
    cnt = ptr[p + 1] - ptr[p]
    offs = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    imgs = idx[np.repeat(ptr[p], cnt) + offs]
    seen_by = np.bincount(imgs, minlength=bundle.n_images)
    out = np.zeros(bundle.n_points, bool)
    for i in np.nonzero(seen_by >= share * max(1, len(p)))[0]:
        out[bundle.image_points(int(i))] = True
    return out
