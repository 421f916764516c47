"""The SfM front-end of the map builder: three inputs, one COLMAP-style reconstruction.

- ``load_colmap_input(model_dir, image_dir)``: an existing COLMAP model, checked against its
  images (``colmap``).
- ``triangulate_known_poses(image_dir, poses_file, camera)``: images with known poses (COLMAP
  list or TUM); SIFT, pose-guided pairs, matching and point triangulation with pycolmap, the
  poses kept exactly: a metric map in the poses' frame (``poses``).
- ``reconstruct_images_only(image_dir, camera=None)``: full incremental SfM with pycolmap; the
  map's frame and scale are arbitrary (``images``).

SIFT comes from OpenCV by default (about 40% of pycolmap's SIFT CPU time for as many and as
accurate points; keypoints converted to COLMAP's pixel convention, descriptors to RootSIFT) or
from pycolmap (``sift_backend="pycolmap"``); matching, verification, triangulation and mapping
are pycolmap's.

Each returns ``sfmloc.io.colmap.Reconstruction`` (cameras, registered images with
``cam_from_world`` and keypoints, points with tracks). Long stages report
``progress(stage, fraction, message)`` (stages: input, features, matching, triangulate,
mapping; it may be called from a worker thread) and poll ``should_cancel()``, raising
``BuildCancelled``. Bad input raises ``InputError`` (``ImageDecodeError``,
``CameraModelError``, ``ModelFormatError``) naming the file; a failed stage raises
``BuildError`` with its ``stage``. Parameters: ``SfmConf``, with presets
``sfm_conf("fast" | "default" | "accurate", **overrides)``; ``num_threads=-1`` uses all cores.
The COLMAP database and intermediate files live in a temporary directory (under ``workdir``
when given) removed afterwards unless ``keep_workdir``.
"""

from __future__ import annotations

from .colmap import load_colmap_input
from .conf import SFM_PRESETS, SfmConf, sfm_conf
from .convert import (
    filter_points,
    reconstruction_from_pycolmap,
    reconstruction_stats,
    reconstruction_to_pycolmap,
    rigid3d_from_pycolmap,
    rigid3d_to_pycolmap,
)
from .images import exhaustive_pairs, reconstruct_images_only, sequential_pairs
from .poses import match_poses_to_images, pairs_from_poses, triangulate_known_poses
from .run import CancelCheck, Progress

__all__ = [
    "SFM_PRESETS",
    "CancelCheck",
    "Progress",
    "SfmConf",
    "exhaustive_pairs",
    "filter_points",
    "load_colmap_input",
    "match_poses_to_images",
    "pairs_from_poses",
    "reconstruct_images_only",
    "reconstruction_from_pycolmap",
    "reconstruction_stats",
    "reconstruction_to_pycolmap",
    "rigid3d_from_pycolmap",
    "rigid3d_to_pycolmap",
    "sequential_pairs",
    "sfm_conf",
    "triangulate_known_poses",
]
