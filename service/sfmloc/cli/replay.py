"""sfmloc replay: run a recorded sequence through the engine and report accuracy and latency."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

DESCRIPTION = """\
Run a recorded sequence through the localization engine in-process, as a 30 Hz video, and
print a summary: frames, localized fraction, position and rotation errors against ground
truth (median, mean; rotation error is the angle of R_est R_gt^T), wrong poses (any status
but LOST with a position error over 5% of the scene scale, the map's median camera-to-point
depth, or a rotation error over 10 degrees), the share of frames within 5 cm / 5 degrees and
within 2.5% of the scene scale / 5 degrees, per-frame latency (mean, std,
p50, p95, p99, max; the engine's time per frame, decoding excluded), how many frames ran
guided or global matching, and where the time goes: per stage (detect: Harris + BRIEF; track:
TRACK-2D; match: guided matching; pose: pose estimation and its covariance; filter: the motion
filter and input checks; reloc: recovery around the prediction and global matching) the mean
per frame, its share, and the mean, p95, p99 and max over the frames it ran in.

FRAMES is a folder whose .jpg/.png images are taken in name order (other files are ignored) or
a video file. Ground truth is a COLMAP list ('name qw qx qy qz tx ty tz [f]', cam_from_world,
matched to frames by file name, or by name stem across folders/extensions) or a TUM file
('timestamp tx ty tz qx qy qz qw', world_from_cam, matched by the frames' timestamps within
half a frame interval). OpenCV, BLAS and faiss run on one thread.

Clock: each frame's timestamp is frame index / --fps (default 30), whatever the file names,
unless --timestamps names another source:
  stem-s, stem-ms, stem-us, stem-ns  the numeric file-name stem in that unit
                                     (TUM RGB-D folders: stem-s; ROS bag exports: stem-ns)
  FILE                               'timestamp filename' lines (TUM rgb.txt), or one
                                     'timestamp ...' line per frame in frame order
The engine's motion model runs on this clock: a gap between frames over max_frame_gap_s (0.9 s)
resets tracking (the frame relocalizes), so a 1 Hz camera relocalizes every frame whatever
jitter or float noise its stamps carry, and a 2 Hz or faster one tracks. The summary names the
clock used and counts such gaps between the frames replayed (--start, --max-frames).

Repeatable: the same map, frames, timestamps, camera and config give bit-identical poses and
covariances in every run (no wall clock or shared random state decides a pose; README,
Conventions, "Repeatable poses").
"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="replay a recorded sequence through the engine (accuracy, latency)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("map", help="map bundle folder (e.g. maps/lab)")
    p.add_argument("frames", help="image folder or video file")
    p.add_argument(
        "--camera",
        required=True,
        help="camera.json or 'MODEL w h params...' (e.g. 'PINHOLE 640 480 525 525 320 240')",
    )
    p.add_argument("--groundtruth", help="ground-truth poses (COLMAP list or TUM)")
    p.add_argument(
        "--json", dest="json_out", help="write the summary (and per-frame records) as JSON here"
    )
    p.add_argument(
        "--trajectory",
        help="write the estimated trajectory here (TUM, world_from_cam, raw poses); "
        "FILE.cov beside it: status and 6x6 covariance per pose (see README, Conventions)",
    )
    p.add_argument(
        "--plot",
        metavar="FILE.png",
        help="draw the trajectory (top view) against --groundtruth, lost frames marked, over "
        "the map's points (needs matplotlib: the bench extra)",
    )
    p.add_argument(
        "--fps",
        type=float,
        default=30.0,
        help="the clock: timestamp = frame index / fps (default 30), unless --timestamps",
    )
    p.add_argument(
        "--timestamps",
        metavar="SOURCE",
        help="take timestamps from stem-s|stem-ms|stem-us|stem-ns (numeric file names "
        "in that unit) or a TUM-style timestamps file, instead of --fps",
    )
    p.add_argument("--start", type=int, default=0, help="first frame index (default 0)")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument(
        "--reset-every",
        type=int,
        default=0,
        metavar="N",
        help="reset the session before every N frames: the tracker relocalizes there "
        "(its relocalizations and the frames tracked on from them; default 0: never)",
    )
    p.add_argument(
        "--config", help="engine config file (JSON/TOML; SFMLOC_ENGINE__* variables also apply)"
    )
    p.add_argument(
        "--no-verify", action="store_true", help="skip bundle checksum verification at load"
    )
    p.set_defaults(func=run)


def format_summary(s: dict, decode_ms: float | None = None) -> str:
    from ..eval.metrics import RECALL_POSITION_FRACTION, WRONG_POSITION_FRACTION, WRONG_ROTATION_DEG

    lat = s["latency_ms"]

    def cm(x):
        return f"{x * 100:.2f} cm" if x == x else "n/a"

    def deg(x):
        return f"{x:.2f} deg" if x == x else "n/a"

    def pct(x):
        return f"{x * 100:.1f}%" if x == x else "n/a"

    statuses = ", ".join(f"{k} {v}" for k, v in s["status_counts"].items())
    wrong_by = ", ".join(f"{k} {v}" for k, v in s["wrong_statuses"].items())
    lines = [
        f"frames               {s['frames']}",
        f"localized            {s['localized_frames']} ({s['localized_fraction'] * 100:.1f}%)  "
        f"[{statuses}]",
        f"evaluated            {s['evaluated_frames']} frames with ground truth and a pose",
        f"position error       median {cm(s['median_position_error_m'])}, mean "
        f"{cm(s['mean_position_error_m'])}",
        f"rotation error       median {deg(s['median_rotation_error_deg'])}, mean "
        f"{deg(s['mean_rotation_error_deg'])}",
        f"wrong poses          {s['confident_wrong']}{f' [{wrong_by}]' if wrong_by else ''} "
        f"(any status but LOST, error > {s['wrong_position_limit']:.3g} = "
        f"{WRONG_POSITION_FRACTION:.0%} of the scene scale {s['scene_scale']:.3g}, "
        f"or > {WRONG_ROTATION_DEG:g} deg)",
        f"within 5 cm / 5 deg  {pct(s['within_5cm_5deg_fraction'])} of the frames with "
        "ground truth",
        f"{f'within {RECALL_POSITION_FRACTION:.1%} / 5 deg':21s}"
        f"{pct(s['within_relative_fraction'])} "
        f"(position within {s['within_relative_position_limit']:.3g} map units = "
        f"{RECALL_POSITION_FRACTION:.1%} of the scene scale)",
        f"latency (ms)         mean {lat['mean']:.1f}, std {lat['std']:.1f}, p50 {lat['p50']:.1f}, "
        f"p95 {lat['p95']:.1f}, "
        f"p99 {lat['p99']:.1f}, max {lat['max']:.1f}",
        f"guided matching      {s['guided_frames']} frames, mean {s['guided_latency_ms_mean']:.1f} "
        "ms",
        f"global matching      {s['global_frames']} frames, mean {s['global_latency_ms_mean']:.1f} "
        "ms",
    ]
    if decode_ms is not None:
        lines.append(f"decode (not counted) {decode_ms:.1f} ms/frame")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from ..threads import pin_threads_env, pin_threads_runtime

    pin_threads_env()
    pin_threads_runtime()
    import sys

    import numpy as np

    from ..cameras import Camera
    from ..config import load_config
    from ..engine import EngineConf
    from ..eval.groundtruth import load_groundtruth
    from ..eval.metrics import absolute_trajectory_error, summarize
    from ..eval.replay import replay
    from ..eval.stages import format_stage_table, stage_stats
    from ..io.frames import FrameSource
    from ..io.poses import write_tum, write_tum_covariances
    from ..map.bundle import MapBundle
    from ._trajplot import check_plot_path, write_plot
    from .progress import ProgressPrinter

    if args.plot:
        check_plot_path(args.plot)
    camera = Camera.parse(args.camera)
    conf = load_config(EngineConf, args.config, prefix="SFMLOC_ENGINE__")
    bundle = MapBundle(args.map, verify=not args.no_verify)
    source = FrameSource(args.frames, fps=args.fps, timestamps=args.timestamps)
    gt = None
    if args.groundtruth:
        stamps = [source.stamp(i) for i in range(len(source))]
        gt = load_groundtruth(args.groundtruth, source.names(), stamps, source.nominal_fps)
    total = len(source) - args.start
    if args.max_frames is not None:
        total = min(total, args.max_frames)
    bar = ProgressPrinter()
    records, decode_ms = replay(
        bundle,
        source,
        camera,
        conf,
        gt,
        start=args.start,
        max_frames=args.max_frames,
        reset_every=args.reset_every,
        on_frame=lambda r: bar(
            "replay", (r.index - args.start + 1) / max(1, total), f"{r.name} {r.status}"
        ),
    )
    bar.close()
    summary = summarize(records, bundle.scene_scale)
    summary["ate_m"] = absolute_trajectory_error(records)
    print(format_summary(summary, decode_ms))
    stages = stage_stats([r.timings_ms for r in records])
    summary["stages_ms"] = stages
    print("time per stage (ms; mean/frame over all frames, the others over the frames it ran in)")
    print(format_stage_table(stages))
    if all(r.cpu_timings_ms for r in records) and records:
        summary["stages_cpu_ms"] = stage_stats([r.cpu_timings_ms for r in records])
    summary["clock"] = source.clock
    summary["clock_fps"] = source.nominal_fps
    # The gaps the engine saw: between the frames replayed (--start, --max-frames), on their
    # stamps as the engine compared them; the source's own count covers every frame in it.
    gaps = int(np.sum(np.diff([r.stamp for r in records]) > conf.max_frame_gap_s))
    summary["clock_gaps_over_max"] = gaps
    print(
        f"clock                {source.clock} ({source.nominal_fps:.3g} frames/s)"
        + (
            f"; {gaps} gaps over max_frame_gap_s {conf.max_frame_gap_s:g} s reset tracking"
            if gaps
            else ""
        )
    )
    if summary["ate_m"] == summary["ate_m"]:
        print(f"ATE (SE(3)-aligned)  {summary['ate_m'] * 100:.2f} cm")
    if args.trajectory:
        posed = [(r, T) for r in records if (T := r.cam_from_world) is not None]
        ok = [r for r, _ in posed]
        write_tum(args.trajectory, [r.stamp for r in ok], [T.inverse() for _, T in posed])
        cov = write_tum_covariances(
            args.trajectory + ".cov",
            [r.stamp for r in ok],
            [r.status for r in ok],
            [r.covariance for r in ok],
        )
        print(
            f"trajectory           {args.trajectory} ({len(ok)} poses, TUM; covariances {cov})",
            file=sys.stderr,
        )
    if args.plot:
        title = f"sfmloc replay: {Path(args.frames).name} on {bundle.name}, {len(records)} frames"
        plot = write_plot(records, args.plot, title, bundle.points_xyz)
        print(f"plot                 {plot}", file=sys.stderr)
    if args.json_out:
        out = dict(summary)
        out["map"] = str(args.map)
        out["frames_source"] = str(args.frames)
        out["per_frame"] = [
            {
                "index": r.index,
                "name": r.name,
                "stamp": r.stamp,
                "status": r.status,
                "matching": r.matching,
                "latency_ms": r.latency_ms,
                "cpu_ms": r.cpu_ms,
                "inliers": r.inliers,
                "detected": r.detected,
                "tracked": r.tracked,
                "tracked_3d": r.tracked_3d,
                "position_error_m": r.position_error_m,
                "rotation_error_deg": r.rotation_error_deg,
                "message": r.message,  # why a frame is LOST (or its pose withheld)
            }
            for r in records
        ]
        Path(args.json_out).write_text(json.dumps(out, indent=2, allow_nan=True) + "\n")
        print(f"json                 {args.json_out}", file=sys.stderr)
    return 0
