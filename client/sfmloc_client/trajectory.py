"""Writing received poses as a TUM trajectory: ``timestamp tx ty tz qx qy qz qw``
(``world_from_cam``: the camera's position and orientation in the map), one line per localized
frame, timestamps in seconds from the frames' ``stamp_ns``."""

from __future__ import annotations

from pathlib import Path
from typing import Any, TextIO

from .wire import PoseMessage


class TumWriter:
    def __init__(self, path: str | Path, *, filtered: bool = False) -> None:
        self.path = Path(path)
        self.filtered = filtered
        self.count = 0
        self._f: TextIO = open(self.path, "w")  # noqa: SIM115 - closed in close()
        self._f.write("# timestamp tx ty tz qx qy qz qw (world_from_cam)\n")

    def write(self, pose: PoseMessage) -> bool:
        """Append ``pose`` if it is localized; returns whether a line was written."""
        T = pose.filtered_world_from_cam if self.filtered else pose.world_from_cam
        if not pose.localized or T is None:
            return False
        vals = [*T.t, *T.quat_xyzw]
        self._f.write(f"{pose.stamp_ns / 1e9:.9f} " + " ".join(f"{v:.9f}" for v in vals) + "\n")
        self.count += 1
        return True

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "TumWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
