"""Finding servers on a Zenoh network: each server holds a liveliness token
``sfmloc/servers/<id>`` and answers ``sfmloc/servers/<id>/info`` with a ``ServerInfo``."""

from __future__ import annotations

import logging
from typing import Any

from .errors import WireError
from .wire import ROOT, SERVER_INFO_KEYEXPR, SERVERS_KEYEXPR, ServerInfo, decode_server_info

log = logging.getLogger(__name__)


def list_server_ids(session: Any, timeout: float = 2.0) -> list[str]:
    """Ids of the servers alive now (their liveliness tokens)."""
    ids = []
    for reply in session.liveliness().get(SERVERS_KEYEXPR, timeout=timeout):
        if reply.ok is not None:
            ids.append(str(reply.ok.key_expr)[len(f"{ROOT}/servers/") :])
    return sorted(set(ids))


def query_servers(session: Any, timeout: float = 2.0, server_id: str = "*") -> list[ServerInfo]:
    """``ServerInfo`` of every server that answers within ``timeout`` (maps, sessions, load)."""
    key = SERVER_INFO_KEYEXPR if server_id == "*" else f"{ROOT}/servers/{server_id}/info"
    out = []
    for reply in session.get(key, timeout=timeout):
        if reply.ok is None:
            continue
        try:
            out.append(decode_server_info(reply.ok.payload.to_bytes()))
        except WireError as exc:
            log.warning("invalid server info from %s: %s", reply.ok.key_expr, exc)
    return sorted(out, key=lambda i: i.server_id)
