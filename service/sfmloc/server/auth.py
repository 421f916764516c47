"""Token authentication and roles for the gRPC API.

A tokens file (JSON) lists who may call, by the SHA-256 of their bearer token (the tokens
themselves are never stored; ``sfmloc auth add-token`` makes one and prints it once)::

    {"tokens": [{"identity": "drone-7", "roles": ["localize"], "sha256": "<hex>"},
                {"identity": "ops", "roles": ["admin"], "sha256": "<hex>"}]}

Clients send ``authorization: Bearer <token>`` metadata. Roles:

- ``localize``: Relocalize, StreamLocalize (its sessions are named by the caller's identity),
  ListMaps, GetMap, and ListSessions / ResetSession of its own sessions;
- ``admin``: everything, LoadMap and UnloadMap included, and other clients' sessions.

Health and reflection stay open (a load balancer's probe carries no token). A missing or
unknown token is UNAUTHENTICATED; a known one without the role is PERMISSION_DENIED.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import secrets
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc

from ..errors import ConfigError
from ..interceptors import same_kind

ROLES = ("localize", "admin")
SERVICE = "/sfmloc.v1.Localization/"
# The role each method needs; methods of other services (health, reflection) need none.
METHOD_ROLES = {
    "Relocalize": "localize",
    "StreamLocalize": "localize",
    "ListMaps": "localize",
    "GetMap": "localize",
    "ListSessions": "localize",
    "ResetSession": "localize",
    "LoadMap": "admin",
    "UnloadMap": "admin",
}


@dataclass(frozen=True)
class Identity:
    name: str
    roles: frozenset[str]

    @property
    def admin(self) -> bool:
        return "admin" in self.roles

    def may(self, role: str) -> bool:
        return self.admin or role in self.roles


def token_sha256(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


class TokenTable:
    """Who a bearer token is (compared by SHA-256, in constant time per entry)."""

    def __init__(self, entries: Sequence[tuple[str, Identity]]) -> None:
        self._entries = list(entries)

    @classmethod
    def load(cls, path: str | Path) -> TokenTable:
        p = Path(path)
        try:
            raw = json.loads(p.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ConfigError(f"tokens file {p}: unreadable ({exc})") from None
        items = raw.get("tokens") if isinstance(raw, dict) else None
        if not isinstance(items, list):
            raise ConfigError(f'tokens file {p}: expected {{"tokens": [...]}}')
        entries = []
        for k, it in enumerate(items):
            if (
                not isinstance(it, dict)
                or not isinstance(it.get("sha256"), str)
                or len(it["sha256"]) != 64
            ):
                raise ConfigError(f"tokens file {p}: entry {k} needs a 64-hex-digit sha256")
            roles = it.get("roles", [])
            if not isinstance(roles, list) or not roles or any(r not in ROLES for r in roles):
                raise ConfigError(f"tokens file {p}: entry {k} needs roles from {', '.join(ROLES)}")
            name = it.get("identity")
            if not isinstance(name, str) or not name:
                raise ConfigError(f"tokens file {p}: entry {k} needs an identity")
            entries.append((it["sha256"].lower(), Identity(name, frozenset(roles))))
        return cls(entries)

    def __len__(self) -> int:
        return len(self._entries)

    def identify(self, metadata: Sequence[tuple[str, Any]] | None) -> Identity | None:
        token = bearer_token(metadata)
        if token is None:
            return None
        digest = token_sha256(token)
        found = None
        for h, ident in self._entries:  # no early exit: the time does not depend on the match
            if hmac.compare_digest(h, digest):
                found = ident
        return found


def bearer_token(metadata: Sequence[tuple[str, Any]] | None) -> str | None:
    for key, value in metadata or ():
        if key == "authorization":
            v = value.decode() if isinstance(value, bytes) else str(value)
            if v.startswith("Bearer "):
                return v[len("Bearer ") :].strip() or None
    return None


def add_token(path: str | Path, identity: str, roles: Sequence[str]) -> str:
    """Make a random token for ``identity`` with ``roles``, append its hash to the tokens file
    (created if missing, written atomically) and return the token (shown once)."""
    if not roles or any(r not in ROLES for r in roles):
        raise ConfigError(f"roles must be from {', '.join(ROLES)}")
    p = Path(path)
    data: dict[str, Any] = {"tokens": []}
    if p.exists():
        TokenTable.load(p)  # refuse to extend a broken file
        data = json.loads(p.read_text())
    # Clients pass it as `--token TOKEN`: a token starting with "-" (1 in 64 of token_urlsafe's)
    # reads as an option to argparse ("expected one argument"), so such a draw is drawn again.
    token = secrets.token_urlsafe(32)
    while token.startswith("-"):
        token = secrets.token_urlsafe(32)
    data["tokens"].append(
        {"identity": identity, "roles": sorted(set(roles)), "sha256": token_sha256(token)}
    )
    tmp = p.with_name(f".{p.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.chmod(0o600)
    tmp.replace(p)
    return token


def _deny(
    handler: grpc.RpcMethodHandler, code: grpc.StatusCode, message: str
) -> grpc.RpcMethodHandler:
    """A handler of the same kind as ``handler`` that only refuses the call."""

    async def refuse(request: Any, context: grpc.aio.ServicerContext) -> None:
        await context.abort(code, message)

    return same_kind(handler, lambda behavior, streaming: refuse)


class AuthInterceptor(grpc.aio.ServerInterceptor):
    """Refuses Localization calls without a valid token (UNAUTHENTICATED) or the method's role
    (PERMISSION_DENIED), before the request is read."""

    def __init__(self, table: TokenTable) -> None:
        self.table = table

    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler]],
        details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler:
        handler = await continuation(details)
        method = details.method or ""
        if handler is None or not method.startswith(SERVICE):
            return handler
        role = METHOD_ROLES.get(method[len(SERVICE) :], "admin")  # a method added later: admin only
        ident = self.table.identify(details.invocation_metadata)
        if ident is None:
            return _deny(
                handler,
                grpc.StatusCode.UNAUTHENTICATED,
                "this server needs a token: send 'authorization: Bearer <token>' (--token)",
            )
        if not ident.may(role):
            return _deny(
                handler,
                grpc.StatusCode.PERMISSION_DENIED,
                f"{ident.name!r} may not call {method[len(SERVICE) :]} (needs the {role} role)",
            )
        return handler


def caller(table: TokenTable | None, context: grpc.aio.ServicerContext) -> Identity | None:
    """Who is calling (None when authentication is off)."""
    if table is None:
        return None
    return table.identify(context.invocation_metadata())
