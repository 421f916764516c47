"""Receiving poses: ``PoseSubscriber`` (a callback, or an iterator over a queue)."""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable, Iterator
from typing import Any

from .errors import WireError
from .wire import PoseMessage, decode_pose, pose_key

log = logging.getLogger(__name__)


class PoseSubscriber:
    """Poses of one client on ``sfmloc/<map>/<client>/pose``.

    With ``callback``, every pose is passed to it (on a Zenoh thread: keep it short); without,
    poses queue up (at most ``maxsize``, the oldest are dropped beyond) for ``get()`` or
    iteration. Either way ``received``, ``last`` and ``wait_for(seq)`` track what came in;
    messages that fail to decode are counted in ``invalid`` and skipped.
    """

    def __init__(
        self,
        session: Any,
        map_name: str,
        client_id: str,
        callback: Callable[[PoseMessage], None] | None = None,
        maxsize: int = 100_000,
    ) -> None:
        self.key = pose_key(map_name, client_id)
        self.callback = callback
        self.received = 0
        self.invalid = 0
        self.errors = 0
        self.last: PoseMessage | None = None
        self.max_seq = -1
        self._queue: queue.Queue[PoseMessage | None] | None = (
            None if callback else queue.Queue(maxsize)
        )
        self._cond = threading.Condition()
        self._closed = False
        self._sub = session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            pose = decode_pose(sample.payload.to_bytes())
        except WireError as exc:
            self.invalid += 1
            log.warning("invalid pose message on %s: %s", self.key, exc)
            return
        with self._cond:
            self.received += 1
            self.errors += pose.error is not None
            self.last = pose
            if pose.seq is not None and pose.seq > self.max_seq:
                self.max_seq = pose.seq
            self._cond.notify_all()
        if self.callback is not None:
            try:
                self.callback(pose)
            except Exception:  # noqa: BLE001 - a user callback must not kill Zenoh's thread
                log.exception("pose callback failed")
            return
        self._put(pose)

    def wait_for(self, seq: int, timeout: float | None = None) -> bool:
        """Wait until a pose with ``seq`` or a later one has arrived; False on timeout."""
        with self._cond:
            return (
                self._cond.wait_for(lambda: self.max_seq >= seq or self._closed, timeout)
                and self.max_seq >= seq
            )

    def wait_received(self, n: int, timeout: float | None = None) -> bool:
        """Wait until ``n`` poses have arrived in total; False on timeout."""
        with self._cond:
            return (
                self._cond.wait_for(lambda: self.received >= n or self._closed, timeout)
                and self.received >= n
            )

    def get(self, timeout: float | None = None) -> PoseMessage | None:
        """The next pose, or None on timeout or once closed (iterator mode only)."""
        if self._queue is None:
            raise RuntimeError("get() needs a PoseSubscriber without callback")
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def __iter__(self) -> Iterator[PoseMessage]:
        while True:
            p = self.get()
            if p is None:
                return
            yield p

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._sub.undeclare()
        except Exception:  # noqa: BLE001 - the session may already be closed
            pass
        with self._cond:
            self._cond.notify_all()
        if self._queue is not None:
            self._put(None)  # wakes an iterator up: the end

    def _put(self, item: PoseMessage | None) -> None:
        """Queue ``item``; when full, the oldest pose makes room (never blocks Zenoh)."""
        assert self._queue is not None
        while True:
            try:
                self._queue.put_nowait(item)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    pass

    def __enter__(self) -> PoseSubscriber:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
