"""sfmloc auth: tokens for a server with authentication."""

from __future__ import annotations

import argparse
import textwrap


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "auth",
        help="make bearer tokens for a server with authentication",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=textwrap.dedent("""\
            Tokens for `sfmloc serve --tokens FILE`: the file keeps each token's SHA-256, an
            identity and its roles; the token itself is printed once and never stored.

            roles:
              localize  Relocalize, StreamLocalize (as its own identity), ListMaps, GetMap,
                        ListSessions and ResetSession of its own sessions
              admin     everything: LoadMap, UnloadMap, other clients' sessions

            Clients pass the token with --token (or $SFMLOC_TOKEN) or LocalizationClient(token=...).
            Without TLS (--tls-cert/--tls-key) the server accepts tokens only on loopback."""),
    )
    ss = p.add_subparsers(dest="auth_command", metavar="ACTION", required=True)
    a = ss.add_parser("add-token", help="make a token, append its hash to FILE, print the token")
    a.add_argument("file", help="tokens file (JSON; created if missing)")
    a.add_argument(
        "--identity", required=True, help="who the token is for (a device's client id, a person)"
    )
    a.add_argument(
        "--role",
        action="append",
        choices=["localize", "admin"],
        required=True,
        help="a role (repeatable)",
    )
    z = ss.add_parser(
        "zenoh-acl",
        help="write the server's Zenoh configuration: TLS and access control per device",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=textwrap.dedent("""\
            A Zenoh configuration for `sfmloc serve --zenoh-config FILE` in which each device
            may publish frames and read poses only under its own client id (Zenoh's
            access_control, default deny), over TLS. Devices are identified by the common name
            of their TLS client certificate (--identify cert: mutual TLS) or by a Zenoh user
            name (--identify user: transport/auth/usrpwd, a dictionary file of user:password
            lines). The client id a device streams under must equal that name. Devices connect
            in Zenoh client mode (see README, Deployment; docker/zenoh-device.json5)."""),
    )
    z.add_argument("--device", action="append", default=[], help="a device's client id")
    z.add_argument(
        "--admin", action="append", default=[], help="a name with every right (builder, operator)"
    )
    z.add_argument("--identify", choices=["cert", "user"], default="cert", help="default cert")
    z.add_argument("--listen", default="tls/0.0.0.0:7447", help="default %(default)s")
    z.add_argument("--tls-ca", default="/certs/ca.pem", help="default %(default)s")
    z.add_argument("--tls-cert", default="/certs/server.pem", help="default %(default)s")
    z.add_argument("--tls-key", default="/certs/server.key", help="default %(default)s")
    z.add_argument(
        "--users-file",
        default="/certs/zenoh-users.txt",
        help="with --identify user: the user:password dictionary (default %(default)s)",
    )
    z.add_argument("--out", help="write here (default: standard output)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.auth_command == "zenoh-acl":
        return _zenoh_acl(args)
    from ..server.auth import add_token

    print(add_token(args.file, args.identity, args.role))
    return 0


def _zenoh_acl(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..server.zenoh_acl import render, server_config

    conf = server_config(
        args.device,
        args.admin,
        args.identify,
        args.listen,
        args.tls_ca,
        args.tls_cert,
        args.tls_key,
        args.users_file,
    )
    text = render(conf, "sfmloc server Zenoh configuration (sfmloc auth zenoh-acl)")
    if args.out:
        Path(args.out).write_text(text)
    else:
        print(text, end="")
    return 0
