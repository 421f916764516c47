"""sfmloc servers: discover running servers on the Zenoh network."""

from __future__ import annotations

import argparse

from ._clientopts import add_zenoh_options, zenoh_config


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "servers",
        help="discover running servers (Zenoh) and what they host",
        description="Query sfmloc/servers/*/info on the Zenoh network: each server's maps, "
        "sessions, load and gRPC address.",
    )
    p.add_argument(
        "--wait",
        type=float,
        default=2.0,
        metavar="S",
        help="how long to collect answers (default 2)",
    )
    add_zenoh_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import time

    import zenoh

    from sfmloc_client import query_servers

    with zenoh.open(zenoh_config(args)) as z:
        time.sleep(min(args.wait, 0.5))  # let scouting find peers before asking
        infos = query_servers(z, timeout=args.wait)
    for i in infos:
        maps = ", ".join(f"{m.get('name')} ({m.get('build_id')})" for m in i.maps) or "-"
        load = i.load
        print(
            f"{i.server_id}: {'ready' if i.ready else 'starting'}, grpc {i.grpc or '-'}, "
            f"{i.workers} workers, "
            f"{i.sessions} sessions, {load.get('frames_per_s', 0):.1f} frames/s, busy "
            f"{100 * load.get('busy', 0):.0f}%\n"
            f"    maps: {maps}"
        )
    if not infos:
        print("no servers answered")
    return 0 if infos else 1
