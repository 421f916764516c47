"""Frame sources for streaming: numpy arrays, an image folder, a video file or a camera index.

Every source yields ``SourceFrame``s. Image folders can pass already-encoded files through
untouched (``passthrough="jpeg"`` sends ``.jpg`` files as they are: no decode, no re-encode).
OpenCV is imported only for folders that need decoding, videos and cameras.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import ImageDecodeError, InputError

if TYPE_CHECKING:
    from .wire import Transform

IMAGE_SUFFIXES = {
    ".jpg": "jpeg",
    ".jpeg": "jpeg",
    ".png": "png",
    ".bmp": None,
    ".tif": None,
    ".tiff": None,
}


@dataclass
class SourceFrame:
    image: np.ndarray | None = None  # uint8 HxW or HxWx3 (BGR); None when ``data`` is set
    data: bytes | None = None  # already-encoded bytes (passthrough)
    encoding: str | None = None  # encoding of ``data``
    stamp_ns: int | None = None  # the source's own timestamp, when it has one
    name: str = ""
    # An outside estimate of the frame's cam_from_world (GPS/IMU) sent with it (wire.Frame's
    # ``prior``; the gRPC StreamFrame's prior_cam_from_world)
    prior: Transform | None = None


def _cv2() -> Any:
    import cv2

    return cv2


def list_images(folder: str | Path, pattern: str = "*") -> list[Path]:
    folder = Path(folder)
    files = [
        p
        for p in sorted(folder.iterdir())
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and fnmatch.fnmatch(p.name, pattern)
    ]
    if not files:
        raise InputError(f"no images matching {pattern!r} in {folder}")
    return files


def folder_frames(
    folder: str | Path, *, pattern: str = "*", passthrough: str | None = None, gray: bool = False
) -> Iterator[SourceFrame]:
    """Images of a folder in name order. With ``passthrough`` ("jpeg" or "png"), files already
    in that encoding are sent as they are."""
    for p in list_images(folder, pattern):
        if passthrough and IMAGE_SUFFIXES[p.suffix.lower()] == passthrough:
            yield SourceFrame(data=p.read_bytes(), encoding=passthrough, name=p.name)
            continue
        cv2 = _cv2()
        # Stored pixels, no EXIF rotation (as the server decodes what the client sends).
        img = cv2.imread(
            str(p),
            (cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR) | cv2.IMREAD_IGNORE_ORIENTATION,
        )
        if img is None:
            raise ImageDecodeError(f"cannot read image {p}")
        yield SourceFrame(image=img, name=p.name)


def video_frames(source: str | int, *, gray: bool = False) -> Iterator[SourceFrame]:
    """Frames of a video file or a camera (an integer index), until the source ends."""
    cv2 = _cv2()
    cap = cv2.VideoCapture(source)
    if not cap.isOpened():
        if isinstance(source, int):  # say it was taken for a camera, and where Linux has it
            raise InputError(
                f"cannot open camera {source} (a number is a camera index: /dev/video{source} "
                "on Linux; no such device, or another program holds it)"
            )
        raise InputError(f"cannot open video {source!r}")
    is_file = isinstance(source, str)
    fps = (cap.get(cv2.CAP_PROP_FPS) or 30.0) if is_file else 0.0
    try:
        k = 0
        last = -1
        while True:
            ok, img = cap.read()
            if not ok:
                break
            if gray and img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            stamp = None  # a live camera: stamped when sent
            if is_file:
                # The file's own clock when it has one that moves forward, else index / fps;
                # never a mix of both (time going back resets the server's motion filter).
                pos = int(cap.get(cv2.CAP_PROP_POS_MSEC) * 1e6)
                stamp = pos if pos > last else int(k * 1e9 / fps)
                stamp = max(stamp, last + 1)
                last = stamp
            yield SourceFrame(image=img, stamp_ns=stamp, name=f"{k:06d}")
            k += 1
    finally:
        cap.release()


def array_frames(frames: Iterable[np.ndarray]) -> Iterator[SourceFrame]:
    for k, img in enumerate(frames):
        yield SourceFrame(image=np.asarray(img), name=f"{k:06d}")


def camera_index(source: Any) -> int | None:
    """The camera index ``source`` names, else None: an int, or a ``str`` of ASCII digits
    (``"0"``), whatever the working directory holds. A folder or file named by digits is read
    when written as a path (``"./0"``, ``Path("0")``): the choice never depends on what exists
    (a folder ``0`` beside ``--source 0`` once gave the folder's timestamps to camera 0's
    frames)."""
    if isinstance(source, int):
        return source
    if isinstance(source, str) and source.isascii() and source.isdigit():
        return int(source)
    return None


def open_source(
    source: Any, *, pattern: str = "*", passthrough: str | None = None, gray: bool = False
) -> Iterator[SourceFrame]:
    """Frames of ``source``: a numpy array stack (N, H, W[, 3]) or an iterable of arrays, an
    image folder, a video file, or a camera index (an int or a string of digits: always a
    camera, see ``camera_index``; write ``./0`` for a folder named ``0``)."""
    if isinstance(source, np.ndarray):
        if source.ndim not in (3, 4):
            raise InputError(
                f"a numpy source must be a stack (N, H, W[, 3]), got shape {source.shape}"
            )
        return array_frames(source)
    index = camera_index(source)
    if index is not None:
        return video_frames(index, gray=gray)
    if isinstance(source, (str, Path)):
        p = Path(source)
        if p.is_dir():
            return folder_frames(p, pattern=pattern, passthrough=passthrough, gray=gray)
        if p.is_file():
            return video_frames(str(p), gray=gray)
        raise InputError(f"source {source} is neither a folder, a video file nor a camera index")
    if isinstance(source, Iterable):
        return array_frames(source)
    raise InputError(f"unsupported frame source {type(source).__name__}")
