"""256-bit BRIEF descriptors on mu x mu patches, and Hamming matching (paper Section 3.1).

Calonder et al.'s BRIEF: the image is smoothed, then 256 intensity comparisons between
pixel pairs drawn from an isotropic Gaussian (sigma = mu / 5, their best "G II" layout) inside
the patch give one bit each. BRIEF is neither rotation- nor scale-invariant; frame-to-frame
motion is small enough that it need not be, and it is cheap: one gather per bit.
Descriptors are (N, 4) uint64 so that Hamming distance is XOR + popcount on 4 words.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

N_BITS = 256
N_WORDS = N_BITS // 64


@lru_cache(maxsize=8)
def brief_pattern(patch_size: int = 32, seed: int = 2012) -> np.ndarray:
    """(256, 4) int offsets ``(dx1, dy1, dx2, dy2)`` inside a ``patch_size`` patch."""
    rng = np.random.default_rng(seed)
    half = patch_size // 2 - 1
    pts = np.rint(rng.normal(0.0, patch_size / 5.0, size=(N_BITS, 4)))
    return np.clip(pts, -half, half).astype(np.int64)


def smooth_for_brief(gray: np.ndarray) -> np.ndarray:
    """The smoothing BRIEF needs before its pixel tests (Calonder: a 9x9 Gaussian, sigma 2)."""
    return cv2.GaussianBlur(gray, (9, 9), 2.0)


def compute_brief(smoothed: np.ndarray, xy: np.ndarray, patch_size: int = 32) -> np.ndarray:
    """BRIEF descriptors (N, 4) uint64 at keypoints ``xy`` (COLMAP convention) of a smoothed
    image. Keypoints must lie at least ``patch_size // 2`` pixels from the border (callers
    detect with that border)."""
    n = len(xy)
    if n == 0:
        return np.zeros((0, N_WORDS), np.uint64)
    h, w = smoothed.shape
    pat = brief_pattern(patch_size)
    # COLMAP coordinates -> nearest array index.
    cx = np.clip(np.floor(xy[:, 0]).astype(np.int64), 0, w - 1)
    cy = np.clip(np.floor(xy[:, 1]).astype(np.int64), 0, h - 1)
    flat = smoothed.reshape(-1)
    base = (cy * w + cx)[:, None]
    i1 = np.clip(base + pat[None, :, 1] * w + pat[None, :, 0], 0, flat.size - 1)
    i2 = np.clip(base + pat[None, :, 3] * w + pat[None, :, 2], 0, flat.size - 1)
    bits = flat[i1] < flat[i2]
    packed = np.packbits(bits, axis=1)  # (N, 32) uint8
    return np.ascontiguousarray(packed).view(np.uint64)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between rows of ``a`` and ``b`` (broadcasting over leading dims)."""
    return np.bitwise_count(np.bitwise_xor(a, b)).sum(axis=-1, dtype=np.int32)
