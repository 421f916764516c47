"""Procedural textures whose corner features are known exactly.

A texture is drawn on a ``Canvas`` in texel units. Texel ``(row b, col a)`` covers the square
``[a, a+1) x [b, b+1)`` in *texel-corner coordinates* (COLMAP's pixel convention applied to
textures: texel centres at half-integers). Rectangles fill whole texels, so every rectangle
corner lies exactly on an integer texel-corner coordinate, which ``scene`` maps to an exact 3D
point. Drawing a rectangle registers its corners as candidates; ``verify_corners`` keeps those
that are still clean junctions in the *final* texture (not covered by a later rectangle, not on
the texture border, enough contrast) and measures how far the clean neighbourhood extends.

Content mixes realistic corner structure (posters, shelves of books, notice boards, text-like
glyph lines, windows, doors, tiles, light panels) with repeated patterns (tile grids,
checkerboards, the same poster several times) because ambiguity is part of the test. A light
grain covers everything so no large area is one flat colour.

Public: ``Canvas``, ``verify_corners``, ``compose_wall``, ``compose_floor``,
``compose_ceiling``, ``compose_box_face``, ``make_poster_designs``.
"""

from __future__ import annotations

import colorsys
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

Color = tuple[int, int, int]  # BGR


# --------------------------------------------------------------------------- colours
def hsv_color(h: float, s: float, v: float) -> Color:
    r, g, b = colorsys.hsv_to_rgb(h % 1.0, float(np.clip(s, 0, 1)), float(np.clip(v, 0, 1)))
    return (int(round(b * 255)), int(round(g * 255)), int(round(r * 255)))


def random_color(
    rng: np.random.Generator,
    s: tuple[float, float] = (0.15, 0.75),
    v: tuple[float, float] = (0.2, 0.9),
) -> Color:
    return hsv_color(rng.random(), rng.uniform(*s), rng.uniform(*v))


def jitter(c: Color, rng: np.random.Generator, amount: float) -> Color:
    """Vary mostly the brightness (a common offset), slightly the hue."""
    common = rng.uniform(-amount, amount)
    out = tuple(int(np.clip(x + common + rng.uniform(-amount, amount) / 4, 12, 243)) for x in c)
    return out  # type: ignore[return-value]


def each(c: Color, f: Callable[[int], int]) -> Color:
    """``f`` applied to each channel."""
    return (f(c[0]), f(c[1]), f(c[2]))


def shifted(c: Color, d: int) -> Color:
    """Each channel plus ``d``, clipped to 0..255."""
    return each(c, lambda v: int(np.clip(v + d, 0, 255)))


def gray_of(c: Color) -> float:
    b, g, r = c
    return 0.114 * b + 0.587 * g + 0.299 * r


def contrasting(rng: np.random.Generator, against: Color, min_diff: float = 45.0, **kw) -> Color:
    """A random colour whose gray level differs from ``against`` by at least ``min_diff``."""
    for _ in range(50):
        c = random_color(rng, **kw)
        if abs(gray_of(c) - gray_of(against)) >= min_diff:
            return c
    return (30, 30, 30) if gray_of(against) > 128 else (225, 225, 225)


# --------------------------------------------------------------------------- canvas
class Canvas:
    """A BGR texture under construction plus the corners its rectangles registered."""

    def __init__(self, width: int, height: int, color: Color, texel: float) -> None:
        self.img = np.empty((max(1, height), max(1, width), 3), np.uint8)
        self.img[:] = color
        self.texel = float(texel)
        self._corners: list[tuple[int, int]] = []

    @property
    def w(self) -> int:
        return self.img.shape[1]

    @property
    def h(self) -> int:
        return self.img.shape[0]

    def t(self, metres: float) -> int:
        """Metres to whole texels (at least 1)."""
        return max(1, int(round(metres / self.texel)))

    def rect(self, x0: int, y0: int, x1: int, y1: int, color: Color, register: bool = True) -> None:
        """Fill texels ``[x0, x1) x [y0, y1)``; its corners are at exactly those coordinates."""
        x0, x1 = sorted((int(x0), int(x1)))
        y0, y1 = sorted((int(y0), int(y1)))
        x0, x1 = max(0, x0), min(self.w, x1)
        y0, y1 = max(0, y0), min(self.h, y1)
        if x1 <= x0 or y1 <= y0:
            return
        self.img[y0:y1, x0:x1] = color
        if register:
            self._corners += [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]

    def frame(self, x0: int, y0: int, x1: int, y1: int, thick: int, color: Color) -> None:
        self.rect(x0, y0, x1, y0 + thick, color)
        self.rect(x0, y1 - thick, x1, y1, color)
        self.rect(x0, y0, x0 + thick, y1, color)
        self.rect(x1 - thick, y0, x1, y1, color)

    def paste(self, other: Canvas, x: int, y: int) -> None:
        """Copy ``other`` with its upper-left texel at ``(x, y)``; its corners come along."""
        x, y = int(x), int(y)
        sx0, sy0 = max(0, -x), max(0, -y)
        sx1, sy1 = min(other.w, self.w - x), min(other.h, self.h - y)
        if sx1 <= sx0 or sy1 <= sy0:
            return
        self.img[y + sy0 : y + sy1, x + sx0 : x + sx1] = other.img[sy0:sy1, sx0:sx1]
        # Corners covered by the pasted block are gone; the block's own come in.
        self._corners += [(cx + x, cy + y) for cx, cy in other._corners]

    def corners(self) -> np.ndarray:
        """Unique registered corners (N, 2) int, texel-corner coordinates ``(x, y)``."""
        if not self._corners:
            return np.zeros((0, 2), np.int64)
        return np.unique(np.array(self._corners, np.int64), axis=0)

    def finish(self, rng: np.random.Generator, grain: float) -> np.ndarray:
        """Add fine grain and a faint large-scale variation; returns the final image."""
        h, w = self.h, self.w
        out = self.img.astype(np.float32)
        if grain > 0:
            g = cv2.GaussianBlur(rng.standard_normal((h, w), dtype=np.float32), (0, 0), 0.7)
            g = g * (grain / max(1e-6, float(g.std())))  # float32 (a Python float is weak)
            out += g[..., None]
        # Large-scale (~1 m) multiplicative variation: dirt, uneven paint, light falloff.
        gh, gw = max(2, int(h * self.texel) + 2), max(2, int(w * self.texel) + 2)
        low: np.ndarray = rng.uniform(0.96, 1.04, (gh, gw)).astype(np.float32)
        low = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
        out *= low[..., None]
        self.img = np.clip(np.rint(out), 0, 255).astype(np.uint8)
        return self.img


# --------------------------------------------------------------------------- verification
@dataclass
class CornerSet:
    """Verified corners of one texture."""

    xy: np.ndarray  # (N, 2) int texel-corner coordinates (x, y)
    radius: np.ndarray  # (N,) int: clean quadrant half-size in texels
    color: np.ndarray  # (N, 3) uint8 BGR: mean colour of the four quadrants


def verify_corners(
    img: np.ndarray,
    candidates: np.ndarray,
    radii: tuple[int, ...] = (2, 3, 4, 6, 8, 12, 16, 24, 32),
    std_max: float = 6.0,
    contrast_min: float = 30.0,
) -> CornerSet:
    """Keep candidates that are clean L-, T- or X-junctions of the final texture.

    Around a candidate, the four ``r x r`` quadrants must each be uniform (gray std below
    ``std_max``) and the junction must have both a horizontal and a vertical edge of at least
    ``contrast_min`` gray levels through the corner; then every edge of the neighbourhood is
    a straight line through the corner, so its image position is well defined. The radius is
    the largest ``r`` of ``radii`` passing together with all smaller ones (first must pass).
    """
    cand = np.asarray(candidates, np.int64).reshape(-1, 2)
    h, w = img.shape[:2]
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float64)
    S, SS = cv2.integral2(gray, sdepth=cv2.CV_64F, sqdepth=cv2.CV_64F)
    x, y = cand[:, 0], cand[:, 1]
    alive = np.ones(len(cand), bool)
    best = np.zeros(len(cand), np.int64)

    def box(I: np.ndarray, xa, ya, xb, yb) -> np.ndarray:
        return I[yb, xb] - I[ya, xb] - I[yb, xa] + I[ya, xa]

    for r in radii:
        ok = alive & (x - r >= 0) & (y - r >= 0) & (x + r <= w) & (y + r <= h)
        # Out-of-range candidates are already rejected; clip only to index safely.
        xm, xc, xp = np.clip(x - r, 0, w), np.clip(x, 0, w), np.clip(x + r, 0, w)
        ym, yc, yp = np.clip(y - r, 0, h), np.clip(y, 0, h), np.clip(y + r, 0, h)
        quads = [(xm, ym, xc, yc), (xc, ym, xp, yc), (xc, yc, xp, yp), (xm, yc, xc, yp)]
        means, stds = [], []
        for xa, ya, xb, yb in quads:  # TL, TR, BR, BL
            area = np.maximum((xb - xa) * (yb - ya), 1)
            s = box(S, xa, ya, xb, yb) / area
            ss = box(SS, xa, ya, xb, yb) / area
            means.append(s)
            stds.append(np.sqrt(np.maximum(ss - s * s, 0.0)))
        tl, tr, br, bl = means
        uniform = np.all(np.stack(stds) <= std_max, axis=0)
        horiz = (np.abs(tl - bl) >= contrast_min) | (np.abs(tr - br) >= contrast_min)
        vert = (np.abs(tl - tr) >= contrast_min) | (np.abs(bl - br) >= contrast_min)
        ok &= uniform & horiz & vert
        best[ok] = r
        alive = ok
    keep = best > 0
    xy, rad = cand[keep], best[keep]
    # Mean colour of the 2x2 texels at the corner (for the model's point colour).
    colors = np.zeros((len(xy), 3), np.uint8)
    if len(xy):
        xx, yy = xy[:, 0], xy[:, 1]
        patch = (
            img[yy - 1, xx - 1].astype(np.int32) + img[yy - 1, xx] + img[yy, xx - 1] + img[yy, xx]
        )
        colors = (patch // 4).astype(np.uint8)
    return CornerSet(xy, rad, colors)


# --------------------------------------------------------------------------- elements
def _snap(v: float, q: int = 2) -> int:
    """Snap to a multiple of ``q`` texels: box-filtered mip levels stay exact at corners."""
    return int(round(v / q)) * q


def mondrian(
    cv: Canvas,
    x0: int,
    y0: int,
    x1: int,
    y1: int,
    rng: np.random.Generator,
    n: int,
    min_m: float = 0.03,
    max_frac: float = 0.35,
    palette: list[Color] | None = None,
) -> None:
    """Random overlapping axis-aligned rectangles (sizes log-uniform) in a region."""
    W, H = x1 - x0, y1 - y0
    if W < 4 or H < 4:
        return
    lo = max(2, cv.t(min_m))
    for _ in range(n):
        hi_w, hi_h = max(lo + 1, int(W * max_frac)), max(lo + 1, int(H * max_frac))
        rw = int(np.exp(rng.uniform(np.log(lo), np.log(hi_w))))
        rh = int(np.exp(rng.uniform(np.log(lo), np.log(hi_h))))
        rx = x0 + _snap(rng.uniform(0, max(1, W - rw)))
        ry = y0 + _snap(rng.uniform(0, max(1, H - rh)))
        col = palette[rng.integers(len(palette))] if palette else random_color(rng)
        cv.rect(rx, ry, min(x1, rx + _snap(rw)), min(y1, ry + _snap(rh)), jitter(col, rng, 10))


def text_lines(
    cv: Canvas,
    x0: int,
    y0: int,
    x1: int,
    y1: int,
    rng: np.random.Generator,
    glyph_m: float,
    color: Color,
    line_gap: float = 1.8,
) -> None:
    """Rows of text-like glyph blocks: words of small rectangles, some with ascenders."""
    gh = max(2, cv.t(glyph_m))
    y = y0 + gh
    while y + gh <= y1:
        x = x0 + int(rng.integers(0, 3 * gh))
        line_end = x1 - int(rng.integers(0, max(1, (x1 - x0) // 3)))
        while x < line_end:
            for _ in range(int(rng.integers(2, 9))):  # one word
                gw = max(1, int(gh * rng.uniform(0.45, 0.9)))
                if x + gw > line_end:
                    break
                kind = rng.random()
                if kind < 0.2:  # ascender
                    cv.rect(x, y - int(gh * 0.4), x + gw, y + gh, color)
                elif kind < 0.3:  # descender
                    cv.rect(x, y, x + gw, y + int(gh * 1.4), color)
                elif kind < 0.4:  # two strokes
                    cv.rect(x, y, x + max(1, gw // 3), y + gh, color)
                    cv.rect(x + gw - max(1, gw // 3), y, x + gw, y + gh, color)
                else:
                    cv.rect(x, y, x + gw, y + gh, color)
                x += gw + max(1, gh // 4)
            x += gh  # word space
        y += int(gh * line_gap) + gh


def tiles(
    cv: Canvas,
    x0: int,
    y0: int,
    x1: int,
    y1: int,
    rng: np.random.Generator,
    tile_m: float,
    grout_m: float,
    colors: list[Color],
    grout: Color,
    checker: bool = False,
    var: float = 6.0,
) -> None:
    """A tile grid: grout lines between tiles, or a checkerboard when ``grout_m`` is 0."""
    T, G = cv.t(tile_m), (cv.t(grout_m) if grout_m > 0 else 0)
    if G:
        cv.rect(x0, y0, x1, y1, grout, register=False)
    for j, ty in enumerate(range(y0, y1, T)):
        for i, tx in enumerate(range(x0, x1, T)):
            c = colors[(i + j) % len(colors)] if checker else colors[int(rng.integers(len(colors)))]
            cv.rect(
                tx + G // 2,
                ty + G // 2,
                min(x1, tx + T) - (G - G // 2),
                min(y1, ty + T) - (G - G // 2),
                jitter(c, rng, var),
            )


def checkerboard(cv: Canvas, x: int, y: int, nx: int, ny: int, sq_m: float) -> None:
    """A printed calibration target: white margin around ``nx x ny`` squares."""
    sq = cv.t(sq_m)
    m = sq
    cv.rect(x, y, x + nx * sq + 2 * m, y + ny * sq + 2 * m, (235, 235, 235))
    for j in range(ny):
        for i in range(nx):
            if (i + j) % 2 == 0:
                cv.rect(
                    x + m + i * sq,
                    y + m + j * sq,
                    x + m + (i + 1) * sq,
                    y + m + (j + 1) * sq,
                    (25, 25, 25),
                )


def books(cv: Canvas, x0: int, x1: int, y_base: int, max_h: int, rng: np.random.Generator) -> None:
    """A row of book spines standing on a shelf at ``y_base`` (texel row of the shelf top)."""
    x = x0 + int(rng.integers(0, cv.t(0.05)))
    while x < x1:
        if rng.random() < 0.08:  # a gap
            x += cv.t(rng.uniform(0.03, 0.12))
            continue
        bw = cv.t(rng.uniform(0.018, 0.06))
        bh = int(max_h * rng.uniform(0.6, 0.95))
        if x + bw > x1:
            break
        col = random_color(rng, s=(0.25, 0.85), v=(0.15, 0.85))
        cv.rect(x, y_base - bh, x + bw, y_base, col)
        if bw > cv.t(0.025) and rng.random() < 0.6:  # a label on the spine
            lab = contrasting(rng, col, 50, s=(0.0, 0.3), v=(0.6, 0.95))
            ly = y_base - bh + cv.t(rng.uniform(0.02, 0.05))
            cv.rect(x + 2, ly, x + bw - 2, ly + cv.t(rng.uniform(0.02, 0.05)), lab)
        x += bw + int(rng.integers(0, 2))


def bookshelf(cv: Canvas, x0: int, y0: int, x1: int, y1: int, rng: np.random.Generator) -> None:
    wood = jitter((40, 70, 110), rng, 20)
    cv.rect(x0, y0, x1, y1, wood)
    inner = jitter((25, 40, 60), rng, 10)  # the dark back of the shelf
    side = cv.t(0.02)
    shelf_h = cv.t(rng.uniform(0.28, 0.38))
    board = cv.t(0.02)
    y = y0 + side
    while y + shelf_h + board <= y1 - side:
        cv.rect(x0 + side, y, x1 - side, y + shelf_h, inner)
        books(cv, x0 + side, x1 - side, y + shelf_h, shelf_h - cv.t(0.02), rng)
        y += shelf_h + board


def poster_design(rng: np.random.Generator, w_m: float, h_m: float, texel: float) -> Canvas:
    """A framed poster: photo-like block, a title of glyphs, a coloured band, fine print."""
    cv = Canvas(1, 1, (0, 0, 0), texel)
    W, H = cv.t(w_m), cv.t(h_m)
    paper = jitter((225, 228, 230), rng, 10)
    cv = Canvas(W, H, paper, texel)
    fr = cv.t(0.015)
    m = cv.t(0.04)
    band = random_color(rng, s=(0.5, 0.9), v=(0.3, 0.7))
    kind = rng.integers(3)
    photo_y1 = int(H * rng.uniform(0.5, 0.65))
    if kind == 0:  # abstract art
        cv.rect(m, m, W - m, photo_y1, random_color(rng, v=(0.3, 0.7)))
        mondrian(cv, m, m, W - m, photo_y1, rng, 40, min_m=0.02)
    elif kind == 1:  # "landscape": horizontal bands and blocky shapes
        yy = m
        while yy < photo_y1:
            bh = cv.t(rng.uniform(0.03, 0.1))
            cv.rect(m, yy, W - m, min(photo_y1, yy + bh), random_color(rng))
            yy += bh
        mondrian(cv, m, m, W - m, photo_y1, rng, 15, min_m=0.03, max_frac=0.3)
    else:  # "chart": bars
        cv.rect(m, m, W - m, photo_y1, jitter((240, 240, 240), rng, 5))
        nb = int(rng.integers(5, 10))
        bw = (W - 2 * m) // (nb * 2 + 1)
        for i in range(nb):
            top = int(rng.uniform(m + 0.1 * (photo_y1 - m), photo_y1 - bw))
            cv.rect(m + (2 * i + 1) * bw, top, m + (2 * i + 2) * bw, photo_y1 - cv.t(0.01), band)
    ty = photo_y1 + cv.t(0.03)
    cv.rect(m, ty, W - m, ty + cv.t(0.05), band)
    text_lines(
        cv, m + cv.t(0.01), ty + cv.t(0.005), W - m, ty + cv.t(0.045), rng, 0.025, (235, 235, 235)
    )
    text_lines(cv, m, ty + cv.t(0.07), W - m, H - m, rng, 0.012, (40, 40, 40), line_gap=1.2)
    cv.frame(0, 0, W, H, fr, jitter((30, 30, 30), rng, 10))
    return cv


def make_poster_designs(rng: np.random.Generator, texel: float, n: int = 4) -> list[Canvas]:
    """Poster designs shared by all walls, so the same poster hangs in several places."""
    sizes = [(0.6, 0.85), (0.5, 0.7), (0.7, 0.5), (0.42, 0.6)]
    return [poster_design(rng, *sizes[i % len(sizes)], texel) for i in range(n)]


def whiteboard(cv: Canvas, x0: int, y0: int, x1: int, y1: int, rng: np.random.Generator) -> None:
    cv.rect(x0, y0, x1, y1, (185, 185, 180))
    f = cv.t(0.02)
    cv.rect(x0 + f, y0 + f, x1 - f, y1 - f, jitter((238, 238, 236), rng, 4))
    ink = [(140, 40, 30), (30, 30, 30), (40, 40, 160), (40, 120, 40)]
    n_blocks = int(rng.integers(2, 5))
    for _ in range(n_blocks):
        bw = int((x1 - x0) * rng.uniform(0.25, 0.5))
        bh = int((y1 - y0) * rng.uniform(0.2, 0.4))
        bx = int(rng.uniform(x0 + 2 * f, max(x0 + 2 * f + 1, x1 - 2 * f - bw)))
        by = int(rng.uniform(y0 + 2 * f, max(y0 + 2 * f + 1, y1 - 2 * f - bh)))
        text_lines(
            cv,
            bx,
            by,
            bx + bw,
            by + bh,
            rng,
            rng.uniform(0.015, 0.03),
            ink[int(rng.integers(len(ink)))],
        )
    for _ in range(int(rng.integers(3, 9))):  # sticky notes
        s = cv.t(0.076)
        nx = int(rng.uniform(x0 + 2 * f, x1 - 2 * f - s))
        ny = int(rng.uniform(y0 + 2 * f, y1 - 2 * f - s))
        cv.rect(nx, ny, nx + s, ny + s, hsv_color(rng.choice([0.15, 0.3, 0.55, 0.9]), 0.55, 0.95))
    cv.rect(x0 + f, y1 - f, x1 - f, y1 + cv.t(0.03), (170, 170, 170))  # pen tray


def notice_board(cv: Canvas, x0: int, y0: int, x1: int, y1: int, rng: np.random.Generator) -> None:
    cv.rect(x0, y0, x1, y1, (50, 60, 70))
    f = cv.t(0.025)
    cork = jitter((90, 140, 180), rng, 10)
    cv.rect(x0 + f, y0 + f, x1 - f, y1 - f, cork)
    for _ in range(int(rng.integers(6, 14))):
        pw, ph = cv.t(rng.choice([0.148, 0.21, 0.1])), cv.t(rng.choice([0.21, 0.297, 0.15]))
        if pw >= x1 - x0 - 2 * f or ph >= y1 - y0 - 2 * f:
            continue
        px = int(rng.uniform(x0 + f, x1 - f - pw))
        py = int(rng.uniform(y0 + f, y1 - f - ph))
        paper = hsv_color(rng.random(), rng.uniform(0, 0.35), rng.uniform(0.85, 0.97))
        cv.rect(px, py, px + pw, py + ph, paper)
        text_lines(
            cv,
            px + cv.t(0.01),
            py + cv.t(0.01),
            px + pw - cv.t(0.01),
            py + ph - cv.t(0.01),
            rng,
            rng.uniform(0.008, 0.016),
            (40, 40, 40),
            line_gap=1.4,
        )
        if rng.random() < 0.5:
            cv.rect(
                px + cv.t(0.01),
                py + cv.t(0.02),
                px + pw - cv.t(0.01),
                py + ph // 3,
                random_color(rng),
            )


def window(cv: Canvas, x0: int, y0: int, x1: int, y1: int, rng: np.random.Generator) -> None:
    frame_c = jitter((230, 230, 228), rng, 6)
    cv.rect(x0, y0, x1, y1, frame_c)
    f = cv.t(0.05)
    nx, ny = int(rng.integers(2, 4)), int(rng.integers(2, 4))
    mull = cv.t(0.03)
    pw = (x1 - x0 - 2 * f - (nx - 1) * mull) // nx
    ph = (y1 - y0 - 2 * f - (ny - 1) * mull) // ny
    for j in range(ny):
        for i in range(nx):
            px, py = x0 + f + i * (pw + mull), y0 + f + j * (ph + mull)
            # Outside seen through the glass: sky and a skyline of buildings.
            cv.rect(px, py, px + pw, py + ph, jitter((225, 200, 170), rng, 8))
            ground = py + int(ph * rng.uniform(0.45, 0.8)) if j == ny - 1 else py + ph
            bx = px
            while bx < px + pw and j == ny - 1:
                bw = cv.t(rng.uniform(0.05, 0.2))
                top = int(rng.uniform(py + ph * 0.2, ground))
                cv.rect(
                    bx,
                    top,
                    min(px + pw, bx + bw),
                    py + ph,
                    random_color(rng, s=(0, 0.3), v=(0.3, 0.7)),
                )
                bx += bw
    cv.rect(x0 - cv.t(0.03), y1, x1 + cv.t(0.03), y1 + cv.t(0.04), frame_c)  # sill


def door(cv: Canvas, x0: int, y0: int, x1: int, y1: int, rng: np.random.Generator) -> None:
    """Mostly low texture on purpose: a plain leaf, frame, handle and a small sign."""
    frame_c = jitter((200, 205, 210), rng, 8)
    cv.rect(x0 - cv.t(0.06), y0 - cv.t(0.06), x1 + cv.t(0.06), y1, frame_c)
    leaf = jitter((60, 100, 140), rng, 20)
    cv.rect(x0, y0, x1, y1, leaf)
    hy = y0 + int((y1 - y0) * 0.48)
    hx = x1 - cv.t(0.1)
    cv.rect(hx, hy, hx + cv.t(0.03), hy + cv.t(0.03), (170, 175, 180))
    cv.rect(hx - cv.t(0.1), hy + cv.t(0.005), hx + cv.t(0.03), hy + cv.t(0.025), (170, 175, 180))
    sx = (x0 + x1) // 2 - cv.t(0.1)
    sy = y0 + cv.t(0.35)
    cv.rect(sx, sy, sx + cv.t(0.2), sy + cv.t(0.1), (240, 240, 240))
    text_lines(
        cv,
        sx + cv.t(0.015),
        sy + cv.t(0.01),
        sx + cv.t(0.185),
        sy + cv.t(0.09),
        rng,
        0.018,
        (30, 30, 30),
    )


def small_fixtures(cv: Canvas, x0: int, x1: int, rng: np.random.Generator, floor_row: int) -> None:
    """Sockets and switches: small high-contrast rectangles at standard heights."""
    for _ in range(int((x1 - x0) * cv.texel / 1.5) + 1):
        x = int(rng.uniform(x0, max(x0 + 1, x1 - cv.t(0.1))))
        y = floor_row - cv.t(rng.choice([0.3, 1.1]))
        cv.rect(x, y, x + cv.t(0.08), y + cv.t(0.08), (228, 228, 226))
        cv.rect(x + cv.t(0.025), y + cv.t(0.02), x + cv.t(0.055), y + cv.t(0.06), (110, 110, 110))


# --------------------------------------------------------------------------- surfaces
def compose_wall(
    width_m: float,
    height_m: float,
    rng: np.random.Generator,
    texel: float,
    posters: list[Canvas],
    grain: float,
) -> tuple[np.ndarray, np.ndarray]:
    """A wall seen from inside the room, upper-left texel first. Returns (texture, corners).

    Three bands along the wall: low (wainscot panels, radiators, tiles), middle (posters,
    boards, windows, doors, shelves, art, calibration targets) and high (banners, frames,
    vents, storage shelves); a little bare paint between items.
    """
    paint = hsv_color(rng.uniform(0.05, 0.6), rng.uniform(0.03, 0.15), rng.uniform(0.72, 0.86))
    cv = Canvas(int(round(width_m / texel)), int(round(height_m / texel)), paint, texel)
    W, H = cv.w, cv.h
    floor = H  # texel row of the floor

    def row(height_above_floor_m: float) -> int:
        return floor - cv.t(height_above_floor_m)

    _wall_low_band(cv, rng, row)
    small_fixtures(cv, 0, W, rng, floor)
    cv.rect(0, row(0.09), W, H, jitter((60, 60, 65), rng, 15))  # baseboard
    cv.rect(0, 0, W, cv.t(0.05), jitter((235, 235, 235), rng, 5))  # crown moulding
    _wall_high_band(cv, rng, row)
    kinds = [
        "poster",
        "poster",
        "whiteboard",
        "notice",
        "window",
        "door",
        "shelf",
        "tiles",
        "art",
        "checker",
        "posters",
    ]
    weights = np.array([3, 2, 1.5, 1.5, 1.2, 0.6, 1.2, 1.0, 1.5, 0.6, 1.2])
    x = cv.t(rng.uniform(0.05, 0.3))
    while x < W - cv.t(0.4):
        kind = kinds[int(rng.choice(len(kinds), p=weights / weights.sum()))]
        if kind == "poster":
            p = posters[int(rng.integers(len(posters)))]
            if x + p.w > W:
                break
            cv.paste(p, x, row(rng.uniform(1.4, 1.65)) - p.h // 2)
            ew = p.w
        elif kind == "posters":  # a gallery of small frames, some repeated
            ew = 0
            for _ in range(int(rng.integers(2, 5))):
                fw, fh = cv.t(rng.uniform(0.25, 0.4)), cv.t(rng.uniform(0.3, 0.45))
                if x + ew + fw > W:
                    break
                top = row(rng.uniform(1.5, 2.0))
                cv.rect(x + ew, top, x + ew + fw, top + fh, jitter((30, 30, 30), rng, 10))
                b = cv.t(0.03)
                cv.rect(x + ew + b, top + b, x + ew + fw - b, top + fh - b, (230, 230, 230))
                mondrian(
                    cv,
                    x + ew + 2 * b,
                    top + 2 * b,
                    x + ew + fw - 2 * b,
                    top + fh - 2 * b,
                    np.random.default_rng(int(rng.integers(3))),
                    12,
                    min_m=0.02,
                )
                ew += fw + cv.t(0.06)
        elif kind == "whiteboard":
            ew = min(cv.t(rng.uniform(1.2, 1.8)), W - x)
            whiteboard(cv, x, row(2.05), x + ew, row(0.95), rng)
        elif kind == "notice":
            ew = cv.t(rng.uniform(0.8, 1.2))
            notice_board(
                cv,
                x,
                row(rng.uniform(1.8, 2.05)),
                min(W, x + ew),
                row(rng.uniform(0.95, 1.15)),
                rng,
            )
        elif kind == "window":
            ew = cv.t(rng.uniform(1.0, 1.5))
            if x + ew > W:
                break
            window(cv, x, row(2.2), x + ew, row(0.95), rng)
        elif kind == "door":
            ew = cv.t(0.9)
            if x + ew + cv.t(0.06) > W:
                break
            door(cv, x, row(2.05), x + ew, floor, rng)
        elif kind == "shelf":
            ew = cv.t(rng.uniform(0.8, 1.3))
            for hgt in (1.25, 1.65, 2.05):
                top = row(hgt)
                books(cv, x, min(W, x + ew), top, cv.t(0.3), rng)
                cv.rect(
                    x - cv.t(0.02),
                    top,
                    min(W, x + ew + cv.t(0.02)),
                    top + cv.t(0.025),
                    jitter((50, 80, 120), rng, 15),
                )
        elif kind == "tiles":
            ew = cv.t(rng.uniform(1.0, 1.8))
            colors = [
                jitter((215, 215, 210), rng, 8),
                jitter(random_color(rng, s=(0.3, 0.6), v=(0.4, 0.7)), rng, 4),
            ]
            tile = rng.choice([0.1, 0.15, 0.2])
            checker = bool(rng.random() < 0.4)
            tiles(
                cv,
                x,
                row(1.6),
                min(W, x + ew),
                row(0.9),
                rng,
                tile,
                0.0 if checker else 0.006,
                colors if checker else colors[:1] * 5 + colors[1:],
                (150, 150, 150),
                checker=checker,
            )
            mondrian(
                cv,
                x + cv.t(0.1),
                row(2.05),
                min(W, x + ew) - cv.t(0.1),
                row(1.7),
                rng,
                25,
                min_m=0.04,
            )
        elif kind == "art":
            ew = cv.t(rng.uniform(0.6, 1.1))
            eh = cv.t(rng.uniform(0.6, 1.0))
            top = row(rng.uniform(1.5, 1.7)) - eh // 2
            cv.rect(x, top, min(W, x + ew), top + eh, jitter((40, 40, 40), rng, 10))
            mondrian(
                cv,
                x + cv.t(0.03),
                top + cv.t(0.03),
                min(W, x + ew) - cv.t(0.03),
                top + eh - cv.t(0.03),
                rng,
                int(rng.integers(20, 50)),
                min_m=0.04,
            )
        else:  # checker
            nx, ny = int(rng.integers(6, 10)), int(rng.integers(4, 7))
            sq = rng.choice([0.04, 0.05, 0.06])
            ew = cv.t(sq * (nx + 2))
            checkerboard(cv, x, row(rng.uniform(1.3, 1.8)), nx, ny, sq)
        x += ew + cv.t(rng.uniform(0.08, 0.3))
    img = cv.finish(rng, grain)
    return img, cv.corners()


def _wall_low_band(cv: Canvas, rng: np.random.Generator, row) -> None:
    """Wainscot panels, radiators and tile strips between 0.1 and 0.85 m."""
    x = 0
    while x < cv.w:
        kind = rng.choice(
            ["wainscot", "radiator", "tiles", "frames", "bare"], p=[0.35, 0.2, 0.15, 0.15, 0.15]
        )
        ew = cv.t(rng.uniform(0.8, 2.0))
        x1 = min(cv.w, x + ew)
        if kind == "wainscot":
            pw = cv.t(rng.uniform(0.35, 0.55))
            frame_c = jitter((150, 160, 170), rng, 25)
            inner = shifted(jitter(frame_c, rng, 10), 45 * (1 if gray_of(frame_c) < 128 else -1))
            cv.rect(x, row(0.85), x1, row(0.1), frame_c)
            for px in range(x + cv.t(0.04), x1 - pw // 2, pw):
                cv.rect(px, row(0.8), min(x1 - cv.t(0.04), px + pw - cv.t(0.05)), row(0.15), inner)
        elif kind == "radiator":
            top, bot = row(rng.uniform(0.55, 0.7)), row(0.15)
            body = jitter((215, 215, 215), rng, 10)
            cv.rect(x, top, x1, bot, body)
            slat = cv.t(0.04)
            for sx in range(x + slat // 2, x1 - slat, slat):
                cv.rect(
                    sx,
                    top + cv.t(0.03),
                    sx + slat // 2,
                    bot - cv.t(0.03),
                    each(body, lambda c: int(c * 0.7)),
                )
        elif kind == "tiles":
            colors = [
                jitter((200, 205, 205), rng, 10),
                jitter(random_color(rng, v=(0.3, 0.6)), rng, 5),
            ]
            tiles(
                cv,
                x,
                row(0.8),
                x1,
                row(0.1),
                rng,
                rng.choice([0.1, 0.15]),
                0.0,
                colors,
                (0, 0, 0),
                checker=True,
            )
        elif kind == "frames":
            fx = x
            while fx < x1 - cv.t(0.3):
                fw, fh = cv.t(rng.uniform(0.2, 0.35)), cv.t(rng.uniform(0.2, 0.4))
                top = row(rng.uniform(0.55, 0.8))
                cv.rect(fx, top, fx + fw, top + fh, jitter((200, 60, 60), rng, 40))
                m = cv.t(0.02)
                mondrian(cv, fx + m, top + m, fx + fw - m, top + fh - m, rng, 10, min_m=0.03)
                fx += fw + cv.t(rng.uniform(0.05, 0.15))
        x = x1 + cv.t(rng.uniform(0.0, 0.3))


def _wall_high_band(cv: Canvas, rng: np.random.Generator, row) -> None:
    """Banners, small frames, vents and storage shelves between 2.25 and 2.9 m."""
    x = cv.t(rng.uniform(0.0, 0.3))
    while x < cv.w - cv.t(0.3):
        kind = rng.choice(
            ["banner", "frames", "vent", "storage", "clock", "bare"],
            p=[0.25, 0.2, 0.15, 0.2, 0.1, 0.1],
        )
        if kind == "banner":
            ew = cv.t(rng.uniform(0.8, 2.0))
            top = row(rng.uniform(2.75, 2.85))
            bh = cv.t(rng.uniform(0.18, 0.3))
            col = random_color(rng, s=(0.4, 0.9), v=(0.25, 0.6))
            cv.rect(x, top, min(cv.w, x + ew), top + bh, col)
            text_lines(
                cv,
                x + cv.t(0.04),
                top + cv.t(0.01),
                min(cv.w, x + ew) - cv.t(0.04),
                top + bh - cv.t(0.02),
                rng,
                rng.uniform(0.05, 0.08),
                (235, 235, 235),
            )
        elif kind == "frames":
            ew = 0
            for _ in range(int(rng.integers(2, 5))):
                fw, fh = cv.t(rng.uniform(0.15, 0.3)), cv.t(rng.uniform(0.2, 0.3))
                top = row(rng.uniform(2.55, 2.75))
                cv.rect(x + ew, top, x + ew + fw, top + fh, jitter((25, 25, 25), rng, 5))
                cv.rect(
                    x + ew + cv.t(0.02),
                    top + cv.t(0.02),
                    x + ew + fw - cv.t(0.02),
                    top + fh - cv.t(0.02),
                    random_color(rng, v=(0.5, 0.9)),
                )
                ew += fw + cv.t(0.05)
        elif kind == "vent":
            ew = cv.t(rng.uniform(0.4, 0.7))
            top, bot = row(2.75), row(2.45)
            cv.rect(x, top, x + ew, bot, (200, 200, 200))
            for yy in range(top + cv.t(0.02), bot - cv.t(0.03), cv.t(0.04)):
                cv.rect(x + cv.t(0.02), yy, x + ew - cv.t(0.02), yy + cv.t(0.02), (70, 70, 70))
        elif kind == "storage":
            ew = cv.t(rng.uniform(0.8, 1.6))
            board = row(2.35)
            bx = x
            while bx < x + ew:  # binders and boxes standing on the board
                bw = cv.t(rng.uniform(0.06, 0.3))
                bh = cv.t(rng.uniform(0.15, 0.35))
                col = random_color(rng, v=(0.25, 0.85))
                cv.rect(bx, board - bh, min(x + ew, bx + bw), board, col)
                if bw > cv.t(0.05):
                    cv.rect(
                        bx + cv.t(0.015),
                        board - bh + cv.t(0.03),
                        min(x + ew, bx + bw) - cv.t(0.015),
                        board - bh + cv.t(0.08),
                        contrasting(rng, col, 50),
                    )
                bx += bw + int(rng.integers(0, cv.t(0.03)))
            cv.rect(
                x - cv.t(0.03),
                board,
                x + ew + cv.t(0.03),
                board + cv.t(0.025),
                jitter((90, 90, 90), rng, 20),
            )
        elif kind == "clock":
            ew = cv.t(0.3)
            top = row(2.7)
            cv.rect(x, top, x + ew, top + ew, (40, 40, 40))
            cv.rect(
                x + cv.t(0.02),
                top + cv.t(0.02),
                x + ew - cv.t(0.02),
                top + ew - cv.t(0.02),
                (235, 235, 235),
            )
            c = ew // 2
            for k in range(4):
                dx, dy = [(0, -1), (1, 0), (0, 1), (-1, 0)][k]
                px, py = x + c + dx * cv.t(0.1), top + c + dy * cv.t(0.1)
                cv.rect(
                    px - cv.t(0.008),
                    py - cv.t(0.008),
                    px + cv.t(0.008),
                    py + cv.t(0.008),
                    (30, 30, 30),
                )
            cv.rect(
                x + c - cv.t(0.006),
                top + c - cv.t(0.09),
                x + c + cv.t(0.006),
                top + c,
                (30, 30, 30),
            )
            cv.rect(
                x + c,
                top + c - cv.t(0.006),
                x + c + cv.t(0.07),
                top + c + cv.t(0.006),
                (30, 30, 30),
            )
        else:
            ew = cv.t(rng.uniform(0.2, 0.6))
        x += ew + cv.t(rng.uniform(0.1, 0.4))


def compose_floor(
    width_m: float,
    depth_m: float,
    rng: np.random.Generator,
    texel: float,
    grain: float,
    rug: tuple[float, float, float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Checkerboard-like tiles (repeated pattern) and a patterned rug at ``rug``
    (x0, y0, x1, y1 m)."""
    cv = Canvas(int(round(width_m / texel)), int(round(depth_m / texel)), (128, 128, 128), texel)
    a = jitter((170, 180, 185), rng, 15)
    b = jitter((95, 105, 115), rng, 15)
    tiles(
        cv,
        0,
        0,
        cv.w,
        cv.h,
        rng,
        rng.choice([0.4, 0.5]),
        0.0,
        [a, b],
        (0, 0, 0),
        checker=True,
        var=8,
    )
    # Speckles: small stones in the terrazzo-like tiles.
    for _ in range(int(cv.w * cv.h * texel * texel * 6)):
        x, y = int(rng.integers(cv.w)), int(rng.integers(cv.h))
        s = int(rng.integers(2, 5))
        cv.rect(x, y, x + s, y + s, jitter((60, 60, 60), rng, 30), register=False)
    if rug is not None:
        x0, y0, x1, y1 = (int(round(v / texel)) for v in rug)
        border = random_color(rng, s=(0.5, 0.8), v=(0.25, 0.45))
        cv.rect(x0, y0, x1, y1, border)
        f = cv.t(0.1)
        inner = random_color(rng, s=(0.3, 0.6), v=(0.45, 0.7))
        cv.rect(x0 + f, y0 + f, x1 - f, y1 - f, inner)
        mondrian(cv, x0 + f, y0 + f, x1 - f, y1 - f, rng, 60, min_m=0.05, max_frac=0.25)
        # A band of repeated motifs along the border.
        step = cv.t(0.1)
        for xx in range(x0 + f, x1 - f - step, step):
            cv.rect(xx + step // 4, y0 + f // 4, xx + 3 * step // 4, y0 + 3 * f // 4, inner)
            cv.rect(xx + step // 4, y1 - 3 * f // 4, xx + 3 * step // 4, y1 - f // 4, inner)
    img = cv.finish(rng, grain)
    return img, cv.corners()


def compose_ceiling(
    width_m: float, depth_m: float, rng: np.random.Generator, texel: float, grain: float
) -> tuple[np.ndarray, np.ndarray]:
    """Suspended-ceiling grid (repeated), speckled acoustic tiles, light panels and vents."""
    cv = Canvas(int(round(width_m / texel)), int(round(depth_m / texel)), (200, 200, 200), texel)
    tiles(
        cv,
        0,
        0,
        cv.w,
        cv.h,
        rng,
        0.6,
        0.024,
        [jitter((215, 218, 220), rng, 5)],
        (150, 150, 155),
        var=4,
    )
    for _ in range(int(cv.w * cv.h * texel * texel * 40)):
        x, y = int(rng.integers(cv.w)), int(rng.integers(cv.h))
        cv.rect(x, y, x + 2, y + 2, (175, 178, 180), register=False)
    T = cv.t(0.6)
    g = cv.t(0.024)
    nx, ny = cv.w // T, cv.h // T
    for j in range(1, ny - 1, 2):
        for i in range(1, nx - 1, 3):
            x0, y0 = i * T + g // 2, j * T + g // 2
            if rng.random() < 0.7:  # light panel with louvres
                cv.rect(x0, y0, x0 + T - g, y0 + T - g, (150, 150, 150))
                for k in range(6):
                    yy = y0 + cv.t(0.03) + k * cv.t(0.09)
                    cv.rect(
                        x0 + cv.t(0.03),
                        yy,
                        x0 + T - g - cv.t(0.03),
                        yy + cv.t(0.06),
                        (250, 250, 250),
                    )
            else:  # vent
                for k in range(5):
                    d = cv.t(0.05) * k
                    cv.rect(
                        x0 + d,
                        y0 + d,
                        x0 + T - g - d,
                        y0 + T - g - d,
                        (90, 90, 90) if k % 2 else (200, 200, 205),
                    )
    img = cv.finish(rng, grain)
    return img, cv.corners()


def compose_box_face(
    kind: str,
    role: str,
    width_m: float,
    height_m: float,
    rng: np.random.Generator,
    texel: float,
    grain: float,
    labels: list[Canvas],
) -> tuple[np.ndarray, np.ndarray]:
    """Texture of one face of a piece of furniture.

    ``kind``: shelf | cabinet | crate | table_top | table_leg;
    ``role``: front | side | top | bottom.
    """
    W, H = max(1, int(round(width_m / texel))), max(1, int(round(height_m / texel)))
    if kind == "shelf":
        cv = Canvas(W, H, jitter((45, 75, 115), rng, 15), texel)
        if role == "front":
            bookshelf(cv, 0, 0, W, H, rng)
        else:
            _wood(cv, rng)
            if role == "top":
                m = cv.t(0.02)
                mondrian(cv, m, m, W - m, H - m, rng, 6, min_m=0.05, max_frac=0.4)
            else:
                _stickers(cv, rng, labels, 2)
    elif kind == "cabinet":
        cv = Canvas(W, H, jitter((180, 185, 190), rng, 30), texel)
        if role == "front":
            _cabinet_front(cv, rng)
        elif role == "top":
            mondrian(
                cv,
                cv.t(0.03),
                cv.t(0.03),
                W - cv.t(0.03),
                H - cv.t(0.03),
                rng,
                10,
                min_m=0.05,
                max_frac=0.5,
            )
        else:
            _stickers(cv, rng, labels, 3)
    elif kind == "crate":
        cv = Canvas(W, H, jitter((95, 150, 190), rng, 12), texel)  # cardboard
        if role == "top":
            tape = cv.t(0.05)
            cv.rect(0, H // 2 - tape // 2, W, H // 2 + tape // 2, jitter((120, 170, 200), rng, 8))
        _stickers(cv, rng, labels, 2 if role == "top" else 4)
        text_lines(cv, cv.t(0.03), H - cv.t(0.12), W // 2, H - cv.t(0.02), rng, 0.02, (40, 50, 60))
    elif kind == "table_top":
        cv = Canvas(W, H, jitter((70, 110, 150), rng, 15), texel)
        _wood(cv, rng)
        if role == "top":
            _desk_clutter(cv, rng)
    else:  # table_leg and anything else: painted metal
        cv = Canvas(W, H, jitter((60, 60, 60), rng, 10), texel)
        for y in range(0, H, max(2, cv.t(0.1))):
            cv.rect(0, y, W, y + max(1, cv.t(0.01)), (90, 90, 90), register=False)
    img = cv.finish(rng, grain)
    return img, cv.corners()


def make_labels(rng: np.random.Generator, texel: float, n: int = 3) -> list[Canvas]:
    """Shipping labels shared by boxes (repeated on purpose)."""
    out = []
    for _ in range(n):
        lw, lh = rng.uniform(0.12, 0.2), rng.uniform(0.08, 0.14)
        cv = Canvas(int(round(lw / texel)), int(round(lh / texel)), (238, 238, 238), texel)
        band = random_color(rng, s=(0.6, 0.9), v=(0.4, 0.8))
        cv.rect(0, 0, cv.w, cv.t(0.025), band)
        text_lines(
            cv,
            cv.t(0.01),
            cv.t(0.03),
            cv.w - cv.t(0.01),
            cv.h - cv.t(0.01),
            rng,
            0.01,
            (30, 30, 30),
            1.3,
        )
        bars = cv.t(0.002)
        bx = cv.w - cv.t(0.06)
        for k in range(10):  # a barcode-ish block
            if rng.random() < 0.6:
                x = bx + k * bars * 2
                cv.rect(x, cv.h - cv.t(0.05), x + bars, cv.h - cv.t(0.01), (20, 20, 20))
        out.append(cv)
    return out


def _wood(cv: Canvas, rng: np.random.Generator) -> None:
    """Planks of slightly different shades: long rectangles, corners at the plank ends."""
    base = tuple(cv.img[0, 0].tolist())
    y = 0
    while y < cv.h:
        ph = cv.t(rng.uniform(0.08, 0.16))
        x = -int(rng.integers(0, cv.t(0.6)))
        while x < cv.w:
            pl = cv.t(rng.uniform(0.4, 1.2))
            cv.rect(x, y, x + pl - 1, y + ph - 1, jitter(base, rng, 18))
            x += pl
        y += ph


def _stickers(cv: Canvas, rng: np.random.Generator, labels: list[Canvas], n: int) -> None:
    for _ in range(n):
        if labels and rng.random() < 0.7:
            lab = labels[int(rng.integers(len(labels)))]
            if lab.w < cv.w and lab.h < cv.h:
                cv.paste(
                    lab,
                    int(rng.integers(0, cv.w - lab.w + 1)),
                    int(rng.integers(0, cv.h - lab.h + 1)),
                )
        else:
            sw, sh = cv.t(rng.uniform(0.05, 0.15)), cv.t(rng.uniform(0.05, 0.15))
            if sw < cv.w and sh < cv.h:
                x, y = int(rng.integers(0, cv.w - sw + 1)), int(rng.integers(0, cv.h - sh + 1))
                cv.rect(x, y, x + sw, y + sh, contrasting(rng, tuple(cv.img[0, 0].tolist()), 50))


def _cabinet_front(cv: Canvas, rng: np.random.Generator) -> None:
    W, H = cv.w, cv.h
    gap = max(1, cv.t(0.006))
    panel = tuple(cv.img[0, 0].tolist())
    dark = (60, 60, 60)
    cv.rect(0, 0, W, H, dark)
    n_cols = 1 if W < cv.t(0.7) else 2
    n_drawers = int(rng.integers(0, 4))
    drawer_h = cv.t(0.18)
    top_doors = H - n_drawers * drawer_h
    cw = W // n_cols
    for c in range(n_cols):
        x0, x1 = c * cw + gap, (c + 1) * cw - gap if c < n_cols - 1 else W - gap
        cv.rect(x0, gap, x1, top_doors - gap, jitter(panel, rng, 6))
        hx = x1 - cv.t(0.06) if c == 0 else x0 + cv.t(0.04)
        cv.rect(hx, top_doors // 3, hx + cv.t(0.02), top_doors // 3 + cv.t(0.15), (190, 190, 195))
        if rng.random() < 0.5:
            lx, ly = x0 + cv.t(0.05), gap + cv.t(0.08)
            cv.rect(lx, ly, min(x1 - cv.t(0.05), lx + cv.t(0.2)), ly + cv.t(0.1), (240, 240, 240))
            lx1 = min(x1 - cv.t(0.05), lx + cv.t(0.2))
            text_lines(cv, lx + 2, ly + 2, lx1 - 2, ly + cv.t(0.1) - 2, rng, 0.012, (20, 20, 20))
    for d in range(n_drawers):
        y0 = top_doors + d * drawer_h + gap
        cv.rect(gap, y0, W - gap, y0 + drawer_h - 2 * gap, jitter(panel, rng, 6))
        cv.rect(
            W // 2 - cv.t(0.08),
            y0 + cv.t(0.04),
            W // 2 + cv.t(0.08),
            y0 + cv.t(0.06),
            (190, 190, 195),
        )


def _desk_clutter(cv: Canvas, rng: np.random.Generator) -> None:
    """Papers, a book and a laptop on a desk, in the desk's texture frame."""
    for _ in range(int(rng.integers(4, 8))):
        pw, ph = cv.t(rng.choice([0.21, 0.297, 0.15])), cv.t(rng.choice([0.297, 0.21, 0.2]))
        if pw >= cv.w or ph >= cv.h:
            continue
        x, y = int(rng.integers(0, cv.w - pw)), int(rng.integers(0, cv.h - ph))
        cv.rect(
            x,
            y,
            x + pw,
            y + ph,
            hsv_color(rng.random(), rng.uniform(0, 0.2), rng.uniform(0.85, 0.97)),
        )
        text_lines(
            cv,
            x + cv.t(0.015),
            y + cv.t(0.015),
            x + pw - cv.t(0.015),
            y + ph - cv.t(0.015),
            rng,
            0.01,
            (40, 40, 40),
            1.3,
        )
    lw, lh = cv.t(0.34), cv.t(0.24)
    if lw < cv.w and lh < cv.h:
        x, y = int(rng.integers(0, cv.w - lw)), int(rng.integers(0, cv.h - lh))
        cv.rect(x, y, x + lw, y + lh, (50, 50, 55))
        k = cv.t(0.018)
        for j in range(5):
            for i in range(12):
                kx, ky = x + cv.t(0.025) + i * (k + 2), y + cv.t(0.03) + j * (k + 2)
                cv.rect(kx, ky, kx + k, ky + k, (120, 120, 125))
        cx = x + lw // 2  # touchpad
        cv.rect(
            cx - cv.t(0.05), y + lh - cv.t(0.08), cx + cv.t(0.05), y + lh - cv.t(0.02), (80, 80, 85)
        )
