"""sfmloc demo: the whole system on a synthetic scene, in about a minute."""

from __future__ import annotations

import argparse
import textwrap


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="end to end on a synthetic room: render, build, serve, stream, relocalize",
        description=textwrap.dedent(
            """\
            1. render a synthetic room (sfmloc.synth): mapping views with an exact COLMAP
               model, and a 30 Hz walk through it with exact ground truth
            2. build the map bundle from the synthetic COLMAP model
            3. start a server (sfmloc serve, a subprocess) on loopback
            4. stream the walk through Zenoh from a separate client session
            5. relocalize single images over gRPC
            6. print frames, localized %, position/rotation errors against the ground truth,
               rate and latency
            Exits 0 when the localization meets the bar (most frames localized, centimetre
            errors), 1 otherwise."""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", metavar="DIR", help="keep everything here (default: a temporary folder, removed)")
    p.add_argument("--frames", type=int, default=150, help="video frames (default 150, 5 s at 30 Hz)")
    p.add_argument("--mapping-views", type=int, default=60, help="mapping images (default 60)")
    p.add_argument("--fps", type=float, default=30.0, help="streaming rate (default 30)")
    p.add_argument("--encoding", choices=["jpeg", "png", "gray8"], default="jpeg", help="how frames are sent (default jpeg)")
    p.add_argument("--workers", type=int, default=0, help="server workers (default: one per core)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import logging
    import shutil
    import sys
    import tempfile
    import threading
    import time
    from pathlib import Path

    import cv2
    import numpy as np
    import zenoh
    from sfmloc_client import CameraSpec, FrameStreamer, LocalizationClient, PoseSubscriber, SourceFrame, make_zenoh_config

    from ..io.poses import read_poses
    from ..mapping.build import BuildConf
    from ..mapping.build import main as build_map
    from ..server.app import ServerProcess
    from ..synth import preset
    from ..synth.main import run as synth_run
    from ..transforms import Rigid3d, rotation_angle_deg

    t_all = time.perf_counter()
    tmp = None
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="sfmloc-demo-"))
    if not args.out:
        tmp = root

    def step(msg: str) -> None:
        print(f"[{time.perf_counter() - t_all:5.1f} s] {msg}", file=sys.stderr, flush=True)

    # Library progress lines only when asked for (-v).
    if not args.verbose:
        logging.getLogger("sfmloc").setLevel(logging.WARNING)
    try:
        step(f"rendering a synthetic room: {args.mapping_views} mapping views, {args.frames} video frames ({root})")
        conf = preset("default", seed=args.seed, mapping_views=args.mapping_views, trajectory={"n_frames": args.frames})
        data = synth_run(conf, root / "synth", overwrite=True)
        step(f"  {data.n_points3D} exact 3D points, {data.n_observations} observations")
        step("building the map bundle from the synthetic COLMAP model")
        bundle = build_map(BuildConf(), "demo-room", root / "maps", colmap=root / "synth" / "sparse",
                           images=root / "synth" / "images")
        step(f"  {bundle}")
        cam_json = root / "synth" / "camera.json"
        import json

        cj = json.loads(cam_json.read_text())
        cam = CameraSpec(cj["model"], cj["width"], cj["height"], tuple(cj["params"]))
        frames = sorted((root / "synth" / "video").glob("frame-*.png"))
        gt = read_poses(root / "synth" / "video_poses.txt").by_stem()
        gt_list = [gt[f.stem] for f in frames]

        step("starting the server (sfmloc serve) on loopback")
        with ServerProcess(root / "maps", workers=args.workers) as srv:
            step(f"  Zenoh {srv.endpoint}, gRPC {srv.grpc}")
            # ---- stream
            step(f"streaming {len(frames)} frames at {args.fps:g} Hz over Zenoh ({args.encoding})")
            sent_at: dict[int, float] = {}
            poses: dict[int, object] = {}
            rtt: list[float] = []
            lock = threading.Lock()

            def on_pose(p) -> None:  # noqa: ANN001 - PoseMessage
                now = time.perf_counter()
                with lock:
                    if p.seq is not None:
                        poses[p.seq] = p
                        if p.seq in sent_at:
                            rtt.append((now - sent_at[p.seq]) * 1e3)

            def on_sent(seq: int, _fr: object, t_put: float) -> None:
                with lock:
                    sent_at[seq] = t_put

            images = [cv2.imread(str(f), cv2.IMREAD_COLOR) for f in frames]
            source = [SourceFrame(image=img) for img in images]
            with zenoh.open(make_zenoh_config("peer", connect=[srv.endpoint], multicast=False)) as z, \
                    PoseSubscriber(z, "demo-room", "demo-camera", callback=on_pose) as sub, \
                    FrameStreamer(z, "demo-room", "demo-camera", cam, encoding=args.encoding) as fs:
                if not fs.wait_for_server(30):
                    step("the server does not subscribe to the frames")
                    return 1
                stats = fs.run(source, fps=args.fps, poses=sub, on_sent=on_sent)
                sub.wait_for(stats.last_seq, 10)
            # ---- relocalize
            step("relocalizing single images over gRPC")
            picks = list(np.linspace(0, len(frames) - 1, 6).astype(int)[1:-1]) + [len(frames) // 3]
            reloc = []
            with LocalizationClient(srv.grpc) as c:
                for k in picks:
                    t0 = time.perf_counter()
                    r = c.relocalize(frames[k].read_bytes(), "demo-room", cam, encoding="png")
                    reloc.append((k, r, (time.perf_counter() - t0) * 1e3))
            exit_code = srv.stop()

        # ---- report
        def errors(p, k: int) -> tuple[float, float]:  # noqa: ANN001
            w = p.world_from_cam
            est = Rigid3d.from_quat_xyzw(np.array(w.quat_xyzw), np.array(w.t))
            ref = gt_list[k].inverse()
            return float(np.linalg.norm(est.translation - ref.translation)), rotation_angle_deg(est.rotation, ref.rotation)

        got = [poses[k] for k in sorted(poses)]
        loc = [(p.seq, *errors(p, p.seq)) for p in got if p.localized]
        dpos = np.array([e[1] for e in loc]) * 100
        drot = np.array([e[2] for e in loc])
        statuses: dict[str, int] = {}
        for p in got:
            statuses[p.status] = statuses.get(p.status, 0) + 1
        lat = np.array(rtt) if rtt else np.array([np.nan])
        eng = np.array([p.engine_ms for p in got if p.error is None]) if got else np.array([np.nan])
        n = len(frames)
        print()
        print("sfmloc demo: synthetic room, 640x480 walk at %g Hz, one Zenoh client, %s frames" % (args.fps, args.encoding))
        print(f"  {'frames sent':<34}{stats.sent}")
        print(f"  {'poses received':<34}{len(got)}  ({', '.join(f'{k} {v}' for k, v in sorted(statuses.items()))}; "
              f"{stats.sent - len(got)} dropped as stale)")
        print(f"  {'localized':<34}{len(loc)} = {100 * len(loc) / n:.1f}% of frames sent")
        if len(loc):
            print(f"  {'position error (cm)':<34}median {np.median(dpos):.2f}  p90 {np.percentile(dpos, 90):.2f}  max {dpos.max():.2f}")
            print(f"  {'rotation error (deg)':<34}median {np.median(drot):.2f}  p90 {np.percentile(drot, 90):.2f}  max {drot.max():.2f}")
        print(f"  {'send rate':<34}{stats.rate_hz:.1f} frames/s")
        print(f"  {'latency, frame sent -> pose (ms)':<34}p50 {np.nanmedian(lat):.1f}  p99 {np.nanpercentile(lat, 99):.1f}")
        print(f"  {'engine time per frame (ms)':<34}p50 {np.nanmedian(eng):.1f}  p99 {np.nanpercentile(eng, 99):.1f}")
        print("  single images over gRPC (Relocalize):")
        ok_reloc = 0
        for k, r, ms in reloc:
            if r.localized:
                dp, dr = errors(r, k)
                ok_reloc += dp < 0.1
                print(f"    frame {k:4d}: {r.status:<11} {r.inliers:4d} inliers  {dp * 100:6.2f} cm  {dr:5.2f} deg  {ms:6.1f} ms")
            else:
                print(f"    frame {k:4d}: {r.status:<11} {r.message}  {ms:6.1f} ms")
        print(f"  server exit code after SIGTERM: {exit_code}")
        print(f"  total {time.perf_counter() - t_all:.1f} s")
        good = (len(loc) >= 0.8 * n and len(loc) > 0 and np.median(dpos) < 5.0 and ok_reloc >= len(reloc) - 1
                and exit_code == 0)
        print("demo " + ("passed" if good else "FAILED: localization below the bar (see the table)"))
        return 0 if good else 1
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
