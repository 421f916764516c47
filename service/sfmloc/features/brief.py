"""256-bit BRIEF descriptors on mu x mu patches, and Hamming matching (paper Section 3.1).

Calonder et al.'s BRIEF: the image is smoothed, then 256 intensity comparisons between
pixel pairs drawn from an isotropic Gaussian (sigma = mu / 5, their best "G II" layout) inside
the patch give one bit each. BRIEF is neither rotation- nor scale-invariant; frame-to-frame
motion is small enough that it need not be, and it is cheap: one gather per bit.
Descriptors are (N, 4) uint64 so that Hamming distance is XOR + popcount on 4 words.
"""

from __future__ import annotations

import threading
from functools import lru_cache

import cv2
import numpy as np
from numpy.lib.stride_tricks import as_strided

N_BITS = 256
N_WORDS = N_BITS // 64


@lru_cache(maxsize=8)
def brief_pattern(patch_size: int = 32, seed: int = 2012) -> np.ndarray:
    """(256, 4) int offsets ``(dx1, dy1, dx2, dy2)`` inside a ``patch_size`` patch."""
    rng = np.random.default_rng(seed)
    half = patch_size // 2 - 1
    pts = np.rint(rng.normal(0.0, patch_size / 5.0, size=(N_BITS, 4)))
    return np.clip(pts, -half, half).astype(np.int64)


def smooth_for_brief(gray: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The smoothing BRIEF needs before its pixel tests (Calonder: a 9x9 Gaussian, sigma 2);
    into ``out`` when given (a buffer of ``gray``'s shape and dtype)."""
    # Measured and not taken (issue 10, nice 19, load 11-17): the same Gaussian as
    # cv2.sepFilter2D of its float kernel, x0.62 CPU (0.45 -> 0.28 ms per frame); 0.8% of the
    # pixels 1 grey level off, descriptors 0.14 of 256 bits on average. The bench's accuracy
    # was the same (python -m sfmloc.bench.ab, GaussianBlur / it: redkitchen 1000/1000 both,
    # median 0.279 / 0.282 cm; every-30th and every-60th maps 999 / 999 and 993 / 993;
    # density-6x 237 / 237; synthetic walk 300 / 300; 0 wrong everywhere), but the issue-9
    # gap frames of test_engine (test_no_wrong_tracked_pose_after_a_gap...) tracked other
    # corners and 4 of 12 poses came out wrong. Two 5x5 box passes (x0.37): density-6x lost
    # 14 of 237 frames and gave a wrong pose. BRIEF is frame-to-frame only, but tracking is
    # that sensitive: keep this filter unless the gap case is re-judged with it.
    # Nothing to crop (issue 10): the rows the engine's keypoints' patches span, plus the
    # kernel's 4, are 99.0% of a redkitchen frame's (mean of 1000 frames; median 100%), and
    # the result into a reused per-thread buffer instead of a fresh array was x1.004 of
    # extract_keypoints (interleaved call by call, 1000 frames x 3, nice 19, load 5-7).
    return cv2.GaussianBlur(gray, (9, 9), 2.0, dst=out)


# Keypoints are described this many at a time through per-thread buffers (1 MiB of indices):
# one (N, 512) index array per frame is megabytes of fresh pages, which cost more than the
# gathers themselves.
_CHUNK = 256
_local = threading.local()


@lru_cache(maxsize=16)
def _flat_offsets(patch_size: int, width: int) -> np.ndarray:
    """(512,) offsets in a row-major image of ``width`` columns: the first pixel of each of
    the 256 tests, then the second."""
    pat = brief_pattern(patch_size)
    off = np.concatenate([pat[:, 1] * width + pat[:, 0], pat[:, 3] * width + pat[:, 2]])
    off = off.astype(np.intp)
    off.setflags(write=False)  # shared through the cache
    return off


def _buffers() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    bufs = getattr(_local, "bufs", None)
    if bufs is None:
        bufs = (
            np.empty((_CHUNK, 2 * N_BITS), np.intp),
            np.empty((_CHUNK, 2 * N_BITS), np.uint8),
            np.empty((_CHUNK, N_BITS), bool),
        )
        _local.bufs = bufs
    return bufs


def compute_brief(smoothed: np.ndarray, xy: np.ndarray, patch_size: int = 32) -> np.ndarray:
    """BRIEF descriptors (N, 4) uint64 at keypoints ``xy`` (COLMAP convention) of a smoothed
    image. Keypoints must lie at least ``patch_size // 2`` pixels from the border (callers
    detect with that border); nearer ones read clamped flat indices."""
    n = len(xy)
    if n == 0:
        return np.zeros((0, N_WORDS), np.uint64)
    h, w = smoothed.shape
    # COLMAP coordinates -> nearest array index.
    cx = np.minimum(np.maximum(np.floor(xy[:, 0]).astype(np.intp), 0), w - 1)
    cy = np.minimum(np.maximum(np.floor(xy[:, 1]).astype(np.intp), 0), h - 1)
    flat = np.ascontiguousarray(smoothed)
    packed = np.empty((n, N_BITS // 8), np.uint8)
    # Keypoints whose whole test window lies in the image (all of them, as the engine detects
    # with a border) read their pixels from a copy of that window: one small contiguous
    # patch per keypoint, then the same 512 columns of every patch. The same pixels as the
    # flat gather below (bit for bit), at ~0.75 of its CPU on redkitchen frames (~700
    # keypoints): the gather's (N, 512) index array is 8 bytes per pixel read.
    half = patch_size // 2 - 1
    inside = (cx >= half) & (cx < w - half) & (cy >= half) & (cy < h - half)
    if inside.all():
        _brief_windows(flat, cx, cy, half, patch_size, packed)
    else:
        ins = np.flatnonzero(inside)
        out = np.flatnonzero(~inside)
        if len(ins):
            packed[ins] = _brief_windows(
                flat,
                cx[ins],
                cy[ins],
                half,
                patch_size,
                np.empty((len(ins), N_BITS // 8), np.uint8),
            )
        packed[out] = _brief_gather(flat, cx[out], cy[out], patch_size)
    return packed.view(np.uint64)


@lru_cache(maxsize=16)
def _window_offsets(patch_size: int) -> np.ndarray:
    """(512,) offsets of the tests' pixels in a row-major (2 half + 1)^2 window around the
    keypoint: the first pixel of each of the 256 tests, then the second."""
    half = patch_size // 2 - 1
    side = 2 * half + 1
    pat = brief_pattern(patch_size) + half
    off = np.concatenate([pat[:, 1] * side + pat[:, 0], pat[:, 3] * side + pat[:, 2]])
    off = off.astype(np.intp)
    off.setflags(write=False)  # shared through the cache
    return off


def _brief_windows(
    image: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    half: int,
    patch_size: int,
    packed: np.ndarray,
) -> np.ndarray:
    """BRIEF of keypoints at pixels (cx, cy), each at least ``half`` pixels inside ``image``,
    into ``packed`` (N, 32) uint8."""
    side = 2 * half + 1
    # The windows as one strided view: ``sliding_window_view``'s argument checks took 6% of
    # this function (x0.94, 60 redkitchen frames, interleaved). Measured and not taken: the
    # tests' columns by fancy indexing (x1.3 of np.take), and cv2.remap INTER_NEAREST of an
    # (N, 512) int16 map (x5.7). Where the time goes (~600 keypoints a redkitchen frame, issue
    # 10, load ~6): the patch copy 0.23 ms, the 512 columns 0.22, the tests 0.04, packing 0.02
    # (the smoothing before it 0.41). The 512 test pixels are 345 distinct, but taking those
    # and then the pairs is the same 512 gathers again; the tests' pixels read straight from
    # the strided view (four index arrays, no patch copy) x2.8.
    h, w = image.shape
    s0, s1 = image.strides
    windows = as_strided(
        image, (h - side + 1, w - side + 1, side, side), (s0, s1, s0, s1), writeable=False
    )
    off = _window_offsets(patch_size)
    patches = windows[cy - half, cx - half].reshape(len(cx), side * side)
    # mode="clip": the offsets lie in the window by construction, and numpy's default
    # ("raise") checks each of the N x 512 indices on the way: the copy and this gather
    # 376 -> 357 us on redkitchen frames (~600 keypoints; 0.235 -> 0.147 ms on a cached array)
    v = np.take(patches, off, axis=1, mode="clip")
    packed[:] = np.packbits(np.less(v[:, :N_BITS], v[:, N_BITS:]), axis=1)
    return packed


def _brief_gather(image: np.ndarray, cx: np.ndarray, cy: np.ndarray, patch_size: int) -> np.ndarray:
    """BRIEF of keypoints at pixels (cx, cy) anywhere in ``image``: flat indices of the
    tests' pixels, clamped to the image (``mode="clip"``), (N, 32) uint8."""
    w = image.shape[1]
    base = cy * w + cx
    flat = image.reshape(-1)
    off = _flat_offsets(patch_size, w)
    idx, vals, bits = _buffers()
    n = len(cx)
    packed = np.empty((n, N_BITS // 8), np.uint8)
    for s in range(0, n, _CHUNK):
        e = min(n, s + _CHUNK)
        i, v, t = idx[: e - s], vals[: e - s], bits[: e - s]
        np.add(base[s:e, None], off, out=i)
        np.take(flat, i, mode="clip", out=v)  # "clip": indices clamped to the image
        np.less(v[:, :N_BITS], v[:, N_BITS:], out=t)
        packed[s:e] = np.packbits(t, axis=1)
    return packed


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between rows of ``a`` and ``b`` (broadcasting over leading dims)."""
    return np.bitwise_count(np.bitwise_xor(a, b)).sum(axis=-1, dtype=np.int32)
