"""Trajectory plots (PNG) for `sfmloc replay --plot` and `sfmloc stream --plot` (not a command).

The figure is the bench's top view (``bench.figures.trajectory``): ground truth as a line, the
estimates as dots, frames without a pose where ground truth has one as crosses, the map's points
behind. matplotlib comes with the ``bench`` extra (``pip install 'sfmloc[bench]'``); its absence
is reported before any work starts.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from ..errors import InputError


def check_plot_path(path: str | Path, flag: str = "--plot") -> None:
    """Fail early, before a long replay or stream, when the plot cannot be drawn."""
    parent = Path(path).parent
    if not parent.is_dir():
        raise InputError(f"{flag} {path}: folder {parent} does not exist")
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise InputError(
            f"{flag} needs matplotlib, which is not installed: pip install 'sfmloc[bench]' "
            "(or pip install matplotlib)"
        ) from None


def check_plot_args(plot: str | None, groundtruth: str | None) -> None:
    """`sfmloc stream`'s --plot and --groundtruth, checked before the stream starts."""
    if plot:
        check_plot_path(plot)
    if groundtruth:
        if not plot:
            raise InputError("--groundtruth is for --plot: give --plot FILE.png too")
        from ..io.poses import read_poses

        read_poses(groundtruth)  # a bad file fails now, not after the stream


def write_plot(records: list, path: str | Path, title: str, points_xyz: Any = None) -> Path:
    """Draw ``records`` (``eval.metrics.FrameRecord``; ground truth where they carry it)."""
    from ..bench import figures

    check_plot_path(path)
    return figures.trajectory(records, title, Path(path), points_xyz)


class StreamRecorder:
    """What `sfmloc stream` sent and got back, as replay-style records for the plot: answered
    frames by their seq (the source's frame index, in order), matched to ground truth by file
    name or by timestamp (the source's own, else index / fps) like `sfmloc replay`. Frames the
    server skipped as stale have no status and are left out (LOST frames are answered)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sent: dict[int, tuple[str, float | None]] = {}
        self._poses: dict[int, Any] = {}

    def sent(self, seq: int, frame: Any) -> None:
        stamp_ns = getattr(frame, "stamp_ns", None)
        with self._lock:
            self._sent[seq] = (
                str(getattr(frame, "name", "") or ""),
                None if stamp_ns is None else stamp_ns / 1e9,
            )

    def pose(self, p: Any) -> None:
        if p.seq is None:
            return
        with self._lock:
            self._poses[p.seq] = p

    def records(self, groundtruth: str | None, fps: float) -> list:
        from ..eval.groundtruth import load_groundtruth
        from ..eval.metrics import FrameRecord, attach_errors
        from ..transforms import Rigid3d

        with self._lock:
            seqs = sorted(self._sent)
            sent = dict(self._sent)
            poses = dict(self._poses)
        names = [sent[s][0] or f"{s:06d}" for s in seqs]
        stamps = [stamp if (stamp := sent[s][1]) is not None else s / fps for s in seqs]
        gt = load_groundtruth(groundtruth, names, stamps, fps) if groundtruth else None
        out = []
        for i, s in enumerate(seqs):
            p = poses.get(s)
            if p is None:  # dropped by the server as stale (counted in the summary): no status
                continue
            est = None
            if p is not None and p.localized and p.cam_from_world is not None:
                est = Rigid3d.from_quat_xyzw(p.cam_from_world.quat_xyzw, p.cam_from_world.t)
            counts = p.counts
            rec = FrameRecord(
                index=s,
                name=names[i],
                stamp=stamps[i],
                status=p.status,
                matching=p.matching,
                latency_ms=p.latency_ms,
                inliers=p.inliers,
                detected=int(counts.get("detected", 0)),
                tracked=int(counts.get("tracked", 0)),
                tracked_3d=int(counts.get("tracked_3d", 0)),
            )
            attach_errors(rec, est, gt[i] if gt is not None else None)
            out.append(rec)
        return out
