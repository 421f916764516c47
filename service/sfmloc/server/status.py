"""The one table from exceptions to status codes.

gRPC calls end with ``STATUS_TABLE``'s code; Zenoh error replies carry the code's name in
``error.code`` (see ``sfmloc_client.wire``), so both transports report a failure the same way.
Errors cross the worker-process boundary as ``{"type": class name, "message": ...}`` and are
rebuilt here (by name, from a fixed list: nothing is unpickled).
"""

from __future__ import annotations

import grpc
from sfmloc_client.errors import ImageDataError, MessageTooLargeError, WireError
from sfmloc_client.wire import ErrorInfo

from .. import errors as E

# First match wins: subclasses before their bases.
STATUS_TABLE: tuple[tuple[type[BaseException], grpc.StatusCode], ...] = (
    (E.MapNotFoundError, grpc.StatusCode.NOT_FOUND),
    (E.SessionNotFoundError, grpc.StatusCode.NOT_FOUND),
    (MessageTooLargeError, grpc.StatusCode.RESOURCE_EXHAUSTED),
    (E.OverloadError, grpc.StatusCode.RESOURCE_EXHAUSTED),
    (E.PermissionDeniedError, grpc.StatusCode.PERMISSION_DENIED),
    (E.BundleError, grpc.StatusCode.FAILED_PRECONDITION),
    (E.UnavailableError, grpc.StatusCode.UNAVAILABLE),
    (WireError, grpc.StatusCode.INVALID_ARGUMENT),  # malformed envelope, bad camera/image data
    (E.InputError, grpc.StatusCode.INVALID_ARGUMENT),  # ImageDecodeError, CameraModelError, MessageError
    (E.ConfigError, grpc.StatusCode.INVALID_ARGUMENT),
    (E.BuildError, grpc.StatusCode.FAILED_PRECONDITION),
    (E.SfmlocError, grpc.StatusCode.INTERNAL),
)

# Classes an error from a worker may be rebuilt as.
_BY_NAME: dict[str, type[Exception]] = {
    cls.__name__: cls  # type: ignore[misc]
    for cls, _ in STATUS_TABLE
}
_BY_NAME.update({"ImageDataError": ImageDataError, "ImageDecodeError": E.ImageDecodeError,
                 "CameraModelError": E.CameraModelError, "MessageError": E.MessageError})


class InternalError(E.SfmlocError):
    """An unexpected failure (a bug), reported as INTERNAL."""


def status_of(exc: BaseException) -> grpc.StatusCode:
    for cls, code in STATUS_TABLE:
        if isinstance(exc, cls):
            return code
    return grpc.StatusCode.INTERNAL


def message_of(exc: BaseException) -> str:
    if isinstance(exc, (E.SfmlocError, WireError)):
        return str(exc)
    return f"internal error: {type(exc).__name__}: {exc}"


def error_info(exc: BaseException) -> ErrorInfo:
    """What a Zenoh error reply carries."""
    return ErrorInfo(status_of(exc).name, message_of(exc))


def error_to_wire(exc: BaseException) -> dict[str, str]:
    name = type(exc).__name__ if type(exc).__name__ in _BY_NAME else "InternalError"
    return {"type": name, "message": message_of(exc)}


def error_from_wire(d: dict[str, str]) -> Exception:
    cls = _BY_NAME.get(str(d.get("type")), InternalError)
    return cls(str(d.get("message", "")))


async def abort(context: "grpc.aio.ServicerContext", exc: BaseException) -> None:
    """End a gRPC call with the status the table gives ``exc`` (raises, as ``abort`` does)."""
    await context.abort(status_of(exc), message_of(exc))
