"""One exception root for everything sfmloc raises on purpose.

Callers catch ``SfmlocError`` to handle any expected failure; the transport layer maps
each subclass to a status code in one table (``sfmloc.server.status``).
"""

from __future__ import annotations


class SfmlocError(Exception):
    """Root of all errors sfmloc raises deliberately."""


class ConfigError(SfmlocError):
    """A configuration value, file or environment variable is invalid."""


class InputError(SfmlocError):
    """User-supplied input (a file, a folder, a command-line value) is missing or invalid."""


class CameraModelError(InputError):
    """A camera model is unknown, unsupported, or has the wrong number of parameters."""


class ModelFormatError(InputError):
    """A COLMAP model or pose file cannot be parsed."""


class ImageDecodeError(InputError):
    """An image or frame cannot be decoded, or has the wrong size or type."""


class BuildError(SfmlocError):
    """A map build failed at a named stage."""

    def __init__(self, message: str, stage: str | None = None) -> None:
        super().__init__(f"[{stage}] {message}" if stage else message)
        self.stage = stage


class BuildCancelled(BuildError):
    """A map build was cancelled before it completed."""


class BundleError(SfmlocError):
    """A map bundle is missing, corrupt, or of an unsupported version."""


class MapNotFoundError(SfmlocError):
    """No map of that name is loaded."""


class OverloadError(SfmlocError):
    """The server is at capacity and rejects new work."""


class SessionNotFoundError(SfmlocError):
    """No localization session matches (it ended, expired or never existed)."""


class UnavailableError(SfmlocError):
    """The server cannot do this now (shutting down, a worker restarting); retry later."""


class PermissionDeniedError(SfmlocError):
    """The request is well formed but not allowed (e.g. a bundle outside the maps folders)."""


class MessageError(InputError):
    """A wire message (msgpack envelope, gRPC request) is malformed."""
