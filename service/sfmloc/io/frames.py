"""Recorded frame sequences: an image folder (jpg/png, in name order, other files ignored) or
a video file. Each frame comes with its name (file name, or ``frame-NNNNNN`` for videos) and a
timestamp in seconds from one stated clock (``timestamps``, see ``frame_clock``):

- ``None`` (default): frame index / fps, whatever the file names;
- ``"stem-s"``, ``"stem-ms"``, ``"stem-us"``, ``"stem-ns"``: the numeric file-name stem, in
  that unit (TUM RGB-D folders: seconds; ROS exports: nanoseconds);
- a file path: a TUM-style list, ``timestamp filename`` per line (TUM ``rgb.txt``, matched by
  file name) or ``timestamp ...`` with one line per frame, in frame order.

File names are never taken as timestamps unless asked: frames named 000000, 000002, ... read as
seconds are 2 s apart, and the engine resets its motion filter on every such gap.
"""

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


def read_image(path: str | Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    """``cv2.imread(path, flags)``, raising ImageDecodeError where it returns None (a missing
    or undecodable file) instead of handing None on."""
    img = cv2.imread(str(path), flags)
    if img is None:
        raise ImageDecodeError(f"cannot read image {path}")
    return img


def decode_image(data: bytes | np.ndarray, flags: int, what: str) -> np.ndarray:
    """``cv2.imdecode`` of encoded bytes, raising ImageDecodeError (naming ``what``) where it
    returns None."""
    buf = np.frombuffer(data, np.uint8) if isinstance(data, bytes) else data
    img = cv2.imdecode(buf, flags) if buf.size else None
    if img is None:
        raise ImageDecodeError(f"cannot decode {what}")
    return img


@dataclass
class Frame:
    index: int
    name: str
    stamp: float
    image: np.ndarray  # uint8, gray or BGR as decoded


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


STEM_UNITS = {"s": 1, "ms": 1_000, "us": 1_000_000, "ns": 1_000_000_000}  # per second
CLOCK_CHOICES = tuple(f"stem-{u}" for u in STEM_UNITS)


def _numeric_stem(name: str, per_second: int) -> float | None:
    stem = Path(name).stem
    if re.fullmatch(r"\d+", stem):
        return int(stem) / per_second  # exact integer division: ns stamps keep their precision
    try:
        return float(stem) / per_second
    except ValueError:
        return None


def _stamps_from_stems(names: list[str], unit: str) -> list[float]:
    out = []
    for n in names:
        s = _numeric_stem(n, STEM_UNITS[unit])
        if s is None:
            raise InputError(f"--timestamps stem-{unit}: file name {n!r} has no numeric stem")
        out.append(s)
    return out


def _stamps_from_file(path: Path, names: list[str] | None, count: int) -> list[float]:
    """A TUM-style timestamp list: ``timestamp filename`` (matched by name, else by stem) or
    one ``timestamp ...`` line per frame in order."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read timestamps file {path}: {exc}") from None
    rows: list[tuple[float, str | None]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            t = float(parts[0])
        except ValueError:
            raise InputError(
                f"{path}:{lineno}: a timestamp (seconds) must start the line, got {parts[0]!r}"
            ) from None
        second = parts[1] if len(parts) > 1 else None
        is_name = second is not None and _is_number(second) is False
        rows.append((t, second if is_name else None))
    if not rows:
        raise InputError(f"timestamps file {path} has no timestamps")
    if names is not None and all(n is not None for _, n in rows):
        by_name = {Path(n).name: t for t, n in rows if n is not None}  # (all are: mypy)
        by_stem = {Path(n).stem: t for t, n in rows if n is not None}
        out = []
        for n in names:
            stamp = by_name.get(n, by_stem.get(Path(n).stem))
            if stamp is None:
                raise InputError(f"timestamps file {path} has no line for frame {n!r}")
            out.append(stamp)
        return out
    if len(rows) != count:
        raise InputError(
            f"timestamps file {path} has {len(rows)} timestamps for {count} frames "
            "(give one line per frame in order, or 'timestamp filename' lines)"
        )
    return [t for t, _ in rows]


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _check_increasing(stamps: list[float], names: list[str], clock: str) -> None:
    for i in range(1, len(stamps)):
        if not stamps[i] > stamps[i - 1]:
            raise InputError(
                f"timestamps from {clock} do not increase: {names[i - 1]} {stamps[i - 1]!r} s, "
                f"then {names[i]} {stamps[i]!r} s"
            )


def folder_stamps(names: list[str], timestamps: str | None, fps: float) -> tuple[list[float], str]:
    """Timestamps (s) of an image folder's frames in the given order and the clock's name:
    index / ``fps``, or ``timestamps`` as ``FrameSource`` takes it (stem-UNIT or a file)."""
    if not fps > 0:
        raise InputError(f"--fps must be positive, got {fps}")
    if timestamps is None:
        return [k / fps for k in range(len(names))], f"frame index / {fps:g} fps"
    if timestamps in CLOCK_CHOICES:
        unit = timestamps.split("-", 1)[1]
        stamps, clock = _stamps_from_stems(names, unit), f"file-name stems in {unit}"
    else:
        p = Path(timestamps)
        if not p.is_file():
            raise InputError(
                f"--timestamps {timestamps!r} is neither one of {', '.join(CLOCK_CHOICES)} nor "
                "a file"
            )
        stamps, clock = _stamps_from_file(p, names, len(names)), f"timestamps file {p}"
    _check_increasing(stamps, names, clock)
    return stamps, clock


class FrameSource:
    """Iterate the frames of a folder or video; ``len()`` is known for folders and, as far as
    the container says, for videos."""

    def __init__(
        self, path: str | Path, fps: float = 30.0, gray: bool = True, timestamps: str | None = None
    ) -> None:
        self.path = Path(path)
        if not fps > 0:
            raise InputError(f"--fps must be positive, got {fps}")
        self.fps = float(fps)
        self.gray = gray
        if self.path.is_dir():
            files = [
                p for p in self.path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
            ]
            if not files:
                raise InputError(f"no .jpg/.png images in {self.path}")
            self.files = sorted(files, key=lambda p: _natural_key(p.name))
            self.kind = "folder"
        elif self.path.is_file() and self.path.suffix.lower() in VIDEO_SUFFIXES:
            self.files = []
            self.kind = "video"
            cap = cv2.VideoCapture(str(self.path))
            if not cap.isOpened():
                raise InputError(f"cannot open video {self.path}")
            self._video_len = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            cap.release()
        elif self.path.exists():
            raise InputError(
                f"{self.path} is neither an image folder nor a video ({', '.join(VIDEO_SUFFIXES)})"
            )
        else:
            raise InputError(f"frames source {self.path} does not exist")
        self._stamps: list[float] | None = None
        self.clock = f"frame index / {self.fps:g} fps"
        if timestamps is not None:
            self._set_clock(timestamps)

    def _set_clock(self, timestamps: str) -> None:
        names = self.names()
        if timestamps in CLOCK_CHOICES:
            unit = timestamps.split("-", 1)[1]
            if self.kind != "folder":
                raise InputError(
                    f"--timestamps {timestamps}: a video has no file names to read stamps from"
                )
            self._stamps = _stamps_from_stems(names, unit)
            self.clock = f"file-name stems in {unit}"
        else:
            p = Path(timestamps)
            if not p.is_file():
                raise InputError(
                    f"--timestamps {timestamps!r} is neither one of "
                    f"{', '.join(CLOCK_CHOICES)} nor a file"
                )
            self._stamps = _stamps_from_file(p, names if self.kind == "folder" else None, len(self))
            self.clock = f"timestamps file {p}"
        _check_increasing(self._stamps, names, self.clock)

    @property
    def nominal_fps(self) -> float:
        """Frames per second of the clock (from the median interval when stamps are given)."""
        if self._stamps is None or len(self._stamps) < 2:
            return self.fps
        return 1.0 / float(np.median(np.diff(self._stamps)))

    def gaps_over(self, seconds: float) -> int:
        """How many frame intervals of the clock exceed ``seconds``."""
        if self._stamps is None:
            return len(self) - 1 if 1.0 / self.fps > seconds and len(self) > 1 else 0
        return int(np.sum(np.diff(self._stamps) > seconds))

    def __len__(self) -> int:
        return len(self.files) if self.kind == "folder" else self._video_len

    def names(self) -> list[str]:
        if self.kind == "folder":
            return [p.name for p in self.files]
        return [f"frame-{i:06d}" for i in range(len(self))]

    def stamp(self, index: int) -> float:
        if self._stamps is not None:
            if index >= len(self._stamps):
                raise InputError(
                    f"frame {index} has no timestamp ({self.clock} lists {len(self._stamps)})"
                )
            return float(self._stamps[index])
        return index / self.fps

    def __iter__(self) -> Iterator[Frame]:
        # Stored pixels, no EXIF rotation (as COLMAP and the builder read images).
        flag = (
            cv2.IMREAD_GRAYSCALE if self.gray else cv2.IMREAD_COLOR
        ) | cv2.IMREAD_IGNORE_ORIENTATION
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
                yield Frame(i, f"frame-{i:06d}", self.stamp(i), img)
                i += 1
        finally:
            cap.release()
