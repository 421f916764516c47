"""The ``scale`` bench (issue 14): several ``sfmloc serve`` processes hosting one map on one
Zenoh network, clients with ``server="auto"`` (one owner per session, placement.py).

Parts, each with real server processes on loopback (peer mode, no multicast; every server
connects to the ones started before it, clients to all):

- ``alone``: each server by itself with the clients it owns in ``together``, in lockstep (next
  frame when the previous pose is back): the poses per second one server delivers.
- ``together``: all servers and all clients in lockstep: total poses per second against the
  sum of ``alone``, every frame answered exactly once (duplicates counted), how the clients
  spread over the servers.
- ``kill``: all servers, clients paced at ``--rate``; one server (the owner of the most
  clients) gets SIGKILL: for its clients the time from the kill to their next answer, and
  duplicates, and clients left without answers at the end.

- ``submaps`` (in process, no server): a map ``--ratio`` times the memory budget (synthetic
  rooms joined into one bundle, split into sub-maps) walked through by one camera with
  ``SubmapLocalizer``, against a whole-map ``Localizer`` on the same frames (``submaps.py``).

The map and frames of the server parts are reliability.py's synthetic room (exact ground truth:
wrong poses are counted too). CPU-bound servers on a small machine: with ``--pin`` (default)
server ``i`` and its workers run on core ``i mod cores`` in alone and together, so "alone" is
what its core delivers; ``together_vs_core_share`` divides each server's rate alone by the
number of servers on its core (3 servers on 2 cores: two share one) and is the issue's "within
10% of the sum of what the servers deliver alone"; ``together_vs_sum_alone`` is the plain
ratio. The ``kill`` part is not pinned: the survivors may use the killed server's core.

Like with like: in both parts the window starts once every client has had ``--warmup-frames``
answers (sessions' first frames cost more), and lockstep frames carry the clip's own clock
(``--stamps video``): stamped when sent, slower servers looked like a faster camera to the
engine (more global matching per pose, the more so the busier the machine).

The clients are threads of this process (each its own Zenoh session) and cost CPU too (1.5-2 ms
per pose: frames out, poses in, each pose checked against the ground truth). With
``--client-core`` (default, 2+ cores) this process runs on the last core in alone and together
and the servers share the others, so that both parts give the servers the same cores; without
it the clients took a free core in alone but the servers' cores together (the comparison was
not like with like). Each part reports the CPU of every server (its process and workers), of
the clients and of the rest of the machine (other people's processes) over the measured
window, per answered pose: ``servers_cpu_per_pose_together_vs_alone`` (near 1: several servers
on one network cost no more per pose than one) holds on a busy machine, where rates do not.

Same frames (``--same-frames``, 60): a time window covers more of the clip alone (faster)
than together, and the clip's frames differ in cost (guided matching ~21 ms of CPU, tracking
alone ~14 ms), so before the timed window every client is held, then all run their next 60
frames and are held again: the servers' CPU and the wall time for exactly these frames of the
same sessions, alone and together (``same_frames``: ``servers_cpu_per_pose_together_vs_alone``
and ``time_alone_sum_vs_together``, the alone runs' times added up against together's, on the
cores they share: the issue's target on equal work and equal cores).

    python -m sfmloc.bench.scale --work /tmp/scale [--servers 3 --clients 12 --seconds 15]
    python -m sfmloc.bench.scale --work /tmp/scale --parts submaps --rooms 8 --ratio 10
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from .reliability import StreamClient, World, _log, _totals, prepare

# Lockstep parts hold clients for the same-frames phase's slowest (minutes under load): a held
# session must not expire (30 s by default), or it restarts, with its global matching, inside
# the phase.
HELD_IDLE_TIMEOUT_S = 600.0


def server_args(
    sid: str,
    endpoints: list[str],
    wait_budget: bool = True,
    idle_timeout_s: float | None = HELD_IDLE_TIMEOUT_S,
) -> tuple[str, ...]:
    """``sfmloc serve`` options of bench server ``sid``, connected to ``endpoints``.
    ``idle_timeout_s`` None: the server's default (the kill part: paced clients, never held,
    measured as deployed)."""
    extra: tuple[str, ...] = ("--server-id", sid)
    if idle_timeout_s is not None:
        extra += ("--idle-timeout", f"{idle_timeout_s:g}")
    if not wait_budget:
        # Lockstep parts: no frame is answered DEADLINE_EXCEEDED for waiting. 12 sessions
        # starting at once (~220 ms CPU each for frame 0) on one shared core waited past the
        # 2 s budget together, never alone: those sessions then began at a later frame, and the
        # engine's work on the same later frames differed (same frames 10-69 of every client:
        # 192 guided matchings alone, 248 together)
        extra += ("--frame-budget-ms", "0")
    for ep in endpoints:
        extra += ("--zenoh-connect", ep)
    return extra


class Servers:
    """``n`` ``sfmloc serve`` processes (``s0``, ``s1``, ...) chained on loopback."""

    def __init__(
        self,
        world: World,
        ids: list[str],
        workers: int,
        cpus: dict[str, set[int]] | None = None,
        wait_budget: bool = True,
        idle_timeout_s: float | None = HELD_IDLE_TIMEOUT_S,
    ) -> None:
        from ..testing import ServerProcess

        self.procs: dict[str, Any] = {}
        endpoints: list[str] = []
        for sid in ids:
            sp = ServerProcess(
                world.maps_dir,
                workers=workers,
                extra_args=server_args(sid, endpoints, wait_budget, idle_timeout_s),
                cpus=(cpus or {}).get(sid),
            )
            self.procs[sid] = sp
            endpoints.append(sp.endpoint)
        self.endpoints = endpoints

    def __enter__(self) -> Servers:
        for sp in self.procs.values():
            sp.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        for sp in self.procs.values():
            sp.stop(30)


def _clients(
    world: World,
    endpoints: list[str],
    ids: list[str],
    stop: threading.Event,
    rate_hz: float | None,
    stamp_hz: float | None = None,
    holds: dict[int, threading.Event] | None = None,
) -> list[StreamClient]:
    cl = [
        StreamClient(
            world,
            endpoints[0],
            cid,
            stop,
            rate_hz=rate_hz,
            server="auto",
            more_endpoints=tuple(endpoints[1:]),
            stamp_hz=stamp_hz,
            holds=holds,
        )
        for cid in ids
    ]
    for c in cl:
        c.start()
    for c in cl:
        c.ready.wait(60)
    return cl


def _machine_cpu_s() -> float:
    """Busy CPU seconds of the whole machine so far (every process, /proc/stat)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    idle = v[3] + (v[4] if len(v) > 4 else 0)  # idle + iowait
    return (sum(v[:8]) - idle) / os.sysconf("SC_CLK_TCK")


class CpuMeter:
    """CPU seconds over the measured window of each server (its process and every descendant:
    zygote, workers), of this process (the benchmark's clients: their threads and Zenoh
    sessions) and of the whole machine (the rest is other people's processes)."""

    def __init__(self, servers: dict[str, Any]) -> None:
        from .transport import _child_pids

        self.groups = {sid: [sp.proc.pid, *_child_pids(sp.proc.pid)] for sid, sp in servers.items()}
        self.groups["clients"] = [os.getpid()]

    def sample(self) -> dict[str, float]:
        from .transport import _cpu_seconds

        out = {k: sum(_cpu_seconds(p) for p in pids) for k, pids in self.groups.items()}
        out["machine"] = _machine_cpu_s()
        return out

    def threads(self) -> dict[str, dict[str, float]]:
        """Per thread kind of the servers (summed over servers): CPU seconds and voluntary /
        involuntary context switches so far, keyed by process name / thread name (workers,
        zygote, the server's Zenoh runtime threads, pumps ...): where the servers' CPU goes."""
        return threads_of(p for k, pids in self.groups.items() if k != "clients" for p in pids)


def threads_of(pids: Iterable[int]) -> dict[str, dict[str, float]]:
    """``_thread_rows`` of every process in ``pids``, summed per thread kind."""
    out: dict[str, dict[str, float]] = {}
    for pid in pids:
        for key, row in _thread_rows(pid).items():
            acc = out.setdefault(key, {"cpu_s": 0.0, "vcs": 0.0, "ivcs": 0.0, "n": 0})
            for f in ("cpu_s", "vcs", "ivcs", "n"):
                acc[f] += row[f]
    return out


def _thread_rows(pid: int) -> dict[str, dict[str, float]]:
    """``{"process/thread": {cpu_s, vcs, ivcs, n}}`` of every thread of ``pid`` (Linux /proc;
    empty once it is gone). Thread names are grouped without their trailing digits."""
    import re

    tck = os.sysconf("SC_CLK_TCK")
    rows: dict[str, dict[str, float]] = {}
    try:
        with open(f"/proc/{pid}/comm") as f:
            pname = f.read().strip()
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return rows
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                head, rest = f.read().rsplit(")", 1)
            tname = head.split("(", 1)[1]
            fields = rest.split()
            cpu = (int(fields[11]) + int(fields[12])) / tck
            vcs = ivcs = 0
            with open(f"/proc/{pid}/task/{tid}/status") as f:
                for line in f:
                    if line.startswith("voluntary_ctxt_switches"):
                        vcs = int(line.split()[1])
                    elif line.startswith("nonvoluntary_ctxt_switches"):
                        ivcs = int(line.split()[1])
        except (OSError, ValueError, IndexError):
            continue
        key = f"{pname}/{re.sub(r'[-_ ]?[0-9]+$', '', tname)}"
        acc = rows.setdefault(key, {"cpu_s": 0.0, "vcs": 0.0, "ivcs": 0.0, "n": 0})
        acc["cpu_s"] += cpu
        acc["vcs"] += vcs
        acc["ivcs"] += ivcs
        acc["n"] += 1
    return rows


def thread_rows_delta(
    t0: dict[str, dict[str, float]], t1: dict[str, dict[str, float]], poses: int
) -> dict[str, dict[str, float]]:
    """Per thread kind between two ``CpuMeter.threads`` samples, per answered pose: CPU ms and
    context switches (voluntary: it waited; involuntary: it was preempted)."""
    out = {}
    for key, b in t1.items():
        a = t0.get(key, {"cpu_s": 0.0, "vcs": 0.0, "ivcs": 0.0})
        n = max(1, poses)
        out[key] = {
            "threads": int(b["n"]),
            "cpu_ms_per_pose": round(1e3 * (b["cpu_s"] - a["cpu_s"]) / n, 3),
            "vcs_per_pose": round((b["vcs"] - a["vcs"]) / n, 2),
            "ivcs_per_pose": round((b["ivcs"] - a["ivcs"]) / n, 2),
        }
    return dict(sorted(out.items(), key=lambda kv: -kv[1]["cpu_ms_per_pose"]))


def cpu_rows(c0: dict[str, float], c1: dict[str, float], dt: float, poses: int) -> dict:
    """Cores used (CPU s per s) and CPU ms per answered pose of each part between two
    ``CpuMeter`` samples; ``servers`` sums the servers, ``other`` is the machine's rest."""
    used = {k: (c1[k] - c0[k]) / dt for k in c0}
    servers = sum(v for k, v in used.items() if k not in ("clients", "machine"))
    used["servers"] = servers
    used["other"] = max(0.0, used["machine"] - servers - used["clients"])
    per = {k: 1e3 * v * dt / poses if poses else float("nan") for k, v in used.items()}
    return {"cores_used": used, "cpu_ms_per_pose": per}


# The measured window starts once every client has had this many answers (and warmup_s has
# passed): a session's first frames cost more than its steady state (synthetic room, engine in
# process, CPU ms: frame 0 ~220 with global matching, frames 1-7 23-27, from frame 8 on ~17;
# about 220 ms extra per session). A warm-up in seconds alone covered ~22 frames per client
# alone (one server on the core, 4 clients) but ~5 together (three servers on that core, 12
# clients): the start-up of every together session fell inside its window, none of alone's.
WARMUP_FRAMES = 10
# Frames of every client in the same-frames phase (after the warm-up): half the clip's
# ping-pong period (118), ~700 poses for 12 clients.
SAME_FRAMES = 60


def wait_warm(cl: list[StreamClient], frames: int, timeout: float) -> float:
    """Wait until every client has ``frames`` answers (or ``timeout`` s); the seconds waited."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if all(len(c.log.answered) >= frames or not c.is_alive() for c in cl):
            break
        time.sleep(0.05)
    return time.monotonic() - t0


def same_frame_holds(warmup_frames: int, same_frames: int) -> dict[int, threading.Event]:
    """The clients' holds of the same-frames phase: every client waits before frame
    ``warmup_frames`` and before ``warmup_frames + same_frames`` (none: ``same_frames`` 0)."""
    if same_frames <= 0:
        return {}
    return {warmup_frames: threading.Event(), warmup_frames + same_frames: threading.Event()}


def wait_held(cl: list[StreamClient], seq: int, timeout: float) -> bool:
    """Wait until every client (still running) waits at its hold before ``seq``."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if all(c.held == seq or not c.is_alive() for c in cl):
            return True
        time.sleep(0.02)
    return False


def same_frames_phase(
    cl: list[StreamClient],
    holds: dict[int, threading.Event],
    meter: CpuMeter,
    timeout: float,
) -> dict:
    """Every client's frames ``a .. b-1`` (the two holds), each client starting at ``a`` at
    once: the servers' CPU and the wall time for exactly these frames. The same frames of the
    same sessions (the engine's work per frame depends on the frame and the session's history,
    not on the timing: video stamps), so alone and together do the same work; a time window
    instead covers more of the clip alone (faster) than together, and the clip's frames differ
    in cost (guided matching ~21 ms, tracking alone ~14 ms of CPU: in one run the window's
    poses were 25% guided alone, 43% together)."""
    a, b = sorted(holds)
    reached_a = wait_held(cl, a, timeout)
    c0, t0 = meter.sample(), time.monotonic()
    holds[a].set()
    reached_b = wait_held(cl, b, timeout)
    t1, c1 = time.monotonic(), meter.sample()
    answered = sum(1 for c in cl for q in range(a, b) if q in c.log.answered)
    kinds: dict[str, int] = {}
    errors = 0
    for c in cl:
        for q in range(a, b):
            ans = c.log.answers.get(q) or {}
            k = str(ans.get("matching"))
            kinds[k] = kinds.get(k, 0) + 1
            errors += ans.get("error") is not None
    rows = cpu_rows(c0, c1, t1 - t0, answered)
    holds[b].set()
    return {
        "frames": [a, b],
        "complete": reached_a and reached_b,
        "expected": len(cl) * (b - a),
        "answered": answered,
        "errors": errors,
        "seconds": t1 - t0,
        "servers_cpu_s": rows["cores_used"]["servers"] * (t1 - t0),
        "servers_cpu_ms_per_pose": rows["cpu_ms_per_pose"]["servers"],
        "cores_used": rows["cores_used"],
        "matching": kinds,
    }


def _measure(
    cl: list[StreamClient],
    stop: threading.Event,
    warmup_s: float,
    seconds: float,
    meter: CpuMeter | None = None,
    warmup_frames: int = WARMUP_FRAMES,
    warmup_timeout: float = 300.0,
    holds: dict[int, threading.Event] | None = None,
):
    same = {}
    if holds and meter is not None:
        same = same_frames_phase(cl, holds, meter, warmup_timeout)
    elif holds:  # nothing to measure the phase with: the clients must not wait at its holds
        for ev in holds.values():
            ev.set()
    time.sleep(warmup_s)
    waited = wait_warm(cl, warmup_frames, warmup_timeout)
    c0 = meter.sample() if meter else None
    th0 = meter.threads() if meter else None
    t0 = time.monotonic()
    time.sleep(seconds)
    t1 = time.monotonic()
    c1 = meter.sample() if meter else None
    th1 = meter.threads() if meter else None
    stop.set()
    for c in cl:
        c.join(15)
    per = [c.summary(t0, t1) for c in cl]
    cpu = {}
    if c0 is not None and c1 is not None:
        # poses answered in the window (what the servers' CPU of the window produced)
        answered = sum(sum(1 for t in c.log.answered.values() if t0 <= t <= t1) for c in cl)
        cpu = {
            **cpu_rows(c0, c1, t1 - t0, answered),
            "answered_in_window": answered,
            "warmup_s": warmup_s + waited,
        }
        if th0 is not None and th1 is not None:
            cpu["server_threads"] = thread_rows_delta(th0, th1, answered)
        cpu["frames"] = frame_mix(cl, t0, t1)
    if same:
        cpu["same_frames"] = same
    return per, t1 - t0, cpu


def frame_mix(cl: list[StreamClient], t0: float, t1: float) -> dict:
    """What the engine did with the frames answered in [t0, t1] (how they were matched:
    GLOBAL is a relocalization, the costly kind) and the clients' frame intervals (send to
    send): their mean and coefficient of variation, what the engine sees of the camera's
    motion when frames are stamped when sent."""
    kinds: dict[str, int] = {}
    gaps: list[float] = []
    for c in cl:
        lg = c.log
        for q, t in lg.answered.items():
            if t0 <= t <= t1:
                k = str((lg.answers.get(q) or {}).get("matching"))
                kinds[k] = kinds.get(k, 0) + 1
        sent = sorted(t for t in lg.sent.values() if t0 <= t <= t1)
        gaps += [b - a for a, b in zip(sent, sent[1:])]
    g = np.array(gaps)
    return {
        "matching": kinds,
        "interval_ms_mean": float(1e3 * g.mean()) if g.size else None,
        "interval_cv": float(g.std() / g.mean()) if g.size and g.mean() > 0 else None,
    }


def pinning(ids: list[str], pin: bool, client_core: bool = False) -> dict[str, set[int]] | None:
    """Server ``i`` on core ``i mod cores`` (``pin``), else every server on every core. With
    ``client_core`` (and at least 2 cores) the last core is left to the clients
    (``client_cores``): the servers go round-robin over the others."""
    cores = sorted(os.sched_getaffinity(0))
    if client_core and len(cores) >= 2:
        cores = cores[:-1]
    return {sid: {cores[i % len(cores)]} for i, sid in enumerate(ids)} if pin else None


def client_cores(pin: bool, client_core: bool) -> set[int] | None:
    """The core this process (the benchmark's clients: their threads and Zenoh sessions) runs
    on in alone and together: the last one when it is left to them, else None (any core)."""
    cores = sorted(os.sched_getaffinity(0))
    return {cores[-1]} if pin and client_core and len(cores) >= 2 else None


def pin_process(cores: set[int]) -> None:
    """Every thread of this process on ``cores`` (``sched_setaffinity`` binds one thread; the
    threads a pinned thread starts inherit it, but Zenoh's runtime threads may exist already)."""
    for tid in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            os.sched_setaffinity(int(tid), cores)


def core_share(alone: list[dict], cpus: dict[str, set[int]] | None) -> float:
    """What the servers can deliver together given the cores each had: a server's rate alone
    divided by the number of servers pinned to its cores (unpinned: all share the machine)."""
    sharing = {
        r["server"]: (sum(c == cpus[r["server"]] for c in cpus.values()) if cpus else len(alone))
        for r in alone
    }
    return sum(r["poses_per_s"] / sharing[r["server"]] for r in alone)


def cpu_comparison(alone: list[dict], together: dict) -> dict:
    """The servers' and the clients' CPU per answered pose, alone (all alone runs together)
    and together: what a pose costs does not depend on what else runs on the machine, so
    ``servers_cpu_per_pose_together_vs_alone`` near 1 says that several servers on one network
    cost no more per pose than one (the rates may still differ: less CPU for the servers)."""
    alone = [r for r in alone if r.get("clients", 1)]  # a server that owned no client: not run
    if not together.get("cpu_ms_per_pose") or not all(r.get("cpu_ms_per_pose") for r in alone):
        return {}

    def per_pose(key: str) -> float:
        # CPU ms summed over the alone runs / poses summed: a weighted mean
        cpu = sum(r["cpu_ms_per_pose"][key] * r["answered_in_window"] for r in alone)
        return cpu / max(1, sum(r["answered_in_window"] for r in alone))

    s_alone, c_alone = per_pose("servers"), per_pose("clients")
    s_tog = together["cpu_ms_per_pose"]["servers"]
    c_tog = together["cpu_ms_per_pose"]["clients"]
    return {
        "cpu_ms_per_pose": {
            "alone": {"servers": s_alone, "clients": c_alone},
            "together": {"servers": s_tog, "clients": c_tog},
        },
        "servers_cpu_per_pose_together_vs_alone": s_tog / s_alone if s_alone else None,
    }


def same_frames_comparison(alone: list[dict], together: dict) -> dict:
    """Alone and together on the same frames (every client's frames ``--warmup-frames`` ..
    ``+ --same-frames``, ``same_frames_phase``): the servers' CPU per pose, and the time
    together against the alone runs' times added up. The alone runs had the cores the
    servers share together (``--pin``), one server at a time: the sum of their times is what
    those cores take for all these frames with one server per run, so
    ``time_alone_sum / time_together`` >= 0.9 is the issue's "within 10% of what the servers
    deliver alone" on equal work and equal cores; the servers' CPU for the frames shows
    what several servers on one network cost beyond one."""
    rows = [r["same_frames"] for r in alone if r.get("clients") and r.get("same_frames")]
    tog = together.get("same_frames")
    if not tog or not rows or len(rows) != sum(1 for r in alone if r.get("clients")):
        return {}
    cpu_a, poses_a = sum(r["servers_cpu_s"] for r in rows), sum(r["answered"] for r in rows)
    t_a = sum(r["seconds"] for r in rows)
    per_a = 1e3 * cpu_a / max(1, poses_a)
    per_t = 1e3 * tog["servers_cpu_s"] / max(1, tog["answered"])
    return {
        "frames": tog["frames"],
        "poses": {"alone": poses_a, "together": tog["answered"], "expected": tog["expected"]},
        "complete": all(r["complete"] for r in rows) and tog["complete"],
        "servers_cpu_ms_per_pose": {"alone": per_a, "together": per_t},
        "servers_cpu_per_pose_together_vs_alone": per_t / per_a if per_a else None,
        "seconds": {"alone_sum": t_a, "together": tog["seconds"]},
        "time_alone_sum_vs_together": t_a / tog["seconds"] if tog["seconds"] else None,
        "matching": {"alone": _sum_kinds(r["matching"] for r in rows), "together": tog["matching"]},
    }


def _sum_kinds(dicts: Any) -> dict[str, int]:
    out: dict[str, int] = {}
    for d in dicts:
        for k, v in d.items():
            out[k] = out.get(k, 0) + v
    return out


def owned_clients(map_name: str, clients: list[str], ids: list[str]) -> dict[str, list[str]]:
    """The clients each server of ``ids`` owns when all of them serve ``map_name`` (the
    rendezvous placement the clients' ``server="auto"`` makes)."""
    from sfmloc_client.placement import rendezvous_owner

    out: dict[str, list[str]] = {sid: [] for sid in ids}
    for c in clients:
        owner = rendezvous_owner(map_name, c, ids)
        if owner is not None:
            out[owner].append(c)
    return out


def run_alone(
    world: World,
    ids: list[str],
    clients: list[str],
    workers: int,
    seconds: float,
    cpus: dict[str, set[int]] | None = None,
    stamp_hz: float | None = None,
    warmup_frames: int = WARMUP_FRAMES,
    same_frames: int = 0,
):
    """Each server alone (on its cores) with the clients it owns in ``together`` (rendezvous
    placement over ``ids``; lockstep): poses per second. The same clients per server in both
    parts (12 clients over s0-s2 go 3/6/3, not 4/4/4), so that each server's frames come from
    as many clients alone as together. A server that owns none is not run (0 poses/s)."""
    rows = []
    owned = owned_clients(world.name, clients, ids)
    for sid in ids:
        mine = owned[sid]
        if not mine:
            rows.append({"server": sid, "clients": 0, "poses_per_s": 0.0})
            continue
        _log(f"scale alone: server {sid} with {len(mine)} lockstep client(s) for {seconds:g} s")
        stop = threading.Event()
        with Servers(world, [sid], workers, cpus, wait_budget=False) as srv:
            holds = same_frame_holds(warmup_frames, same_frames)
            cl = _clients(world, srv.endpoints, mine, stop, None, stamp_hz, holds)
            per, dt, cpu = _measure(
                cl, stop, 2.0, seconds, CpuMeter(srv.procs), warmup_frames, holds=holds
            )
        tot = _totals(per)
        rows.append(
            {"server": sid, "clients": len(mine), "poses_per_s": tot["answered"] / dt, **tot, **cpu}
        )
    return rows


def run_together(
    world: World,
    ids: list[str],
    clients: list[str],
    workers: int,
    seconds: float,
    cpus: dict[str, set[int]] | None = None,
    stamp_hz: float | None = None,
    warmup_frames: int = WARMUP_FRAMES,
    same_frames: int = 0,
) -> dict:
    _log(f"scale together: {len(ids)} servers, {len(clients)} lockstep clients, {seconds:g} s")
    stop = threading.Event()
    with Servers(world, ids, workers, cpus, wait_budget=False) as srv:
        holds = same_frame_holds(warmup_frames, same_frames)
        cl = _clients(world, srv.endpoints, clients, stop, None, stamp_hz, holds)
        per, dt, cpu = _measure(
            cl, stop, 2.0, seconds, CpuMeter(srv.procs), warmup_frames, holds=holds
        )
    tot = _totals(per)
    spread: dict[str, int] = {}
    for p in per:
        for sid, n in p["servers"].items():
            spread[sid] = spread.get(sid, 0) + (n > 0)
    return {
        "poses_per_s": tot["answered"] / dt,
        "clients_per_server": spread,
        "clients_on_two_servers": sum(len(p["servers"]) > 1 for p in per),
        **tot,
        **cpu,
    }


def run_kill(
    world: World,
    ids: list[str],
    clients: list[str],
    workers: int,
    rate_hz: float,
    seconds: float,
    cpus: dict[str, set[int]] | None = None,
    records: Path | None = None,
) -> dict:
    """``records``: write every client's per-frame records there (JSON; times relative to
    the kill): which frame, which server, with a prior or not, the answer and its error."""
    from sfmloc_client.placement import rendezvous_owner

    owners = {c: rendezvous_owner(world.name, c, ids) for c in clients}
    victim = max(ids, key=lambda s: sum(o == s for o in owners.values()))
    moved = [c for c in clients if owners[c] == victim]
    _log(
        f"scale kill: {len(ids)} servers, {len(clients)} clients at {rate_hz:g} Hz; SIGKILL "
        f"{victim} (owner of {len(moved)}) after {seconds / 2:g} s"
    )
    stop = threading.Event()
    # as deployed: the frame budget and the idle timeout are the server's defaults
    with Servers(world, ids, workers, cpus, idle_timeout_s=None) as srv:
        cl = _clients(world, srv.endpoints, clients, stop, rate_hz)
        time.sleep(2.0)  # warm up: every session tracking
        t0 = time.monotonic()
        time.sleep(seconds / 2)
        t_kill = time.monotonic()
        sp = srv.procs[victim]
        with contextlib.suppress(ProcessLookupError):
            os.kill(sp.proc.pid, signal.SIGKILL)
        sp.proc.wait(10)
        time.sleep(seconds / 2)
        t1 = time.monotonic()
        stop.set()
        for c in cl:
            c.join(15)
        recovery = []
        for c in cl:
            if c.log.client_id in moved:
                after = sorted(t for t in c.log.answered.values() if t > t_kill)
                recovery.append(after[0] - t_kill if after else float("inf"))
        stuck = [
            c.log.client_id for c in cl if not any(t > t1 - 2.0 for t in c.log.answered.values())
        ]
        per = [c.summary(t0, t1) for c in cl]
        if records is not None:
            records.write_text(
                json.dumps({c.log.client_id: c.records(t_kill) for c in cl}, separators=(",", ":"))
            )
        wrong = [
            {"client": c.log.client_id, **r}
            for c in cl
            for r in c.records(t_kill)
            if r["seq"] in c.log.wrong_seqs
        ]
    tot = _totals(per)
    rec = np.array(recovery)
    finite = rec[np.isfinite(rec)]
    return {
        "victim": victim,
        "moved_clients": len(moved),
        "recovery_s_p50": float(np.percentile(finite, 50)) if finite.size else None,
        "recovery_s_p99": float(np.percentile(finite, 99)) if finite.size else None,
        "recovery_s_max": float(rec.max()) if rec.size else None,
        "never_recovered": int(np.sum(~np.isfinite(rec))),
        "stuck_clients": stuck,
        **tot,
        "wrong_detail": wrong[:20],
    }


def share_child(work: Path, frames: int, slice_ms: float, core: int, start: float) -> dict:
    """One engine process of the ``share`` part: on ``core``, a Localizer over the clip's
    frames 10 .. 10 + ``frames`` (after 10 warm-up frames), started at wall time ``start``:
    its CPU per frame and involuntary context switches."""
    from ..cameras import Camera
    from ..engine import Localizer
    from ..map.bundle import MapBundle
    from ..threads import pin_threads
    from .reliability import pingpong

    os.sched_setaffinity(0, {core})
    pin_threads(True)
    world = prepare(work)
    loc = Localizer(MapBundle(world.bundle, verify=False), Camera.parse(world.camera))
    n = len(world.gray)
    for seq in range(10):
        loc.localize(world.gray[pingpong(n, seq)], seq / 30.0, None)
    if slice_ms > 0:
        from ..server.sched import set_slice

        set_slice(0, slice_ms)
    while time.time() < start:
        time.sleep(0.01)
    c0, t0, i0 = time.thread_time(), time.monotonic(), _involuntary_switches()
    for seq in range(10, 10 + frames):
        loc.localize(world.gray[pingpong(n, seq)], seq / 30.0, None)
    cpu, wall = time.thread_time() - c0, time.monotonic() - t0
    # the timed frames' switches only: the count since start also held the imports, the
    # world's load and the warm-up frames, which the per-frame figure divides by ``frames``
    ivcs = _involuntary_switches() - i0
    return {"frames": frames, "cpu_s": cpu, "wall_s": wall, "ivcs": ivcs}


def _involuntary_switches() -> int:
    """This process's involuntary context switches so far (0 where /proc cannot tell)."""
    with contextlib.suppress(OSError, ValueError), open("/proc/self/status") as f:
        for line in f:
            if line.startswith("nonvoluntary_ctxt_switches"):
                return int(line.split()[1])
    return 0


def run_share(work: Path, procs: int, frames: int, slice_ms: float, rounds: int, core: int) -> dict:
    """What sharing one core costs without servers or Zenoh: ``procs`` engine processes on
    ``core``, each localizing the same frames, against one alone (the same frames), with the
    kernel's default scheduler slice and with ``slice_ms`` (sched.py), interleaved over
    ``rounds``: CPU per frame of each phase and ``cpu_per_frame_shared_vs_alone`` per slice."""
    import subprocess

    prepare(work)  # built once here, not by every child at once
    phases = [(1, 0.0), (procs, 0.0), (1, slice_ms), (procs, slice_ms)]
    rows = []
    for rd in range(rounds):
        for n, sl in phases if rd % 2 == 0 else phases[::-1]:
            start = time.time() + 20.0  # every child imported and warmed up by then
            spec = f"{frames}:{sl}:{core}:{start}"
            cmd = [sys.executable, "-m", "sfmloc.bench.scale", "--work", str(work)]
            kids = [
                subprocess.Popen([*cmd, "--share-child", spec], stdout=subprocess.PIPE, text=True)
                for _ in range(n)
            ]
            # every child waited for before any is judged: one that failed must not leave
            # the others running on the core unwaited
            texts = [(k.communicate()[0], k.returncode) for k in kids]
            bad = [rc for _, rc in texts if rc != 0]
            if bad:
                raise RuntimeError(f"scale share: {len(bad)} of {n} children failed (exit {bad})")
            outs = [json.loads(t.strip().splitlines()[-1]) for t, _ in texts]
            tot = sum(o["frames"] for o in outs)
            rows.append(
                {
                    "round": rd,
                    "procs": n,
                    "slice_ms": sl,
                    "cpu_ms_per_frame": 1e3 * sum(o["cpu_s"] for o in outs) / tot,
                    "ivcs_per_frame": sum(o["ivcs"] for o in outs) / tot,
                    "load": os.getloadavg()[0],
                }
            )
            _log(f"scale share: {rows[-1]}")

    def mean(n: int, sl: float) -> float:
        v = [r["cpu_ms_per_frame"] for r in rows if r["procs"] == n and r["slice_ms"] == sl]
        return float(np.mean(v))

    return {
        "procs": procs,
        "frames": frames,
        "core": core,
        "rows": rows,
        "cpu_per_frame_shared_vs_alone": {
            "default_slice": mean(procs, 0.0) / mean(1, 0.0),
            f"slice_{slice_ms:g}_ms": mean(procs, slice_ms) / mean(1, slice_ms),
        },
    }


def run(args: argparse.Namespace) -> dict:
    out_sub: dict[str, Any] = {}
    if "share" in args.parts:
        out_sub["share"] = run_share(
            Path(args.work),
            args.servers,
            args.share_frames,
            args.share_slice_ms,
            args.share_rounds,
            min(os.sched_getaffinity(0)),
        )
        if not args.parts - {"share"}:
            return out_sub
    if "submaps" in args.parts:
        from .submaps import run_submaps

        out_sub["submaps"] = run_submaps(
            Path(args.work) / "rooms",
            rooms=args.rooms,
            parts_per_room=args.parts_per_room,
            ratio=args.ratio,
            log=_log,
            overlap=args.overlap,
            vote_fraction=args.vote_fraction,
        )
        if not args.parts - {"submaps"}:
            return out_sub
    world = prepare(Path(args.work))
    ids = [f"s{i}" for i in range(args.servers)]
    clients = [f"scale-client-{i}" for i in range(args.clients)]
    cpus = pinning(ids, args.pin, args.client_core)
    ccores = client_cores(args.pin, args.client_core)
    stamp_hz = args.stamp_hz if args.stamps == "video" else None
    all_cores = set(os.sched_getaffinity(0))
    out: dict[str, Any] = {
        "servers": args.servers,
        "clients": args.clients,
        "workers_per_server": args.workers,
        "cores": os.cpu_count(),
        "server_cores": {s: sorted(c) for s, c in cpus.items()} if cpus else "all",
        "client_cores": sorted(ccores) if ccores else "all",
        "stamps": args.stamps if args.stamps == "wall" else f"video {args.stamp_hz:g} Hz",
        "warmup_frames": args.warmup_frames,
        "load_before": os.getloadavg()[0],
    }
    if ccores:
        pin_process(ccores)
    if "alone" in args.parts or "together" in args.parts:  # together is judged against alone
        out["alone"] = run_alone(
            world,
            ids,
            clients,
            args.workers,
            args.seconds,
            cpus,
            stamp_hz,
            args.warmup_frames,
            args.same_frames,
        )
    if "together" in args.parts:
        together = run_together(
            world,
            ids,
            clients,
            args.workers,
            args.seconds,
            cpus,
            stamp_hz,
            args.warmup_frames,
            args.same_frames,
        )
        total_alone = sum(r["poses_per_s"] for r in out["alone"])
        share = core_share(out["alone"], cpus)
        out["together"] = together
        out["together_vs_sum_alone"] = (
            together["poses_per_s"] / total_alone if total_alone else None
        )
        # the target, on cores shared by servers: each server's rate alone over the
        # number of servers on its cores (2 servers on 2 cores: the plain sum)
        out["together_vs_core_share"] = together["poses_per_s"] / share if share else None
        out.update(cpu_comparison(out["alone"], together))
        same = same_frames_comparison(out["alone"], together)
        if same:
            out["same_frames"] = same
    if ccores:
        pin_process(all_cores)
    if "kill" in args.parts:
        # unpinned: the survivors may use the victim's core (pinned, the 6 moved clients of a
        # 3-server run would land on the one core two survivors share and overload it)
        out["kill"] = run_kill(
            world,
            ids,
            clients,
            args.workers,
            args.rate,
            args.seconds,
            records=Path(args.records) if args.records else None,
        )
    out["load_after"] = os.getloadavg()[0]
    return {**out, **out_sub}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m sfmloc.bench.scale",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--work", required=True, help="folder for the synthetic map (reused)")
    p.add_argument("--servers", type=int, default=3, help="server processes (default 3)")
    p.add_argument("--clients", type=int, default=12, help="streaming clients (default 12)")
    p.add_argument("--workers", type=int, default=1, help="engine workers per server (1)")
    p.add_argument("--seconds", type=float, default=15.0, help="measured time per part (15)")
    p.add_argument("--rate", type=float, default=10.0, help="frame rate in the kill part (10)")
    p.add_argument(
        "--parts",
        default="alone,together,kill",
        help="comma-separated: alone,together,kill,submaps,share (default: the three server "
        "parts; share: --servers engine processes on one core against one, no servers)",
    )
    p.add_argument("--rooms", type=int, default=8, help="submaps: synthetic rooms (8)")
    p.add_argument(
        "--parts-per-room", type=float, default=3.0, help="submaps: sub-maps per room (3)"
    )
    p.add_argument("--ratio", type=float, default=10.0, help="submaps: map memory / budget (10)")
    p.add_argument(
        "--overlap",
        type=float,
        default=0.5,
        help="submaps: map split --overlap (0.5: 8 rooms in 24 parts localized 318/320 frames, "
        "0.25 313/320, parts 1.5x smaller)",
    )
    p.add_argument(
        "--vote-fraction",
        type=float,
        default=0.05,
        help="submaps: map split --vote-fraction (0.05)",
    )
    p.add_argument(
        "--pin",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="server i (and its workers) on core i mod cores in alone and together, so that each "
        "server's rate alone is what its cores deliver (default on; --no-pin: all share all)",
    )
    p.add_argument(
        "--client-core",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="with --pin on 2+ cores: the last core runs this process (the clients) in alone and "
        "together and the servers share the others, so that the servers have the same cores in "
        "both parts (default on; --no-client-core: the clients float over every core, free in "
        "alone, taken from the servers together)",
    )
    p.add_argument(
        "--stamps",
        choices=("video", "wall"),
        default="video",
        help="lockstep frames' stamps in alone and together: 'video' (default), the clip's own "
        "clock (frame k at k/--stamp-hz s), so the engine does the same work per frame however "
        "slow the servers are; 'wall', the time each was sent (the engine then sees the camera "
        "move faster when the servers are slower: more relocalizations and second starts, "
        "more CPU per pose together than alone)",
    )
    p.add_argument("--stamp-hz", type=float, default=30.0, help="the video clock (30 Hz)")
    p.add_argument(
        "--warmup-frames",
        type=int,
        default=WARMUP_FRAMES,
        help="alone and together: the window starts once every client has had this many "
        f"answers (and 2 s passed): sessions' costlier first frames stay out ({WARMUP_FRAMES})",
    )
    p.add_argument(
        "--same-frames",
        type=int,
        default=SAME_FRAMES,
        help="alone and together: before the timed window, every client's next this many "
        "frames after the warm-up, all clients starting at once: the servers' CPU and time for "
        f"exactly these frames in both parts (same_frames; 0: skip) ({SAME_FRAMES})",
    )
    p.add_argument("--share-frames", type=int, default=118, help="share: frames per process (118)")
    p.add_argument(
        "--share-slice-ms",
        type=float,
        default=20.0,
        help="share: the long scheduler slice tried against the kernel's default (20)",
    )
    p.add_argument("--share-rounds", type=int, default=2, help="share: rounds (2)")
    p.add_argument("--share-child", help=argparse.SUPPRESS)
    p.add_argument("--out", help="write the results as JSON here too")
    p.add_argument(
        "--records", help="kill: write every client's per-frame records (JSON) to this file"
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.share_child:  # one process of the share part
        frames, sl, core, start = args.share_child.split(":")
        got = share_child(Path(args.work), int(frames), float(sl), int(core), float(start))
        print(json.dumps(got))
        return 0
    args.parts = set(args.parts.split(","))
    res = run(args)
    text = json.dumps(res, indent=2, default=str)
    print(text)
    if args.out:
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
