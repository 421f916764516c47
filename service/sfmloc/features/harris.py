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


# The detector computes on the raw Sobel of the uint8 image (int16, one cv2.spatialGradient
# pass) rather than on Sobel / 8 in float32. Raw Sobel values are integers below 2^11 in
# magnitude and their products integers below 2^21, exact in float32, so every plane
# downstream is the unit-step one times a power of two (M x 64, the response x 4096); scaling
# by a power of two commutes with float rounding, so responses, maxima and sub-pixel offsets
# are bit for bit those of the unit-step formula (tests/test_feature_kernels.py).
# Measured per 640x480 redkitchen frame (load ~9, one process): both gradients 0.11 ms against
# 0.29 for two float32 Sobels, the three products 0.36 against 0.52 ms.
#
# Detectors measured against this one and not taken (issue 10; 50 redkitchen frames, tracker
# settings, load ~24; time per frame with their NMS, share of our corners with one of theirs
# within 1 / 2 px): ours 3.2 ms; cv2.cornerHarris (5x5 box window) 3.8 ms, 55% / 78%;
# cv2.cornerMinEigenVal 4.3 ms, 50% / 81%; FAST (threshold 10, its NMS, strongest 1500)
# 2.1 ms, 42% / 78%; ORB's FAST then Harris at FAST pixels 3.0 ms, 42% / 78%; our Harris at half
# resolution 1.3 ms, 11% / 32% (the rendered walk: the same picture). None is both much
# cheaper and the same corners, and the map's descriptors and refined points sit at these
# corners (tau = 2 px, sub-pixel): a detector change needs every map rebuilt for a gain of at
# most 1-2 ms. Computing the response only where a cheap bound (a b >= response) passes the
# threshold is exact but slower: the bound passes 24% of a frame's pixels.
# Candidate-first, measured and not taken (issue 10, engine only): FAST (no suppression)
# picks pixels and this response is computed only at their 3x3 neighbourhoods, bit for bit
# (each pixel's 9x9 patch laid side by side in one 9-row image through these same OpenCV
# passes), then this maximum test, threshold, cap and quadratic step: where it finds a corner
# it is this detector's, to the bit (116,192 corners, none extra). But a candidate costs ~1.2
# us (its 81 pixels at the dense pass's ~11 ns each), and FAST is a poor guide to the ~600
# maxima of a frame: at threshold 10 it fires on 8,300 pixels and hits 73% of them (its 7_12
# pattern 3,800 and 55%, 5_8 under 3% at any threshold). 200 redkitchen frames at the
# tracker's settings, interleaved call by call (nice 19, load 0.1-1.0; 3.28-3.42 ms here),
# FAST threshold 10: x2.98, 73% of our corners at
# the same sub-pixel position (89% of the pose inliers of a 300-frame replay); 10 plus two
# steps up the response to the neighbour's maximum: x4.54, 96% (99.6%); 20: x0.85, 48% (74%);
# 25: x0.65, 37% (64%); 30: x0.49, 28% (53%); 20 with its NMS: x0.32, 16% (24%). The synthetic
# walk, flight and orbit (100 frames each) are worse (x3.9-5.2 for 97%). Free gathering would
# still save under 1 ms: FAST 10 has a pixel within 2 px of 98.4% of our corners, and FAST plus
# its patches' share of the image (34%) times this pass is 1.32 against 2.22 ms; grouping the
# candidates into boxes (cv2.connectedComponentsWithStats) costs 1.56 ms. It wins on large,
# sharp frames, which the engine never detects at (it works at 640x480 at most): the walk at
# 3072x2048, threshold 20 plus two steps, x0.33 for 99.9%; redkitchen upsampled to 1920x1440
# x0.16 but 62%.
# Also measured and not taken (issue 10, 50 redkitchen frames in one process, nice 19, load
# 7-16; each bit-identical to this code): the tensor and response in strips of 16 / 32 / 64
# rows that stay in L2 (x1.15-1.29 / x0.96-0.98 / x0.90-0.98 of the whole-image passes: they
# are not memory-bound); the 3x3 maximum tested by 8 gathers at the pixels over the threshold
# instead of cv2.dilate (0.53 -> 0.64 ms); interleaved call by call, the response's seven
# passes as cv2.multiply / subtract / add (x1.16) and cv2.sepFilter2D for the Gaussian (x0.99).
# Compiled kernels measured and not taken (issue 10; numba 0.68.1, one thread, parallel=False,
# fastmath=False, cache=True; redkitchen, interleaved call by call, nice 19, load 10-17). One
# fused pass (Sobel, products, 5-tap rows into a 5-row ring, 5-tap columns, response, and the 3x3
# maximum test of the row above at the engine's threshold; LLVM vectorizes it to AVX-512):
# 3.49 against 3.97 ms per detect_corners call (x0.88; 50 frames x 5). The response alone was
# x0.87-0.92 of _Tensor + response_into; a separate compiled maximum test was slower than
# cv2.dilate and the compare (0.83 against 0.76 ms). At 1920x1440 x0.29-0.36, only because images
# over 1 MP got fresh buffers here then (page faults; now an arena, below).
# The same corners: the same pixels in every frame (200 frames, 60,361 corners), sub-pixel
# positions within 2.9e-5 px, 47% of the response pixels bit for bit; the rest differ by 1-2 ulp
# (relative 1.6e-6 at most) because OpenCV's symmetric row filter rounds through fused
# multiply-adds, which numba without fastmath never emits (that order emulated in numpy matches
# 83% of the row pass). BRIEF's 256 tests compiled: bit-identical, 0.57 against 0.73 ms (570
# keypoints). Both in the engine (1000 frames, replays main / numba / numba / main, load 7-10):
# CPU per frame after the first x0.954 and x0.899 (-0.5 and -1.3 ms; frame by frame median
# x0.947, x0.905), poses within 2e-8 m of these kernels' (29% bit for bit), accuracy the same
# (1000/1000, median 0.279 cm, 0 wrong). Less than the 2 ms asked of a new dependency that costs
# 208 MB installed (llvmlite 173 MB), 0.6 s CPU at each worker start to import numba and load
# its cache (the first frame 88-120 -> 389-577 ms; 4.7 s CPU compiling without a cache), and an
# on-disk cache that numba pickles (we read no pickle from disk).
# Exact cuts (issue 10; the same corners, responses, maxima bit for bit; extract_keypoints
# interleaved call by call against the code before, redkitchen 1000 frames, nice 19, load
# 4-7): the response's (k p) p as one scaled cv2.multiply (x0.98 of the call) and the maximum
# test on the rows a corner may lie in (x0.99). Measured and not taken: the tensor, response
# and maximum test on the interior only (the border plus the filters' 4 px): r_max, the next
# frame's threshold, is the whole image's, and lay within 15 px of the edge on 19 of 200
# frames (every 5th); the bound (1/4 - k) max(gx^2 + gy^2)^2 over that ring cleared it on 7
# (median 5.9x the interior maximum), so the ring's response is needed anyway, and the ring is
# 11% of the pixels. The quadratic step's nine gathers as one (3, 3, N) gather (124 -> 66 us
# alone): x1.001 of the call. The products from float32 copies of dx, dy (0.35 -> 0.45 ms);
# the Gaussian out of place (164 -> 194 us a plane).
_M_SCALE = 64.0  # (Sobel / 8)^2 -> Sobel^2
_R_SCALE = _M_SCALE * _M_SCALE
_INV_R_SCALE = np.float32(1.0 / _R_SCALE)


class _Workspace:
    """The full-image buffers of one image shape, reused from call to call.

    A fresh 640x480 float32 image is 300 pages the kernel faults in and zeroes on first touch;
    with numpy's temporaries for the response the page faults cost more than the arithmetic:
    on this machine the response took 4-20 ms per frame with fresh arrays and about 1 ms in
    reused buffers (the same arithmetic, the same results)."""

    dx: np.ndarray
    dy: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    r: np.ndarray
    s: np.ndarray
    gt: np.ndarray
    m: np.ndarray
    # (dtype, trailing shape) of each buffer, in arena order; the interleaved (h, w, 3) one is
    # needed only at widths off the vector width (``_Tensor``)
    _LAYOUT = (
        ("dx", np.int16, ()),
        ("dy", np.int16, ()),
        ("a", np.float32, ()),
        ("b", np.float32, ()),
        ("c", np.float32, ()),
        ("r", np.float32, ()),
        ("s", np.float32, ()),
        ("gt", np.bool_, ()),
        ("m", np.float32, (3,)),
    )

    def __init__(self, shape: tuple[int, int], arena: np.ndarray | None = None) -> None:
        """Buffers for ``shape``: views into ``arena`` (uint8, at least ``nbytes(shape)``), or
        fresh arrays."""
        self.shape = shape
        at = 0
        for name, dtype, tail in self._buffers(shape):
            full = shape + tail
            if arena is None:
                buf = np.empty(full, dtype)
            else:
                n = int(np.prod(full)) * np.dtype(dtype).itemsize
                buf = arena[at : at + n].view(dtype).reshape(full)
                at += _aligned(n)
            setattr(self, name, buf)

    @classmethod
    def _buffers(cls, shape: tuple[int, int]) -> tuple:
        return cls._LAYOUT if shape[1] % _SIMD_COLUMNS else cls._LAYOUT[:-1]

    @classmethod
    def nbytes(cls, shape: tuple[int, int]) -> int:
        """The arena bytes ``shape``'s buffers take (26 per pixel, 38 off the vector width)."""
        px = shape[0] * shape[1]
        return sum(
            _aligned(px * int(np.prod(t, dtype=np.int64)) * np.dtype(d).itemsize)
            for _, d, t in cls._buffers(shape)
        )

    def interleaved(self) -> np.ndarray:
        """The (h, w, 3) float32 buffer (widths off the vector width)."""
        return self.m


# Widths at which one-channel and interleaved blurs round alike: a multiple of every vector
# width (AVX-512: 16 floats), so neither has a scalar tail. 640, 320, 1280 are.
_SIMD_COLUMNS = 16
# One arena of bytes per thread that the workspace of every image shape is carved from, so its
# pages are faulted in once whatever shapes follow: the builder's pyramid cycles through 11
# shapes per image (with one workspace per shape and two shapes kept, every level's buffers
# were fresh in every image), and images over 1 MP had none. It grows to the largest shape
# seen up to _ARENA_MAX_BYTES (per thread, held until ``release_buffers``); larger shapes get
# fresh buffers per call. 640x480's pyramid with its two levels up (905x679 the largest, off the
# vector width: 38 bytes per pixel) takes 23 MB; 1920x1440's 210 MB (2715x2036). The builder's
# detection on a 1920x1440 pyramid (11 levels, redkitchen frames upsampled x3, 19 images, one
# process interleaving this and the two-shape cache image by image, nice 19, load 9): x0.59 CPU
# with this bound (835 -> 493 ms per image), x0.96 with 96 MB (the two levels up fresh); one
# 1920x1440 call x0.71; 640x480's pyramid x0.87. The same corners and responses, bit for bit.
_ARENA_MAX_BYTES = 256 << 20
_MAX_SHAPES = 64
_ALIGN = 64  # bytes: each buffer starts on a cache line, as numpy's large allocations do
_local = threading.local()


def _aligned(n: int) -> int:
    return -(-n // _ALIGN) * _ALIGN


def release_buffers() -> None:
    """Drop this thread's arena (the builder does between stages: its later stages peak)."""
    _local.__dict__.pop("arena", None)
    _local.__dict__.pop("shapes", None)


def _workspace(shape: tuple[int, int]) -> _Workspace:
    # the common case first: this shape's buffers are already carved (``nbytes`` is ~50 us
    # of Python per call, a per-frame cost for the engine's one shape)
    shapes: dict[tuple[int, int], _Workspace] | None = getattr(_local, "shapes", None)
    if shapes is not None and (ws := shapes.get(shape)) is not None:
        return ws
    need = _Workspace.nbytes(shape)
    if need > _ARENA_MAX_BYTES:
        return _Workspace(shape)
    arena: np.ndarray | None = getattr(_local, "arena", None)
    if arena is None or arena.size < need:
        # over-allocated by one cache line: the arena's start is aligned by hand
        raw = np.empty(need + _ALIGN, np.uint8)
        arena = raw[-raw.ctypes.data % _ALIGN :][:need]
        _local.arena, _local.shapes = arena, {}
    shapes = _local.shapes
    ws = shapes.get(shape)
    if ws is None:
        if len(shapes) >= _MAX_SHAPES:  # views only, but a server may see any query size
            shapes.clear()
        ws = shapes[shape] = _Workspace(shape, arena)
    return ws


class _Tensor:
    """The Gaussian-integrated structure tensor (a, b, c) = (gx^2, gy^2, gx gy) of an image,
    times ``_M_SCALE``, in a workspace's buffers (three planes, or one interleaved image)."""

    def __init__(self, gray: np.ndarray, sigma: float, ws: _Workspace) -> None:
        if gray.dtype != np.uint8:
            raise ValueError(f"expected a uint8 grayscale image, got {gray.dtype}")
        ksize = int(2 * round(2.5 * sigma) + 1)
        g = (ksize, ksize)
        cv2.spatialGradient(gray, ws.dx, ws.dy)
        dx, dy = ws.dx, ws.dy
        self.ws = ws
        self.planar = gray.shape[1] % _SIMD_COLUMNS == 0
        if self.planar:
            # M's entries as contiguous planes, each blurred in place (a third faster than the
            # interleaved image below, and bit-identical to it at such widths). The product of
            # two int16 planes into float32 is one OpenCV pass, exact (integers below 2^21).
            for u, v, out in ((dx, dx, ws.a), (dy, dy, ws.b), (dx, dy, ws.c)):
                cv2.multiply(u, v, dst=out, dtype=cv2.CV_32F)
                cv2.GaussianBlur(out, g, sigma, dst=out)
            self.a, self.b, self.c = ws.a, ws.b, ws.c
        else:
            # At other widths OpenCV's vector loops end on a scalar tail at different columns
            # for one and three channels, and the last columns differ in rounding: blur the
            # three products as one interleaved image, as the detector always did.
            m = ws.interleaved()
            for i, (u, v) in enumerate(((dx, dx), (dy, dy), (dx, dy))):
                np.multiply(u, v, out=m[..., i], dtype=np.float32)
            cv2.GaussianBlur(m, g, sigma, dst=m)
            self.a, self.b, self.c = m[..., 0], m[..., 1], m[..., 2]

    def response_into(self, k: float) -> np.ndarray:
        """The (scaled) response over the whole image in ``ws.r``, without full-image
        allocation. The arithmetic is that of ``det(M) - k trace(M)^2`` written as numpy
        expressions, operation for operation (float32, no fused multiply-add). Uses up the
        tensor (its planes are scratch)."""
        ws, a, b, c = self.ws, self.a, self.b, self.c
        p, t = (c, a) if self.planar else (ws.b, ws.c)  # c once c * c is taken, a once a + b is
        r = ws.r
        # ((a * b) - (c * c)) - ((k * (a + b)) * (a + b))
        np.multiply(a, b, out=r)
        np.multiply(c, c, out=p)
        np.subtract(r, p, out=r)
        np.add(a, b, out=p)
        # (k * p) * p in one pass: OpenCV's float32 multiply with a scale computes
        # ``(scale * src1) * src2`` in float32, in its vector loop and its scalar tail alike
        # (core/src/arithm.simd.hpp, op_mul_scale), the order of the two numpy passes it
        # replaces (which (p * p) * k is not: it differs on a third of the pixels)
        cv2.multiply(p, p, dst=t, scale=k)
        np.subtract(r, t, out=r)
        return r


def harris_response(gray: np.ndarray, sigma: float = 1.0, k: float = 0.04) -> np.ndarray:
    """Harris cornerness ``det(M) - k trace(M)^2`` (float32) of a uint8 image, M from Sobel
    gradients integrated with a Gaussian of ``sigma`` pixels. Gradients are scaled to unit
    pixel steps (Sobel / 8) so the response is comparable across images and pyramid levels."""
    if gray.ndim != 2:
        raise ValueError(f"expected a grayscale image, got shape {gray.shape}")
    r = _Tensor(gray, sigma, _workspace(gray.shape)).response_into(k)
    return np.multiply(r, _INV_R_SCALE)


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
    tensor = _Tensor(gray, sigma, ws)
    R = tensor.response_into(0.04)
    r_max_s = float(R.max()) if R.size else 0.0
    thr = threshold if threshold is not None else rel_threshold * r_max_s / _R_SCALE
    thr_s = max(float(thr), 1e-12) * _R_SCALE  # exact: a power of two
    # 3x3 local maxima above the threshold: the pixels over it first (2-6% of a redkitchen
    # frame), then the maximum test on those only. Contiguous masks: np.flatnonzero on one is
    # ~10x faster than np.nonzero on a strided view of the interior. Only the rows a corner
    # may lie in (``border`` off the top and bottom; contiguous, and the maximum is exact
    # whatever the rows around): the dilation reads one row more each side, and its rows at
    # that block's edge, which see the border value, are never read.
    y0 = min(border, h)
    y1 = max(h - border, y0)
    idx = np.flatnonzero(np.greater(R[y0:y1], thr_s, out=ws.gt[y0:y1]))
    if y0:
        idx += y0 * w
    lo, hi = max(y0 - 1, 0), min(y1 + 1, h)
    if y1 > y0:
        cv2.dilate(R[lo:hi], _KERNEL_3X3, dst=ws.s[lo:hi])
    r_flat = R.ravel()
    resp_s = r_flat[idx]
    idx = idx[resp_s >= ws.s.ravel()[idx]]
    ys, xs = np.divmod(idx, w)
    if border > 0:
        inside = (xs >= border) & (xs < w - border)
        idx, ys, xs = idx[inside], ys[inside], xs[inside]
    if mask is not None:
        allowed = mask[ys, xs] != 0
        idx, ys, xs = idx[allowed], ys[allowed], xs[allowed]
    resp_s = r_flat[idx]
    if max_corners and len(xs) > max_corners:
        keep = np.argpartition(-resp_s, max_corners - 1)[:max_corners]
        keep.sort()  # raster order, deterministic
        xs, ys, resp_s = xs[keep], ys[keep], resp_s[keep]
    xy = np.stack([xs, ys], axis=1).astype(np.float64)
    if method == "quadratic" and len(xs):
        xy += _subpixel_offsets(R, xs, ys)
    elif method == "forstner" and len(xs):
        xy += _forstner_offsets(ws.dx, ws.dy, xs, ys)
    xy += PIXEL_CENTER_OFFSET
    if border > 0 and len(xy):  # a sub-pixel step may not cross the border (descriptor support)
        xy = np.minimum(np.maximum(xy, border), np.array([w - border, h - border], np.float64))
    resp = np.multiply(resp_s, _INV_R_SCALE)
    return Corners(xy=xy, response=resp, max_response=r_max_s / _R_SCALE)


_KERNEL_3X3 = np.ones((3, 3), np.uint8)


def _subpixel_offsets(R: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Offsets of the maximum of a 2D quadratic fitted to the 3x3 responses around each
    maximum (Newton step ``-H^-1 g`` with central differences, including the cross term, which
    matters for corners whose peak is elongated along a diagonal); clipped to half a pixel.
    Scale-free: the scaled response gives the offsets of the unit-step one."""
    h, w = R.shape
    f = R.ravel()  # flat gathers: a third of the cost of R[ys, xs] pairs
    # (np.minimum / np.maximum: np.clip's Python wrapper costs ~10 us per call on ints)
    xm, xp = np.maximum(xs - 1, 0), np.minimum(xs + 1, w - 1)
    ym, yp = np.maximum(ys - 1, 0) * w, np.minimum(ys + 1, h - 1) * w
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
    return np.stack(
        [np.minimum(np.maximum(dx, -0.5), 0.5), np.minimum(np.maximum(dy, -0.5), 0.5)], axis=1
    )


_FO = np.arange(-FORSTNER_RADIUS, FORSTNER_RADIUS + 1)
_FO_Y_INT, _FO_X_INT = (a.ravel() for a in np.meshgrid(_FO, _FO, indexing="ij"))
_FOX, _FOY = _FO_X_INT.astype(np.float64), _FO_Y_INT.astype(np.float64)


def _forstner_offsets(gx: np.ndarray, gy: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Offsets from each pixel to the least-squares intersection of the edge lines in the
    window around it (Forstner): the point c minimizing ``sum_p (g_p . (p - c))^2``, one
    closed-form step. Where that system is ill-conditioned or the step leaves the window's
    core, the offset is 0. Scale-free in the gradients: the raw Sobel gives the same offsets
    as Sobel / 8 (a power of two)."""
    h, w = gx.shape
    px = np.minimum(np.maximum(xs[:, None] + _FO_X_INT, 0), w - 1)
    py = np.minimum(np.maximum(ys[:, None] + _FO_Y_INT, 0), h - 1)
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
