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
    ``pred[i]``, grouped by i (ascending). Candidates are sorted by (row of height ``half``,
    x): a window spans 3 rows, and in each its candidates in x are one range of that order
    (two binary searches), so only the rows' 3 x 2 ``half`` strip is tested, not 3 x 3 cells."""
    if len(pred) == 0 or len(cand) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cx, cy = cand[:, 0], cand[:, 1]
    px, py = pred[:, 0], pred[:, 1]
    row = np.floor(cy / half)
    x0 = cx.min()
    width = float(cx.max() - x0)
    # key = row * span + (x - x0); span leaves more than 6 half between rows, so a range
    # reaching 3 half (half past a clipped x below) beyond either end of a row stays in it
    span = float(2.0 ** np.ceil(np.log2(width + 8.0 * half + 1.0)))
    key = row * span + (cx - x0)
    order = np.argsort(key, kind="stable")
    skey = key[order]
    # A window's first row, and its x, clipped to just outside the candidates' rows and
    # columns: a prediction far off the image (or not finite) looks at empty ranges.
    with np.errstate(invalid="ignore"):
        r0 = np.floor((py - half) / half)
        xq = px - x0
    rlo, rhi = row.min() - 3.0, row.max() + 1.0
    # (np.fmax: the lower bound where NaN, as np.where(np.isnan) then np.maximum gave)
    r0 = np.minimum(np.fmax(r0, rlo), rhi)
    xq = np.minimum(np.fmax(xq, -2.0 * half), width + 2.0 * half)
    # the ranges of the three rows; a margin far above the keys' rounding (1e-12 px at image
    # coordinates) makes them a superset, and the exact test below the window's pairs
    margin = half + 1e-6 * span
    base = (r0[:, None] + _ROWS3) * span + xq[:, None]
    lo = np.searchsorted(skey, (base - margin).ravel(), "left")
    lens = np.searchsorted(skey, (base + margin).ravel(), "right") - lo
    ends = np.cumsum(lens)
    total = int(ends[-1])
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    per_row = lens.reshape(-1, 3)
    # (the three rows' lengths added as columns: .sum(axis=1)'s reduction costs x3 on rows of 3)
    owner = np.repeat(np.arange(len(pred)), per_row[:, 0] + per_row[:, 1] + per_row[:, 2])
    j = order[np.repeat(lo - (ends - lens), lens) + np.arange(total)]
    inside = np.abs(cy[j] - py[owner]) <= half
    inside &= np.abs(cx[j] - px[owner]) <= half
    return owner[inside], j[inside]


_ROWS3 = np.arange(3, dtype=np.float64)


def track_2d(
    table: TrackTable, pred_xy: np.ndarray, kps: Keypoints, conf: EngineConf, dt: float = 0.0
) -> np.ndarray:
    """TRACK-2D: for each row of ``table``, the index of its match among ``kps`` or -1;
    ``dt``: the frame interval (s), which widens the window (``window_size``).

    A candidate claimed by several tracks goes to the closest one (in Hamming distance); the
    others are lost, so identities stay unique."""
    n = len(table)
    match = np.full(n, -1, np.int64)
    if n == 0 or len(kps) == 0:
        return match
    ti, cj = window_pairs(pred_xy, kps.xy, window_size(conf, dt) / 2.0)
    if len(ti) == 0:
        return match
    dist = pair_distances(table.brief, ti, kps.brief, cj)
    # per track (pairs come grouped by track): the best distance, how many candidates have
    # it, and the best of the others. A tie for the best fails the ratio test (best < psi best
    # is false), so the accepted best is always one pair, whatever the order within a track.
    # (written out: np.concatenate of a list and np.diff(append=) cost 15 us of Python layers)
    first = np.empty(len(ti), bool)
    first[0] = True
    np.not_equal(ti[1:], ti[:-1], out=first[1:])
    starts = first.nonzero()[0]
    lens = np.empty_like(starts)
    np.subtract(starts[1:], starts[:-1], out=lens[:-1])
    lens[-1] = len(ti) - starts[-1]
    best = np.minimum.reduceat(dist, starts)
    is_best = dist == np.repeat(best, lens)
    n_best = np.add.reduceat(is_best, starts, dtype=np.int64)
    second = np.minimum.reduceat(np.where(is_best, _FAR, dist), starts)
    second = np.where(n_best > 1, best, second)  # _FAR where the best is all there is
    accept = (best <= conf.max_hamming) & (best < conf.psi * second)
    pick = is_best & np.repeat(accept, lens)
    at = pick.nonzero()[0]  # (one nonzero for the three gathers)
    rows, cands, bdist = ti[at], cj[at], dist[at]
    # unique candidates: the closest track wins
    o = np.argsort(cands * 257 + bdist, kind="stable")
    rows, cands = rows[o], cands[o]
    uniq = np.ones(len(cands), bool)
    uniq[1:] = cands[1:] != cands[:-1]
    match[rows[uniq]] = cands[uniq]
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
    popcounts (bytes of at most 64) are summed within one uint32 by two shift-and-add steps:
    a fifth of the CPU of summing the (P, 4) counts along their short axis."""
    x = np.take(a, i, axis=0)
    x ^= np.take(b, j, axis=0)
    c = np.bitwise_count(x).view(np.uint32).ravel()
    c = (c & 0x00FF00FF) + ((c >> 8) & 0x00FF00FF)  # two 16-bit sums of at most 128
    return ((c & 0xFFFF) + (c >> 16)).astype(np.int64)


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
