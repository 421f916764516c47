"""The one exception hierarchy of sfmloc (client, server and builder), and the one table from
exceptions to status codes.

Callers catch ``SfmlocError`` for any expected failure. Codes are gRPC status code names
everywhere: the gRPC services end a failed call with ``code_of(exc)`` (a server interceptor
applies it), a Zenoh error reply carries the same name in ``error.code``, and a client sees it
in ``RemoteError.code``: both transports report a failure alike. The table lives here, not in
the server, so that it needs no grpc import and a client can read it.
"""

from __future__ import annotations

# The codes we use (gRPC status code names).
INVALID_ARGUMENT = "INVALID_ARGUMENT"
NOT_FOUND = "NOT_FOUND"
PERMISSION_DENIED = "PERMISSION_DENIED"
RESOURCE_EXHAUSTED = "RESOURCE_EXHAUSTED"
FAILED_PRECONDITION = "FAILED_PRECONDITION"
UNAVAILABLE = "UNAVAILABLE"
DEADLINE_EXCEEDED = "DEADLINE_EXCEEDED"
INTERNAL = "INTERNAL"


class SfmlocError(Exception):
    """Root of all errors sfmloc raises deliberately."""

    @property
    def code(self) -> str:
        """The status code name ``STATUS_TABLE`` gives this error."""
        return code_of(self)


class ConfigError(SfmlocError):
    """A configuration value, file or environment variable is invalid."""


class InputError(SfmlocError):
    """User-supplied input (a file, a folder, a command-line value, a request) is invalid."""


class CameraModelError(InputError):
    """A camera model is unknown, unsupported, or has the wrong size or parameters."""


class ModelFormatError(InputError):
    """A COLMAP model or pose file cannot be parsed."""


class ImageDecodeError(InputError, ValueError):
    """An image or frame cannot be decoded, or does not match its declared size or encoding."""


class WireError(InputError, ValueError):
    """A message (msgpack envelope, announcement, gRPC request) is malformed or fails
    validation."""


class MessageTooLargeError(WireError):
    """A message is larger than the configured limit."""


class BuildError(SfmlocError):
    """A map build failed at a named stage."""

    def __init__(self, message: str, stage: str | None = None) -> None:
        super().__init__(f"[{stage}] {message}" if stage else message)
        self.stage = stage


class BuildCancelled(BuildError):
    """A map build was cancelled before it completed."""


class BundleError(SfmlocError):
    """A map bundle is missing, corrupt, or of an unsupported version."""


class NotFoundError(SfmlocError):
    """The named thing (a map, a session, a build job) does not exist."""


class MapNotFoundError(NotFoundError):
    """No map of that name is loaded."""


class SessionNotFoundError(NotFoundError):
    """No localization session matches (it ended, expired or never existed)."""


class JobNotFoundError(NotFoundError):
    """No build job has that id."""


class OverloadError(SfmlocError):
    """The server is at capacity and rejects new work."""


class DeadlineExceededError(SfmlocError):
    """The caller's deadline passed before the work started (the work was dropped)."""


class UnavailableError(SfmlocError):
    """The server cannot do this now (shutting down, a worker restarting); retry later."""


class PermissionDeniedError(SfmlocError):
    """The request is well formed but not allowed (e.g. a bundle outside the maps folders)."""


class InternalError(SfmlocError):
    """An unexpected failure (a bug), reported as INTERNAL."""


class RemoteError(SfmlocError):
    """The server answered a call with an error status (``code`` is the gRPC status name)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.remote_code = code
        self.message = message

    @property
    def code(self) -> str:
        return self.remote_code


# Older names of the same classes (the client and the server each had one): kept so that
# existing imports work; new code uses the names above.
ClientError = SfmlocError
MessageError = WireError
ImageDataError = ImageDecodeError

# First match wins: subclasses before their bases.
STATUS_TABLE: tuple[tuple[type[BaseException], str], ...] = (
    (NotFoundError, NOT_FOUND),
    (MessageTooLargeError, RESOURCE_EXHAUSTED),
    (OverloadError, RESOURCE_EXHAUSTED),
    (PermissionDeniedError, PERMISSION_DENIED),
    (BundleError, FAILED_PRECONDITION),
    (UnavailableError, UNAVAILABLE),
    (DeadlineExceededError, DEADLINE_EXCEEDED),
    (InputError, INVALID_ARGUMENT),  # wire, camera, image, model file
    (ConfigError, INVALID_ARGUMENT),
    (BuildError, FAILED_PRECONDITION),
    (SfmlocError, INTERNAL),
)


def code_of(exc: BaseException) -> str:
    """The status code name of ``exc`` (INTERNAL for anything not raised on purpose; a
    ``RemoteError`` passed on keeps the code the remote side gave it)."""
    if isinstance(exc, RemoteError):
        return exc.remote_code
    for cls, code in STATUS_TABLE:
        if isinstance(exc, cls):
            return code
    return INTERNAL


def message_of(exc: BaseException) -> str:
    """What a caller is told: our own errors' text; for anything else, that it is internal."""
    if isinstance(exc, SfmlocError):
        return str(exc)
    return f"internal error: {type(exc).__name__}: {exc}"


def _all_classes() -> dict[str, type[SfmlocError]]:
    out: dict[str, type[SfmlocError]] = {}
    todo: list[type[SfmlocError]] = [SfmlocError]
    while todo:
        cls = todo.pop()
        out[cls.__name__] = cls
        todo.extend(cls.__subclasses__())
    return out


def error_class(name: str) -> type[SfmlocError]:
    """The class of this hierarchy named ``name`` (``InternalError`` when there is none), to
    rebuild an error that crossed a process boundary by name (nothing is unpickled)."""
    cls = _BY_NAME.get(name, InternalError)
    return InternalError if cls is RemoteError else cls  # RemoteError takes (code, message)


_BY_NAME = _all_classes()
