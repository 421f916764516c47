"""``sfmloc bench-transport``: what the transport costs, and how the server scales.

Sections (``--only``, comma-separated; all by default):

``wire``      frame envelope (image inside the msgpack map) vs Zenoh attachment (header in the
              attachment, image as the payload): encode + decode time, and the loopback
              publish -> subscriber-decoded time, at the frames' size.
``overhead``  end to end over Zenoh on loopback (frame published -> pose received) against the
              in-process engine on the same frames (one thread): p50 and per-frame overhead
              (round trip minus the engine time the server reports), raw gray8 and JPEG.
``clients``   N clients (own Zenoh session each) at R Hz for D seconds, each streaming the
              frames from its own starting point: per client frames sent / poses back /
              dropped, latency p50 and p99.
``workers``   the same with thread workers instead of processes (why processes).
``memory``    resident memory (RSS, PSS, anonymous) of the server and its workers with 1, 2 and
              4 workers, and how much of each worker's index is the shared file mapping.

The server runs as a subprocess (``sfmloc serve``) so that the benchmark's own client threads
do not share its interpreter. Other processes on the machine add noise: the load average is
printed with the results.
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from ..testing import ServerProcess, free_port
from ..threads import pin_threads_env, pin_threads_runtime


def _pct(v: list[float], q: float) -> float:
    return float(np.percentile(v, q)) if len(v) else float("nan")


@dataclass
class BenchInput:
    maps: Path
    map_name: str
    frames: list[Path]
    camera: str  # "MODEL w h params..."
    jpeg: list[bytes] = field(default_factory=list)
    gray: list[np.ndarray] = field(default_factory=list)

    def load(self, n: int) -> None:
        import cv2

        from ..io.frames import decode_image

        self.jpeg = [p.read_bytes() for p in self.frames[:n]]
        self.gray = [
            decode_image(b, cv2.IMREAD_GRAYSCALE, str(p))
            for p, b in zip(self.frames[:n], self.jpeg)
        ]


def _zenoh(endpoint: str) -> Any:
    import zenoh

    from sfmloc_client import make_zenoh_config

    return zenoh.open(make_zenoh_config("peer", connect=[endpoint], multicast=False))


# ============================================================================ wire
def bench_wire(inp: BenchInput, n: int = 300) -> dict[str, Any]:
    import msgpack
    import zenoh

    from sfmloc_client import CameraSpec, Frame, decode_frame, encode_frame, make_zenoh_config

    cam = CameraSpec.parse(inp.camera)
    out: dict[str, Any] = {}
    for enc, data in (("gray8", inp.gray[0].tobytes()), ("jpeg", inp.jpeg[0])):
        t_env, t_att = [], []
        for k in range(n):
            t0 = time.perf_counter()
            decode_frame(encode_frame(Frame(k, k, cam, enc, data)))
            t1 = time.perf_counter()
            header = msgpack.packb(
                {"seq": k, "stamp_ns": k, "camera": cam.to_wire(), "encoding": enc}
            )
            h = msgpack.unpackb(header)
            CameraSpec.from_wire(h["camera"])
            payload = bytes(data)
            t2 = time.perf_counter()
            assert payload
            t_env.append((t1 - t0) * 1e6)
            t_att.append((t2 - t1) * 1e6)
        out[f"{enc}_bytes"] = len(data)
        out[f"{enc}_envelope_codec_us_p50"] = _pct(t_env, 50)
        out[f"{enc}_attachment_codec_us_p50"] = _pct(t_att, 50)

        # Loopback: publish -> decoded in the subscriber's callback.
        ep = f"tcp/127.0.0.1:{free_port()}"
        with (
            zenoh.open(make_zenoh_config("peer", listen=[ep], multicast=False)) as a,
            zenoh.open(make_zenoh_config("peer", connect=[ep], multicast=False)) as b,
        ):
            got: dict[int, float] = {}
            ev = threading.Event()

            # got/ev bound now: a callback must not see a later iteration's objects
            def on_env(s: Any, got: dict[int, float] = got, ev: threading.Event = ev) -> None:
                f = decode_frame(s.payload.to_bytes())
                got[f.seq] = time.perf_counter()
                ev.set()

            def on_att(s: Any, got: dict[int, float] = got, ev: threading.Event = ev) -> None:
                h = msgpack.unpackb(s.attachment.to_bytes())
                CameraSpec.from_wire(h["camera"])
                s.payload.to_bytes()
                got[h["seq"]] = time.perf_counter()
                ev.set()

            for mode, cb in (("envelope", on_env), ("attachment", on_att)):
                sub = a.declare_subscriber(f"bench/{mode}", cb)
                pub = b.declare_publisher(
                    f"bench/{mode}", express=True, congestion_control=zenoh.CongestionControl.BLOCK
                )
                time.sleep(0.3)
                lat = []
                for k in range(n):
                    ev.clear()
                    t0 = time.perf_counter()
                    if mode == "envelope":
                        pub.put(encode_frame(Frame(k, k, cam, enc, data)))
                    else:
                        pub.put(
                            data,
                            attachment=msgpack.packb(
                                {"seq": k, "stamp_ns": k, "camera": cam.to_wire(), "encoding": enc}
                            ),
                        )
                    if ev.wait(5) and k in got:
                        lat.append((got[k] - t0) * 1e3)
                out[f"{enc}_{mode}_loopback_ms_p50"] = _pct(lat, 50)
                out[f"{enc}_{mode}_loopback_ms_p99"] = _pct(lat, 99)
                sub.undeclare()
                pub.undeclare()
                got.clear()
    return out


# ============================================================================ overhead
def bench_overhead(inp: BenchInput, n: int) -> dict[str, Any]:
    from sfmloc_client import CameraSpec, FrameStreamer, PoseSubscriber, encode_image

    from ..cameras import Camera
    from ..engine import Localizer
    from ..map.bundle import MapBundle

    pin_threads_runtime()
    out: dict[str, Any] = {}
    # In-process engine, one thread, decoded frames.
    cam = Camera.parse(inp.camera)
    bundle = MapBundle(inp.maps / inp.map_name)
    loc = Localizer(bundle, cam)
    eng = []
    for k, g in enumerate(inp.gray[:n]):
        t0 = time.perf_counter()
        loc.localize(g, k / 30.0)
        eng.append((time.perf_counter() - t0) * 1e3)
    out["inprocess_engine_ms_p50"] = _pct(eng[5:], 50)
    out["inprocess_engine_ms_p99"] = _pct(eng[5:], 99)

    spec = CameraSpec.parse(inp.camera)
    with ServerProcess(inp.maps, workers=1) as srv, _zenoh(srv.endpoint) as z:
        # The server's CPU (its process and its workers, /proc) beyond the engine's own
        # (each pose's engine_cpu_ms), per frame, from the 6th frame on: nothing is dropped
        # in lockstep, so this is the server's cost around the engine per pose.
        pids = [srv.proc.pid, *_child_pids(srv.proc.pid)]
        for enc in ("gray8", "jpeg"):
            payloads = (
                [encode_image(g, "gray8") for g in inp.gray[:n]] if enc == "gray8" else inp.jpeg[:n]
            )
            cid = f"bench-{enc}"
            recv: dict[int, tuple[float, Any]] = {}
            cond = threading.Condition()

            def on_pose(
                p: Any, recv: dict[int, tuple[float, Any]] = recv, cond: threading.Condition = cond
            ) -> None:
                with cond:
                    recv[p.seq] = (time.perf_counter(), p)
                    cond.notify_all()

            rtt, per_frame, server_lat, engine, engine_cpu = [], [], [], [], []
            cpu0 = 0.0
            with (
                PoseSubscriber(z, inp.map_name, cid, callback=on_pose),
                FrameStreamer(z, inp.map_name, cid, spec) as fs,
            ):
                fs.wait_for_server(30)
                for k, data in enumerate(payloads):
                    if k == 5:
                        cpu0 = sum(_cpu_seconds(p) for p in pids)
                    t0 = time.perf_counter()
                    fs.publish(data=data, encoding=enc, seq=k, stamp_ns=int(k * 1e9 / 30))
                    with cond:
                        cond.wait_for(partial(recv.__contains__, k), 10)
                    if k not in recv or k < 5:
                        continue
                    t1, p = recv[k]
                    rtt.append((t1 - t0) * 1e3)
                    per_frame.append((t1 - t0) * 1e3 - p.engine_ms)
                    server_lat.append(p.latency_ms)
                    engine.append(p.engine_ms)
                    engine_cpu.append(p.engine_cpu_ms)
                cpu1 = sum(_cpu_seconds(p) for p in pids)
            frames = len(payloads) - 5
            server_cpu = 1e3 * (cpu1 - cpu0) / frames if frames > 0 else float("nan")
            out[f"{enc}_server_cpu_ms_per_frame"] = server_cpu
            out[f"{enc}_engine_cpu_ms_mean"] = float(np.mean(engine_cpu)) if engine_cpu else 0.0
            out[f"{enc}_cpu_beyond_engine_ms"] = server_cpu - out[f"{enc}_engine_cpu_ms_mean"]
            out[f"{enc}_e2e_ms_p50"] = _pct(rtt, 50)
            out[f"{enc}_e2e_ms_p99"] = _pct(rtt, 99)
            out[f"{enc}_server_engine_ms_p50"] = _pct(engine, 50)
            out[f"{enc}_overhead_ms_p50"] = _pct(per_frame, 50)  # round trip - engine, per frame
            out[f"{enc}_overhead_ms_p90"] = _pct(per_frame, 90)
            out[f"{enc}_e2e_minus_inprocess_p50_ms"] = (
                out[f"{enc}_e2e_ms_p50"] - out["inprocess_engine_ms_p50"]
            )
    return out


# ============================================================================ clients
def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc), 0 when unknown."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


def _child_pids(pid: int) -> list[int]:
    """Every descendant of ``pid``: the server's workers are children of its zygote
    (``server/zygote.py``), or its own children when started as fresh interpreters."""
    parent: dict[int, int] = {}
    for d in os.listdir("/proc") if os.path.isdir("/proc") else []:
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    parent[int(d)] = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                pass
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out += kids
        todo += kids
    return sorted(out)


def _relocalize_load(
    grpc_addr: str,
    inp: BenchInput,
    spec: Any,
    rate: float,
    stop: threading.Event,
    out: dict[str, Any],
) -> None:
    """Single-image Relocalize calls over gRPC at ``rate`` Hz (back to back when slower) until
    ``stop``: the load of one client relocalizing beside the streams."""
    from sfmloc_client import LocalizationClient

    lat: list[float] = []
    with LocalizationClient(grpc_addr, timeout=60) as c:
        t_next, k = time.perf_counter(), 0
        while not stop.is_set():
            delay = t_next - time.perf_counter()
            if delay > 0 and stop.wait(delay):
                break
            t0 = time.perf_counter()
            try:
                image = inp.jpeg[(k * 37) % len(inp.jpeg)]
                c.relocalize(image, inp.map_name, spec, encoding="jpeg")
                lat.append((time.perf_counter() - t0) * 1e3)
            except Exception:  # noqa: BLE001 - counted
                out["errors"] = out.get("errors", 0) + 1
            k += 1
            t_next += 1.0 / rate
    out.update(calls=len(lat), ms_p50=_pct(lat, 50), ms_p99=_pct(lat, 99))


def loop_order(n: int, frame_loop: str) -> list[int]:
    """The order in which a throughput client plays ``n`` loaded frames, looping over it:
    "wrap" 0..n-1 (then 0 again: the camera jumps from the last frame to the first), "pingpong"
    0..n-1..1 (then 0 again: every step is to a neighbouring frame)."""
    if frame_loop == "wrap":
        return list(range(n))
    if frame_loop == "pingpong":
        return list(range(n)) + list(range(n - 2, 0, -1))
    raise ValueError(f"frame_loop must be 'wrap' or 'pingpong', not {frame_loop!r}")


def phase_of(i: int, clients: int, phases: str) -> float:
    """When client ``i`` of ``clients`` sends, in frame intervals after the common start:
    "aligned" 0 for all (each frame interval begins with a burst of one frame per client),
    "spread" i / clients (independent cameras are not synchronized)."""
    if phases == "aligned":
        return 0.0
    if phases == "spread":
        return i / clients
    raise ValueError(f"phases must be 'aligned' or 'spread', not {phases!r}")


def bench_clients(
    inp: BenchInput,
    clients: int,
    rate: float,
    duration: float,
    workers: int,
    kind: str,
    encoding: str = "jpeg",
    max_pending: int = 1,
    reloc_rate: float = 0.0,
    reloc_workers: int | None = None,
    phases: str = "aligned",
    frame_loop: str = "wrap",
) -> dict[str, Any]:
    """``clients`` streams at ``rate`` Hz for ``duration`` s against a fresh server. Each client
    starts at its own frame of ``inp`` and loops over them. ``phases``: "aligned" (every client
    sends at the same instants after the warm-up barrier: bursts of one frame per client) or
    "spread" (client i sends i / clients of a frame interval later, as independent cameras
    would). ``frame_loop``: "wrap" (after the last frame the first again: the camera jumps, and
    every session that wraps relocalizes) or "pingpong" (forwards, then backwards: no jump)."""
    from sfmloc_client import CameraSpec, FrameStreamer, PoseSubscriber

    from ..server.sessions import TIMELINE_ENV
    from .scale import threads_of

    spec = CameraSpec.parse(inp.camera)
    timeline = bool(os.environ.get(TIMELINE_ENV))  # the server records one too (its env)
    n_frames = int(rate * duration)
    loaded = inp.jpeg if encoding == "jpeg" else [g.tobytes() for g in inp.gray]
    frames = [loaded[j] for j in loop_order(len(loaded), frame_loop)]
    phase_of(0, clients, phases)  # a bad value fails here, before the server starts
    results: list[dict[str, Any]] = [{} for _ in range(clients)]
    load0 = os.getloadavg()[0]
    extra: tuple[str, ...] = ("--max-pending", str(max_pending))
    if reloc_workers is not None:
        extra += ("--relocalize-workers", str(reloc_workers))
    reloc: dict[str, Any] = {"rate_hz": reloc_rate, "workers": reloc_workers}
    with ServerProcess(inp.maps, workers=workers, kind=kind, extra_args=extra) as srv:
        pids = {
            "server": [srv.proc.pid],
            "workers": _child_pids(srv.proc.pid),
            "clients": [os.getpid()],
        }
        start: dict[str, Any] = {}

        def streams_start() -> None:
            # The CPU counts from here (every client warmed up: its first frame, which
            # relocalizes, is not a pose of the measurement), to the CPU of the poses counted.
            start["cpu"] = {k: sum(_cpu_seconds(p) for p in v) for k, v in pids.items()}
            start["threads"] = threads_of(pids["server"] + pids["workers"])
            start["t"] = time.perf_counter()

        barrier = threading.Barrier(clients + (1 if reloc_rate > 0 else 0), action=streams_start)
        stop_reloc = threading.Event()

        def relocalizer() -> None:
            barrier.wait()
            _relocalize_load(srv.grpc, inp, spec, reloc_rate, stop_reloc, reloc)

        def client(i: int) -> None:
            cid = f"bench-client-{i}"
            sent_at: dict[int, float] = {}
            lat: list[float] = []
            server_lat: list[float] = []
            engine: list[float] = []
            engine_cpu: list[float] = []  # the engine's CPU per pose (engine_cpu_ms)
            last: dict[str, Any] = {"dropped": 0, "errors": 0, "received": 0}
            statuses: dict[str, int] = {}  # of the poses without error
            # ... of the frames sent after the stream's first second: the start is a burst
            # (every client's first measured frame comes past the engine's frame gap after the
            # warm-up barrier, so every session relocalizes at once); these show what follows.
            settled: dict[str, int] = {}
            codes: dict[str, int] = {}  # error answers by code (DEADLINE_EXCEEDED, ...)
            # Poses by the frames since the client's previous pose (1: none dropped between):
            # bucket -> [poses, engine CPU ms summed]. The engine's CPU per pose grows with the
            # gap (motion since the last pose), so this says why a loaded server's CPU per pose
            # rises (throughput.gap_rows).
            gaps: dict[str, list[float]] = {}
            prev = [0]  # seq of the previous pose (the warm-up frame is seq 0)
            lock = threading.Lock()
            # Every answer as it came (perf_counter, the server's clock on this machine), for
            # the server's timeline (``sessions.TIMELINE_ENV``); None when that is off.
            answers: list[tuple[Any, ...]] | None = [] if timeline else None

            def on_pose(p: Any) -> None:
                now = time.perf_counter()
                with lock:
                    if answers is not None:
                        answers.append(
                            (
                                p.seq,
                                now,
                                p.status,
                                p.matching,
                                p.engine_ms,
                                p.engine_cpu_ms,
                                p.latency_ms,
                                None if p.error is None else p.error.code,
                            )
                        )
                    last["received"] += 1  # answers: those with an error carry no pose
                    last["dropped"] = max(last["dropped"], p.dropped)
                    last["errors"] += p.error is not None
                    if p.error is not None:  # e.g. DEADLINE_EXCEEDED: the server was overloaded
                        codes[p.error.code] = codes.get(p.error.code, 0) + 1
                    else:
                        statuses[p.status] = statuses.get(p.status, 0) + 1
                        if p.seq is not None and p.seq > rate:
                            settled[p.status] = settled.get(p.status, 0) + 1
                        if p.seq is not None and p.seq > prev[0]:
                            g = gaps.setdefault(gap_bucket(p.seq - prev[0]), [0, 0.0])
                            g[0] += 1
                            g[1] += p.engine_cpu_ms
                            prev[0] = p.seq
                    if p.seq in sent_at:
                        lat.append((now - sent_at[p.seq]) * 1e3)
                        server_lat.append(p.latency_ms)
                        engine.append(p.engine_ms)
                        if p.error is None:
                            engine_cpu.append(p.engine_cpu_ms)

            offset = (i * len(frames)) // clients
            phase = phase_of(i, clients, phases)
            with (
                _zenoh(srv.endpoint) as z,
                PoseSubscriber(z, inp.map_name, cid, callback=on_pose) as poses,
                FrameStreamer(z, inp.map_name, cid, spec) as fs,
            ):
                fs.wait_for_server(30)
                # Warm-up: the first frame relocalizes; the measurement starts tracking.
                fs.publish(data=frames[offset], encoding=encoding, seq=0)
                poses.wait_for(0, 30)
                with lock:
                    last.update(received=0, dropped=0, errors=0)
                    statuses.clear()
                    codes.clear()
                    gaps.clear()
                    prev[0] = 0
                base_dropped = poses.last.dropped if poses.last else 0
                barrier.wait()
                t_start = time.perf_counter()
                for k in range(1, n_frames + 1):
                    t_due = t_start + (k - 1 + phase) / rate
                    delay = t_due - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                    data = frames[(offset + k) % len(frames)]
                    with lock:
                        sent_at[k] = time.perf_counter()
                    fs.publish(data=data, encoding=encoding, seq=k)
                poses.wait_for(n_frames, 10)
                elapsed = time.perf_counter() - t_start
            with lock:
                received = last["received"]
                results[i] = {
                    "client": cid,
                    "sent": n_frames,
                    "received": received,
                    "dropped_by_server": last["dropped"] - base_dropped,
                    "lost": n_frames - received,
                    "drop_pct": 100.0 * (n_frames - received) / n_frames,
                    "errors": last["errors"],
                    "error_codes": dict(codes),
                    "rate_hz": n_frames / elapsed,
                    "latency_ms_p50": _pct(lat, 50),
                    "latency_ms_p99": _pct(lat, 99),
                    "server_latency_ms_p50": _pct(server_lat, 50),
                    "server_latency_ms_p99": _pct(server_lat, 99),
                    "engine_ms_p50": _pct(engine, 50),
                    "engine_ms_mean": float(np.mean(engine)) if engine else float("nan"),
                    "engine_cpu_ms_sum": float(np.sum(engine_cpu)),
                    "engine_cpu_poses": len(engine_cpu),
                    "localized": sum(1 for _ in engine),
                    "statuses": dict(statuses),
                    "statuses_after_1s": dict(settled),
                    "gaps": {k: list(v) for k, v in gaps.items()},
                }
                if answers is not None:
                    results[i]["timeline"] = {"sent": sent_at, "answers": answers}

        threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
        reloc_thread = threading.Thread(target=relocalizer) if reloc_rate > 0 else None
        for t in threads + ([reloc_thread] if reloc_thread else []):
            t.start()
        for t in threads:
            t.join()
        stop_reloc.set()
        if reloc_thread:
            reloc_thread.join()
        # From the streams' start to the last answer (or a client's 10 s wait for it): the
        # CPU of every pose the clients count, over the time it took. (It counted from before
        # the warm-up over the whole run's wall, and per pose was divided by the rate over the
        # send time: under overload, with clients waiting for answers that never came, the CPU
        # per pose came out at a fraction of what it was.)
        wall = time.perf_counter() - start["t"]
        cpu_s = {k: sum(_cpu_seconds(p) for p in v) - start["cpu"][k] for k, v in pids.items()}
        cores = {k: v / wall for k, v in cpu_s.items()}
        # Per thread kind of the server and its workers, over the same window: which thread
        # the server's CPU beyond the engine is spent on (intake, results, Zenoh, workers).
        by_thread = {"start": start["threads"], "end": threads_of(pids["server"] + pids["workers"])}
    return {
        "workers": workers,
        "kind": kind,
        "encoding": encoding,
        "clients": results,
        "load_before": load0,
        "load_after": os.getloadavg()[0],
        "cores_used": cores,
        "cpu_seconds": cpu_s,
        "threads": by_thread,
        "relocalize": reloc,
    }


# Buckets of the frames between a client's two poses (1: consecutive frames), which the
# throughput rows report. The engine's CPU per frame against the gap (one Localizer fed every
# k-th redkitchen frame, nice 19, load ~11): flat up to k = 4 (10-11.6 ms), x1.35 at 5-6, x2.1
# at 8, x5 at 12 (more motion to bridge: guided matching, relocalizations).
GAP_BUCKETS = ("1", "2", "3", "4-7", "8+")


def gap_bucket(frames: int) -> str:
    """The ``GAP_BUCKETS`` bucket of a pose that came ``frames`` frames after the previous."""
    return str(frames) if frames <= 3 else ("4-7" if frames <= 7 else "8+")


# ============================================================================ memory
def _smaps_rollup(pid: int) -> dict[str, int]:
    """Resident memory of a process in kB (Linux): Rss, Pss (shared pages divided among the
    processes that map them), Anonymous (private heap: what a copy per process costs)."""
    out: dict[str, int] = {}
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                parts = line.split()
                if len(parts) == 3 and parts[2] == "kB":
                    out[parts[0].rstrip(":")] = int(parts[1])
    except OSError:
        pass
    return out


def _mapped_kb(pid: int, fragment: str) -> int:
    """Resident kB of the file mappings of ``pid`` whose path contains ``fragment``."""
    total, hit = 0, False
    try:
        with open(f"/proc/{pid}/smaps") as f:
            for line in f:
                parts = line.split()
                if parts and "-" in parts[0] and len(parts) >= 5:  # a mapping's header line
                    hit = len(parts) >= 6 and fragment in parts[-1]
                elif hit and parts and parts[0] == "Rss:":
                    total += int(parts[1])
    except OSError:
        pass
    return total


def bench_memory(
    inp: BenchInput,
    workers_list: tuple[int, ...] = (1, 2, 4),
    frames: int = 30,
    env: dict[str, str] | None = None,
) -> dict[str, Any]:
    """Resident memory of the server and its workers with the map loaded and one session per
    worker that has streamed ``frames`` frames (every worker has searched the index)."""
    from sfmloc_client import CameraSpec, FrameStreamer, PoseSubscriber

    spec = CameraSpec.parse(inp.camera)
    out: dict[str, Any] = {"frames_per_session": frames, "runs": []}
    for w in workers_list:
        with ServerProcess(inp.maps, workers=w, env=env) as srv, _zenoh(srv.endpoint) as z:
            for i in range(w):  # sessions go to the least busy worker: one each
                cid = f"bench-memory-{i}"
                with (
                    PoseSubscriber(z, inp.map_name, cid) as poses,
                    FrameStreamer(z, inp.map_name, cid, spec) as fs,
                ):
                    fs.wait_for_server(30)
                    for k in range(frames):
                        data = inp.jpeg[(i * 97 + k) % len(inp.jpeg)]
                        fs.publish(data=data, encoding="jpeg", seq=k)
                        poses.wait_for(k, 30)
            workers = _child_pids(srv.proc.pid)
            procs = {"server": srv.proc.pid, **{f"worker{j}": p for j, p in enumerate(workers)}}
            rows = {}
            for name, pid in procs.items():
                r = _smaps_rollup(pid)
                rows[name] = {
                    "rss_kb": r.get("Rss", 0),
                    "pss_kb": r.get("Pss", 0),
                    "anon_kb": r.get("Anonymous", 0),
                    # Pages this process alone maps (Anonymous also counts pages a forked
                    # worker still shares with its siblings).
                    "private_kb": r.get("Private_Clean", 0) + r.get("Private_Dirty", 0),
                    "index_file_kb": _mapped_kb(pid, "index_faiss"),
                }
            total = {
                k: sum(r[k] for r in rows.values())
                for k in ("rss_kb", "pss_kb", "anon_kb", "private_kb")
            }
            out["runs"].append({"workers": w, "processes": rows, "total": total})
    return out


# ============================================================================ engine scaling
def _engine_job(
    maps: str, map_name: str, frames: list[str], camera: str, start_at: float = 0.0
) -> tuple[float, float, list[float]]:
    """Localize ``frames`` in sequence (one Localizer): (start, end) wall times and per-frame
    engine milliseconds. Runs in a worker thread or process; all start at ``start_at`` (wall
    time), after their imports and loading."""
    pin_threads_env()
    import cv2

    from ..cameras import Camera
    from ..engine import Localizer
    from ..io.frames import read_image
    from ..map.bundle import MapBundle

    pin_threads_runtime()
    loc = Localizer(MapBundle(Path(maps) / map_name, verify=False), Camera.parse(camera))
    imgs = [read_image(f, cv2.IMREAD_GRAYSCALE) for f in frames]
    loc.localize(imgs[0], 0.0)  # the first frame relocalizes: not part of the steady state
    time.sleep(max(0.0, start_at - time.time()))
    lat = []
    t0 = time.time()
    for k, img in enumerate(imgs[1:], 1):
        t = time.perf_counter()
        loc.localize(img, k / 30.0)
        lat.append((time.perf_counter() - t) * 1e3)
    return t0, time.time(), lat


def bench_engine(inp: BenchInput, parallel: int, n: int, repeat: int = 3) -> dict[str, Any]:
    """``parallel`` Localizers flat out on their own frame sequences: one alone, then in
    threads, then in processes; aggregate frames/s shows what the GIL costs. Each mode runs
    ``repeat`` times, interleaved, and keeps its best run: other processes on the machine only
    ever slow a run down, so the best run is the least disturbed one."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

    step = max(1, len(inp.frames) // parallel)
    jobs = [[str(p) for p in (inp.frames[i * step :] + inp.frames)[:n]] for i in range(parallel)]
    args = (str(inp.maps), inp.map_name)
    best: dict[str, tuple[float, float]] = {}  # mode -> (frames/s, p50 ms)
    runs: dict[str, list[float]] = {"single": [], "thread": [], "process": []}
    for _ in range(repeat):
        t0, t1, lat = _engine_job(*args, jobs[0], inp.camera)
        runs["single"].append(len(lat) / (t1 - t0))
        if runs["single"][-1] >= best.get("single", (0.0, 0.0))[0]:
            best["single"] = (runs["single"][-1], _pct(lat, 50))
        for kind in ("thread", "process"):
            if kind == "thread":
                ex: Any = ThreadPoolExecutor(parallel)
                start_at = time.time() + 1.0
            else:
                ex = ProcessPoolExecutor(parallel, mp_context=mp.get_context("spawn"))
                start_at = time.time() + 8.0  # time for the processes to import and load
            with ex:
                res = list(
                    ex.map(_engine_job, *zip(*[(*args, j, inp.camera, start_at) for j in jobs]))
                )
            start, end = min(r[0] for r in res), max(r[1] for r in res)
            lats = [x for r in res for x in r[2]]
            fps = len(lats) / (end - start)
            runs[kind].append(fps)
            if fps >= best.get(kind, (0.0, 0.0))[0]:
                best[kind] = (fps, _pct(lats, 50))
    out: dict[str, Any] = {
        "parallel": parallel,
        "frames_each": n - 1,
        "repeat": repeat,
        "runs_fps": runs,
    }
    for mode, (fps, p50) in best.items():
        out[f"{mode}_fps"], out[f"{mode}_ms_p50"] = fps, p50
    for kind in ("thread", "process"):
        out[f"{kind}_speedup"] = out[f"{kind}_fps"] / out["single_fps"]
    return out


# ============================================================================ report
def _print_table(title: str, rows: list[tuple[str, str]]) -> None:
    print(f"\n== {title}")
    w = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"  {k:<{w}}  {v}")


def run(args: Any) -> int:
    from ..cameras import Camera
    from ..errors import InputError

    frames_dir = Path(args.frames)
    if not frames_dir.is_dir():
        raise InputError(f"frames folder {frames_dir} does not exist (--frames)")
    frames = sorted(p for p in frames_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
    if not frames:
        raise InputError(f"no JPEG frames in {frames_dir}")
    maps = Path(args.maps)
    if not (maps / args.map / "manifest.json").is_file():
        raise InputError(
            f"no map bundle {maps / args.map} (--maps DIR --map NAME; build one with `sfmloc "
            "build`)"
        )
    Camera.parse(args.camera)
    inp = BenchInput(maps, args.map, frames, args.camera)
    every = {"wire", "overhead", "engine", "clients", "workers", "memory"}
    only = set(args.only.split(",")) if args.only else every
    inp.load(
        max(args.n, int(args.rate * args.duration) + 10)
        if only & {"clients", "workers"}
        else args.n
    )
    report: dict[str, Any] = {"load_average": os.getloadavg(), "cpus": os.cpu_count()}
    print(
        f"sfmloc bench-transport: {len(inp.jpeg)} frames of {frames_dir}, map {maps / args.map}, "
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}"
    )
    if "wire" in only:
        w = report["wire"] = bench_wire(inp, n=min(300, args.n * 2))
        rows = []
        for enc in ("gray8", "jpeg"):
            rows += [
                (f"{enc} frame", f"{w[f'{enc}_bytes']} bytes"),
                (
                    f"{enc} envelope encode+decode",
                    f"{w[f'{enc}_envelope_codec_us_p50']:.1f} us p50",
                ),
                (
                    f"{enc} attachment encode+decode",
                    f"{w[f'{enc}_attachment_codec_us_p50']:.1f} us p50",
                ),
                (
                    f"{enc} loopback envelope",
                    f"{w[f'{enc}_envelope_loopback_ms_p50']:.3f} ms p50, "
                    f"{w[f'{enc}_envelope_loopback_ms_p99']:.3f} p99",
                ),
                (
                    f"{enc} loopback attachment",
                    f"{w[f'{enc}_attachment_loopback_ms_p50']:.3f} ms p50, "
                    f"{w[f'{enc}_attachment_loopback_ms_p99']:.3f} p99",
                ),
            ]
        _print_table("wire: envelope vs attachment (publish -> decoded in the subscriber)", rows)
    if "overhead" in only:
        o = report["overhead"] = bench_overhead(inp, args.n)
        rows = [
            (
                "in-process engine",
                f"{o['inprocess_engine_ms_p50']:.2f} ms p50, {o['inprocess_engine_ms_p99']:.2f} "
                "p99",
            )
        ]
        for enc in ("gray8", "jpeg"):
            rows += [
                (
                    f"{enc} end to end (publish -> pose)",
                    f"{o[f'{enc}_e2e_ms_p50']:.2f} ms p50, {o[f'{enc}_e2e_ms_p99']:.2f} p99",
                ),
                (f"{enc} engine in the server", f"{o[f'{enc}_server_engine_ms_p50']:.2f} ms p50"),
                (
                    f"{enc} overhead per frame (e2e - engine)",
                    f"{o[f'{enc}_overhead_ms_p50']:.2f} ms p50, {o[f'{enc}_overhead_ms_p90']:.2f} "
                    "p90",
                ),
                (
                    f"{enc} e2e p50 - in-process p50",
                    f"{o[f'{enc}_e2e_minus_inprocess_p50_ms']:.2f} ms",
                ),
                (
                    f"{enc} server CPU per frame (process + workers)",
                    f"{o[f'{enc}_server_cpu_ms_per_frame']:.2f} ms, engine "
                    f"{o[f'{enc}_engine_cpu_ms_mean']:.2f}, beyond the engine "
                    f"{o[f'{enc}_cpu_beyond_engine_ms']:.2f}",
                ),
            ]
        _print_table(
            f"overhead: Zenoh loopback vs in-process engine ({args.n} frames, lockstep, 1 worker)",
            rows,
        )
    if "engine" in only:
        e = report["engine"] = bench_engine(
            inp, args.workers or (os.cpu_count() or 1), args.n, args.repeat
        )
        rows = [("1 Localizer", f"{e['single_fps']:.1f} frames/s, {e['single_ms_p50']:.1f} ms p50")]
        for kind, kinds in (("thread", "threads"), ("process", "processes")):
            rows.append(
                (
                    f"{e['parallel']} Localizers in {kinds}",
                    f"{e[f'{kind}_fps']:.1f} frames/s ({e[f'{kind}_speedup']:.2f}x), "
                    f"{e[f'{kind}_ms_p50']:.1f} ms p50 per frame",
                )
            )
        rows.append(
            (
                "all runs (frames/s)",
                "; ".join(
                    f"{k} " + ", ".join(f"{v:.0f}" for v in vs) for k, vs in e["runs_fps"].items()
                ),
            )
        )
        _print_table(
            f"engine scaling: Localizers flat out, {e['frames_each']} frames each, best of "
            f"{e['repeat']} (no transport)",
            rows,
        )
    lanes: list[int | None] = [None]
    if args.relocalize_workers:
        lanes = [int(v) for v in args.relocalize_workers.split(",")]
    sections = (("clients", "process"), ("workers", "thread"))
    runs = [
        (section, kind, lane) for section, kind in sections if section in only for lane in lanes
    ]
    for section, kind, lane in runs:
        c = bench_clients(
            inp,
            args.clients,
            args.rate,
            args.duration,
            args.workers or (os.cpu_count() or 1),
            kind,
            args.encoding,
            args.max_pending,
            args.relocalize_rate,
            lane,
        )
        report[section if len(lanes) == 1 else f"{section}-relocalize-workers-{lane}"] = c
        rows = []
        for r in c["clients"]:
            rows.append(
                (
                    r["client"],
                    f"sent {r['sent']} poses {r['received']} dropped {r['drop_pct']:.2f}% "
                    f"({r['dropped_by_server']} stale) errors {r['errors']}  latency p50 "
                    f"{r['latency_ms_p50']:.1f} ms p99 {r['latency_ms_p99']:.1f} ms  "
                    f"(server p50 {r['server_latency_ms_p50']:.1f} p99 "
                    f"{r['server_latency_ms_p99']:.1f}, "
                    f"engine p50 {r['engine_ms_p50']:.1f} mean {r['engine_ms_mean']:.1f})",
                )
            )
        worst = max(r["drop_pct"] for r in c["clients"])
        rows.append(
            (
                "worst drop",
                f"{worst:.2f}%  (load average {c['load_before']:.2f} -> {c['load_after']:.2f})",
            )
        )
        cu = c["cores_used"]
        rows.append(
            (
                "CPU (cores)",
                f"server main process {cu['server']:.2f}, workers {cu['workers']:.2f}, "
                f"clients (this process) {cu['clients']:.2f}",
            )
        )
        rl = c["relocalize"]
        if args.relocalize_rate > 0:
            nan = float("nan")
            rows.append(
                (
                    "Relocalize beside them",
                    f"{rl.get('calls', 0)} calls at {args.relocalize_rate:g} Hz, p50 "
                    f"{rl.get('ms_p50', nan):.0f} ms p99 {rl.get('ms_p99', nan):.0f} ms, "
                    f"errors {rl.get('errors', 0)}",
                )
            )
        lane_s = "" if lane is None else f", relocalize workers {lane}"
        _print_table(
            f"{args.clients} clients x {args.rate:g} Hz x {args.duration:g} s, {args.encoding} "
            "frames, "
            f"{c['workers']} {kind} workers{lane_s}, max pending {args.max_pending}",
            rows,
        )
    if "memory" in only:
        m = report["memory"] = bench_memory(inp)
        rows = []
        for r in m["runs"]:
            t = r["total"]
            wk = [v for k, v in r["processes"].items() if k.startswith("worker")]
            pss = ", ".join(f"{v['pss_kb'] / 1024:.0f}" for v in wk)
            index = ", ".join(f"{v['index_file_kb'] / 1024:.1f}" for v in wk)
            rows.append(
                (
                    f"{r['workers']} worker(s)",
                    f"total RSS {t['rss_kb'] / 1024:.0f} MB, PSS {t['pss_kb'] / 1024:.0f} MB, "
                    f"anonymous {t['anon_kb'] / 1024:.0f} MB; per worker PSS {pss} MB, "
                    f"index file resident {index} MB",
                )
            )
        _print_table(
            "memory: server + workers, map loaded, one session per worker "
            f"({m['frames_per_session']} frames each)",
            rows,
        )
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2, default=float))
        print(f"\nwrote {args.json}")
    return 0
