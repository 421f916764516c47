"""The fast Harris and BRIEF kernels (reused buffers, fused passes) against the plain formulas
they replace: the same corners, responses and descriptors, bit for bit, on synthetic images,
rendered views and real redkitchen frames."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from sfmloc.cameras import PIXEL_CENTER_OFFSET
from sfmloc.features import harris
from sfmloc.features.brief import brief_pattern, compute_brief, smooth_for_brief
from sfmloc.features.harris import detect_corners, harris_response


# ----------------------------------------------------------------------------- references
def reference_response(gray: np.ndarray, sigma: float = 1.0, k: float = 0.04) -> np.ndarray:
    """Harris response as the plain numpy formula (the implementation before the buffers)."""
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
    ksize = int(2 * round(2.5 * sigma) + 1)
    m = np.empty(gx.shape + (3,), np.float32)
    np.multiply(gx, gx, out=m[..., 0])
    np.multiply(gy, gy, out=m[..., 1])
    np.multiply(gx, gy, out=m[..., 2])
    m = cv2.GaussianBlur(m, (ksize, ksize), sigma)
    a, b, c = m[..., 0], m[..., 1], m[..., 2]
    tr = a + b
    return a * b - c * c - k * tr * tr


def reference_corners(
    gray,
    threshold=None,
    rel_threshold=0.001,
    max_corners=0,
    border=0,
    mask=None,
    subpixel="quadratic",
):
    """Integer maxima (3x3 dilation of the whole response), responses and max of the plain
    implementation; the quadratic sub-pixel step as it was, Forstner's from the module's own
    per-corner function (unchanged, it reads the same gradients)."""
    R = reference_response(gray)
    r_max = float(R.max()) if R.size else 0.0
    thr = max(float(threshold if threshold is not None else rel_threshold * r_max), 1e-12)
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
        keep = np.sort(np.argpartition(-resp, max_corners - 1)[:max_corners])
        xs, ys, resp = xs[keep], ys[keep], resp[keep]
    xy = np.stack([xs, ys], axis=1).astype(np.float64)
    if subpixel == "quadratic" and len(xs):
        xy += reference_subpixel_offsets(R, xs, ys)
    elif subpixel == "forstner" and len(xs):
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
        xy += harris._forstner_offsets(gx, gy, xs, ys)
    xy += PIXEL_CENTER_OFFSET
    if border > 0 and len(xy):
        h, w = gray.shape
        xy = np.clip(xy, border, np.array([w - border, h - border], np.float64))
    return xy, resp, r_max


def reference_subpixel_offsets(R: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """The quadratic sub-pixel step with 2D gathers (the implementation before flat ones)."""
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
    ok = (det > 0) & (hxx < 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = np.where(ok, -(hyy * gx - hxy * gy) / det, 0.0)
        dy = np.where(ok, -(hxx * gy - hxy * gx) / det, 0.0)
    return np.stack([np.clip(dx, -0.5, 0.5), np.clip(dy, -0.5, 0.5)], axis=1)


def reference_brief(smoothed: np.ndarray, xy: np.ndarray, patch_size: int = 32) -> np.ndarray:
    """BRIEF as one (N, 256) gather with clamped flat indices (the implementation before)."""
    h, w = smoothed.shape
    pat = brief_pattern(patch_size)
    cx = np.clip(np.floor(xy[:, 0]).astype(np.int64), 0, w - 1)
    cy = np.clip(np.floor(xy[:, 1]).astype(np.int64), 0, h - 1)
    flat = smoothed.reshape(-1)
    base = (cy * w + cx)[:, None]
    i1 = np.clip(base + pat[None, :, 1] * w + pat[None, :, 0], 0, flat.size - 1)
    i2 = np.clip(base + pat[None, :, 3] * w + pat[None, :, 2], 0, flat.size - 1)
    return np.packbits(flat[i1] < flat[i2], axis=1).view(np.uint64)


def assert_same_corners(gray, **kw):
    c = detect_corners(gray, **kw)
    xy, resp, r_max = reference_corners(gray, **kw)
    np.testing.assert_array_equal(c.xy, xy)
    np.testing.assert_array_equal(c.response, resp.astype(np.float32))
    assert c.max_response == r_max
    return c


# ----------------------------------------------------------------------------- images
def blocks_image(seed: int, shape: tuple[int, int]) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full(shape, 128, np.uint8)
    for _ in range(max(4, shape[0] * shape[1] // 500)):
        x, y = int(rng.integers(0, shape[1])), int(rng.integers(0, shape[0]))
        w, h = (int(v) for v in rng.integers(3, 40, size=2))
        cv2.rectangle(img, (x, y), (x + w, y + h), int(rng.integers(0, 255)), -1)
    noise = rng.normal(0, 3, shape)
    return np.clip(cv2.GaussianBlur(img, (3, 3), 0.8) + noise, 0, 255).astype(np.uint8)


SETTINGS = [
    dict(rel_threshold=0.001, max_corners=1500, border=16),  # the tracker
    dict(rel_threshold=0.0005, max_corners=6000, border=8, subpixel="forstner"),  # the builder
    dict(threshold=0.05, subpixel="none"),
    dict(rel_threshold=0.01, max_corners=7, border=3),
]


@pytest.mark.parametrize(
    "shape", [(480, 640), (427, 640), (97, 131), (31, 45), (1, 50), (720, 1280)]
)
def test_harris_equals_the_plain_formula_across_sizes_and_settings(shape):
    for seed in range(2):
        img = blocks_image(seed, shape)
        np.testing.assert_array_equal(harris_response(img), reference_response(img))
        for kw in SETTINGS:
            assert_same_corners(img, **kw)
    mask = np.zeros(shape, np.uint8)
    mask[:, : shape[1] // 2] = 7  # any nonzero value allows
    assert_same_corners(img, rel_threshold=0.001, border=2, mask=mask)


def test_harris_equals_the_plain_formula_on_rendered_views_with_exact_corners():
    from server_helpers import room_scene
    from sfmloc.cameras import Camera
    from sfmloc.synth import mapping_views, render_full

    scene = room_scene(0)
    camera = Camera.pinhole(640, 480, 525.0, 525.0, 320.0, 240.0)
    n = 0
    for i, T in enumerate(mapping_views(scene, 6, seed=1)[::2]):
        bgr = render_full(scene, camera, T, noise_seed=(0, 2, i)).bgr
        gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        for kw in SETTINGS[:2]:
            n += len(assert_same_corners(gray, **kw))
    assert n > 1000


def test_harris_buffers_are_not_shared_between_results_shapes_or_threads():
    a, b = blocks_image(3, (120, 160)), blocks_image(4, (90, 70))
    ra = harris_response(a)
    rb = harris_response(b)  # another shape, then the first again: results are copies
    harris_response(a[::-1].copy())
    np.testing.assert_array_equal(ra, reference_response(a))
    np.testing.assert_array_equal(rb, reference_response(b))
    # Several shapes in turn (the arena grows for the largest, over 1 MP) still agree.
    big = blocks_image(5, (1100, 1000))
    for img in (blocks_image(6, (50, 60)), blocks_image(7, (51, 60)), big, a):
        assert_same_corners(img, rel_threshold=0.001, border=4)
    # Threads detecting at once each get their own buffers.
    imgs = [blocks_image(10 + i, (240, 320)) for i in range(4)]
    want = [reference_corners(im, border=16)[0] for im in imgs]
    got: dict[int, list[np.ndarray]] = {i: [] for i in range(4)}

    def run(i):
        for _ in range(15):
            got[i].append(detect_corners(imgs[i], border=16).xy)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i in range(4):
        assert len(got[i]) == 15
        for xy in got[i]:
            np.testing.assert_array_equal(xy, want[i])


@pytest.mark.parametrize("n", [0, 1, 255, 256, 257, 700])
def test_brief_equals_the_plain_gather_including_clamped_keypoints(n):
    img = blocks_image(8, (200, 300))
    sm = smooth_for_brief(img)
    rng = np.random.default_rng(n)
    xy = rng.uniform([16, 16], [284, 184], size=(n, 2))
    xy[: n // 10] = rng.uniform([-5, -5], [305, 205], size=(n // 10, 2))  # near and past edges
    d = compute_brief(sm, xy)
    assert d.shape == (n, 4) and d.dtype == np.uint64
    np.testing.assert_array_equal(d, reference_brief(sm, xy))
    for patch in (24, 48):  # other patch sizes, other offsets
        np.testing.assert_array_equal(compute_brief(sm, xy, patch), reference_brief(sm, xy, patch))
    out = np.empty_like(img)
    assert smooth_for_brief(img, out=out) is out
    np.testing.assert_array_equal(out, sm)


def test_kernels_equal_the_plain_formulas_on_redkitchen_frames(redkitchen: Path):
    for i in range(0, 1000, 125):
        gray = cv2.imread(str(redkitchen / f"frame-{i:06d}.color.jpg"), cv2.IMREAD_GRAYSCALE)
        c = assert_same_corners(gray, rel_threshold=0.001, max_corners=1500, border=16)
        assert len(c) > 100
        assert_same_corners(
            gray, rel_threshold=0.0005, max_corners=6000, border=8, subpixel="forstner"
        )
        sm = smooth_for_brief(gray)
        np.testing.assert_array_equal(compute_brief(sm, c.xy), reference_brief(sm, c.xy))


def test_harris_equals_the_plain_formula_at_full_contrast_and_rejects_other_dtypes():
    # The detector works on the raw Sobel (int16) and its products in float32, exact only while
    # they are integers below 2^24: the extreme case is a 0/255 image (Sobel up to 1020,
    # products up to 1040400).
    rng = np.random.default_rng(11)
    for shape in ((120, 160), (75, 101)):
        img = (rng.random(shape) > 0.5).astype(np.uint8) * 255
        yy, xx = np.mgrid[: shape[0] // 2, : shape[1]]
        img[: shape[0] // 2] = ((yy // 5 + xx // 5) % 2 * 255).astype(np.uint8)  # checkerboard
        np.testing.assert_array_equal(harris_response(img), reference_response(img))
        for kw in SETTINGS:
            assert_same_corners(img, **kw)
    with pytest.raises(ValueError, match="uint8"):
        detect_corners(np.zeros((40, 40), np.float32))
    with pytest.raises(ValueError, match="uint8"):
        harris_response(np.zeros((40, 40), np.uint16))


@pytest.mark.parametrize("width", [640, 641, 655, 7])
def test_opencv_scaled_multiply_rounds_as_k_times_p_then_times_p(width):
    # The response takes k (a + b)^2 from cv2.multiply(p, p, scale=k) as (k * p) * p, the
    # numpy formula's order; (p * p) * k rounds differently on about a third of such floats,
    # so an OpenCV computing that order (in its vector loop or its scalar tail: odd widths)
    # fails here.
    rng = np.random.default_rng(width)
    p = (rng.random((40, width), dtype=np.float32) * np.float32(1e9)).astype(np.float32)
    p[::2] -= np.float32(5e8)
    want = np.multiply(np.multiply(0.04, p), p)
    assert want.dtype == np.float32
    got = cv2.multiply(p, p, scale=0.04)
    np.testing.assert_array_equal(got.view(np.int32), want.view(np.int32))
    assert (np.multiply(np.multiply(p, p), np.float32(0.04)) != want).mean() > 0.1


def tracker_sequence(grays, **kw):
    """Corners of consecutive frames detected as the tracker does: the threshold of a frame is
    gamma times the previous frame's maximum (None on the first)."""
    prev, out = None, []
    for g in grays:
        thr = None if prev is None else 0.001 * prev
        c = assert_same_corners(g, threshold=thr, rel_threshold=0.001, **kw)
        prev = c.max_response
        out.append(c)
    return out


def test_harris_equals_the_plain_formula_with_the_previous_frames_threshold():
    from server_helpers import room_scene
    from sfmloc.cameras import Camera
    from sfmloc.synth import make_trajectory, render_full

    scene = room_scene(0)
    camera = Camera.pinhole(640, 480, 525.0, 525.0, 320.0, 240.0)
    traj = make_trajectory("walk", 12, 3, scene)  # cam_from_world, 30 Hz
    grays = [
        cv2.cvtColor(render_full(scene, camera, T, noise_seed=(0, 5, i)).bgr, cv2.COLOR_BGR2GRAY)
        for i, T in enumerate(traj[::3])
    ]
    cs = tracker_sequence(grays, max_corners=1500, border=16)
    assert min(len(c) for c in cs) > 100
    # A threshold over the image's maximum: no corners, and still the image's maximum.
    g = grays[0]
    c = assert_same_corners(g, threshold=2.0 * cs[0].max_response, border=16)
    assert len(c) == 0 and c.max_response == cs[0].max_response


def test_harris_equals_the_plain_formula_on_consecutive_redkitchen_frames(redkitchen: Path):
    for start in (0, 500):
        grays = [
            cv2.imread(str(redkitchen / f"frame-{i:06d}.color.jpg"), cv2.IMREAD_GRAYSCALE)
            for i in range(start, start + 6)
        ]
        cs = tracker_sequence(grays, max_corners=1500, border=16)
        assert min(len(c) for c in cs) > 100


def test_harris_buffers_come_from_one_arena_across_a_pyramid_and_large_images(monkeypatch):
    """Every shape's buffers are views of one arena per thread, grown to the largest shape and
    kept (the builder's pyramid cycles through 11 shapes per image; 1920x1440 images had fresh
    buffers on every call): the same corners bit for bit at every level, in any order, with the
    arena grown, reused and released, and over its bound (fresh buffers)."""
    from sfmloc.features.pyramid import build_pyramid, level_scales

    harris.release_buffers()
    big = blocks_image(20, (1440, 1920))
    pyramid = build_pyramid(blocks_image(21, (480, 640)), level_scales(2, 4, 2))
    builder = SETTINGS[1]
    for level in pyramid:  # 905x679 (off the vector width) down to 160x120
        assert_same_corners(level.image, **builder)
    arena = harris._local.arena
    assert arena.size == harris._Workspace.nbytes(pyramid[0].image.shape)
    for level in pyramid[::-1]:  # the other way round: the same arena, the same corners
        assert_same_corners(level.image, **SETTINGS[0])
    assert harris._local.arena is arena and len(harris._local.shapes) == len(pyramid)
    assert_same_corners(big, **builder)  # grows it: 72 MB, under the bound
    assert harris._local.arena.size == harris._Workspace.nbytes(big.shape) > arena.size
    grown = harris._local.arena
    for img in (pyramid[3].image, big, pyramid[0].image):
        assert_same_corners(img, **builder)
    assert harris._local.arena is grown
    harris.release_buffers()
    assert not hasattr(harris._local, "arena")
    monkeypatch.setattr(harris, "_ARENA_MAX_BYTES", harris._Workspace.nbytes(big.shape) - 1)
    assert_same_corners(big, **builder)  # over the bound: fresh buffers, not kept
    assert not hasattr(harris._local, "arena")
    assert_same_corners(pyramid[2].image, **builder)
    assert harris._local.arena.size == harris._Workspace.nbytes(pyramid[2].image.shape)
