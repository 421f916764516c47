"""sfmloc serve: the localization server (Zenoh + gRPC)."""

from __future__ import annotations

import argparse
import textwrap

HELP = "serve maps: poses for frame streams (Zenoh, gRPC) and single images (gRPC)"

DESCRIPTION = textwrap.dedent(
    """\
    Load every map bundle in --maps and localize frames against them.

    Zenoh: clients publish frames on sfmloc/<map>/<client>/frame (msgpack envelope, see
    sfmloc_client.wire) and receive poses on sfmloc/<map>/<client>/pose. Each client gets
    its own session (track table, motion filter) on one worker; frames that arrive while
    one is being processed are dropped, newest kept. The server announces itself with a
    liveliness token sfmloc/servers/<id> and answers sfmloc/servers/<id>/info.

    gRPC (sfmloc.v1.Localization at --grpc): Relocalize, StreamLocalize, ListMaps, GetMap,
    LoadMap, UnloadMap, ListSessions, ResetSession, plus grpc.health.v1 and reflection.
    Health: "" and sfmloc.v1.Localization are SERVING once start-up is done and at least
    one map is loaded (--allow-empty: also with none); sfmloc.v1.Localization/<map> is
    SERVING while that map is loaded.

    Settings: flags > environment (SFMLOC_WORKERS, SFMLOC_ZENOH__MODE, SFMLOC_GRPC__ADDRESS,
    SFMLOC_ENGINE__K, ...) > --config FILE (JSON or TOML, the ServerConfig fields) > defaults.
    Logs: one line per event on stderr, key=value (or --log-format json).
    SIGTERM/SIGINT: stop accepting, finish in-flight frames (grace period), exit 0.
    """
)

EPILOG = textwrap.dedent(
    """\
    examples:
      sfmloc serve --maps maps/ --zenoh-listen tcp/0.0.0.0:7447 --grpc 0.0.0.0:50051
      sfmloc serve --maps maps/ --zenoh-mode client --zenoh-connect tcp/router:7447 \\
          --metrics-port 9100
    """
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--maps", metavar="DIR", help="folder of map bundles loaded at start (default: maps)"
    )
    p.add_argument(
        "--grpc",
        metavar="HOST:PORT",
        help="gRPC address (default 0.0.0.0:50051; port 0 = any; 'off' disables)",
    )
    p.add_argument(
        "--zenoh-mode", choices=["peer", "client", "router"], help="Zenoh mode (default peer)"
    )
    p.add_argument(
        "--zenoh-listen",
        metavar="ENDPOINT",
        action="append",
        help="Zenoh listen endpoint, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    p.add_argument(
        "--zenoh-connect",
        metavar="ENDPOINT",
        action="append",
        help="Zenoh endpoint to connect to (repeatable)",
    )
    p.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="a Zenoh JSON5 config file; the flags above go over it",
    )
    p.add_argument(
        "--no-multicast",
        action="store_true",
        help="no Zenoh multicast scouting (explicit endpoints only)",
    )
    p.add_argument(
        "--zenoh-shm",
        action="store_true",
        help="Zenoh's shared-memory transport on (default off: with it on, each local "
        "client's 16 MiB segment stays mapped in the server after it leaves)",
    )
    p.add_argument("--no-zenoh", action="store_true", help="gRPC only")
    p.add_argument(
        "--ros2",
        action="store_true",
        help="also publish poses as ROS 2 geometry_msgs PoseStamped and "
        "PoseWithCovarianceStamped on rmw_zenoh's keys, and take sensor_msgs images (README, "
        "ROS 2; settings in the config's [ros2] section)",
    )
    p.add_argument(
        "--ros2-camera",
        metavar="CAMERA",
        help="the camera of frames coming in as ROS 2 images ('MODEL w h params...')",
    )
    p.add_argument(
        "--workers", type=int, metavar="N", help="engine worker processes (default: one per core)"
    )
    p.add_argument("--worker-kind", choices=["process", "thread"], help=argparse.SUPPRESS)
    p.add_argument(
        "--relocalize-workers",
        type=int,
        metavar="N",
        help="extra worker processes only for single-image Relocalize, at a lower CPU "
        "priority, so that it never delays streams' frames (default 1; 0: on the "
        "stream workers)",
    )
    p.add_argument(
        "--worker-slice-ms",
        type=float,
        metavar="MS",
        help="the stream workers' scheduler time slice (Linux 6.12+; 0: the kernel's default, "
        "1.4 ms on 2 cores): frame-long slices keep workers that share a core from switching "
        "~10 times per frame onto each other's caches",
    )
    p.add_argument(
        "--map-memory",
        type=float,
        metavar="MB",
        help="host sub-map sets (folders made by 'sfmloc map split') in the maps folder: each "
        "engine worker keeps at most MB of a set's parts in memory, loading the parts near its "
        "sessions' cameras and evicting the others; PER WORKER, so the server holds at most "
        "(workers + relocalize workers) x MB of parts. Without it, sets are refused; whole "
        "bundles are always loaded whole",
    )
    p.add_argument(
        "--idle-timeout",
        type=float,
        metavar="S",
        help="end a Zenoh session after S seconds without frames (default 30)",
    )
    p.add_argument(
        "--max-pending",
        type=int,
        metavar="N",
        help="frames of a client that may wait while one is processed (default 1: latest frame "
        "only)",
    )
    p.add_argument(
        "--worker-queue",
        type=int,
        metavar="N",
        help="stream frames in one engine worker at once; sessions whose worker is full wait in "
        "the server with their newest frame and take turns, tracked sessions first (default 2; "
        "0: no limit)",
    )
    p.add_argument(
        "--relocalize-share",
        type=float,
        metavar="F",
        help="the most of a stream worker's time relocalizing frames take while tracked "
        "sessions' frames wait (default 0.5; 1: no cap; with --worker-queue > 0)",
    )
    p.add_argument(
        "--frame-budget-ms",
        type=float,
        metavar="MS",
        help="a stream frame its worker has not started this long after its receipt is "
        "answered DEADLINE_EXCEEDED and the client's next frame goes on (default 2000; 0: none)",
    )
    p.add_argument(
        "--frame-hang-ms",
        type=float,
        metavar="MS",
        help="a stream frame in the works is answered DEADLINE_EXCEEDED only when its worker "
        "has not answered it this long after its receipt (stopped, stuck; default 8000)",
    )
    p.add_argument(
        "--follow-builder",
        action="store_true",
        help="load bundles the builder announces on sfmloc/maps/*",
    )
    p.add_argument(
        "--allow-empty",
        action="store_true",
        help="health SERVING even with no map loaded (default: NOT_SERVING until one is)",
    )
    p.add_argument(
        "--metrics-port",
        type=int,
        metavar="N",
        help="serve Prometheus metrics on http://0.0.0.0:N/metrics",
    )
    p.add_argument(
        "--server-id", metavar="ID", help="id in sfmloc/servers/<id> (default <hostname>-<pid>)"
    )
    p.add_argument(
        "--tls-cert", metavar="PEM", help="serve gRPC over TLS with this certificate chain"
    )
    p.add_argument("--tls-key", metavar="PEM", help="the private key of --tls-cert")
    p.add_argument(
        "--tls-client-ca",
        metavar="PEM",
        help="require client certificates signed by this CA (mutual TLS)",
    )
    p.add_argument(
        "--tokens",
        metavar="FILE",
        help="require bearer tokens with roles on gRPC (see `sfmloc auth`)",
    )
    p.add_argument(
        "--max-message-mb",
        type=float,
        metavar="MB",
        help="largest gRPC message and Zenoh frame (default 16)",
    )
    p.add_argument("--log-format", choices=["kv", "json"], help="log line format (default kv)")
    p.add_argument("--config", metavar="FILE", help="ServerConfig as JSON or TOML")
    p.set_defaults(func=run)


def overrides_from_args(args: argparse.Namespace) -> dict:
    """Only what was given on the command line (so that it wins over file and environment)."""
    o: dict = {
        "maps": args.maps,
        "workers": args.workers,
        "worker_kind": args.worker_kind,
        "idle_timeout_s": args.idle_timeout,
        "metrics_port": args.metrics_port,
        "max_pending": args.max_pending,
        "worker_queue": args.worker_queue,
        "relocalize_share": args.relocalize_share,
        "frame_budget_ms": args.frame_budget_ms,
        "frame_hang_ms": args.frame_hang_ms,
        "server_id": args.server_id,
        "log_format": args.log_format,
        "relocalize_workers": args.relocalize_workers,
        "worker_slice_ms": args.worker_slice_ms,
    }
    if args.follow_builder:
        o["follow_builder"] = True
    if args.allow_empty:
        o["allow_empty"] = True
    z: dict = {}
    if args.zenoh_mode:
        z["mode"] = args.zenoh_mode
    if args.zenoh_listen:
        z["listen"] = args.zenoh_listen
    if args.zenoh_connect:
        z["connect"] = args.zenoh_connect
    if args.zenoh_config:
        z["config_file"] = args.zenoh_config
    if args.no_multicast:
        z["multicast"] = False
    if args.zenoh_shm:
        z["shared_memory"] = True
    if args.no_zenoh:
        z["enabled"] = False
    if z:
        o["zenoh"] = z
    r: dict = {}
    if args.ros2:
        r["enabled"] = True
    if args.ros2_camera:
        r["default_camera"] = args.ros2_camera
    if r:
        o["ros2"] = r
    g: dict = {}
    if args.grpc is not None:
        g["address"] = "" if args.grpc.lower() in ("off", "none", "") else args.grpc
    for flag, key in (
        ("tls_cert", "tls_cert"),
        ("tls_key", "tls_key"),
        ("tls_client_ca", "tls_client_ca"),
        ("tokens", "tokens_file"),
    ):
        if getattr(args, flag):
            g[key] = getattr(args, flag)
    if args.max_message_mb is not None:
        g["max_message_mb"] = args.max_message_mb
        o["max_frame_bytes"] = int(args.max_message_mb * 1024 * 1024)
    if g:
        o["grpc"] = g
    if args.map_memory is not None:
        o["engine"] = {"map_memory_mb": args.map_memory}
    return o


def prestart_zygote() -> None:
    """Start the worker zygote before anything else of the server: its imports are the longest
    part of a start (issue 16: SERVING within 2 s of a restart); they then overlap this
    process's own. The image limit is a guess (the configuration is not read yet): the pool
    checks it and starts another zygote if the configuration says otherwise."""
    import os

    from ..server.zygote import prestart

    try:
        pixels = int(os.environ.get("SFMLOC_MAX_IMAGE_PIXELS", "") or 4096 * 4096)
    except ValueError:
        pixels = 4096 * 4096
    prestart(pixels)


def run(args: argparse.Namespace) -> int:
    import logging

    if args.worker_kind != "thread":
        prestart_zygote()  # a no-op when `sfmloc` (cli.main) already started it

    from ..config import load_config
    from ..server.app import run_server
    from ..server.config import ServerConfig
    from ..server.logfmt import setup_logging

    conf = load_config(ServerConfig, args.config, overrides=overrides_from_args(args))
    level = (
        logging.WARNING if args.quiet else (logging.DEBUG if args.verbose >= 2 else logging.INFO)
    )
    setup_logging(conf.log_format, level)  # the server's own structured format
    return run_server(conf)
