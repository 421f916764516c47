"""``python -m sfmloc.bench.startup``: how fast the server starts, and replaces a killed worker.

Two measurements, each interleaved between worker start modes (``worker_start``: ``fork``,
workers forked from the pre-imported zygote; ``exec``, a fresh interpreter each) so that both
see the same machine load (printed; the machine may be shared, only the ratio is evidence):

``start``    launch of ``sfmloc serve`` (a subprocess, loopback, no multicast) until its gRPC
             health says SERVING, with every bundle of ``--maps`` loaded.
``restart``  kill -9 of a stream worker of a ``WorkerPool`` holding the first bundle until its
             replacement serves with that map again.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

from ..testing import free_port, serve_command

MODES = ("exec", "fork")


def time_to_serving(maps: Path, workers: int, mode: str, timeout: float = 120.0) -> float:
    """Seconds from the launch of ``sfmloc serve`` to SERVING (its gRPC health)."""
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    address = f"127.0.0.1:{free_port()}"
    cmd = serve_command(maps, f"tcp/127.0.0.1:{free_port()}", address, workers)
    env = dict(os.environ, SFMLOC_WORKER_START=mode)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL)
    try:
        with grpc.insecure_channel(address) as channel:
            stub = health_pb2_grpc.HealthStub(channel)
            serving = health_pb2.HealthCheckResponse.SERVING
            while time.perf_counter() - t0 < timeout:
                if proc.poll() is not None:
                    raise RuntimeError(f"sfmloc serve exited with {proc.returncode}")
                try:
                    req = health_pb2.HealthCheckRequest(service="")
                    if stub.Check(req, timeout=0.2).status == serving:
                        return time.perf_counter() - t0
                except grpc.RpcError:
                    pass
                time.sleep(0.01)
        raise TimeoutError(f"not SERVING within {timeout:g} s")
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def restart_times(bundle: Path, kills: int) -> dict[str, list[float]]:
    """Per mode, seconds from kill -9 of worker 0 until its replacement serves with
    ``bundle``; the two pools run side by side and are killed in turn."""
    from ..server.pool import WorkerHandle, WorkerPool

    pools = {}
    for m in MODES:
        pools[m] = WorkerPool(2, "process", "{}", on_result=lambda r: None, fork=m == "fork")
    out: dict[str, list[float]] = {m: [] for m in MODES}
    try:
        for pool in pools.values():
            pool.start(120)
            pool.load_map(bundle.name, 1, str(bundle), "", timeout=300)
        for _ in range(kills):
            for m, pool in pools.items():
                victim = pool.workers[0]
                t0 = time.monotonic()
                os.kill(victim.pid, signal.SIGKILL)

                def replaced(p: WorkerPool = pool, v: WorkerHandle = victim) -> bool:
                    return p.workers[0] is not v and p.is_alive(0)

                if not pool.wait_for(replaced, 120):
                    raise TimeoutError("the replacement did not serve within 120 s")
                out[m].append(time.monotonic() - t0)
                time.sleep(0.5)
    finally:
        for pool in pools.values():
            pool.stop()
    return out


def _line(name: str, runs: dict[str, list[float]]) -> str:
    parts = [
        f"{m} median {statistics.median(v):.2f} s ({', '.join(f'{x:.2f}' for x in v)})"
        for m, v in runs.items()
    ]
    ratio = statistics.median(runs["fork"]) / statistics.median(runs["exec"])
    return f"{name:8s} " + "; ".join(parts) + f"; fork/exec x{ratio:.2f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m sfmloc.bench.startup",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--maps", type=Path, required=True, help="a maps folder (every bundle loads)")
    p.add_argument("--workers", type=int, default=2, help="stream workers (default 2; + 1 lane)")
    p.add_argument("--runs", type=int, default=4, help="launches per mode (default 4)")
    p.add_argument("--kills", type=int, default=5, help="worker kills per mode (default 5)")
    p.add_argument("--parts", default="start,restart", help="start, restart (default both)")
    a = p.parse_args(argv)
    parts = {s.strip() for s in a.parts.split(",") if s.strip()}
    bundles = sorted(d for d in a.maps.iterdir() if (d / "manifest.json").is_file())
    if not bundles:
        p.error(f"no bundle in {a.maps}")
    print(f"load average {os.getloadavg()[0]:.1f} at start ({os.cpu_count()} CPUs)", flush=True)
    if "start" in parts:
        runs: dict[str, list[float]] = {m: [] for m in MODES}
        for _ in range(a.runs):
            for m in MODES:
                runs[m].append(time_to_serving(a.maps, a.workers, m))
        print(_line("start", runs), flush=True)
    if "restart" in parts:
        print(_line("restart", restart_times(bundles[0], a.kills)), flush=True)
    print(f"load average {os.getloadavg()[0]:.1f} at the end", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
