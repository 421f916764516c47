"""The linear Kalman filter the motion filters use: filterpy's ``KalmanFilter`` predict and
update (the Joseph-form covariance update) and its constant-velocity process noise, in plain
numpy with the same operations in the same order (tests/test_kalman.py: equal to filterpy's
results).

Why not filterpy itself: importing ``filterpy.kalman`` pulls in scipy.stats, 0.8 of the 1.4 s
CPU an engine worker spends importing at start (3 workers start together: start to SERVING,
issue 16); the filter itself is these few lines."""

from __future__ import annotations

import numpy as np


class KalmanFilter:
    """State ``x`` (dim_x x 1), covariance ``P``, measurement model ``H`` and noise ``R``;
    initialised as filterpy's (zeros, identities, a zero ``H``)."""

    def __init__(self, dim_x: int, dim_z: int) -> None:
        self.x = np.zeros((dim_x, 1))
        self.P = np.eye(dim_x)
        self.H = np.zeros((dim_z, dim_x))
        self.R = np.eye(dim_z)
        self._I = np.eye(dim_x)

    def predict(self, F: np.ndarray, Q: np.ndarray) -> None:
        """x = F x; P = F P F' + Q."""
        self.x = np.dot(F, self.x)
        self.P = 1.0 * np.dot(np.dot(F, self.P), F.T) + Q

    def update(self, z: np.ndarray) -> None:
        """Fuse the measurement ``z`` (dim_z x 1); P = (I-KH) P (I-KH)' + K R K'."""
        H, R = self.H, self.R
        y = z - np.dot(H, self.x)
        PHT = np.dot(self.P, H.T)
        S = np.dot(H, PHT) + R
        K = np.dot(PHT, np.linalg.inv(S))
        self.x = self.x + np.dot(K, y)
        I_KH = self._I - np.dot(K, H)
        self.P = np.dot(np.dot(I_KH, self.P), I_KH.T) + np.dot(np.dot(K, R), K.T)


def white_noise_cv(dt: float, var: float, block_size: int) -> np.ndarray:
    """Discrete white-noise acceleration of a constant-velocity model, ``block_size``
    independent axes ordered [positions..., velocities...] (filterpy's
    ``Q_discrete_white_noise(dim=2, order_by_dim=False)``)."""
    q = np.array([[0.25 * dt**4, 0.5 * dt**3], [0.5 * dt**3, dt**2]])
    D = np.zeros((2 * block_size, 2 * block_size))
    for i, v in enumerate(q.ravel()):
        ix, iy = (i // 2) * block_size, (i % 2) * block_size
        D[ix : ix + block_size, iy : iy + block_size] = np.eye(block_size) * v
    return D * var
