"""Worker processes forked from one pre-imported interpreter (the *zygote*).

A fresh interpreter per worker pays the engine's imports (numpy, OpenCV, faiss, pydantic, the
engine) every time: with 2+1 workers on 2 cores that was most of the server's start, and a
replacement for a killed worker paid it again. The zygote is started once, as the pool's first
act, so its imports overlap the server's own; it imports what a worker needs and then only
forks. A forked worker starts in milliseconds and shares the imported modules' pages with its
siblings (copy on write; ``gc.freeze`` keeps the collector from touching them).

The zygote has one thread (it forks; a forked child of a threaded process may inherit held
locks) and never runs engine code. It speaks msgpack arrays over a Unix socket pair with the
server; the worker's socket and its stderr pipe travel as file descriptors (SCM_RIGHTS).

    server -> zygote   ["spawn", token, index, engine_conf_json, log_level, log_format, nice]
                       + fds (worker socket, stderr pipe write end)
    zygote -> server   ["spawned", token, pid]   ["exited", pid, returncode]

``returncode`` follows ``subprocess``: negative for a signal. The zygote reaps its children at
once (SIGCHLD wakes it) and exits when the server's end closes (the server died or stopped);
workers then see their own sockets close and exit too. Nothing is pickled.
"""

from __future__ import annotations

import logging
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import msgpack

from ..threads import THREAD_VARS, single_thread_env

log = logging.getLogger(__name__)

# Process names (/proc/PID/comm) of the zygote and of the workers it forks.
ZYGOTE_NAME = "sfmloc-zygote"
WORKER_NAME = "sfmloc-worker"
MAX_MSG = 64 * 1024  # one spawn request (the engine configuration is a few kB)
MAX_PIXELS_VAR = "OPENCV_IO_MAX_IMAGE_PIXELS"

# How the zygote starts: by module path, without the working directory on sys.path (as
# ``pool._BOOTSTRAP``: a folder named ``sfmloc`` where the server started must not shadow it).
BOOTSTRAP = (
    "import sys; sys.path[:] = [p for p in sys.path if p not in ('', '.')]; "
    "sys.argv[0] = 'sfmloc-zygote'; from sfmloc.server.zygote import _main; _main()"
)


# ============================================================================ server side


def relay_stderr(stream: Any, holder: Any) -> None:
    """Copy a child's stderr ``stream`` (binary, line by line) to ours until it closes, keeping
    its last non-empty line (at most 300 characters) in ``holder.last_line``: why it died."""
    out = getattr(sys.stderr, "buffer", None)
    for line in iter(stream.readline, b""):
        text = line.decode("utf-8", "replace").strip()
        if text:
            holder.last_line = text[-300:]
        try:
            if out is not None:
                out.write(line)
                out.flush()
            else:
                sys.stderr.write(line.decode("utf-8", "replace"))
        except (OSError, ValueError):
            pass


class RelayedStderr:
    """A worker runner whose child's stderr a pump thread (``_stderr_pump``, running
    ``relay_stderr``) passes through to ours: ``pool._Process`` and ``ForkedWorker``."""

    last_line = ""
    _stderr_pump: threading.Thread | None = None

    def drain_stderr(self, timeout: float) -> None:
        """Wait (at most ``timeout`` s) until the exited child's stderr is read to its end, so
        ``last_line`` is its last line, not one the pump had not reached yet."""
        if self._stderr_pump is not None:
            self._stderr_pump.join(timeout)


class ForkedWorker(RelayedStderr):
    """A worker forked by the zygote, with the ``Popen``-like methods the pool uses. Its exit
    status comes from the zygote (it is the zygote's child, not ours)."""

    def __init__(self, pid: int, stderr_fd: int) -> None:
        self.pid = pid
        self._code: int | None = None
        self._exited = threading.Event()
        self.orphaned = False  # the zygote died: nobody reports our exit, poll the pid
        self._stderr_pump = threading.Thread(target=self._pump, args=(stderr_fd,), daemon=True)
        self._stderr_pump.start()

    def _pump(self, fd: int) -> None:
        """Passes the worker's stderr through to ours and keeps its last line (why it died)."""
        with os.fdopen(fd, "rb") as f:
            relay_stderr(f, self)

    def _set_exit(self, code: int) -> None:
        self._code = code
        self._exited.set()

    def join(self, timeout: float | None = None) -> None:
        if not self.orphaned:
            self._exited.wait(timeout)
            return
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.is_alive() and (deadline is None or time.monotonic() < deadline):
            time.sleep(0.01)

    def _gone(self) -> bool:
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            self._set_exit(-signal.SIGKILL)  # the real status went to whoever reaped it
            return True
        except PermissionError:
            pass
        return False

    def is_alive(self) -> bool:
        if self._exited.is_set():
            return False
        return not (self.orphaned and self._gone())

    def _signal(self, sig: int) -> None:
        if not self._exited.is_set():
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def terminate(self) -> None:
        self._signal(signal.SIGTERM)

    def kill(self) -> None:
        self._signal(signal.SIGKILL)

    @property
    def exitcode(self) -> int | None:
        return self._code


class Zygote:
    """The server's handle on its zygote process: ``spawn`` forks a worker."""

    def __init__(self, env: dict[str, str]) -> None:
        self.env = env
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        fd = theirs.fileno()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", BOOTSTRAP, str(fd)],
            pass_fds=(fd,),
            env=env,
            stdin=subprocess.DEVNULL,
        )
        theirs.close()
        self._sock = ours
        self._lock = threading.Lock()  # one spawn at a time (requests and replies in order)
        self._spawned: dict[int, list[Any]] = {}  # token -> [event, pid]
        self._workers: dict[int, ForkedWorker] = {}  # pid -> handle
        self._early_exits: dict[int, int] = {}  # exits reported before the spawn reply was read
        self._token = 0
        self.on_exit: Callable[[], None] | None = None
        self._reader = threading.Thread(target=self._read, name="sfmloc-zygote", daemon=True)
        self._reader.start()

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None and self._reader.is_alive()

    def spawn(
        self,
        worker_fd: int,
        index: int,
        engine_conf_json: str,
        log_level: int,
        log_format: str,
        nice: int,
        timeout: float = 30.0,
    ) -> ForkedWorker:
        """Fork a worker on ``worker_fd`` (our copy stays open: the caller closes it)."""
        r, w = os.pipe()
        try:
            with self._lock:
                self._token += 1
                token = self._token
                waiter: list[Any] = [threading.Event(), 0]
                self._spawned[token] = waiter
                msg = ["spawn", token, index, engine_conf_json, log_level, log_format, nice]
                socket.send_fds(self._sock, [msgpack.packb(msg)], [worker_fd, w])
        except OSError:
            os.close(r)
            raise
        finally:
            os.close(w)
        if not waiter[0].wait(timeout) or not waiter[1]:
            os.close(r)
            raise OSError("the worker zygote did not fork a worker (it is gone)")
        pid = int(waiter[1])
        handle = ForkedWorker(pid, r)
        with self._lock:
            self._workers[pid] = handle
            code = self._early_exits.pop(pid, None)
        if code is not None:
            handle._set_exit(code)
        return handle

    def _read(self) -> None:
        while True:
            try:
                raw = self._sock.recv(MAX_MSG)
            except OSError:
                raw = b""
            if not raw:
                break
            try:
                msg = msgpack.unpackb(raw)
                kind = msg[0]
            except Exception:  # noqa: BLE001 - our own child: a bug, but keep reading
                log.exception("the worker zygote sent a malformed message")
                continue
            if kind == "spawned":
                with self._lock:
                    waiter = self._spawned.pop(int(msg[1]), None)
                if waiter is not None:
                    waiter[1] = int(msg[2])
                    waiter[0].set()
            elif kind == "exited":
                pid, code = int(msg[1]), int(msg[2])
                with self._lock:
                    handle = self._workers.pop(pid, None)
                    if handle is None:
                        self._early_exits[pid] = code
                if handle is not None:
                    handle._set_exit(code)
        # The zygote is gone: nothing will report its children's exits any more.
        with self._lock:
            waiting = list(self._spawned.values())
            self._spawned.clear()
            for handle in self._workers.values():
                handle.orphaned = True
        for waiter in waiting:
            waiter[0].set()  # pid 0: the spawn fails
        try:
            self.proc.wait(5)  # reaped: no zombie zygote
        except subprocess.TimeoutExpired:
            pass
        if self.on_exit is not None:
            self.on_exit()

    def close(self, timeout: float = 5.0) -> None:
        """Stop the zygote (its workers are stopped by the pool, or exit when their sockets
        close)."""
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._sock.close()
        self._reader.join(timeout)


def worker_env(max_image_pixels: int) -> dict[str, str]:
    """The environment of the zygote (hence of every worker): one thread for BLAS/OpenMP, in
    place before numpy loads, and OpenCV's decoding limit, which OpenCV reads once when it
    loads (so it must be right before the zygote imports cv2: it cannot be sent later)."""
    env = single_thread_env()
    # OpenCV refuses to decode larger images (decompression bombs: a small JPEG that claims a
    # huge size would otherwise be decoded before its size is checked).
    env[MAX_PIXELS_VAR] = str(max_image_pixels)
    return env


# The zygote started ahead of the server (``prestart``), until the pool takes it.
_prestarted: Zygote | None = None


def prestart(max_image_pixels: int) -> None:
    """Start the zygote now, before the server process imports its own modules: its imports
    (OpenCV, faiss, scipy, the engine: the longest part of a server start) then overlap the
    server's (gRPC, Zenoh, pydantic, the configuration) instead of following them. The pool
    takes it (``take_prestarted``) if it was started with the environment the pool needs;
    ``max_image_pixels`` is therefore a guess made before the configuration is read, checked
    when it is taken."""
    global _prestarted
    if _prestarted is None:
        _prestarted = Zygote(worker_env(max_image_pixels))


def take_prestarted(env: dict[str, str]) -> Zygote | None:
    """The prestarted zygote if it has the environment ``env`` the pool's workers need (else it
    is stopped: a wrong guess costs only its start); None without one."""
    global _prestarted
    z, _prestarted = _prestarted, None
    if z is None:
        return None
    if all(z.env.get(k) == env.get(k) for k in (MAX_PIXELS_VAR, *THREAD_VARS)) and z.alive:
        return z
    z.close()
    return None


def discard_prestarted() -> None:
    """Stop a prestarted zygote nobody took (the configuration asked for no forking)."""
    global _prestarted
    z, _prestarted = _prestarted, None
    if z is not None:
        z.close()


# ============================================================================ zygote side
def _preload() -> None:
    """Everything a worker imports before its first message, and what its first map load
    imports (the sub-map host: 0.33-0.4 s per worker at load 14, after the fork), imported
    once here."""
    from ..threads import pin_threads_env

    pin_threads_env()  # before numpy loads
    import concurrent.futures.thread  # noqa: F401

    import cv2  # noqa: F401
    import scipy.spatial  # noqa: F401 - the scope weights (engine.scope), not the server's

    from sfmloc_client import images  # noqa: F401

    from .. import engine  # noqa: F401
    from ..engine import config, submaps  # noqa: F401
    from ..map import bundle  # noqa: F401
    from . import logfmt, protocol, worker  # noqa: F401
    from .submaps import SubmapHost  # noqa: F401 - the server side of sub-map sets


def set_process_name(name: str) -> None:
    """The name ``ps``, ``top`` and /proc/PID/stat show (Linux ``PR_SET_NAME``, at most 15
    bytes): a forked worker's command line is the zygote's, this tells them apart."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(15, name.encode()[:15], 0, 0, 0)  # 15: PR_SET_NAME
    except (OSError, AttributeError):  # not Linux: names are cosmetic
        pass


def _child(sock: socket.socket, wake_r: int, wake_w: int, msg: list[Any], fds: list[int]) -> None:
    """In the forked child: become the worker (never returns)."""
    code = 1
    try:
        set_process_name(WORKER_NAME)
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        sock.close()
        os.close(wake_r)
        os.close(wake_w)
        worker_fd, err_fd = fds
        os.dup2(err_fd, 2)  # sys.stderr writes to fd 2: now this worker's own pipe
        os.close(err_fd)
        from multiprocessing.connection import Connection

        from .worker import worker_main

        _, _, index, conf_json, log_level, log_format, nice = msg
        worker_main(Connection(worker_fd), index, conf_json, log_level, log_format, True, nice)
        code = 0
    except BaseException:  # noqa: BLE001 - report and leave; never return into the zygote
        import traceback

        traceback.print_exc()
    finally:
        try:
            sys.stderr.flush()
        except Exception:  # noqa: BLE001
            pass
        os._exit(code)


def _reap(sock: socket.socket) -> None:
    while True:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        code = -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)
        try:
            sock.send(msgpack.packb(["exited", pid, code]))
        except OSError:
            pass


def _main() -> None:
    import gc

    sock = socket.socket(fileno=int(sys.argv[1]))
    # Ctrl-C or SIGTERM to the process group: the server coordinates shutdown (we exit when
    # its end of the socket closes).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    set_process_name(ZYGOTE_NAME)
    _preload()
    gc.freeze()  # the preloaded objects stay out of the collector: shared pages stay shared
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)  # a handler, so the wake-up fd is written
    while True:
        try:
            ready, _, _ = select.select([sock.fileno(), wake_r], [], [])
        except InterruptedError:
            continue
        if wake_r in ready:
            os.read(wake_r, 512)
            _reap(sock)
        if sock.fileno() in ready:
            try:
                data, fds, _, _ = socket.recv_fds(sock, MAX_MSG, 2)
            except OSError:
                data, fds = b"", []
            if not data:
                break  # the server is gone
            try:
                msg = msgpack.unpackb(data)
                if msg[0] != "spawn" or len(msg) != 7 or len(fds) != 2:
                    raise ValueError(f"unexpected request {msg!r:.80}")
            except Exception as exc:  # noqa: BLE001 - only the server writes here
                print(f"sfmloc-zygote: {exc}", file=sys.stderr)
                for fd in fds:
                    os.close(fd)
                continue
            sys.stderr.flush()  # nothing buffered may be written twice
            pid = os.fork()
            if pid == 0:
                _child(sock, wake_r, wake_w, msg, fds)
            for fd in fds:
                os.close(fd)
            sock.send(msgpack.packb(["spawned", msg[1], pid]))
            _reap(sock)
    _reap(sock)
    os._exit(0)


__all__ = [
    "WORKER_NAME",
    "ZYGOTE_NAME",
    "ForkedWorker",
    "Zygote",
    "discard_prestarted",
    "prestart",
    "set_process_name",
    "take_prestarted",
    "worker_env",
]
