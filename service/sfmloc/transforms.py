"""Rigid transforms (``Rigid3d``), rotation vectors and alignment.

The quaternion conventions and conversions are the contract shared with the client
(``sfmloc_client.rotations``, re-exported here). Names follow pycolmap: a transform
``tgt_from_src`` maps points in frame ``src`` into frame ``tgt``: ``x_tgt = R @ x_src + t``.
``cam_from_world`` is what COLMAP stores per image (and what the ``images.txt`` ``qw qx qy qz
tx ty tz`` line means); ``world_from_cam`` is the camera pose in the world (TUM files,
trajectories). Quaternion element order is always in the name: ``quat_wxyz`` (COLMAP files) or
``quat_xyzw`` (TUM files, scipy, our wire format). Quaternions are returned normalized with a
non-negative scalar part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sfmloc_client.rotations import (
    quat_wxyz_from_rotmat,
    quat_xyzw_from_rotmat,
    rotmat_from_quat_wxyz,
    rotmat_from_quat_xyzw,
)

__all__ = [
    "Rigid3d",
    "align_umeyama",
    "pose_errors",
    "quat_wxyz_from_rotmat",
    "quat_xyzw_from_rotmat",
    "rotation_angle_deg",
    "rotmat_from_quat_wxyz",
    "rotmat_from_quat_xyzw",
    "rotmat_from_rotvec",
    "rotvec_from_rotmat",
]


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
    c = ((np.asarray(R1) @ np.asarray(R2).T).trace() - 1.0) / 2.0
    # (min/max: np.clip's dispatch on a scalar cost more than the rest; a few calls a frame)
    return float(np.degrees(np.arccos(min(max(c, -1.0), 1.0))))


_F64 = np.dtype(np.float64)  # (float64 arrays' dtype is this object: tested by identity)


@dataclass(frozen=True)
class Rigid3d:
    """A rigid transform ``tgt_from_src``: ``x_tgt = rotation @ x_src + translation``.

    The variable name carries the frames (``cam_from_world``, ``world_from_cam``); the type
    does not, so keep the names honest.
    """

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        # Arrays already float64 of the right shape (the engine's own: ~5 constructions a
        # tracked frame) are kept as they are; asarray + reshape made a new view of each, 2 of
        # a construction's ~4.3 us (issue 10). Anything else is converted as before: the same
        # arrays, and the same errors for a wrong size or type.
        R, t = self.rotation, self.translation
        if not (type(R) is np.ndarray and R.dtype is _F64 and R.shape == (3, 3)):
            object.__setattr__(self, "rotation", np.asarray(R, dtype=np.float64).reshape(3, 3))
        if not (type(t) is np.ndarray and t.dtype is _F64 and t.shape == (3,)):
            object.__setattr__(self, "translation", np.asarray(t, dtype=np.float64).reshape(3))

    @classmethod
    def identity(cls) -> Rigid3d:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_quat_wxyz(cls, quat_wxyz: np.ndarray, translation: np.ndarray) -> Rigid3d:
        return cls(rotmat_from_quat_wxyz(quat_wxyz), translation)

    @classmethod
    def from_quat_xyzw(cls, quat_xyzw: np.ndarray, translation: np.ndarray) -> Rigid3d:
        return cls(rotmat_from_quat_xyzw(quat_xyzw), translation)

    @classmethod
    def from_rotvec(cls, rotvec: np.ndarray, translation: np.ndarray) -> Rigid3d:
        return cls(rotmat_from_rotvec(rotvec), translation)

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> Rigid3d:
        """From a 3x4 or 4x4 matrix ``[R | t]``."""
        T = np.asarray(T, dtype=np.float64)
        if T.shape not in ((3, 4), (4, 4)):
            raise ValueError(f"expected a 3x4 or 4x4 matrix, got shape {T.shape}")
        return cls(T[:3, :3], T[:3, 3])

    @classmethod
    def from_transform(cls, transform: Any) -> Rigid3d:
        """From the client's ``Transform`` (``quat_xyzw``, ``t``; a ``PoseMessage``'s poses),
        read by its fields, so the core does not load the wire format. The other way:
        ``Transform.from_matrix(rigid.matrix4())``."""
        return cls.from_quat_xyzw(np.asarray(transform.quat_xyzw), np.asarray(transform.t))

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

    def inverse(self) -> Rigid3d:
        """``src_from_tgt`` of this ``tgt_from_src``."""
        Rt = self.rotation.T
        return Rigid3d(Rt, -Rt @ self.translation)

    def __mul__(self, other: Rigid3d) -> Rigid3d:
        """Composition: ``a_from_b * b_from_c -> a_from_c``."""
        return Rigid3d(
            self.rotation @ other.rotation, self.rotation @ other.translation + self.translation
        )

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points of shape (3,) or (N, 3) from ``src`` into ``tgt``."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.rotation.T + self.translation

    @property
    def center(self) -> np.ndarray:
        """For a ``cam_from_world``: the camera center in world coordinates (``-R^T t``)."""
        return -self.rotation.T @ self.translation

    def is_finite(self) -> bool:
        # On its twelve numbers as Python floats (a float64 is finite exactly when its Python
        # float is): x0.3 of np.isfinite's four numpy calls (~4.8 us; issue 10). Two to three
        # calls a tracked frame (pose estimation's checks).
        isfinite = math.isfinite
        return all(map(isfinite, self.rotation.ravel().tolist())) and all(
            map(isfinite, self.translation.tolist())
        )

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


def align_umeyama(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = True
) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, t)`` minimizing ``sum ||dst - (s R src + t)||^2`` over points (N, 3)
    (Umeyama 1991); ``with_scale=False`` fixes ``s = 1`` (SE(3) alignment)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, D, Vt = np.linalg.svd(b.T @ a / len(src))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0  # a reflection is not a rotation
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / (a**2).sum(1).mean()) if with_scale else 1.0
    return s, R, mu_d - s * R @ mu_s
