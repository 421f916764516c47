"""The map-point lookup behind the pose covariance's per-point term: the vectorized lookup
returns what the per-row dict did (the row whose bytes equal the query's, the last of
identical rows, -1 for points not in the map), hash collisions included."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from sfmloc.engine import point_uncertainty as pu
from sfmloc.transforms import Rigid3d


def small_map(seed: int, n: int = 400):
    rng = np.random.default_rng(seed)
    X = rng.normal(0, 2.0, (n, 3))
    X[5] = X[17]  # byte-identical rows: the dict keeps the last
    X[40] = X[41] = X[n - 100]
    X[7] = [0.0, -0.0, 1.0]
    X[8] = [0.0, 0.0, 1.0]  # equal to row 7 as floats, not as bytes
    views = [Rigid3d(np.eye(3), rng.normal(0, 1.0, 3)) for _ in range(6)]
    idx = [np.sort(rng.choice(n, n // 2, replace=False)) for _ in views]
    ptr = np.concatenate([[0], np.cumsum([len(i) for i in idx])])
    bundle = SimpleNamespace(
        points_xyz=X,
        image_cam_from_world=views,
        image_points_ptr=ptr,
        image_points_idx=np.concatenate(idx).astype(np.int32),
    )
    return bundle, rng


def dict_lookup(X_map: np.ndarray, X: np.ndarray) -> np.ndarray:
    index = {X_map[i].tobytes(): i for i in range(len(X_map))}
    X = np.ascontiguousarray(X, np.float64)
    return np.array([index.get(x.tobytes(), -1) for x in X], np.int64)


def test_lookup_equals_the_per_row_dict():
    for seed in range(3):
        bundle, rng = small_map(seed)
        p = pu.PointUncertainty(bundle)
        X_map = bundle.points_xyz
        rows = rng.choice(len(X_map), 250)
        q = np.vstack([X_map[rows], rng.normal(0, 2.0, (30, 3)), X_map[[5, 17, 40, 7, 8]]])
        q[3] = np.nextafter(q[3], np.inf)  # one ulp off a map point: not in the map
        got = p.lookup(q)
        np.testing.assert_array_equal(got, dict_lookup(X_map, q))
        assert got[-5] == 17 and got[-3] == len(X_map) - 100 and got[-2] == 7 and got[-1] == 8
        assert (got[250:280] == -1).all()
        assert len(p.lookup(np.zeros((0, 3)))) == 0
        # sigma_px: the formula with the looked-up kappa, 0 for points not in the map
        z = rng.uniform(0.5, 5.0, len(q))
        want = np.where(got >= 0, p.kappa[np.maximum(got, 0)], 0.0) * 0.4 / z
        np.testing.assert_array_equal(p.sigma_px(q, z, 0.4), want)


def test_lookup_with_every_hash_colliding_falls_back_to_the_dict(monkeypatch):
    bundle, rng = small_map(7, 120)
    monkeypatch.setattr(pu, "_row_keys", lambda rows: np.zeros(len(rows), np.uint64))
    p = pu.PointUncertainty(bundle)
    q = np.vstack([bundle.points_xyz[rng.choice(120, 60)], rng.normal(0, 2.0, (10, 3))])
    np.testing.assert_array_equal(p.lookup(q), dict_lookup(bundle.points_xyz, q))


def test_kappa_equals_the_per_observation_accumulation():
    """The per-point ray sums by bincount (PointUncertainty) give exactly the kappa of the
    unbuffered np.add.at accumulation they replaced."""
    bundle, _ = small_map(3)
    X = np.asarray(bundle.points_xyz, np.float64)
    centers = np.array([T.center for T in bundle.image_cam_from_world])
    ptr = np.asarray(bundle.image_points_ptr)
    pts = np.asarray(bundle.image_points_idx, np.int64)
    img = np.repeat(np.arange(len(centers)), np.diff(ptr))
    rays = X[pts] - centers[img]
    dist = np.linalg.norm(rays, axis=1)
    rays /= np.maximum(dist, 1e-12)[:, None]
    mean = np.zeros((len(X), 3))
    np.add.at(mean, pts, rays)
    mean /= np.maximum(np.linalg.norm(mean, axis=1), 1e-12)[:, None]
    half = np.arccos(np.clip(np.sum(rays * mean[pts], axis=1), -1.0, 1.0))
    theta = np.zeros(len(X))
    np.maximum.at(theta, pts, 2.0 * half)
    d_min = np.full(len(X), np.inf)
    np.minimum.at(d_min, pts, dist)
    d_min[~np.isfinite(d_min)] = 0.0
    theta = np.maximum(theta, np.radians(pu.MIN_ANGLE_DEG))
    want = d_min / np.sin(np.minimum(theta, np.pi / 2))
    got = pu.PointUncertainty(bundle).kappa
    assert np.count_nonzero(want == 0) > 0  # points no image lists are in the test
    assert np.array_equal(got, want)
