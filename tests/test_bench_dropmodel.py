"""``sfmloc.bench.dropmodel``: the simulated throughput run against the real session manager
(a model, seeded: the same draws every time; nothing is timed)."""

from __future__ import annotations

import numpy as np

from sfmloc.bench.dropmodel import simulate

COSTS = np.array([5.0, 6.0, 7.0])  # engine CPU per tracked frame (ms), drawn per frame


def test_two_clients_on_two_workers_lose_nothing():
    r = simulate(COSTS, clients=2, frames=120, wrap=False, seed=0)
    assert r["dropped_pct"] == 0.0 and r["dropped_pct_worst_client"] == 0.0
    # one session per worker: each frame waits for nothing but its own work (the dearest
    # draw and the decoding at 0.88 of a core) and the transport
    assert r["latency_ms_p99"] <= (7.0 + 0.85) / 0.88 + 1.5 + 1e-9


def test_a_relocalization_on_a_full_worker_costs_frames_and_stepping_moves_them():
    full = {"clients": 8, "frames": 300, "seed": 1}
    base = simulate(COSTS, wrap=False, **full)
    wrap = simulate(COSTS, wrap=True, **full)
    assert wrap["dropped_pct"] > base["dropped_pct"]
    # stepped, the others' frames go first: never worse for them, the total about the same
    stepped = simulate(COSTS, wrap=True, step_ms=10.0, **full)
    assert stepped["dropped_pct"] > base["dropped_pct"]
    assert abs(stepped["dropped_pct"] - wrap["dropped_pct"]) < 0.5 * wrap["dropped_pct"]
