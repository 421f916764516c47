"""Rotation-invariant DAISY (T2-8a-2r6s) from resampled oriented patches, and its PCA.

Paper Section 2: "At each keypoint, its orientation is computed by finding a peak in the
gradient orientation histogram, and a rotation invariant T2-8a-2r6s-32d DAISY descriptor is
computed from a resampled patch" (Winder, Hua, Brown, "Picking the best DAISY", 2009):

- T2-8: per pixel, rectified gradients along 0/90 and 45/135 degrees,
  ``max(+-g, 0)`` for the four directions: 8 non-negative channels;
- S 2r6s: Gaussian pooling in 13 regions, a centre and two rings of six (the outer ring
  rotated by 30 degrees so it fills the gaps of the inner one): 13 x 8 = 104 dimensions;
- N: unit length, clip at 0.2, unit length again (SIFT-style robust normalization);
- PCA to 32 dimensions (``Pca``), fitted by the builder and stored in the bundle so the server
  applies exactly the same projection.

We never run a dense whole-image DAISY: every descriptor is computed from a small patch
resampled around its keypoint in ``cv2.remap`` calls batching many keypoints (chunked under
OpenCV's limit of 32767 rows and columns, ``REMAP_MAX``), so the cost is proportional to the
number of keypoints (OpenCV's DAISY precomputes the whole image on every
call, 6-30 ms whatever the keypoint count). Patch geometry is in pixels of the image the
keypoints come from; the builder runs it on every pyramid level, so the support scales with
the level.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..cameras import PIXEL_CENTER_OFFSET

RAW_DIM = 104
# cv2.remap asserts that its maps and its source image have fewer than SHRT_MAX (32767) rows
# and columns: one call on (n * side, side) maps fails from n = 1490 keypoints (side 22), and
# an image 32767 pixels wide fails whatever the keypoints. Maps are cut into chunks of whole
# patches, and larger images are read through crops of REMAP_TILE pixels plus the patch reach.
REMAP_MAX = 32766
REMAP_TILE = 16384


@dataclass(frozen=True)
class DaisyParams:
    grid: int = 20  # patch samples per side
    spacing: float = 1.6  # pixels between patch samples
    ring_radii: tuple[float, float] = (4.0, 9.0)  # pixels
    sigmas: tuple[float, float, float] = (2.0, 2.5, 3.5)  # centre, ring 1, ring 2 (pixels)
    clip: float = 0.2
    # Orientation: 36-bin histogram of gradient orientations in a Gaussian window.
    ori_bins: int = 36
    ori_grid: int = 13
    ori_spacing: float = 1.5
    ori_sigma: float = 4.5
    pre_smooth: float = 0.8  # Gaussian sigma applied before sampling (anti-aliasing)

    @property
    def support_radius(self) -> float:
        """Pixels from the keypoint that the descriptor and orientation read."""
        half = (self.grid + 1) / 2 * self.spacing * np.sqrt(2)
        ori_half = (self.ori_grid + 1) / 2 * self.ori_spacing * np.sqrt(2)
        return float(max(half, ori_half)) + 1.0


@dataclass
class DaisyExtractor:
    """Orientation + raw DAISY (104-d) for keypoints of one image; ``Pca`` reduces to 32-d."""

    params: DaisyParams = field(default_factory=DaisyParams)

    def __post_init__(self) -> None:
        # The patch grids, pooling weights and orientation window depend on the params only:
        # made once per params and shared read-only (issue 10: single-image relocalization
        # makes an extractor per call, and building them was ~0.25 ms of its ~25 ms CPU).
        (
            self._grid_xy,
            self._pool,
            self._half_pool,
            self._ori_xy,
            self._ori_weight,
        ) = _extractor_constants(self.params)

    # ------------------------------------------------------------------ public
    def prepare(self, gray: np.ndarray) -> np.ndarray:
        """The image the extractor samples from (float32, lightly smoothed). Compute once per
        image and pass it to ``orientations`` and ``describe``."""
        img: np.ndarray = gray.astype(np.float32)
        if self.params.pre_smooth > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.params.pre_smooth)
        return img

    def orientations(self, prepared: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Dominant gradient orientation (radians) at each keypoint: the peak of a smoothed
        36-bin histogram of gradient orientations weighted by magnitude and a Gaussian window,
        refined by a parabola through the peak bin and its neighbours."""
        n = len(xy)
        if n == 0:
            return np.zeros(0, np.float32)
        p = self.params
        go = p.ori_grid + 2
        patches = self._sample(prepared, xy, None, self._ori_xy, go)
        dx = 0.5 * (patches[:, 1:-1, 2:] - patches[:, 1:-1, :-2])
        dy = 0.5 * (patches[:, 2:, 1:-1] - patches[:, :-2, 1:-1])
        mag = np.sqrt(dx * dx + dy * dy).reshape(n, -1) * self._ori_weight
        ang = np.arctan2(dy, dx).reshape(n, -1)
        nb = p.ori_bins
        # The bin in [0, nb] (arctan2 lies in [-pi, pi]); nb wraps to 0, as ``% nb`` did, on
        # the float (an int64 modulo per sample cost more than the rest of the binning).
        f = np.floor((ang + np.pi) / (2 * np.pi) * nb)
        f[f >= nb] -= nb
        key = f.astype(np.int64)
        key += nb * np.arange(n)[:, None]
        hist = np.bincount(key.ravel(), weights=mag.ravel(), minlength=n * nb)
        hist = hist.reshape(n, nb)
        # Circular smoothing [1 4 6 4 1] / 16, the neighbours as slices of the histogram
        # padded by two bins on each side (np.roll's values without its four copies).
        hp = np.concatenate([hist[:, -2:], hist, hist[:, :2]], axis=1)
        hist = (
            6 * hist
            + 4 * (hp[:, 1 : nb + 1] + hp[:, 3 : nb + 3])
            + (hp[:, 0:nb] + hp[:, 4 : nb + 4])
        ) / 16.0
        k = np.argmax(hist, axis=1)
        rows = np.arange(n)
        l, c, r = hist[rows, (k - 1) % nb], hist[rows, k], hist[rows, (k + 1) % nb]
        den = l - 2 * c + r
        off = np.where(den < 0, 0.5 * (l - r) / np.where(den < 0, den, -1.0), 0.0)
        theta = (k + 0.5 + off) / nb * 2 * np.pi - np.pi
        return theta.astype(np.float32)

    def describe(self, prepared: np.ndarray, xy: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Raw 104-d DAISY descriptors (float32, unit length) of keypoints with orientations."""
        n = len(xy)
        if n == 0:
            return np.zeros((0, RAW_DIM), np.float32)
        p = self.params
        g = p.grid + 2
        patches = self._sample(prepared, xy, theta, self._grid_xy, g)
        # Twice the gradients (the 1/2 is in ``_half_pool``; every value below is exactly
        # twice the one of 0.5 * (...), so the pooled sums are the same bit for bit).
        gx = patches[:, 1:-1, 2:] - patches[:, 1:-1, :-2]
        gy = patches[:, 2:, 1:-1] - patches[:, :-2, 1:-1]
        s = np.float32(np.sqrt(0.5))
        d1 = gx + gy
        d1 *= s
        d2 = gy - gx
        d2 *= s
        m = p.grid * p.grid
        feats = np.empty((8, n, m), np.float32)
        for i, comp in enumerate((gx, gy, d1, d2)):
            comp = comp.reshape(n, m)
            np.maximum(comp, 0, out=feats[2 * i])
            # max(-c, 0) as max(c, 0) - c: exact (c - c = 0 where c > 0, 0 - c elsewhere)
            np.subtract(feats[2 * i], comp, out=feats[2 * i + 1])
        # Pool: (13, m) @ (m, 8n) -> (13, 8, n) -> (n, 13, 8). The (m, 8n) operand is the
        # transposed view of feats (no copy), as BLAS has always been given it.
        pooled = self._half_pool @ feats.transpose(2, 0, 1).reshape(m, 8 * n)
        desc = pooled.reshape(13, 8, n).transpose(2, 0, 1).reshape(n, RAW_DIM)
        return _normalize_clip(desc, p.clip)

    def compute(self, gray: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Orientations and raw descriptors in one call (``prepare`` done here)."""
        prepared = self.prepare(gray)
        theta = self.orientations(prepared, xy)
        return theta, self.describe(prepared, xy, theta)

    # ------------------------------------------------------------------ internals
    def _sample(
        self,
        img: np.ndarray,
        xy: np.ndarray,
        theta: np.ndarray | None,
        offsets: np.ndarray,
        side: int,
    ) -> np.ndarray:
        """Bilinear samples (N, side, side) of ``img`` on ``offsets`` rotated by ``theta``
        (None: not rotated) around each keypoint, in as few remaps as OpenCV's map-size limit
        allows.

        The sample positions are the float32 numbers ``kx + c * ox - s * oy`` and
        ``ky + s * ox + c * oy``, computed in place (two temporaries fewer); unrotated
        (c = 1, s = 0) they are exactly ``kx + ox`` and ``ky + oy`` (issue 10)."""
        n = len(xy)
        ox, oy = offsets[:, 0], offsets[:, 1]
        # Keypoint in array-index coordinates.
        kx = (xy[:, 0] - PIXEL_CENTER_OFFSET).astype(np.float32)[:, None]
        ky = (xy[:, 1] - PIXEL_CENTER_OFFSET).astype(np.float32)[:, None]
        if theta is None:
            mx = kx + ox
            my = ky + oy
        else:
            c = np.cos(theta).astype(np.float32)[:, None]
            s = np.sin(theta).astype(np.float32)[:, None]
            tmp = np.empty((n, len(offsets)), np.float32)
            mx = np.multiply(c, ox)
            mx += kx
            mx -= np.multiply(s, oy, out=tmp)
            my = np.multiply(s, ox)
            my += ky
            my += np.multiply(c, oy, out=tmp)
        mx = mx.reshape(n * side, side)
        my = my.reshape(n * side, side)
        h, w = img.shape[:2]
        if h <= REMAP_MAX and w <= REMAP_MAX:
            return _remap_patches(img, mx, my, side).reshape(n, side, side)
        # A source over OpenCV's limit: keypoints grouped by tile, each tile read from a crop
        # that holds every sample of its patches (shifting the maps by whole pixels keeps the
        # bilinear weights, so the samples are exactly those of the whole image).
        reach = int(np.ceil(np.abs(offsets).max() * np.sqrt(2))) + 2
        out = np.empty((n, side, side), img.dtype)
        tiles = np.floor(np.hstack([kx, ky]) / REMAP_TILE).astype(np.int64)
        _, tile_of = np.unique(tiles, axis=0, return_inverse=True)
        mx3, my3 = mx.reshape(n, side, side), my.reshape(n, side, side)
        for k in range(int(tile_of.max()) + 1):
            idx = np.nonzero(tile_of.ravel() == k)[0]
            x0 = max(0, int(np.floor(kx[idx].min())) - reach)
            x1 = min(w, int(np.ceil(kx[idx].max())) + reach + 1)
            y0 = max(0, int(np.floor(ky[idx].min())) - reach)
            y1 = min(h, int(np.ceil(ky[idx].max())) + reach + 1)
            sub = img[y0:y1, x0:x1]
            ax = (mx3[idx] - np.float32(x0)).reshape(-1, side)
            ay = (my3[idx] - np.float32(y0)).reshape(-1, side)
            out[idx] = _remap_patches(sub, ax, ay, side).reshape(len(idx), side, side)
        return out


@functools.lru_cache(maxsize=8)
def _extractor_constants(
    p: DaisyParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``DaisyExtractor``'s constants for ``p`` (read-only, shared by every extractor): the
    descriptor patch's sample offsets, the pooling matrix and its half, the orientation
    window's sample offsets and its Gaussian weights."""
    # Descriptor patch: (grid+2)^2 samples so central differences leave grid^2.
    g = p.grid + 2
    c = (np.arange(g) - (g - 1) / 2.0) * p.spacing
    gx, gy = np.meshgrid(c, c)
    grid_xy = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float32)  # (g*g, 2)
    pool = _pooling_matrix(p).astype(np.float32)  # (13, grid*grid)
    # The central differences' 1/2 moved into the pooling weights: halving is exact in
    # float32, so (w / 2) @ rect(2 g) adds the very products w @ rect(g) adds.
    half_pool = pool * np.float32(0.5)
    # Orientation window.
    go = p.ori_grid + 2
    co = (np.arange(go) - (go - 1) / 2.0) * p.ori_spacing
    ox, oy = np.meshgrid(co, co)
    ori_xy = np.stack([ox.ravel(), oy.ravel()], axis=1).astype(np.float32)
    inner = (np.arange(p.ori_grid) - (p.ori_grid - 1) / 2.0) * p.ori_spacing
    ix, iy = np.meshgrid(inner, inner)
    ori_weight = np.exp(-(ix**2 + iy**2) / (2 * p.ori_sigma**2)).astype(np.float32).ravel()
    out = (grid_xy, pool, half_pool, ori_xy, ori_weight)
    for a in out:
        a.flags.writeable = False
    return out


def _remap_patches(img: np.ndarray, mx: np.ndarray, my: np.ndarray, side: int) -> np.ndarray:
    """``cv2.remap`` of (n * side, side) maps in chunks of whole patches under REMAP_MAX rows."""
    out = np.empty(mx.shape, img.dtype)
    step = max(1, REMAP_MAX // side) * side
    for a in range(0, len(mx), step):
        out[a : a + step] = cv2.remap(
            img,
            mx[a : a + step],
            my[a : a + step],
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT_101,
        )
    return out


def _pooling_matrix(p: DaisyParams) -> np.ndarray:
    """(13, grid^2) normalized Gaussian weights of the DAISY regions over the patch samples."""
    c = (np.arange(p.grid) - (p.grid - 1) / 2.0) * p.spacing
    gx, gy = np.meshgrid(c, c)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    centers = [(0.0, 0.0, p.sigmas[0])]
    for radius, sigma, phase in (
        (p.ring_radii[0], p.sigmas[1], 0.0),
        (p.ring_radii[1], p.sigmas[2], np.pi / 6),
    ):
        for k in range(6):
            a = phase + k * np.pi / 3
            centers.append((radius * np.cos(a), radius * np.sin(a), sigma))
    W = np.empty((len(centers), len(pts)))
    for i, (cx, cy, sg) in enumerate(centers):
        w = np.exp(-((pts[:, 0] - cx) ** 2 + (pts[:, 1] - cy) ** 2) / (2 * sg * sg))
        W[i] = w / w.sum()
    return W


def _normalize_clip(desc: np.ndarray, clip: float) -> np.ndarray:
    norm = np.linalg.norm(desc, axis=1, keepdims=True)
    desc = desc / np.maximum(norm, 1e-12)
    np.minimum(desc, clip, out=desc)
    norm = np.linalg.norm(desc, axis=1, keepdims=True)
    return (desc / np.maximum(norm, 1e-12)).astype(np.float32)


@dataclass
class Pca:
    """PCA projection of raw descriptors: ``(d - mean) @ basis`` (basis columns are the
    principal directions, in decreasing variance)."""

    mean: np.ndarray  # (RAW_DIM,) float32
    basis: np.ndarray  # (RAW_DIM, dim) float32

    @classmethod
    def fit(cls, raw: np.ndarray, dim: int = 32, max_samples: int = 200_000, seed: int = 0) -> Pca:
        raw = np.asarray(raw, dtype=np.float64)
        if len(raw) < dim + 1:
            raise ValueError(
                f"PCA to {dim} dimensions needs more than {dim} descriptors, got {len(raw)}"
            )
        if len(raw) > max_samples:
            raw = raw[np.random.default_rng(seed).choice(len(raw), max_samples, replace=False)]
        mean = raw.mean(axis=0)
        cov = np.cov(raw - mean, rowvar=False)
        evals, evecs = np.linalg.eigh(cov)
        order = np.argsort(evals)[::-1][:dim]
        basis = evecs[:, order]
        # Deterministic sign: largest-magnitude entry of each component positive.
        signs = np.sign(basis[np.argmax(np.abs(basis), axis=0), np.arange(dim)])
        basis = basis * signs
        return cls(mean.astype(np.float32), basis.astype(np.float32))

    @property
    def dim(self) -> int:
        return int(self.basis.shape[1])

    def project(self, raw: np.ndarray) -> np.ndarray:
        return ((raw - self.mean) @ self.basis).astype(np.float32)
