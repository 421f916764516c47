"""The ``throughput`` suite: N clients at camera rate against one real ``sfmloc serve``.

Reuses the server benchmark's client run (``sfmloc.bench.transport.bench_clients``, also behind
``sfmloc bench-transport``): the server is a subprocess (``ServerProcess``: Zenoh on a free
loopback port, multicast scouting off, process workers, one per core by default); each client
has its own Zenoh session and streams redkitchen JPEGs at ``rate_hz`` from its own starting
frame (after one warm-up frame that relocalizes), and is timed from publish to pose received.
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
    fraction (frames without a pose), latency p50 (median over clients) and p99 (worst client)."""
    sent = sum(c["sent"] for c in clients)
    recv = sum(c["received"] for c in clients)
    # A client sends `sent` frames in sent / rate seconds; poses delivered over that time.
    per_client = [c["received"] * rate_hz / c["sent"] if c["sent"] else 0.0 for c in clients]
    return {
        "clients": len(clients),
        "offered_hz": rate_hz * len(clients),
        "delivered_hz_total": float(np.sum(per_client)),
        "delivered_hz_per_client": float(np.mean(per_client)),
        "dropped_pct": 100.0 * (sent - recv) / sent if sent else float("nan"),
        "latency_ms_p50": float(np.nanmedian([c["latency_ms_p50"] for c in clients])),
        "latency_ms_p99": float(np.nanmax([c["latency_ms_p99"] for c in clients])),
        "engine_ms_mean": float(np.nanmean([c["engine_ms_mean"] for c in clients])),
        "errors": int(sum(c["errors"] for c in clients)),
    }


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
) -> dict[str, Any]:
    from ..bench.transport import BenchInput, bench_clients

    frames = sorted(
        p for p in Path(frames_dir).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")
    )
    if not frames:
        raise InputError(f"no frames in {frames_dir}")
    maps = serve_folder(work, bundle)
    inp = BenchInput(maps, bundle.name, frames, camera)
    inp.load(min(len(frames), int(rate_hz * duration_s) + 10))
    n_workers = workers or (os.cpu_count() or 1)
    rows, raw = [], []
    for k, n in enumerate(clients):
        if progress:
            progress(
                "throughput", k / len(clients), f"{n} client(s) x {rate_hz:g} Hz x {duration_s:g} s"
            )
        log.info(
            "throughput: %d client(s) at %g Hz for %g s, %d server workers",
            n,
            rate_hz,
            duration_s,
            n_workers,
        )
        res = bench_clients(inp, n, rate_hz, duration_s, n_workers, "process")
        row = aggregate(res["clients"], rate_hz)
        row["load_before"], row["load_after"] = res["load_before"], res["load_after"]
        rows.append(row)
        raw.append(res)
    if progress:
        progress("throughput", 1.0, "done")
    return {
        "server": "sfmloc serve (subprocess), Zenoh tcp loopback, multicast scouting off, process "
        "workers",
        "workers": n_workers,
        "rate_hz": rate_hz,
        "duration_s": duration_s,
        "map": bundle.name,
        "encoding": "jpeg",
        "rows": rows,
        "per_client": [r["clients"] for r in raw],
    }
