"""Running a single-image localizer over chosen frames of a sequence, timed like our engine.

Both peers (``global-every-frame``: our own ``sfmloc.engine.relocalize`` on every frame, no
tracking; ``pycolmap-sift``: ``sift_peer.SiftLocalizer``) produce the same ``FrameRecord``s as
``sfmloc.eval.replay`` so one summary, one ATE and one set of figures serve all three. A frame's
time is that of the call on the decoded frame (decoding excluded, as for our engine), wall
clock (``latency_ms``) and the process's CPU time (``cpu_ms``); OpenCV, BLAS and faiss
run on one thread. One untimed warm-up call precedes the timed frames (lazy initialisation is
not a per-frame cost; our engine gets no such warm-up: its first frame is a global matching).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ..engine.types import Matching, Status
from ..errors import ImageDecodeError
from ..eval.metrics import FrameRecord, attach_errors
from ..io.frames import FrameSource
from ..transforms import Rigid3d

log = logging.getLogger(__name__)


@dataclass
class PeerOutput:
    """What a peer returns for one frame."""

    cam_from_world: Rigid3d | None
    inliers: int = 0
    detected: int = 0  # keypoints of the frame
    matches: int = 0  # 2D-3D matches handed to the pose solver
    timings_ms: dict[str, float] | None = None


PeerFn = Callable[[np.ndarray], PeerOutput]


def decode_frames(
    source: FrameSource, indices: Sequence[int]
) -> Iterator[tuple[int, str, float, np.ndarray]]:
    """(index, name, stamp, gray image) of the chosen frames only (folders decode just those)."""
    wanted = sorted(set(int(i) for i in indices))
    if source.kind == "folder":
        names = source.names()
        for i in wanted:
            p = source.files[i]
            data = np.fromfile(str(p), dtype=np.uint8)
            img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
            if img is None:
                raise ImageDecodeError(f"cannot decode frame {p}")
            yield i, names[i], source.stamp(i), img
        return
    keep = set(wanted)
    for fr in source:
        if fr.index in keep:
            img = fr.image if fr.image.ndim == 2 else cv2.cvtColor(fr.image, cv2.COLOR_BGR2GRAY)
            yield fr.index, fr.name, fr.stamp, img
        if fr.index >= wanted[-1]:
            break


def run_peer(
    name: str,
    fn: PeerFn,
    source: FrameSource,
    indices: Sequence[int],
    groundtruth: list[Rigid3d | None] | None,
    *,
    warmup: bool = True,
    progress: Callable[[str, float, str], None] | None = None,
) -> list[FrameRecord]:
    """Records of ``fn`` on the frames ``indices`` of ``source``."""
    records: list[FrameRecord] = []
    n = len(indices)
    for k, (i, fname, stamp, gray) in enumerate(decode_frames(source, indices)):
        if warmup and k == 0:
            fn(gray)
        cpu0 = time.process_time()
        t0 = time.perf_counter()
        out = fn(gray)
        wall = (time.perf_counter() - t0) * 1e3
        cpu = (time.process_time() - cpu0) * 1e3
        rec = FrameRecord(
            index=i,
            name=fname,
            stamp=stamp,
            status=Status.LOST if out.cam_from_world is None else Status.RELOCALIZED,
            matching=Matching.GLOBAL,
            latency_ms=wall,
            inliers=out.inliers,
            detected=out.detected,
            tracked=0,
            tracked_3d=out.matches,
            timings_ms=dict(out.timings_ms or {}),
            cpu_ms=cpu,
        )
        gt = groundtruth[i] if groundtruth is not None and i < len(groundtruth) else None
        attach_errors(rec, out.cam_from_world, gt)
        records.append(rec)
        if progress is not None:
            progress(name, (k + 1) / max(1, n), f"{fname} {rec.status} {wall:.0f} ms")
    return records


def global_every_frame(bundle, camera, conf=None) -> PeerFn:
    """Our single-image global matching (``relocalize``) as a per-frame localizer."""
    from ..engine import EngineConf, relocalize
    from ..engine.localizer import prepare

    conf = conf or EngineConf()
    # The per-bundle tables our engine computes when its Localizer is made (untimed there):
    # else the first call that verifies a pose pays them (scipy.spatial's import and the
    # scope's image weights, 0.2-0.8 s of one timed call on redkitchen).
    prepare(bundle, conf)

    def fn(gray: np.ndarray) -> PeerOutput:
        res = relocalize(gray, camera, bundle, conf)
        return PeerOutput(res.cam_from_world, res.inliers, res.detected, 0, dict(res.timings_ms))

    return fn


def sift_peer(localizer) -> PeerFn:
    """A ``sift_peer.SiftLocalizer`` as a per-frame localizer."""

    def fn(gray: np.ndarray) -> PeerOutput:
        r = localizer.localize(gray)
        return PeerOutput(r.cam_from_world, r.inliers, r.keypoints, r.matches, r.timings_ms)

    return fn
