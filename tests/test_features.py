"""Feature primitives against exact ground truth: Harris corner positions, BRIEF, oriented
DAISY rotation invariance, PCA, pyramid coordinate scaling."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sfmloc.features.brief import compute_brief, hamming, smooth_for_brief
from sfmloc.features.daisy import RAW_DIM, DaisyExtractor, Pca
from sfmloc.features.harris import detect_corners
from sfmloc.features.pyramid import build_pyramid, level_scales


def checker_corner_image(
    cx: float, cy: float, size=(160, 200), angle_deg: float = 0.0
) -> np.ndarray:
    """A corner of a dark square on a bright background at (cx, cy) (COLMAP convention),
    rendered with 8x supersampling so the true corner position is known to sub-pixel."""
    h, w = size
    s = 8
    ys, xs = np.mgrid[0 : h * s, 0 : w * s]
    # sample centres in COLMAP coordinates
    u = (xs + 0.5) / s
    v = (ys + 0.5) / s
    a = np.radians(angle_deg)
    du, dv = u - cx, v - cy
    ru = np.cos(a) * du + np.sin(a) * dv
    rv = -np.sin(a) * du + np.cos(a) * dv
    inside = (ru > 0) & (rv > 0)
    img = np.where(inside, 40.0, 210.0)
    img = img.reshape(h, s, w, s).mean(axis=(1, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def best_corner(img, subpixel=True):
    c = detect_corners(img, rel_threshold=0.1, border=4, subpixel=subpixel)
    assert len(c) >= 1
    return c.xy[np.argmax(c.response)]


SHIFTS = [(0.3, 0.7), (-0.4, 0.2), (0.5, -0.5), (0.25, 0.25)]


@pytest.mark.parametrize("dx,dy", SHIFTS)
@pytest.mark.parametrize("method", ["forstner", "quadratic"])
def test_harris_corner_position_follows_subpixel_shifts(dx, dy, method):
    # Harris' maximum of an L-corner lies a fraction of a pixel inside the corner (a property
    # of the detector, which the quadratic fit keeps); Forstner's step moves it onto the corner.
    # Either must follow the corner to ~1/4 pixel.
    base = best_corner(checker_corner_image(100.0, 80.0), method)
    moved = best_corner(checker_corner_image(100.0 + dx, 80.0 + dy), method)
    assert np.linalg.norm(base - [100.0, 80.0]) < (0.3 if method == "forstner" else 1.05)
    assert np.linalg.norm((moved - base) - [dx, dy]) < 0.25, (moved - base, dx, dy)


def test_forstner_corners_sit_on_the_true_corner_at_every_angle():
    # The quadratic fit finds Harris' biased peak precisely; its offset from the corner turns
    # with the corner (so with the viewpoint). Forstner's point is the corner itself.
    errs = {"forstner": [], "quadratic": [], "none": []}
    for angle in (0, 20, 45, 70, 110, 160, 200, 300):
        for dx, dy in [(0.0, 0.0)] + SHIFTS[:2]:
            img = checker_corner_image(100.0 + dx, 80.0 + dy, angle_deg=angle)
            for method, e in errs.items():
                e.append(np.linalg.norm(best_corner(img, method) - [100.0 + dx, 80.0 + dy]))
    mean = {m: float(np.mean(e)) for m, e in errs.items()}
    assert mean["quadratic"] > 0.8 and mean["none"] > 0.8, mean  # the bias exists
    assert mean["forstner"] < 0.2, mean
    assert max(errs["forstner"]) < 0.45, errs["forstner"]


def test_forstner_corners_are_closer_to_exact_projections_on_a_rendered_view():
    # Exact ground truth: the renderer's texture corners, projected (the visible ones).
    from scipy.spatial import cKDTree

    from server_helpers import room_scene
    from sfmloc.cameras import Camera
    from sfmloc.synth import mapping_views, render_full, visible_points

    scene = room_scene(0)
    camera = Camera.pinhole(640, 480, 525.0, 525.0, 320.0, 240.0)
    dist = {"forstner": [], "quadratic": [], "none": []}
    for i, T in enumerate(mapping_views(scene, 12, seed=0)[::4]):
        r = render_full(scene, camera, T, noise_seed=(0, 1, i))
        gray = cv2.cvtColor(r.bgr, cv2.COLOR_BGR2GRAY)
        truth = visible_points(scene, camera, T, face_id=r.face_id).xy
        # pair corners with true projections by the integer maxima, the same pairs for all
        ref = detect_corners(gray, rel_threshold=0.001, border=16, subpixel="none")
        d0, nn = cKDTree(truth).query(ref.xy, distance_upper_bound=2.0)
        hit = np.isfinite(d0)
        for method, d in dist.items():
            c = detect_corners(gray, rel_threshold=0.001, border=16, subpixel=method)
            assert len(c) == len(ref)  # same maxima, moved
            d.append(np.linalg.norm(c.xy[hit] - truth[nn[hit]], axis=1))
    med = {m: float(np.median(np.concatenate(d))) for m, d in dist.items()}
    assert len(np.concatenate(dist["none"])) >= 300
    assert med["forstner"] < 0.5 and med["forstner"] < 0.5 * med["quadratic"], med


def test_detect_corners_rejects_an_unknown_subpixel_method():
    with pytest.raises(ValueError, match="subpixel"):
        detect_corners(checker_corner_image(100.0, 80.0), subpixel="parabolic")


def test_harris_subpixel_refinement_beats_integer_positions():
    def err(subpixel):
        base = best_corner(checker_corner_image(100.0, 80.0), subpixel)
        return np.mean(
            [
                np.linalg.norm(
                    best_corner(checker_corner_image(100.0 + dx, 80.0 + dy), subpixel)
                    - base
                    - [dx, dy]
                )
                for dx, dy in SHIFTS
            ]
        )

    assert err(True) < 0.6 * err(False)


def test_harris_threshold_border_mask_and_cap():
    rng = np.random.default_rng(0)
    img = (rng.random((120, 160)) * 255).astype(np.uint8)
    img = cv2.GaussianBlur(img, (5, 5), 1.5)
    loose = detect_corners(img, rel_threshold=0.001)
    tight = detect_corners(img, rel_threshold=0.2)
    assert len(tight) < len(loose)
    absolute = detect_corners(img, threshold=0.2 * loose.max_response)
    assert len(absolute) == len(tight)
    b = detect_corners(img, rel_threshold=0.001, border=20)
    assert np.all((b.xy >= 20) & (b.xy <= np.array([160, 120]) - 20 + 1))
    capped = detect_corners(img, rel_threshold=0.001, max_corners=10)
    assert len(capped) == 10
    assert np.min(capped.response) >= np.sort(loose.response)[-10] - 1e-6
    mask = np.zeros_like(img)
    mask[:, :80] = 1
    m = detect_corners(img, rel_threshold=0.001, mask=mask)
    assert len(m) > 0 and np.all(m.xy[:, 0] < 80.5)


def test_harris_constant_image_has_no_corners():
    c = detect_corners(np.full((100, 100), 128, np.uint8))
    assert len(c) == 0


def test_brief_identity_and_discrimination():
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur((rng.random((200, 200)) * 255).astype(np.uint8), (3, 3), 1)
    sm = smooth_for_brief(img)
    xy = np.array([[50.5, 60.5], [120.5, 130.5], [150.5, 40.5]])
    d = compute_brief(sm, xy)
    assert d.shape == (3, 4) and d.dtype == np.uint64
    assert np.all(hamming(d, d) == 0)
    # Different places differ by roughly half the bits.
    cross = hamming(d[:, None], d[None])
    off = cross[~np.eye(3, dtype=bool)]
    assert np.all(off > 64) and np.all(off < 192)
    # A one-pixel shift keeps most bits: tracking relies on it.
    shifted = compute_brief(sm, xy + [1.0, 0.0])
    assert np.all(hamming(d, shifted) < off.min())


def textured_image(seed=0, shape=(240, 320)):
    rng = np.random.default_rng(seed)
    img = np.full(shape, 128, np.uint8)
    for _ in range(150):
        x, y = rng.integers(0, shape[1]), rng.integers(0, shape[0])
        w, h = rng.integers(5, 40, size=2)
        cv2.rectangle(
            img, (int(x), int(y)), (int(x + w), int(y + h)), int(rng.integers(0, 255)), -1
        )
    return cv2.GaussianBlur(img, (3, 3), 0.8)


@pytest.mark.parametrize("angle", [0.0, 37.0, 90.0, 180.0, 251.0])
def test_daisy_is_rotation_invariant(angle):
    img = textured_image()
    h, w = img.shape
    ex = DaisyExtractor()
    c = detect_corners(img, rel_threshold=0.01, border=30)
    assert len(c) > 50
    th0, d0 = ex.compute(img, c.xy)
    # Rotate about the image centre (array coordinates), map the keypoints exactly.
    M = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), angle, 1.0)
    rot = cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    xy_r = np.hstack([c.xy - 0.5, np.ones((len(c), 1))]) @ M.T + 0.5
    keep = np.all((xy_r > 35) & (xy_r < [w - 35, h - 35]), axis=1)
    th1, d1 = ex.compute(rot, xy_r[keep])
    d0k = d0[keep]
    # Orientation follows the rotation (image rotation by +angle is -angle in our y-down frame).
    dth = np.degrees(np.angle(np.exp(1j * (th1 - th0[keep] + np.radians(angle)))))
    assert np.median(np.abs(dth)) < 5.0  # half a histogram bin
    # Each rotated descriptor's nearest neighbour is its own original for most keypoints.
    D = np.linalg.norm(d1[:, None] - d0k[None], axis=2)
    acc = np.mean(D.argmin(axis=1) == np.arange(len(d1)))
    assert acc > 0.85, acc


def test_daisy_shape_norm_and_empty():
    ex = DaisyExtractor()
    img = textured_image(2)
    c = detect_corners(img, rel_threshold=0.01, border=30)
    th, d = ex.compute(img, c.xy)
    assert d.shape == (len(c), RAW_DIM) and d.dtype == np.float32
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-4)
    assert np.all(d >= 0)
    th, d = ex.compute(img, np.zeros((0, 2)))
    assert d.shape == (0, RAW_DIM)


def test_daisy_on_5000_keypoints_equals_small_chunks():
    """One call on 5000 keypoints (cv2.remap asserts from 1490 in one map) gives exactly what
    describing them 100 at a time gives."""
    ex = DaisyExtractor()
    rng = np.random.default_rng(5)
    noise = rng.normal(0, 8, (600, 800))  # no flat regions: every patch is distinct
    img = np.clip(textured_image(4, shape=(600, 800)) + noise, 0, 255).astype(np.uint8)
    xy = rng.uniform([20, 20], [780, 580], size=(5000, 2)).astype(np.float32)
    prepared = ex.prepare(img)
    theta = ex.orientations(prepared, xy)
    d = ex.describe(prepared, xy, theta)
    assert d.shape == (5000, RAW_DIM) and np.all(np.isfinite(d))
    parts = [slice(a, a + 100) for a in range(0, 5000, 100)]
    theta_small = np.concatenate([ex.orientations(prepared, xy[p]) for p in parts])
    d_small = np.concatenate([ex.describe(prepared, xy[p], theta[p]) for p in parts])
    np.testing.assert_array_equal(theta, theta_small)
    np.testing.assert_array_equal(d, d_small)
    # Different keypoints get different descriptors (the chunks are not one patch repeated).
    assert len(np.unique(d, axis=0)) == 5000


def test_daisy_on_an_image_wider_than_opencvs_remap_limit():
    """cv2.remap refuses sources of 32767 pixels or more: a 40000-pixel-wide strip is read
    through crops, with exactly the samples of the whole image."""
    rng = np.random.default_rng(6)
    strip = cv2.resize(
        textured_image(7, shape=(120, 4000)), (40000, 120), interpolation=cv2.INTER_LINEAR
    )
    strip = np.clip(strip + rng.normal(0, 6, strip.shape), 0, 255).astype(np.uint8)
    ex = DaisyExtractor()
    xy = np.column_stack([rng.uniform(15, 39985, 400), rng.uniform(30, 90, 400)]).astype(np.float32)
    xy[:4, 0] = [16383.0, 16386.0, 32766.5, 32769.0]  # either side of tile and limit edges
    prepared = ex.prepare(strip)
    theta = ex.orientations(prepared, xy)
    d = ex.describe(prepared, xy, theta)
    # The same keypoints described in small windows of the strip (under the limit); float32
    # sample coordinates near x = 40000 are only 1/256 px fine, hence the tolerance.
    for x0 in range(0, 40000, 2000):
        sel = np.nonzero((xy[:, 0] >= x0) & (xy[:, 0] < x0 + 2000))[0]
        a = max(0, x0 - 100)
        win = prepared[:, a : x0 + 2100]
        local = xy[sel] - np.float32([a, 0])
        np.testing.assert_allclose(ex.orientations(win, local), theta[sel], atol=1e-3)
        np.testing.assert_allclose(ex.describe(win, local, theta[sel]), d[sel], atol=1e-3)


def test_pca_projects_to_principal_subspace():
    rng = np.random.default_rng(3)
    basis = np.linalg.qr(rng.standard_normal((RAW_DIM, RAW_DIM)))[0]
    scales = np.concatenate([np.linspace(10, 5, 32), np.full(RAW_DIM - 32, 0.01)])
    x = (rng.standard_normal((5000, RAW_DIM)) * scales) @ basis.T + 7.0
    pca = Pca.fit(x.astype(np.float32), dim=32)
    y = pca.project(x.astype(np.float32))
    assert y.shape == (5000, 32)
    # Nearly all variance is kept, and the components are decorrelated, in decreasing order.
    assert y.var(axis=0).sum() / x.var(axis=0).sum() > 0.999
    var = y.var(axis=0)
    assert np.all(np.diff(var) <= 1e-3 * var[0])
    cov = np.cov(y, rowvar=False)
    assert np.abs(cov - np.diag(np.diag(cov))).max() < 0.05 * var[0]
    with pytest.raises(ValueError):
        Pca.fit(x[:10], dim=32)


def test_pyramid_scales_and_coordinates():
    scales = level_scales(2, 4)
    assert len(scales) == 9 and scales[0] == 1.0 and abs(scales[-1] - 0.25) < 1e-12
    assert len(level_scales(2, 4, up_levels=2)) == 11
    # Two corners far apart: their detected separation at every level must be the scaled
    # separation (a wrong coordinate convention shows up as an offset growing with 1/scale).
    a = build_pyramid(checker_corner_image(60.0, 50.0, size=(160, 200)), scales)
    b = build_pyramid(checker_corner_image(140.0, 110.0, size=(160, 200)), scales)
    for la, lb in zip(a, b):
        pa = best_corner(la.image)
        pb = best_corner(lb.image)
        expect_a = np.array([60.0 * la.scale_x, 50.0 * la.scale_y])
        assert np.linalg.norm(pa - expect_a) < 1.5, (la.scale, pa, expect_a)
        sep = np.array([80.0 * la.scale_x, 60.0 * la.scale_y])
        assert np.linalg.norm((pb - pa) - sep) < 0.35, (la.scale, pb - pa, sep)


def test_daisy_pools_each_channel_as_the_pooling_matrix_says():
    """The 104 dimensions are, per region j and channel c, the Gaussian pooling of c's
    rectified gradients (region-major: index 8 j + c), before normalization: checked against a
    direct per-keypoint computation in float64."""
    from sfmloc.features.daisy import _normalize_clip

    ex = DaisyExtractor()
    img = textured_image(3)
    xy = detect_corners(img, rel_threshold=0.01, border=30).xy[:40]
    prepared = ex.prepare(img)
    theta = ex.orientations(prepared, xy)
    got = ex.describe(prepared, xy, theta)
    g = ex.params.grid
    patches = ex._sample(prepared, xy, theta, ex._grid_xy, g + 2).astype(np.float64)
    gx = 0.5 * (patches[:, 1:-1, 2:] - patches[:, 1:-1, :-2]).reshape(len(xy), -1)
    gy = 0.5 * (patches[:, 2:, 1:-1] - patches[:, :-2, 1:-1]).reshape(len(xy), -1)
    s = np.sqrt(0.5)
    want = np.empty((len(xy), RAW_DIM))
    pool = ex._pool.astype(np.float64)
    for c, comp in enumerate((gx, gy, (gx + gy) * s, (gy - gx) * s)):
        for sign in (0, 1):
            rect = np.maximum(comp if sign == 0 else -comp, 0)
            for j in range(13):
                want[:, 8 * j + 2 * c + sign] = rect @ pool[j]
    want = _normalize_clip(want.astype(np.float32), ex.params.clip)
    np.testing.assert_allclose(got, want, atol=2e-6)
