"""Fakes for the server's unit tests, speaking the real worker protocol without the engine.

- ``FakeWorkers``: the program of a pool's thread workers (``WorkerPool(thread_target=...)``).
  It answers every message of ``sfmloc.server.protocol`` over the real socket pair, records
  what each incarnation of each worker received, and can be told to hold a start or a load on
  an event, or to die (close its socket, as a killed process does).
- ``FakePool``: the pool's interface for the session manager and the map registry, recording
  the frames handed over; the test plays the worker by calling ``on_result`` itself.

Everything waits on conditions and events, never on sleeps.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from typing import Any

from sfmloc.server import protocol as P
from sfmloc_client.wire import Transform

TF = Transform((0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0))


def pose(status: str = "TRACKING") -> P.PoseResult:
    located = status != "LOST"
    return P.PoseResult(
        status,
        TF if located else None,
        TF if located else None,
        None,
        None,
        30 if located else 0,
        100,
        80,
        40,
        "guided",
        5.0,
        "",
        tuple([0.0] * 36) if located else None,
    )


def summary(build_id: str = "b") -> P.MapSummary:
    return P.MapSummary(
        points=100,
        descriptors=200,
        images=10,
        clusters=4,
        memory_mb=1.0,
        build_id=build_id,
        index_in_place=True,
    )


class FakeWorkers:
    """``__call__`` is a worker's program (the signature of ``worker_main``)."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.starts: dict[int, int] = defaultdict(int)  # index -> incarnations started
        self.received: list[tuple[int, int, P.Message]] = []  # (index, incarnation, message)
        self.hold_start: dict[tuple[int, int], threading.Event] = {}  # wait before "ready"
        self.hold_load: dict[tuple[int, int], threading.Event] = {}  # wait before answering loads
        self.hold_reloc: threading.Event | None = None  # a "hold" relocalization waits on it

    def __call__(self, conn: Any, index: int, *_: Any) -> None:
        with self.cond:
            self.starts[index] += 1
            me = (index, self.starts[index])
            self.cond.notify_all()
        gate = self.hold_start.get(me)
        if gate is not None:
            gate.wait(60)
        try:
            self._serve(conn, me)
        finally:
            conn.close()

    def _serve(self, conn: Any, me: tuple[int, int]) -> None:
        P.TO_SERVER.send(conn, P.Ready(me[0], 1000 * me[0] + me[1]))
        while True:
            try:
                msg = P.TO_WORKER.recv(conn)
            except (EOFError, OSError):
                return
            with self.cond:
                self.received.append((*me, msg))
                self.cond.notify_all()
            if isinstance(msg, P.Stop):
                return
            if isinstance(msg, P.Load):
                gate = self.hold_load.get(me)
                if gate is not None:
                    gate.wait(60)
                P.TO_SERVER.send(conn, P.Loaded(msg.req, summary(msg.build_id), None, 1.0))
            elif isinstance(msg, P.LocalizeFrame):
                if msg.encoding == "die":  # a crash: the socket closes, nothing is answered
                    return
                P.TO_SERVER.send(
                    conn,
                    P.Result(
                        msg.sid,
                        msg.seq,
                        msg.stamp_ns,
                        msg.gen,
                        "b",
                        pose(),
                        None,
                        0.1,
                        1.0,
                        msg.ticket,
                    ),
                )
            elif isinstance(msg, P.Relocalize):
                if msg.encoding == "die":
                    return
                if msg.encoding == "hold" and self.hold_reloc is not None:
                    self.hold_reloc.wait(60)
                P.TO_SERVER.send(conn, P.RelocResult(msg.req, pose("RELOCALIZED"), None, 2.0))

    def messages(self, index: int, incarnation: int, kind: type) -> list[Any]:
        with self.cond:
            return [
                m
                for i, k, m in self.received
                if (i, k) == (index, incarnation) and isinstance(m, kind)
            ]

    def wait_for(self, pred: Any, timeout: float = 30.0) -> bool:
        with self.cond:
            return self.cond.wait_for(pred, timeout)


class FakePool:
    """What the session manager and the map registry use of ``WorkerPool``."""

    def __init__(self, n: int = 2) -> None:
        self.n = n
        self.alive = [True] * n
        self.frames: list[tuple[int, P.LocalizeFrame]] = []  # (worker, message) handed over
        self.closed: list[tuple[int, int]] = []
        self.resets: list[tuple[int, int]] = []
        self.maps: dict[tuple[str, int], str] = {}  # (name, gen) -> path, on the workers
        self.dropped: list[tuple[str, int]] = []
        self.loading: dict[tuple[str, int], threading.Event] = {}  # hold a load_map
        self.working: dict[int, int] = {}  # worker -> ticket of the frame it works on (test sets)

    def is_alive(self, worker: int) -> bool:
        return 0 <= worker < self.n and self.alive[worker]

    def started(self, worker: int, ticket: int) -> bool:
        return bool(ticket) and self.working.get(worker) == ticket

    def inflight(self) -> list[int]:
        return [0] * self.n

    def submit_frame(self, worker: int, msg: P.LocalizeFrame) -> None:
        assert self.alive[worker], "a frame went to a dead worker"
        self.frames.append((worker, msg))

    def close_session(self, worker: int, sid: int) -> None:
        self.closed.append((worker, sid))

    def reset_session(self, worker: int, sid: int) -> None:
        self.resets.append((worker, sid))

    def load_map(self, name: str, gen: int, path: str, build_id: str) -> P.MapSummary:
        gate = self.loading.get((name, gen))
        if gate is not None:
            gate.wait(60)
        self.maps[(name, gen)] = path
        return summary(build_id)

    def drop_map(self, name: str, gen: int) -> None:
        self.maps.pop((name, gen), None)
        self.dropped.append((name, gen))


class ListSink:
    """A session's sink that keeps the poses (a Zenoh publisher or a gRPC stream in the server)."""

    def __init__(self) -> None:
        self.poses: list[Any] = []
        self.closed = False

    def send(self, p: Any) -> None:
        self.poses.append(p)

    def close(self) -> None:
        self.closed = True
