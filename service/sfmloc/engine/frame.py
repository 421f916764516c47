"""Validation of incoming frames: what reaches the engine is a uint8 grayscale image of the
camera's size, or an ``ImageDecodeError`` that names the problem."""

from __future__ import annotations

import cv2
import numpy as np

from ..cameras import Camera
from ..errors import ImageDecodeError


def to_gray(frame: np.ndarray, camera: Camera) -> np.ndarray:
    """A grayscale uint8 view/copy of ``frame`` (gray HxW, gray HxWx1, BGR HxWx3 or BGRA HxWx4)."""
    if not isinstance(frame, np.ndarray):
        raise ImageDecodeError(f"frame must be a numpy array, got {type(frame).__name__}")
    if frame.size == 0:
        raise ImageDecodeError("frame is empty")
    if frame.dtype != np.uint8:
        raise ImageDecodeError(f"frame must be uint8, got {frame.dtype}")
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    if frame.ndim == 2:
        gray = frame
    elif frame.ndim == 3 and frame.shape[2] == 3:
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    elif frame.ndim == 3 and frame.shape[2] == 4:
        gray = cv2.cvtColor(frame, cv2.COLOR_BGRA2GRAY)
    else:
        raise ImageDecodeError(f"frame must be HxW or HxWx(1|3|4), got shape {frame.shape}")
    if gray.shape != (camera.height, camera.width):
        raise ImageDecodeError(
            f"frame is {gray.shape[1]}x{gray.shape[0]}, the camera is "
            f"{camera.width}x{camera.height}"
        )
    return np.ascontiguousarray(gray)


# A working scale within half a pyramid sub-octave (2^(1/8)) of 1 is not applied: the map
# already holds descriptors within half a step of it, and resampling would only blur.
_SCALE_DEAD_BAND = 2.0 ** (-1.0 / 8.0)


def working_scale(
    camera: Camera,
    native_focal_px: float,
    mode: str = "map",
    max_pixels: int = 0,
    coarsest_focal_px: float = 0.0,
) -> float:
    """The factor (<= 1) by which a frame of ``camera`` is resized before keypoints are
    extracted. Three rules, in this order of precedence:

    - never finer than the map: at most the mapping images' own pixels per radian
      (``native_focal_px``), so keypoints are described at a scale the map holds. A 3072x2048
      frame with f = 2520 against a map of 640x480 images (f = 525) runs at 640x427;
    - within the engine's pixel budget (``max_pixels``; its parameters are VGA pixels), ...
    - ... but never coarser than the map's coarsest descriptors (``coarsest_focal_px``).

    Never above 1 (no upsampling). ``mode="full"``: always the full resolution (the paper)."""
    if mode == "full" or not np.isfinite(native_focal_px) or native_focal_px <= 0:
        return 1.0
    fx, fy = camera.focal
    f = float(np.sqrt(fx * fy))
    s = native_focal_px / f
    if max_pixels > 0:
        budget = float(np.sqrt(max_pixels / (camera.width * camera.height)))
        s = min(s, max(budget, coarsest_focal_px / f))
    if s >= _SCALE_DEAD_BAND:
        return 1.0
    # The width lands on an integer, so the working image spans exactly ``s`` times the original.
    return max(1, round(camera.width * s)) / camera.width


def to_working(gray: np.ndarray, scale: float) -> np.ndarray:
    """``gray`` resized by ``scale`` with area averaging (anti-aliased). ``cv2.resize`` with a
    factor maps the image extent exactly (x_working = scale * x in COLMAP's corner-origin
    pixels), which is what ``Camera.scaled(scale)`` assumes for the intrinsics."""
    if scale == 1.0:
        return gray
    return cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
