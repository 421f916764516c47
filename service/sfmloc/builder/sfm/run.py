"""Running a pycolmap stage: progress, cancellation (``Reporter``), pycolmap's log level and
the work directory."""

from __future__ import annotations

import contextlib
import logging
import shutil
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pycolmap

from ...errors import BuildCancelled, BuildError

log = logging.getLogger(__name__)

Progress = Callable[[str, float, str], None]
CancelCheck = Callable[[], bool]


class Reporter:
    """Progress and cancellation for one run: ``report(stage, fraction, message)``,
    ``check(stage)``."""

    def __init__(self, progress: Progress | None, should_cancel: CancelCheck | None) -> None:
        self.progress = progress
        self.should_cancel = should_cancel

    def report(self, stage: str, fraction: float, message: str = "") -> None:
        if message:
            log.debug("[%s] %.0f%% %s", stage, 100 * fraction, message)
        if self.progress is not None:
            self.progress(stage, float(min(1.0, max(0.0, fraction))), message)

    def check(self, stage: str) -> None:
        if self.should_cancel is not None and self.should_cancel():
            raise BuildCancelled("cancelled", stage=stage)

    def run(self, stage: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """Call a pycolmap function that takes ``cancellation_token``; cancel it when asked.

        pycolmap releases the GIL, so the call runs in a worker thread while this one polls
        ``should_cancel``. Its failures become ``BuildError`` naming the stage.
        """
        self.check(stage)
        token = pycolmap.CancellationToken()
        out: dict[str, Any] = {}

        def target() -> None:
            try:
                out["value"] = fn(*args, cancellation_token=token, **kwargs)
            except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
                out["error"] = exc

        if self.should_cancel is None:
            target()
        else:
            th = threading.Thread(target=target, name=f"pycolmap-{stage}", daemon=True)
            th.start()
            try:
                while th.is_alive():
                    th.join(0.05)
                    if th.is_alive() and self.should_cancel():
                        raise BuildCancelled("cancelled", stage=stage)
            except BaseException:
                # Cancelled, Ctrl-C or a failing check: stop pycolmap before the work
                # directory it writes to is removed.
                token.cancel()
                th.join()
                raise
        exc = out.get("error")
        if exc is not None:
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise exc
            if isinstance(exc, InterruptedError) or token_cancelled(token):
                raise BuildCancelled("cancelled", stage=stage) from None
            name = getattr(fn, "__name__", "pycolmap")
            raise BuildError(f"pycolmap {name} failed: {exc}", stage=stage) from exc
        return out.get("value")


def token_cancelled(token: Any) -> bool:
    """Whether a pycolmap ``CancellationToken`` was cancelled: a method in some pycolmap
    releases, a property in others (4.2: calling it raised ``TypeError: 'bool' object is not
    callable`` and hid the stage's real error)."""
    flag = token.is_cancelled
    return bool(flag() if callable(flag) else flag)


@contextlib.contextmanager
def quiet_colmap() -> Iterator[None]:
    """Keep pycolmap's INFO log lines off stderr unless our logger is at DEBUG."""
    if log.isEnabledFor(logging.DEBUG):
        yield
        return
    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(before, 1)  # 0 INFO, 1 WARNING, 2 ERROR
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


@contextlib.contextmanager
def work_directory(parent: str | Path | None, keep: bool) -> Iterator[Path]:
    """A fresh directory (inside ``parent`` when given) for the database and intermediate
    files, removed afterwards, on success and failure, unless ``keep``."""
    if parent is not None:
        Path(parent).mkdir(parents=True, exist_ok=True)
    path = Path(tempfile.mkdtemp(prefix="sfmloc-sfm-", dir=None if parent is None else str(parent)))
    try:
        yield path
    finally:
        if keep:
            log.info("kept SfM work directory %s", path)
        else:
            shutil.rmtree(path, ignore_errors=True)
