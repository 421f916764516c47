"""Pose lists: TUM trajectories and COLMAP-style image lists.

- **TUM** (``timestamp tx ty tz qx qy qz qw``): ``world_from_cam``, quaternion ``xyzw``.
- **COLMAP list** (``name qw qx qy qz tx ty tz [extra...]``): ``cam_from_world``, quaternion
  ``wxyz``, as in COLMAP's ``images.txt`` header lines and the 7-Scenes pseudo ground truth
  (whose trailing focal length is ignored here).

Both read into ``PoseList``: ordered entries, each with a ``key`` (image name, or timestamp as
text) and a ``cam_from_world``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ModelFormatError
from ..transforms import Rigid3d


@dataclass
class PoseEntry:
    key: str
    cam_from_world: Rigid3d
    timestamp: float | None = None

    @property
    def world_from_cam(self) -> Rigid3d:
        return self.cam_from_world.inverse()

    @property
    def stamp(self) -> float:
        """The timestamp of a TUM entry (a COLMAP list's entries have none)."""
        if self.timestamp is None:
            raise ModelFormatError(f"pose {self.key!r} has no timestamp (not a TUM entry)")
        return self.timestamp


@dataclass
class PoseList:
    entries: list[PoseEntry] = field(default_factory=list)
    format: str = "colmap"

    def __len__(self) -> int:
        return len(self.entries)

    def __iter__(self):
        return iter(self.entries)

    def by_key(self) -> dict[str, Rigid3d]:
        return {e.key: e.cam_from_world for e in self.entries}

    def by_stem(self) -> dict[str, Rigid3d]:
        """Keyed by ``name_stem`` of the key, to match files whatever their folder or extension."""
        return {name_stem(e.key): e.cam_from_world for e in self.entries}


def name_stem(name: str) -> str:
    """``seq-01/frame-000001.color.png`` -> ``frame-000001.color``."""
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    return base.rsplit(".", 1)[0] if "." in base else base


def _lines(path: Path):
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelFormatError(f"cannot read pose file {path}: {exc}") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield lineno, s


def detect_pose_format(path: str | Path) -> str:
    """``"tum"`` when the first data line starts with a number and has 8 fields, else
    ``"colmap"``."""
    path = Path(path)
    for _, line in _lines(path):
        parts = line.split()
        try:
            float(parts[0])
            numeric_first = True
        except ValueError:
            numeric_first = False
        if numeric_first and len(parts) == 8:
            return "tum"
        if len(parts) >= 8:
            return "colmap"
        raise ModelFormatError(
            f"{path}: cannot tell the pose format from {line!r}; expected TUM "
            "'timestamp tx ty tz qx qy qz qw' or COLMAP 'name qw qx qy qz tx ty tz'"
        )
    raise ModelFormatError(f"{path}: no poses in file")


def read_poses(path: str | Path, fmt: str | None = None) -> PoseList:
    """Read a TUM or COLMAP-list pose file (format detected when ``fmt`` is None)."""
    path = Path(path)
    fmt = fmt or detect_pose_format(path)
    out = PoseList(format=fmt)
    for lineno, line in _lines(path):
        parts = line.split()
        try:
            if fmt == "tum":
                if len(parts) != 8:
                    raise ValueError(f"expected 8 fields, got {len(parts)}")
                ts = float(parts[0])
                t = np.array([float(v) for v in parts[1:4]])
                q_xyzw = np.array([float(v) for v in parts[4:8]])
                world_from_cam = Rigid3d.from_quat_xyzw(q_xyzw, t)
                out.entries.append(PoseEntry(parts[0], world_from_cam.inverse(), ts))
            elif fmt == "colmap":
                if len(parts) < 8:
                    raise ValueError(f"expected at least 8 fields, got {len(parts)}")
                q_wxyz = np.array([float(v) for v in parts[1:5]])
                t = np.array([float(v) for v in parts[5:8]])
                out.entries.append(PoseEntry(parts[0], Rigid3d.from_quat_wxyz(q_wxyz, t)))
            else:
                raise ModelFormatError(f"unknown pose format {fmt!r}")
        except ValueError as exc:
            raise ModelFormatError(f"{path}:{lineno}: malformed {fmt} pose line ({exc})") from None
    if not out.entries:
        raise ModelFormatError(f"{path}: no poses in file")
    return out


def format_tum_line(timestamp: float, world_from_cam: Rigid3d) -> str:
    t = world_from_cam.translation
    q = world_from_cam.quat_xyzw
    return f"{timestamp:.6f} " + " ".join(f"{v:.9f}" for v in (*t, *q))


def write_tum(path: str | Path, timestamps: list[float], world_from_cams: list[Rigid3d]) -> Path:
    """Write a TUM trajectory (``world_from_cam`` per timestamp)."""
    path = Path(path)
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw (world_from_cam)\n")
        for ts, T in zip(timestamps, world_from_cams):
            f.write(format_tum_line(ts, T) + "\n")
    return path


# The same text as sfmloc_client.trajectory.COVARIANCE_HEADER (a test compares them): the
# client package is not imported here (it pulls in the transports).
COVARIANCE_HEADER = (
    "# timestamp status c00 c01 ... c55: 6x6 covariance of the pose on the same line of the TUM "
    "file (row-major; order rx ry rz cx cy cz: r a small rotation vector in radians on the world "
    "side of world_from_cam's rotation, c the camera centre in world coordinates, map units)"
)


def write_tum_covariances(
    path: str | Path,
    timestamps: list[float],
    statuses: list[str],
    covariances: list[np.ndarray | None],
) -> Path:
    """The covariance side file of a TUM trajectory (``FILE.cov``; format and order as
    ``sfmloc_client.trajectory``): ``timestamp status c00 ... c55`` per pose line."""
    path = Path(path)
    with open(path, "w") as f:
        f.write(COVARIANCE_HEADER + "\n")
        for ts, st, C in zip(timestamps, statuses, covariances):
            vals = np.full(36, np.nan) if C is None else np.asarray(C, np.float64).ravel()
            f.write(
                f"{ts:.6f} {st} " + " ".join(f"{v:.6e}" for v in vals) + "\n"
            )  # as format_tum_line
    return path


def write_colmap_list(path: str | Path, names: list[str], cam_from_worlds: list[Rigid3d]) -> Path:
    """Write ``name qw qx qy qz tx ty tz`` lines (``cam_from_world``)."""
    path = Path(path)
    with open(path, "w") as f:
        f.write("# name qw qx qy qz tx ty tz (cam_from_world)\n")
        for name, T in zip(names, cam_from_worlds):
            f.write(
                name + " " + " ".join(f"{v:.9f}" for v in (*T.quat_wxyz, *T.translation)) + "\n"
            )
    return path
