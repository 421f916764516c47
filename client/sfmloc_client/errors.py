"""Errors of the client library (it does not depend on the server package, so it has its own).

Error codes are gRPC status code names everywhere: in ``RemoteError.code`` (gRPC calls) and in
the ``error.code`` of a Zenoh pose message, so a client handles both transports alike.
"""

from __future__ import annotations

# The codes the server uses (gRPC status code names).
INVALID_ARGUMENT = "INVALID_ARGUMENT"
NOT_FOUND = "NOT_FOUND"
RESOURCE_EXHAUSTED = "RESOURCE_EXHAUSTED"
FAILED_PRECONDITION = "FAILED_PRECONDITION"
UNAVAILABLE = "UNAVAILABLE"
INTERNAL = "INTERNAL"


class ClientError(Exception):
    """Root of the errors this library raises on purpose."""


class WireError(ClientError, ValueError):
    """A wire message (msgpack envelope, announcement) is malformed or fails validation."""

    code = INVALID_ARGUMENT


class MessageTooLargeError(WireError):
    """A message is larger than the configured limit."""

    code = RESOURCE_EXHAUSTED


class ImageDataError(WireError):
    """Image bytes cannot be decoded, or do not match the declared size or encoding."""


class RemoteError(ClientError):
    """The server answered a call with an error status (``code`` is the gRPC status name)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
