"""The map report: how much of each image the map covers, and whether that is enough.

A map can be built without error and still be too thin to localize against (a handful of
views, short tracks). ``map_report`` summarizes what the engine will have to work with:

- points per image (the map points each database image sees): min / median / max;
- track lengths (database images per point): min / median / mean / max and a histogram;
- coverage: each image split into a ``COVERAGE_GRID`` of cells, the fraction of cells holding
  at least one of its map points (projected with its pose and camera): min / median / max;
- ``sparse``: True, with a warning, when the median image sees fewer than
  ``SPARSE_POINTS_PER_IMAGE`` points (the threshold and the data behind it are below).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..cameras import Camera
from ..transforms import Rigid3d

COVERAGE_GRID = (8, 6)  # cells across, down (~80 px cells at 640x480)
TRACK_HISTOGRAM_MAX = 10  # the last histogram bin holds tracks of this length or longer

# Too sparse to localize against when the median database image sees fewer map points than
# this. Measured with ``python -m sfmloc.bench.sparse_maps --before-after`` on redkitchen maps
# triangulated at known poses (40 non-map frames relocalized one by one, the SIFT peer 95-100%
# on every map): median points per image -> our localized fraction (tracks >= 3: before this
# issue's changes; >= 2: with relocalization verification)
#   every 120th frame, tracks >= 3:  107 -> 50%      tracks >= 2:  274 -> 60%
#   every 60th frame,  tracks >= 3:  158 -> 65%      tracks >= 2:  320 -> 88%
#   every 30th frame,  tracks >= 3:  312 -> 82%      tracks >= 2:  540 -> 95%
#   every 10th frame,  tracks >= 3:  574 -> 98%
# (the 30 Hz replay of frames 0-299: 55%, 60%, 63%, 85%, 99%, 99%, 100%). Synthetic maps from
# the exact model localize better at the same count (every point sits on a texture corner:
# 104 points per image, 88%), so the number is a warning for real SfM maps, not a limit.
SPARSE_POINTS_PER_IMAGE = 300


def _stats(x: np.ndarray) -> dict[str, float]:
    if len(x) == 0:
        return {"min": 0, "median": 0, "max": 0}
    return {"min": float(np.min(x)), "median": float(np.median(x)), "max": float(np.max(x))}


def coverage(
    camera: Camera,
    cam_from_world: Rigid3d,
    points_xyz: np.ndarray,
    grid: tuple[int, int] = COVERAGE_GRID,
) -> float:
    """Fraction of the image's ``grid`` cells holding at least one of ``points_xyz``."""
    if len(points_xyz) == 0:
        return 0.0
    uv, z = camera.project(cam_from_world, points_xyz)
    ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
    uv = uv[ok]
    gx, gy = grid
    cx = np.floor(uv[:, 0] / camera.width * gx).astype(np.int64)
    cy = np.floor(uv[:, 1] / camera.height * gy).astype(np.int64)
    inside = (cx >= 0) & (cx < gx) & (cy >= 0) & (cy < gy)
    return len(np.unique(cy[inside] * gx + cx[inside])) / float(gx * gy)


def map_report(
    points_xyz: np.ndarray,
    image_points_ptr: np.ndarray,
    image_points_idx: np.ndarray,
    cameras: Sequence[Camera],
    image_camera: np.ndarray,
    image_cam_from_world: Sequence[Rigid3d],
) -> dict[str, Any]:
    """The report of a map given as a bundle's arrays (see the module docstring)."""
    n_img, n_pts = len(image_points_ptr) - 1, len(points_xyz)
    ppi = np.diff(np.asarray(image_points_ptr)).astype(np.int64)
    tracks = np.bincount(np.asarray(image_points_idx, np.int64), minlength=n_pts)
    hist: dict[str, int] = {}
    for k in range(1, TRACK_HISTOGRAM_MAX):
        if np.any(tracks == k):
            hist[str(k)] = int(np.sum(tracks == k))
    hist[f"{TRACK_HISTOGRAM_MAX}+"] = int(np.sum(tracks >= TRACK_HISTOGRAM_MAX))
    cov = np.array(
        [
            coverage(
                cameras[int(image_camera[i])],
                image_cam_from_world[i],
                points_xyz[image_points_idx[image_points_ptr[i] : image_points_ptr[i + 1]]],
            )
            for i in range(n_img)
        ]
    )
    track_stats = _stats(tracks)
    track_stats["mean"] = round(float(tracks.mean()), 2) if n_pts else 0.0
    report: dict[str, Any] = {
        "images": int(n_img),
        "points": int(n_pts),
        "points_per_image": _stats(ppi),
        "track_length": {**track_stats, "histogram": hist},
        "coverage": {
            **{k: round(v, 3) for k, v in _stats(cov).items()},
            "grid": list(COVERAGE_GRID),
        },
        "sparse_threshold_points_per_image": SPARSE_POINTS_PER_IMAGE,
    }
    report["warnings"] = sparse_warnings(report)
    report["sparse"] = bool(report["warnings"])
    return report


def sparse_warnings(report: dict[str, Any]) -> list[str]:
    """The warnings a report calls for (empty when the map is dense enough)."""
    med = report["points_per_image"]["median"]
    if med >= SPARSE_POINTS_PER_IMAGE:
        return []
    return [
        f"map too sparse to localize against reliably: the median image sees {med:.0f} map points "
        f"(fewer than {SPARSE_POINTS_PER_IMAGE}); add mapping images (a smaller --stride, more "
        f"views of each place), or with known poses keep two-view points (--min-track-length 2)"
    ]


def report_lines(report: dict[str, Any]) -> list[str]:
    """Human-readable lines for ``sfmloc build`` and ``sfmloc map inspect``."""
    p, t, c = report["points_per_image"], report["track_length"], report["coverage"]
    hist = " ".join(f"{k}:{v}" for k, v in t["histogram"].items())
    return [
        f"points/image min {p['min']:.0f}  median {p['median']:.0f}  max {p['max']:.0f}",
        f"track length min {t['min']:.0f}  median {t['median']:.0f}  mean {t['mean']:.2f}  "
        f"max {t['max']:.0f}  (images per point: {hist})",
        f"coverage     min {c['min']:.0%}  median {c['median']:.0%}  max {c['max']:.0%}"
        f"  (of {c['grid'][0]}x{c['grid'][1]} cells per image with a map point)",
    ] + [f"WARNING: {w}" for w in report["warnings"]]
