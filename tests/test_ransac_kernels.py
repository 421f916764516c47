"""The one-to-many RANSAC's bookkeeping against the code it replaces: the pool stop's log miss
probability summed incrementally (only the batches added since the last check) equals, bit for
bit, the sum over every batch recomputed at each check."""

from __future__ import annotations

import math

import numpy as np

from sfmloc.engine import pose


def reference_pool_miss_log(pools, in_best) -> float:
    """The sum over every pool, recomputed (before: quadratic in the batches)."""
    out = 0.0
    for pool, n in pools:
        w = float(in_best[pool - 1]) / pool
        if w >= 1.0:
            return -math.inf
        out += n * math.log(1.0 - w**3)
    return out


def test_incremental_pool_miss_log_equals_the_full_sum():
    rng = np.random.default_rng(0)
    checked = infinite = 0
    for trial in range(300):
        n1 = int(rng.integers(3, 700))
        pools: list[tuple[int, int]] = []
        out, done = 0.0, 0
        in_best = np.cumsum(rng.random(n1) < rng.uniform(0.05, 1.0))
        for it in range(0, 1000, 16):
            if rng.random() < 0.1:  # a new best pose: the sum starts again
                in_best = np.cumsum(rng.random(n1) < rng.uniform(0.05, 1.0))
                out, done = 0.0, 0
            if pools:
                out, done = pose._pool_miss_log(pools, in_best, out, done)
                want = reference_pool_miss_log(pools, in_best)
                assert out == want, (trial, it, out, want)  # bit for bit, -inf included
                assert done == len(pools)
                checked += 1
                infinite += out == -math.inf
            pools.append((min(n1, max(8, n1 // 5) + (n1 * it) // 200), 16))
    assert checked > 10000 and infinite > 100  # both branches taken
    # the whole sum at once, as before
    assert pose._pool_miss_log(pools, in_best) == (
        reference_pool_miss_log(pools, in_best),
        len(pools),
    )
