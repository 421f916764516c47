"""Image bytes <-> numpy arrays for the wire encodings. OpenCV is imported only for JPEG/PNG."""

from __future__ import annotations

from typing import Any

import numpy as np

from .errors import ImageDecodeError, WireError
from .wire import ENCODINGS, raw_size


def _cv2() -> Any:
    import cv2  # lazily: raw encodings need no OpenCV

    return cv2


def encode_image(image: np.ndarray, encoding: str = "jpeg", jpeg_quality: int = 90) -> bytes:
    """Bytes of ``image`` (uint8 HxW gray or HxWx3 BGR) in ``encoding``."""
    if encoding not in ENCODINGS:
        raise WireError(f"encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ImageDecodeError(f"image must be uint8, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ImageDecodeError(f"image must be HxW or HxWx3, got shape {img.shape}")
    if encoding == "gray8":
        if img.ndim == 3:
            img = _cv2().cvtColor(img, _cv2().COLOR_BGR2GRAY)
        return np.ascontiguousarray(img).tobytes()
    if encoding == "bgr8":
        if img.ndim == 2:
            img = _cv2().cvtColor(img, _cv2().COLOR_GRAY2BGR)
        return np.ascontiguousarray(img).tobytes()
    cv2 = _cv2()
    params = (
        [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
        if encoding == "jpeg"
        else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    )
    ok, buf = cv2.imencode(".jpg" if encoding == "jpeg" else ".png", img, params)
    if not ok:
        raise ImageDecodeError(f"OpenCV could not encode the image as {encoding}")
    return buf.tobytes()


def decode_image(
    encoding: str,
    data: bytes | bytearray | memoryview,
    width: int,
    height: int,
    *,
    gray: bool = True,
) -> np.ndarray:
    """The image in ``data``, checked against ``width`` x ``height``: uint8 HxW when ``gray``
    (what the engine uses; JPEG decodes straight to luma), else as sent."""
    n = raw_size(encoding, width, height)
    if encoding in ("gray8", "bgr8"):
        if len(data) != n:
            raise ImageDecodeError(
                f"{encoding} data of {len(data)} bytes does not match {width}x{height} ({n} bytes "
                "expected)"
            )
        arr = np.frombuffer(data, np.uint8)
        if encoding == "gray8":
            return arr.reshape(height, width)
        bgr = arr.reshape(height, width, 3)
        return _cv2().cvtColor(bgr, _cv2().COLOR_BGR2GRAY) if gray else bgr
    if encoding not in ENCODINGS:
        raise WireError(f"encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    cv2 = _cv2()
    buf = np.frombuffer(data, np.uint8)
    try:
        # Stored pixels, no EXIF rotation: the camera describes the stored image (as COLMAP and
        # the map builder read images).
        flag = (
            cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION if gray else cv2.IMREAD_UNCHANGED
        )
        img = cv2.imdecode(buf, flag) if buf.size else None
    except cv2.error as exc:  # e.g. larger than OPENCV_IO_MAX_IMAGE_PIXELS allows
        reason = (
            "larger than the decoder allows"
            if "MAX_IMAGE_PIXELS" in str(exc)
            else str(exc).strip().splitlines()[-1]
        )
        raise ImageDecodeError(
            f"the {encoding} data ({len(data)} bytes) cannot be decoded: {reason}"
        ) from None
    if img is None:
        raise ImageDecodeError(
            f"the {encoding} data ({len(data)} bytes) cannot be decoded (corrupt or not {encoding})"
        )
    if img.shape[:2] != (height, width):
        raise ImageDecodeError(
            f"the {encoding} image is {img.shape[1]}x{img.shape[0]}, the camera is {width}x{height}"
        )
    return img
