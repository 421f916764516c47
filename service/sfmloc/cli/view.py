"""sfmloc view: a live web viewer of the maps and of every client localizing against them."""

from __future__ import annotations

import argparse
import textwrap

from ._clientopts import add_zenoh_options, zenoh_config

DESCRIPTION = textwrap.dedent(
    """\
    Serve a web page that shows a map's point cloud (the bundle's point colours) and the
    cameras it was built from, and, live, every client localizing against it: its camera
    (coloured by status: TRACKING green, RELOCALIZED blue, UNVERIFIED orange, LOST red, at
    its last pose), its recent trajectory, pose rate, server latency, inliers and the
    reason of its last LOST frame.

    The viewer listens to the pose messages servers publish on sfmloc/<map>/<client>/pose
    over Zenoh (it sends nothing; connect it like a client, --zenoh-connect to the server
    or a router) and reads the bundles from --maps (the server's maps folders; a map the
    server loaded from elsewhere shows its clients but no point cloud). Open the printed
    address in a browser; ?map=NAME picks the map. It binds to loopback unless --host says
    otherwise, and has no authentication: put it behind a proxy before exposing it.
    """
)

EPILOG = textwrap.dedent(
    """\
    examples:
      sfmloc view --maps maps --zenoh-connect tcp/127.0.0.1:7447
      sfmloc view --maps maps --host 0.0.0.0 --port 8090 --zenoh-connect tcp/server:7447
    """
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="live web viewer: map point cloud, clients' poses, trajectories, status, latency",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--maps",
        action="append",
        metavar="DIR",
        help="folder of map bundles (repeatable; default maps)",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8090, help="HTTP port (default 8090; 0: any)")
    p.add_argument(
        "--max-points",
        type=int,
        default=300_000,
        metavar="N",
        help="draw at most N map points (a fixed random subset of larger maps; default 300000)",
    )
    p.add_argument(
        "--trail",
        type=int,
        default=600,
        metavar="N",
        help="positions kept per client for a page that opens later (default 600)",
    )
    p.add_argument(
        "--forget-after",
        type=float,
        default=60.0,
        metavar="S",
        help="drop a client silent this long from the page (default 60)",
    )
    add_zenoh_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import signal
    import sys
    import threading

    import zenoh

    from ..errors import InputError
    from ..viewer.http import ViewerServer
    from ..viewer.live import LiveState, PoseFeed

    if args.max_points < 1 or args.trail < 1 or not args.forget_after > 0:
        raise InputError("--max-points and --trail must be at least 1, --forget-after above 0")
    state = LiveState(trail=args.trail, forget_after_s=args.forget_after)
    try:
        viewer = ViewerServer(
            args.maps or ["maps"],
            state,
            host=args.host,
            port=args.port,
            max_points=args.max_points,
        )
    except OSError as exc:
        raise InputError(f"cannot listen on {args.host}:{args.port}: {exc.strerror}") from None
    # SIGINT and SIGTERM stop it, by handlers of its own (as `sfmloc serve` and `router`): a
    # command started in the background of a script (`make test &`) inherits SIGINT ignored,
    # and Python then raises no KeyboardInterrupt: the viewer ignored Ctrl-C and kill -INT
    # (test_view_command_serves_until_interrupted failed in every such full-suite run).
    stop = threading.Event()
    caught: list[int] = []

    def on_signal(signum: int, _frame: object) -> None:
        caught.append(signum)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    with zenoh.open(zenoh_config(args)) as z, PoseFeed(z, state), viewer:
        maps = ", ".join(sorted(viewer.maps())) or "none yet"
        print(f"sfmloc view on {viewer.url} (maps: {maps}); Ctrl-C stops", file=sys.stderr)
        stop.wait()
    print(f"sfmloc view: stopped ({signal.Signals(caught[0]).name})", file=sys.stderr)
    return 128 + caught[0]  # as the shell reports a command a signal ended (Ctrl-C: 130)
