"""A model of the throughput suite's 8 clients on 2 workers (issue 10's drops), played on a
simulated clock against the real ``SessionManager`` (turns, worker queue, latest-frame-only)::

    python -m sfmloc.bench.dropmodel RUN [--seeds 6] [--mean-ms 6.1]

``RUN`` is a ``python -m sfmloc.bench.droptimeline`` recording: its poses' engine CPU (global
matching left out) is the distribution each simulated frame's cost is drawn from, scaled to
``--mean-ms`` (the quiet bench's engine CPU per pose), plus ``--extra-ms`` of decoding per
frame; each worker runs at ``--speed`` of a core (what the server process and the clients leave
of two). A client's frame at the suite's wrap (frame 309 -> 0: the camera jumps) relocalizes for
``--reloc-ms``. Variants: clients' send phases aligned (the suite's warm-up barrier) or spread,
the wrap's relocalization or none, a relocalization stepped in pieces with every other waiting
frame of its worker going first (the bound for a relocalization that never delays another
session's frame, as on a worker of its own), ``max_pending`` 2. Per variant: frames dropped
(all, worst client), latency p50 (median over clients) and p99 (worst client), with a fixed
1.5 ms of transport on top. A model, not a measurement: the scheduling is the server's, the
costs are drawn, and nothing else competes for the cores.
"""

from __future__ import annotations

import argparse
import functools
import heapq
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

WRAP_FRAMES = 310  # the suite loads rate x duration + 10 frames and loops over them


@dataclass
class _Pool:
    """What the session manager uses of ``WorkerPool``: frames handed over are recorded."""

    n: int = 2
    frames: list[tuple[int, Any]] = field(default_factory=list)

    def is_alive(self, worker: int) -> bool:
        return 0 <= worker < self.n

    def started(self, worker: int, ticket: int) -> bool:
        return False

    def inflight(self) -> list[int]:
        return [0] * self.n

    def submit_frame(self, worker: int, msg: Any) -> None:
        self.frames.append((worker, msg))

    def close_session(self, worker: int, sid: int) -> None:
        pass

    def reset_session(self, worker: int, sid: int) -> None:
        pass


class _Registry:
    def __init__(self) -> None:
        from ..server.maps import MapEntry

        self.entry = MapEntry("m", "/maps/m", "build", 1, 1, 1, 1, 1, 1.0, "")

    def find(self, name: str) -> Any:
        return self.entry

    def get(self, name: str) -> Any:
        return self.entry


def simulate(
    costs_ms: np.ndarray,
    *,
    clients: int = 8,
    rate_hz: float = 30.0,
    frames: int = 300,
    spread: bool = False,
    wrap: bool = True,
    step_ms: float = 0.0,
    max_pending: int = 1,
    reloc_ms: float = 95.0,
    extra_ms: float = 0.85,
    speed: float = 0.88,
    seed: int = 0,
) -> dict[str, float]:
    """One simulated run; ``costs_ms``: engine CPU per tracked frame to draw from (already
    scaled)."""
    from sfmloc_client.wire import CameraSpec, Frame, Transform

    from ..server import protocol as P
    from ..server.metrics import ServerMetrics
    from ..server.sessions import SessionManager

    rng = np.random.default_rng(seed)
    cam = CameraSpec("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
    tf = Transform((0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    pool = _Pool()
    sm = SessionManager(
        pool,  # type: ignore[arg-type]
        _Registry(),  # type: ignore[arg-type]
        ServerMetrics(),
        server_id="model",
        max_image_pixels=64 * 48,
        worker_queue=2,  # the server's defaults
        relocalize_share=0.5,
        frame_budget_ms=0,
        max_pending=max_pending,
    )
    poses: dict[int, list[tuple[int, float]]] = {i: [] for i in range(clients)}
    sent: dict[tuple[int, int], float] = {}
    clock = [0.0]
    events: list[tuple[float, int, str, Any]] = []
    order = 0
    for i in range(clients):
        # aligned: the barrier releases every client at once (~1 ms apart)
        phase = i / clients if spread else rng.uniform(0.0, 0.002) * rate_hz
        for k in range(1, frames + 1):
            events.append(((k - 1 + phase) / rate_hz, order, "frame", (i, k)))
            order += 1
    heapq.heapify(events)
    wraps = {i: WRAP_FRAMES - (i * WRAP_FRAMES) // clients for i in range(clients)}
    client_of: dict[str, int] = {f"c{i}": i for i in range(clients)}
    handed = 0
    backlog: list[list[Any]] = [[] for _ in range(pool.n)]
    running: list[Any] = [None] * pool.n
    total_of: dict[tuple[int, int], float] = {}

    class _Sink:
        def __init__(self, i: int) -> None:
            self.i = i

        def send(self, p: Any) -> None:
            poses[self.i].append((p.seq, clock[0]))

        def send_encoded(self, data: bytes) -> None:  # pragma: no cover - poses come decoded
            raise AssertionError

        def close(self) -> None:
            pass

    while events:
        now, _, kind, data = heapq.heappop(events)
        clock[0] = now
        if kind == "frame":
            i, k = data
            sent[(i, k)] = now
            frame = Frame(k, int(now * 1e9), cam, "gray8", b"")
            sm.submit("m", f"c{i}", "zenoh", frame, now, make_sink=functools.partial(_Sink, i))
        elif kind == "done":
            w, m, ms, status, matching = data
            running[w] = None
            pose = P.PoseResult(
                status, tf, tf, None, None, 30, 100, 80, 40, matching, ms, "", tuple([0.0] * 36)
            )
            sm.on_result(P.Result(m.sid, m.seq, m.stamp_ns, m.gen, "build", pose, None, 0.0, ms,
                                  m.ticket))  # fmt: skip
        else:  # a relocalization's piece ended: the worker's other frames may go first
            running[data] = None
        for w, m in pool.frames[handed:]:
            backlog[w].append(m)
        handed = len(pool.frames)
        for w in range(pool.n):
            if running[w] is not None or not backlog[w]:
                continue
            # a suspended relocalization ([message, ms left]) waits while a new frame is there
            j = next((j for j, it in enumerate(backlog[w]) if not isinstance(it, list)), 0)
            item = backlog[w].pop(j)
            if isinstance(item, list):
                m, left = item
            else:
                m = item
                sess = next(s for s in sm.list() if s.sid == m.sid)
                reloc = wrap and m.seq == wraps[client_of[sess.client_id]]
                drawn = float(costs_ms[rng.integers(len(costs_ms))])
                left = (reloc_ms if reloc else drawn) + extra_ms
                total_of[(m.sid, m.seq)] = left
                if reloc and step_ms > 0:
                    item = [m, left]
            total = total_of[(m.sid, m.seq)]
            status, matching = (
                ("RELOCALIZED", "global") if total > reloc_ms / 2 else ("TRACKING", "none")
            )
            if isinstance(item, list) and left > step_ms:
                item[1] = left - step_ms
                backlog[w].append(item)  # behind every frame waiting now
                running[w] = "piece"
                heapq.heappush(events, (now + step_ms / speed / 1e3, order, "piece", w))
            else:
                running[w] = m
                done = (w, m, total, status, matching)
                heapq.heappush(events, (now + left / speed / 1e3, order, "done", done))
            order += 1
    drops = [frames - sum(1 for seq, _ in poses[i] if seq and seq >= 1) for i in range(clients)]
    lat = {
        i: [(t - sent[(i, seq)]) * 1e3 + 1.5 for seq, t in poses[i] if seq] for i in range(clients)
    }
    return {
        "dropped_pct": 100.0 * sum(drops) / (frames * clients),
        "dropped_pct_worst_client": 100.0 * max(drops) / frames,
        "latency_ms_p50": float(np.median([np.percentile(v, 50) for v in lat.values()])),
        "latency_ms_p99": float(max(np.percentile(v, 99) for v in lat.values())),
    }


VARIANTS: dict[str, dict[str, Any]] = {
    "aligned, wrap (the suite)": {},
    "aligned, no wrap": {"wrap": False},
    "spread, wrap": {"spread": True},
    "spread, no wrap": {"spread": True, "wrap": False},
    "aligned, wrap, stepped 10 ms": {"step_ms": 10.0},
    "spread, wrap, stepped 10 ms": {"spread": True, "step_ms": 10.0},
    "aligned, wrap, max_pending 2": {"max_pending": 2},
}


def run_costs(run: Path) -> np.ndarray:
    """Engine CPU (ms) of the recorded run's poses that did not relocalize."""
    res = json.loads((run / "clients.json").read_text())
    xs = [
        a[5]
        for c in res["clients"]
        for a in c["timeline"]["answers"]
        if a[3] != "global" and a[5] and a[5] > 0
    ]
    if not xs:
        raise ValueError(f"no engine CPU per pose in {run}/clients.json")
    return np.asarray(xs, dtype=float)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a droptimeline recording (its clients.json)")
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--mean-ms", type=float, default=6.1)
    ap.add_argument("--extra-ms", type=float, default=0.85)
    ap.add_argument("--reloc-ms", type=float, default=95.0)
    ap.add_argument("--speed", type=float, default=0.88)
    args = ap.parse_args(argv)
    costs = run_costs(args.run)
    costs = costs * (args.mean_ms / costs.mean())
    for name, kw in VARIANTS.items():
        runs = [
            simulate(
                costs,
                seed=s,
                extra_ms=args.extra_ms,
                reloc_ms=args.reloc_ms,
                speed=args.speed,
                **kw,
            )  # fmt: skip
            for s in range(args.seeds)
        ]
        mean = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
        print(
            f"{name:30s} dropped {mean['dropped_pct']:5.2f}%  worst client "
            f"{mean['dropped_pct_worst_client']:5.2f}%  latency p50 {mean['latency_ms_p50']:5.1f}"
            f"  p99 {mean['latency_ms_p99']:6.1f} ms",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
