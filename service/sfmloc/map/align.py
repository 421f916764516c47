"""Maps in the user's frame: a similarity ``target_from_map`` applied to a whole bundle.

An images-only map has an arbitrary frame and scale. Given correspondences (image names with
known camera positions, or 3D points in both frames) the least-squares similarity is Umeyama's
(``transforms.align_umeyama``); with a known up direction (gravity) the rotation is constrained
to take the map's up onto the target's up, leaving a rotation about that axis, a scale and a
translation (at least 2 correspondences instead of 3). With an up direction alone the map is
only rotated (scale 1, no translation).

Applying ``x' = s R x + t`` to a bundle: points ``s R x + t``; each ``cam_from_world`` (R_c,
t_c) becomes ``(R_c R^T, s t_c - R_c R^T t)`` (the camera frame scales with the world, so
projections are unchanged); descriptors, index, clusters and cameras are untouched, and
``scene_scale`` (median depth, computed at load) scales by ``s``. The result is a new bundle
(new build id) written atomically: on any failure the old one stays as it was.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.poses import name_stem
from ..transforms import Rigid3d, align_umeyama, quat_wxyz_from_rotmat
from .bundle import ARRAY_SPECS, MapBundle, MapData, write_bundle

# Correspondences closer than this fraction of their spread are one point for the fit.
_DEGENERATE_REL = 1e-9


@dataclass(frozen=True)
class Sim3:
    """A similarity ``tgt_from_src``: ``x_tgt = scale * rotation @ x_src + translation``."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        return self.scale * p @ self.rotation.T + self.translation

    def transform_cam_from_world(self, cam_from_world: Rigid3d) -> Rigid3d:
        """The camera's ``cam_from_world`` in the target frame (camera units scale with it)."""
        R = cam_from_world.rotation @ self.rotation.T
        return Rigid3d(R, self.scale * cam_from_world.translation - R @ self.translation)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scale": float(self.scale),
            "quat_wxyz": [float(v) for v in quat_wxyz_from_rotmat(self.rotation)],
            "translation": [float(v) for v in self.translation],
        }


@dataclass
class Correspondences:
    """Map-frame points and where they belong in the target frame; ``labels`` name them."""

    src: np.ndarray  # (N, 3) in the map
    dst: np.ndarray  # (N, 3) in the target frame
    labels: list[str] = field(default_factory=list)


def _floats(parts: Sequence[str], path: Path, lineno: int) -> list[float]:
    try:
        vals = [float(v) for v in parts]
    except ValueError:
        raise InputError(f"{path}:{lineno}: expected numbers, got {' '.join(parts)!r}") from None
    if not all(np.isfinite(vals)):
        raise InputError(f"{path}:{lineno}: non-finite number in {' '.join(parts)!r}")
    return vals


def read_positions(path: str | Path) -> dict[str, np.ndarray]:
    """``name x y z`` lines (camera centres in the target frame), keyed by ``name_stem``.

    Blank lines and ``#`` comments are skipped; a name given twice is an error."""
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    for lineno, parts in _rows(path):
        if len(parts) != 4:
            raise InputError(
                f"{path}:{lineno}: expected 'name x y z' (a camera position), got {len(parts)} "
                "fields"
            )
        key = name_stem(parts[0])
        if key in out:
            raise InputError(f"{path}:{lineno}: image {parts[0]!r} given twice")
        out[key] = np.array(_floats(parts[1:], path, lineno))
    if not out:
        raise InputError(f"{path}: no positions ('name x y z' lines)")
    return out


def read_point_pairs(path: str | Path) -> Correspondences:
    """``x y z X Y Z`` lines: a point in map coordinates and the same point in the target's."""
    path = Path(path)
    src, dst, labels = [], [], []
    for lineno, parts in _rows(path):
        if len(parts) != 6:
            raise InputError(
                f"{path}:{lineno}: expected 'x y z X Y Z' (map point, target point), got "
                f"{len(parts)} fields"
            )
        v = _floats(parts, path, lineno)
        src.append(v[:3])
        dst.append(v[3:])
        labels.append(f"{path.name}:{lineno}")
    if not src:
        raise InputError(f"{path}: no point pairs ('x y z X Y Z' lines)")
    return Correspondences(np.array(src), np.array(dst), labels)


def _rows(path: Path):
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if line:
            yield lineno, line.split()


def image_centers(bundle: MapBundle) -> dict[str, np.ndarray]:
    """Camera centres of the map's images in map coordinates, keyed by ``name_stem``."""
    return {
        name_stem(n): bundle.image_cam_from_world[i].center
        for i, n in enumerate(bundle.image_names)
    }


def match_positions(
    centers: Mapping[str, np.ndarray], positions: Mapping[str, np.ndarray], what: str = "positions"
) -> Correspondences:
    """Pairs (map centre, known position) for the named images; unknown names are an error."""
    missing = [k for k in positions if k not in centers]
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise InputError(
            f"{len(missing)} image(s) of the {what} are not in the map: {shown} (names are matched "
            "by file stem, e.g. frame-000020.color)"
        )
    keys = sorted(positions)
    return Correspondences(
        np.array([centers[k] for k in keys]).reshape(-1, 3),
        np.array([positions[k] for k in keys]).reshape(-1, 3),
        keys,
    )


def _unit(v: Sequence[float] | np.ndarray, what: str) -> np.ndarray:
    u = np.asarray(v, dtype=np.float64).reshape(-1)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-12:
        raise InputError(f"{what} must be a non-zero 3-vector, got {list(np.ravel(v))}")
    return u / np.linalg.norm(u)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: half a turn about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def cameras_up(bundle: MapBundle) -> np.ndarray:
    """The mean "up" of the map's cameras (their -y axis in the world, unit): gravity's opposite
    for cameras held roughly level (robots, handheld video), a guess for anything else."""
    ups = np.array([-T.rotation[1] for T in bundle.image_cam_from_world])
    return _unit(ups.mean(0), "the cameras' mean up direction")


def estimate_sim3(
    corr: Correspondences,
    *,
    up_map: Sequence[float] | np.ndarray | None = None,
    up_target: Sequence[float] | np.ndarray = (0.0, 0.0, 1.0),
    with_scale: bool = True,
) -> Sim3:
    """The least-squares similarity taking ``corr.src`` onto ``corr.dst``.

    With ``up_map`` the rotation takes it onto ``up_target`` exactly (the remaining rotation
    about that axis, scale and translation are least squares). ``InputError`` when the
    correspondences cannot fix the transform (too few, coincident, collinear without up)."""
    src, dst = np.asarray(corr.src, np.float64), np.asarray(corr.dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise InputError(f"correspondences must be (N, 3) pairs, got {src.shape} and {dst.shape}")
    n_min = 2 if up_map is not None else 3
    if len(src) < n_min:
        raise InputError(
            f"{len(src)} correspondence(s): a similarity needs at least {n_min}"
            + (" (2 with an up direction)" if up_map is None else "")
        )
    a, b = src - src.mean(0), dst - dst.mean(0)
    spread_a = float(np.sqrt((a**2).sum(1).max()))
    spread_b = float(np.sqrt((b**2).sum(1).max()))
    if spread_a <= _DEGENERATE_REL * max(1.0, float(np.abs(src).max())) or spread_b <= 0:
        raise InputError("the correspondences coincide: they cannot fix a scale or rotation")
    if up_map is None:
        sv = np.linalg.svd(a, compute_uv=False)
        if sv[1] <= 1e-6 * sv[0]:
            raise InputError(
                "the correspondences are collinear: the rotation about their line is not fixed "
                "(add a point off the line, or give an up direction)"
            )
        s, R, t = align_umeyama(src, dst, with_scale=with_scale)
        return Sim3(s, R, t)
    u_src = _unit(up_map, "the map's up direction")
    u_dst = _unit(up_target, "the target's up direction")
    R0 = rotation_between(u_src, u_dst)
    a0 = a @ R0.T
    # The rest is a rotation about u_dst: a 2D Procrustes in the plane perpendicular to it.
    e1 = np.cross(u_dst, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(u_dst, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u_dst, e1)
    pa = np.stack([a0 @ e1, a0 @ e2], 1)
    pb = np.stack([b @ e1, b @ e2], 1)
    cross = float(np.sum(pa[:, 0] * pb[:, 1] - pa[:, 1] * pb[:, 0]))
    dot = float(np.sum(pa * pb))
    if abs(cross) + abs(dot) <= 1e-12 * float((pa**2).sum() + (pb**2).sum()):
        raise InputError(
            "the correspondences lie along the up direction: the rotation about it is not fixed"
        )
    theta = np.arctan2(cross, dot)
    Rz = (
        np.cos(theta) * np.eye(3)
        + np.sin(theta) * _skew(u_dst)
        + (1 - np.cos(theta)) * np.outer(u_dst, u_dst)
    )
    R = Rz @ R0
    Ra = a @ R.T
    s = float(np.sum(b * Ra) / np.sum(a**2)) if with_scale else 1.0
    if s <= 0:
        raise InputError(
            "the fitted scale is not positive: the correspondences contradict the up direction"
        )
    return Sim3(s, R, dst.mean(0) - s * R @ src.mean(0))


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=np.float64)


def up_only(up_map: Sequence[float] | np.ndarray, up_target: Sequence[float] | np.ndarray) -> Sim3:
    """A rotation taking the map's up onto the target's (scale 1, no translation)."""
    R = rotation_between(_unit(up_map, "the map's up direction"), _unit(up_target, "up target"))
    return Sim3(1.0, R, np.zeros(3))


def residuals(sim: Sim3, corr: Correspondences) -> np.ndarray:
    """Distances (target units) between the transformed map points and their targets."""
    if len(corr.src) == 0:
        return np.zeros(0)
    return np.linalg.norm(sim.apply(corr.src) - corr.dst, axis=1)


def aligned_data(bundle: MapBundle, sim: Sim3) -> MapData:
    """The bundle's arrays with ``sim`` applied (everything else shared, unchanged)."""
    if not (np.isfinite(sim.scale) and sim.scale > 0):
        raise InputError(f"the similarity's scale must be positive, got {sim.scale}")
    arrays = {name: bundle.array(name) for name in ARRAY_SPECS}
    arrays["points_xyz"] = sim.apply(np.asarray(arrays["points_xyz"]))
    poses = np.empty((bundle.n_images, 7))
    for i, T in enumerate(bundle.image_cam_from_world):
        T2 = sim.transform_cam_from_world(T)
        poses[i, :4] = T2.quat_wxyz
        poses[i, 4:] = T2.translation
    arrays["image_cam_from_world"] = poses
    return MapData(
        **arrays,
        cameras=list(bundle.cameras),
        image_names=list(bundle.image_names),
        keypoint_scales=dict(bundle.keypoint_scales),
    )


def write_aligned(
    bundle: MapBundle,
    sim: Sim3,
    out_dir: str | Path,
    name: str,
    *,
    record: dict[str, Any] | None = None,
) -> Path:
    """Write ``bundle`` transformed by ``sim`` as ``out_dir/name`` (atomic, new build id).

    The manifest keeps the source, parameters and report (coverage does not change under a
    similarity) and adds ``source["alignments"]``: each alignment applied, with ``record``."""
    m = bundle.manifest
    source = dict(m.source)
    entry = {
        "target_from_map": sim.to_dict(),
        "from_build_id": m.build_id,
        "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **(record or {}),
    }
    source["alignments"] = [*source.get("alignments", []), entry]
    return write_bundle(
        aligned_data(bundle, sim),
        out_dir,
        name,
        source=source,
        params=dict(m.params),
        timings_s=dict(m.timings_s),
        index_info=dict(m.index),
        report=dict(m.report),
    )
