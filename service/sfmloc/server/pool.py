"""The worker pool: the server's side of its engine workers.

``n`` stream workers (sessions stick to one: their track table and filter live there) and an
optional relocalization lane; per worker a sender and a reader thread (pumps), request/response
bookkeeping, and the restart of a worker that died (with the maps current when it is ready).
The worker program itself is ``worker.py``; the messages are ``protocol.py``.

Why processes: the engine is numpy/OpenCV with many small Python-level steps, and the GIL
serializes those across threads; measured with ``sfmloc bench-transport --only engine,workers``
(numbers in ``app.py``). ``worker_kind="thread"`` exists for that comparison only (and tests).

A worker process is a fresh interpreter holding one end of a socket pair. The messages are
msgpack arrays framed by ``multiprocessing.connection.Connection``; frame bytes follow their
header as a second frame. Nothing is pickled anywhere (no ``multiprocessing`` queues, which
pickle, and no spawn arguments).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import itertools
import logging
import queue
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

from ..childproc import write_frames
from ..errors import OverloadError, UnavailableError
from ..threads import pin_threads_env
from . import protocol as P
from .logfmt import event
from .sched import set_slice
from .worker import worker_main
from .zygote import (
    RelayedStderr,
    Zygote,
    relay_stderr,
    set_process_name,
    take_prestarted,
    worker_env,
)

log = logging.getLogger(__name__)

SOCKET_BUFFER = 4 * 1024 * 1024  # per direction: a few raw frames fit in one write


@dataclass
class WorkerHandle:
    index: int
    conn: Any
    runner: Any  # _Process (a worker process) or threading.Thread
    outbox: queue.SimpleQueue[tuple[bytes, bytes | None] | None] = field(
        default_factory=queue.SimpleQueue
    )
    inflight: int = 0  # frames and relocalizations sent, not yet answered
    # What it was sent that it answers, in order (the worker works through its messages one
    # by one): a frame's ticket, 0 for a load or relocalization. The first is the one it works
    # on now (``started``).
    order: collections.deque[int] = field(default_factory=collections.deque)
    busy_ms: float = 0.0  # engine time so far (load reporting)
    alive: bool = True  # its pumps run (False once it died)
    # Takes part: frames, sessions and LoadMap go to it. A replacement is stored in the pool at
    # once (stop and drops reach it) but serves only once it has reloaded the current maps.
    serving: bool = False
    pid: int = 0
    # Which process of this index it is (1 for the first, +1 per restart): the restart
    # bookkeeping and the log tell replacements of one index apart by it.
    gen: int = 1
    threads: list[threading.Thread] = field(default_factory=list)
    ready: threading.Event = field(default_factory=threading.Event)  # this process said "ready"


class WorkerPool:
    """``n`` workers, their message pumps, and request/response bookkeeping.

    ``on_result(result)`` is called (on a pump thread) with every frame result; ``on_lost(index)``
    when a worker died (it is restarted and its maps reloaded; its sessions lose their state).
    """

    def __init__(
        self,
        n: int,
        kind: str,
        engine_conf_json: str,
        *,
        on_result: Callable[[P.Result], None],
        on_lost: Callable[[int], None] | None = None,
        on_dead: Callable[[int], None] | None = None,
        log_level: int = logging.INFO,
        log_format: str = "kv",
        max_pending_relocalize: int = 16,
        max_image_pixels: int = 4096 * 4096,
        reloc_workers: int = 0,
        reloc_nice: int = 15,
        worker_slice_ms: float = 0.0,
        thread_target: Callable[..., None] = worker_main,
        fork: bool = True,
    ) -> None:
        self.n = n  # stream workers (sessions live on workers 0..n-1)
        # Workers n..n+reloc_workers-1 only serve single-image relocalizations (their own
        # lane): a 70-120 ms (or, for a huge image, seconds-long) relocalization never
        # holds a worker that streams' frames queue on. 0: they share the stream workers.
        self.reloc_workers = reloc_workers
        self.reloc_nice = reloc_nice
        # The stream workers' scheduler slice (sched.py): frame-long, so workers sharing a
        # core do not refill each other's caches every 1.4 ms. 0: the kernel's default.
        self.worker_slice_ms = worker_slice_ms
        self.kind = kind
        # What a thread worker runs: ``worker_main``, or a fake speaking the protocol (tests).
        self.thread_target = thread_target
        # Process workers are forked from one pre-imported interpreter (``zygote.py``): start
        # and restart without re-importing the engine, imports' pages shared. False: a fresh
        # interpreter each (also the fallback when the zygote is gone).
        self.fork = fork and kind == "process"
        self._zygote: Zygote | None = None
        self.engine_conf_json = engine_conf_json
        self.on_result = on_result
        self.on_lost = on_lost or (lambda i: None)
        self.on_dead = on_dead or (lambda i: None)
        self.log_level, self.log_format = log_level, log_format
        self.max_pending_relocalize = max_pending_relocalize
        self.max_image_pixels = max_image_pixels
        self.workers: list[WorkerHandle] = []
        self._lock = threading.Lock()
        # Notified whenever a worker's state changes (ready, died, replaced, serving) and when
        # a relocalization is queued.
        self._changed = threading.Condition(self._lock)
        self._req = itertools.count(1)
        self._futures: dict[int, tuple[int, Future]] = {}  # req -> (worker, future)
        self._maps: dict[tuple[str, int], tuple[str, str]] = {}  # (name, gen) -> (path, build_id)
        self._stopping = False
        self._reloc_pending = 0
        # With a relocalization lane, requests wait here (not in a worker's socket) until a
        # lane worker is idle: one whose caller went away or whose deadline passed meanwhile
        # is dropped before any work (issue 16).
        self._reloc_queue: collections.deque[tuple[P.Relocalize, Future]] = collections.deque()
        self.restarts = 0
        # Deaths in a row before serving, per worker index (reset once one serves).
        self._start_failures = [0] * (n + reloc_workers)
        self._gens = [0] * (n + reloc_workers)  # the last generation spawned, per worker index
        self._maps_version = 0  # bumped by every load/drop (a restart reloads until it is stable)
        self.fatal: Exception | None = None  # a worker that cannot start: the pool gives up
        self._started = False  # start() returned: every worker was ready once

    # ------------------------------------------------------------------ lifecycle
    def start(self, timeout: float = 120.0) -> None:
        pin_threads_env()
        if self.fork:
            env = self._worker_env()
            self._zygote = take_prestarted(env) or Zygote(env)
        for i in range(self.n + self.reloc_workers):
            self.workers.append(self._spawn(i))
            self.workers[i].serving = True  # no map is loaded before start() returns
        deadline = time.monotonic() + timeout
        for i in range(self.n + self.reloc_workers):
            # A worker that dies while starting is restarted (with back-off) by its reader
            # thread, which replaces self.workers[i]; after MAX_START_FAILURES it gives up.
            while not self.workers[i].ready.wait(0.05):
                if self.fatal is not None:
                    raise self.fatal
                if self._stopping:  # SIGTERM during start-up: do not keep the process waiting
                    raise UnavailableError("the server stopped while its workers were starting")
                if time.monotonic() > deadline:
                    raise UnavailableError(f"worker {i} did not start within {timeout:.0f} s")
        with self._lock:
            self._start_failures = [0] * len(self._start_failures)
        self._started = True

    def _spawn(self, i: int) -> WorkerHandle:
        ours, theirs = socket.socketpair()
        for sock in (ours, theirs):  # a whole frame fits: one write, one read, fewer wake-ups
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
        runner: Any = None
        nice = self.reloc_nice if i >= self.n else 0
        if self.kind == "process" and self._zygote is not None and self._zygote.alive:
            try:
                runner = self._zygote.spawn(
                    theirs.fileno(),
                    i,
                    self.engine_conf_json,
                    self.log_level,
                    self.log_format,
                    nice,
                    timeout=120.0,  # the zygote may still be importing
                )
            except OSError as exc:
                log.warning("worker %d: the zygote cannot fork (%s): starting afresh", i, exc)
            if runner is not None:
                theirs.close()
        if self.kind == "process" and runner is None:
            # A fresh interpreter (not multiprocessing's spawn): it does not re-import the
            # caller's __main__, nothing is pickled, and the one-thread environment is in place
            # before numpy loads.
            env = self._worker_env()
            fd = theirs.fileno()
            cmd = [
                sys.executable,
                "-c",
                _BOOTSTRAP,
                "--fd",
                str(fd),
                "--index",
                str(i),
                "--log-level",
                str(self.log_level),
                "--log-format",
                self.log_format,
                "--engine-conf",
                self.engine_conf_json,
                "--nice",
                str(nice),
            ]
            runner = _Process(
                subprocess.Popen(
                    cmd, pass_fds=(fd,), env=env, stdin=subprocess.DEVNULL, stderr=subprocess.PIPE
                )
            )
            theirs.close()  # the child holds its end; ours must not keep it open (EOF detection)
        elif runner is None:
            conn = Connection(theirs.detach())
            args = (conn, i, self.engine_conf_json, self.log_level, self.log_format, False)
            runner = threading.Thread(
                target=self.thread_target, args=args, name=f"sfmloc-worker-{i}", daemon=True
            )
            runner.start()
        self._gens[i] += 1
        h = WorkerHandle(i, Connection(ours.detach()), runner, gen=self._gens[i])
        h.threads = [
            threading.Thread(
                target=self._sender, args=(h,), name=f"sfmloc-worker-{i}-send", daemon=True
            ),
            threading.Thread(
                target=self._reader, args=(h,), name=f"sfmloc-worker-{i}-recv", daemon=True
            ),
        ]
        for t in h.threads:
            t.start()
        return h

    def _worker_env(self) -> dict[str, str]:
        return worker_env(self.max_image_pixels)

    def stop(self, timeout: float = 10.0) -> None:
        self._stopping = True
        for h in self.workers:
            h.outbox.put(P.TO_WORKER.frames(P.Stop()))
            h.outbox.put(None)
        deadline = time.monotonic() + timeout
        for h in self.workers:
            h.runner.join(max(0.1, deadline - time.monotonic()))
            if self.kind == "process" and h.runner.is_alive():
                # Workers ignore SIGTERM (a Ctrl-C or SIGTERM to the process group must not end
                # them mid-frame), so SIGTERM would not end one busy with a long request.
                log.warning("worker %d did not stop in time: killing it", h.index)
                h.runner.kill()
                h.runner.join(5)
            try:
                h.conn.close()
            except OSError:
                pass
        for h in self.workers:
            for t in h.threads:
                t.join(2)
        if self._zygote is not None:
            self._zygote.close()
        self._fail_all(UnavailableError("the server is shutting down"))

    # ------------------------------------------------------------------ pumps
    def _sender(self, h: WorkerHandle) -> None:
        """Writes to one worker's socket. A separate thread, so a busy worker (its socket
        full) never blocks the Zenoh or gRPC thread that handed over a frame."""
        set_process_name(f"sfmloc-send-{h.index}")  # this thread's name in top -H, /proc
        while True:
            item = h.outbox.get()
            if item is None:
                return
            header, data = item
            try:
                write_frames(h.conn, header, data)  # one syscall: the worker wakes once
            except (OSError, ValueError):
                return  # the reader notices the dead worker

    def _reader(self, h: WorkerHandle) -> None:
        set_process_name(f"sfmloc-recv-{h.index}")
        while True:
            try:
                msg = P.TO_SERVER.recv(h.conn)
            except (EOFError, OSError, ValueError, TypeError):  # TypeError: closed by stop()
                break
            except P.ProtocolError:
                log.exception("worker %d sent a malformed message", h.index)
                continue
            try:
                self._dispatch(h, msg)
            except Exception:  # noqa: BLE001 - keep pumping
                log.exception("handling a message of worker %d failed", h.index)
        if not self._stopping:
            self._worker_lost(h)

    def _dispatch(self, h: WorkerHandle, msg: P.Message) -> None:
        if isinstance(msg, P.Result):
            with self._lock:
                h.inflight -= 1
                h.busy_ms += msg.worker_ms
                _answered(h.order, msg.ticket)
            self.on_result(msg)
        elif isinstance(msg, (P.Loaded, P.RelocResult)):
            with self._lock:
                _answered(h.order, 0)
                entry = self._futures.pop(msg.req, None)
                if isinstance(msg, P.RelocResult):
                    h.inflight -= 1
                    h.busy_ms += msg.worker_ms
            if entry is not None:
                fut = entry[1]
                if msg.error is not None:
                    _settle(fut, exc=msg.error.exception())
                else:
                    _settle(fut, result=msg)
            if isinstance(msg, P.RelocResult):
                self._pump_reloc()
        elif isinstance(msg, P.Ready):
            if self.kind == "process" and h.index < self.n and self.worker_slice_ms > 0:
                # the relocalization lane keeps the default: niced, it should yield at once
                if not set_slice(msg.pid, self.worker_slice_ms):
                    log.info(
                        "worker %d: the kernel did not take a %g ms slice (default kept)",
                        h.index,
                        self.worker_slice_ms,
                    )
            with self._changed:
                h.pid = msg.pid
                h.ready.set()
                self._changed.notify_all()

    def _worker_lost(self, h: WorkerHandle) -> None:
        """A worker died (a crash in native code, killed): fail what it had, restart it with
        the current maps, and tell the sessions (they relocalize on the new worker)."""
        # It had started when it served: ready, and (a replacement) its maps reloaded. One that
        # died before had no sessions and counts towards the start failures.
        started = h.ready.is_set() and h.serving
        with self._lock:
            h.alive = False
            self._changed.notify_all()
            h.outbox.put(None)
            lost = [r for r, (w, _) in self._futures.items() if w == h.index]
            futures = [self._futures.pop(r)[1] for r in lost]
        # Its answers first, then the bookkeeping: the socket's EOF is the death (the kernel
        # closes it with the process), while its exit status comes from the zygote's SIGCHLD
        # report, a wake-up of another process later (tens of ms on a loaded machine), which
        # the frames it had and its sessions' next frames need not wait for.
        for f in futures:
            _settle(f, exc=UnavailableError(f"worker {h.index} died; retry"))
        if started and not self._stopping:
            try:
                self.on_dead(h.index)  # at once: answer its frames, move its sessions
            except Exception:  # noqa: BLE001 - the restart must go on
                log.exception("handling the death of worker %d failed", h.index)
        if self.kind == "process":
            h.runner.join(5)  # reap it now: no zombie, and its exit code is known
        code = getattr(h.runner, "exitcode", None)
        # Its stderr read to the end first: the pump may still be behind when the exit is seen
        # (a clean clone once reported a traceback's 'File "<string>"' line, not its ImportError).
        if code is not None and isinstance(h.runner, RelayedStderr):
            h.runner.drain_stderr(1.0)
        pid = (
            h.pid
            or getattr(h.runner, "pid", 0)
            or getattr(getattr(h.runner, "popen", None), "pid", 0)
        )
        event(
            log,
            logging.ERROR,
            "worker_lost",
            worker=h.index,
            gen=h.gen,
            pid=pid,
            exitcode=code,
            during_start=not started,
            said_ready=h.ready.is_set(),
            stderr=getattr(h.runner, "last_line", ""),
        )
        if self._stopping:
            return
        fails = 0 if started else self._start_failures[h.index] + 1
        self._start_failures[h.index] = fails
        if fails >= MAX_START_FAILURES:
            # Restarting would loop forever (e.g. the package does not import): give up loudly.
            self.fatal = UnavailableError(
                f"worker {h.index} exited {fails} times before it was ready (exit code {code})"
                + (f": {h.runner.last_line}" if getattr(h.runner, "last_line", "") else "")
            )
            event(
                log,
                logging.ERROR,
                "worker_start_failed",
                worker=h.index,
                gen=h.gen,
                attempts=fails,
                error=str(self.fatal),
            )
            return
        if fails:
            time.sleep(min(5.0, 0.25 * 2**fails))  # back-off before the next attempt
        reload = self._started  # before start() returns there are no maps to reload
        new = self._spawn(h.index)
        new.serving = not reload
        with self._lock:
            # At once, not after the reload: stop() must reach the replacement, and a handle
            # stored late could overwrite the replacement of a replacement that died meanwhile.
            self.workers[h.index] = new
            self.restarts += 1
            self._changed.notify_all()
        event(
            log,
            logging.WARNING,
            "worker_restarting",
            worker=h.index,
            gen=new.gen,
            replaces=h.gen,
            attempt=fails + 1,
        )
        if not reload:
            return  # start() waits on the replacement
        while not new.ready.wait(0.1):
            if not new.alive or self._stopping:
                return  # the replacement died too: its own reader thread handles that
        # The current maps (not those at the time of death: LoadMap/UnloadMap may have run
        # meanwhile, skipping the dead worker), until no load or drop happened during the reload.
        loaded: set[tuple[str, int]] = set()
        while True:
            with self._lock:
                maps, version = dict(self._maps), self._maps_version
            for (name, gen), (path, build_id) in maps.items():
                if (name, gen) in loaded:
                    continue
                try:
                    self._request(new, P.Load(0, name, gen, path, build_id)).result(120)
                    loaded.add((name, gen))
                except Exception as exc:  # noqa: BLE001
                    log.error("worker %d: reloading map %s failed: %s", h.index, name, exc)
            with self._lock:
                if self.workers[h.index] is not new or not new.alive:
                    return  # it died while reloading: its own reader thread restarts it
                if self._maps_version == version:
                    new.serving = True
                    self._start_failures[h.index] = 0  # it serves: a later death starts afresh
                    self._changed.notify_all()
                    stale = loaded - set(self._maps)
                    break
            if not new.alive or self._stopping:
                return
        for name, gen in stale:
            self._send(new, P.Drop(name, gen))
        self._pump_reloc()  # relocalizations queued while the lane's worker was restarting
        event(
            log,
            logging.WARNING,  # with worker_lost, the story of a restart even at -q
            "worker_restarted",
            worker=h.index,
            gen=new.gen,
            replaces=h.gen,
            pid=new.pid,
            maps=len(loaded - stale),
        )
        self.on_lost(h.index)

    # ------------------------------------------------------------------ requests
    def _send(self, h: WorkerHandle, msg: P.Message) -> None:
        h.outbox.put(P.TO_WORKER.frames(msg))

    def _request(self, h: WorkerHandle, msg: P.Load | P.Relocalize) -> Future:
        """Send ``msg`` with a fresh request number; the future gets the answer."""
        fut: Future = Future()
        with self._lock:
            req = next(self._req)
            self._futures[req] = (h.index, fut)
        msg.req = req
        if not h.alive:  # its pump is gone: nothing would ever answer
            with self._lock:
                self._futures.pop(req, None)
            fut.set_exception(UnavailableError(f"worker {h.index} is restarting; retry"))
            return fut
        with self._lock:
            h.order.append(0)
        self._send(h, msg)
        return fut

    def load_map(
        self, name: str, gen: int, path: str, build_id: str, timeout: float = 300.0
    ) -> P.MapSummary:
        """Load a bundle on every worker; returns the first worker's summary. All or nothing."""
        with self._lock:
            self._maps[(name, gen)] = (path, build_id)  # a worker restarting meanwhile loads it too
            self._maps_version += 1
            # A restarting worker's replacement loads it when it reloads the current maps.
            live = [h for h in self.workers if h.alive and h.serving]
        futures = [self._request(h, P.Load(0, name, gen, path, build_id)) for h in live]
        try:
            if not futures:
                raise UnavailableError("no engine worker is running (one is restarting); retry")
            results: list[P.Loaded] = [f.result(timeout) for f in futures]
        except BaseException:
            self.drop_map(name, gen)
            raise
        summaries = [r.summary for r in results if r.summary is not None]
        if len(summaries) != len(results):
            raise P.ProtocolError("a worker answered a load with neither a summary nor an error")
        return dataclasses.replace(
            summaries[0], index_in_place=all(s.index_in_place for s in summaries)
        )

    def drop_map(self, name: str, gen: int) -> None:
        with self._lock:
            self._maps.pop((name, gen), None)
            self._maps_version += 1
        for h in self.workers:
            self._send(h, P.Drop(name, gen))

    def wait_for(self, pred: Callable[[], bool], timeout: float) -> bool:
        """Wait until ``pred()`` holds; it is evaluated, under the pool's lock, whenever a
        worker's state changes (ready, died, replaced, serving) or a relocalization is queued.
        False on timeout."""
        with self._changed:
            return self._changed.wait_for(pred, timeout)

    def is_alive(self, worker: int) -> bool:
        """Whether worker ``worker`` is up (False from its death until its replacement has
        reloaded the maps)."""
        if not 0 <= worker < len(self.workers):
            return False
        h = self.workers[worker]
        return h.alive and h.serving

    def submit_frame(self, worker: int, msg: P.LocalizeFrame) -> None:
        h = self.workers[worker]
        with self._lock:
            h.inflight += 1
            h.order.append(msg.ticket)
        self._send(h, msg)

    def started(self, worker: int, ticket: int) -> bool:
        """Whether worker ``worker`` is working on the frame of ``ticket`` now: everything
        sent to it before has been answered (it works through its messages in order)."""
        if not ticket or not 0 <= worker < len(self.workers):
            return False
        h = self.workers[worker]
        with self._lock:
            return h.alive and bool(h.order) and h.order[0] == ticket

    def reset_session(self, worker: int, sid: int) -> None:
        self._send(self.workers[worker], P.Reset(sid))

    def close_session(self, worker: int, sid: int) -> None:
        self._send(self.workers[worker], P.Close(sid))

    def relocalize(self, msg: P.Relocalize) -> Future:
        """Single-image relocalization on an idle worker of the relocalization lane (queued
        until one is; cancel the future to drop it), or, without a lane, on the least busy
        worker. The future gets the ``RelocResult``."""
        if not self._started:  # gRPC opens while the workers start (health: NOT_SERVING)
            raise UnavailableError("the engine workers are starting; retry")
        with self._lock:
            pending = self._reloc_pending
            if pending >= self.max_pending_relocalize:
                raise OverloadError(
                    f"{pending} relocalizations are already queued (limit "
                    f"{self.max_pending_relocalize}); retry later"
                )
            if self.reloc_workers:
                fut: Future = Future()
                self._reloc_pending += 1
                if len(self._reloc_queue) > 2 * self.max_pending_relocalize:  # cancelled ones
                    self._reloc_queue = collections.deque(
                        e for e in self._reloc_queue if not e[1].done()
                    )
                self._reloc_queue.append((msg, fut))
                self._changed.notify_all()
        if self.reloc_workers:
            fut.add_done_callback(self._reloc_done)
            self._pump_reloc()
            return fut
        with self._lock:
            lane = self.workers[self.n :] or self.workers
            lane = [w for w in lane if w.alive and w.serving] or lane  # a dead one answers at once
            h = min(lane, key=lambda w: (w.inflight, w.index))
            h.inflight += 1
            self._reloc_pending += 1
            self._changed.notify_all()  # a relocalization is queued (rare: not per frame)
        fut = self._request(h, msg)
        fut.add_done_callback(self._reloc_done)
        return fut

    def _reloc_done(self, fut: Future) -> None:
        with self._lock:
            self._reloc_pending -= 1

    def _pump_reloc(self) -> None:
        """Send queued relocalizations to idle lane workers, one each; drop those whose
        caller went away (future cancelled) or whose deadline passed while queued."""
        expired: list[Future] = []
        with self._lock:
            while self._reloc_queue:
                idle = [
                    w for w in self.workers[self.n :] if w.alive and w.serving and w.inflight == 0
                ]
                if not idle:
                    break
                msg, fut = self._reloc_queue.popleft()
                if fut.done():  # cancelled by its caller
                    continue
                if msg.deadline and time.monotonic() >= msg.deadline:
                    expired.append(fut)
                    continue
                h = idle[0]
                h.inflight += 1
                h.order.append(0)
                msg.req = next(self._req)
                self._futures[msg.req] = (h.index, fut)
                self._send(h, msg)
        for f in expired:
            _settle(f, exc=_lane_busy())

    def expire_relocalizations(self) -> int:
        """Answer the queued relocalizations whose time is up (``Relocalize.deadline``: when
        the answer must go back to reach the caller in time) at once, not when a lane worker
        frees up, which may be seconds after the caller gave up. The server calls it every
        0.1 s. Returns how many."""
        now = time.monotonic()
        with self._lock:
            if not self._reloc_queue:
                return 0
            keep: collections.deque[tuple[P.Relocalize, Future]] = collections.deque()
            expired: list[Future] = []
            for msg, fut in self._reloc_queue:
                if fut.done():
                    continue
                if msg.deadline and now >= msg.deadline:
                    expired.append(fut)
                else:
                    keep.append((msg, fut))
            self._reloc_queue = keep
        for f in expired:
            _settle(f, exc=_lane_busy())
        return len(expired)

    def _fail_all(self, exc: Exception) -> None:
        with self._lock:
            futures = [f for _, f in self._futures.values()]
            self._futures.clear()
        with self._lock:
            futures += [f for _, f in self._reloc_queue]
            self._reloc_queue.clear()
        for f in futures:
            _settle(f, exc=exc)

    def inflight(self) -> list[int]:
        return [h.inflight for h in self.workers]

    def busy_ms(self) -> list[float]:
        return [h.busy_ms for h in self.workers]


def _lane_busy() -> OverloadError:
    return OverloadError(
        "the relocalization lane was busy for the whole of the call's deadline (the work did "
        "not start); retry later or with a longer deadline"
    )


def _answered(order: collections.deque[int], ticket: int) -> None:
    """Strike an answered message from a worker's ``order`` (the first, as it answers in
    order; searched, so that a stray answer cannot shift every later one)."""
    if order and order[0] == ticket:
        order.popleft()
        return
    with contextlib.suppress(ValueError):
        order.remove(ticket)


def _settle(fut: Future, result: Any = None, exc: BaseException | None = None) -> None:
    """Complete ``fut`` unless its caller cancelled it (or it is already done)."""
    try:
        if exc is not None:
            fut.set_exception(exc)
        else:
            fut.set_result(result)
    except InvalidStateError:
        pass


# How a worker process starts: by module path, with the working directory (sys.path[0] of
# ``-m`` or ``-c``) removed from sys.path, so that a folder named ``sfmloc`` where the server
# was started (the parent of a clone) cannot shadow the installed package (``-P``, Python 3.11+).
_BOOTSTRAP = (
    "import sys; sys.path[:] = [p for p in sys.path if p not in ('', '.')]; "
    "sys.argv[0] = 'sfmloc-worker'; from sfmloc.server.worker import _main; _main()"
)
MAX_START_FAILURES = 3


class _Process(RelayedStderr):
    """``subprocess.Popen`` with the few ``Process``/``Thread`` methods the pool uses. The
    child's stderr is passed through to ours, and its last line kept (why it died)."""

    def __init__(self, popen: subprocess.Popen) -> None:
        self.popen = popen
        if popen.stderr is not None:
            self._stderr_pump = threading.Thread(
                target=self._pump, name=f"sfmloc-worker-stderr-{popen.pid}", daemon=True
            )
            self._stderr_pump.start()

    def _pump(self) -> None:
        assert self.popen.stderr is not None
        relay_stderr(self.popen.stderr, self)

    def join(self, timeout: float | None = None) -> None:
        try:
            self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            pass

    def is_alive(self) -> bool:
        return self.popen.poll() is None

    def terminate(self) -> None:
        self.popen.terminate()

    def kill(self) -> None:
        self.popen.kill()

    @property
    def exitcode(self) -> int | None:
        return self.popen.poll()
