"""Keypoint extraction and frame-to-frame tracking (paper Section 3.1: EXTRACT-KEYPOINTS,
TRACK-2D, ADD-GOOD-FEATURES).

Each tracked keypoint is compared with every candidate keypoint of the new frame inside a
rho x rho window around its *predicted* position (the projection of its 3D point with the
Kalman prediction when it has one, else its previous position moved by the median motion of
those that do), by Hamming distance of 256-bit BRIEF descriptors; the best candidate is
accepted when best / second-best < psi. No geometric verification here: RANSAC handles
outliers. Candidate search uses a grid of rho-sized cells so that each keypoint looks at exactly
the 2x2 cells its window overlaps, all vectorized.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..features.brief import compute_brief, smooth_for_brief
from ..features.harris import SUBPIXEL_DEFAULT, Corners, detect_corners
from .config import EngineConf
from .track_table import TrackTable


@dataclass
class Keypoints:
    xy: np.ndarray  # (M, 2) COLMAP convention
    response: np.ndarray  # (M,)
    brief: np.ndarray  # (M, 4) uint64
    max_response: float

    def __len__(self) -> int:
        return len(self.xy)


def map_subpixel(conf: EngineConf, map_params: dict) -> str:
    """The sub-pixel keypoint method to use with a map (``EngineConf.subpixel``; "map": the
    method its keypoints were localized with, recorded in its build parameters: "quadratic"
    when the parameters predate the record, the detector's default when there are none)."""
    if conf.subpixel != "map":
        return conf.subpixel
    if "descriptors" not in map_params:
        return SUBPIXEL_DEFAULT
    return map_params["descriptors"].get("subpixel", "quadratic")


def _corners(
    gray: np.ndarray, threshold: float | None, conf: EngineConf, border: int, subpixel: str | None
) -> Corners:
    """The engine's Harris corners of ``gray`` at least ``border`` px from its edge."""
    return detect_corners(
        gray,
        threshold=threshold,
        rel_threshold=conf.gamma,
        max_corners=conf.max_keypoints,
        border=border,
        subpixel=subpixel or (SUBPIXEL_DEFAULT if conf.subpixel == "map" else conf.subpixel),
    )


def extract_keypoints(
    gray: np.ndarray, threshold: float | None, conf: EngineConf, subpixel: str | None = None
) -> Keypoints:
    """Harris corners above ``threshold`` (gamma times the previous frame's maximum; None on
    the first frame: gamma times this frame's) with BRIEF descriptors; ``subpixel``: the
    sub-pixel method (see ``map_subpixel``)."""
    corners = _corners(gray, threshold, conf, conf.mu // 2, subpixel)
    # Every corner described at once. Measured and not taken (issue 10): lazy BRIEF, only the
    # corners inside some track's window (85% of a redkitchen frame's) and later the rows new
    # tracks take: detect + track CPU x1.08 (+0.31 ms per frame; 300 frames, 8 ABBA pairs,
    # nice 19, load 4-7): the subset calls, gathers and scatters cost more than 15% of BRIEF.
    smoothed = smooth_for_brief(gray)
    brief = compute_brief(smoothed, corners.xy, conf.mu)
    return Keypoints(corners.xy, corners.response, brief, corners.max_response)


def edge_keypoints(
    gray: np.ndarray,
    threshold: float | None,
    conf: EngineConf,
    border: int,
    subpixel: str | None = None,
) -> Keypoints:
    """The corners ``extract_keypoints`` leaves out for its border: those between ``border``
    and ``conf.mu // 2`` pixels from the image edge (detected with the same threshold, among
    the ``max_keypoints`` strongest of the frame with the smaller border), with BRIEF (its test
    window there reads clamped pixels: still the same descriptor frame to frame) for the
    track table."""
    inner = conf.mu // 2
    corners = _corners(gray, threshold, conf, border, subpixel)
    h, w = gray.shape
    x, y = corners.xy[:, 0], corners.xy[:, 1]
    band = (x < inner) | (y < inner) | (x >= w - inner) | (y >= h - inner)
    xy = corners.xy[band]
    brief = compute_brief(smooth_for_brief(gray), xy, conf.mu)
    return Keypoints(xy, corners.response[band], brief, corners.max_response)


def with_keypoints(kps: Keypoints, more: Keypoints) -> Keypoints:
    """``kps`` followed by ``more`` (``kps``'s maximum response: the next frame's threshold)."""
    if len(more) == 0:
        return kps
    return Keypoints(
        np.concatenate([kps.xy, more.xy]),
        np.concatenate([kps.response, more.response]),
        np.concatenate([kps.brief, more.brief]),
        kps.max_response,
    )


def window_pairs(pred: np.ndarray, cand: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray]:
    """All (i, j) with candidate j inside the square window of half-size ``half`` around
    ``pred[i]``, grouped by i (ascending; within a group in no promised order).

    Candidates go into cells of ``half`` rows by ``half / 2`` columns, counted into a table of
    each cell's first index in cell order (one bincount and cumsum, and a radix argsort of the
    cells): a window spans 3 rows, and in each its columns are one range of that order, read
    from the table (two gathers; the binary searches of (row, x)-sorted keys they replace cost
    60 us of a frame's 200, issue 10). Only the ranges' candidates are tested exactly."""
    if len(pred) == 0 or len(cand) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if not 0 < half < np.inf:  # a window of no size, or not finite: no grid
        return _window_pairs_plain(pred, cand, half)
    cx, cy = cand[:, 0], cand[:, 1]
    px, py = pred[:, 0], pred[:, 1]
    row = np.floor(cy / half)
    rmin, rmax = row.min(), row.max()
    x0 = cx.min()
    width = float(cx.max() - x0)
    if not (np.isfinite(rmax - rmin + width) and rmax - rmin < _MAX_CELLS):
        # nor for candidates not finite, or windows below a 4096th of the candidates' height
        return _window_pairs_plain(pred, cand, half)
    # 3 empty rows padded either side (a window's rows are clipped into them) and an empty
    # column either side (its columns likewise): a window off the candidates reads empty cells
    nrow = int(rmax - rmin) + 7
    col_w = half / _COLS_PER_HALF
    if nrow * (width / col_w + 3.0) > _MAX_CELLS:  # wider columns: the table's size bounded
        col_w = max(col_w, width / max(1.0, _MAX_CELLS // nrow - 3.0))
    cols = int(width / col_w) + 3
    # (cx - x0 >= 0: the truncation is the floor)
    cell = (row - (rmin - 3.0)).astype(np.int64) * cols + ((cx - x0) / col_w).astype(np.int64) + 1
    starts = np.zeros(nrow * cols + 1, np.int64)
    np.cumsum(np.bincount(cell, minlength=nrow * cols), out=starts[1:])
    # (int16 cells: numpy's stable argsort is a radix sort, x5 against int64's)
    order = np.argsort(cell.astype(np.int16) if nrow * cols < 2**15 else cell, kind="stable")
    # A window's first row and its column range (end exclusive), clipped to the padding: a
    # prediction far off the image (or not finite: np.fmax takes the bound) reads empty cells.
    # The columns' margin, far above the rounding (1e-13 px), makes the ranges a superset,
    # and the exact test below the window's pairs.
    with np.errstate(invalid="ignore"):
        r0 = np.floor((py - half) / half) - (rmin - 3.0)
        xq = (px - x0) / col_w
    r0 = np.minimum(np.fmax(r0, 0.0), nrow - 3.0)
    m = half * (1.0 + 1e-6) / col_w
    c_lo = np.minimum(np.fmax(np.floor(xq - m) + 1.0, 0.0), cols - 1.0)
    c_end = np.minimum(np.fmax(np.floor(xq + m) + 2.0, 1.0), float(cols))
    rows3 = _ROWS3_INT * cols
    lo = starts[((r0 * cols + c_lo).astype(np.int64)[:, None] + rows3).ravel()]
    lens = starts[((r0 * cols + c_end).astype(np.int64)[:, None] + rows3).ravel()] - lo
    ends = np.cumsum(lens)
    total = int(ends[-1])
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    per_row = lens.reshape(-1, 3)
    # (the three rows' lengths added as columns: .sum(axis=1)'s reduction costs x3 on rows of 3)
    counts = per_row[:, 0] + per_row[:, 1] + per_row[:, 2]
    owner = np.repeat(np.arange(len(pred)), counts)
    k = np.repeat(lo - (ends - lens), lens) + np.arange(total)  # positions in cell order
    # the exact test on the candidates in cell order (one gather fewer than through order[k])
    # against the owners' coordinates repeated (cheaper than gathered); one nonzero, two takes
    t = cy[order][k]
    t -= np.repeat(py, counts)
    inside = np.abs(t, out=t) <= half
    t = cx[order][k]
    t -= np.repeat(px, counts)
    inside &= np.abs(t, out=t) <= half
    at = np.flatnonzero(inside)
    return owner[at], order[k[at]]


# Columns of half / 2: against the binary searches, on the calls of 1000 redkitchen frames,
# x0.77; half / 3 x0.79, half / 4 x0.81 (the larger table); rows of half / 2, 5 a window,
# x0.80. At most _MAX_CELLS cells (wider columns past it): ADD-GOOD-FEATURES' 6 px windows
# would make 19k cells of a 640 x 480 frame, whose bincount and cumsum cost more than the
# wider ranges (2**14 cells x1.15 of 2**12 there; the tracking windows' 1.5k cells unaffected).
_COLS_PER_HALF = 2.0
_MAX_CELLS = 2**12
_ROWS3_INT = np.arange(3, dtype=np.int64)


def _window_pairs_plain(
    pred: np.ndarray, cand: np.ndarray, half: float
) -> tuple[np.ndarray, np.ndarray]:
    """``window_pairs`` by testing every pair, a block of predictions at a time (the cases
    the cell grid does not hold; none of the engine's defaults)."""
    ti, cj = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    step = max(1, (1 << 20) // len(cand))
    for s in range(0, len(pred), step):
        d = np.abs(pred[s : s + step, None, :] - cand[None, :, :])
        i, j = np.nonzero((d[..., 0] <= half) & (d[..., 1] <= half))
        ti.append(i + s)
        cj.append(j)
    return np.concatenate(ti), np.concatenate(cj)


def track_2d(
    table: TrackTable, pred_xy: np.ndarray, kps: Keypoints, conf: EngineConf, dt: float = 0.0
) -> np.ndarray:
    """TRACK-2D: for each row of ``table``, the index of its match among ``kps`` or -1;
    ``dt``: the frame interval (s), which widens the window (``window_size``).

    A candidate claimed by several tracks goes to the closest one (in Hamming distance; the
    lower row on a tie); the others are lost, so identities stay unique."""
    n = len(table)
    match = np.full(n, -1, np.int64)
    if n == 0 or len(kps) == 0:
        return match
    ti, cj = window_pairs(pred_xy, kps.xy, window_size(conf, dt) / 2.0)
    if len(ti) == 0:
        return match
    dist = pair_distances(table.brief, ti, kps.brief, cj)
    # (pairs come grouped by track; written out: np.diff(append=) cost 15 us of Python layers)
    first = np.empty(len(ti), bool)
    first[0] = True
    np.not_equal(ti[1:], ti[:-1], out=first[1:])
    starts = first.nonzero()[0]
    # Per track the smallest (distance, position) key, and with that one pair set aside the
    # next: the best and the second best counted with multiplicity, so a tie for the best
    # gives second == best and fails the ratio test (best < psi best is false), whatever the
    # order within a track; the key's position is the accepted pair. (With the packed sort
    # below, against the best, its count and the best of the others by five reductions and an
    # argsort: track_2d's own CPU 128 -> 94 us a redkitchen frame.)
    key = dist << 32
    key |= np.arange(len(ti))
    low = np.minimum.reduceat(key, starts)
    at = low & 0xFFFFFFFF
    key[at] = _FAR << 32
    best = low >> 32
    second = np.minimum.reduceat(key, starts) >> 32  # _FAR where the best is all there is
    accept = (best <= conf.max_hamming) & (best < conf.psi * second)
    at = at[accept]
    # unique candidates: the closest track wins, the lower row on a tie; one sort of
    # (candidate, distance, row) packed in an int64 (rows < 2**31, distances < 2**9,
    # candidates < 2**23)
    claim = cj[at] << 40
    claim |= best[accept] << 31
    claim |= ti[at]
    claim.sort()
    cand = claim >> 40
    won = np.empty(len(claim), bool)
    won[:1] = True
    np.not_equal(cand[1:], cand[:-1], out=won[1:])
    match[claim[won] & 0x7FFFFFFF] = cand[won]
    return match


def window_size(conf: EngineConf, dt: float) -> float:
    """The tracking window's side (pixels) for a frame ``dt`` seconds after the previous:
    ``rho``, widened in proportion past ``wide_window_gap_s`` (at most ``wide_window_max``
    times): the motion prediction the window is placed at errs more the longer it
    extrapolates, and a window it misses loses the track."""
    if conf.wide_window_gap_s <= 0 or dt <= conf.wide_window_gap_s:
        return float(conf.rho)
    return conf.rho * min(conf.wide_window_max, dt / conf.wide_window_gap_s)


_FAR = np.int64(1 << 20)  # above every distance: "no second candidate"


def pair_distances(a: np.ndarray, i: np.ndarray, b: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Hamming distances (int64) between BRIEF rows ``a[i]`` and ``b[j]``. The four words'
    popcounts (bytes of at most 64) are summed within one uint32 by a shift-and-add step and
    a multiply: a fifth of the CPU of summing the (P, 4) counts along their short axis."""
    x = np.take(a, i, axis=0)
    x ^= np.take(b, j, axis=0)
    c = np.bitwise_count(x).view(np.uint32).ravel()
    c = (c & 0x00FF00FF) + ((c >> 8) & 0x00FF00FF)  # two 16-bit sums of at most 128
    # (hi << 16 | lo) * 0x10001 mod 2**32 = (hi + lo) << 16 | lo, and hi + lo <= 256
    return ((c * 0x10001) >> 16).astype(np.int64)


def free_candidates(
    tracked_xy: np.ndarray, kps: Keypoints, used: np.ndarray, min_dist: float
) -> np.ndarray:
    """ADD-GOOD-FEATURES: indices of candidates not used by a track and not within
    ``min_dist`` of a tracked keypoint (regions where there are no tracked keypoints)."""
    free = np.ones(len(kps), bool)
    free[used[used >= 0]] = False
    if len(tracked_xy) and free.any():
        ti, cj = window_pairs(kps.xy[free], tracked_xy, min_dist)
        blocked = np.zeros(int(free.sum()), bool)
        blocked[ti] = True
        idx = np.nonzero(free)[0]
        free[idx[blocked]] = False
    return np.nonzero(free)[0]
