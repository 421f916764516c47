"""engine.kalman against filterpy (the library it replaces, issue 16): the same states and
covariances, bit for bit, over random filters and measurement sequences, and the same
process noise; so the motion filters built on it give the same poses as before."""

from __future__ import annotations

import numpy as np
import pytest

from sfmloc.engine.kalman import KalmanFilter, white_noise_cv

filterpy = pytest.importorskip("filterpy")


@pytest.mark.parametrize("dims", [(12, 6), (6, 3)])
def test_predict_and_update_equal_filterpy(dims):
    from filterpy.kalman import KalmanFilter as Reference

    dim_x, dim_z = dims
    rng = np.random.default_rng(dim_x)
    ours, ref = KalmanFilter(dim_x, dim_z), Reference(dim_x=dim_x, dim_z=dim_z)
    for a, b in ((ours.x, ref.x), (ours.P, ref.P), (ours.H, ref.H), (ours.R, ref.R)):
        assert np.array_equal(a, b)
    H = np.hstack([np.eye(dim_z), np.zeros((dim_z, dim_x - dim_z))])
    R = np.diag(rng.uniform(1e-4, 1e-2, dim_z))
    x0 = rng.normal(size=(dim_x, 1))
    P0 = np.diag(rng.uniform(0.01, 1.0, dim_x))
    for kf in (ours, ref):
        kf.H, kf.R, kf.x, kf.P = H.copy(), R.copy(), x0.copy(), P0.copy()
    for _ in range(50):
        dt = float(rng.uniform(0.01, 0.5))
        F = np.eye(dim_x) + np.diag(np.full(dim_x - dim_z, dt), dim_z)
        A = rng.normal(size=(dim_x, dim_x)) * 1e-3
        Q = A @ A.T
        z = rng.normal(size=(dim_z, 1))
        ours.predict(F=F, Q=Q)
        ref.predict(F=F, Q=Q)
        ours.update(z)
        ref.update(z)
        assert np.array_equal(ours.x, ref.x) and np.array_equal(ours.P, ref.P)


@pytest.mark.parametrize("dt, var, block", [(0.033, 4.0, 3), (1e-4, 64.0, 3), (0.5, 0.3, 2)])
def test_white_noise_equals_filterpy(dt, var, block):
    from filterpy.common import Q_discrete_white_noise

    ref = Q_discrete_white_noise(dim=2, dt=dt, var=var, block_size=block, order_by_dim=False)
    assert np.array_equal(white_noise_cv(dt, var, block), ref)
