"""Rotation conventions shared by client, server and builder: quaternions and matrices.

A transform ``tgt_from_src`` maps points of frame ``src`` into frame ``tgt``:
``x_tgt = R @ x_src + t`` (pycolmap's naming: ``cam_from_world``, ``world_from_cam``).
Quaternion element order is always in the name: ``quat_wxyz`` (COLMAP files) or ``quat_xyzw``
(TUM files, scipy, our wire format). Quaternions are returned normalized with ``w >= 0``.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _normalize_quat(q: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"not a rotation quaternion: {q!r}")
    return q / n


def rotmat_from_quat_wxyz(quat_wxyz: Any) -> np.ndarray:
    """3x3 rotation matrix from a (not necessarily unit) quaternion ``[w, x, y, z]``."""
    w, x, y, z = _normalize_quat(np.asarray(quat_wxyz, dtype=np.float64))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_from_quat_xyzw(quat_xyzw: Any) -> np.ndarray:
    """3x3 rotation matrix from ``[x, y, z, w]``."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    return rotmat_from_quat_wxyz(np.array([q[3], q[0], q[1], q[2]]))


def quat_wxyz_from_rotmat(R: Any) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` with ``w >= 0`` from a rotation matrix (Shepperd)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array(
            [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
        )
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array(
            [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
        )
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array(
            [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
        )
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array(
            [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
        )
    q = _normalize_quat(q)
    return -q if q[0] < 0 else q


def quat_xyzw_from_rotmat(R: Any) -> np.ndarray:
    """Unit quaternion ``[x, y, z, w]`` with ``w >= 0`` from a rotation matrix."""
    w, x, y, z = quat_wxyz_from_rotmat(R)
    return np.array([x, y, z, w])
