"""One thread for OpenCV, BLAS and OpenMP (faiss), as the engine is measured and deployed, so a
frame's latency does not depend on what else the machine runs. The one helper for every process
that runs the engine or builds maps (commands, server workers, build jobs, benchmarks).

The environment variables take effect only if set before numpy (BLAS) loads: call
``pin_threads_env`` first thing, ``pin_threads_runtime`` once OpenCV and faiss may be imported.
"""

from __future__ import annotations

import ctypes
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


# glibc's mallopt parameters (malloc.h) and the heap a process keeps (``pin_allocator``).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 16 << 20
TRIM_THRESHOLD_BYTES = 16 << 20


def pin_allocator() -> bool:
    """glibc malloc at fixed thresholds: blocks under 16 MB come from the heap (not their own
    mmap) and up to 16 MB of free heap top are kept (not returned to the kernel), so a
    frame's temporaries (DAISY patches and gradients, distance matrices: a few MB, 12.8 MB for
    DAISY's channels of 1,000 keypoints) reuse memory instead of faulting fresh zeroed pages
    in. glibc's adaptive rule maps any block at least as large as the largest freed so far
    afresh (up to 32 MB) and trims past twice that, so the page faults depended on the sizes
    a process had met: engine.relocalize on redkitchen frames faulted 40-270 pages per call
    (p95 160-1900) in fresh processes, 6-7 with this (issue 10). 16 MB rather than the
    adaptive rule's 32 / 64 MB maxima: the same faults, and a worker's memory after its
    frames (``bench.mapstats``, redkitchen, 5 frames) 62.4 MB over the bundle against 63.7
    by default (32 / 64 MB: 70.4). Returns whether the thresholds were set (False where the
    C library has no mallopt, e.g. macOS, or musl's stub)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )


def pin_threads_runtime() -> None:
    """Single-thread OpenCV and faiss (imports them); the allocator's thresholds fixed as
    well (``pin_allocator``: every process that runs the engine calls this)."""
    pin_allocator()
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
