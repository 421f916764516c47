"""Kalman filtering of the pose (paper Section 3.3): constant velocity and constant angular
velocity, as two independent filters, position and orientation (filterpy).

- Position: state ``[p, v]`` (world frame, metres), discrete white-noise acceleration.
- Orientation: an error-state filter around a reference rotation ``R_ref`` (of
  ``world_from_cam``): state ``[theta, omega]`` where ``theta`` is the rotation vector of
  ``R R_ref^T`` and ``omega`` the angular velocity (world frame). Predict integrates
  ``theta += omega dt``; a measured rotation enters as ``z = log(R_meas R_ref^T)``; after each
  update the error is folded into ``R_ref`` and reset to zero. This keeps a linear filter on a
  vector space while the rotation itself stays on SO(3).

The prediction seeds tracking and guided matching for the next frame.
"""

from __future__ import annotations

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter

from ..transforms import Rigid3d, rotmat_from_rotvec, rotvec_from_rotmat


def _cv_filter(meas_sigma: float) -> KalmanFilter:
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
    kf.R = np.eye(3) * meas_sigma**2
    return kf


def _transition(dt: float) -> np.ndarray:
    F = np.eye(6)
    F[:3, 3:] = np.eye(3) * dt
    return F


def _process_noise(dt: float, accel_sigma: float) -> np.ndarray:
    # order_by_dim=False: [x y z x' y' z']
    return Q_discrete_white_noise(dim=2, dt=max(dt, 1e-4), var=accel_sigma**2, block_size=3, order_by_dim=False)


class PoseFilter:
    """Two independent constant-velocity Kalman filters (position, orientation)."""

    def __init__(
        self,
        accel_noise: float = 4.0,
        angular_accel_noise: float = 8.0,
        position_noise: float = 0.02,
        orientation_noise: float = 0.01,
    ) -> None:
        self.accel_noise = accel_noise
        self.angular_accel_noise = angular_accel_noise
        self.pos = _cv_filter(position_noise)
        self.rot = _cv_filter(orientation_noise)
        self.R_ref = np.eye(3)
        self.stamp: float | None = None
        self.initialized = False

    def reset(self, cam_from_world: Rigid3d, stamp: float) -> None:
        """Start from a pose with unknown velocity."""
        world_from_cam = cam_from_world.inverse()
        self.pos.x = np.concatenate([world_from_cam.translation, np.zeros(3)]).reshape(6, 1)
        self.pos.P = np.diag([self.pos.R[0, 0]] * 3 + [1.0] * 3)
        self.R_ref = world_from_cam.rotation.copy()
        self.rot.x = np.zeros((6, 1))
        self.rot.P = np.diag([self.rot.R[0, 0]] * 3 + [1.0] * 3)
        self.stamp = stamp
        self.initialized = True

    def predict(self, stamp: float) -> Rigid3d | None:
        """Advance to ``stamp`` and return the predicted ``cam_from_world`` (None before the
        first pose)."""
        if not self.initialized or self.stamp is None:
            return None
        dt = max(0.0, stamp - self.stamp)
        if dt > 0:
            F = _transition(dt)
            self.pos.predict(F=F, Q=_process_noise(dt, self.accel_noise))
            self.rot.predict(F=F, Q=_process_noise(dt, self.angular_accel_noise))
            self.stamp = stamp
        return self.current()

    def update(self, cam_from_world: Rigid3d) -> Rigid3d:
        """Fuse a measured pose; return the filtered ``cam_from_world``."""
        world_from_cam = cam_from_world.inverse()
        self.pos.update(world_from_cam.translation.reshape(3, 1))
        z = rotvec_from_rotmat(world_from_cam.rotation @ self.R_ref.T)
        self.rot.update(z.reshape(3, 1))
        # fold the error into the reference
        theta = self.rot.x[:3, 0].copy()
        self.R_ref = rotmat_from_rotvec(theta) @ self.R_ref
        self.rot.x[:3, 0] = 0.0
        return self.current()

    def current(self) -> Rigid3d:
        """The filter's present ``cam_from_world`` (predicted or filtered)."""
        R = rotmat_from_rotvec(self.rot.x[:3, 0]) @ self.R_ref
        world_from_cam = Rigid3d(R, self.pos.x[:3, 0])
        return world_from_cam.inverse()

    @property
    def velocity(self) -> np.ndarray:
        return self.pos.x[3:, 0].copy()

    @property
    def angular_velocity(self) -> np.ndarray:
        return self.rot.x[3:, 0].copy()
