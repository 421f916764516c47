"""TRACK-2D's window lookup (``tracker.window_pairs``) against brute force: every candidate in
the square window of each prediction, grouped by prediction, on cell borders too, and
predictions far off the image or not finite look at no candidate (and cost no memory)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sfmloc.engine.config import EngineConf
from sfmloc.engine.track_table import TrackTable
from sfmloc.engine.tracker import (
    Keypoints,
    extract_keypoints,
    pair_distances,
    track_2d,
    window_pairs,
    window_size,
)
from sfmloc.features.brief import hamming


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


def _plain_track_2d(brief_t, pred, brief_k, xy, conf):
    """TRACK-2D written per track: the best candidate in the window if it passes the distance
    cap and the ratio test (a tie for the best does not), then each candidate to its closest
    claiming track (the lower row on a tie)."""
    claims = {}
    for i in range(len(pred)):
        d = np.abs(xy - pred[i])
        js = np.nonzero((d[:, 0] <= conf.rho / 2) & (d[:, 1] <= conf.rho / 2))[0]
        if len(js) == 0:
            continue
        dist = np.array([hamming(brief_t[i], brief_k[j]) for j in js])
        o = np.argsort(dist, kind="stable")
        best = dist[o[0]]
        if best > conf.max_hamming or (len(js) > 1 and not best < conf.psi * dist[o[1]]):
            continue
        j = int(js[o[0]])
        if j not in claims or best < claims[j][1]:
            claims[j] = (i, best)
    match = np.full(len(pred), -1, np.int64)
    for j, (i, _) in claims.items():
        match[i] = j
    return match


def _table(brief):
    table = TrackTable.empty(1)
    table.brief = brief
    table.track_id = np.arange(len(brief), dtype=np.int64)
    return table


def test_track_2d_equals_the_per_track_rule_with_ties_and_shared_candidates():
    conf = EngineConf()
    rng = np.random.default_rng(7)
    for trial in range(60):
        m, n = int(rng.integers(1, 300)), int(rng.integers(1, 200))
        xy = rng.uniform(0, 200, (m, 2))
        # few distinct descriptors and bits: equal distances, ties for the best and candidates
        # claimed by several tracks are common
        words = rng.integers(0, 2**63, (5, 4), dtype=np.uint64)
        flips = rng.integers(0, 2**63, (m, 4), dtype=np.uint64) & rng.integers(
            0, 2**63, (m, 4), dtype=np.uint64
        )
        brief_k = words[rng.integers(0, 5, m)] ^ (flips if trial % 2 else 0)
        brief_t = words[rng.integers(0, 5, n)]
        pred = xy[rng.integers(0, m, n)] + rng.normal(0, 10, (n, 2))
        pred[: n // 10] = np.nan
        kps = Keypoints(xy, np.ones(m), brief_k, 1.0)
        got = track_2d(_table(brief_t), pred, kps, conf)
        np.testing.assert_array_equal(got, _plain_track_2d(brief_t, pred, brief_k, xy, conf))
        assert (got >= 0).any() or trial % 2  # not vacuous on the tie-heavy trials


def test_the_window_widens_with_the_frame_interval():
    """rho up to wide_window_gap_s, then in proportion to the interval, at most
    wide_window_max times rho; track_2d at an interval is the plain search with that window."""
    conf = EngineConf()
    gap, rho = conf.wide_window_gap_s, conf.rho
    assert window_size(conf, 0.0) == window_size(conf, 1 / 30) == window_size(conf, gap) == rho
    assert window_size(conf, 2 * gap) == pytest.approx(2 * rho)
    assert window_size(conf, 100.0) == pytest.approx(conf.wide_window_max * rho)
    assert window_size(EngineConf(wide_window_gap_s=0), 100.0) == rho
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 640, (400, 2))
    brief_k = rng.integers(0, 2**63, (400, 4), dtype=np.uint64)
    pick = rng.integers(0, 400, 150)
    brief_t = brief_k[pick] ^ (rng.integers(0, 2**63, (150, 4), dtype=np.uint64) & 7)
    pred = xy[pick] + rng.uniform(-60, 60, (150, 2))  # up to 60 px off: past rho / 2
    kps = Keypoints(xy, np.ones(400), brief_k, 1.0)
    wide = conf.model_copy(update={"rho": window_size(conf, 3 * gap)})
    got = track_2d(_table(brief_t), pred, kps, conf, dt=3 * gap)
    np.testing.assert_array_equal(got, _plain_track_2d(brief_t, pred, brief_k, xy, wide))
    narrow = track_2d(_table(brief_t), pred, kps, conf)
    assert (got >= 0).sum() > (narrow >= 0).sum()


def test_pair_distances_equal_hamming_up_to_all_256_bits():
    rng = np.random.default_rng(3)
    a = rng.integers(0, 2**64, (50, 4), dtype=np.uint64, endpoint=False)
    a[0] = np.uint64(2**64 - 1)
    b = np.concatenate([~a[:1], a[:1], rng.integers(0, 2**63, (40, 4), dtype=np.uint64)])
    i, j = (g.ravel() for g in np.meshgrid(np.arange(50), np.arange(len(b)), indexing="ij"))
    d = pair_distances(a, i, b, j)
    np.testing.assert_array_equal(d, hamming(a[i], b[j]))
    assert d.max() == 256 and d.min() == 0


def test_track_2d_and_window_pairs_on_consecutive_redkitchen_frames(redkitchen):
    conf = EngineConf()
    rng = np.random.default_rng(11)
    threshold = None
    prev = None
    matched = 0
    for i in range(0, 40, 4):
        gray = cv2.imread(str(redkitchen / f"frame-{i:06d}.color.jpg"), cv2.IMREAD_GRAYSCALE)
        kps = extract_keypoints(gray, threshold, conf)
        threshold = conf.gamma * kps.max_response
        if prev is not None:
            pred = prev.xy + rng.normal(0, 3, prev.xy.shape)
            ti, cj = window_pairs(pred, kps.xy, conf.rho / 2)
            assert sorted(zip(ti.tolist(), cj.tolist())) == _brute(pred, kps.xy, conf.rho / 2)
            got = track_2d(_table(prev.brief), pred, kps, conf)
            want = _plain_track_2d(prev.brief, pred, kps.brief, kps.xy, conf)
            np.testing.assert_array_equal(got, want)
            matched += int((got >= 0).sum())
        prev = kps
    assert matched > 1000


@pytest.mark.parametrize("half", [24.0, 6.0, 1.5])
def test_window_pairs_on_cell_borders_and_wide_extents(half):
    """The cell table's columns (half / 2 wide, wider past its size bound, int64 cells past
    int16's range) and its padding: candidates on column borders and window edges, negative
    coordinates, one column of candidates, extents from a few cells to 100k px."""
    rng = np.random.default_rng(int(half * 100) + 1)
    for extent in (3.0 * half, 640.0, 5000.0, 1e5):
        for trial in range(40):
            m, n = int(rng.integers(1, 200)), int(rng.integers(1, 80))
            cand = rng.uniform(-extent / 3, extent, (m, 2))
            cand[: m // 3] = np.round(cand[: m // 3] / (half / 2)) * (half / 2)  # on borders
            if trial % 5 == 0:
                cand[:, 0] = cand[0, 0]  # one column
            pred = rng.uniform(-extent / 2, 1.2 * extent, (n, 2))
            near = cand[rng.integers(0, m, n // 2)]
            pred[: n // 2] = near + rng.choice([-half, 0.0, half, half / 2], (n // 2, 2))
            ti, cj = window_pairs(pred, cand, half)
            assert sorted(zip(ti.tolist(), cj.tolist())) == _brute(pred, cand, half)
            assert np.all(np.diff(ti) >= 0)  # grouped by prediction


def test_window_pairs_of_degenerate_windows_and_candidates():
    """Windows of no size (exactly equal positions), negative, not finite or far below a
    pixel, and candidates not finite: the pairs the plain test gives (no grid)."""
    rng = np.random.default_rng(2)
    cand = np.round(rng.uniform(0, 40, (60, 2)))
    pred = np.concatenate([cand[:20], np.round(rng.uniform(0, 40, (20, 2)))])
    for half in (0.0, -1.0, np.inf, np.nan, 1e-300, 1e-3):
        with np.errstate(all="ignore"):
            ti, cj = window_pairs(pred, cand, half)
            want = _brute(pred, cand, half)
        assert sorted(zip(ti.tolist(), cj.tolist())) == want
        assert np.all(np.diff(ti) >= 0)
    assert len(window_pairs(pred, cand, 0.0)[0]) >= 20  # equal positions pair at 0
    bad = cand.copy()
    bad[::7] = np.nan
    bad[1] = np.inf
    with np.errstate(all="ignore"):
        ti, cj = window_pairs(pred, bad, 3.0)
        assert sorted(zip(ti.tolist(), cj.tolist())) == _brute(pred, bad, 3.0)
