"""The worker pool: where frames are localized.

Each worker (a process by default) holds every loaded map (memory-mapped arrays; the faiss
index read in place from the bundle's mapped file, so all workers share one copy) and the
``Localizer`` of each session assigned to it, and processes one message at a time, so a frame
runs start to end on one core and its latency does not depend on what other threads do.
Sessions stick to their worker (their track table and filter live there).

Why processes: the engine is numpy/OpenCV with many small Python-level steps, and the GIL
serializes those across threads; measured with ``sfmloc bench-transport --only engine,workers``
(numbers in ``app.py``). ``worker_kind="thread"`` exists for that comparison only.

A worker process is a fresh interpreter (``python -m sfmloc.server.workers``) holding one end
of a socket pair. Messages are msgpack, framed by ``multiprocessing.connection.Connection``
(``send_bytes``/``recv_bytes``); frame bytes follow their header as a second message. Nothing
is pickled anywhere (no ``multiprocessing`` queues, which pickle, and no spawn arguments).

Protocol (server -> worker): ``load`` (name, gen, path), ``drop`` (name, gen), ``frame`` (sid,
map, gen, seq, stamp, camera, encoding; + data), ``reloc`` (req, map, gen, camera, encoding,
prior; + data), ``reset`` (sid), ``close`` (sid), ``stop``. Worker -> server: ``ready``,
``loaded`` (req, summary | error), ``result`` (sid, seq, res | error), ``reloc_result``.
"""

from __future__ import annotations

import itertools
import logging
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

import msgpack

from ..errors import BundleError, OverloadError, UnavailableError
from .logfmt import event
from .status import error_from_wire, error_to_wire

log = logging.getLogger(__name__)

SOCKET_BUFFER = 4 * 1024 * 1024  # per direction: a few raw frames fit in one write
# One thread per worker for BLAS/OpenMP: in the worker's environment before numpy loads.
THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def _pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _unpack(raw: bytes) -> Any:
    return msgpack.unpackb(raw, raw=False)


# ============================================================================ worker side
def worker_main(conn: Any, index: int, engine_conf_json: str, log_level: int, log_format: str,
                is_process: bool, nice: int = 0) -> None:
    """Entry point of a worker (a process, or a thread for measurements). ``nice`` > 0 lowers
    the process's CPU priority (the relocalization lane: streams' frames win the CPU)."""
    if is_process and nice > 0:
        try:
            os.nice(nice)
        except OSError:  # not permitted: run at the normal priority
            pass
    if is_process:
        # The server process coordinates shutdown: Ctrl-C in a terminal signals the whole
        # process group, and a worker must not die mid-frame. It exits on "stop" or when its
        # pipe closes (the server went away).
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        for var in THREAD_ENV:
            os.environ.setdefault(var, "1")
        from .logfmt import setup_logging

        setup_logging(log_format, log_level)
    import cv2  # noqa: E402 - after the thread environment is set
    import faiss

    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    from .. import engine  # noqa: F401 - imported now (scipy, filterpy...), not on the first frame
    try:
        _Worker(conn, index, engine_conf_json).run()
    finally:
        try:
            conn.close()
        except OSError:
            pass


@dataclass
class _SessionState:
    localizer: Any
    map_key: tuple[str, int]
    camera_key: tuple


class _Worker:
    def __init__(self, conn: Any, index: int, engine_conf_json: str) -> None:
        from ..engine.config import EngineConf

        self.conn = conn
        self.index = index
        self.conf = EngineConf.model_validate_json(engine_conf_json)
        self.bundles: dict[tuple[str, int], Any] = {}
        self.sessions: dict[int, _SessionState] = {}
        self._cameras: dict[tuple, Any] = {}

    def send(self, msg: dict[str, Any]) -> None:
        self.conn.send_bytes(_pack(msg))

    def run(self) -> None:
        self.send({"op": "ready", "index": self.index, "pid": os.getpid()})
        while True:
            try:
                msg = _unpack(self.conn.recv_bytes())
                data = self.conn.recv_bytes() if msg.get("has_data") else None
            except (EOFError, OSError):
                return  # the server is gone
            op = msg.get("op")
            if op == "stop":
                return
            try:
                getattr(self, f"op_{op}")(msg, data)
            except (EOFError, OSError, BrokenPipeError):
                return
            except Exception:  # noqa: BLE001 - a bug in one handler must not end the worker
                log.exception("worker %d: %s failed", self.index, op)

    # ------------------------------------------------------------------ maps
    def op_load(self, m: dict[str, Any], data: bytes | None) -> None:
        from ..map.bundle import MapBundle

        t0 = time.perf_counter()
        try:
            # The server verified the checksums once; here only the structure is checked.
            b = MapBundle(m["path"], verify=False)
            if m.get("build_id") and b.build_id != m["build_id"]:
                raise BundleError(
                    f"map bundle {m['path']} changed while loading (build {b.build_id}, expected {m['build_id']}); retry"
                )
            _warm_up(b, self.conf)
            self.bundles[(m["name"], m["gen"])] = b
            s = b.summary()
            summary = {k: s[k] for k in ("points", "descriptors", "images", "clusters", "memory_mb", "build_id")}
            # The index reads the bundle's mapped file in place: every worker shares one copy.
            summary["index_in_place"] = b.index.shared_buffer is not None
            self.send({"op": "loaded", "req": m["req"], "summary": summary, "ms": (time.perf_counter() - t0) * 1e3})
        except Exception as exc:  # noqa: BLE001
            self.send({"op": "loaded", "req": m["req"], "error": error_to_wire(exc)})

    def op_drop(self, m: dict[str, Any], data: bytes | None) -> None:
        key = (m["name"], m["gen"])
        self.bundles.pop(key, None)
        for sid in [s for s, st in self.sessions.items() if st.map_key == key]:
            del self.sessions[sid]  # its next frame (on the new generation) starts afresh

    # ------------------------------------------------------------------ sessions
    def _camera(self, c: list[Any]) -> Any:
        from ..cameras import Camera

        key = (c[0], c[1], c[2], tuple(c[3]))
        cam = self._cameras.get(key)
        if cam is None:
            cam = Camera(c[0], c[1], c[2], list(c[3]))
            if len(self._cameras) > 64:
                self._cameras.clear()
            self._cameras[key] = cam
        return cam

    def op_frame(self, m: dict[str, Any], data: bytes | None) -> None:
        from sfmloc_client.images import decode_image

        from ..engine import Localizer
        from ..errors import MapNotFoundError, SfmlocError

        t0 = time.perf_counter()
        sid = m["sid"]
        out: dict[str, Any] = {"op": "result", "sid": sid, "seq": m["seq"], "stamp_ns": m["stamp_ns"], "gen": m["gen"]}
        try:
            key = (m["map"], m["gen"])
            bundle = self.bundles.get(key)
            if bundle is None:
                raise MapNotFoundError(f"map {m['map']!r} is not loaded (it was unloaded or replaced)")
            cam = self._camera(m["camera"])
            ckey = (cam.model, cam.width, cam.height, tuple(cam.params.tolist()))
            st = self.sessions.get(sid)
            if st is None or st.map_key != key or st.camera_key != ckey:
                # New session, a replaced map or another camera: a fresh Localizer (relocalizes).
                st = _SessionState(Localizer(bundle, cam, self.conf), key, ckey)
                self.sessions[sid] = st
            img = decode_image(m["enc"], data or b"", cam.width, cam.height)
            out["decode_ms"] = (time.perf_counter() - t0) * 1e3
            out["res"] = result_to_wire(st.localizer.localize(img, m["stamp_ns"] * 1e-9))
        except Exception as exc:  # noqa: BLE001 - reported to the client, never fatal
            from sfmloc_client.errors import WireError

            if not isinstance(exc, (SfmlocError, WireError)):
                log.exception("worker %d: frame %s of session %d failed", self.index, m.get("seq"), sid)
                self.sessions.pop(sid, None)  # do not keep state an exception may have corrupted
            out["error"] = error_to_wire(exc)
        out["worker_ms"] = (time.perf_counter() - t0) * 1e3
        self.send(out)

    def op_reset(self, m: dict[str, Any], data: bytes | None) -> None:
        st = self.sessions.get(m["sid"])
        if st is not None:
            st.localizer.reset()

    def op_close(self, m: dict[str, Any], data: bytes | None) -> None:
        self.sessions.pop(m["sid"], None)

    # ------------------------------------------------------------------ single images
    def op_reloc(self, m: dict[str, Any], data: bytes | None) -> None:
        from sfmloc_client.images import decode_image

        from ..engine import relocalize
        from ..errors import MapNotFoundError
        from ..transforms import Rigid3d

        t0 = time.perf_counter()
        out: dict[str, Any] = {"op": "reloc_result", "req": m["req"]}
        try:
            bundle = self.bundles.get((m["map"], m["gen"]))
            if bundle is None:
                raise MapNotFoundError(f"map {m['map']!r} is not loaded (it was unloaded or replaced)")
            cam = self._camera(m["camera"])
            img = decode_image(m["enc"], data or b"", cam.width, cam.height)
            prior = None
            if m.get("prior"):
                q, t = m["prior"]
                prior = Rigid3d.from_quat_xyzw(q, t)
            out["res"] = result_to_wire(relocalize(img, cam, bundle, self.conf, prior=prior))
        except Exception as exc:  # noqa: BLE001
            from sfmloc_client.errors import WireError

            from ..errors import SfmlocError

            if not isinstance(exc, (SfmlocError, WireError)):
                log.exception("worker %d: relocalize failed", self.index)
            out["error"] = error_to_wire(exc)
        out["worker_ms"] = (time.perf_counter() - t0) * 1e3
        self.send(out)


def _warm_up(bundle: Any, conf: Any) -> None:
    """One relocalization of a textured dummy image: first-call costs (allocations, caches,
    the index's first search) are paid at load time rather than by a client's first frame."""
    import numpy as np

    from ..engine import relocalize

    if not bundle.cameras:
        return
    cam = bundle.cameras[0]
    rng = np.random.default_rng(0)
    img = (rng.random((cam.height // 8 + 1, cam.width // 8 + 1)) * 255).astype(np.uint8)
    img = np.kron(img, np.ones((8, 8), np.uint8))[: cam.height, : cam.width]
    try:
        relocalize(np.ascontiguousarray(img), cam, bundle, conf)
    except Exception as exc:  # noqa: BLE001 - a warm-up failure is not a load failure
        log.debug("warm-up failed: %s", exc)


def _tf(T: Any) -> list[float] | None:
    """Rigid3d -> [qx, qy, qz, qw, tx, ty, tz]."""
    if T is None:
        return None
    return [*(float(v) for v in T.quat_xyzw), *(float(v) for v in T.translation)]


def result_to_wire(r: Any) -> dict[str, Any]:
    """An engine ``FrameResult`` as plain values (all four transforms: the inverse is computed
    here, on the worker, rather than in the server's intake thread)."""
    return {
        "status": r.status.value,
        "cfw": _tf(r.cam_from_world),
        "wfc": _tf(r.world_from_cam),
        "fcfw": _tf(r.filtered_cam_from_world),
        "fwfc": _tf(r.filtered_world_from_cam),
        "inliers": int(r.inliers),
        "detected": int(r.detected),
        "tracked": int(r.tracked),
        "tracked_3d": int(r.tracked_3d),
        "matching": r.matching,
        "engine_ms": float(r.latency_ms),
        "message": r.message,
        "cov": None if r.covariance is None else [float(v) for v in r.covariance.ravel()],
    }


# ============================================================================ server side
@dataclass
class WorkerHandle:
    index: int
    conn: Any
    runner: Any  # _Process (a worker process) or threading.Thread
    outbox: "queue.SimpleQueue[tuple[bytes, bytes | None] | None]" = field(default_factory=queue.SimpleQueue)
    inflight: int = 0  # frames and relocalizations sent, not yet answered
    busy_ms: float = 0.0  # engine time so far (load reporting)
    alive: bool = True
    pid: int = 0
    threads: list[threading.Thread] = field(default_factory=list)
    ready: threading.Event = field(default_factory=threading.Event)  # this process said "ready"


class WorkerPool:
    """``n`` workers, their message pumps, and request/response bookkeeping.

    ``on_result(msg)`` is called (on a pump thread) with every frame result; ``on_lost(index)``
    when a worker died (it is restarted and its maps reloaded; its sessions lose their state).
    """

    def __init__(
        self,
        n: int,
        kind: str,
        engine_conf_json: str,
        *,
        on_result: Callable[[dict[str, Any]], None],
        on_lost: Callable[[int], None] | None = None,
        on_dead: Callable[[int], None] | None = None,
        log_level: int = logging.INFO,
        log_format: str = "kv",
        max_pending_relocalize: int = 16,
        max_image_pixels: int = 4096 * 4096,
        reloc_workers: int = 0,
        reloc_nice: int = 5,
    ) -> None:
        self.n = n  # stream workers (sessions live on workers 0..n-1)
        # Workers n..n+reloc_workers-1 only serve single-image relocalizations (their own
        # lane): a 70-120 ms (or, for a huge image, seconds-long) relocalization never
        # holds a worker that streams' frames queue on. 0: they share the stream workers.
        self.reloc_workers = reloc_workers
        self.reloc_nice = reloc_nice
        self.kind = kind
        self.engine_conf_json = engine_conf_json
        self.on_result = on_result
        self.on_lost = on_lost or (lambda i: None)
        self.on_dead = on_dead or (lambda i: None)
        self.log_level, self.log_format = log_level, log_format
        self.max_pending_relocalize = max_pending_relocalize
        self.max_image_pixels = max_image_pixels
        self.workers: list[WorkerHandle] = []
        self._lock = threading.Lock()
        self._req = itertools.count(1)
        self._futures: dict[int, tuple[int, Future]] = {}  # req -> (worker, future)
        self._ready: dict[int, threading.Event] = {}
        self._maps: dict[tuple[str, int], tuple[str, str]] = {}  # (name, gen) -> (path, build_id)
        self._stopping = False
        self._reloc_pending = 0
        self.restarts = 0
        self._start_failures = [0] * (n + reloc_workers)  # deaths before "ready", per worker index
        self._maps_version = 0  # bumped by every load/drop (a restart reloads until it is stable)
        self.fatal: Exception | None = None  # a worker that cannot start: the pool gives up
        self._started = False  # start() returned: every worker was ready once

    # ------------------------------------------------------------------ lifecycle
    def start(self, timeout: float = 120.0) -> None:
        for var in THREAD_ENV:
            os.environ.setdefault(var, "1")
        for i in range(self.n + self.reloc_workers):
            self.workers.append(self._spawn(i))
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
        self._started = True

    def _spawn(self, i: int) -> WorkerHandle:
        ours, theirs = socket.socketpair()
        for sock in (ours, theirs):  # a whole frame fits: one write, one read, fewer wake-ups
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
        if self.kind == "process":
            # A fresh interpreter (not multiprocessing's spawn): it does not re-import the
            # caller's __main__, nothing is pickled, and the one-thread environment is in place
            # before numpy loads.
            env = dict(os.environ, **{var: "1" for var in THREAD_ENV})
            # OpenCV refuses to decode larger images (decompression bombs: a small JPEG that
            # claims a huge size would otherwise be decoded before its size is checked).
            env["OPENCV_IO_MAX_IMAGE_PIXELS"] = str(self.max_image_pixels)
            fd = theirs.fileno()
            cmd = [sys.executable, "-c", _BOOTSTRAP, "--fd", str(fd), "--index", str(i),
                   "--log-level", str(self.log_level), "--log-format", self.log_format,
                   "--engine-conf", self.engine_conf_json,
                   "--nice", str(self.reloc_nice if i >= self.n else 0)]
            runner: Any = _Process(subprocess.Popen(cmd, pass_fds=(fd,), env=env, stdin=subprocess.DEVNULL,
                                                    stderr=subprocess.PIPE))
            theirs.close()  # the child holds its end; ours must not keep it open (EOF detection)
        else:
            conn = Connection(theirs.detach())
            args = (conn, i, self.engine_conf_json, self.log_level, self.log_format, False)
            runner = threading.Thread(target=worker_main, args=args, name=f"sfmloc-worker-{i}", daemon=True)
            runner.start()
        self._ready[i] = threading.Event()
        h = WorkerHandle(i, Connection(ours.detach()), runner)
        h.threads = [
            threading.Thread(target=self._sender, args=(h,), name=f"sfmloc-worker-{i}-send", daemon=True),
            threading.Thread(target=self._reader, args=(h,), name=f"sfmloc-worker-{i}-recv", daemon=True),
        ]
        for t in h.threads:
            t.start()
        return h

    def stop(self, timeout: float = 10.0) -> None:
        self._stopping = True
        for h in self.workers:
            h.outbox.put((_pack({"op": "stop"}), None))
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
        self._fail_all(UnavailableError("the server is shutting down"))

    # ------------------------------------------------------------------ pumps
    def _sender(self, h: WorkerHandle) -> None:
        """Writes to one worker's socket. A separate thread, so a busy worker (its socket
        full) never blocks the Zenoh or gRPC thread that handed over a frame."""
        while True:
            item = h.outbox.get()
            if item is None:
                return
            header, data = item
            try:
                h.conn.send_bytes(header)
                if data is not None:
                    h.conn.send_bytes(data)
            except (OSError, ValueError):
                return  # the reader notices the dead worker

    def _reader(self, h: WorkerHandle) -> None:
        while True:
            try:
                msg = _unpack(h.conn.recv_bytes())
            except (EOFError, OSError, ValueError, TypeError):  # TypeError: closed by stop()
                break
            try:
                self._dispatch(h, msg)
            except Exception:  # noqa: BLE001 - keep pumping
                log.exception("handling a message of worker %d failed", h.index)
        if not self._stopping:
            self._worker_lost(h)

    def _dispatch(self, h: WorkerHandle, msg: dict[str, Any]) -> None:
        op = msg.get("op")
        if op == "result":
            with self._lock:
                h.inflight -= 1
                h.busy_ms += msg.get("worker_ms", 0.0)
            self.on_result(msg)
        elif op in ("loaded", "reloc_result"):
            with self._lock:
                entry = self._futures.pop(msg["req"], None)
                if op == "reloc_result":
                    h.inflight -= 1
                    h.busy_ms += msg.get("worker_ms", 0.0)
            if entry is not None:
                fut = entry[1]
                if "error" in msg:
                    fut.set_exception(error_from_wire(msg["error"]))
                else:
                    fut.set_result(msg)
        elif op == "ready":
            h.pid = msg.get("pid", 0)
            h.ready.set()
            self._ready[h.index].set()

    def _worker_lost(self, h: WorkerHandle) -> None:
        """A worker died (a crash in native code, killed): fail what it had, restart it with
        the current maps, and tell the sessions (they relocalize on the new worker)."""
        if self.kind == "process":
            h.runner.join(5)  # reap it now: no zombie, and its exit code is known
        code = getattr(h.runner, "exitcode", None)
        pid = h.pid or getattr(getattr(h.runner, "popen", None), "pid", 0)
        started = h.ready.is_set()
        event(log, logging.ERROR, "worker_lost", worker=h.index, pid=pid, exitcode=code,
              during_start=not started, stderr=getattr(h.runner, "last_line", ""))
        with self._lock:
            h.alive = False
            h.outbox.put(None)
            lost = [r for r, (w, _) in self._futures.items() if w == h.index]
            futures = [self._futures.pop(r)[1] for r in lost]
        for f in futures:
            f.set_exception(UnavailableError(f"worker {h.index} died; retry"))
        if self._stopping:
            return
        if started:
            try:
                self.on_dead(h.index)  # at once: answer its frames, move its sessions
            except Exception:  # noqa: BLE001 - the restart must go on
                log.exception("handling the death of worker %d failed", h.index)
        fails = 0 if started else self._start_failures[h.index] + 1
        self._start_failures[h.index] = fails
        if fails >= MAX_START_FAILURES:
            # Restarting would loop forever (e.g. the package does not import): give up loudly.
            self.fatal = UnavailableError(
                f"worker {h.index} exited {fails} times before it was ready (exit code {code})"
                + (f": {h.runner.last_line}" if getattr(h.runner, "last_line", "") else "")
            )
            event(log, logging.ERROR, "worker_start_failed", worker=h.index, attempts=fails, error=str(self.fatal))
            return
        if fails:
            time.sleep(min(5.0, 0.25 * 2**fails))  # back-off before the next attempt
        self.restarts += 1
        new = self._spawn(h.index)
        if not self._started:
            self.workers[h.index] = new  # start() waits on the replacement
            return
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
                    self._request(new, {"op": "load", "name": name, "gen": gen, "path": path,
                                        "build_id": build_id}).result(120)
                    loaded.add((name, gen))
                except Exception as exc:  # noqa: BLE001
                    log.error("worker %d: reloading map %s failed: %s", h.index, name, exc)
            with self._lock:
                if self._maps_version == version:
                    self.workers[h.index] = new
                    stale = loaded - set(self._maps)
                    break
            if not new.alive or self._stopping:
                return
        for name, gen in stale:
            self._send(new, {"op": "drop", "name": name, "gen": gen})
        event(log, logging.INFO, "worker_restarted", worker=h.index, pid=new.pid, maps=len(loaded - stale))
        self.on_lost(h.index)

    # ------------------------------------------------------------------ requests
    def _send(self, h: WorkerHandle, msg: dict[str, Any], data: bytes | None = None) -> None:
        if data is not None:
            msg["has_data"] = True
        h.outbox.put((_pack(msg), data))

    def _request(self, h: WorkerHandle, msg: dict[str, Any], data: bytes | None = None) -> Future:
        fut: Future = Future()
        with self._lock:
            req = next(self._req)
            self._futures[req] = (h.index, fut)
        msg["req"] = req
        if not h.alive:  # its pump is gone: nothing would ever answer
            with self._lock:
                self._futures.pop(req, None)
            fut.set_exception(UnavailableError(f"worker {h.index} is restarting; retry"))
            return fut
        self._send(h, msg, data)
        return fut

    def load_map(self, name: str, gen: int, path: str, build_id: str, timeout: float = 300.0) -> dict[str, Any]:
        """Load a bundle on every worker; returns the first worker's summary. All or nothing."""
        msg = {"op": "load", "name": name, "gen": gen, "path": path, "build_id": build_id}
        with self._lock:
            self._maps[(name, gen)] = (path, build_id)  # a worker restarting meanwhile loads it too
            self._maps_version += 1
            live = [h for h in self.workers if h.alive]  # a dead one's replacement loads it
        futures = [self._request(h, dict(msg)) for h in live]
        try:
            if not futures:
                raise UnavailableError("no engine worker is running (one is restarting); retry")
            results = [f.result(timeout) for f in futures]
        except BaseException:
            self.drop_map(name, gen)
            raise
        summary = dict(results[0]["summary"])
        summary["index_in_place"] = all(r["summary"].get("index_in_place", False) for r in results)
        return summary

    def drop_map(self, name: str, gen: int) -> None:
        with self._lock:
            self._maps.pop((name, gen), None)
            self._maps_version += 1
        for h in self.workers:
            self._send(h, {"op": "drop", "name": name, "gen": gen})

    def is_alive(self, worker: int) -> bool:
        """Whether worker ``worker`` is up (False from its death until its replacement is ready)."""
        return 0 <= worker < len(self.workers) and self.workers[worker].alive

    def submit_frame(self, worker: int, msg: dict[str, Any], data: bytes) -> None:
        h = self.workers[worker]
        with self._lock:
            h.inflight += 1
        msg["op"] = "frame"
        self._send(h, msg, data)

    def reset_session(self, worker: int, sid: int) -> None:
        self._send(self.workers[worker], {"op": "reset", "sid": sid})

    def close_session(self, worker: int, sid: int) -> None:
        self._send(self.workers[worker], {"op": "close", "sid": sid})

    def relocalize(self, msg: dict[str, Any], data: bytes) -> Future:
        """Single-image relocalization on the least busy worker of the relocalization lane
        (of all workers when it has none)."""
        with self._lock:
            pending = self._reloc_pending
            if pending >= self.max_pending_relocalize:
                raise OverloadError(
                    f"{pending} relocalizations are already queued (limit {self.max_pending_relocalize}); retry later"
                )
            lane = self.workers[self.n:] or self.workers
            h = min(lane, key=lambda w: (w.inflight, w.index))
            h.inflight += 1
            self._reloc_pending += 1
        msg["op"] = "reloc"
        fut = self._request(h, msg, data)
        fut.add_done_callback(self._reloc_done)
        return fut

    def _reloc_done(self, fut: Future) -> None:
        with self._lock:
            self._reloc_pending -= 1

    def _fail_all(self, exc: Exception) -> None:
        with self._lock:
            futures = [f for _, f in self._futures.values()]
            self._futures.clear()
        for f in futures:
            if not f.done():
                f.set_exception(exc)

    def inflight(self) -> list[int]:
        return [h.inflight for h in self.workers]

    def busy_ms(self) -> list[float]:
        return [h.busy_ms for h in self.workers]


# How a worker process starts: by module path, with the working directory (sys.path[0] of
# ``-m`` or ``-c``) removed from sys.path, so that a folder named ``sfmloc`` where the server
# was started (the parent of a clone) cannot shadow the installed package (``-P``, Python 3.11+).
_BOOTSTRAP = (
    "import sys; sys.path[:] = [p for p in sys.path if p not in ('', '.')]; "
    "sys.argv[0] = 'sfmloc-worker'; from sfmloc.server.workers import _main; _main()"
)
MAX_START_FAILURES = 3


class _Process:
    """``subprocess.Popen`` with the few ``Process``/``Thread`` methods the pool uses. The
    child's stderr is passed through to ours, and its last line kept (why it died)."""

    def __init__(self, popen: subprocess.Popen) -> None:
        self.popen = popen
        self.last_line = ""
        if popen.stderr is not None:
            threading.Thread(target=self._pump, name=f"sfmloc-worker-stderr-{popen.pid}", daemon=True).start()

    def _pump(self) -> None:
        assert self.popen.stderr is not None
        out = getattr(sys.stderr, "buffer", None)
        for line in iter(self.popen.stderr.readline, b""):
            text = line.decode("utf-8", "replace").strip()
            if text:
                self.last_line = text[-300:]
            try:
                if out is not None:
                    out.write(line)
                    out.flush()
                else:
                    sys.stderr.write(line.decode("utf-8", "replace"))
            except (OSError, ValueError):
                pass

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


def _main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description="sfmloc engine worker (started by the server, not by hand)")
    ap.add_argument("--fd", type=int, required=True)
    ap.add_argument("--index", type=int, required=True)
    ap.add_argument("--log-level", type=int, default=logging.INFO)
    ap.add_argument("--log-format", default="kv")
    ap.add_argument("--engine-conf", default="{}")
    ap.add_argument("--nice", type=int, default=0)
    a = ap.parse_args()
    worker_main(Connection(a.fd), a.index, a.engine_conf, a.log_level, a.log_format, True, a.nice)


if __name__ == "__main__":
    _main()
