"""sfmloc bench-transport: transport overhead and multi-client scaling of the server."""

from __future__ import annotations

import argparse
import textwrap
from pathlib import Path

_SHARED = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "redkitchen-seq01"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench-transport",
        help="measure the server: Zenoh overhead vs the engine, clients at camera rate",
        description=textwrap.dedent(
            """\
            Benchmarks of the localization server on this machine (loopback):
              wire      frame envelope vs Zenoh attachment (codec and loopback time)
              overhead  frame published -> pose received, against the in-process engine
              engine    Localizers flat out in threads vs processes (no transport)
              clients   N clients at R Hz (own Zenoh session each), process workers:
                        frames dropped per client, latency p50/p99
              workers   the same with thread workers (the GIL comparison)
              memory    resident memory (RSS, PSS, anonymous) of server + workers with 1,
                        2 and 4 workers: each map's index is held once, not per worker
            The server runs as a subprocess (sfmloc serve). Numbers are noisy when other
            processes load the CPU; the load average is printed with them."""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--maps", default="maps", help="folder holding the map bundle (default maps)")
    p.add_argument("--map", default="redkitchen", help="map name (default redkitchen)")
    p.add_argument(
        "--frames",
        default=str(_SHARED),
        help="folder of JPEG frames (default ../shared/data/redkitchen-seq01)",
    )
    p.add_argument(
        "--camera", default="PINHOLE 640 480 525.505 525.505 320 240", help="camera of the frames"
    )
    p.add_argument(
        "--only",
        default="",
        help="comma-separated sections: wire,overhead,engine,clients,workers,memory (default all)",
    )
    p.add_argument(
        "--n",
        type=int,
        default=200,
        help="frames for the overhead and engine sections (default 200)",
    )
    p.add_argument("--clients", type=int, default=4, help="clients (default 4)")
    p.add_argument(
        "--rate", type=float, default=30.0, help="frames per second per client (default 30)"
    )
    p.add_argument(
        "--duration", type=float, default=20.0, help="seconds per client run (default 20)"
    )
    p.add_argument("--workers", type=int, default=0, help="server workers (default: one per core)")
    p.add_argument(
        "--max-pending",
        type=int,
        default=1,
        help="the server's --max-pending (default 1: latest frame only)",
    )
    p.add_argument(
        "--encoding",
        choices=["jpeg", "gray8"],
        default="jpeg",
        help="clients/workers sections: frames as the JPEG files (default) or raw gray8",
    )
    p.add_argument(
        "--relocalize-rate",
        type=float,
        default=0.0,
        metavar="HZ",
        help="clients/workers sections: one more client calls single-image Relocalize "
        "over gRPC at HZ beside the streams (default 0: none)",
    )
    p.add_argument(
        "--relocalize-workers",
        default="",
        metavar="N[,N...]",
        help="clients/workers sections: the server's --relocalize-workers, one run per "
        "value (e.g. 0,1: relocalizations on the stream workers vs their own lane)",
    )
    p.add_argument(
        "--repeat",
        type=int,
        default=3,
        help="engine section: runs per mode, the best is kept (default 3)",
    )
    p.add_argument("--json", metavar="FILE", help="also write the numbers as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # The in-process measurements must run like a server worker: one BLAS/OpenMP thread, set
    # before numpy loads (the benchmark module imports it).
    from ..threads import pin_threads_env

    pin_threads_env(force=True)
    from ..bench.transport import run as bench

    return bench(args)
