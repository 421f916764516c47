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
            f"frame is {gray.shape[1]}x{gray.shape[0]}, the camera is {camera.width}x{camera.height}"
        )
    return np.ascontiguousarray(gray)


# A working scale within half a pyramid sub-octave (2^(1/8)) of 1 is not applied: the map
# already holds descriptors within half a step of it, and resampling would only blur.
_SCALE_DEAD_BAND = 2.0 ** (-1.0 / 8.0)


def working_scale(camera: Camera, native_focal_px: float, mode: str = "map") -> float:
    """The factor (<= 1) by which a frame of ``camera`` is resized before keypoints are
    extracted, so that they describe the scene at about the map's own pixels per radian
    (``MapBundle.native_focal_px``, the mapping images' focal length). A 3072x2048 frame with
    f = 2520 against a map of 640x480 images with f = 525 is processed at 640x427. Frames at
    or below the map's resolution are used as they are (never upsampled). ``mode="full"``:
    always the full resolution (the paper's behaviour)."""
    if mode == "full" or not np.isfinite(native_focal_px) or native_focal_px <= 0:
        return 1.0
    fx, fy = camera.focal
    s = float(native_focal_px) / float(np.sqrt(fx * fy))
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
