"""Guided matching's scope covers a place, whatever the map's density (engine/scope.py; issue
17): a synthetic corridor walked at 30 Hz, mapped from every frame and from every 10th, the
same map points; a frame's matched points scope the same stretch of corridor in both maps.
The wall is 25 units away (the scene scale): scope_radius 0.02 is 0.5 units, 5 frames."""

from __future__ import annotations

import numpy as np
import pytest

from sfmloc.builder.clusters import ClusterConf, cluster_images
from sfmloc.cameras import Camera
from sfmloc.engine.config import EngineConf
from sfmloc.engine.matching import scope_images
from sfmloc.engine.scope import duplicate_counts, image_weights, is_dense
from sfmloc.map.bundle import MapBundle, MapData, write_bundle
from sfmloc.map.index import DescriptorIndex
from sfmloc.transforms import Rigid3d

STEP = 0.1  # corridor length units walked per frame
HALF = 1.25  # a camera sees the points within this of its position: frames 10 apart share 60%
DENSITY = 40  # points per unit of corridor
DEPTH = 25.0  # the wall's distance: the scene scale
LENGTH = 100.0


def _corridor_points() -> np.ndarray:
    return np.arange(0.0, LENGTH, 1.0 / DENSITY)


def _corridor_map(tmp_path, stride: int) -> MapBundle:
    """A bundle of every ``stride``-th frame of the walk: image k sees the corridor points
    within HALF of its position (real arrays, written and loaded like any bundle)."""
    u = _corridor_points()
    n_points = len(u)
    centres = np.arange(0.0, LENGTH, STEP)[::stride]
    image_points = [np.nonzero(np.abs(u - c) <= HALF)[0] for c in centres]
    n_images = len(centres)
    rng = np.random.default_rng(stride)
    per_image = 4  # descriptors: a few per image, enough for a valid index
    desc = rng.standard_normal((n_images * per_image, 32)).astype(np.float16)
    desc_image = np.repeat(np.arange(n_images), per_image).astype(np.int32)
    desc_point = np.concatenate([p[:per_image] for p in image_points]).astype(np.int32)
    ip_ptr = np.concatenate([[0], np.cumsum([len(p) for p in image_points])]).astype(np.int64)
    cl = cluster_images(image_points, n_points, ClusterConf(max_size=8))
    pc_ptr, pc_idx = cl.point_clusters(image_points, n_points)
    ci_ptr = np.concatenate([[0], np.cumsum([len(c) for c in cl.images])]).astype(np.int64)
    cam_from_world = np.zeros((n_images, 7))
    cam_from_world[:, 0] = 1.0
    cam_from_world[:, 4] = -centres
    data = MapData(
        points_xyz=np.stack([u, np.zeros(n_points), np.full(n_points, DEPTH)], axis=1),
        point_ids=np.arange(n_points) + 1,
        point_rgb=np.zeros((n_points, 3), np.uint8),
        descriptors=desc,
        desc_point=desc_point,
        desc_image=desc_image,
        desc_level=np.zeros(len(desc), np.uint8),
        desc_xy=rng.uniform(0, 100, (len(desc), 2)).astype(np.float32),
        image_desc_ptr=np.arange(n_images + 1, dtype=np.int64) * per_image,
        image_cam_from_world=cam_from_world,
        image_camera=np.zeros(n_images, np.int32),
        image_points_ptr=ip_ptr,
        image_points_idx=np.concatenate(image_points).astype(np.int32),
        cluster_images_ptr=ci_ptr,
        cluster_images_idx=np.concatenate(cl.images).astype(np.int32),
        point_clusters_ptr=pc_ptr,
        point_clusters_idx=pc_idx,
        pca_mean=np.zeros(104, np.float32),
        pca_basis=np.eye(104, 32, dtype=np.float32),
        index_faiss=DescriptorIndex.build(desc.astype(np.float32)).serialize(),
        cameras=[Camera.pinhole(640, 480, 500, 500, 320, 240)],
        image_names=[f"frame-{i * stride:04d}.png" for i in range(n_images)],
    )
    return MapBundle(write_bundle(data, tmp_path, f"corridor-s{stride}"))


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    root = tmp_path_factory.mktemp("scope")
    return {s: _corridor_map(root, s) for s in (10, 1)}


def _covered(bundle: MapBundle, imgs: np.ndarray) -> np.ndarray:
    """The corridor points the scope's images see."""
    ptr, idx = bundle.image_points_ptr, bundle.image_points_idx
    return np.unique(np.concatenate([idx[ptr[i] : ptr[i + 1]] for i in imgs]))


def test_duplicates_count_the_images_from_one_viewpoint(maps):
    conf = EngineConf(scope_radius=0.02)  # the dense-video setting (default 0: the paper's)
    assert maps[10].scene_scale == pytest.approx(DEPTH)
    # every 10th frame: neighbours 1 unit apart, beyond 0.02 * 25
    assert np.all(duplicate_counts(maps[10], conf.scope_radius) == 1)
    assert np.all(image_weights(maps[10], conf.scope_radius) == 1.0)
    # every frame: the frames within 0.5 units, 5 on either side (the 5th at the limit: 4-5)
    # and itself in the corridor's middle, fewer at its ends
    d = duplicate_counts(maps[1], conf.scope_radius)
    assert np.all((d[10:-10] >= 9) & (d[10:-10] <= 11))
    assert d[0] in (5, 6)
    # 0: the paper's scope, every image counts 1
    assert np.all(image_weights(maps[1], 0.0) == 1.0)


def test_images_looking_elsewhere_are_not_duplicates(tmp_path):
    b = _corridor_map(tmp_path, 1)
    conf = EngineConf(scope_radius=0.02)  # the dense-video setting (default 0: the paper's)
    d0 = duplicate_counts(b, conf.scope_radius)
    T = b.image_cam_from_world[500]
    turn = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # 90 deg about y
    b.image_cam_from_world[500] = Rigid3d(turn @ T.rotation, turn @ T.translation)
    d1 = duplicate_counts(b, conf.scope_radius)
    assert d1[500] == 1 and d0[500] >= 9
    near = np.array([496, 497, 498, 499, 501, 502, 503, 504])  # within 0.5 units of it
    assert np.all(d1[near] == d0[near] - 1)


@pytest.mark.parametrize("centre", [10.0, 50.0, 97.5])
def test_the_scope_covers_the_same_place_at_every_density(maps, centre):
    conf = EngineConf(scope_radius=0.02)  # the dense-video setting (default 0: the paper's)
    u = _corridor_points()
    matched = np.nonzero(np.abs(u - centre) <= 1.0)[0]  # what a frame there has matched
    top = 3
    sparse = scope_images(maps[10], matched, top, image_weights(maps[10], conf.scope_radius))
    assert len(sparse) == top  # every image counts 1: the paper's scope, unchanged
    assert np.array_equal(sparse, scope_images(maps[10], matched, top))
    want = _covered(maps[10], sparse)
    dense_w = scope_images(maps[1], matched, top, image_weights(maps[1], conf.scope_radius))
    dense_n = scope_images(maps[1], matched, top)
    got_w, got_n = _covered(maps[1], dense_w), _covered(maps[1], dense_n)
    # the weighted scope of the dense map covers the sparse map's place (within one frame's
    # step), not ten times less of it
    assert np.isin(want, got_w).mean() >= 0.95
    assert len(got_w) <= 1.3 * len(want)
    assert len(dense_w) >= 5 * top
    # the paper's image count on the dense map: a much narrower stretch
    assert np.isin(want, got_n).mean() < 0.7


def test_only_maps_from_dense_video_get_the_place_sized_scope(tmp_path, maps):
    """The default engine weights images on a map whose median image has a near-duplicate
    (dense video), and keeps the paper's scope where only some images have one (redkitchen's
    every-10th map: 20% of its images, whose weighting cost it accuracy)."""
    conf = EngineConf()
    r, m = conf.scope_radius, conf.scope_min_duplicates
    assert r > 0 and m > 1
    dense = duplicate_counts(maps[1], r)
    assert is_dense(dense, m)
    assert np.array_equal(image_weights(maps[1], r, m), 1.0 / dense)
    assert image_weights(maps[1], r, m).sum() < 0.15 * maps[1].n_images
    assert np.all(image_weights(maps[10], r, m) == 1.0)
    # a sparse map with every 5th image taken again 0.3 units (0.012 scene scales) on: 40% of
    # its images have a duplicate, the median image none
    b = _corridor_map(tmp_path, 10)
    for k in range(0, b.n_images, 5):
        c = b.image_cam_from_world[k].center + np.array([0.3, 0.0, 0.0])
        b.image_cam_from_world[k + 1] = Rigid3d(np.eye(3), -c)
    d = duplicate_counts(b, r)
    assert (d > 1).mean() == pytest.approx(0.4)
    assert not is_dense(d, m)
    assert np.all(image_weights(b, r, m) == 1.0)
    assert np.any(image_weights(b, r) < 1.0)  # by the radius alone it would be weighted


def test_weights_are_cached_per_bundle(maps):
    w1 = image_weights(maps[1], 0.02)
    assert image_weights(maps[1], 0.02) is w1
    assert image_weights(maps[1], 0.03) is not w1


def test_a_localizer_prepares_the_per_bundle_tables_before_its_first_frame(tmp_path):
    """The point uncertainty and the scope's weights are computed when the tracker is made
    (a map load), not by its first frame: on redkitchen's every-frame map they were 0.5 s of
    it."""
    from sfmloc.engine import Localizer, point_uncertainty, scope

    b = _corridor_map(tmp_path, 1)
    assert b not in point_uncertainty._cache and b not in scope._cache
    conf = EngineConf(scope_radius=0.02, scope_min_duplicates=2.0)
    Localizer(b, b.cameras[0], conf)
    assert b in point_uncertainty._cache
    w = scope._cache[b][(0.02, 2.0)]
    assert np.allclose(w, 1.0 / duplicate_counts(b, 0.02))  # the dense map's weights


def test_the_guided_search_scans_fewer_lists_only_on_maps_from_dense_video(maps):
    """With scope_dense_nprobe (off by default): nprobe / sqrt(n) on the every-frame corridor
    (n: its median image's near-duplicates, 10-11 here), nprobe on the every-10th one."""
    from sfmloc.engine.scope import guided_nprobe

    assert guided_nprobe(maps[1], EngineConf(scope_radius=0.02, nprobe=16)) == 16  # off
    conf = EngineConf(
        scope_radius=0.02, scope_min_duplicates=2.0, nprobe=16, scope_dense_nprobe=True
    )
    assert guided_nprobe(maps[10], conf) == 16
    n = float(np.median(duplicate_counts(maps[1], 0.02)))
    assert 9 <= n <= 11
    assert guided_nprobe(maps[1], conf) == round(16 / np.sqrt(n)) == 5
    assert guided_nprobe(maps[1], conf.model_copy(update={"scope_dense_nprobe": False})) == 16
    assert guided_nprobe(maps[1], conf.model_copy(update={"nprobe": 32})) == round(32 / np.sqrt(n))
    assert guided_nprobe(maps[1], conf.model_copy(update={"nprobe": 4})) == 4  # at least 4
    # a caller's list count (the localizer's scope_nprobe) replaces nprobe, and on the dense
    # map it is the one divided
    assert guided_nprobe(maps[10], EngineConf(nprobe=16), 8) == 8
    assert guided_nprobe(maps[10], EngineConf(nprobe=16), None) == 16
    assert guided_nprobe(maps[1], conf, 32) == round(32 / np.sqrt(n))


def test_guided_matching_searches_with_the_dense_maps_nprobe(maps):
    from sfmloc.engine.matching import guided_matching

    conf = EngineConf(
        scope_radius=0.02, scope_min_duplicates=2.0, nprobe=16, scope_dense_nprobe=True
    )
    u = _corridor_points()
    matched = np.nonzero(np.abs(u - 50.0) <= 1.0)[0]
    rng = np.random.default_rng(0)
    for stride, want in ((1, 5), (10, 16)):
        b = maps[stride]
        seen: list[int | None] = []
        search = b.index.search

        def spy(*a, _search=search, _seen=seen, **kw):
            _seen.append(kw.get("nprobe"))
            return _search(*a, **kw)

        b.index.search = spy  # the real search runs; only its nprobe is recorded
        try:
            desc = rng.standard_normal((8, 32)).astype(np.float32)
            xy = rng.uniform(0, 400, (8, 2))
            K = b.cameras[0].K
            guided_matching(desc, xy, b, matched, b.image_cam_from_world[0], K, conf)
        finally:
            del b.index.search
        assert seen == [want], (stride, seen)
