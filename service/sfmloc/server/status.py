"""gRPC status codes and worker-boundary encoding of the one exception table.

The table itself (``sfmloc_client.errors.STATUS_TABLE``) is shared with the client and the
builder; gRPC calls end with its code (``sfmloc.interceptors`` applies it), Zenoh error
replies carry the code's name in ``error.code``. Errors cross the worker-process boundary as
``{"type": class name, "message": ...}`` and are rebuilt by name from the hierarchy (nothing
is unpickled).
"""

from __future__ import annotations

import grpc
from sfmloc_client.errors import InternalError, code_of, error_class, message_of
from sfmloc_client.wire import ErrorInfo

from ..interceptors import status_of

__all__ = [
    "InternalError",
    "abort",
    "error_from_wire",
    "error_info",
    "error_to_wire",
    "message_of",
    "status_of",
]


def error_info(exc: BaseException) -> ErrorInfo:
    """What a Zenoh error reply carries."""
    return ErrorInfo(code_of(exc), message_of(exc))


def error_to_wire(exc: BaseException) -> dict[str, str]:
    name = type(exc).__name__
    name = name if error_class(name).__name__ == name else "InternalError"
    return {"type": name, "message": message_of(exc)}


def error_from_wire(d: dict[str, str]) -> Exception:
    return error_class(str(d.get("type")))(str(d.get("message", "")))


async def abort(context: "grpc.aio.ServicerContext", exc: BaseException) -> None:
    """End a gRPC call with the status the table gives ``exc`` (raises, as ``abort`` does)."""
    await context.abort(status_of(exc), message_of(exc))
