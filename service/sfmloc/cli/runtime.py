"""Process-wide runtime settings for commands that run the engine: one thread for OpenCV,
BLAS and OpenMP (faiss), as the engine is measured and deployed, so a frame's latency does not
depend on what else the machine runs. Environment variables must be set before numpy loads."""

from __future__ import annotations

import os

THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def pin_threads_env() -> None:
    """Set single-thread BLAS/OpenMP defaults (the user's explicit values win)."""
    for var in THREAD_VARS:
        os.environ.setdefault(var, "1")


def pin_threads_runtime() -> None:
    """Single-thread OpenCV and faiss, once they are imported."""
    import cv2

    cv2.setNumThreads(1)
    try:
        import faiss

        faiss.omp_set_num_threads(1)
    except ImportError:  # pragma: no cover - faiss is a dependency
        pass
