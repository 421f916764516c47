"""Build jobs, each run start to end in its own worker process.

A crash in a build (an exception, a segfault in native code, the OOM killer) ends that
process, never the service: the job is marked FAILED with what is known. Progress events come
back over a pipe as typed messages (``sfmloc.childproc``, the framing the server's engine workers
use: msgpack arrays, no pickle). Cancellation sets an event the build polls between
steps (``BuildCancelled`` unwinds it and the bundle writer removes its temporary folder); a
build stuck inside native code is terminated after a grace period, and the parent removes what
the child left (its SfM work folder and any ``.NAME.tmp-<pid>-*`` bundle folder).
"""

from __future__ import annotations

import builtins
import enum
import logging
import multiprocessing as mp
import multiprocessing.connection
import shutil
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..childproc import Message, Protocol, ProtocolError
from ..errors import InputError, SfmlocError

log = logging.getLogger(__name__)


class JobState(str, enum.Enum):
    QUEUED = "QUEUED"
    RUNNING = "RUNNING"
    SUCCEEDED = "SUCCEEDED"
    FAILED = "FAILED"
    CANCELLED = "CANCELLED"

    @property
    def final(self) -> bool:
        return self in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)


@dataclass
class BuildSpec(Message):
    """What to build: the arguments of ``sfmloc.builder.build.main`` (paths on this machine).
    Also the message that starts a build process."""

    OP = "build"

    name: str
    out_dir: str
    input_kind: str  # "colmap" | "posed_images" | "images_only"
    images: str
    colmap: str | None = None
    poses: str | None = None
    camera: str | None = None  # "MODEL w h params..." or a camera.json path
    matching: str | None = None
    stride: int = 1
    preset: str = "default"
    config: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        from ..map.bundle import validate_name

        validate_name(self.name)
        if self.input_kind not in ("colmap", "posed_images", "images_only"):
            raise InputError(f"unknown input kind {self.input_kind!r}")
        if not self.images:
            raise InputError("an image folder is required")
        if self.input_kind == "colmap" and not self.colmap:
            raise InputError("a COLMAP input needs model_dir")
        if self.input_kind == "posed_images" and (not self.poses or not self.camera):
            raise InputError("a posed-images input needs poses_file and camera")
        if self.stride < 1:
            raise InputError(f"stride must be >= 1, got {self.stride}")


# ---------------------------------------------------------------- build process -> manager
@dataclass
class Progress(Message):
    OP = "progress"
    stage: str
    fraction: float
    message: str


@dataclass
class Done(Message):
    OP = "done"
    path: str
    build_id: str
    warnings: list[str]


@dataclass
class Cancelled(Message):
    OP = "cancelled"


@dataclass
class Failed(Message):
    OP = "failed"
    error: str
    stage: str


TO_BUILD = Protocol(BuildSpec)
FROM_BUILD = Protocol(Progress, Done, Cancelled, Failed)


@dataclass
class BuildEvent:
    job_id: str
    state: JobState
    stage: str = ""
    fraction: float = 0.0
    message: str = ""
    elapsed_s: float = 0.0
    bundle_path: str = ""
    error: str = ""


@dataclass
class Job:
    job_id: str
    spec: BuildSpec
    submitted: float = field(default_factory=time.time)
    state: JobState = JobState.QUEUED
    stage: str = ""
    fraction: float = 0.0
    message: str = ""
    started: float | None = None
    ended: float | None = None
    bundle_path: str = ""
    build_id: str = ""
    error: str = ""
    events: list[BuildEvent] = field(default_factory=list)
    process: Any = None
    conn: Any = None  # our end of the worker's progress pipe
    cancel_event: Any = None
    cancel_requested: bool = False
    cancel_time: float | None = None
    reaped: bool = True  # no worker process, or it has exited and been cleaned up
    workdir: str = ""

    @property
    def elapsed_s(self) -> float:
        if self.started is None:
            return 0.0
        return (self.ended or time.time()) - self.started

    def snapshot(self) -> BuildEvent:
        return BuildEvent(
            self.job_id,
            self.state,
            self.stage,
            self.fraction,
            self.message,
            self.elapsed_s,
            self.bundle_path,
            self.error,
        )


# ============================================================================ child process
def _child_main(spec_bytes: bytes, conn, cancel_event, workdir: str) -> None:
    """Entry point of a build worker process (spawned: a fresh interpreter)."""
    from ..threads import pin_threads_env

    pin_threads_env()  # before numpy loads

    def send(msg: Message) -> None:
        try:
            FROM_BUILD.send(conn, msg)
        except (BrokenPipeError, OSError):
            pass

    try:
        from ..builder.build import main, preset
        from ..builder.sfm import sfm_conf
        from ..config import merge_presets
        from ..errors import BuildCancelled
        from ..map.bundle import read_manifest

        spec = TO_BUILD.decode(spec_bytes)
        assert isinstance(spec, BuildSpec)
        conf = preset(spec.preset)
        if spec.config:
            conf = merge_presets(conf, **spec.config)
        sconf = sfm_conf("default", **({"matching": spec.matching} if spec.matching else {}))
        last: list[Any] = [0.0, ""]  # time and stage of the last event sent

        def progress(stage: str, fraction: float, message: str) -> None:
            now = time.monotonic()
            # Throttle to ~10 events/s per stage, but never drop a stage change or its end.
            if stage != last[1] or fraction >= 1.0 or now - last[0] > 0.1:
                last[0], last[1] = now, stage
                send(Progress(stage, float(fraction), str(message)))

        path = main(
            conf,
            spec.name,
            spec.out_dir,
            colmap=spec.colmap if spec.input_kind == "colmap" else None,
            images=spec.images,
            poses=spec.poses if spec.input_kind == "posed_images" else None,
            camera=spec.camera,
            sfm_conf=sconf,
            stride=spec.stride,
            workdir=workdir,
            progress=progress,
            should_cancel=cancel_event.is_set,
        )
        manifest = read_manifest(path)
        send(
            Done(
                str(path), manifest.build_id, [str(w) for w in manifest.report.get("warnings", [])]
            )
        )
    except BuildCancelled:
        send(Cancelled())
    except SfmlocError as exc:
        send(Failed(str(exc), getattr(exc, "stage", "") or ""))
    except Exception as exc:  # noqa: BLE001 - a bug in a build must reach the client, not vanish
        send(Failed(f"internal error: {type(exc).__name__}: {exc}", ""))
    finally:
        conn.close()


# ============================================================================ manager
class JobManager:
    """Queue of build jobs; at most ``max_concurrent`` worker processes at a time.

    ``on_success(job)`` is called (from a manager thread) when a bundle lands, e.g. to announce
    it on Zenoh. Watchers wait on ``wait_events``.
    """

    def __init__(
        self,
        default_out_dir: str | Path,
        work_root: str | Path | None = None,
        max_concurrent: int = 1,
        cancel_grace_s: float = 10.0,
        on_success: Callable[[Job], None] | None = None,
        history: int = 200,
    ) -> None:
        self.default_out_dir = Path(default_out_dir)
        # SfM work folders (COLMAP databases, ...) live outside the maps folder by default.
        self._own_work_root = work_root is None
        self.work_root = (
            Path(work_root) if work_root else Path(tempfile.mkdtemp(prefix="sfmloc-builder-"))
        )
        self.max_concurrent = max(1, max_concurrent)
        self.cancel_grace_s = cancel_grace_s
        self.on_success = on_success
        self.history = history
        self.jobs: dict[str, Job] = {}
        self._order: list[str] = []
        self._cond = threading.Condition()
        self._ctx = mp.get_context("spawn")  # never fork a process that runs gRPC threads
        self._closed = False
        self._thread = threading.Thread(target=self._loop, name="build-jobs", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ API
    def submit(self, spec: BuildSpec) -> Job:
        if not spec.out_dir:
            spec.out_dir = str(self.default_out_dir)
        spec.validate()
        with self._cond:
            if self._closed:
                raise SfmlocError("the builder is shutting down")
            job = Job(uuid.uuid4().hex[:12], spec)
            self.jobs[job.job_id] = job
            self._order.append(job.job_id)
            self._emit(job)
            self._trim()
            self._cond.notify_all()
        log.info("job %s queued: %s (%s)", job.job_id, spec.name, spec.input_kind)
        return job

    def get(self, job_id: str) -> Job:
        with self._cond:
            job = self.jobs.get(job_id)
        if job is None:
            raise KeyError(job_id)
        return job

    def list(self) -> list[Job]:
        with self._cond:
            return [self.jobs[j] for j in self._order]

    def cancel(self, job_id: str) -> bool:
        """Request cancellation; False when the job had already ended."""
        with self._cond:
            job = self.jobs.get(job_id)
            if job is None:
                raise KeyError(job_id)
            if job.state.final:
                return False
            job.cancel_requested = True
            if job.state is JobState.QUEUED:
                self._finish(job, JobState.CANCELLED, message="cancelled before it started")
            elif job.cancel_event is not None:
                job.cancel_event.set()
            self._cond.notify_all()
            return True

    # builtins.list: inside this class `list` is the method below
    def wait_events(
        self, job_id: str, start: int, timeout: float | None = None
    ) -> tuple[builtins.list[BuildEvent], bool]:
        """Events of a job from index ``start`` on (blocking until there is one, or timeout),
        and whether the job has ended."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            job = self.jobs.get(job_id)
            if job is None:
                raise KeyError(job_id)
            while len(job.events) <= start and not job.state.final:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    break
                self._cond.wait(remaining)
            return list(job.events[start:]), job.state.final

    def close(self, cancel_running: bool = True, timeout: float = 30.0) -> None:
        """Stop taking jobs; cancel (or wait for) running ones."""
        with self._cond:
            self._closed = True
            for job in self.jobs.values():
                if job.state is JobState.QUEUED:
                    self._finish(job, JobState.CANCELLED, message="builder shut down")
                elif (
                    job.state is JobState.RUNNING
                    and cancel_running
                    and job.cancel_event is not None
                ):
                    job.cancel_requested = True
                    job.cancel_event.set()
            self._cond.notify_all()
        self._thread.join(timeout)
        if self._own_work_root:
            shutil.rmtree(self.work_root, ignore_errors=True)

    # ------------------------------------------------------------------ internals
    def _emit(self, job: Job) -> None:
        job.events.append(job.snapshot())

    def _finish(self, job: Job, state: JobState, message: str = "", error: str = "") -> None:
        job.state = state
        job.ended = time.time()
        if message:
            job.message = message
        if error:
            job.error = error
        self._emit(job)

    def _trim(self) -> None:
        while len(self._order) > self.history:
            old = self.jobs[self._order[0]]
            if not old.state.final:
                break
            del self.jobs[self._order.pop(0)]

    def _start(self, job: Job) -> None:
        parent, child = self._ctx.Pipe(duplex=False)
        job.cancel_event = self._ctx.Event()
        job.workdir = str(self.work_root / f"job-{job.job_id}")
        Path(job.workdir).mkdir(parents=True, exist_ok=True)
        spec_bytes = TO_BUILD.encode(job.spec)
        proc = self._ctx.Process(
            target=_child_main,
            args=(spec_bytes, child, job.cancel_event, job.workdir),
            name=f"build-{job.job_id}",
            daemon=True,
        )
        proc.start()
        child.close()
        job.process = proc
        job.conn = parent
        job.reaped = False
        job.state = JobState.RUNNING
        job.started = time.time()
        job.stage, job.message = "start", f"worker pid {proc.pid}"
        self._emit(job)
        log.info("job %s started in pid %d", job.job_id, proc.pid)

    def _loop(self) -> None:
        while True:
            with self._cond:
                # A worker counts until its process has exited and been reaped, even after it
                # reported a final state.
                running = [j for j in self.jobs.values() if not j.reaped]
                if self._closed and not running:
                    return
                queued = [
                    self.jobs[i] for i in self._order if self.jobs[i].state is JobState.QUEUED
                ]
                while not self._closed and queued and len(running) < self.max_concurrent:
                    job = queued.pop(0)
                    self._start(job)
                    running.append(job)
            if not running:
                with self._cond:
                    self._cond.wait(0.5)
                continue
            conns = [j.conn for j in running]
            ready = multiprocessing.connection.wait(
                conns + [j.process.sentinel for j in running], timeout=0.2
            )
            for job in running:
                if job.conn in ready:
                    self._drain(job)
                if job.process.sentinel in ready or not job.process.is_alive():
                    self._drain(job)
                    self._reap(job)
                elif job.cancel_requested and job.cancel_event.is_set():
                    self._maybe_terminate(job)

    def _drain(self, job: Job) -> None:
        while True:
            try:
                if not job.conn.poll():
                    return
                msg = FROM_BUILD.recv(job.conn)
            except (EOFError, OSError):
                return
            except ProtocolError:
                log.exception("job %s: malformed message from its build process", job.job_id)
                continue
            with self._cond:
                if isinstance(msg, Progress):
                    job.stage, job.fraction, job.message = msg.stage, msg.fraction, msg.message
                    self._emit(job)
                elif isinstance(msg, Done):
                    job.bundle_path, job.build_id = msg.path, msg.build_id
                    job.stage, job.fraction = "done", 1.0
                    warn = "".join(f"; WARNING: {w}" for w in msg.warnings)
                    self._finish(
                        job,
                        JobState.SUCCEEDED,
                        message=f"bundle written to {job.bundle_path}{warn}",
                    )
                elif isinstance(msg, Cancelled):
                    self._finish(job, JobState.CANCELLED, message="cancelled")
                elif isinstance(msg, Failed):
                    job.stage = msg.stage or job.stage
                    self._finish(job, JobState.FAILED, error=msg.error)
                self._cond.notify_all()
            if isinstance(msg, Done) and self.on_success is not None:
                try:
                    self.on_success(job)
                except Exception:  # noqa: BLE001 - announcing must not break the build record
                    log.exception("announcing bundle of job %s failed", job.job_id)

    def _maybe_terminate(self, job: Job) -> None:
        if job.cancel_time is None:
            job.cancel_time = time.monotonic()
        elif time.monotonic() - job.cancel_time > self.cancel_grace_s and job.process.is_alive():
            log.warning(
                "job %s did not stop within %.0f s of cancel: terminating pid %d",
                job.job_id,
                self.cancel_grace_s,
                job.process.pid,
            )
            job.process.terminate()

    def _reap(self, job: Job) -> None:
        job.process.join(5)
        code = job.process.exitcode
        with self._cond:
            if not job.state.final:
                if job.cancel_requested:
                    self._finish(job, JobState.CANCELLED, message="cancelled (worker terminated)")
                else:
                    self._finish(
                        job, JobState.FAILED, error=f"build worker process died (exit code {code})"
                    )
            self._cond.notify_all()
        try:
            job.conn.close()
        except OSError:
            pass
        self._cleanup(job)
        job.reaped = True

    def _cleanup(self, job: Job) -> None:
        """Remove the job's work folder and any bundle temp folder its process left."""
        if job.workdir:
            shutil.rmtree(job.workdir, ignore_errors=True)
        pid = job.process.pid if job.process is not None else None
        if pid is not None and job.state is not JobState.SUCCEEDED:
            out = Path(job.spec.out_dir)
            for leftover in out.glob(f".{job.spec.name}.tmp-{pid}-*"):
                shutil.rmtree(leftover, ignore_errors=True)
