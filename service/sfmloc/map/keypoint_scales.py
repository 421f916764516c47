"""The keypoint scales of a map: at how many pixels per radian its descriptors were computed.

A descriptor from pyramid level ``l`` of an image with focal length ``f`` (pixels) describes
its patch at ``f * scale(l)`` pixels per radian. The engine compares a camera with the map's
"native" focal length (the mapping images' own resolution, the pyramid's anchor) to choose
the resolution at which it describes a frame (``engine.frame.working_scale``): a 6-megapixel
query against a map of VGA images is described at about VGA resolution, where the map's
descriptors are.

The builder records ``keypoint_scales(...)`` in the bundle's manifest; bundles written before
it are given the same statistics at load time from their cameras, ``desc_level`` and the
builder parameters in the manifest (``from_bundle_arrays``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..cameras import Camera
from ..features.pyramid import level_scales

PERCENTILES = (5, 25, 50, 75, 95)


def camera_focal_px(camera: Camera) -> float:
    """One focal length per camera: the geometric mean of fx and fy."""
    fx, fy = camera.focal
    return float(np.sqrt(fx * fy))


def pyramid_level_scales(descriptor_params: dict[str, Any] | None) -> list[float]:
    """Scale of each ``desc_level`` index for the builder's ``DescriptorConf`` (as a dict)."""
    p = descriptor_params or {}
    return level_scales(
        int(p.get("octaves", 2)), int(p.get("per_octave", 4)), int(p.get("up_levels", 0))
    )


def keypoint_scales(
    desc_image: np.ndarray,
    desc_level: np.ndarray,
    image_camera: np.ndarray,
    cameras: Sequence[Camera],
    scales: Sequence[float] | None,
) -> dict[str, Any]:
    """Statistics of the focal length (pixels) at which the map's descriptors were computed:
    ``native_focal_px`` (median over descriptors of their image's full-resolution focal) and
    percentiles of ``descriptor_focal_px`` (focal times the level's scale). Without
    ``scales`` (unknown pyramid) the descriptor percentiles are left out."""
    cam_f = np.array([camera_focal_px(c) for c in cameras], np.float64)
    out: dict[str, Any] = {"source": "descriptors"}
    if len(desc_image) == 0 or len(cam_f) == 0:
        img_f = cam_f[np.asarray(image_camera, np.int64)] if len(cam_f) else np.zeros(0)
        out["native_focal_px"] = float(np.median(img_f)) if len(img_f) else 0.0
        out["source"] = "cameras"
        return out
    f = cam_f[np.asarray(image_camera, np.int64)[np.asarray(desc_image, np.int64)]]
    out["native_focal_px"] = float(np.median(f))
    if scales is not None:
        s = np.asarray(scales, np.float64)
        lv = np.asarray(desc_level, np.int64)
        if len(lv) and lv.max() < len(s):
            fd = f * s[lv]
            pct = np.percentile(fd, PERCENTILES)
            out["descriptor_focal_px"] = {f"p{q:02d}": float(v) for q, v in zip(PERCENTILES, pct)}
            out["level_scales"] = [float(x) for x in s]
    return out


def coarsest_focal_px(scales: dict[str, Any]) -> float:
    """The focal length (px) of the map's coarsest pyramid level; for maps whose pyramid is not
    recorded, that of the default (and the paper's) pyramid, two octaves below the images."""
    native = float(scales.get("native_focal_px") or 0.0)
    levels = scales.get("level_scales")
    if isinstance(levels, list) and levels:
        try:
            return native * min(float(x) for x in levels)
        except (TypeError, ValueError):
            pass
    return native * 0.25
