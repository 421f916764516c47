"""sfmloc sessions: the client sessions of a running server (gRPC)."""

from __future__ import annotations

import argparse

from ._clientopts import add_grpc_option, grpc_client


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sessions",
        help="list or reset the client sessions of a running server",
        description="Client sessions of a running server: one per streaming client and map, "
        "with frame counts, drops (stale frames skipped) and latencies.",
    )
    ss = p.add_subparsers(dest="sessions_command", metavar="ACTION", required=True)
    a = ss.add_parser("list", help="active sessions")
    a.add_argument("--map", default="", help="only this map")
    add_grpc_option(a)
    a = ss.add_parser(
        "reset", help="forget a client's tracks and filter (its next frame relocalizes)"
    )
    a.add_argument("client_id")
    a.add_argument("--map", default="", help="only on this map")
    add_grpc_option(a)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from sfmloc_client import RemoteError
    from sfmloc_client.convert import STATUS_FROM_PB

    from ..errors import InputError

    try:
        with grpc_client(args) as c:
            if args.sessions_command == "list":
                rows = c.list_sessions(args.map)
                print(
                    f"{'client':<24} {'map':<16} {'transport':<9} {'frames':>7} {'localized':>9} "
                    f"{'dropped':>7} "
                    f"{'last ms':>8} {'mean ms':>8} {'status':<12} {'idle s':>7}"
                )
                for s in rows:
                    print(
                        f"{s.client_id:<24} {s.map:<16} {s.transport:<9} {s.frames:>7} "
                        f"{s.localized:>9} {s.dropped:>7} "
                        f"{s.last_latency_ms:>8.1f} {s.mean_latency_ms:>8.1f} "
                        f"{STATUS_FROM_PB.get(s.status, '-'):<12} {s.idle_s:>7.1f}"
                    )
                if not rows:
                    print("(no sessions)")
            else:
                c.reset_session(args.client_id, args.map)
                print(f"reset {args.client_id}")
    except RemoteError as exc:
        raise InputError(str(exc)) from None
    return 0
