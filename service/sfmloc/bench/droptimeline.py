"""Where a loaded server's drops and late poses come from (issue 10): one throughput run with the
server's per-frame timeline on (``sessions.TIMELINE_ENV``), then every dropped frame and every
pose over ``--late-ms`` classified by what its session's worker was doing meanwhile::

    python -m sfmloc.bench.droptimeline OUT --maps MAPS_DIR --map redkitchen \\
        --frames /work/shared/data/redkitchen-seq01 [--clients 8] [--workers 2] \\
        [--client-phases aligned|spread] [--frame-loop wrap|pingpong]
    python -m sfmloc.bench.droptimeline OUT --analyze-only

The run is the throughput suite's (``transport.bench_clients``: a real ``sfmloc serve``
subprocess, real Zenoh clients at 30 Hz); both sides stamp with ``time.perf_counter`` (the same
monotonic clock for every process of the machine). A worker's frames are intervals [its result
- ``worker_ms``, its result]. A drop (a frame superseded by a newer one of its session while it
waited) or a late pose (client send to pose received) is put down to the first of, in order:

- ``own-reloc``: its session's own frame in the worker relocalized (sent cold, not TRACKING, or
  global matching);
- ``other-reloc``: another session's relocalization ran on the same worker in the window, or
  ended within 100 ms before it (``other-reloc-100ms``);
- ``heavy-cpu``: a frame of more than 15 ms of engine CPU ran there (a guided batch, a densify
  re-match);
- ``preempted``: a frame there took more than 12 ms of wall and over twice its engine CPU (+1 ms
  of decoding): it waited for a core (the other worker, the server, the clients, other load);
- ``nothing special``: the worker's queue alone (its sessions' ordinary frames).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

CAUSES = ("own-reloc", "other-reloc", "other-reloc-100ms", "heavy-cpu", "preempted")


def record(out: Path, maps: Path, map_name: str, frames_dir: Path, camera: str, clients: int,
           workers: int, rate_hz: float, duration_s: float, phases: str = "aligned",
           frame_loop: str = "wrap") -> dict[str, Any]:  # fmt: skip
    """One ``bench_clients`` run with the timeline on: the server writes its rows into ``out``
    at shutdown, the clients' sends and answers go to ``out/clients.json``."""
    from ..server.sessions import TIMELINE_ENV
    from .throughput import aggregate, serve_folder
    from .transport import BenchInput, bench_clients

    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("timeline-*.jsonl"):
        old.unlink()
    os.environ[TIMELINE_ENV] = str(out)  # the server subprocess inherits it
    frames = sorted(p for p in frames_dir.iterdir() if p.suffix.lower() in (".jpg", ".png"))
    inp = BenchInput(serve_folder(out, maps / map_name), map_name, frames, camera)
    inp.load(min(len(frames), int(rate_hz * duration_s) + 10))  # as the throughput suite
    res = bench_clients(
        inp, clients, rate_hz, duration_s, workers, "process", phases=phases, frame_loop=frame_loop
    )
    (out / "clients.json").write_text(json.dumps(res))
    return aggregate(res["clients"], rate_hz)


def analyze(out: Path, late_ms: float = 50.0) -> dict[str, Any]:
    """The shares of drops and late poses by cause (module docstring), and per relocalization
    the other sessions' drops on its worker during it and 100 ms after."""
    files = sorted(out.glob("timeline-*.jsonl"))
    if not files:
        raise FileNotFoundError(f"no timeline-*.jsonl in {out}")
    rows = [json.loads(line) for line in files[-1].read_text().splitlines()]
    res = json.loads((out / "clients.json").read_text())
    client_of = {r[2]: r[3] for r in rows if r[0] == "open"}
    worker_of = {r[2]: r[4] for r in rows if r[0] == "open"}
    sid_of = {c: s for s, c in client_of.items()}
    sent = {
        c["client"]: {int(k): v for k, v in c["timeline"]["sent"].items()} for c in res["clients"]
    }
    answers = {(c["client"], a[0]): a for c in res["clients"] for a in c["timeline"]["answers"]}
    t0 = min(min(v.values()) for v in sent.values())
    t1 = max(max(v.values()) for v in sent.values()) + 0.1
    # worker -> intervals (start, end, sid, seq, relocalized, worker_ms, engine CPU ms)
    runs: dict[int, list[tuple[float, float, int, int, bool, float, float]]] = (
        collections.defaultdict(list)
    )
    for r in rows:
        if r[0] == "res" and r[4] is not None:
            _, t, sid, seq, w, _, _, _, wms, _, _, reloc = r
            a = answers.get((client_of.get(sid), seq))
            cpu = float(a[5]) if a else float("nan")
            runs[w].append((t - wms / 1e3, t, sid, seq, bool(reloc), wms, cpu))

    def causes(sid: int, a: float, b: float, seq: int | None = None) -> set[str]:
        w = worker_of[sid]
        over = [x for x in runs[w] if x[1] > a and x[0] < b]
        out: set[str] = set()
        for x in over:
            if x[4]:
                out.add("own-reloc" if x[2] == sid else "other-reloc")
            if not x[4] and x[6] > 15:
                out.add("heavy-cpu")
            if x[5] > 12 and x[5] > 2 * (x[6] + 1.0):
                out.add("preempted")
        for x in runs[w]:
            if x[4] and a - 0.1 < x[1] <= a:
                out.add("own-reloc" if x[2] == sid else "other-reloc-100ms")
        return out

    def first(c: set[str]) -> str:
        return next((k for k in CAUSES if k in c), "nothing special")

    recv = {(r[2], r[3]): r[1] for r in rows if r[0] == "recv"}
    drop_causes: collections.Counter[str] = collections.Counter()
    drops = [r for r in rows if r[0] == "drop" and t0 <= r[1] <= t1]
    for _, t_d, sid, seq, _ in drops:
        t_r = recv.get((sid, seq), t_d - 0.033)
        drop_causes[first(causes(sid, t_r - 0.033, t_d))] += 1
    late_causes: collections.Counter[str] = collections.Counter()
    latencies = []
    for (cid, seq), a in answers.items():
        if seq in sent[cid] and seq > 0:
            ms = (a[1] - sent[cid][seq]) * 1e3
            latencies.append(ms)
            if ms > late_ms:
                late_causes[first(causes(sid_of[cid], sent[cid][seq], a[1], seq))] += 1
    relocs = [(x, w) for w, xs in runs.items() for x in xs if x[4] and t0 <= x[1] <= t1]
    drop_t = [(r[1], r[2]) for r in drops]
    per_reloc = [
        {
            "worker": w,
            "client": client_of[x[2]],
            "seq": x[3],
            "worker_ms": round(x[5], 1),
            "engine_cpu_ms": round(x[6], 1),
            "other_drops": sum(
                1 for t, s in drop_t if worker_of[s] == w and s != x[2] and x[0] <= t <= x[1] + 0.1
            ),
            "own_drops": sum(1 for t, s in drop_t if s == x[2] and x[0] <= t <= x[1] + 0.1),
        }
        for x, w in relocs
    ]
    n_sent = sum(len(v) for v in sent.values())
    return {
        "frames_sent": n_sent,
        "drops": len(drops),
        "drop_causes": dict(drop_causes.most_common()),
        "late_poses": sum(late_causes.values()),
        "late_causes": dict(late_causes.most_common()),
        "latency_ms_p50": float(np.percentile(latencies, 50)) if latencies else float("nan"),
        "latency_ms_p99": float(np.percentile(latencies, 99)) if latencies else float("nan"),
        "relocalizations": per_reloc,
        "drops_near_relocalizations": sum(r["other_drops"] + r["own_drops"] for r in per_reloc),
    }


def _print(a: dict[str, Any]) -> None:
    n, m = max(a["drops"], 1), max(a["late_poses"], 1)
    print(f"{a['drops']} drops of {a['frames_sent']} frames; by first cause:")
    for k, v in a["drop_causes"].items():
        print(f"  {k:18s} {v:5d} {100 * v / n:5.1f}%")
    print(f"{a['late_poses']} late poses (p50 {a['latency_ms_p50']:.1f}, p99 "
          f"{a['latency_ms_p99']:.1f} ms); by first cause:")  # fmt: skip
    for k, v in a["late_causes"].items():
        print(f"  {k:18s} {v:5d} {100 * v / m:5.1f}%")
    near = a["drops_near_relocalizations"]
    print(f"drops during a relocalization (+100 ms) on its worker: {near} ({100 * near / n:.0f}%)")
    for r in a["relocalizations"]:
        print(f"  {r}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--analyze-only", action="store_true")
    ap.add_argument("--maps", type=Path)
    ap.add_argument("--map", default="redkitchen")
    ap.add_argument("--frames", type=Path, default=Path("/work/shared/data/redkitchen-seq01"))
    ap.add_argument("--camera", default="PINHOLE 640 480 525.505 525.505 320 240")
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--late-ms", type=float, default=50.0)
    ap.add_argument("--client-phases", choices=("aligned", "spread"), default="aligned")
    ap.add_argument("--frame-loop", choices=("wrap", "pingpong"), default="wrap")
    args = ap.parse_args(argv)
    if not args.analyze_only:
        if args.maps is None:
            ap.error("--maps is needed to record")
        row = record(args.out, args.maps, args.map, args.frames, args.camera, args.clients,
                     args.workers, args.rate, args.duration, args.client_phases,
                     args.frame_loop)  # fmt: skip
        keys = ("dropped_pct", "dropped_pct_worst_client", "latency_ms_p50", "latency_ms_p99")
        print({k: round(row[k], 2) for k in keys}, "load", [round(x, 2) for x in os.getloadavg()])
    a = analyze(args.out, args.late_ms)
    (args.out / "analysis.json").write_text(json.dumps(a, indent=1))
    _print(a)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
