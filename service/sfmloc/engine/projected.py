"""More correspondences for a tracked frame's final refinement: map points associated with the
frame's keypoints by projection at its pose (issue 9, accuracy).

A tracked pose rests on the tracked keypoints that guided matching gave a 3D point (on
redkitchen about 76) while most of the frame's Harris corners are the corners the map's points
were triangulated from (the map is built from the same detector). At a pose already good to a
fraction of a pixel, a map point seen by the images around the pose that projects within
``radius_px`` of exactly one keypoint, with no other map point or keypoint near either, is the
same corner: no descriptor is needed to tell, only the geometry. Ambiguous neighbourhoods
(two keypoints or two projections close together: repeated texture, occlusion boundaries) are
left out rather than guessed.

``projected_matches`` returns those associations (``unmatched_only``: those the tracked matches
do not already hold); ``refine_with_projections`` refines the pose once more on them together
with the tracked inliers. The status and the covariance stay the tracked matches' (the
associations were chosen for lying near the pose: their residuals understate the noise), and
the associations never enter the track table: a wrong one is not carried to the next frame.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace

import numpy as np

from ..map.bundle import MapBundle
from ..transforms import Rigid3d
from .matching import scope_images
from .pose import PoseEstimate, RansacParams, reprojection_errors, robust_refine

# ``projected_matches`` adds a neighbourhood's keypoint count and index sum in one float64
# grid up to this many keypoints (exact integers below 2^53).
_ONE_GRID_MAX_KEYPOINTS = 100_000


class ScopePoints:
    """The map points seen by the ``top`` images that see most of a frame's matched points,
    each once (in the order of its first listing: ``projected_matches`` then gives the same
    pairs as from the listing with repeats, half of it on redkitchen), and their coordinates.
    The answers of the ``keep`` most recent scopes (image sets) of the bundle are kept (a
    sub-map session swaps bundles, and another bundle starts afresh), so the deduplication and
    the gather of the coordinates are paid once per scope, not per frame. Issue 10: on
    redkitchen (1000 frames) the top images changed on 319 frames, often back to a set of a
    few frames before (a tie between two images flipping): 218 new scopes with the last 4
    kept (8: 211), each ~100 us of CPU."""

    def __init__(self, top: int, keep: int = 4) -> None:
        self.top = top
        self.keep = keep
        self._bundle: MapBundle | None = None
        # image set (sorted indices' bytes) -> (points, coordinates), the most recent last
        self._recent: OrderedDict[bytes, tuple[np.ndarray, np.ndarray]] = OrderedDict()

    def __call__(self, bundle: MapBundle, matched_points: np.ndarray) -> np.ndarray:
        return self.with_xyz(bundle, matched_points)[0]

    def with_xyz(
        self, bundle: MapBundle, matched_points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The scope's point indices and their coordinates (N, 3) (shared: read only)."""
        imgs = np.sort(scope_images(bundle, matched_points, self.top))
        key = imgs.tobytes()
        if bundle is not self._bundle:
            self._recent.clear()
            self._bundle = bundle
        hit = self._recent.get(key)
        if hit is not None:
            self._recent.move_to_end(key)
            return hit
        ptr = bundle.image_points_ptr
        idx = bundle.image_points_idx
        points = _first_listed(bundle.n_points, [idx[ptr[i] : ptr[i + 1]] for i in imgs])
        # (stored axis by axis, (3, N) C-contiguous, and handed out as its (N, 3) transpose:
        # ``projected_matches`` projects it as R @ X^T, whose rows are contiguous)
        xyz_by_axis = np.ascontiguousarray(bundle.points_xyz[points].T, np.float64)
        for a in (points, xyz_by_axis):
            a.flags.writeable = False  # (shared with later frames; before the view is taken)
        out = points, xyz_by_axis.T
        self._recent[key] = out
        if len(self._recent) > self.keep:
            self._recent.popitem(last=False)
        return out


def _first_listed(n_points: int, parts: list[np.ndarray]) -> np.ndarray:
    """The point indices of ``parts`` (the images' point lists, in order) each once, in the
    order of its first listing. An image lists a point once: each part keeps the points no
    earlier part listed, marked in a mask over the map's points (x0.42 CPU of a sort-based
    ``np.unique`` on the every-frame redkitchen map's scopes, ~7,000 listed, 2,650 distinct);
    a part listing a point twice falls back to the sort, so the answer is the same anyway."""
    if not parts:
        return np.zeros(0, np.int64)
    seen = np.zeros(n_points, bool)
    kept = []
    for p in parts:
        p = p[~seen[p]]
        seen[p] = True
        kept.append(p)
    out = np.concatenate(kept).astype(np.int64)
    if len(out) == np.count_nonzero(seen):
        return out
    listed = np.concatenate(parts).astype(np.int64)
    _, first = np.unique(listed, return_index=True)
    return listed[np.sort(first)]


_WEIGHTS_BY_9: dict[int, np.ndarray] = {}


def _weights_by_9(bits: int) -> np.ndarray:
    """``projected_matches``' keypoint weights 1 + (index + 1) * span, span = 2^bits, each
    repeated 9 times, for every index below the span: the first 9 n are those of n keypoints
    (made once per span up to 2^14 keypoints, 1.2 MB, not per frame)."""
    w = _WEIGHTS_BY_9.get(bits)
    if w is None:
        span = float(1 << bits)
        w = np.repeat(np.arange(1, (1 << bits) + 1, dtype=np.float64) * span + 1.0, 9)
        w.flags.writeable = False
        if bits <= 14:
            _WEIGHTS_BY_9[bits] = w
    return w


def projected_matches(
    cam_from_world: Rigid3d,
    K: np.ndarray,
    width: int,
    height: int,
    kp_xy: np.ndarray,
    points_xyz: np.ndarray,
    candidates: np.ndarray,
    radius_px: float,
    clear_px: float,
    candidates_xyz: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(keypoint index, map point index) pairs: each candidate map point projecting within
    ``radius_px`` of a keypoint (undistorted pixels ``kp_xy``) with no other keypoint near
    it ("near": in the 3x3 cells of ``clear_px`` around it, which hold everything within
    ``clear_px``); per keypoint, the closest such projection (the first listed candidate on
    a tie). ``candidates_xyz``: ``points_xyz[candidates]`` when the caller has it
    (``ScopePoints.with_xyz``: the transpose of a C-contiguous (3, N) array, used as is)."""
    empty = np.zeros(0, np.int64)
    if len(candidates) == 0 or len(kp_xy) < 2:
        return empty, empty
    X = points_xyz[candidates] if candidates_xyz is None else candidates_xyz
    # The camera coordinates axis by axis, (3, N): R @ X^T is the product X @ R^T transposed,
    # the same three products summed in the same order by the same BLAS kernel (the same bits,
    # two points or more: tests/test_projected.py), and each axis's row is contiguous for the
    # divisions and comparisons below, which ran on stride-3 columns (issue 10: this block
    # 30 -> 17 us hot on 2,274 points). X^T is free for ScopePoints' coordinates.
    if len(X) > 1:
        pc = cam_from_world.rotation @ np.ascontiguousarray(X.T)
    else:  # (a single point: numpy takes matrix-vector products, not the same bits)
        pc = (X @ np.ascontiguousarray(cam_from_world.rotation.T)).T
    pc += cam_from_world.translation[:, None]
    z = pc[2]
    # (behind the camera: NaN, which every comparison below rejects, instead of a mask of its
    # own and-ed in)
    zs = np.where(z > 1e-9, z, np.nan)
    u = K[0, 0] * pc[0] / zs + K[0, 2]
    v = K[1, 1] * pc[1] / zs + K[1, 2]
    inside = np.nonzero((u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5))[0]
    if len(inside) == 0:
        return empty, empty
    # (coordinates as separate vectors: no (N, 2) stacking; x0.5 CPU with the deduplicated
    # candidates, the same pairs)
    u, v = u[inside], v[inside]
    # Neighbourhoods on a grid of clear_px cells: whatever lies within clear_px of a position
    # lies in the 3x3 cells around its own, so the keypoint counts (and the sums of their
    # indices + 1: the index itself where the count is 1) over the 3x3 cells around each
    # projection decide every association (x0.2 of two k-d trees' CPU). Each keypoint's weight
    # goes to the 3x3 cells around its own in a grid padded by one empty cell (a keypoint is in
    # a projection's 3x3 cells exactly when the projection is in the keypoint's), so a
    # projection's sum is one gather at its cell: 9 x the keypoints (~650) scattered instead of
    # 9 x the projections (~1,500) gathered (issue 10: x0.9 CPU of this function), and not
    # box filters over the whole grid (~35k cells). Integer sums: exact in any order.
    gw, gh = int(width / clear_px) + 3, int(height / clear_px) + 3
    pw = gw + 2  # padded row length
    offsets = np.array([-pw - 1, -pw, -pw + 1, -1, 0, 1, pw - 1, pw, pw + 1])

    def cells(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        i = np.floor(x / clear_px).astype(np.int64) + 1
        j = np.floor(y / clear_px).astype(np.int64) + 1
        np.minimum(np.maximum(i, 0, out=i), gw - 1, out=i)  # np.clip's wrapper: ~10 us a call
        np.minimum(np.maximum(j, 0, out=j), gh - 1, out=j)
        return (j + 1) * pw + (i + 1)

    kp_cell = cells(kp_xy[:, 0], kp_xy[:, 1])
    if clear_px >= 0.5:
        # A projection inside the image (u, v >= -0.5, u <= width - 0.5) lies in cells
        # 0 .. int(width / clear_px) + 1 of ``cells``' padded numbering: its clipping never
        # binds there (the same cells without its four passes; undistorted keypoints may lie
        # outside and keep them)
        p_cell = (np.floor(v / clear_px).astype(np.int64) + 2) * pw
        p_cell += np.floor(u / clear_px).astype(np.int64) + 2
    else:
        p_cell = cells(u, v)
    # The count and the index sum in one grid, one bincount and one gather (CPU x0.6 of two):
    # each keypoint weighs 1 + (its index + 1) * span, span a power of two above the keypoint
    # count, so a 3x3 sum is its count (at most the keypoint count: below the span) plus its
    # index sum times the span; integers, exact in float64 below 2^53 (n + span n (n + 1) / 2:
    # up to ~10^5 keypoints; more take the two sums apart).
    n_kp = len(kp_xy)
    if n_kp <= _ONE_GRID_MAX_KEYPOINTS:
        span = float(1 << n_kp.bit_length())
        # (measured, not taken: a preallocated grid filled by np.add.at, read, and zeroed again
        # at the keypoints' cells: 12.9 against 12.6 us hot, each with the gather; the grid's
        # zeroing is not what costs)
        grid = np.bincount(
            (kp_cell[:, None] + offsets).ravel(),
            _weights_by_9(n_kp.bit_length())[: 9 * n_kp],
            minlength=pw * (gh + 2),
        )
        total = grid[p_cell]
        index_sum = np.floor(total / span)
        p_idx = np.nonzero(total - index_sum * span == 1.0)[0]  # one keypoint near it
        kp = index_sum[p_idx].astype(np.int64) - 1
    else:
        counts = np.bincount(kp_cell, minlength=pw * (gh + 2))
        p_idx = np.nonzero(counts[p_cell[:, None] + offsets].sum(axis=1) == 1)[0]
        sums = np.bincount(kp_cell, np.arange(1, n_kp + 1.0), minlength=pw * (gh + 2))
        kp = np.rint(sums[p_cell[p_idx, None] + offsets].sum(axis=1)).astype(np.int64) - 1
    du = kp_xy[kp, 0] - u[p_idx]
    dv = kp_xy[kp, 1] - v[p_idx]
    d2 = du * du + dv * dv
    ok = d2 < radius_px * radius_px
    p_idx, kp, d2 = p_idx[ok], kp[ok], d2[ok]
    # Several map points may project onto one keypoint: mostly one corner triangulated more
    # than once (on redkitchen a quarter of the projections have another within 1.7 px), so
    # the closest is kept.
    # (measured, not taken: two stable argsorts, d2 then kp, the same order: x1.5-2 the CPU of
    # lexsort on ~130 pairs, 6.2-6.5 against 3.3-4.2 us hot)
    order = np.lexsort((d2, kp))
    first = np.ones(len(order), bool)
    first[1:] = kp[order[1:]] != kp[order[:-1]]
    sel = order[first]
    return kp[sel], candidates[inside[p_idx[sel]]].astype(np.int64, copy=False)


def unmatched_only(
    kp_i: np.ndarray,
    pt_i: np.ndarray,
    kp_xy: np.ndarray,
    matched_xy: np.ndarray,
    matched_points: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of ``projected_matches`` whose keypoint (position in ``kp_xy``) is not among
    the tracked matches' positions ``matched_xy`` (the same keypoints, bytes equal) and whose
    point is not among ``matched_points``."""
    keep = np.ones(len(kp_i), bool)
    if len(matched_xy):
        used = np.sort(np.ascontiguousarray(matched_xy, np.float64).view(np.complex128).ravel())
        key = np.ascontiguousarray(kp_xy[kp_i], np.float64).view(np.complex128).ravel()
        keep &= used[np.minimum(np.searchsorted(used, key), len(used) - 1)] != key
    if len(matched_points):
        # (measured, not taken: np.isin(kind="table"), x1.27 the CPU of this sort and search
        # on 299 recorded redkitchen calls, 27.7 -> 35.3 us, issue 10)
        taken = np.sort(matched_points)
        keep &= taken[np.minimum(np.searchsorted(taken, pt_i), len(taken) - 1)] != pt_i
    return kp_i[keep], pt_i[keep]


def refine_with_projections(
    est: PoseEstimate,
    K: np.ndarray,
    extra_xy: np.ndarray,
    extra_X: np.ndarray,
    params: RansacParams,
    keep_fraction: float = 0.9,
    iterations: int = 2,
) -> PoseEstimate:
    """``est``'s pose refined once more with the robust loss on its inliers and the projected
    matches (``extra_xy`` undistorted px, ``extra_X``). Everything else stays the tracked
    matches' (inliers, their count, the inputs of the covariance): the projected matches were
    chosen for lying near the pose, so their residuals understate the noise and they are no
    independent evidence for it. Unchanged when the new pose keeps fewer than
    ``keep_fraction`` of the tracked inliers within ``refine_threshold``."""
    if est.inlier_xy is None or est.inlier_X is None or len(extra_xy) == 0:
        return est
    n = len(est.inlier_xy)
    xy = np.concatenate([est.inlier_xy, extra_xy])
    X = np.concatenate([est.inlier_X, extra_X])
    # from a pose already refined on the tracked matches: two Gauss-Newton steps suffice
    pose = robust_refine(est.cam_from_world, K, xy, X, params.loss_scale, iterations=iterations)
    err = reprojection_errors(pose, K, est.inlier_xy, est.inlier_X)
    if np.count_nonzero(err < params.refine_threshold) < keep_fraction * n:
        return est
    # (the mean as np.mean takes it, np.add.reduce over n, without its Python layer)
    return replace(est, cam_from_world=pose, mean_error_px=float(np.add.reduce(err)) / n)
