"""Matching ground-truth poses to frames.

- COLMAP lists (``name qw qx qy qz tx ty tz [f]``) match by file name: the exact name, else the
  name's stem (``seq-01/frame-000001.color.png`` matches ``frame-000001.color.jpg``).
- TUM trajectories match by timestamp: the frame's timestamp (a numeric file stem, else
  index / fps) to the nearest ground-truth timestamp within half a frame period.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.poses import PoseList, name_stem, read_poses
from ..transforms import Rigid3d


def match_groundtruth(
    gt: PoseList, names: list[str], stamps: list[float], fps: float = 30.0
) -> list[Rigid3d | None]:
    """The ground-truth ``cam_from_world`` of each frame, or None where there is none."""
    if gt.format == "tum":
        ts = np.array([e.timestamp for e in gt.entries], dtype=np.float64)
        order = np.argsort(ts)
        ts = ts[order]
        poses = [gt.entries[i].cam_from_world for i in order]
        out: list[Rigid3d | None] = []
        tol = 0.5 / fps
        for s in stamps:
            j = int(np.searchsorted(ts, s))
            best = None
            for k in (j - 1, j):
                if (
                    0 <= k < len(ts)
                    and abs(ts[k] - s) <= tol
                    and (best is None or abs(ts[k] - s) < abs(ts[best] - s))
                ):
                    best = k
            out.append(None if best is None else poses[best])
        return out
    exact = gt.by_key()
    by_stem = gt.by_stem()
    return [exact.get(n, by_stem.get(name_stem(n))) for n in names]


def load_groundtruth(
    path: str | Path, names: list[str], stamps: list[float], fps: float = 30.0
) -> list[Rigid3d | None]:
    gt = read_poses(path)
    out = match_groundtruth(gt, names, stamps, fps)
    if not any(p is not None for p in out):
        raise InputError(
            f"ground truth {path} ({gt.format}, {len(gt)} poses) matches none of the {len(names)} "
            "frames "
            f"(first frame {names[0] if names else '-'}): check names/timestamps and --fps"
        )
    return out
