"""Does a denser input give a better map? Redkitchen maps from every N-th frame (known poses),
per pair selection (issue 17: adding images must never make the map worse).

Per map: 3D points, median points per image, the 30 Hz replay of the first ``--frames`` frames
(localized %, wrong poses, mean engine ms per frame) and single-image relocalization of
``--reloc`` frames spread evenly over them (success: a pose within 5% of the scene scale and
10 deg). Bundles are built under ``--work`` and reused when present.

    python -m sfmloc.bench.density --work /tmp/density --strides 4 2 1 --frames 300 \\
        --pairs nearest geometric
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from .config import DEFAULT_DATA, REDKITCHEN_CAMERA, REDKITCHEN_POSES

log = logging.getLogger(__name__)

WRONG_FRACTION = 0.05  # of scene_scale
WRONG_DEG = 10.0


def build_map(
    work: Path, data: Path, frames: int, stride: int, pairs: str, sfm_over: dict | None = None
) -> tuple[Path, float]:
    """The bundle of every ``stride``-th of the first ``frames`` frames, built with
    ``pair_selection=pairs`` and ``sfm_over`` (reused when present); (bundle path, build
    seconds or 0)."""
    from ..builder import build, sfm
    from ..io.frames import FrameSource

    sfm_over = sfm_over or {}
    name = f"rk{frames}-s{stride}-{pairs}" + "".join(
        f"-{k}{v}" for k, v in sorted(sfm_over.items())
    )
    bundle = work / name
    if (bundle / "manifest.json").is_file():
        return bundle, 0.0
    names = FrameSource(data).names()[:frames]
    subset = work / f"frames{frames}"  # symlinks: the data are read in place, never copied
    if not subset.is_dir():
        subset.mkdir(parents=True)
        for n in names:
            (subset / n).symlink_to((data / n).resolve())
    t0 = time.perf_counter()
    build.main(
        build.preset("default"),
        name,
        work,
        images=subset,
        poses=data / REDKITCHEN_POSES,
        camera=REDKITCHEN_CAMERA,
        stride=stride,
        sfm_conf=sfm.sfm_conf(pair_selection=pairs, **sfm_over),
    )
    return bundle, time.perf_counter() - t0


def evaluate(bundle_dir: Path, data: Path, frames: int, n_reloc: int) -> dict:
    from ..cameras import Camera
    from ..engine import EngineConf, relocalize
    from ..eval.groundtruth import load_groundtruth
    from ..eval.metrics import summarize
    from ..eval.replay import replay
    from ..io.frames import FrameSource
    from ..map.bundle import MapBundle
    from ..transforms import pose_errors
    from .peers import decode_frames

    bundle = MapBundle(bundle_dir, verify=False)
    cam = Camera.parse(REDKITCHEN_CAMERA)
    source = FrameSource(data)
    n = min(frames, len(source))
    gt = load_groundtruth(
        data / REDKITCHEN_POSES,
        source.names(),
        [source.stamp(i) for i in range(len(source))],
        source.fps,
    )
    conf = EngineConf()
    scale = bundle.scene_scale
    ok = 0
    for i, _name, _stamp, gray in decode_frames(
        source, np.linspace(0, n - 1, n_reloc).round().astype(int)
    ):
        r = relocalize(gray, cam, bundle, conf)
        g = gt[i]
        if r.cam_from_world is not None and g is not None:
            dp, dr = pose_errors(r.cam_from_world, g)
            ok += dp <= WRONG_FRACTION * scale and dr <= WRONG_DEG
    recs, _ = replay(bundle, source, cam, conf, gt, max_frames=n)
    s = summarize(recs, scale)
    return {
        "images": bundle.n_images,
        "points": bundle.n_points,
        "points_per_image_median": float(np.median(np.diff(bundle.image_points_ptr))),
        "replay_localized_pct": round(100 * s["localized_fraction"], 2),
        "median_position_error_cm": round(100 * s["median_position_error_m"], 3),
        "replay_wrong": s["confident_wrong"],
        "replay_global_frames": s["global_frames"],
        "mean_ms_per_frame": round(s["latency_ms"]["mean"], 1),
        "p99_ms_per_frame": round(s["latency_ms"]["p99"], 1),
        "mean_cpu_ms_per_frame": round(float(np.mean([r.cpu_ms for r in recs])), 1),
        "reloc_ok": ok,
        "reloc_of": n_reloc,
    }


def interleaved_cpu(bundle_dirs: list[Path], data: Path, frames: int) -> list[dict]:
    """The 30 Hz replay of the first ``frames`` frames through one ``Localizer`` per bundle,
    interleaved frame by frame (the order alternating), so that the machine's load falls on
    all alike: per bundle the CPU ms per frame (mean, p99) and the frames localized. Only
    these same-run numbers compare the maps' times (issue 17's target: the every-frame map
    within 10% of the every-10th's)."""
    from ..cameras import Camera
    from ..engine import EngineConf, Localizer
    from ..eval.metrics import is_pose
    from ..io.frames import FrameSource
    from ..map.bundle import MapBundle

    cam = Camera.parse(REDKITCHEN_CAMERA)
    locs = [Localizer(MapBundle(b, verify=False), cam, EngineConf()) for b in bundle_dirs]
    cpu: list[list[float]] = [[] for _ in locs]
    ok = [0] * len(locs)
    for frame in FrameSource(data):
        if frame.index >= frames:
            break
        order = range(len(locs)) if frame.index % 2 == 0 else reversed(range(len(locs)))
        for k in order:
            c0 = time.process_time()
            res = locs[k].localize(frame.image, frame.stamp)
            cpu[k].append((time.process_time() - c0) * 1e3)
            ok[k] += is_pose(res.status)
    return [
        {
            "bundle": Path(b).name,
            "cpu_ms_mean": round(float(np.mean(c)), 2),
            "cpu_ms_p99": round(float(np.percentile(c, 99)), 2),
            "localized": ok[k],
            "frames": len(c),
        }
        for k, (b, c) in enumerate(zip(bundle_dirs, cpu))
    ]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--work", default="/tmp/sfmloc-density")
    p.add_argument("--data", default=str(DEFAULT_DATA))
    p.add_argument(
        "--frames", type=int, default=1000, help="the first N frames: map input and replay"
    )
    p.add_argument("--strides", type=int, nargs="+", default=[10, 4, 2, 1])
    p.add_argument(
        "--pairs", nargs="+", default=["nearest", "geometric"], help="SfmConf.pair_selection values"
    )
    p.add_argument("--reloc", type=int, default=40)
    p.add_argument(
        "--sfm", nargs="*", default=[], metavar="KEY=VALUE", help="SfmConf overrides (JSON values)"
    )
    p.add_argument("--build-only", action="store_true")
    p.add_argument("--json", help="append results as JSON lines here")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    work, data = Path(a.work), Path(a.data)
    work.mkdir(parents=True, exist_ok=True)
    sfm_over = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in a.sfm)}
    for pairs in a.pairs:
        for stride in a.strides:
            bundle, secs = build_map(work, data, a.frames, stride, pairs, sfm_over)
            res = {
                "pairs": pairs,
                "sfm": sfm_over,
                "stride": stride,
                "frames": a.frames,
                "build_s": round(secs),
            }
            if not a.build_only:
                res.update(evaluate(bundle, data, a.frames, a.reloc))
            print(json.dumps(res), flush=True)
            if a.json:
                with open(a.json, "a") as f:
                    f.write(json.dumps(res) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
