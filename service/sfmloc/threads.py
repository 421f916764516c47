"""One thread for OpenCV, BLAS and OpenMP (faiss), as the engine is measured and deployed, so a
frame's latency does not depend on what else the machine runs. The one helper for every process
that runs the engine or builds maps (commands, server workers, build jobs, benchmarks).

The environment variables take effect only if set before numpy (BLAS) loads: call
``pin_threads_env`` first thing, ``pin_threads_runtime`` once OpenCV and faiss may be imported.
"""

from __future__ import annotations

import os

THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def single_thread_env(base: dict[str, str] | None = None) -> dict[str, str]:
    """A copy of ``base`` (default: this process's environment) for a child process that must
    run single-threaded."""
    return {**(os.environ if base is None else base), **{var: "1" for var in THREAD_VARS}}


def pin_threads_env(force: bool = False) -> None:
    """Single-thread BLAS/OpenMP defaults in this process's environment (the user's explicit
    values win unless ``force``: measurements that must run like a server worker)."""
    for var in THREAD_VARS:
        if force:
            os.environ[var] = "1"
        else:
            os.environ.setdefault(var, "1")


def pin_threads_runtime() -> None:
    """Single-thread OpenCV and faiss (imports them)."""
    import cv2

    cv2.setNumThreads(1)
    try:
        import faiss

        faiss.omp_set_num_threads(1)
    except ImportError:  # pragma: no cover - faiss is a dependency
        pass


def pin_threads(force: bool = False) -> None:
    """Both: the environment, then OpenCV and faiss."""
    pin_threads_env(force)
    pin_threads_runtime()
