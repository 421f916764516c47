"""How much of the map a guided-matching scope counts an image for (issue 17: a denser map must
not shrink the scope).

The paper scopes guided matching to the top-30 database images by matched points. Thirty images
are a place only at the map's density: from every 10th frame of redkitchen they span ~300
frames, from every frame ~30, and a scope that covers 10x less space leaves the keypoints of the
frame's newly seen parts unmatched, the tracks thin out and the tracker falls back to global
matching (the every-frame map ran at x1.27 the every-10th map's CPU per frame; top-100 images
x1.12). So an image counts for ``1 / n`` of a place, ``n`` the map images (itself included)
taken from about the same viewpoint: camera centre within ``radius`` times the scene scale and
optical axis within ``MAX_ANGLE_DEG``; a scope takes ranked images until their weights add up to
``top``. Redkitchen at radius 0.02: from every 10th frame the median ``n`` is 1 (the weights
add up to 88 places for 100 images), from every frame 11 (92 places for 1,000 images).

Shared points do not tell the density: the builder gives neighbouring images different points
(adjacent images share a median 63% of their points on the every-frame map, 60% on the
every-10th), so near-duplicates by points were rare on both maps.
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING

import numpy as np

from ..map.bundle import MapBundle

if TYPE_CHECKING:
    from .config import EngineConf

MAX_ANGLE_DEG = 15.0  # images looking more than this apart see different things

_cache: weakref.WeakKeyDictionary[MapBundle, dict[tuple[float, float], np.ndarray]] = (
    weakref.WeakKeyDictionary()
)


def duplicate_counts(bundle: MapBundle, radius: float) -> np.ndarray:
    """Per image, the number of images (itself included) whose camera centre lies within
    ``radius * bundle.scene_scale`` of its own and whose optical axis is within
    ``MAX_ANGLE_DEG`` of its own."""
    poses = bundle.image_cam_from_world
    n = len(poses)
    if n == 0:
        return np.ones(0, np.int64)
    centres = np.array([t.center for t in poses], np.float64)
    axes = np.array([t.rotation[2] for t in poses], np.float64)  # optical axis in the world
    # Here, not at the top: scipy.spatial was 2.2 of the server process's 5.4 s of imports at
    # load 14 (it imports the engine's config, hence the engine package), where it is never
    # used; the worker zygote imports it before it forks (zygote._preload) and a worker
    # computes this when it loads the map (worker.on_load), before any frame.
    from scipy.spatial import cKDTree

    pairs = cKDTree(centres).query_pairs(radius * bundle.scene_scale, output_type="ndarray")
    out = np.ones(n, np.int64)
    if len(pairs):
        cos = np.einsum("ij,ij->i", axes[pairs[:, 0]], axes[pairs[:, 1]])
        pairs = pairs[cos >= np.cos(np.radians(MAX_ANGLE_DEG))]
        out += np.bincount(pairs.ravel(), minlength=n)
    return out


def is_dense(counts: np.ndarray, min_duplicates: float) -> bool:
    """A map from dense video: its median image has at least ``min_duplicates`` images
    (itself included) from its viewpoint (``counts``: ``duplicate_counts``)."""
    return len(counts) > 0 and float(np.median(counts)) >= min_duplicates


def image_weights(bundle: MapBundle, radius: float, min_duplicates: float = 0.0) -> np.ndarray:
    """Per image, the fraction of a place it counts for in a scope: ``1 / duplicate_counts``
    on a dense map (``is_dense`` with ``min_duplicates``), all 1 on a sparser one and when
    ``radius`` is 0: the paper's image count. Cached per bundle."""
    if not radius > 0.0:
        return np.ones(bundle.n_images)
    per = _cache.setdefault(bundle, {})
    key = (radius, min_duplicates)
    w = per.get(key)
    if w is None:
        d = duplicate_counts(bundle, radius)
        w = 1.0 / d if is_dense(d, min_duplicates) else np.ones(bundle.n_images)
        per[key] = w
    return w


def guided_nprobe(bundle: MapBundle, conf: EngineConf, nprobe: int | None = None) -> int:
    """Inverted lists the scoped (guided) k-ANN search scans per query: ``nprobe`` (None:
    ``conf.nprobe``), on a
    map from dense video (``is_dense``) divided by the square root of its median image's
    near-duplicate count ``n`` (``conf.scope_dense_nprobe``; at least 4). The index's lists
    grow as the square root of its descriptors (``map.index.choose_nlist``), and a map from
    every frame holds each place's descriptors ``n`` times over: scanning ``nprobe /
    sqrt(n)`` of its lists scans as many entries per query as ``nprobe`` on the map of one
    image per place."""
    nprobe = int(nprobe or conf.nprobe)
    if not (conf.scope_dense_nprobe and conf.scope_radius > 0):
        return nprobe
    per = _nprobe_cache.setdefault(bundle, {})
    key = (float(conf.scope_radius), float(conf.scope_min_duplicates), nprobe)
    got = per.get(key)
    if got is None:
        d = duplicate_counts(bundle, conf.scope_radius)
        got = nprobe
        if is_dense(d, conf.scope_min_duplicates):
            got = max(min(4, got), int(round(nprobe / np.sqrt(float(np.median(d))))))
        per[key] = got
    return got


def median_track_length(bundle: MapBundle) -> float:
    """The number of map images the median map point is observed in (cached per bundle)."""
    got = _track_cache.get(bundle)
    if got is None:
        n = np.bincount(bundle.image_points_idx, minlength=len(bundle.points_xyz))
        got = float(np.median(n)) if len(n) else 0.0
        _track_cache[bundle] = got
    return got


_track_cache: weakref.WeakKeyDictionary[MapBundle, float] = weakref.WeakKeyDictionary()
_nprobe_cache: weakref.WeakKeyDictionary[MapBundle, dict[tuple[float, float, int], int]] = (
    weakref.WeakKeyDictionary()
)
