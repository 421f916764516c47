"""The one exception table's server side: Zenoh error replies and errors across the
worker-process boundary.

The table itself (``sfmloc_client.errors.STATUS_TABLE``) is shared with the client and the
builder; gRPC calls end with its code (``sfmloc.interceptors`` applies it), Zenoh error
replies carry the code's name in ``error.code``. Errors cross the worker-process boundary as
``{"type": class name, "message": ...}`` and are rebuilt by name from the hierarchy (nothing
is unpickled).
"""

from __future__ import annotations

from typing import Any

from sfmloc_client.errors import InternalError, code_of, error_class, message_of
from sfmloc_client.wire import ErrorInfo

__all__ = [
    "InternalError",
    "error_from_wire",
    "error_info",
    "error_to_wire",
    "message_of",
]


def error_info(exc: BaseException) -> ErrorInfo:
    """What a Zenoh error reply carries."""
    return ErrorInfo(code_of(exc), message_of(exc))


def error_to_wire(exc: BaseException) -> dict[str, str]:
    # Only our own classes keep their name (a foreign KeyError is an internal error).
    ours = error_class(type(exc).__name__) is type(exc)
    return {"type": type(exc).__name__ if ours else "InternalError", "message": message_of(exc)}


def error_from_wire(d: dict[str, str]) -> Exception:
    return error_class(str(d.get("type")))(str(d.get("message", "")))


def __getattr__(name: str) -> Any:
    # ``status_of`` (gRPC codes) loads grpc: only on use, so that engine workers, which import
    # this module through ``protocol``, do not import grpc (0.2-0.6 s of a worker's start).
    if name == "status_of":
        from ..interceptors import status_of

        return status_of
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
