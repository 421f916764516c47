"""One exception root for everything sfmloc raises on purpose.

The hierarchy and its table to status codes are the contract shared by client, server and
builder, so they live in the client package (``sfmloc_client.errors``); this module gives the
service its usual import path to the same classes.
"""

from __future__ import annotations

from sfmloc_client.errors import (
    STATUS_TABLE,
    BuildCancelled,
    BuildError,
    BundleError,
    CameraModelError,
    ConfigError,
    DeadlineExceededError,
    ImageDecodeError,
    InputError,
    InternalError,
    JobNotFoundError,
    MapNotFoundError,
    MessageError,
    MessageTooLargeError,
    ModelFormatError,
    NotFoundError,
    OverloadError,
    PermissionDeniedError,
    RemoteError,
    SessionNotFoundError,
    SfmlocError,
    UnavailableError,
    WireError,
    code_of,
    error_class,
    message_of,
)

__all__ = [
    "STATUS_TABLE",
    "BuildCancelled",
    "BuildError",
    "BundleError",
    "CameraModelError",
    "ConfigError",
    "DeadlineExceededError",
    "ImageDecodeError",
    "InputError",
    "InternalError",
    "JobNotFoundError",
    "MapNotFoundError",
    "MessageError",
    "MessageTooLargeError",
    "ModelFormatError",
    "NotFoundError",
    "OverloadError",
    "PermissionDeniedError",
    "RemoteError",
    "SessionNotFoundError",
    "SfmlocError",
    "UnavailableError",
    "WireError",
    "code_of",
    "error_class",
    "message_of",
]
