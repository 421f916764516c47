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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..server.auth import add_token

    print(add_token(args.file, args.identity, args.role))
    return 0
