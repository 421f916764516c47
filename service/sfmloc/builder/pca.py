"""PCA of raw descriptors for the builder, in bounded memory.

``Pca.fit`` (features/daisy.py) converts its whole input to float64 and ``np.cov`` makes two
more float64 copies: 2.5 KB per 104-d sample, 500 MB for its 200,000 samples. ``fit_pca``
gives the same projection (the same mean and covariance up to float64 summation order, the
same component order and sign rule) from a float32 sample, accumulating the mean and the
scatter matrix ``chunk_rows`` rows at a time (7 MB of float64 per chunk).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..features.daisy import Pca
from .desc_store import RawStore


def fit_pca(sample: np.ndarray, dim: int = 32, chunk_rows: int = 8192) -> Pca:
    """PCA to ``dim`` dimensions of ``sample`` (N, D), any float dtype; raises ValueError when
    N <= dim (as ``Pca.fit``)."""
    n, d = sample.shape
    if n < dim + 1:
        raise ValueError(f"PCA to {dim} dimensions needs more than {dim} descriptors, got {n}")
    step = max(1, chunk_rows)
    total = np.zeros(d, np.float64)
    for s in range(0, n, step):
        total += sample[s : s + step].sum(axis=0, dtype=np.float64)
    mean = total / n
    scatter = np.zeros((d, d), np.float64)
    for s in range(0, n, step):
        x = sample[s : s + step].astype(np.float64)
        x -= mean
        scatter += x.T @ x
    cov = scatter / (n - 1)
    evals, evecs = np.linalg.eigh(cov)
    order = np.argsort(evals)[::-1][:dim]
    basis = evecs[:, order]
    # Deterministic sign: largest-magnitude entry of each component positive (as Pca.fit).
    signs = np.sign(basis[np.argmax(np.abs(basis), axis=0), np.arange(dim)])
    return Pca(mean.astype(np.float32), (basis * signs).astype(np.float32))


def project_store(
    store: RawStore,
    dim: int = 32,
    samples: int = 200_000,
    seed: int = 0,
    progress: Callable[[str, float, str], None] | None = None,
) -> tuple[np.ndarray, Pca]:
    """PCA fitted on ``samples`` random rows of ``store`` (``Pca.fit``'s rows: drawn before
    any float64 copy), then every row projected, chunk by chunk: (N, dim) float16 and the PCA."""
    n = len(store)
    rows = np.arange(n)
    if n > samples:
        rows = np.random.default_rng(seed).choice(n, samples, replace=False)
    pca = fit_pca(store.take(rows), dim=dim)
    del rows
    desc = np.empty((n, dim), np.float16)
    for start, chunk in store.chunks():
        desc[start : start + len(chunk)] = pca.project(chunk)
        if progress:
            progress("pca", (start + len(chunk)) / n, f"projected {start + len(chunk)} descriptors")
    return desc, pca
