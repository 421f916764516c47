"""The bench's data and maps, prepared in a child process: the process that then times our
engine never builds a map, as a server worker never does.

Why: a process that has built a map in-process (``builder.build``: pycolmap, SIFT, the
triangulation's and the bundle's big arrays) replays the same frames slower than a fresh one,
with the same poses, and so would the published numbers: its glibc heap is left at ~170 MB
with ~110 MB free in some 2,400 scattered chunks (a fresh engine process: ~45 MB, ~350 chunks),
and every one of the engine's per-frame allocations then walks malloc's bins of free chunks
(``_int_malloc``). The lead's quiet runs read 6.7 -> 7.8 ms a frame after a build in the same
process; the bench's own redkitchen mean read 7.07 / 8.31 / 8.06 ms in reps 1-3 after a
rebuild against 6.1 with the maps reused (docs/development.md#bench-isolation).

Interface: the child gets the ``BenchConf`` as a JSON file and the suites' names, builds (and
stamps) what the ``--reuse`` cache lacks, exactly as ``suites.prepare`` does in-process, and
exits; the parent then ``prepare``s the same suites with ``reuse`` on, which only reads the
stamped files. Nothing crosses but files (no pickle).

``python -m sfmloc.bench.prepare CONF_JSON WORK LOG_LEVEL SUITE...`` (SUITE: a localization
suite's name; ``redkitchen`` is also the map and throughput suites' map; ``robust``: every
selected robust row's maps and frames, ``robust.prepare_robust``, after the localization suites
named before it, whose data it reuses).
"""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from pathlib import Path

from ..errors import InputError, SfmlocError
from .config import BenchConf

# By name: run as ``-m`` the module is ``__main__``; the child's log lines name this module.
log = logging.getLogger("sfmloc.bench.prepare")

CONF_FILE = "prepare-conf.json"
# The child's user-facing error (``InputError``: e.g. no real data), raised again by the parent.
ERROR_FILE = "prepare-error.txt"
INPUT_ERROR_EXIT = 2


class PrepareError(SfmlocError):
    """The child that prepares the bench's maps failed (its log is above, on stderr)."""


def prepare_in_child(names: list[str], conf: BenchConf, work: Path) -> float:
    """Build what ``names`` need under ``work`` in a child process (``--reuse`` semantics of
    ``conf``); the child's wall time in seconds. Raises ``PrepareError`` if it fails."""
    if not names:
        return 0.0
    work.mkdir(parents=True, exist_ok=True)
    conf_path = work / CONF_FILE
    conf_path.write_text(conf.model_dump_json(indent=1))
    error_path = work / ERROR_FILE
    error_path.unlink(missing_ok=True)
    t0 = time.perf_counter()
    log.info("preparing %s in a child process", ", ".join(names))
    # stdout and stderr are the parent's: the child's log lines appear as the build goes.
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "sfmloc.bench.prepare",
            str(conf_path),
            str(work),
            str(logging.getLogger().getEffectiveLevel()),
            *names,
        ],
        check=False,
    )
    if proc.returncode == INPUT_ERROR_EXIT and error_path.is_file():
        raise InputError(error_path.read_text())
    if proc.returncode != 0:
        raise PrepareError(
            f"preparing {', '.join(names)} failed in the child process (exit {proc.returncode})"
        )
    return time.perf_counter() - t0


def _child(argv: list[str]) -> int:
    from ..threads import pin_threads_env, pin_threads_runtime

    # As the bench's own process: builds are reproducible on one thread per call.
    pin_threads_env()
    pin_threads_runtime()
    from ..cli.main import configure_logging
    from .main import LogProgress
    from .suites import Prepared, prepare

    level = int(argv[2])  # the parent's: -v / -q carry over
    configure_logging(2 if level <= logging.DEBUG else 0, level >= logging.WARNING)
    conf = BenchConf.model_validate_json(Path(argv[0]).read_text())
    work = Path(argv[1])
    progress = LogProgress()
    preps: dict[str, Prepared] = {}  # the suites' data, which the robust rows reuse
    try:
        for name in argv[3:]:
            log.info("== %s: preparing data and maps (child process)", name)
            if name == "robust":
                from .robust import prepare_robust

                prepare_robust(conf, work, progress, preps)
            else:
                preps[name] = prepare(name, conf, work, progress)
    except InputError as exc:
        (work / ERROR_FILE).write_text(str(exc))
        return INPUT_ERROR_EXIT
    return 0


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1:]))
