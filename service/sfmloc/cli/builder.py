"""sfmloc builder serve|submit|list|watch|cancel: the map builder service and its client."""

from __future__ import annotations

import argparse
import sys

DESCRIPTION = """\
The map builder service builds bundles from inputs on its own machine, one worker process per
build (a crash in a build never takes the service down), streams progress over gRPC
(sfmloc.v1.MapBuilder) and announces each finished bundle on Zenoh at sfmloc/maps/NAME
(msgpack {name, build_id, path}) so servers started with --follow-builder load it.
"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "builder",
        help="run the map builder service, or submit/watch/cancel builds",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    bsub = p.add_subparsers(dest="builder_command", metavar="ACTION", required=True)

    s = bsub.add_parser(
        "serve",
        help="run the builder service",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("--out", help="default folder for bundles (default: maps)")
    s.add_argument("--grpc", help="listen address HOST:PORT (default 127.0.0.1:50052)")
    s.add_argument(
        "--max-concurrent", type=int, help="builds at once, one process each (default 1)"
    )
    s.add_argument(
        "--workdir", help="parent of per-job SfM work folders (default: a temporary folder)"
    )
    s.add_argument(
        "--zenoh-mode", choices=["peer", "client", "router"], help="Zenoh mode (default peer)"
    )
    s.add_argument(
        "--zenoh-listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh listen endpoint (repeatable)",
    )
    s.add_argument(
        "--zenoh-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh connect endpoint (repeatable)",
    )
    s.add_argument("--zenoh-config", help="Zenoh JSON5 config file (explicit flags override it)")
    s.add_argument("--no-multicast", action="store_true", help="turn Zenoh multicast scouting off")
    s.add_argument(
        "--no-announce", action="store_true", help="do not open Zenoh or announce bundles"
    )
    s.add_argument(
        "--config", help="builder service config file (JSON/TOML); SFMLOC_BUILDER_* variables apply"
    )
    s.set_defaults(func=run_serve)

    def client_args(q):
        q.add_argument(
            "--builder",
            default="127.0.0.1:50052",
            help="builder address HOST:PORT (default 127.0.0.1:50052)",
        )

    sb = bsub.add_parser(
        "submit",
        help="submit a build and follow its progress",
        description="Submit a build (paths are on the builder's machine) and show its progress "
        "until it ends (--no-wait to return the job id at once). Inputs as in 'sfmloc build'.",
    )
    sb.add_argument("name")
    sb.add_argument(
        "--out", default="", help="bundle folder on the builder (default: the service's)"
    )
    sb.add_argument("--colmap", metavar="MODEL_DIR")
    sb.add_argument("--images", metavar="DIR", required=True)
    sb.add_argument("--poses", metavar="FILE")
    sb.add_argument("--camera", help="'MODEL w h params...' or camera.json (read here)")
    sb.add_argument("--matching", choices=["sequential", "exhaustive"])
    sb.add_argument("--preset", default="", help="builder preset (default, fast, dense)")
    sb.add_argument("--stride", type=int, default=1, help="posed/images-only: use every N-th image")
    sb.add_argument("--no-wait", action="store_true")
    client_args(sb)
    sb.set_defaults(func=run_submit)

    ls = bsub.add_parser("list", help="list build jobs", description="List the builder's jobs.")
    client_args(ls)
    ls.set_defaults(func=run_list)
    w = bsub.add_parser(
        "watch", help="follow a job's progress", description="Follow a job until it ends."
    )
    w.add_argument("job_id")
    client_args(w)
    w.set_defaults(func=run_watch)
    c = bsub.add_parser(
        "cancel", help="cancel a job", description="Cancel a queued or running job."
    )
    c.add_argument("job_id")
    client_args(c)
    c.set_defaults(func=run_cancel)


def run_serve(args: argparse.Namespace) -> int:
    from ..threads import pin_threads_env

    pin_threads_env()
    from ..builder_service.app import BuilderConfig, serve
    from ..config import load_config

    overrides = {
        "out": args.out,
        "grpc": args.grpc,
        "max_concurrent": args.max_concurrent,
        "workdir": args.workdir,
        "zenoh_mode": args.zenoh_mode,
        "zenoh_config": args.zenoh_config,
        "zenoh_listen": args.zenoh_listen or None,
        "zenoh_connect": args.zenoh_connect or None,
        "zenoh_multicast": False if args.no_multicast else None,
        "announce": False if args.no_announce else None,
    }
    return serve(
        load_config(BuilderConfig, args.config, prefix="SFMLOC_BUILDER_", overrides=overrides)
    )


def _stub(address: str):
    import grpc

    from sfmloc_client.pb import builder_pb2_grpc

    channel = grpc.insecure_channel(address)
    return channel, builder_pb2_grpc.MapBuilderStub(channel)


def _grpc_call(fn, *a):
    import grpc

    from ..errors import SfmlocError

    try:
        return fn(*a)
    except grpc.RpcError as exc:
        raise SfmlocError(f"builder: {exc.code().name}: {exc.details()}") from None


def _watch(stub, job_id: str) -> int:
    """Follow a job to its end (a job that has ended already: its recorded progress, each stage
    with the time it took); 0 when it succeeded."""
    from sfmloc_client.pb import builder_pb2 as pb

    from .progress import ProgressPrinter

    job = _grpc_call(stub.GetBuild, pb.GetBuildRequest(job_id=job_id))
    if job.state in (pb.BUILD_STATE_SUCCEEDED, pb.BUILD_STATE_FAILED, pb.BUILD_STATE_CANCELLED):
        # WatchBuild replays the recorded events at once: say so, rather than let the replay
        # pass for a build happening now.
        state = pb.BuildState.Name(job.state).removeprefix("BUILD_STATE_")
        print(
            f"{job_id} ({job.name}) had already ended: {state} at {job.ended_utc or '?'} "
            f"after {job.elapsed_s:.1f} s (submitted {job.submitted_utc}). Its recorded "
            "progress, times from the job's events:",
            file=sys.stderr,
        )
    bar = ProgressPrinter()
    last = None
    for ev in _grpc_call(stub.WatchBuild, pb.WatchBuildRequest(job_id=job_id)):
        last = ev
        if ev.stage:
            # The event's own time (since the job started), not the time it reached us.
            bar(ev.stage, ev.fraction, ev.message, t=ev.elapsed_s)
    bar.close()
    if last is None:
        return 1
    stages = [(s, d) for s, d in bar.stage_times().items() if s != "done"]
    if stages:
        print("stages: " + ", ".join(f"{s} {d:.1f} s" for s, d in stages), file=sys.stderr)
    state = pb.BuildState.Name(last.state).removeprefix("BUILD_STATE_")
    if last.state == pb.BUILD_STATE_SUCCEEDED:
        print(f"{job_id}: SUCCEEDED in {last.elapsed_s:.1f} s: {last.bundle_path}")
        return 0
    print(f"{job_id}: {state}{': ' + last.error if last.error else ''}", file=sys.stderr)
    return 1


def run_submit(args: argparse.Namespace) -> int:
    from sfmloc_client.pb import builder_pb2 as pb
    from sfmloc_client.pb import common_pb2

    from ..cameras import Camera

    cam = None
    if args.camera:
        c = Camera.parse(args.camera)
        cam = common_pb2.Camera(
            model=c.model, width=c.width, height=c.height, params=list(c.params)
        )
    req = pb.SubmitBuildRequest(
        name=args.name, out_dir=args.out, preset=args.preset, stride=args.stride
    )
    if args.colmap:
        req.colmap.CopyFrom(pb.ColmapInput(model_dir=args.colmap, image_dir=args.images))
    elif args.poses:
        req.posed_images.CopyFrom(
            pb.PosedImagesInput(image_dir=args.images, poses_file=args.poses, camera=cam)
        )
    else:
        req.images_only.CopyFrom(
            pb.ImagesOnlyInput(image_dir=args.images, camera=cam, matching=args.matching or "")
        )
    channel, stub = _stub(args.builder)
    with channel:
        job_id = _grpc_call(stub.SubmitBuild, req).job_id
        print(f"submitted {args.name}: job {job_id}", file=sys.stderr)
        if args.no_wait:
            print(job_id)
            return 0
        return _watch(stub, job_id)


def run_list(args: argparse.Namespace) -> int:
    from sfmloc_client.pb import builder_pb2 as pb

    channel, stub = _stub(args.builder)
    with channel:
        jobs = _grpc_call(stub.ListBuilds, pb.ListBuildsRequest()).jobs
    print(f"{'JOB':12s}  {'NAME':20s}  {'STATE':10s}  {'STAGE':12s}  {'ELAPSED':>8s}  RESULT")
    for j in jobs:
        state = pb.BuildState.Name(j.state).removeprefix("BUILD_STATE_")
        print(
            f"{j.job_id:12s}  {j.name:20s}  {state:10s}  {j.stage:12s}  {j.elapsed_s:7.1f}s  "
            f"{j.bundle_path or j.error}"
        )
    return 0


def run_watch(args: argparse.Namespace) -> int:
    channel, stub = _stub(args.builder)
    with channel:
        return _watch(stub, args.job_id)


def run_cancel(args: argparse.Namespace) -> int:
    from sfmloc_client.pb import builder_pb2 as pb

    channel, stub = _stub(args.builder)
    with channel:
        ok = _grpc_call(stub.CancelBuild, pb.CancelBuildRequest(job_id=args.job_id)).cancelled
    print(f"{args.job_id}: {'cancel requested' if ok else 'already ended'}")
    return 0
