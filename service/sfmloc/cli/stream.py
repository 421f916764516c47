"""sfmloc stream: stream a video to a server over Zenoh and record the trajectory."""

from __future__ import annotations

import argparse
import textwrap
from typing import Any

from ._clientopts import add_zenoh_options, camera_spec, default_client_id, zenoh_config

DESCRIPTION = textwrap.dedent(
    """\
    Publish frames of SOURCE on sfmloc/<map>/<client>/frame and receive their poses on
    sfmloc/<map>/<client>/pose. Live status (rate, latency, status) goes to stderr; with
    --out the trajectory is written in TUM format (timestamp tx ty tz qx qy qz qw,
    world_from_cam, localized frames only), FILE.cov beside it (per pose: timestamp,
    status, 6x6 covariance, row-major, order rx ry rz cx cy cz; see README, Conventions) and
    FILE.frames (every answered frame, LOST ones too: seq, timestamp, status, inliers,
    matching, error code, covariance).

    SOURCE is an image folder, a video file or a camera index. Digits are always a camera
    (--source 0 is /dev/video0 on Linux), even where a folder or file of that name exists (a
    note on stderr says so): write --source ./0 for the folder.

    Timestamps are the frames' own: an image folder's are frame index / --fps (30 without
    --fps) unless --timestamps reads them from the file names (stem-s, stem-ms, stem-us,
    stem-ns) or a 'timestamp filename' file (TUM rgb.txt); a video's are its container's
    clock; a live camera's are the send times. So a trajectory compares with ground truth
    on the same clock without hand alignment.

    Pacing: --fps N sends at N frames/s (the server drops frames it cannot keep up with,
    newest kept); without --fps the next frame goes out when the previous pose is back.
    Exit 0 once the source is exhausted, the last pose arrived (or --timeout passed) and at
    least one frame was localized; 1 when none was, or the server does not host the map
    (each distinct error is printed with its count); 2 on bad input (e.g. a missing or
    empty source, checked before connecting).
    """
)

EPILOG = textwrap.dedent(
    """\
    examples:
      sfmloc stream --map lab --source frames/ --camera camera.json --fps 30 --out lab.tum
      sfmloc stream --map lab --source 0 --camera "PINHOLE 640 480 525 525 320 240" \\
          --zenoh-connect tcp/server:7447
    """
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "stream",
        help="stream frames over Zenoh, print live status, write a TUM trajectory",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--map", required=True, help="map name on the server")
    p.add_argument(
        "--source",
        required=True,
        metavar="PATH|DEVICE",
        help="image folder, video file or camera index; digits are always a camera (0: "
        "/dev/video0), even where a folder of that name exists: write ./0 for the folder",
    )
    p.add_argument(
        "--camera", required=True, metavar="CAMERA", help="camera.json or 'MODEL w h params...'"
    )
    p.add_argument(
        "--fps", type=float, metavar="N", help="send rate (default: as fast as poses come back)"
    )
    p.add_argument("--client-id", metavar="ID", help="client id (default <hostname>-<pid>)")
    p.add_argument(
        "--server",
        metavar="ID|auto",
        help="with several servers hosting the map: the one that answers ('auto': pick one of "
        "the ready servers hosting it, by rendezvous hashing of the client id, and move to "
        "another when it disappears; default: every server hosting the map answers)",
    )
    p.add_argument(
        "--out",
        metavar="FILE.tum",
        help="write the trajectory (TUM, world_from_cam); FILE.tum.cov "
        "beside it: status and 6x6 covariance per pose (see README, Conventions)",
    )
    p.add_argument(
        "--filtered", action="store_true", help="write the Kalman-filtered poses to --out"
    )
    p.add_argument(
        "--encoding",
        choices=["jpeg", "png", "gray8", "bgr8"],
        default="jpeg",
        help="how frames are sent (default jpeg; .jpg files are sent as they are)",
    )
    p.add_argument(
        "--pattern",
        default="*",
        metavar="GLOB",
        help="file names to take from a folder (default *)",
    )
    p.add_argument(
        "--timestamps",
        metavar="SOURCE",
        help="an image folder's clock: stem-s|stem-ms|stem-us|stem-ns (numeric file names in "
        "that unit) or a 'timestamp filename' file (default: frame index / --fps)",
    )
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    p.add_argument(
        "--timeout",
        type=float,
        default=5.0,
        metavar="S",
        help="wait this long for the last pose (default 5)",
    )
    p.add_argument(
        "--wait-server",
        type=float,
        default=10.0,
        metavar="S",
        help="wait this long for a server (default 10)",
    )
    p.add_argument(
        "--plot",
        metavar="FILE.png",
        help="draw the trajectory (top view; with --groundtruth against it; needs matplotlib)",
    )
    p.add_argument(
        "--groundtruth",
        metavar="FILE",
        help="for --plot: COLMAP list (by file name) or TUM (by the frames' timestamps, else "
        "index / fps, fps 30 without --fps), as in sfmloc replay",
    )
    add_zenoh_options(p)
    p.set_defaults(func=run)


def open_stamped_source(args: argparse.Namespace) -> Any:
    """The frames of --source with their own timestamps, checked before connecting: a missing
    or empty source, or an unreadable clock, is an ``InputError`` (exit 2), not a traceback
    after a wait for the server."""
    import itertools
    import sys
    from pathlib import Path

    from sfmloc_client import open_source
    from sfmloc_client.sources import camera_index, list_images

    from ..errors import InputError
    from ..io.frames import folder_stamps

    src = args.source
    passthrough = args.encoding if args.encoding in ("jpeg", "png") else None
    # Decided once, and the frames and their clock both follow it: digits are a camera, a
    # folder or file of that name is read when written as a path (./0). They once came from
    # both: a folder 0 beside --source 0 gave its timestamps to camera 0's frames.
    index = camera_index(src)
    path = None if index is not None else Path(src)
    if index is not None and Path(src).exists():
        kind = "folder" if Path(src).is_dir() else "file"
        print(
            f"sfmloc stream: --source {src} is camera {index}; a {kind} named {src} is here "
            f"too: write --source ./{src} to stream it",
            file=sys.stderr,
        )
    is_dir = path is not None and path.is_dir()
    if not is_dir and args.timestamps:
        raise InputError(
            "--timestamps applies to an image folder (a video or a camera has its own clock)"
        )
    if path is not None and not path.exists():
        raise InputError(f"--source {src}: no such file or folder (or a camera index)")
    stamps_ns = None
    if is_dir:
        names = [p.name for p in list_images(src, args.pattern)]  # InputError when none
        stamps, clock = folder_stamps(names, args.timestamps, args.fps or 30.0)
        stamps_ns = [round(t * 1e9) for t in stamps]
    frames = open_source(
        index if path is None else path, pattern=args.pattern, passthrough=passthrough
    )
    first = next(frames, None)
    if first is None:
        raise InputError(f"--source {src} gave no frames (an empty or unreadable video?)")
    frames = itertools.chain([first], frames)
    if stamps_ns is None:
        return frames, "send time" if path is None else "the video's clock"

    def stamped() -> Any:
        for fr, t in zip(frames, stamps_ns):
            fr.stamp_ns = t
            yield fr

    return stamped(), clock


def run(args: argparse.Namespace) -> int:
    import sys
    import threading
    import time
    from pathlib import Path

    import numpy as np
    import zenoh

    from sfmloc_client import (
        FrameStreamer,
        FramesWriter,
        PoseMessage,
        PoseSubscriber,
        TumWriter,
    )
    from sfmloc_client.streamer import OUTAGE_FRAMES
    from sfmloc_client.trajectory import frames_path

    from ._trajplot import StreamRecorder, check_plot_args, write_plot

    check_plot_args(args.plot, args.groundtruth)
    recorder = StreamRecorder()
    cam = camera_spec(args.camera)
    client_id = args.client_id or default_client_id()
    source, clock = open_stamped_source(args)
    tty = sys.stderr.isatty()
    sent_at: dict[int, float] = {}
    rtt: list[float] = []
    server_ms: list[float] = []
    statuses: dict[str, int] = {}
    reasons: dict[tuple[str, str], int] = {}  # (code, message) -> frames
    lock = threading.Lock()
    writer = TumWriter(args.out, filtered=args.filtered) if args.out else None
    frames_out = FramesWriter(frames_path(args.out)) if args.out else None
    state: dict[str, Any] = {
        "last": None,
        "errors": 0,
        "localized": 0,
        "dropped": 0,
        "t_status": 0.0,
        "sent": 0,
        "t0": time.monotonic(),
        "poses": None,
    }

    def status_line(final: bool = False) -> None:
        with lock:
            n = sum(statuses.values())
            el = max(1e-6, time.monotonic() - state["t0"])
            p50 = float(np.median(rtt[-100:])) if rtt else float("nan")
            last = state["last"]
        line = (
            f"sent {state['sent']} poses {n} "
            f"({', '.join(f'{k} {v}' for k, v in sorted(statuses.items()))}) "
            f"{n / el:5.1f} Hz  round trip p50 {p50:5.1f} ms  dropped {state['dropped']}  "
            f"last {last.status if last else '-'}"
        )
        if last is not None and last.error is not None:
            line += f" [{last.error.code}: {last.error.message}]"
        gap = state["sent"] - 1 - (state["poses"].max_seq if state["poses"] is not None else -1)
        if gap >= OUTAGE_FRAMES:  # "last TRACKING" would hide that nothing comes back
            line += f"  NO ANSWER for {gap} frames"
        if tty and not final:
            sys.stderr.write("\r" + line[:160].ljust(160))
        else:
            sys.stderr.write(("\r" if tty else "") + line + "\n")
        sys.stderr.flush()

    def on_pose(p: PoseMessage) -> None:
        now = time.monotonic()
        t_now = time.perf_counter()
        recorder.pose(p)
        with lock:
            if p.seq is not None and p.seq in sent_at:
                rtt.append((t_now - sent_at.pop(p.seq)) * 1e3)
            server_ms.append(p.latency_ms)
            statuses[p.status] = statuses.get(p.status, 0) + 1
            state["errors"] += p.error is not None
            state["localized"] += p.localized
            if p.error is not None:
                key = (p.error.code, p.error.message)
                reasons[key] = reasons.get(key, 0) + 1
            state["dropped"] = max(state["dropped"], p.dropped)
            state["last"] = p
            if writer is not None:
                writer.write(p)
            if frames_out is not None:
                frames_out.write(p)
        if now - state["t_status"] > 0.5:
            state["t_status"] = now
            status_line()

    def on_sent(seq: int, fr: object, t_put: float) -> None:
        recorder.sent(seq, fr)
        with lock:
            sent_at[seq] = t_put
            state["sent"] += 1
        now = time.monotonic()
        if now - state["t_status"] > 0.5:  # also while no pose comes back
            state["t_status"] = now
            status_line()

    try:
        with zenoh.open(zenoh_config(args)) as z:
            with (
                PoseSubscriber(z, args.map, client_id, callback=on_pose) as poses,
                FrameStreamer(
                    z, args.map, client_id, cam, encoding=args.encoding, server=args.server
                ) as fs,
            ):
                if not fs.wait_for_server(args.wait_server):
                    sys.stderr.write(
                        f"no server subscribes to {fs.key} after {args.wait_server:.0f} s "
                        "(is one running, reachable with --zenoh-connect, hosting this map?)\n"
                    )
                    return 1
                state["t0"] = time.monotonic()
                state["poses"] = poses  # the status line reads the newest answered frame
                stats = fs.run(
                    source,
                    fps=args.fps,
                    lockstep=args.fps is None,
                    poses=poses,
                    pose_timeout=args.timeout,
                    max_frames=args.max_frames,
                    on_sent=on_sent,
                    # An unknown map answers every frame the same: stop at the first answer.
                    should_stop=lambda: any(code == "NOT_FOUND" for code, _ in reasons),
                )
                if stats.sent:
                    poses.wait_for(stats.last_seq, args.timeout)
                received = poses.received
    finally:
        if writer is not None:
            writer.close()
        if frames_out is not None:
            frames_out.close()
    status_line(final=True)
    summary = (
        f"{received} poses received for {stats.sent} frames sent ({stats.rate_hz:.1f} frames/s"
    )
    if server_ms:
        summary += (
            f"; server dropped {state['dropped']} stale, {state['errors']} errors; server latency "
            f"p50 {np.median(server_ms):.1f} ms p99 {np.percentile(server_ms, 99):.1f} ms"
        )
    if rtt:
        summary += f"; round trip p50 {np.median(rtt):.1f} ms"
    if stats.undelivered:  # Zenoh drops them unsaid: no server subscribed at the time
        summary += f"; {stats.undelivered} frames sent while no server subscribed (lost)"
    if stats.outages:
        summary += (
            f"; {stats.outages} outage(s), longest {stats.max_unanswered} frames without an answer"
        )
    summary += f"; {state['localized']} localized; clock: {clock})"
    if writer is not None:
        summary += (
            f"; {writer.count} poses written to {args.out} (every frame: {frames_path(args.out)})"
        )
    print(summary)
    if args.plot:
        recs = recorder.records(args.groundtruth, args.fps or 30.0)
        title = f"sfmloc stream: {Path(args.source).name} on {args.map}, {len(recs)} answered"
        print(f"plot: {write_plot(recs, args.plot, title)}")
    for (code, message), n in sorted(reasons.items(), key=lambda kv: -kv[1]):
        print(f"error: {code}: {message} ({n} frame{'s' if n != 1 else ''})", file=sys.stderr)
    unknown_map = any(code == "NOT_FOUND" for code, _ in reasons)
    if unknown_map:
        print(f"the server does not host map {args.map!r}", file=sys.stderr)
    elif state["localized"] == 0:
        print("no frame was localized", file=sys.stderr)
    return 1 if unknown_map or state["localized"] == 0 else 0
