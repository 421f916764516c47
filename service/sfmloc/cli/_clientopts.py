"""Options shared by the client commands (not a command itself)."""

from __future__ import annotations

import argparse
import os
import socket
from typing import Any

DEFAULT_GRPC = "localhost:50051"


def add_zenoh_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument(
        "--zenoh-connect",
        metavar="ENDPOINT",
        action="append",
        default=[],
        help="endpoint of the server or a router, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    g.add_argument(
        "--zenoh-listen",
        metavar="ENDPOINT",
        action="append",
        default=[],
        help="listen endpoint (repeatable)",
    )
    g.add_argument("--zenoh-mode", choices=["peer", "client"], default="peer", help="default peer")
    g.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh JSON5 config file")
    g.add_argument(
        "--no-multicast",
        action="store_true",
        help="no multicast scouting (explicit endpoints only)",
    )
    g.add_argument(
        "--zenoh-shm",
        action="store_true",
        help="Zenoh's shared-memory transport on (default off, see README, Zenoh)",
    )


def zenoh_config(args: argparse.Namespace) -> Any:
    from sfmloc_client import make_zenoh_config

    return make_zenoh_config(
        args.zenoh_mode,
        args.zenoh_listen,
        args.zenoh_connect,
        multicast=False if args.no_multicast else None,
        config_file=args.zenoh_config,
        shared_memory=True if args.zenoh_shm else None,
    )


def add_grpc_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--grpc",
        metavar="HOST:PORT",
        default=DEFAULT_GRPC,
        help=f"the server's gRPC address (default {DEFAULT_GRPC})",
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=60.0,
        metavar="S",
        help="call timeout in seconds (default 60)",
    )
    p.add_argument(
        "--token",
        default=os.environ.get("SFMLOC_TOKEN"),
        metavar="TOKEN",
        help="bearer token for a server with authentication (default: $SFMLOC_TOKEN)",
    )
    p.add_argument(
        "--tls-ca",
        metavar="PEM",
        help="use TLS; PEM of the CA that signed the server's certificate",
    )
    p.add_argument(
        "--tls-cert",
        metavar="PEM",
        help="our certificate (servers that require client certificates)",
    )
    p.add_argument("--tls-key", metavar="PEM", help="the key of --tls-cert")


def grpc_client(args: argparse.Namespace) -> Any:
    """A LocalizationClient from the options of ``add_grpc_option``."""
    from sfmloc_client import LocalizationClient

    return LocalizationClient(
        args.grpc,
        timeout=args.timeout,
        token=args.token,
        tls_ca=args.tls_ca,
        tls_cert=args.tls_cert,
        tls_key=args.tls_key,
    )


def default_client_id() -> str:
    host = (
        "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())[:40]
        or "client"
    )
    return f"{host}-{os.getpid()}"


def camera_spec(spec: str) -> Any:
    """CAMERA as in `sfmloc build` (validated by sfmloc.cameras), as the client's CameraSpec."""
    from sfmloc_client import CameraSpec

    from ..cameras import Camera

    cam = Camera.parse(spec)
    return CameraSpec(cam.model, cam.width, cam.height, tuple(float(v) for v in cam.params))
