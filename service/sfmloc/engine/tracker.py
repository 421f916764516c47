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
    ``pred[i]``, grouped by i (ascending). Candidates are bucketed in cells of size ``half``,
    so a window overlaps at most 3x3 cells (56% of the area of 2x2 cells of size 2*half)."""
    if len(pred) == 0 or len(cand) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    c = np.floor(cand / half).astype(np.int64)  # (M, 2) cell of each candidate
    # A window's first cell, clipped to just outside the candidates' cells: a prediction far
    # off the image (or not finite) then looks at empty cells, and the grid stays small.
    lo, hi = c.min(axis=0) - 3, c.max(axis=0) + 1
    with np.errstate(invalid="ignore"):
        w = np.floor((pred - half) / half)
    w = np.minimum(np.maximum(np.where(np.isnan(w), lo, w), lo), hi).astype(np.int64)
    ncols, nrows = hi[0] + 3 - lo[0], hi[1] + 3 - lo[1]
    c -= lo
    cid = c[:, 1] * ncols + c[:, 0]
    counts = np.bincount(cid, minlength=ncols * nrows)
    first = np.cumsum(counts) - counts
    order = np.argsort(cid, kind="stable")
    # the 3x3 cells of each window
    offs3 = (np.arange(3)[:, None] * ncols + np.arange(3)[None, :]).ravel()
    w -= lo
    cells = (w[:, 1] * ncols + w[:, 0])[:, None] + offs3
    lens = counts[cells].ravel()
    ends = np.cumsum(lens)
    total = int(ends[-1])
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    owner = np.repeat(np.arange(len(pred)), lens.reshape(-1, 9).sum(axis=1))
    # position in ``order`` of each pair: its cell's first candidate plus its rank in the cell
    j = order[np.repeat(first[cells].ravel() - (ends - lens), lens) + np.arange(total)]
    d = np.abs(cand[j] - pred[owner])
    inside = (d[:, 0] <= half) & (d[:, 1] <= half)
    return owner[inside], j[inside]


def track_2d(
    table: TrackTable, pred_xy: np.ndarray, kps: Keypoints, conf: EngineConf
) -> np.ndarray:
    """TRACK-2D: for each row of ``table``, the index of its match among ``kps`` or -1.

    A candidate claimed by several tracks goes to the closest one (in Hamming distance); the
    others are lost, so identities stay unique."""
    n = len(table)
    match = np.full(n, -1, np.int64)
    if n == 0 or len(kps) == 0:
        return match
    ti, cj = window_pairs(pred_xy, kps.xy, conf.rho / 2.0)
    if len(ti) == 0:
        return match
    dist = np.bitwise_count(table.brief[ti] ^ kps.brief[cj]).sum(axis=1, dtype=np.int64)
    # by track, then distance (<= 256): one stable sort of a combined key
    order = np.argsort(ti * 257 + dist, kind="stable")
    ti, cj, dist = ti[order], cj[order], dist[order]
    first = np.ones(len(ti), bool)
    first[1:] = ti[1:] != ti[:-1]
    best_pos = np.nonzero(first)[0]
    has_second = np.zeros(len(best_pos), bool)
    second = np.full(len(best_pos), np.iinfo(np.int32).max, np.int64)
    nxt = best_pos + 1
    ok = nxt < len(ti)
    ok[ok] &= ti[nxt[ok]] == ti[best_pos[ok]]
    has_second[ok] = True
    second[ok] = dist[nxt[ok]]
    best = dist[best_pos].astype(np.int64)
    accept = (best <= conf.max_hamming) & (~has_second | (best < conf.psi * second))
    rows, cands, bdist = ti[best_pos][accept], cj[best_pos][accept], best[accept]
    # unique candidates: the closest track wins
    o = np.argsort(cands * 257 + bdist, kind="stable")
    rows, cands = rows[o], cands[o]
    uniq = np.ones(len(cands), bool)
    uniq[1:] = cands[1:] != cands[:-1]
    match[rows[uniq]] = cands[uniq]
    return match


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
