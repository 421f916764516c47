"""Which server answers a client's frames when several host its map (one owner per session).

The client decides: it picks one of the ready servers hosting the map and names it in every
frame (``Frame.server``); the others ignore those frames, so no frame gets two poses. The pick
is rendezvous (highest-random-weight) hashing of ``map/client`` over the server ids by default:
stable (a client keeps its server across restarts of the client), spread evenly, and when a
server leaves only its own clients move. ``least-loaded`` picks the server with the fewest
sessions instead (ties by rendezvous).

The owner's liveliness token (``sfmloc/servers/<id>``) is watched: when it drops (the server
stopped, crashed, or its network went away), ``owner_lost`` becomes true and ``repick`` moves
the client to another server hosting the map; the new server relocalizes from the next frame.
A server that joins later is used by sessions that start after it (existing ones stay).
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Iterable
from typing import Any

from .discovery import query_servers
from .keys import ROOT, SERVERS_KEYEXPR
from .wire import ServerInfo

POLICIES = ("rendezvous", "least-loaded")


def rendezvous_weight(map_name: str, client_id: str, server_id: str) -> int:
    digest = hashlib.blake2b(
        f"{map_name}\0{client_id}\0{server_id}".encode(), digest_size=8
    ).digest()
    return int.from_bytes(digest, "big")


def rendezvous_owner(map_name: str, client_id: str, server_ids: Iterable[str]) -> str | None:
    """The server of ``server_ids`` that owns ``client_id`` on ``map_name`` (None: no server)."""
    ids = list(server_ids)
    if not ids:
        return None
    return max(ids, key=lambda s: (rendezvous_weight(map_name, client_id, s), s))


def hosts(info: ServerInfo, map_name: str) -> bool:
    return info.ready and any(m.get("name") == map_name for m in info.maps)


def choose(
    infos: Iterable[ServerInfo], map_name: str, client_id: str, policy: str = "rendezvous"
) -> str | None:
    """The server of ``infos`` a new session of ``client_id`` on ``map_name`` should use."""
    if policy not in POLICIES:
        raise ValueError(f"placement policy must be one of {', '.join(POLICIES)}, got {policy!r}")
    candidates = [i for i in infos if hosts(i, map_name)]
    if not candidates:
        return None
    if policy == "least-loaded":
        fewest = min(i.sessions for i in candidates)
        candidates = [i for i in candidates if i.sessions == fewest]
    return rendezvous_owner(map_name, client_id, [i.server_id for i in candidates])


class Placement:
    """The owner of one client's session on one map, kept up to date from liveliness."""

    def __init__(
        self,
        session: Any,
        map_name: str,
        client_id: str,
        policy: str = "rendezvous",
        query_timeout: float = 1.0,
        late_timeout: float = 5.0,
    ) -> None:
        if policy not in POLICIES:
            raise ValueError(
                f"placement policy must be one of {', '.join(POLICIES)}, got {policy!r}"
            )
        self.session, self.map_name, self.client_id = session, map_name, client_id
        self.policy, self.query_timeout = policy, query_timeout
        # How long ``pick`` waits for live servers (their liveliness token seen) that did not
        # answer within ``query_timeout``: a server on a busy machine answers late, and
        # picking without it would give this client another server than rendezvous names (a
        # client must keep its server across restarts; tests/test_placement.py at load ~14).
        self.late_timeout = late_timeout
        self.owner: str | None = None
        self.moves = 0  # times the owner changed after the first pick
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._known: dict[str, ServerInfo] = {}  # servers hosting the map, from the last query
        self._sub = session.liveliness().declare_subscriber(
            SERVERS_KEYEXPR, self._on_token, history=True
        )

    def _on_token(self, sample: Any) -> None:
        import zenoh

        sid = str(sample.key_expr)[len(f"{ROOT}/servers/") :]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(sid)
            else:
                self._alive.discard(sid)

    @property
    def owner_lost(self) -> bool:
        with self._lock:
            return self.owner is not None and self.owner not in self._alive

    def pick(self) -> str | None:
        """Ask the servers (``query_timeout``) and choose; None when no ready server hosts the
        map yet."""
        infos = query_servers(self.session, self.query_timeout)
        with self._lock:
            late = self._alive - {i.server_id for i in infos}
        if late and self.late_timeout > self.query_timeout:
            # Ask again, longer: a Zenoh query ends when every server answered (or at the
            # timeout), so only a server that is live and slow makes it wait.
            again = query_servers(self.session, self.late_timeout)
            answered = {i.server_id for i in infos}
            infos += [i for i in again if i.server_id not in answered]
        infos = [i for i in infos if hosts(i, self.map_name)]
        with self._lock:
            self._known = {i.server_id: i for i in infos}
            alive = [i for i in infos if i.server_id in self._alive or not self._alive]
        chosen = choose(alive, self.map_name, self.client_id, self.policy)
        self._set(chosen)
        return chosen

    def repick(self) -> str | None:
        """After the owner was lost: another live server known to host the map, at once (no
        query), or, when none is known, ``pick``."""
        with self._lock:
            alive = [i for sid, i in self._known.items() if sid in self._alive]
        chosen = choose(alive, self.map_name, self.client_id, self.policy)
        if chosen is None:
            return self.pick()
        self._set(chosen)
        return chosen

    def _set(self, chosen: str | None) -> None:
        with self._lock:
            if chosen is not None and self.owner is not None and chosen != self.owner:
                self.moves += 1
            self.owner = chosen

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:  # noqa: BLE001 - the session may be closed already
            pass
