"""Rigid transforms and rotation conventions.

Names follow pycolmap: a transform ``tgt_from_src`` maps points in frame ``src`` into frame
``tgt``: ``x_tgt = R @ x_src + t``. ``cam_from_world`` is what COLMAP stores per image (and
what the ``images.txt`` ``qw qx qy qz tx ty tz`` line means); ``world_from_cam`` is the camera
pose in the world (TUM files, trajectories). Quaternion element order is always in the name:
``quat_wxyz`` (COLMAP files) or ``quat_xyzw`` (TUM files, scipy, our wire format). Quaternions
are returned normalized with a non-negative scalar part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _normalize_quat(q: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"not a rotation quaternion: {q!r}")
    return q / n


def rotmat_from_quat_wxyz(quat_wxyz: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix from a (not necessarily unit) quaternion ``[w, x, y, z]``."""
    w, x, y, z = _normalize_quat(np.asarray(quat_wxyz, dtype=np.float64))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_from_quat_xyzw(quat_xyzw: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix from ``[x, y, z, w]``."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    return rotmat_from_quat_wxyz(np.array([q[3], q[0], q[1], q[2]]))


def quat_wxyz_from_rotmat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` with ``w >= 0`` from a rotation matrix
    (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q = _normalize_quat(q)
    return -q if q[0] < 0 else q


def quat_xyzw_from_rotmat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[x, y, z, w]`` with ``w >= 0`` from a rotation matrix."""
    w, x, y, z = quat_wxyz_from_rotmat(R)
    return np.array([x, y, z, w])


def rotmat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrix from an axis-angle vector (radians)."""
    r = np.asarray(rotvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        K = _skew(r)
        return np.eye(3) + K
    k = r / theta
    K = _skew(k)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)


def rotvec_from_rotmat(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (radians) of a rotation matrix."""
    w, x, y, z = quat_wxyz_from_rotmat(R)
    v = np.array([x, y, z])
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return 2.0 * v
    return v / s * 2.0 * np.arctan2(s, w)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=np.float64)


def rotation_angle_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """The angle metric of the paper: the angle of ``R1 @ R2.T``, in degrees."""
    c = (np.trace(np.asarray(R1) @ np.asarray(R2).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@dataclass(frozen=True)
class Rigid3d:
    """A rigid transform ``tgt_from_src``: ``x_tgt = rotation @ x_src + translation``.

    The variable name carries the frames (``cam_from_world``, ``world_from_cam``); the type
    does not, so keep the names honest.
    """

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        R = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        t = np.asarray(self.translation, dtype=np.float64).reshape(3)
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "translation", t)

    @classmethod
    def identity(cls) -> "Rigid3d":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_quat_wxyz(cls, quat_wxyz: np.ndarray, translation: np.ndarray) -> "Rigid3d":
        return cls(rotmat_from_quat_wxyz(quat_wxyz), translation)

    @classmethod
    def from_quat_xyzw(cls, quat_xyzw: np.ndarray, translation: np.ndarray) -> "Rigid3d":
        return cls(rotmat_from_quat_xyzw(quat_xyzw), translation)

    @classmethod
    def from_rotvec(cls, rotvec: np.ndarray, translation: np.ndarray) -> "Rigid3d":
        return cls(rotmat_from_rotvec(rotvec), translation)

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> "Rigid3d":
        """From a 3x4 or 4x4 matrix ``[R | t]``."""
        T = np.asarray(T, dtype=np.float64)
        if T.shape not in ((3, 4), (4, 4)):
            raise ValueError(f"expected a 3x4 or 4x4 matrix, got shape {T.shape}")
        return cls(T[:3, :3], T[:3, 3])

    @property
    def quat_wxyz(self) -> np.ndarray:
        return quat_wxyz_from_rotmat(self.rotation)

    @property
    def quat_xyzw(self) -> np.ndarray:
        return quat_xyzw_from_rotmat(self.rotation)

    @property
    def rotvec(self) -> np.ndarray:
        return rotvec_from_rotmat(self.rotation)

    def matrix(self) -> np.ndarray:
        """The 3x4 matrix ``[R | t]``."""
        return np.hstack([self.rotation, self.translation[:, None]])

    def matrix4(self) -> np.ndarray:
        """The homogeneous 4x4 matrix."""
        T = np.eye(4)
        T[:3, :4] = self.matrix()
        return T

    def inverse(self) -> "Rigid3d":
        """``src_from_tgt`` of this ``tgt_from_src``."""
        Rt = self.rotation.T
        return Rigid3d(Rt, -Rt @ self.translation)

    def __mul__(self, other: "Rigid3d") -> "Rigid3d":
        """Composition: ``a_from_b * b_from_c -> a_from_c``."""
        return Rigid3d(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points of shape (3,) or (N, 3) from ``src`` into ``tgt``."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.rotation.T + self.translation

    @property
    def center(self) -> np.ndarray:
        """For a ``cam_from_world``: the camera center in world coordinates (``-R^T t``)."""
        return -self.rotation.T @ self.translation

    def is_finite(self) -> bool:
        return bool(np.all(np.isfinite(self.rotation)) and np.all(np.isfinite(self.translation)))

    def __repr__(self) -> str:
        q = np.round(self.quat_wxyz, 6).tolist()
        t = np.round(self.translation, 6).tolist()
        return f"Rigid3d(quat_wxyz={q}, t={t})"


def pose_errors(est_cam_from_world: Rigid3d, gt_cam_from_world: Rigid3d) -> tuple[float, float]:
    """(position error in map units, rotation error in degrees) between two ``cam_from_world``.

    Position error compares camera centers; rotation error is the paper's angle metric.
    """
    dpos = float(np.linalg.norm(est_cam_from_world.center - gt_cam_from_world.center))
    return dpos, rotation_angle_deg(est_cam_from_world.rotation, gt_cam_from_world.rotation)
