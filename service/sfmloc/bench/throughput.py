"""The ``throughput`` suite: N clients at camera rate against one real ``sfmloc serve``.

Reuses the server benchmark's client run (``sfmloc.bench.transport.bench_clients``, also behind
``sfmloc bench-transport``): the server is a subprocess (``ServerProcess``: Zenoh on a free
loopback port, multicast scouting off, process workers, one per core by default); each client
has its own Zenoh session and streams redkitchen JPEGs at ``rate_hz`` from its own starting
frame (after one warm-up frame that relocalizes), and is timed from publish to pose received.

Besides rates and latencies, each row has the CPU each part spent per delivered pose (server
process, its workers, the benchmark's clients: /proc, so it holds on a shared machine where
wall times do not) and what that CPU allows: ``capacity_hz``, the poses per second the
server's own CPU per pose would sustain on every core of this machine with nothing else
running (a bound, not a measurement). Then the resident memory of the server and its workers
with 1, 2 and 4 workers (``bench_memory``: RSS, PSS, private).
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)


def serve_folder(work: Path, bundle: Path) -> Path:
    """A maps folder holding only ``bundle`` (the server loads every bundle of its folder)."""
    folder = work / "serve-maps"
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    link = folder / bundle.name
    try:
        link.symlink_to(bundle.resolve(), target_is_directory=True)
    except OSError:
        shutil.copytree(bundle, link)
    return folder


def aggregate(clients: list[dict[str, Any]], rate_hz: float) -> dict[str, Any]:
    """One row per client count: delivered pose rate per client and in total, dropped
    fraction (frames without a pose: no answer, or an error answer such as DEADLINE_EXCEEDED,
    counted by code in ``error_codes``), latency p50 (median over clients) and p99 (worst
    client), and the share of poses that relocalized, of all and of the frames sent after the
    stream's first second (the start is a burst: every session relocalizes at once)."""
    sent = sum(c["sent"] for c in clients)
    # An answer with an error carries no pose: not delivered (they were counted as delivered).
    posed = [c["received"] - c["errors"] for c in clients]
    worst = max(
        (100.0 * (c["sent"] - p) / c["sent"] for c, p in zip(clients, posed) if c["sent"]),
        default=float("nan"),
    )
    # A client sends `sent` frames in sent / rate seconds; poses delivered over that time.
    per_client = [p * rate_hz / c["sent"] if c["sent"] else 0.0 for c, p in zip(clients, posed)]
    # Poses by status over all clients: a share of RELOCALIZED far above the 1-client run's is
    # the collapse under overload (every frame after a gap relocalizes, at 5-20x the CPU).
    statuses, settled = _sum(clients, "statuses"), _sum(clients, "statuses_after_1s")
    n_status = sum(statuses.values())
    return {
        "clients": len(clients),
        "offered_hz": rate_hz * len(clients),
        "delivered_hz_total": float(np.sum(per_client)),
        "delivered_hz_per_client": float(np.mean(per_client)),
        # fairness: the client served least, against the mean above
        "delivered_hz_worst_client": float(min(per_client, default=float("nan"))),
        "statuses": statuses,
        "relocalized_pct": 100.0 * statuses.get("RELOCALIZED", 0) / n_status
        if n_status
        else float("nan"),
        "relocalized_pct_after_1s": 100.0 * settled.get("RELOCALIZED", 0) / sum(settled.values())
        if settled
        else float("nan"),
        "dropped_pct": 100.0 * (sent - sum(posed)) / sent if sent else float("nan"),
        "dropped_pct_worst_client": float(worst),
        "latency_ms_p50": float(np.nanmedian([c["latency_ms_p50"] for c in clients])),
        "latency_ms_p99": float(np.nanmax([c["latency_ms_p99"] for c in clients])),
        "engine_ms_mean": float(np.nanmean([c["engine_ms_mean"] for c in clients])),
        # The engine's CPU per pose delivered (0 from a server without engine_cpu_ms)
        "engine_cpu_ms_mean": _ratio(
            sum(c.get("engine_cpu_ms_sum", 0.0) for c in clients),
            sum(c.get("engine_cpu_poses", 0) for c in clients),
        ),
        "errors": int(sum(c["errors"] for c in clients)),
        "error_codes": _sum(clients, "error_codes"),
        **gap_summary(clients),
    }


def gap_summary(clients: list[dict[str, Any]]) -> dict[str, Any]:
    """Poses by the frames since their client's previous pose (``transport.GAP_BUCKETS``):
    share of the poses and the engine's CPU per pose in each bucket, and the share of poses
    that came 4 or more frames after the previous one. Under overload latest-frame-only
    widens the gaps, and past 4 frames a pose costs the engine more (x1.35 at 5-6 frames, x2
    at 8, x5 at 12: more motion to track over): why the CPU per pose rises with the client
    count.
    Empty for clients without gap records (an older run)."""
    from .transport import GAP_BUCKETS

    if not any("gaps" in c for c in clients):
        return {}
    poses = {b: 0 for b in GAP_BUCKETS}
    cpu = {b: 0.0 for b in GAP_BUCKETS}
    for c in clients:
        for b, (n, ms) in c.get("gaps", {}).items():
            poses[b] += int(n)
            cpu[b] += float(ms)
    total = sum(poses.values())
    wide = poses["4-7"] + poses["8+"]
    return {
        "gaps": {
            b: {
                "poses": poses[b],
                "pct": 100.0 * poses[b] / total if total else float("nan"),
                "engine_cpu_ms": _ratio(cpu[b], poses[b]),
            }
            for b in GAP_BUCKETS
        },
        "gap_4plus_pct": 100.0 * wide / total if total else float("nan"),
        # the engine's CPU per pose after 1-3 frames and after 4 or more
        "engine_cpu_ms_gap_1_3": _ratio(cpu["1"] + cpu["2"] + cpu["3"], total - wide),
        "engine_cpu_ms_gap_4plus": _ratio(cpu["4-7"] + cpu["8+"], wide),
    }


def _ratio(a: float, b: float) -> float:
    return a / b if b else float("nan")


def _sum(clients: list[dict[str, Any]], key: str) -> dict[str, int]:
    """The counts under ``key`` of every client, summed."""
    out: dict[str, int] = {}
    for c in clients:
        for k, v in c.get(key, {}).items():
            out[k] = out.get(k, 0) + v
    return out


def run_throughput(
    work: Path,
    bundle: Path,
    frames_dir: Path,
    camera: str,
    clients: list[int],
    rate_hz: float,
    duration_s: float,
    workers: int,
    progress=None,
    memory_workers: tuple[int, ...] = (1, 2, 4),
    phases: str = "spread",
    frame_loop: str = "pingpong",
    stress_clients: int = 0,
) -> dict[str, Any]:
    """One server run per client count (``phases``, ``frame_loop``: see ``bench_clients``),
    then, with ``stress_clients`` > 0, one run at that many clients sending aligned and
    wrapping (``stress_rows``: the suite's mode before issue 10's drop diagnosis)."""
    from ..bench.transport import BenchInput, bench_clients, bench_memory

    frames = sorted(
        p for p in Path(frames_dir).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")
    )
    if not frames:
        raise InputError(f"no frames in {frames_dir}")
    maps = serve_folder(work, bundle)
    inp = BenchInput(maps, bundle.name, frames, camera)
    inp.load(min(len(frames), int(rate_hz * duration_s) + 10))
    n_workers = workers or (os.cpu_count() or 1)
    rows, raw, stress_rows = [], [], []
    runs = [(n, phases, frame_loop) for n in clients]
    if stress_clients > 0:
        runs.append((stress_clients, "aligned", "wrap"))
    for k, (n, ph, loop) in enumerate(runs):
        if progress:
            progress(
                "throughput",
                k / len(runs),
                f"{n} client(s) x {rate_hz:g} Hz x {duration_s:g} s ({ph}, {loop})",
            )
        log.info(
            "throughput: %d client(s) at %g Hz for %g s, %d server workers, %s sends, %s loop",
            n,
            rate_hz,
            duration_s,
            n_workers,
            ph,
            loop,
        )
        res = bench_clients(
            inp, n, rate_hz, duration_s, n_workers, "process", phases=ph, frame_loop=loop
        )
        row = aggregate(res["clients"], rate_hz)
        posed = sum(c["received"] - c["errors"] for c in res["clients"])
        row.update(cpu_per_pose(res["cores_used"], row["delivered_hz_total"]))
        if "cpu_seconds" in res:  # the CPU of the streams over the poses they got
            row.update(cpu_per_pose(res["cores_used"], 0.0, res["cpu_seconds"], posed))
        row["outside_engine_ms"] = outside_engine_ms(row)
        row.update(server_threads(res, posed))
        row["load_before"], row["load_after"] = res["load_before"], res["load_after"]
        row["client_phases"], row["frame_loop"] = ph, loop
        if k < len(clients):
            rows.append(row)
            raw.append(res)
        else:
            stress_rows.append(row)
    memory: dict[str, Any] = {}
    if memory_workers:
        if progress:
            progress("throughput", 0.99, f"resident memory, {memory_workers} workers")
        memory = memory_rows(bench_memory(inp, tuple(memory_workers)))
    if progress:
        progress("throughput", 1.0, "done")
    return {
        "memory": memory,
        "server": "sfmloc serve (subprocess), Zenoh tcp loopback, multicast scouting off, process "
        "workers",
        "workers": n_workers,
        "rate_hz": rate_hz,
        "duration_s": duration_s,
        "map": bundle.name,
        "encoding": "png" if frames[0].suffix.lower() == ".png" else "jpeg",  # as the files
        "client_phases": phases,
        "frame_loop": frame_loop,
        "rows": rows,
        "stress_rows": stress_rows,
        "per_client": [r["clients"] for r in raw],
    }


def cpu_per_pose(
    cores: dict[str, float],
    delivered_hz: float,
    cpu_seconds: dict[str, float] | None = None,
    poses: int = 0,
) -> dict[str, Any]:
    """CPU ms per delivered pose of each part, and the pose rate the server's (process +
    workers) CPU per pose allows on all of this machine's cores: ``cpu_seconds`` of each part
    over the ``poses`` delivered meanwhile, or (without them) ``cores`` (CPU seconds per
    second of each) over ``delivered_hz``."""
    if cpu_seconds is not None:
        per = {k: 1e3 * v / poses if poses else float("nan") for k, v in cpu_seconds.items()}
    else:
        per = {
            k: 1e3 * v / delivered_hz if delivered_hz > 0 else float("nan")
            for k, v in cores.items()
        }
    server_ms = per.get("server", 0.0) + per.get("workers", 0.0)
    ncpu = os.cpu_count() or 1
    return {
        "cores_used": {k: float(v) for k, v in cores.items()},
        "cpu_ms_per_pose": per,
        "capacity_hz": 1e3 * ncpu / server_ms if server_ms > 0 else float("nan"),
    }


def server_threads(res: dict[str, Any], posed: int) -> dict[str, Any]:
    """Where the CPU of the server and its workers goes, per thread kind ("process/thread",
    trailing digits dropped: ``sfmloc-worker/sfmloc-worker``, the server's ``sfmloc-recv``
    result threads, Zenoh's ``rx``/``tx`` runtime threads, ``python`` for Zenoh's Python
    callback thread, ...): CPU ms and context switches per delivered pose; and the server
    process's CPU per frame sent, which its intake spends on every frame, the ones superseded
    or refused too. Empty for a run without thread samples."""
    from .scale import thread_rows_delta

    th = res.get("threads")
    if not th:
        return {}
    sent = sum(c["sent"] for c in res["clients"])
    server_s = res.get("cpu_seconds", {}).get("server", float("nan"))
    return {
        "server_threads": thread_rows_delta(th["start"], th["end"], posed),
        "server_cpu_ms_per_frame_sent": 1e3 * server_s / sent if sent else float("nan"),
    }


def outside_engine_ms(row: dict[str, Any]) -> float:
    """The server's CPU per pose (process + workers) beyond the engine's CPU per pose: what
    the server spends around the engine (JPEG decoding, Zenoh, the hand-off to and from its
    workers, scheduling) plus the engine's CPU on frames that delivered no pose (answered
    DEADLINE_EXCEEDED). NaN when the server did not report the engine's CPU."""
    per = row.get("cpu_ms_per_pose") or {}
    engine = row.get("engine_cpu_ms_mean", float("nan"))
    if not engine or engine != engine:  # 0 or NaN: not reported (an older server)
        return float("nan")
    return per.get("server", float("nan")) + per.get("workers", float("nan")) - engine


def memory_rows(mem: dict[str, Any]) -> dict[str, Any]:
    """``bench_memory``'s runs as MB per worker count: all processes together (RSS counts
    shared pages once per process, PSS divides them among the processes that map them, private
    is what each process holds alone) and the largest single worker."""
    rows = []
    for run in mem["runs"]:
        workers = [v for k, v in run["processes"].items() if k != "server"]
        rows.append(
            {
                "workers": run["workers"],
                "processes": len(run["processes"]),
                "rss_mb": run["total"]["rss_kb"] / 1024,
                "pss_mb": run["total"]["pss_kb"] / 1024,
                "private_mb": run["total"].get("private_kb", 0) / 1024,
                "server_pss_mb": run["processes"].get("server", {}).get("pss_kb", 0) / 1024,
                "worker_pss_mb_max": max((w["pss_kb"] for w in workers), default=0) / 1024,
                "index_file_mb_per_worker": max((w["index_file_kb"] for w in workers), default=0)
                / 1024,
            }
        )
    return {"frames_per_session": mem["frames_per_session"], "rows": rows}
