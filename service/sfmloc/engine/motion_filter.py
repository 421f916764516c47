"""Kalman filtering of the pose (paper Section 3.3): two motion models, chosen by
``EngineConf.motion_model``.

``se3`` (default), ``Se3PoseFilter``: one constant-velocity model on SE(3). The state is the
pose ``cam_from_world`` (T) and the camera's velocity as a twist in its own frame,
``xi = [v, w]`` (translation rate, angular rate): over ``dt`` the pose moves to
``exp(dt xi) T``, so a camera that keeps turning while it moves (an orbit, a car taking a bend)
is predicted along its arc instead of along a straight line with an independently extrapolated
orientation. The filter is an error-state Kalman filter (``kalman``): its 12-vector is
``[delta, xi]`` with ``T_true = exp(delta) T``; a measured pose enters as
``z = log(T_meas T^-1)``, and after each update ``delta`` is folded into ``T`` and reset to 0.

Translational noises are given in scene scales (``scale``, the map's median camera-to-point
depth, in map units), so the same settings mean the same thing in a 0.2-unit object scan and
a 500-unit street. ``delta``'s translational part is the camera's displacement in its own frame
(a rotation perturbation turns the camera about its centre), so the noises separate cleanly.

``paper``, ``DecoupledPoseFilter``: the paper's constant velocity and constant angular
velocity, as two independent filters (position in the world frame; orientation as an error
state around a reference rotation). Exact for a camera moving straight while it turns; on an
orbit its straight-line extrapolation cuts the chord.

Both take their translational noises in scene scales. The prediction seeds tracking and guided
matching for the next frame.
"""

from __future__ import annotations

import numpy as np

from ..transforms import Rigid3d, rotmat_from_rotvec, rotvec_from_rotmat
from .kalman import KalmanFilter, white_noise_cv


def _hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian V: ``exp([rho, phi])`` translates by ``V(phi) rho``."""
    th = float(np.linalg.norm(phi))
    W = _hat(phi)
    if th < 1e-6:
        return np.eye(3) + 0.5 * W + W @ W / 6.0
    return np.eye(3) + (1 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * (W @ W)


def se3_exp(xi: np.ndarray) -> Rigid3d:
    """The rigid motion of twist ``xi = [rho, phi]`` (translation part first)."""
    xi = np.asarray(xi, dtype=np.float64)
    return Rigid3d(rotmat_from_rotvec(xi[3:]), _left_jacobian(xi[3:]) @ xi[:3])


def se3_log(T: Rigid3d) -> np.ndarray:
    """The twist ``[rho, phi]`` of a rigid motion (inverse of ``se3_exp``)."""
    phi = rotvec_from_rotmat(T.rotation)
    rho = np.linalg.solve(_left_jacobian(phi), T.translation)
    return np.concatenate([rho, phi])


def _scene_scale(scale: float) -> float:
    """The filters' unit of length (map units per scene scale), checked."""
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scene scale must be positive, got {scale}")
    return float(scale)


def _process_noise(dt: float, accel_var: np.ndarray) -> np.ndarray:
    """Continuous white-noise acceleration, per twist component. (The piecewise-constant
    model's velocity gain tends to 2/dt when frames are far apart: at 3 Hz its velocity
    overshoots every frame and the prediction misses by 12 px on an orbit, 5 px with this.)"""
    dt = max(dt, 1e-4)
    Q = np.zeros((12, 12))
    i = np.arange(6)
    Q[i, i] = dt**3 / 3 * accel_var
    Q[i, i + 6] = Q[i + 6, i] = dt**2 / 2 * accel_var
    Q[i + 6, i + 6] = dt * accel_var
    return Q


class Se3PoseFilter:
    """Constant-velocity Kalman filter on SE(3) (pose and body-frame twist).

    ``accel_noise`` (scene scales / s^2) and ``angular_accel_noise`` (rad / s^2) are the white
    accelerations the model allows; ``position_noise`` (scene scales) and ``orientation_noise``
    (rad) the measurement noise of a pose; ``scale`` the scene scale in map units.
    """

    def __init__(
        self,
        accel_noise: float = 2.0,
        angular_accel_noise: float = 8.0,
        position_noise: float = 0.01,
        orientation_noise: float = 0.01,
        scale: float = 1.0,
    ) -> None:
        self.scale = _scene_scale(scale)
        self.accel_var = np.array([(accel_noise * scale) ** 2] * 3 + [angular_accel_noise**2] * 3)
        self.kf = KalmanFilter(12, 6)
        self.kf.H = np.hstack([np.eye(6), np.zeros((6, 6))])
        self.kf.R = np.diag([(position_noise * scale) ** 2] * 3 + [orientation_noise**2] * 3)
        self.T = Rigid3d(np.eye(3), np.zeros(3))  # cam_from_world
        self.stamp: float | None = None
        self.last: tuple[Rigid3d, float] | None = None  # the last fused pose and its stamp
        self.initialized = False

    def reset(
        self,
        cam_from_world: Rigid3d,
        stamp: float,
        keep_motion_s: float = 0.0,
        max_speed: float = np.inf,
        max_rate: float = np.inf,
    ) -> None:
        """Start from a pose. The velocity is unknown (1 scene scale/s, 1 rad/s of std), or,
        when the last fused pose is at most ``keep_motion_s`` old, the motion from it (unless
        faster than ``max_speed``, map units/s, or ``max_rate``, rad/s: then one was wrong)."""
        xi = np.zeros(6)
        if self.last is not None and 0 < stamp - self.last[1] <= keep_motion_s:
            xi = se3_log(cam_from_world * self.last[0].inverse()) / (stamp - self.last[1])
            moved = np.linalg.norm(cam_from_world.center - self.last[0].center)
            speed = moved / (stamp - self.last[1])
            if speed > max_speed or np.linalg.norm(xi[3:]) > max_rate:
                xi = np.zeros(6)
        self.T = Rigid3d(cam_from_world.rotation.copy(), cam_from_world.translation.copy())
        self.kf.x = np.concatenate([np.zeros(6), xi]).reshape(12, 1)
        self.kf.P = np.diag(np.concatenate([np.diag(self.kf.R), [self.scale**2] * 3 + [1.0] * 3]))
        self.stamp = stamp
        self.last = (self.current(), stamp)
        self.initialized = True

    def predict(self, stamp: float) -> Rigid3d | None:
        """Advance to ``stamp`` and return the predicted ``cam_from_world`` (None before the
        first pose)."""
        if not self.initialized or self.stamp is None:
            return None
        dt = max(0.0, stamp - self.stamp)
        if dt > 0:
            F = np.eye(12)
            F[:6, 6:] = np.eye(6) * dt
            self.kf.predict(F=F, Q=_process_noise(dt, self.accel_var))
            self._fold()
            self.stamp = stamp
        return self.current()

    def update(self, cam_from_world: Rigid3d) -> Rigid3d:
        """Fuse a measured pose; return the filtered ``cam_from_world``."""
        assert self.stamp is not None, "update() before reset()"
        z = se3_log(cam_from_world * self.T.inverse())
        self.kf.update(z.reshape(6, 1))
        self._fold()
        self.last = (self.current(), self.stamp)
        return self.current()

    def _fold(self) -> None:
        # Move the error into the pose: the linear state stays near zero, the pose on SE(3).
        delta = self.kf.x[:6, 0].copy()
        if np.any(delta):
            self.T = se3_exp(delta) * self.T
            self.kf.x[:6, 0] = 0.0

    def current(self) -> Rigid3d:
        """The filter's present ``cam_from_world`` (predicted or filtered)."""
        return Rigid3d(self.T.rotation.copy(), self.T.translation.copy())

    @property
    def twist(self) -> np.ndarray:
        """Body-frame velocity ``[v, w]`` of ``cam_from_world`` (map units / s, rad / s)."""
        return self.kf.x[6:, 0].copy()

    @property
    def velocity(self) -> np.ndarray:
        """The camera centre's velocity in the world frame (map units / s)."""
        return -self.T.rotation.T @ self.kf.x[6:9, 0]

    @property
    def angular_velocity(self) -> np.ndarray:
        """The angular velocity of ``world_from_cam`` in the world frame (rad / s)."""
        return -self.T.rotation.T @ self.kf.x[9:, 0]


def _cv_filter(meas_sigma: float) -> KalmanFilter:
    kf = KalmanFilter(6, 3)
    kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
    kf.R = np.eye(3) * meas_sigma**2
    return kf


def _transition(dt: float) -> np.ndarray:
    F = np.eye(6)
    F[:3, 3:] = np.eye(3) * dt
    return F


def _cv_noise(dt: float, accel_sigma: float) -> np.ndarray:
    # order_by_dim=False: [x y z x' y' z']
    return white_noise_cv(max(dt, 1e-4), accel_sigma**2, 3)


class DecoupledPoseFilter:
    """The paper's model: two independent constant-velocity Kalman filters, the camera centre
    (world frame) and the orientation of ``world_from_cam`` (an error state ``[theta, omega]``
    around ``R_ref``, folded into it after each update). Same settings as ``Se3PoseFilter``."""

    def __init__(
        self,
        accel_noise: float = 2.0,
        angular_accel_noise: float = 8.0,
        position_noise: float = 0.01,
        orientation_noise: float = 0.01,
        scale: float = 1.0,
    ) -> None:
        self.scale = _scene_scale(scale)
        self.accel_noise = accel_noise * scale
        self.angular_accel_noise = angular_accel_noise
        self.pos = _cv_filter(position_noise * scale)
        self.rot = _cv_filter(orientation_noise)
        self.R_ref = np.eye(3)
        self.stamp: float | None = None
        self.last: tuple[Rigid3d, float] | None = None
        self.initialized = False

    def reset(
        self,
        cam_from_world: Rigid3d,
        stamp: float,
        keep_motion_s: float = 0.0,
        max_speed: float = np.inf,
        max_rate: float = np.inf,
    ) -> None:
        """Start from a pose with unknown velocity (or the motion from the last fused pose, as
        ``Se3PoseFilter.reset``)."""
        world_from_cam = cam_from_world.inverse()
        v, w = np.zeros(3), np.zeros(3)
        if self.last is not None and 0 < stamp - self.last[1] <= keep_motion_s:
            prev, dt = self.last[0].inverse(), stamp - self.last[1]
            v = (world_from_cam.translation - prev.translation) / dt
            w = rotvec_from_rotmat(world_from_cam.rotation @ prev.rotation.T) / dt
            if np.linalg.norm(v) > max_speed or np.linalg.norm(w) > max_rate:
                v, w = np.zeros(3), np.zeros(3)
        self.pos.x = np.concatenate([world_from_cam.translation, v]).reshape(6, 1)
        self.pos.P = np.diag([self.pos.R[0, 0]] * 3 + [self.scale**2] * 3)
        self.R_ref = world_from_cam.rotation.copy()
        self.rot.x = np.concatenate([np.zeros(3), w]).reshape(6, 1)
        self.rot.P = np.diag([self.rot.R[0, 0]] * 3 + [1.0] * 3)
        self.stamp = stamp
        self.last = (self.current(), stamp)
        self.initialized = True

    def predict(self, stamp: float) -> Rigid3d | None:
        if not self.initialized or self.stamp is None:
            return None
        dt = max(0.0, stamp - self.stamp)
        if dt > 0:
            F = _transition(dt)
            self.pos.predict(F=F, Q=_cv_noise(dt, self.accel_noise))
            self.rot.predict(F=F, Q=_cv_noise(dt, self.angular_accel_noise))
            self.stamp = stamp
        return self.current()

    def update(self, cam_from_world: Rigid3d) -> Rigid3d:
        assert self.stamp is not None, "update() before reset()"
        world_from_cam = cam_from_world.inverse()
        self.pos.update(world_from_cam.translation.reshape(3, 1))
        z = rotvec_from_rotmat(world_from_cam.rotation @ self.R_ref.T)
        self.rot.update(z.reshape(3, 1))
        theta = self.rot.x[:3, 0].copy()
        self.R_ref = rotmat_from_rotvec(theta) @ self.R_ref
        self.rot.x[:3, 0] = 0.0
        self.last = (self.current(), self.stamp)
        return self.current()

    def current(self) -> Rigid3d:
        R = rotmat_from_rotvec(self.rot.x[:3, 0]) @ self.R_ref
        return Rigid3d(R, self.pos.x[:3, 0]).inverse()

    @property
    def velocity(self) -> np.ndarray:
        return self.pos.x[3:, 0].copy()

    @property
    def angular_velocity(self) -> np.ndarray:
        return self.rot.x[3:, 0].copy()


PoseFilter = Se3PoseFilter | DecoupledPoseFilter
MODELS: dict[str, type[PoseFilter]] = {"se3": Se3PoseFilter, "paper": DecoupledPoseFilter}


def make_pose_filter(
    model: str,
    accel_noise: float,
    angular_accel_noise: float,
    position_noise: float,
    orientation_noise: float,
    scale: float,
) -> PoseFilter:
    """The motion model ``model`` ("se3" or "paper") with its noises (scene scales, radians)."""
    return MODELS[model](accel_noise, angular_accel_noise, position_noise, orientation_noise, scale)
