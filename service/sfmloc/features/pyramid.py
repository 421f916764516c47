"""Gaussian image pyramids for multi-scale map descriptors (paper Section 2, footnote 4:
"two octaves and four sub-octaves")."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Level:
    image: np.ndarray  # uint8 grayscale
    scale_x: float  # level width / original width
    scale_y: float

    @property
    def scale(self) -> float:
        return 0.5 * (self.scale_x + self.scale_y)


def level_scales(octaves: int = 2, per_octave: int = 4, up_levels: int = 0) -> list[float]:
    """Scale factors ``2^(-i / per_octave)`` for ``i = -up_levels .. octaves * per_octave``."""
    return [2.0 ** (-i / per_octave) for i in range(-up_levels, octaves * per_octave + 1)]


def build_pyramid(gray: np.ndarray, scales: list[float]) -> list[Level]:
    """Resized copies of ``gray`` at each scale. Downsampling uses area averaging (an
    anti-aliasing low-pass); upsampling is bilinear. Coordinates map as ``x_level = x * s``
    in COLMAP's corner-origin convention, which is exactly how ``cv2.resize`` maps the image
    extent, so projections scale without offsets."""
    h, w = gray.shape
    levels = []
    for s in scales:
        lw, lh = max(1, round(w * s)), max(1, round(h * s))
        if lw == w and lh == h:
            img = gray
        else:
            interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
            img = cv2.resize(gray, (lw, lh), interpolation=interp)
        levels.append(Level(img, lw / w, lh / h))
    return levels
