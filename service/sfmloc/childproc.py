"""Typed messages to and from a child process: one framing for every child sfmloc starts.

A message is a dataclass with an ``OP`` name; on the wire it is one msgpack array
``[op, field, field, ...]`` (fields in declaration order, nested messages as their own arrays),
framed by ``multiprocessing.connection.Connection`` (``send_bytes``/``recv_bytes``). A message
with ``HAS_DATA`` carries a bytes payload (an image) as a second frame, so the payload is never
copied into the msgpack buffer. Nothing is pickled: a child reads only the types its
``Protocol`` lists.

Used by the localization server's engine workers (``server/protocol.py``) and by the builder
service's build jobs (``builder_service/jobs.py``).
"""

from __future__ import annotations

import operator
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, TypeVar

import msgpack

from .errors import SfmlocError

P = TypeVar("P", bound="Part")


class ProtocolError(SfmlocError):
    """A message between the server (or builder) and its child process is malformed: a bug on
    one side, never the client's fault."""


def payload() -> Any:
    """The bytes payload of a ``HAS_DATA`` message: sent as its own frame, not in the array."""
    return field(default=b"", repr=False, metadata={"wire": False})


class Part:
    """A value nested in a message (encoded as an array of its fields)."""

    def to_wire(self) -> list[Any]:
        values = _getter(type(self))(self)
        return [v.to_wire() if isinstance(v, Part) else v for v in values]

    @classmethod
    def from_wire(cls: type[P], values: Any) -> P:
        names = _field_names(cls)
        if not isinstance(values, (list, tuple)) or len(values) != len(names):
            raise ProtocolError(f"{cls.__name__}: expected {len(names)} fields, got {values!r:.80}")
        return cls(*values)


class Message(Part):
    """A top-level message: ``OP`` names it on the wire."""

    OP: ClassVar[str] = ""
    HAS_DATA: ClassVar[bool] = False


_NAMES: dict[type, tuple[str, ...]] = {}
_GETTERS: dict[type, Callable[[Any], tuple[Any, ...]]] = {}


def _field_names(cls: type) -> tuple[str, ...]:
    names = _NAMES.get(cls)
    if names is None:
        names = _NAMES[cls] = tuple(f.name for f in fields(cls) if f.metadata.get("wire", True))
    return names


def _getter(cls: type) -> Callable[[Any], tuple[Any, ...]]:
    """The wire fields' values of an instance of ``cls``, as a tuple. Per frame, so one C call
    (``attrgetter``) rather than a getattr per field; plain values (a 36-value covariance,
    a camera's parameters) go to msgpack as they are, only nested parts are converted."""
    get = _GETTERS.get(cls)
    if get is None:
        names = _field_names(cls)
        if not names:
            get = _GETTERS[cls] = lambda obj: ()
        elif len(names) == 1:
            one = operator.attrgetter(names[0])
            get = _GETTERS[cls] = lambda obj: (one(obj),)
        else:
            get = _GETTERS[cls] = operator.attrgetter(*names)
    return get


class Protocol:
    """The messages one side may receive, and the framing (``send``/``recv``)."""

    def __init__(self, *messages: type[Message]) -> None:
        self._by_op: dict[str, type[Message]] = {}
        for cls in messages:
            if not cls.OP or cls.OP in self._by_op:
                raise ValueError(f"{cls.__name__}: OP must be set and unique")
            self._by_op[cls.OP] = cls

    @staticmethod
    def encode(msg: Message) -> bytes:
        return msgpack.packb([msg.OP, *msg.to_wire()], use_bin_type=True)

    def decode(self, raw: bytes) -> Message:
        try:
            arr = msgpack.unpackb(raw, raw=False)
        except Exception as exc:  # noqa: BLE001 - msgpack raises several types
            raise ProtocolError(f"undecodable message: {exc}") from None
        if not isinstance(arr, list) or not arr:
            raise ProtocolError(f"a message must be a non-empty array, got {type(arr).__name__}")
        cls = self._by_op.get(arr[0])
        if cls is None:
            raise ProtocolError(f"unknown message {arr[0]!r}")
        try:
            return cls.from_wire(arr[1:])
        except ProtocolError:
            raise
        except (TypeError, ValueError, IndexError) as exc:
            raise ProtocolError(f"malformed {cls.__name__}: {exc}") from None

    @classmethod
    def frames(cls, msg: Message) -> tuple[bytes, bytes | None]:
        """The frames ``send`` writes: the header, and the payload of a ``HAS_DATA`` message."""
        data = getattr(msg, "data", b"")  # declared by the HAS_DATA messages only
        return cls.encode(msg), (bytes(data) if msg.HAS_DATA else None)

    @classmethod
    def send(cls, conn: Any, msg: Message) -> None:
        header, data = cls.frames(msg)
        write_frames(conn, header, data)

    def recv(self, conn: Any) -> Message:
        """The next message (its payload read too). EOFError/OSError when the peer is gone."""
        msg = self.decode(conn.recv_bytes())
        if msg.HAS_DATA:
            msg.data = conn.recv_bytes()  # type: ignore[attr-defined]
        return msg


def write_frames(conn: Any, header: bytes, data: bytes | None = None) -> None:
    """``conn.send_bytes(header)`` then ``conn.send_bytes(data)`` (when not None), the same
    bytes (``Connection``'s framing: a 4-byte big-endian length before each), in one
    ``writev`` rather than three writes. The reader, blocked on the first length, wakes once
    with the whole message in its socket, not once per write (a frame's header, its data's
    length, then its data: a worker waiting for its next frame woke up to three times)."""
    bufs: list[Any] = []
    for b in (header, data):
        if b is None:
            continue
        if len(b) > 0x7FFFFFFF:  # Connection's long form; never a frame (16 MiB at most)
            conn.send_bytes(header)
            if data is not None:
                conn.send_bytes(data)
            return
        bufs += [struct.pack("!i", len(b)), b]
    fd = conn.fileno()  # OSError once closed, as send_bytes raises
    views = [memoryview(b) for b in bufs]
    while views:
        n = os.writev(fd, views)
        while views and n >= len(views[0]):  # drop what went out; keep a partial buffer's rest
            n -= len(views[0])
            views.pop(0)
        if views and n:
            views[0] = views[0][n:]


__all__ = ["Message", "Part", "Protocol", "ProtocolError", "dataclass", "payload", "write_frames"]
