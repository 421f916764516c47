"""The image folder: listing, selecting and checking images (readable, one size, the
camera's size), the way COLMAP names them."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from ...errors import ImageDecodeError, InputError
from .conf import SfmConf, num_threads
from .run import Reporter

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")


def list_images(image_dir: str | Path) -> list[str]:
    """Image files under ``image_dir`` (recursive, hidden entries skipped) as sorted relative
    POSIX names, the way COLMAP names images."""
    root = Path(image_dir)
    if not root.is_dir():
        raise InputError(f"[input] image folder {root} does not exist or is not a folder")
    names = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for fn in filenames:
            if not fn.startswith(".") and fn.lower().endswith(IMAGE_EXTENSIONS):
                names.append((Path(dirpath) / fn).relative_to(root).as_posix())
    return sorted(names)


def select_images(
    names: list[str], image_names: Sequence[str] | None, stride: int, image_dir: Path
) -> list[str]:
    """Restrict to ``image_names`` (relative names) when given, then keep every ``stride``-th."""
    if stride < 1:
        raise InputError(f"[input] stride must be >= 1, got {stride}")
    if image_names is not None:
        have = set(names)
        wanted = [str(n).replace("\\", "/") for n in image_names]
        missing = [n for n in wanted if n not in have]
        if missing:
            raise InputError(
                f"[input] {len(missing)} of the {len(wanted)} requested images are not in "
                f"{image_dir}: " + ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
            )
        names = wanted
    return names[::stride]


def check_names(names: Sequence[str], image_dir: Path) -> None:
    """COLMAP's pair lists are whitespace-separated: such names cannot be matched."""
    spaced = [n for n in names if any(c.isspace() for c in n)]
    if spaced:
        raise InputError(
            f"[input] {len(spaced)} image name(s) in {image_dir} contain whitespace, which "
            "COLMAP's pair "
            f"lists cannot hold, e.g. {spaced[0]!r}; rename them"
        )


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file as stored (no EXIF rotation, as COLMAP), decoding it;
    ``ImageDecodeError`` naming the file."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise ImageDecodeError(f"[input] cannot read image {path}: {exc.strerror or exc}") from None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise ImageDecodeError(f"[input] cannot decode image {path} (not an image, or corrupt)")
    return int(img.shape[1]), int(img.shape[0])


def check_images(
    image_dir: Path,
    names: Sequence[str],
    expected_size: Callable[[str], tuple[int, int] | None],
    conf: SfmConf,
    rep: Reporter,
    what: str = "the camera",
) -> dict[str, tuple[int, int]]:
    """Decode every image (threaded); raise ``ImageDecodeError`` naming the first unreadable
    one or the first whose size differs from ``expected_size(name)`` (None: no constraint)."""
    sizes: dict[str, tuple[int, int]] = {}
    if not conf.check_images:
        return sizes
    rep.report("input", 0.0, f"checking {len(names)} images in {image_dir}")
    with ThreadPoolExecutor(max_workers=num_threads(conf)) as pool:
        futures = [(n, pool.submit(image_size, image_dir / n)) for n in names]
        try:
            for i, (name, fut) in enumerate(futures):
                sizes[name] = fut.result()
                want = expected_size(name)
                if want is not None and sizes[name] != tuple(want):
                    w, h = sizes[name]
                    raise ImageDecodeError(
                        f"[input] image {image_dir / name} is {w}x{h} but {what} is "
                        f"{want[0]}x{want[1]}"
                    )
                if (i + 1) % 50 == 0:
                    rep.check("input")
                    rep.report(
                        "input", (i + 1) / len(names), f"checked {i + 1}/{len(names)} images"
                    )
        except BaseException:
            for _, f in futures:  # fail now, not after decoding the rest
                f.cancel()
            raise
    rep.report("input", 1.0, f"{len(names)} images readable")
    return sizes
