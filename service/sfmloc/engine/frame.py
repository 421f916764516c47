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
