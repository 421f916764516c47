"""Writing received poses as a TUM trajectory: ``timestamp tx ty tz qx qy qz qw``
(``world_from_cam``: the camera's position and orientation in the map), one line per localized
frame, timestamps in seconds from the frames' ``stamp_ns``.

Beside it, ``FILE.cov`` (the TUM file stays plain TUM for every tool that reads it) holds one
line per pose line: ``timestamp status c00 c01 ... c55``, the status and the 6x6 covariance of
the raw pose, row-major, in the wire format's order (rotation vector on the world side in
radians, then camera centre in map units; see ``wire.py``). ``nan`` when the server sent none.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TextIO

from .wire import PoseMessage

COVARIANCE_HEADER = (
    "# timestamp status c00 c01 ... c55: 6x6 covariance of the pose on the same line of the TUM "
    "file (row-major; order rx ry rz cx cy cz: r a small rotation vector in radians on the world "
    "side of world_from_cam's rotation, c the camera centre in world coordinates, map units)"
)


def covariance_path(tum_path: str | Path) -> Path:
    """The covariance side file of a TUM trajectory: ``FILE.cov`` beside ``FILE``."""
    p = Path(tum_path)
    return p.with_name(p.name + ".cov")


class TumWriter:
    def __init__(self, path: str | Path, *, filtered: bool = False) -> None:
        self.path = Path(path)
        self.filtered = filtered
        self.count = 0
        self.cov_path = covariance_path(self.path)
        self._f: TextIO = open(self.path, "w")  # noqa: SIM115 - closed in close()
        self._f.write("# timestamp tx ty tz qx qy qz qw (world_from_cam)\n")
        self._cov: TextIO = open(self.cov_path, "w")  # noqa: SIM115 - closed in close()
        self._cov.write(COVARIANCE_HEADER + "\n")

    def write(self, pose: PoseMessage) -> bool:
        """Append ``pose`` if it is localized; returns whether a line was written."""
        T = pose.filtered_world_from_cam if self.filtered else pose.world_from_cam
        if not pose.localized or T is None:
            return False
        vals = [*T.t, *T.quat_xyzw]
        stamp = f"{pose.stamp_ns / 1e9:.9f}"
        self._f.write(f"{stamp} " + " ".join(f"{v:.9f}" for v in vals) + "\n")
        cov = pose.covariance if pose.covariance is not None else (float("nan"),) * 36
        self._cov.write(f"{stamp} {pose.status} " + " ".join(f"{v:.6e}" for v in cov) + "\n")
        self.count += 1
        return True

    def close(self) -> None:
        self._f.close()
        self._cov.close()

    def __enter__(self) -> TumWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


FRAMES_HEADER = (
    "# seq timestamp status inliers matching error c00 c01 ... c55: every answered frame, LOST "
    "ones too (error: the error code, '-' when none; covariance as in FILE.cov, nan without a "
    "pose)"
)


def frames_path(tum_path: str | Path) -> Path:
    """The per-frame side file of a TUM trajectory: ``FILE.frames`` beside ``FILE``."""
    p = Path(tum_path)
    return p.with_name(p.name + ".frames")


class FramesWriter:
    """One line per answered frame, LOST and refused ones included (the TUM file has only
    poses): ``seq timestamp status inliers matching error c00 ... c55``."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.count = 0
        self._f: TextIO = open(self.path, "w")  # noqa: SIM115 - closed in close()
        self._f.write(FRAMES_HEADER + "\n")

    def write(self, pose: PoseMessage) -> None:
        cov = pose.covariance if pose.covariance is not None else (float("nan"),) * 36
        seq = "-" if pose.seq is None else str(pose.seq)
        err = pose.error.code if pose.error is not None else "-"
        self._f.write(
            f"{seq} {pose.stamp_ns / 1e9:.9f} {pose.status} {pose.inliers} {pose.matching} {err} "
            + " ".join(f"{v:.6e}" for v in cov)
            + "\n"
        )
        self.count += 1

    def close(self) -> None:
        self._f.close()
