"""The name rule and the Zenoh key expressions (the table is in ``sfmloc_client.wire``'s
docstring).

A map name, client id or server id is 1-64 characters of ``[A-Za-z0-9_.-]`` starting with a
letter or digit: each is a single key-expression chunk and appears in file names. The server,
the builder and the map bundle check names with ``check_name``.
"""

from __future__ import annotations

import re

from .errors import WireError

ROOT = "sfmloc"
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
NAME_RULE = "use 1-64 letters, digits, '_', '-' or '.', starting with a letter or digit"

FRAME_KEYEXPR = f"{ROOT}/*/*/frame"
SERVERS_KEYEXPR = f"{ROOT}/servers/*"
SERVER_INFO_KEYEXPR = f"{ROOT}/servers/*/info"
MAPS_KEYEXPR = f"{ROOT}/maps/*"
BUNDLES_KEYEXPR = f"{ROOT}/bundles/**"


def check_name(value: str, what: str = "name") -> str:
    """``value`` when it is a valid map name, client id or server id; ``WireError`` naming the
    rule otherwise."""
    if not isinstance(value, str) or not NAME_RE.match(value):
        raise WireError(f"invalid {what} {value!r}: {NAME_RULE}")
    return value


def frame_key(map_name: str, client_id: str, server_id: str = "") -> str:
    """Where a client publishes its frames: ``sfmloc/<map>/<client>/frame`` reaches every server
    hosting the map; with ``server_id``, ``.../frame/<server>`` reaches only that server (one
    owner per session: the others never receive the frame, so N servers do not each take in
    every client's images)."""
    key = f"{ROOT}/{check_name(map_name, 'map name')}/{check_name(client_id, 'client id')}/frame"
    return f"{key}/{check_name(server_id, 'server id')}" if server_id else key


def addressed_frame_keyexpr(server_id: str) -> str:
    """What a server subscribes to, besides ``FRAME_KEYEXPR``: frames addressed to it."""
    return f"{FRAME_KEYEXPR}/{check_name(server_id, 'server id')}"


def pose_key(map_name: str, client_id: str) -> str:
    return f"{ROOT}/{check_name(map_name, 'map name')}/{check_name(client_id, 'client id')}/pose"


def parse_frame_key(key: str) -> tuple[str, str]:
    """``(map, client)`` of a ``sfmloc/<map>/<client>/frame`` key, or of one addressed to a
    server (``.../frame/<server>``); names not yet validated."""
    parts = str(key).split("/")
    if len(parts) not in (4, 5) or parts[0] != ROOT or parts[3] != "frame":
        raise WireError(f"not a frame key: {key!r}")
    return parts[1], parts[2]


def server_token_key(server_id: str) -> str:
    return f"{ROOT}/servers/{check_name(server_id, 'server id')}"


def server_info_key(server_id: str) -> str:
    return f"{server_token_key(server_id)}/info"


def map_announce_key(name: str) -> str:
    return f"{ROOT}/maps/{check_name(name, 'map name')}"


def bundle_key(name: str, build_id: str) -> str:
    """Queryable of a builder: the file list of the bundle ``name`` at ``build_id``."""
    return f"{ROOT}/bundles/{check_name(name, 'map name')}/{check_name(build_id, 'build id')}"


def bundle_file_key(name: str, build_id: str, file: str) -> str:
    """Queryable of a builder: bytes of one file of a bundle (``?offset=N;size=M``)."""
    return f"{bundle_key(name, build_id)}/{check_name(file, 'bundle file name')}"
