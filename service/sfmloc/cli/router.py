"""sfmloc router: a Zenoh router, for deployments with several servers and many clients."""

from __future__ import annotations

import argparse
import signal
import threading

DESCRIPTION = """\
Run a Zenoh router (the equivalent of zenohd, from the eclipse-zenoh package sfmloc already
depends on). Servers, builders and clients then run in client mode and connect to it:

  sfmloc router --listen tcp/0.0.0.0:7447
  sfmloc serve --maps maps --zenoh-mode client --zenoh-connect tcp/ROUTER:7447 --server-id s1
  sfmloc serve --maps maps --zenoh-mode client --zenoh-connect tcp/ROUTER:7447 --server-id s2
  sfmloc stream --map kitchen --source video.mp4 --camera camera.json --server auto \\
      --zenoh-mode client --zenoh-connect tcp/ROUTER:7447

Clients in client mode talk only to the router (no peer-to-peer links, no multicast), so the
router is the one address to open in a firewall and the place for TLS and access control
(--config FILE: a zenohd JSON5 file; see README, Deployment). Runs until Ctrl-C or SIGTERM.
"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "router",
        help="run a Zenoh router (zenohd equivalent) for servers and clients in client mode",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--listen",
        metavar="ENDPOINT",
        action="append",
        default=[],
        help="listen endpoint, e.g. tcp/0.0.0.0:7447 (repeatable; default tcp/0.0.0.0:7447)",
    )
    p.add_argument(
        "--connect",
        metavar="ENDPOINT",
        action="append",
        default=[],
        help="another router to join (repeatable)",
    )
    p.add_argument("--config", metavar="FILE", help="a Zenoh JSON5 config file (TLS, ACL, ...)")
    p.add_argument(
        "--multicast",
        action="store_true",
        help="multicast scouting on (default off: explicit endpoints only)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import zenoh

    from sfmloc_client import make_zenoh_config

    from ..errors import ConfigError

    listen = args.listen or ([] if args.config else ["tcp/0.0.0.0:7447"])
    try:
        conf = make_zenoh_config(
            "router", listen, args.connect, multicast=args.multicast, config_file=args.config
        )
    except Exception as exc:  # noqa: BLE001 - zenoh raises ZError/ValueError on bad settings
        raise ConfigError(f"invalid Zenoh configuration: {exc}") from None
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        session = zenoh.open(conf)
    except Exception as exc:  # noqa: BLE001 - e.g. the port is taken
        raise ConfigError(f"cannot start the router: {exc}") from None
    with session:
        print(
            f"sfmloc router {session.zid()} listening on {', '.join(listen) or '(config)'}",
            flush=True,
        )
        stop.wait()
    return 0
