"""Servers for tests, the demo and benchmarks (not used by the server itself).

- ``ServerThread``: a ``Server`` on a background thread with its own event loop, in this
  process (tests reach into ``srv.server``).
- ``ServerProcess``: ``sfmloc serve`` in a subprocess on free loopback ports.
- ``scene_points``: a synthetic scene in front of a camera, for the pose kernels' tests.
"""

from __future__ import annotations

import asyncio
import fcntl
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from typing import TYPE_CHECKING, Any

import numpy as np

from .server.config import ServerConfig
from .transforms import Rigid3d

if TYPE_CHECKING:  # the server (grpc, the map index) only where a test starts one
    from .server.app import Server


class ServerThread:
    """A server on a background thread with its own event loop (tests, the demo, benchmarks)::

    with ServerThread(conf) as srv:     # returns once SERVING
        srv.grpc_port, srv.server.registry ...
    """

    def __init__(self, conf: ServerConfig, load_maps: bool = True) -> None:
        self.conf = conf
        self.load_maps = load_maps
        self.server: Server | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=self._run, name="sfmloc-server", daemon=True)
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._done = threading.Event()

    def _run(self) -> None:
        self.loop = asyncio.new_event_loop()
        asyncio.set_event_loop(self.loop)
        try:
            from .server.app import Server

            self.server = Server(self.conf)
            self.loop.run_until_complete(self.server.start(load_maps=self.load_maps))
        except BaseException as exc:  # noqa: BLE001 - handed to start()
            self._error = exc
            self._started.set()
            if self.server is not None:
                try:
                    self.loop.run_until_complete(self.server.stop(0))
                except Exception:  # noqa: BLE001
                    pass
            self.loop.close()
            self._done.set()
            return
        self._started.set()
        try:
            self.loop.run_until_complete(self.server.wait_stopped())
        finally:
            self.loop.close()
            self._done.set()

    def start(self, timeout: float = 120.0) -> ServerThread:
        self._thread.start()
        if not self._started.wait(timeout):
            raise TimeoutError("the server did not start in time")
        if self._error is not None:
            raise self._error
        return self

    def call(self, coro: Any, timeout: float = 60.0) -> Any:
        """Run a coroutine on the server's loop
        (e.g. ``srv.call(srv.server.load_initial_maps())``)."""
        assert self.loop is not None
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def stop(self, grace: float | None = None, timeout: float = 60.0) -> None:
        if self.server is not None and self.loop is not None and not self._done.is_set():
            self.call(self.server.stop(grace), timeout)
        self._done.wait(timeout)
        self._thread.join(timeout)

    @property
    def grpc_port(self) -> int | None:
        return None if self.server is None else self.server.grpc_port

    def __enter__(self) -> ServerThread:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


# Ports for test servers come from below the kernel's ephemeral range: a port that bind(0)
# picked and we released (the old way) could be handed to any connect() or another process's
# bind(0) before the server bound it, a race when tests run in parallel (pytest-xdist). Each
# xdist worker takes its own block (any other process the last one), from a random start, in
# turn, skipping ports in use; the lowest port of the blocks:
PORT_LOW = 16384
PORT_BLOCKS = 16
# Two test runs side by side (helpers run suites at once) both have a gw0 with the same block,
# and a port free when handed out is bound only later: each port handed out is also reserved,
# machine-wide, by an exclusive lock on a file named by it, held until this process exits (the
# kernel drops it then, even on a crash). Another process skips a port it cannot lock.
PORT_LOCK_DIR = os.path.join(tempfile.gettempdir(), "sfmloc-test-ports")
_port_lock = threading.Lock()
_port_cursor: list[int] = []
_port_reserved: dict[int, int] = {}  # port -> the open lock file holding it for this process


def ephemeral_low() -> int:
    """The first port of the kernel's ephemeral range (ip_local_port_range; 32768 elsewhere)."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def port_block() -> range:
    """This process's ports: block N of an xdist worker gwN, else the last block."""
    size = (ephemeral_low() - PORT_LOW) // PORT_BLOCKS
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    digits = worker[2:] if worker.startswith("gw") else ""
    i = int(digits) % PORT_BLOCKS if digits.isdigit() else PORT_BLOCKS - 1
    return range(PORT_LOW + i * size, PORT_LOW + (i + 1) * size)


def _bindable(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def _reserve(port: int) -> bool:
    """Whether this process holds ``port``'s lock (taken now, or before)."""
    if port in _port_reserved:
        return True
    path = os.path.join(PORT_LOCK_DIR, f"{port}.lock")
    try:
        if not os.path.isdir(PORT_LOCK_DIR):
            os.makedirs(PORT_LOCK_DIR, exist_ok=True)
            os.chmod(PORT_LOCK_DIR, 0o1777)  # every user's test runs reserve here
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        # Another user's lock file is theirs; with no lock directory at all, nothing to share:
        # the bind test alone decides, as before.
        return not os.path.exists(path)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:  # another process (another test run) holds it
        os.close(fd)
        return False
    _port_reserved[port] = fd
    return True


def free_port() -> int:
    """A loopback TCP port nobody listens on, for a server about to bind it: the next free one
    of this process's ``port_block`` (never one of another xdist worker's or the kernel's
    ephemeral ones) that no other process has reserved (``PORT_LOCK_DIR``)."""
    block = port_block()
    if len(block) < 64:  # an ephemeral range reaching down here: the kernel picks
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            return s.getsockname()[1]
    with _port_lock:
        if not _port_cursor:
            _port_cursor.append(random.randrange(len(block)))
        for _ in range(len(block)):
            port = block[_port_cursor[0] % len(block)]
            _port_cursor[0] = (_port_cursor[0] + 1) % len(block)
            if _bindable(port) and _reserve(port):
                return port
    raise OSError(f"no free port in {block.start}-{block.stop - 1}")


def serve_command(
    maps: str | os.PathLike,
    endpoint: str,
    grpc: str,
    workers: int = 0,
    kind: str = "process",
    quiet: bool = True,
    extra_args: tuple[str, ...] = (),
) -> list[str]:
    """The ``sfmloc serve`` command line of a test server: Zenoh listening on ``endpoint``
    without multicast, gRPC on ``grpc``, ``workers`` engine workers of ``kind``."""
    return [
        sys.executable,
        "-m",
        "sfmloc",
        *(["-q"] if quiet else []),
        "serve",
        "--maps",
        str(maps),
        "--zenoh-listen",
        endpoint,
        "--no-multicast",
        "--grpc",
        grpc,
        "--workers",
        str(workers),
        "--worker-kind",
        kind,
        *extra_args,
    ]


class ServerProcess:
    """``sfmloc serve`` in a subprocess on free loopback ports (the demo, benchmarks)::

    with ServerProcess(maps_dir, workers=2) as srv:   # returns once SERVING
        srv.endpoint (Zenoh), srv.grpc (host:port)
    """

    def __init__(
        self,
        maps: str | os.PathLike,
        workers: int = 0,
        kind: str = "process",
        quiet: bool = True,
        extra_args: tuple[str, ...] = (),
        env: dict[str, str] | None = None,
        cpus: set[int] | None = None,
        stderr: Any = None,
    ) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.grpc = f"127.0.0.1:{free_port()}"
        cmd = serve_command(maps, self.endpoint, self.grpc, workers, kind, quiet, extra_args)
        # cpus: the server and every worker it starts (they inherit the affinity) run only on
        # these cores (benchmarks that give each server its own share of the machine).
        # stderr: e.g. a file to read its log from.
        pin = (lambda: os.sched_setaffinity(0, cpus)) if cpus else None
        self.proc = subprocess.Popen(cmd, env=env, preexec_fn=pin, stderr=stderr)

    def __enter__(self) -> ServerProcess:
        from sfmloc_client import LocalizationClient

        from .errors import UnavailableError

        with LocalizationClient(self.grpc) as c:
            if not c.wait_ready(180):
                self.proc.kill()
                self.proc.wait()
                raise UnavailableError(
                    f"the server did not become ready (exit code {self.proc.returncode})"
                )
        return self

    def stop(self, timeout: float = 60.0) -> int | None:
        """SIGTERM (graceful shutdown); the exit code (0 after a clean stop)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    def __exit__(self, *exc: Any) -> None:
        self.stop()


def scene_points(
    rng: np.random.Generator,
    n: int,
    cam_from_world: Rigid3d,
    K: np.ndarray,
    depth: tuple[float, float] = (1.5, 6.0),
    margin: float = 20.0,
    size: tuple[int, int] = (640, 480),
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` world points (N, 3) in front of the camera ``cam_from_world`` (intrinsics ``K``)
    at depths uniform in ``depth``, and their exact pixels (N, 2), uniform over the image of
    ``size`` at least ``margin`` px inside its border."""
    uv = rng.uniform([margin, margin], [size[0] - margin, size[1] - margin], (n, 2))
    z = rng.uniform(depth[0], depth[1], n)
    xc = np.hstack([(uv - K[:2, 2]) / K[[0, 1], [0, 1]] * z[:, None], z[:, None]])
    return cam_from_world.inverse().apply(xc), uv


def one_to_many_matches(
    rng: np.random.Generator, n: int, n1: int, wrong_share: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matches of ``n`` keypoints to the ``n`` points of a scene (keypoint i's point is i) as
    global matching hands them to the one-to-many RANSAC: set 1, the first ``n1`` keypoints'
    best points with about ``wrong_share`` of them another random point (``p1``, (n1,)); set
    2, every keypoint with three hypotheses, its true point and two random ones (keypoints
    ``q2`` and points ``p2``, (3n,) each)."""
    p1 = np.arange(n1)
    wrong = rng.random(n1) < wrong_share
    p1[wrong] = rng.integers(0, n, wrong.sum())
    q2 = np.repeat(np.arange(n), 3)
    p2 = np.stack([np.arange(n), rng.integers(0, n, n), rng.integers(0, n, n)], 1).ravel()
    return p1, q2, p2
