"""sfmloc maps: list, show, load and unload the maps of a running server (gRPC)."""

from __future__ import annotations

import argparse

from ._clientopts import add_grpc_option, grpc_client


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "maps",
        help="list/show/load/unload the maps of a running server",
        description="Manage the maps a running server hosts (gRPC). Loading a map that is "
        "already loaded replaces it atomically: live sessions relocalize on the new one.",
    )
    ms = p.add_subparsers(dest="maps_command", metavar="ACTION", required=True)
    a = ms.add_parser("list", help="maps loaded on the server")
    add_grpc_option(a)
    a = ms.add_parser("show", help="details of one map")
    a.add_argument("name")
    add_grpc_option(a)
    a = ms.add_parser(
        "load",
        help="load (or replace) a bundle from the server's maps folders",
        description="Load (or replace) a bundle the server can see: a map name (a folder "
        "in the server's --maps folder or its map_roots), or a path inside "
        "those folders. Paths elsewhere are refused (PERMISSION_DENIED).",
    )
    a.add_argument("path", help="map name, or bundle folder inside the server's maps folders")
    a.add_argument("--name", default="", help="name to serve it under (default: the bundle's own)")
    add_grpc_option(a)
    a = ms.add_parser("unload", help="unload a map (its sessions end)")
    a.add_argument("name")
    add_grpc_option(a)
    p.set_defaults(func=run)


def _row(m) -> str:  # noqa: ANN001 - a MapInfo message
    return (
        f"{m.name:<20} {m.build_id:<28} {m.points:>8} {m.descriptors:>11} {m.images:>6} "
        f"{m.memory_mb:>8.1f} {m.sessions:>8}  {m.path}"
    )


def _details(m) -> str:  # noqa: ANN001 - a MapInfo message
    """``maps show``: one labelled field per line (not the message's protobuf text form)."""
    rows = [
        ("name", m.name),
        ("build id", m.build_id),
        ("path", m.path),
        ("points", f"{m.points:,}"),
        ("descriptors", f"{m.descriptors:,}"),
        ("images", f"{m.images:,}"),
        ("clusters", f"{m.clusters:,}"),
        ("memory", f"{m.memory_mb:.1f} MB"),
        ("sessions", f"{m.sessions}"),
        ("loaded", m.loaded_utc or "-"),
    ]
    if m.submaps:  # a sub-map set served with --map-memory
        rows.insert(7, ("sub-maps", f"{m.submaps}, {m.map_memory_mb:g} MB per worker"))
        rows.insert(8, ("resident", f"{m.resident_mb:.1f} MB (the most one worker holds)"))
    return "\n".join(f"{k + ':':<13} {v}" for k, v in rows)


def run(args: argparse.Namespace) -> int:
    from sfmloc_client import RemoteError

    from ..errors import InputError

    try:
        with grpc_client(args) as c:
            if args.maps_command == "list":
                maps = c.list_maps()
                print(
                    f"{'name':<20} {'build_id':<28} {'points':>8} {'descriptors':>11} "
                    f"{'images':>6} "
                    f"{'mem MB':>8} {'sessions':>8}  path"
                )
                for m in maps:
                    print(_row(m))
                if not maps:
                    print("(no maps loaded)")
            elif args.maps_command == "show":
                print(_details(c.get_map(args.name)))
            elif args.maps_command == "load":
                m = c.load_map(args.path, args.name, timeout=args.timeout)
                print(
                    f"loaded {m.name} (build {m.build_id}, {m.points} points, {m.memory_mb:.1f} MB)"
                )
            else:
                r = c.unload_map(args.name)
                print(f"unloaded {args.name} ({r.sessions_closed} sessions closed)")
    except RemoteError as exc:
        raise InputError(str(exc)) from None
    return 0
