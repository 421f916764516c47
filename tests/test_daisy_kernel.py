"""The DAISY kernel (features/daisy.py, issue 10: maps in place, unrotated orientation windows,
the central differences' 1/2 in the pooling weights, histogram smoothing by slices, the bin
wrap on the float) against the implementation it replaces, copied here: the same orientations
and descriptors, bit for bit, on synthetic images (keypoints at the borders, any rotation,
gradients pointing exactly at +-pi) and on real redkitchen frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from sfmloc.cameras import PIXEL_CENTER_OFFSET
from sfmloc.features.daisy import (
    RAW_DIM,
    DaisyExtractor,
    DaisyParams,
    _extractor_constants,
    _normalize_clip,
)
from sfmloc.features.harris import detect_corners


# ----------------------------------------------------------------------------- reference
def reference_sample(ex, img, xy, theta, offsets, side):
    """Bilinear patches (N, side, side) as the broadcast formula computed them (one remap:
    the images here are under OpenCV's limits)."""
    n = len(xy)
    c, s = np.cos(theta).astype(np.float32), np.sin(theta).astype(np.float32)
    ox, oy = offsets[:, 0], offsets[:, 1]
    kx = (xy[:, 0] - PIXEL_CENTER_OFFSET).astype(np.float32)[:, None]
    ky = (xy[:, 1] - PIXEL_CENTER_OFFSET).astype(np.float32)[:, None]
    mx = (kx + c[:, None] * ox - s[:, None] * oy).reshape(n * side, side)
    my = (ky + s[:, None] * ox + c[:, None] * oy).reshape(n * side, side)
    out = cv2.remap(img, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    return out.reshape(n, side, side)


def reference_orientations(ex, prepared, xy):
    n = len(xy)
    p = ex.params
    go = p.ori_grid + 2
    patches = reference_sample(ex, prepared, xy, np.zeros(n, np.float32), ex._ori_xy, go)
    dx = 0.5 * (patches[:, 1:-1, 2:] - patches[:, 1:-1, :-2])
    dy = 0.5 * (patches[:, 2:, 1:-1] - patches[:, :-2, 1:-1])
    mag = np.sqrt(dx * dx + dy * dy).reshape(n, -1) * ex._ori_weight
    ang = np.arctan2(dy, dx).reshape(n, -1)
    nb = p.ori_bins
    b = np.floor((ang + np.pi) / (2 * np.pi) * nb).astype(np.int64) % nb
    hist = np.bincount(
        (b + nb * np.arange(n)[:, None]).ravel(), weights=mag.ravel(), minlength=n * nb
    ).reshape(n, nb)
    hist = (
        6 * hist
        + 4 * (np.roll(hist, 1, axis=1) + np.roll(hist, -1, axis=1))
        + (np.roll(hist, 2, axis=1) + np.roll(hist, -2, axis=1))
    ) / 16.0
    k = np.argmax(hist, axis=1)
    rows = np.arange(n)
    l, c, r = hist[rows, (k - 1) % nb], hist[rows, k], hist[rows, (k + 1) % nb]
    den = l - 2 * c + r
    off = np.where(den < 0, 0.5 * (l - r) / np.where(den < 0, den, -1.0), 0.0)
    return ((k + 0.5 + off) / nb * 2 * np.pi - np.pi).astype(np.float32)


def reference_describe(ex, prepared, xy, theta):
    n = len(xy)
    p = ex.params
    patches = reference_sample(ex, prepared, xy, theta, ex._grid_xy, p.grid + 2)
    gx = 0.5 * (patches[:, 1:-1, 2:] - patches[:, 1:-1, :-2])
    gy = 0.5 * (patches[:, 2:, 1:-1] - patches[:, :-2, 1:-1])
    s = np.float32(np.sqrt(0.5))
    d1 = (gx + gy) * s
    d2 = (gy - gx) * s
    m = p.grid * p.grid
    feats = np.empty((8, n, m), np.float32)
    for i, comp in enumerate((gx, gy, d1, d2)):
        comp = comp.reshape(n, m)
        np.maximum(comp, 0, out=feats[2 * i])
        np.maximum(-comp, 0, out=feats[2 * i + 1])
    pooled = ex._pool @ feats.transpose(2, 0, 1).reshape(m, 8 * n)
    desc = pooled.reshape(13, 8, n).transpose(2, 0, 1).reshape(n, RAW_DIM)
    return _normalize_clip(desc, p.clip)


def assert_same_daisy(img: np.ndarray, xy: np.ndarray, theta: np.ndarray | None = None):
    """Orientations and descriptors of the kernel equal the reference's, bit for bit (with
    the computed orientations, and with ``theta`` when given); returns the orientations."""
    ex = DaisyExtractor()
    prepared = ex.prepare(img)
    th = ex.orientations(prepared, xy)
    np.testing.assert_array_equal(th, reference_orientations(ex, prepared, xy))
    np.testing.assert_array_equal(
        ex.describe(prepared, xy, th), reference_describe(ex, prepared, xy, th)
    )
    if theta is not None:
        np.testing.assert_array_equal(
            ex.describe(prepared, xy, theta), reference_describe(ex, prepared, xy, theta)
        )
    return th


def noisy_blocks(seed: int, shape: tuple[int, int]) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full(shape, 128, np.uint8)
    for _ in range(shape[0] * shape[1] // 600):
        x, y = rng.integers(0, shape[1]), rng.integers(0, shape[0])
        w, h = rng.integers(4, 40, size=2)
        cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), int(rng.integers(256)), -1)
    noisy = img + rng.normal(0, 6, shape)
    return np.clip(cv2.GaussianBlur(noisy, (3, 3), 0.8), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------- tests
@pytest.mark.parametrize("n", [1, 7, 84, 700])
def test_daisy_equals_the_reference_on_synthetic_images_at_any_rotation(n):
    """Keypoints anywhere, the borders included (samples reflected outside the image), and
    descriptors at arbitrary orientations besides the computed ones."""
    rng = np.random.default_rng(n)
    img = noisy_blocks(n, (240, 320))
    xy = rng.uniform([0, 0], [320, 240], size=(n, 2))
    xy[: min(n, 4)] = [[0.0, 0.0], [319.9, 239.9], [0.5, 120.25], [160.0, 239.5]][: min(n, 4)]
    theta = rng.uniform(-np.pi, np.pi, n).astype(np.float32)
    th = assert_same_daisy(img, xy, theta)
    assert len(np.unique(th)) > 0.5 * n  # the orientations are computed, not one constant


def test_daisy_equals_the_reference_where_gradients_point_exactly_at_pi():
    """A horizontal ramp falling to the right: dy = 0 and dx < 0 everywhere, so every sample's
    angle is exactly pi and lands in bin nb, which wraps to bin 0 (the old ``% nb``); and its
    mirror image (angle 0) and a vertical ramp (angle +-pi/2)."""
    ramp = np.tile(np.linspace(250, 5, 200), (120, 1)).astype(np.uint8)
    xy = np.array([[100.0, 60.0], [40.5, 30.25], [150.0, 90.0]])
    for img in (ramp, ramp[:, ::-1].copy(), ramp.T.copy()):
        th = assert_same_daisy(img, xy if img.shape[1] == 200 else xy[:, ::-1].copy())
        assert np.all(np.isfinite(th))
    # the falling ramp's orientation is the first bin's centre, not the last's
    ex = DaisyExtractor()
    th = ex.orientations(ex.prepare(ramp), xy)
    assert np.all(np.abs(th - (-np.pi + np.pi / 36)) < 0.05), th


def test_daisy_equals_the_reference_on_redkitchen_frames(redkitchen: Path):
    """Real frames: a guided batch's size (84 keypoints) and a relocalization's (up to 1000
    Harris corners, those near the borders included)."""
    for i in range(0, 1000, 200):
        gray = cv2.imread(str(redkitchen / f"frame-{i:06d}.color.jpg"), cv2.IMREAD_GRAYSCALE)
        xy = detect_corners(gray, rel_threshold=0.001, max_corners=1000, border=4).xy
        assert len(xy) > 300
        assert_same_daisy(gray, xy)
        assert_same_daisy(gray, xy[::12])


@pytest.mark.parametrize(
    "params", [DaisyParams(), DaisyParams(grid=14, spacing=2.0, ori_grid=9, ori_sigma=3.0)]
)
def test_extractor_constants_are_made_once_per_params_and_equal_the_reference(params):
    """Issue 10: ``relocalize`` makes an extractor per call; its constants (patch grids,
    pooling weights, orientation window) are made once per params, shared read-only, and
    equal bit for bit to a fresh computation (the cached function unwrapped; the descriptors
    themselves are checked against the reference extractor above)."""
    a, b = DaisyExtractor(params), DaisyExtractor(params)
    got = (a._grid_xy, a._pool, a._half_pool, a._ori_xy, a._ori_weight)
    shared = (b._grid_xy, b._pool, b._half_pool, b._ori_xy, b._ori_weight)
    for g, s, want in zip(got, shared, _extractor_constants.__wrapped__(params)):
        assert g.dtype == want.dtype
        np.testing.assert_array_equal(g, want)
        assert s is g and not g.flags.writeable
