"""Run a recorded sequence through the engine in-process, as a video (``sfmloc replay``).

Latency is the time of ``Localizer.localize`` on the decoded frame (decoding from disk is not
the engine's cost and is reported separately).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from ..cameras import Camera
from ..engine import EngineConf, Localizer
from ..io.frames import FrameSource
from ..map.bundle import MapBundle
from ..transforms import Rigid3d
from .metrics import FrameRecord, attach_errors


def replay(
    bundle: MapBundle,
    source: FrameSource,
    camera: Camera,
    conf: EngineConf | None = None,
    groundtruth: list[Rigid3d | None] | None = None,
    *,
    start: int = 0,
    max_frames: int | None = None,
    on_frame: Callable[[FrameRecord], None] | None = None,
    reset_every: int = 0,
) -> tuple[list[FrameRecord], float]:
    """Per-frame records, and the mean decode time (ms). ``reset_every`` > 0: the session is
    reset before every that many frames (the first included), so the tracker relocalizes
    there: its own relocalizations, and the frames tracked on from them, as a stream whose
    client reconnects sees them."""
    loc = Localizer(bundle, camera, conf)
    records: list[FrameRecord] = []
    decode_ms = 0.0
    t_dec = time.perf_counter()
    for frame in source:
        if frame.index < start:
            t_dec = time.perf_counter()
            continue
        if max_frames is not None and len(records) >= max_frames:
            break
        decode_ms += (time.perf_counter() - t_dec) * 1e3
        if reset_every > 0 and len(records) % reset_every == 0:
            loc.reset()
        cpu0 = time.process_time()
        res = loc.localize(frame.image, frame.stamp)
        cpu_ms = (time.process_time() - cpu0) * 1e3
        rec = FrameRecord(
            index=frame.index,
            name=frame.name,
            stamp=frame.stamp,
            status=res.status,
            matching=res.matching,
            latency_ms=res.latency_ms,
            inliers=res.inliers,
            detected=res.detected,
            tracked=res.tracked,
            tracked_3d=res.tracked_3d,
            timings_ms=dict(res.timings_ms),
            cpu_timings_ms=dict(res.cpu_timings_ms),
            cpu_ms=cpu_ms,
            covariance=res.covariance,
            message=res.message,
        )
        gt = (
            groundtruth[frame.index]
            if groundtruth is not None and frame.index < len(groundtruth)
            else None
        )
        attach_errors(rec, res.cam_from_world, gt)
        records.append(rec)
        if on_frame:
            on_frame(rec)
        t_dec = time.perf_counter()
    return records, decode_ms / max(1, len(records))
