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

import threading
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from ..cameras import PIXEL_CENTER_OFFSET

# Sub-pixel localization of the Harris maxima. The Harris maximum of an L-corner sits inside
# the corner, by an offset that depends on the corner's angle and so on the viewpoint; a
# quadratic fit of the response only finds that biased peak more precisely. Forstner's
# operator (as cv2.cornerSubPix) finds the point the edges around the maximum point at.
# Measured on the synthetic walk (exact texture corners, 9800 corners in 30 frames): distance to
# the true corner, median / mean, integer 1.22 / 1.20 px, quadratic 1.27 / 1.24 px, Forstner
# 0.36 / 0.62 px; the median signed bias in y drops from +0.31 to +0.01 px, and map points
# refined at Forstner keypoints are 1.0 mm from the truth instead of 4.8 mm (median). End to
# end (map built with the same method), synthetic walk median error 0.52 -> 0.44 cm, mean
# 0.94 -> 0.61 cm; flight unchanged (0.36 -> 0.37 cm); but redkitchen (400 frames) 0.77 ->
# 1.00 cm, with larger residuals at the ground-truth pose (median 1.37 -> 1.83 px): on real,
# blurred corners the 5x5 step is noisier than the bias it removes, and the map keeps 22% fewer
# descriptors (corners move away from the SfM points' projections, tau = 2 px). With the Cauchy
# final refinement (engine/pose.py): walk 0.41 -> 0.27 cm, flight 0.26 -> 0.29 cm, redkitchen
# 0.62 -> 1.17 cm; a step limited to 1 px with the quadratic fit as fallback: redkitchen still
# 0.52 -> 0.65 cm. Quadratic stays the default; a map built with the builder setting
# {"descriptors": {"subpixel": "forstner"}} is tracked with Forstner corners (EngineConf.subpixel).
SUBPIXEL_METHODS = ("forstner", "quadratic", "none")
SUBPIXEL_DEFAULT = "quadratic"
# One step in a uniform 5x5 window (the support of the Harris window, sigma = 1). Measured on
# the walk above: Gaussian weights (sigma 1, 1.5, 2.5) give medians 0.60, 0.46, 0.39 px against
# 0.36 uniform; iterating (re-centred windows) lowers the median 0.02 px but raises the mean
# (neighbouring corners pull the window away); a 7x7 window is worse (0.55 px).
FORSTNER_RADIUS = 2
FORSTNER_MAX_SHIFT = 1.5  # px; a larger step is not this maximum's corner: keep the pixel


@dataclass
class Corners:
    xy: np.ndarray  # (N, 2) float64, COLMAP pixel convention
    response: np.ndarray  # (N,) float32 cornerness
    max_response: float  # maximum cornerness over the whole image (for the next threshold)

    def __len__(self) -> int:
        return len(self.xy)


class _Workspace:
    """The full-image float32 buffers of one image shape, reused from call to call.

    A fresh 640x480 float32 image is 300 pages the kernel faults in and zeroes on first touch;
    the detector needs six, and with numpy's temporaries for the response the page faults
    cost more than the arithmetic: on this machine the response took 4-20 ms per frame with
    fresh arrays and about 1 ms in reused buffers (the same arithmetic, the same results)."""

    def __init__(self, shape: tuple[int, int]) -> None:
        self.shape = shape
        gx, gy, a, b, c, r = (np.empty(shape, np.float32) for _ in range(6))
        self.gx, self.gy, self.a, self.b, self.c, self.r = gx, gy, a, b, c, r
        self.ge = np.empty(shape, bool)
        self.gt = np.empty(shape, bool)
        self._interleaved: np.ndarray | None = None

    def interleaved(self) -> np.ndarray:
        """An (h, w, 3) float32 buffer, made on first use (widths off the vector width)."""
        if self._interleaved is None:
            self._interleaved = np.empty(self.shape + (3,), np.float32)
        return self._interleaved


# One workspace per thread and image shape (the engine detects at one shape; the builder's
# pyramid cycles through several). Images over the pixel limit get a workspace per call, so a
# long-lived process does not hold the 30 bytes per pixel of a large image.
_CACHE_SHAPES = 2
# Widths at which one-channel and interleaved blurs round alike: a multiple of every vector
# width (AVX-512: 16 floats), so neither has a scalar tail. 640, 320, 1280 are.
_SIMD_COLUMNS = 16
_CACHE_MAX_PIXELS = 1 << 20
_local = threading.local()


def _workspace(shape: tuple[int, int]) -> _Workspace:
    if shape[0] * shape[1] > _CACHE_MAX_PIXELS:
        return _Workspace(shape)
    cache: OrderedDict[tuple[int, int], _Workspace] | None = getattr(_local, "cache", None)
    if cache is None:
        cache = _local.cache = OrderedDict()
    ws = cache.pop(shape, None) or _Workspace(shape)
    cache[shape] = ws
    while len(cache) > _CACHE_SHAPES:
        cache.popitem(last=False)
    return ws


def _response_into(gray: np.ndarray, sigma: float, k: float, ws: _Workspace) -> np.ndarray:
    """The Harris response of ``gray`` in ``ws.r`` (gradients in ``ws.gx``, ``ws.gy``),
    computed in the workspace's buffers: no full-image allocation. The arithmetic is that of
    ``det(M) - k trace(M)^2`` written as numpy expressions, operation for operation (float32,
    no fused multiply-add), so the response is bit-identical to the plain formula."""
    ksize = int(2 * round(2.5 * sigma) + 1)
    g = (ksize, ksize)
    scale = 1.0 / 8.0  # Sobel / 8: unit pixel steps
    cv2.Sobel(gray, cv2.CV_32F, 1, 0, dst=ws.gx, ksize=3, scale=scale)
    cv2.Sobel(gray, cv2.CV_32F, 0, 1, dst=ws.gy, ksize=3, scale=scale)
    if gray.shape[1] % _SIMD_COLUMNS == 0:
        # M's entries as contiguous planes, each blurred in place (a third faster than the
        # interleaved image below, and bit-identical to it at such widths).
        for u, v, out in ((ws.gx, ws.gx, ws.a), (ws.gy, ws.gy, ws.b), (ws.gx, ws.gy, ws.c)):
            np.multiply(u, v, out=out)
            cv2.GaussianBlur(out, g, sigma, dst=out)
        a, b, c = ws.a, ws.b, ws.c
        p, t = c, a  # scratch: c once c * c is taken, a once a + b is
    else:
        # At other widths OpenCV's vector loops end on a scalar tail at different columns for
        # one and three channels, and the last columns differ in rounding: blur the three
        # products as one interleaved image, as the detector always did.
        m = ws.interleaved()
        np.multiply(ws.gx, ws.gx, out=m[..., 0])
        np.multiply(ws.gy, ws.gy, out=m[..., 1])
        np.multiply(ws.gx, ws.gy, out=m[..., 2])
        cv2.GaussianBlur(m, g, sigma, dst=m)
        a, b, c = m[..., 0], m[..., 1], m[..., 2]
        p, t = ws.b, ws.c
    r = ws.r
    # ((a * b) - (c * c)) - ((k * (a + b)) * (a + b))
    np.multiply(a, b, out=r)
    np.multiply(c, c, out=p)
    np.subtract(r, p, out=r)
    np.add(a, b, out=p)
    np.multiply(k, p, out=t)
    np.multiply(t, p, out=t)
    np.subtract(r, t, out=r)
    return r


def harris_response(gray: np.ndarray, sigma: float = 1.0, k: float = 0.04) -> np.ndarray:
    """Harris cornerness ``det(M) - k trace(M)^2`` (float32), M from Sobel gradients
    integrated with a Gaussian of ``sigma`` pixels. Gradients are scaled to unit pixel steps
    (Sobel / 8) so the response is comparable across images and pyramid levels."""
    if gray.ndim != 2:
        raise ValueError(f"expected a grayscale image, got shape {gray.shape}")
    return _response_into(gray, sigma, k, _workspace(gray.shape)).copy()


def detect_corners(
    gray: np.ndarray,
    *,
    threshold: float | None = None,
    rel_threshold: float = 0.001,
    max_corners: int = 0,
    border: int = 0,
    mask: np.ndarray | None = None,
    sigma: float = 1.0,
    subpixel: bool | str = True,
) -> Corners:
    """Harris corners of a uint8 grayscale image.

    ``threshold`` is an absolute cornerness threshold (the adaptive ``gamma * r_max`` of the
    previous frame); when None, ``rel_threshold`` times this image's maximum is used.
    ``border`` drops corners closer than that to the image edge (descriptor support);
    ``mask`` (uint8, nonzero = allowed) restricts where corners may be; ``max_corners`` > 0
    keeps the strongest. ``subpixel`` locates each maximum to sub-pixel precision (pose
    accuracy depends on it): "forstner" moves it to the point where the edges around it meet,
    "quadratic" (or True) to the peak of a quadratic fit of the response, "none" (or False)
    keeps the pixel.
    """
    method = SUBPIXEL_DEFAULT if subpixel is True else ("none" if subpixel is False else subpixel)
    if method not in SUBPIXEL_METHODS:
        raise ValueError(f"subpixel must be one of {SUBPIXEL_METHODS}, got {subpixel!r}")
    if gray.ndim != 2:
        raise ValueError(f"expected a grayscale image, got shape {gray.shape}")
    h, w = gray.shape
    ws = _workspace(gray.shape)
    R = _response_into(gray, sigma, 0.04, ws)
    r_max = float(R.max()) if R.size else 0.0
    thr = threshold if threshold is not None else rel_threshold * r_max
    thr = max(float(thr), 1e-12)
    # 3x3 local maxima above the threshold. Contiguous full-image masks: np.flatnonzero on one
    # is ~10x faster than np.nonzero on a strided view of the interior.
    dil = cv2.dilate(R, _KERNEL_3X3, dst=ws.b)
    cand = np.greater_equal(R, dil, out=ws.ge)
    np.logical_and(cand, np.greater(R, thr, out=ws.gt), out=cand)
    if border > 0:
        cand[:border, :] = False
        cand[-border:, :] = False
        cand[:, :border] = False
        cand[:, -border:] = False
    if mask is not None:
        np.logical_and(cand, mask != 0, out=cand)
    ys, xs = np.divmod(np.flatnonzero(cand), w)
    resp = R[ys, xs]
    if max_corners and len(xs) > max_corners:
        keep = np.argpartition(-resp, max_corners - 1)[:max_corners]
        keep.sort()  # raster order, deterministic
        xs, ys, resp = xs[keep], ys[keep], resp[keep]
    xy = np.stack([xs, ys], axis=1).astype(np.float64)
    if method == "quadratic" and len(xs):
        xy += _subpixel_offsets(R, xs, ys)
    elif method == "forstner" and len(xs):
        xy += _forstner_offsets(ws.gx, ws.gy, xs, ys)
    xy += PIXEL_CENTER_OFFSET
    if border > 0 and len(xy):  # a sub-pixel step may not cross the border (descriptor support)
        xy = np.clip(xy, border, np.array([w - border, h - border], np.float64))
    return Corners(xy=xy, response=resp.astype(np.float32), max_response=r_max)


_KERNEL_3X3 = np.ones((3, 3), np.uint8)


def _subpixel_offsets(R: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Offsets of the maximum of a 2D quadratic fitted to the 3x3 responses around each
    maximum (Newton step ``-H^-1 g`` with central differences, including the cross term, which
    matters for corners whose peak is elongated along a diagonal); clipped to half a pixel."""
    h, w = R.shape
    f = R.ravel()  # flat gathers: a third of the cost of R[ys, xs] pairs
    xm, xp = np.clip(xs - 1, 0, w - 1), np.clip(xs + 1, 0, w - 1)
    ym, yp = np.clip(ys - 1, 0, h - 1) * w, np.clip(ys + 1, 0, h - 1) * w
    y0 = ys * w
    c = f[y0 + xs].astype(np.float64)
    r_ym = f[ym + xs]
    r_yp = f[yp + xs]
    r_xm = f[y0 + xm]
    r_xp = f[y0 + xp]
    gx = 0.5 * (r_xp - r_xm)
    gy = 0.5 * (r_yp - r_ym)
    hxx = r_xp - 2 * c + r_xm
    hyy = r_yp - 2 * c + r_ym
    hxy = 0.25 * (f[yp + xp] - f[yp + xm] - f[ym + xp] + f[ym + xm])
    det = hxx * hyy - hxy * hxy
    ok = (det > 0) & (hxx < 0)  # a proper maximum
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = np.where(ok, -(hyy * gx - hxy * gy) / det, 0.0)
        dy = np.where(ok, -(hxx * gy - hxy * gx) / det, 0.0)
    return np.stack([np.clip(dx, -0.5, 0.5), np.clip(dy, -0.5, 0.5)], axis=1)


_FO = np.arange(-FORSTNER_RADIUS, FORSTNER_RADIUS + 1)
_FO_Y_INT, _FO_X_INT = (a.ravel() for a in np.meshgrid(_FO, _FO, indexing="ij"))
_FOX, _FOY = _FO_X_INT.astype(np.float64), _FO_Y_INT.astype(np.float64)


def _forstner_offsets(gx: np.ndarray, gy: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Offsets from each pixel to the least-squares intersection of the edge lines in the
    window around it (Forstner): the point c minimizing ``sum_p (g_p . (p - c))^2``, one
    closed-form step. Where that system is ill-conditioned or the step leaves the window's
    core, the offset is 0."""
    h, w = gx.shape
    px = np.clip(xs[:, None] + _FO_X_INT, 0, w - 1)
    py = np.clip(ys[:, None] + _FO_Y_INT, 0, h - 1)
    flat = py * w + px
    a = gx.ravel()[flat].astype(np.float64)
    b = gy.ravel()[flat].astype(np.float64)
    gaa, gbb, gab = a * a, b * b, a * b
    aa, bb, ab = gaa.sum(1), gbb.sum(1), gab.sum(1)
    # sum g g^T (p - centre)
    qx = gaa @ _FOX + gab @ _FOY
    qy = gab @ _FOX + gbb @ _FOY
    det = aa * bb - ab * ab
    tr = aa + bb
    ok = det > 1e-3 * tr * tr  # two independent edge directions
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = (bb * qx - ab * qy) / det
        dy = (aa * qy - ab * qx) / det
    ok &= (np.abs(dx) <= FORSTNER_MAX_SHIFT) & (np.abs(dy) <= FORSTNER_MAX_SHIFT)
    return np.stack([np.where(ok, dx, 0.0), np.where(ok, dy, 0.0)], axis=1)
