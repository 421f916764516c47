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

import math

import numpy as np

from ..transforms import Rigid3d, rotmat_from_rotvec, rotvec_from_rotmat
from .kalman import KalmanFilter, white_noise_cv


def _exp(xi: list[float]) -> tuple[list[list[float]], list[float]]:
    """``exp([rho, phi])`` in Python floats: the rotation ``I + A W + B W^2`` (``W`` the
    cross-product matrix of ``phi``) and the translation ``V rho``, ``V = I + B W + C W^2``.
    (The filter's per-frame poses: three numpy calls per 3x3 matrix cost more than these
    few dozen multiplications.)"""
    r0, r1, r2, x, y, z = xi
    th2 = x * x + y * y + z * z
    if th2 < 1e-6:  # theta < 1e-3: the series, to theta^4 (the next terms are below 1e-18)
        A = 1.0 - th2 / 6.0 * (1.0 - th2 / 20.0)
        B = 0.5 - th2 / 24.0 * (1.0 - th2 / 30.0)
        C = 1.0 / 6.0 - th2 / 120.0 * (1.0 - th2 / 42.0)
    else:
        th = math.sqrt(th2)
        s = math.sin(th)
        h = math.sin(0.5 * th)
        A = s / th
        B = 2.0 * h * h / th2  # (1 - cos) / theta^2 without the cancellation
        C = (th - s) / (th2 * th)
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    R = [
        [1.0 - B * (yy + zz), B * xy - A * z, B * xz + A * y],
        [B * xy + A * z, 1.0 - B * (xx + zz), B * yz - A * x],
        [B * xz - A * y, B * yz + A * x, 1.0 - B * (xx + yy)],
    ]
    c0, c1, c2 = y * r2 - z * r1, z * r0 - x * r2, x * r1 - y * r0  # phi x rho
    d0, d1, d2 = y * c2 - z * c1, z * c0 - x * c2, x * c1 - y * c0  # phi x (phi x rho)
    return R, [r0 + B * c0 + C * d0, r1 + B * c1 + C * d1, r2 + B * c2 + C * d2]


def _log(R: list[list[float]], t: list[float]) -> list[float]:
    """``log`` of the rigid motion ``(R, t)`` in Python floats, ``[rho, phi]``: ``phi`` the
    rotation vector (``rotvec_from_rotmat``'s quaternion, Shepperd's branches) and
    ``rho = V^-1 t = t - W t / 2 + D W^2 t``."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = R
    tr = m00 + m11 + m22
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not (math.isfinite(n) and n >= 1e-12):
        raise ValueError(f"not a rotation: {R!r}")
    w, x, y, z = (v / n for v in q) if q[0] >= 0 else (-v / n for v in q)
    sv = math.sqrt(x * x + y * y + z * z)
    k = 2.0 if sv < 1e-12 else 2.0 * math.atan2(sv, w) / sv
    x, y, z = x * k, y * k, z * k
    th2 = x * x + y * y + z * z
    if th2 < 1e-6:  # the series of (1 - (theta/2) cot(theta/2)) / theta^2, to theta^4
        D = 1.0 / 12.0 + th2 / 720.0 * (1.0 + th2 / 42.0)
    else:
        half = 0.5 * math.sqrt(th2)
        D = (1.0 - half * math.cos(half) / math.sin(half)) / th2
    t0, t1, t2 = t
    c0, c1, c2 = y * t2 - z * t1, z * t0 - x * t2, x * t1 - y * t0  # phi x t
    d0, d1, d2 = y * c2 - z * c1, z * c0 - x * c2, x * c1 - y * c0  # phi x (phi x t)
    return [t0 - 0.5 * c0 + D * d0, t1 - 0.5 * c1 + D * d1, t2 - 0.5 * c2 + D * d2, x, y, z]


def se3_exp(xi: np.ndarray) -> Rigid3d:
    """The rigid motion of twist ``xi = [rho, phi]`` (translation part first)."""
    R, t = _exp(np.asarray(xi, dtype=np.float64).reshape(6).tolist())
    return Rigid3d(np.array(R), np.array(t))


def se3_log(T: Rigid3d) -> np.ndarray:
    """The twist ``[rho, phi]`` of a rigid motion (inverse of ``se3_exp``)."""
    return np.array(_log(T.rotation.tolist(), T.translation.tolist()))


def _scene_scale(scale: float) -> float:
    """The filters' unit of length (map units per scene scale), checked."""
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scene scale must be positive, got {scale}")
    return float(scale)


def _process_noise(dt: float, accel_var: list[float]) -> tuple[list[float], ...]:
    """Continuous white-noise acceleration, per twist component. (The piecewise-constant
    model's velocity gain tends to 2/dt when frames are far apart: at 3 Hz its velocity
    overshoots every frame and the prediction misses by 12 px on an orbit, 5 px with this.)
    Per component i, Q's entries (i, i), (i, i+6) = (i+6, i) and (i+6, i+6); the rest of the
    12x12 matrix is zero."""
    dt = max(dt, 1e-4)
    q3, q2 = dt**3 / 3, dt**2 / 2
    return [q3 * a for a in accel_var], [q2 * a for a in accel_var], [dt * a for a in accel_var]


def _matmul3(A: list[list[float]], B: list[list[float]]) -> list[list[float]]:
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = B
    return [
        [
            a0 * b00 + a1 * b10 + a2 * b20,
            a0 * b01 + a1 * b11 + a2 * b21,
            a0 * b02 + a1 * b12 + a2 * b22,
        ]
        for a0, a1, a2 in A
    ]


def _matmul3_t(A: list[list[float]], B: list[list[float]]) -> list[list[float]]:
    """``A @ B.T``: the products of A's rows with B's rows (unrolled: x0.4-0.55 of the
    nested comprehension's 1.4-3.1 us)."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = A
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = B
    return [
        [a00 * b00 + a01 * b01 + a02 * b02, a00 * b10 + a01 * b11 + a02 * b12,
         a00 * b20 + a01 * b21 + a02 * b22],
        [a10 * b00 + a11 * b01 + a12 * b02, a10 * b10 + a11 * b11 + a12 * b12,
         a10 * b20 + a11 * b21 + a12 * b22],
        [a20 * b00 + a21 * b01 + a22 * b02, a20 * b10 + a21 * b11 + a22 * b12,
         a20 * b20 + a21 * b21 + a22 * b22],
    ]  # fmt: skip


def _matvec3(A: list[list[float]], v: list[float]) -> list[float]:
    return [a[0] * v[0] + a[1] * v[1] + a[2] * v[2] for a in A]


class Se3PoseFilter:
    """Constant-velocity Kalman filter on SE(3) (pose and body-frame twist).

    ``accel_noise`` (scene scales / s^2) and ``angular_accel_noise`` (rad / s^2) are the white
    accelerations the model allows; ``position_noise`` (scene scales) and ``orientation_noise``
    (rad) the measurement noise of a pose; ``scale`` the scene scale in map units.

    The linear filter is a Kalman filter on ``x = [delta, xi]`` with ``F = [[I, dt I],
    [0, I]]``, ``H = [I, 0]``, a diagonal ``R`` and the process noise of ``_process_noise``;
    ``delta`` is folded into the pose after every step, so it is 0 when a step starts. F, Q, R
    and the initial covariance couple twist component i only with i + 6: the 12x12 covariance
    is six independent 2x2 blocks ``[[a, b], [bl, c]]`` (``P[i, i]``, ``P[i, i+6]``,
    ``P[i+6, i]``, ``P[i+6, i+6]``), and the filter is six scalar filters, written here in
    Python floats with the generic filter's arithmetic per entry (filterpy's operations,
    Joseph-form update; ``tests/test_motion.py``: the same covariances, twists and poses as
    the generic ``kalman.KalmanFilter`` to 1e-12). The 12x12 numpy filter spent its time in
    the dozens of small numpy calls a frame, not in arithmetic (x0.2 CPU).
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
        self.accel_var = [(accel_noise * scale) ** 2] * 3 + [angular_accel_noise**2] * 3
        self.meas_var = [(position_noise * scale) ** 2] * 3 + [orientation_noise**2] * 3
        # the covariance's 2x2 blocks, per twist component (see the class docstring)
        self._a, self._b, self._bl, self._c = [1.0] * 6, [0.0] * 6, [0.0] * 6, [1.0] * 6
        self._xi = [0.0] * 6  # the body-frame twist [v, w]
        self._R = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]  # cam_from_world
        self._t = [0.0, 0.0, 0.0]
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
        self._R = cam_from_world.rotation.tolist()
        self._t = cam_from_world.translation.tolist()
        self._xi = xi.tolist()
        self._a = list(self.meas_var)
        self._b, self._bl = [0.0] * 6, [0.0] * 6
        self._c = [self.scale**2] * 3 + [1.0] * 3
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
            q3, q2, q1 = _process_noise(dt, self.accel_var)
            a, b, bl, c = self._a, self._b, self._bl, self._c
            for i in range(6):
                # F P F' + Q of the block: F P = [[a + dt bl, b + dt c], [bl, c]]
                bli, ci = bl[i], c[i]
                top = b[i] + dt * ci
                a[i] = a[i] + dt * bli + dt * top + q3[i]
                b[i] = top + q2[i]
                bl[i] = bli + dt * ci + q2[i]
                c[i] = ci + q1[i]
            self._fold([dt * v for v in self._xi])  # delta = dt xi (delta was 0)
            self.stamp = stamp
        return self.current()

    def update(self, cam_from_world: Rigid3d) -> Rigid3d:
        """Fuse a measured pose; return the filtered ``cam_from_world``."""
        assert self.stamp is not None, "update() before reset()"
        # z = log(cam_from_world T^-1), T^-1 = (R', -R' t); y = z - H x = z (delta is 0)
        Rm, R, t = cam_from_world.rotation.tolist(), self._R, self._t
        Rz = _matmul3_t(Rm, R)
        Rt_t = [R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2] for j in range(3)]  # R' t
        u = _matvec3(Rm, [-v for v in Rt_t])
        tm = cam_from_world.translation.tolist()
        z = _log(Rz, [u[0] + tm[0], u[1] + tm[1], u[2] + tm[2]])
        a, b, bl, c, r, xi = self._a, self._b, self._bl, self._c, self.meas_var, self._xi
        delta = [0.0] * 6
        for i in range(6):
            # (each entry read once into a local: the list indexing was a third of the loop)
            ai, bi, bli, ci, ri, zi = a[i], b[i], bl[i], c[i], r[i], z[i]
            s_inv = 1.0 / (ai + ri)  # S = H P H' + R is diagonal
            k1, k2 = ai * s_inv, bli * s_inv  # K = P H' S^-1: K[i, i], K[i+6, i]
            delta[i] = k1 * zi
            xi[i] = xi[i] + k2 * zi
            # Joseph form: (I - K H) P (I - K H)' + K R K', I - K H = [[1 - k1, 0], [-k2, 1]]
            m = 1.0 - k1
            p00, p01 = m * ai, m * bi
            p10, p11 = -k2 * ai + bli, -k2 * bi + ci
            k1r, k2r = k1 * ri, k2 * ri
            a[i] = p00 * m + k1r * k1
            b[i] = p00 * -k2 + p01 + k1r * k2
            bl[i] = p10 * m + k2r * k1
            c[i] = p10 * -k2 + p11 + k2r * k2
        self._fold(delta)
        # one pose for both (poses are not changed in place: Rigid3d's operations make new ones)
        filtered = self.current()
        self.last = (filtered, self.stamp)
        return filtered

    def _fold(self, delta: list[float]) -> None:
        # Move the error into the pose: the linear state stays near zero, the pose on SE(3).
        if any(delta):
            E, te = _exp(delta)
            t = _matvec3(E, self._t)
            self._R = _matmul3(E, self._R)
            self._t = [t[0] + te[0], t[1] + te[1], t[2] + te[2]]

    def current(self) -> Rigid3d:
        """The filter's present ``cam_from_world`` (predicted or filtered)."""
        return Rigid3d(np.array(self._R), np.array(self._t))

    @property
    def T(self) -> Rigid3d:
        """The present ``cam_from_world`` (``current``)."""
        return self.current()

    @property
    def P(self) -> np.ndarray:
        """The 12x12 covariance of ``[delta, xi]`` (built from its blocks)."""
        P = np.zeros((12, 12))
        i = np.arange(6)
        P[i, i], P[i, i + 6], P[i + 6, i], P[i + 6, i + 6] = self._a, self._b, self._bl, self._c
        return P

    @property
    def twist(self) -> np.ndarray:
        """Body-frame velocity ``[v, w]`` of ``cam_from_world`` (map units / s, rad / s)."""
        return np.array(self._xi)

    @property
    def velocity(self) -> np.ndarray:
        """The camera centre's velocity in the world frame (map units / s)."""
        return -np.array(self._R).T @ self._xi[:3]

    @property
    def angular_velocity(self) -> np.ndarray:
        """The angular velocity of ``world_from_cam`` in the world frame (rad / s)."""
        return -np.array(self._R).T @ self._xi[3:]


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
