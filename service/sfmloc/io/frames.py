"""Recorded frame sequences: an image folder (jpg/png, in name order, other files ignored) or
a video file. Each frame comes with its name (file name, or ``frame-NNNNNN`` for videos) and a
timestamp in seconds (a numeric file stem, as in TUM RGB-D folders, else index / fps)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import ImageDecodeError, InputError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg")


@dataclass
class Frame:
    index: int
    name: str
    stamp: float
    image: np.ndarray  # uint8, gray or BGR as decoded


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _numeric_stem(name: str) -> float | None:
    stem = Path(name).stem
    try:
        return float(stem)
    except ValueError:
        return None


class FrameSource:
    """Iterate the frames of a folder or video; ``len()`` is known for folders and, as far as
    the container says, for videos."""

    def __init__(self, path: str | Path, fps: float = 30.0, gray: bool = True) -> None:
        self.path = Path(path)
        self.fps = float(fps)
        self.gray = gray
        if self.path.is_dir():
            files = [p for p in self.path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
            if not files:
                raise InputError(f"no .jpg/.png images in {self.path}")
            self.files = sorted(files, key=lambda p: _natural_key(p.name))
            stamps = [_numeric_stem(p.name) for p in self.files]
            self._stamps = stamps if all(s is not None for s in stamps) else None
            self.kind = "folder"
        elif self.path.is_file() and self.path.suffix.lower() in VIDEO_SUFFIXES:
            self.files = []
            self._stamps = None
            self.kind = "video"
            cap = cv2.VideoCapture(str(self.path))
            if not cap.isOpened():
                raise InputError(f"cannot open video {self.path}")
            self._video_len = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            cap.release()
        elif self.path.exists():
            raise InputError(f"{self.path} is neither an image folder nor a video ({', '.join(VIDEO_SUFFIXES)})")
        else:
            raise InputError(f"frames source {self.path} does not exist")

    def __len__(self) -> int:
        return len(self.files) if self.kind == "folder" else self._video_len

    def names(self) -> list[str]:
        if self.kind == "folder":
            return [p.name for p in self.files]
        return [f"frame-{i:06d}" for i in range(len(self))]

    def stamp(self, index: int) -> float:
        if self._stamps is not None:
            return float(self._stamps[index])
        return index / self.fps

    def __iter__(self) -> Iterator[Frame]:
        # Stored pixels, no EXIF rotation (as COLMAP and the builder read images).
        flag = (cv2.IMREAD_GRAYSCALE if self.gray else cv2.IMREAD_COLOR) | cv2.IMREAD_IGNORE_ORIENTATION
        if self.kind == "folder":
            for i, p in enumerate(self.files):
                data = np.fromfile(str(p), dtype=np.uint8)
                img = cv2.imdecode(data, flag) if data.size else None
                if img is None:
                    raise ImageDecodeError(f"cannot decode frame {p}")
                yield Frame(i, p.name, self.stamp(i), img)
            return
        cap = cv2.VideoCapture(str(self.path))
        try:
            i = 0
            while True:
                ok, img = cap.read()
                if not ok:
                    break
                if self.gray:
                    img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
                yield Frame(i, f"frame-{i:06d}", i / self.fps, img)
                i += 1
        finally:
            cap.release()
