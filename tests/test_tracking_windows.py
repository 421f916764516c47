"""TRACK-2D's window lookup (``tracker.window_pairs``) against brute force: every candidate in
the square window of each prediction, grouped by prediction, on cell borders too, and
predictions far off the image or not finite look at no candidate (and cost no memory)."""

from __future__ import annotations

import numpy as np
import pytest

from sfmloc.engine.tracker import window_pairs


def _brute(pred, cand, half):
    d = np.abs(pred[:, None, :] - cand[None, :, :])
    i, j = np.nonzero((d[..., 0] <= half) & (d[..., 1] <= half))
    return sorted(zip(i.tolist(), j.tolist()))


@pytest.mark.parametrize("half", [24.0, 6.0, 3.5])
def test_window_pairs_are_exactly_the_candidates_in_each_window(half):
    rng = np.random.default_rng(int(half * 10))
    for _ in range(200):
        n, m = rng.integers(1, 60), rng.integers(1, 120)
        cand = rng.uniform(0, 320, (m, 2))
        cand[: m // 4] = np.round(cand[: m // 4] / half) * half  # on cell borders
        pred = rng.uniform(-60, 380, (n, 2))
        pred[: n // 4] = cand[rng.integers(0, m, n // 4)] + half  # candidates on window edges
        ti, cj = window_pairs(pred, cand, half)
        assert sorted(zip(ti.tolist(), cj.tolist())) == _brute(pred, cand, half)
        assert np.all(np.diff(ti) >= 0)  # grouped by prediction


def test_predictions_off_the_image_or_not_finite_find_nothing():
    cand = np.array([[12.0, 12.0], [100.0, 100.0]])
    pred = np.array([[1e12, 5.0], [np.nan, 3.0], [-1e15, np.inf], [10.0, 10.0]])
    ti, cj = window_pairs(pred, cand, 24.0)
    assert ti.tolist() == [3] and cj.tolist() == [0]
    assert [len(a) for a in window_pairs(pred[:0], cand, 24.0)] == [0, 0]
