"""SfM configuration: ``SfmConf``, its named presets (``sfm_conf``) and pycolmap's
incremental/triangulation options derived from it."""

from __future__ import annotations

import logging
import os
from typing import Any, Literal

import pycolmap
from pydantic import Field

from ...config import StrictModel, merge_presets
from ...errors import ConfigError

log = logging.getLogger(__name__)


class SfmConf(StrictModel):
    """Parameters of the SfM front-end (known-poses triangulation and images-only SfM).

    Defaults were chosen on 100 redkitchen frames (every 10th of seq-01, 640x480) on a
    2-core machine (table above ``SFM_PRESETS``; module docstrings of ``sfm.poses`` and
    ``sfm.images``) and checked against exact geometry on synthetic scenes (the tests).
    """

    # SIFT (CPU): OpenCV's (~3x less CPU per image) or pycolmap's own, both into COLMAP's database
    sift_backend: Literal["opencv", "pycolmap"] = "opencv"
    max_features: int = Field(4000, ge=64, description="max SIFT features per image")
    first_octave: int = Field(
        -1,
        ge=-1,
        le=2,
        description="pycolmap: -1 upsamples 2x first: ~3x the features on VGA, ~3x slower",
    )
    peak_threshold: float = Field(
        0.02 / 3, gt=0, description="pycolmap SIFT DoG peak threshold (COLMAP default)"
    )
    contrast_threshold: float = Field(
        0.015, gt=0, description="OpenCV SIFT contrastThreshold (OpenCV default 0.04)"
    )
    max_image_size: int = Field(
        1600, ge=64, description="images larger than this are downscaled for SIFT"
    )
    # matching
    max_ratio: float = Field(0.8, gt=0, le=1, description="Lowe ratio test")
    min_num_inliers: int = Field(15, ge=5, description="min verified matches per image pair")
    # pairs for known poses. "geometric" (sfm.pairs): per image its pair_near nearest cameras
    # plus one partner per target triangulation angle among cameras whose frustum overlaps
    # its view, a budget that does not grow with the frame rate. "nearest": the old rule, the
    # pair_neighbors nearest cameras plus pair_sequential next images; in 30 Hz video these
    # are centimetres apart and the 1.5 deg angle filter drops what they see. Measured on the
    # first 300 redkitchen frames (triangulated points, every 4th / 2nd / every frame):
    # nearest 8874 / 9956 / 4539 (its every-frame pairs: all under 1.5 deg, median 0.31 deg at
    # the 2 m scene depth); geometric 7710 / 11407 / 19990 (pair angles median 5.6 deg).
    # All 1000 frames, every 10th/4th/2nd/1st: 9434/19176/29176/49819 map points, replay
    # 99.0/99.1/99.2/99.6% (nearest: every frame 16336 points, 81.5-91%);
    # docs/beyond-the-paper.md#pair-selection.
    pair_selection: Literal["geometric", "nearest"] = "geometric"
    pair_near: int = Field(2, ge=0, description="known poses, geometric: nearest views per image")
    pair_angles_deg: tuple[float, ...] = Field(
        (2.5, 5.0, 10.0, 20.0), description="known poses, geometric: target triangulation angles"
    )
    pair_min_overlap: float = Field(
        0.5, gt=0, le=1, description="known poses, geometric: min frustum overlap at scene depth"
    )
    pair_neighbors: int = Field(5, ge=0, description="known poses: nearest views matched per image")
    pair_sequential: int = Field(
        2, ge=0, description="known poses: also match this many next images in order"
    )
    pair_max_angle_deg: float = Field(
        45.0, gt=0, le=180, description="known poses: max viewing-direction angle"
    )
    # pairs for images only
    matching: Literal["sequential", "exhaustive"] = "sequential"
    sequential_overlap: int = Field(
        5, ge=1, description="images only: match each image with the next N"
    )
    quadratic_overlap: bool = Field(
        True, description="images only: and with the next 2^k, k < overlap"
    )
    # triangulation and point filtering
    min_track_length: int = Field(3, ge=2, description="drop points seen in fewer images")
    # Known poses: when the median image would see fewer points than this with tracks of
    # min_track_length, triangulate again keeping two-view tracks (the poses are given, so two
    # views fix a point). 0: never. Measured with ``python -m sfmloc.bench.sparse_maps`` (40
    # non-map frames relocalized, 300 replayed at 30 Hz): redkitchen every 60th frame, 158 ->
    # 320 points/image, 28/40 -> 35/40 relocalized, replay 65% -> 96%; every 30th, 312 -> 540,
    # 35/40 -> 39/40, median 0.70 -> 0.57 cm; no wrong relocalization either way. Every 10th
    # (the default map, 574 points/image) is left as it is.
    two_view_below: int = Field(
        400, ge=0, description="known poses: keep two-view points when the median image sees fewer"
    )
    max_reproj_error: float = Field(4.0, gt=0, description="px; COLMAP's filter_max_reproj_error")
    min_tri_angle_deg: float = Field(1.5, gt=0, description="deg; COLMAP's filter_min_tri_angle")
    # images only: intrinsics refinement when a camera is given (always refined otherwise)
    refine_given_intrinsics: bool = False
    global_ba_ratio: float = Field(
        1.4,
        ge=1.0,
        description="images only: global BA when the model grew by this factor (COLMAP 1.1)",
    )
    # execution
    num_threads: int = Field(-1, description="-1: all cores")
    seed: int = Field(0, ge=0, description="random seed of RANSAC and the mapper")
    check_images: bool = Field(True, description="decode every image first to name bad ones")
    keep_workdir: bool = False


# Known-poses path on 100 redkitchen frames (every 10th of seq-01, VGA), CPU seconds of the
# whole stage (wall time is about half on an idle 2-core machine):
#   default   OpenCV SIFT, contrast 0.015, k=5      ~21 CPU-s  ~11.0k points  0.71 px  track 5.5
#   fast      OpenCV SIFT, contrast 0.03, 2000, k=4 ~13 CPU-s   ~7.3k points  0.69 px  track 5.5
#   accurate  pycolmap SIFT, 8192 features, k=8     ~40 CPU-s  ~10.5k points  0.81 px  track 6.6
# (pycolmap SIFT with the default pairs: ~34 CPU-s, 10.2k points, 0.72 px.)
SFM_PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "fast": {"contrast_threshold": 0.03, "max_features": 2000, "pair_neighbors": 4},
    "accurate": {
        "sift_backend": "pycolmap",
        "max_features": 8192,
        "pair_neighbors": 8,
        "pair_sequential": 3,
        "sequential_overlap": 8,
    },
}


def sfm_conf(preset: str = "default", **overrides: Any) -> SfmConf:
    """A named preset merged over the defaults, then explicit overrides (hloc style)."""
    if preset not in SFM_PRESETS:
        raise ConfigError(f"unknown SfM preset {preset!r}; known: {', '.join(SFM_PRESETS)}")
    return merge_presets(SfmConf(), **{**SFM_PRESETS[preset], **overrides})


def num_threads(conf: SfmConf) -> int:
    return conf.num_threads if conf.num_threads > 0 else (os.cpu_count() or 1)


def incremental_options(conf: SfmConf) -> pycolmap.IncrementalPipelineOptions:
    """Mapper/triangulator options with our filtering thresholds and thread count."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = conf.num_threads
    opts.random_seed = conf.seed
    opts.mapper.num_threads = conf.num_threads
    opts.mapper.random_seed = conf.seed
    opts.mapper.filter_max_reproj_error = conf.max_reproj_error
    opts.mapper.filter_min_tri_angle = conf.min_tri_angle_deg
    tri = opts.triangulation
    tri.random_seed = conf.seed
    tri.min_angle = conf.min_tri_angle_deg
    tri.complete_max_reproj_error = conf.max_reproj_error
    tri.merge_max_reproj_error = conf.max_reproj_error
    # Two-view tracks are only worth triangulating when we keep them.
    tri.ignore_two_view_tracks = conf.min_track_length > 2
    return opts
