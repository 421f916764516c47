"""Harris corners with a contrast-adaptive threshold (paper Section 3.1).

The cornerness is the Harris response of Sobel gradients integrated with a Gaussian window.
Candidates are the pixels that are 3x3 local maxima of the response and exceed
``threshold``; the paper sets the threshold to ``gamma * r_max`` of the previous frame
(gamma = 0.001) so that it adapts to contrast. We keep the 3x3 local-maximum test: without
it every pixel of a blob-like corner passes, and the neighbours of one corner carry nearly
identical BRIEF descriptors, which defeats the best/second-best ratio test of the tracker.
No other suppression (no minimum distance between corners) is applied, as in the paper.
A cap on the count keeps the per-frame cost bounded on highly textured frames; the strongest
corners are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..cameras import PIXEL_CENTER_OFFSET


@dataclass
class Corners:
    xy: np.ndarray  # (N, 2) float64, COLMAP pixel convention
    response: np.ndarray  # (N,) float32 cornerness
    max_response: float  # maximum cornerness over the whole image (for the next threshold)

    def __len__(self) -> int:
        return len(self.xy)


def harris_response(gray: np.ndarray, sigma: float = 1.0, k: float = 0.04) -> np.ndarray:
    """Harris cornerness ``det(M) - k trace(M)^2`` (float32), M from Sobel gradients
    integrated with a Gaussian of ``sigma`` pixels. Gradients are scaled to unit pixel steps
    (Sobel / 8) so the response is comparable across images and pyramid levels."""
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
    ksize = int(2 * round(2.5 * sigma) + 1)
    # The three products as one interleaved 3-channel image: one blur call instead of three
    # (measured 1.0 vs 1.5 ms at 640x480).
    m = np.empty(gx.shape + (3,), np.float32)
    np.multiply(gx, gx, out=m[..., 0])
    np.multiply(gy, gy, out=m[..., 1])
    np.multiply(gx, gy, out=m[..., 2])
    m = cv2.GaussianBlur(m, (ksize, ksize), sigma)
    a, b, c = m[..., 0], m[..., 1], m[..., 2]
    tr = a + b
    return a * b - c * c - k * tr * tr


def detect_corners(
    gray: np.ndarray,
    *,
    threshold: float | None = None,
    rel_threshold: float = 0.001,
    max_corners: int = 0,
    border: int = 0,
    mask: np.ndarray | None = None,
    sigma: float = 1.0,
    subpixel: bool = True,
) -> Corners:
    """Harris corners of a uint8 grayscale image.

    ``threshold`` is an absolute cornerness threshold (the adaptive ``gamma * r_max`` of the
    previous frame); when None, ``rel_threshold`` times this image's maximum is used.
    ``border`` drops corners closer than that to the image edge (descriptor support);
    ``mask`` (uint8, nonzero = allowed) restricts where corners may be; ``max_corners`` > 0
    keeps the strongest. ``subpixel`` refines each maximum with a 2D quadratic fit of the
    response (pose accuracy depends on it).
    """
    if gray.ndim != 2:
        raise ValueError(f"expected a grayscale image, got shape {gray.shape}")
    R = harris_response(gray, sigma=sigma)
    r_max = float(R.max()) if R.size else 0.0
    thr = threshold if threshold is not None else rel_threshold * r_max
    thr = max(float(thr), 1e-12)
    # 3x3 local maxima above the threshold.
    dil = cv2.dilate(R, np.ones((3, 3), np.uint8))
    cand = (R >= dil) & (R > thr)
    if border > 0:
        cand[:border, :] = False
        cand[-border:, :] = False
        cand[:, :border] = False
        cand[:, -border:] = False
    if mask is not None:
        cand &= mask.astype(bool)
    ys, xs = np.nonzero(cand)
    resp = R[ys, xs]
    if max_corners and len(xs) > max_corners:
        keep = np.argpartition(-resp, max_corners - 1)[:max_corners]
        keep.sort()  # raster order, deterministic
        xs, ys, resp = xs[keep], ys[keep], resp[keep]
    xy = np.stack([xs, ys], axis=1).astype(np.float64)
    if subpixel and len(xs):
        xy += _subpixel_offsets(R, xs, ys)
    xy += PIXEL_CENTER_OFFSET
    return Corners(xy=xy, response=resp.astype(np.float32), max_response=r_max)


def _subpixel_offsets(R: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Offsets of the maximum of a 2D quadratic fitted to the 3x3 responses around each
    maximum (Newton step ``-H^-1 g`` with central differences, including the cross term, which
    matters for corners whose peak is elongated along a diagonal); clipped to half a pixel."""
    h, w = R.shape
    xm, xp = np.clip(xs - 1, 0, w - 1), np.clip(xs + 1, 0, w - 1)
    ym, yp = np.clip(ys - 1, 0, h - 1), np.clip(ys + 1, 0, h - 1)
    c = R[ys, xs].astype(np.float64)
    gx = 0.5 * (R[ys, xp] - R[ys, xm])
    gy = 0.5 * (R[yp, xs] - R[ym, xs])
    hxx = R[ys, xp] - 2 * c + R[ys, xm]
    hyy = R[yp, xs] - 2 * c + R[ym, xs]
    hxy = 0.25 * (R[yp, xp] - R[yp, xm] - R[ym, xp] + R[ym, xm])
    det = hxx * hyy - hxy * hxy
    ok = (det > 0) & (hxx < 0)  # a proper maximum
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = np.where(ok, -(hyy * gx - hxy * gy) / det, 0.0)
        dy = np.where(ok, -(hxx * gy - hxy * gx) / det, 0.0)
    return np.stack([np.clip(dx, -0.5, 0.5), np.clip(dy, -0.5, 0.5)], axis=1)
