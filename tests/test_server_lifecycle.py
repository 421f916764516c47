"""Server start-up, idle expiry and shutdown; configuration, the status table, log lines."""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import subprocess
import threading

import grpc
import pytest

from server_helpers import (
    camera,
    client_zenoh,
    free_port,
    running_server,
    server_config,
    stream_lockstep,
    wait_until,
    zenoh_endpoint,
)
from sfmloc import errors as E
from sfmloc.testing import serve_command
from sfmloc_client import LocalizationClient
from sfmloc_client.discovery import list_server_ids


# ----------------------------------------------------------------------------- start-up
@pytest.fixture()
def late(world):
    """A server started without its maps (the test loads them)."""
    ep = zenoh_endpoint()
    with running_server(server_config(world, ep, server_id="late-server"), load_maps=False) as srv:
        yield srv, ep


@pytest.fixture()
def impatient(world):
    """A server whose Zenoh sessions expire after half a second without frames."""
    ep = zenoh_endpoint()
    with running_server(server_config(world, ep, idle_timeout_s=0.5)) as srv:
        yield srv, ep


def test_health_is_serving_only_after_the_maps_are_loaded(late):
    srv, ep = late
    with LocalizationClient(f"127.0.0.1:{srv.grpc_port}") as c, client_zenoh(ep) as z:
        assert c.health() == "NOT_SERVING"
        assert c.health("sfmloc.v1.Localization") == "NOT_SERVING"
        assert c.list_maps() == []
        assert "late-server" not in list_server_ids(z, timeout=1)  # not discoverable yet
        srv.call(srv.server.load_initial_maps())
        assert c.health() == "SERVING" and c.health("sfmloc.v1.Localization") == "SERVING"
        assert {m.name for m in c.list_maps()} == {"room", "room2"}
        assert wait_until(lambda: "late-server" in list_server_ids(z, timeout=1), 30)


@pytest.mark.parametrize("allow_empty", [False, True])
def test_health_with_no_map_loaded(world, tmp_path, allow_empty):
    """A server whose maps folder is empty (or missing) cannot localize: NOT_SERVING on gRPC
    health and 503 on /healthz, unless --allow-empty says an empty server is fine."""
    import urllib.error
    import urllib.request

    port = free_port()
    conf = server_config(
        world,
        zenoh_endpoint(),
        maps=str(tmp_path / "nonexistent"),
        allow_empty=allow_empty,
        metrics_port=port,
        map_roots=[str(world.maps_dir)],
    )
    with running_server(conf) as srv, LocalizationClient(f"127.0.0.1:{srv.grpc_port}") as c:
        assert srv.server.ready and c.list_maps() == []
        want = "SERVING" if allow_empty else "NOT_SERVING"
        assert c.health() == want and c.health("sfmloc.v1.Localization") == want
        try:
            code = urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=10).status
        except urllib.error.HTTPError as exc:
            code = exc.code
        assert code == (200 if allow_empty else 503)
        # a map loaded later (LoadMap from the server's map roots) makes it SERVING
        c.load_map(str(world.maps_dir / "room"))
        assert wait_until(lambda: c.health() == "SERVING", 10)
        assert c.health("sfmloc.v1.Localization/room") == "SERVING"
        c.unload_map("room")
        assert wait_until(lambda: c.health("sfmloc.v1.Localization/room") == "NOT_SERVING", 10)
        assert wait_until(lambda: c.health() == want, 10)


def test_an_idle_session_expires(world, impatient):
    srv, ep = impatient
    with client_zenoh(ep) as z, LocalizationClient(f"127.0.0.1:{srv.grpc_port}") as c:
        first = stream_lockstep(z, "room", "sleepy", world, n=3)
        assert [p.seq for p in first] == [0, 1, 2]
        assert wait_until(lambda: not any(s.client_id == "sleepy" for s in c.list_sessions()), 30)
        assert srv.server.metrics.sessions_closed.get("room", "idle") >= 1
        again = stream_lockstep(z, "room", "sleepy", world, n=2)  # a new session: from scratch
        assert again[0].status in ("RELOCALIZED", "LOST")
        assert srv.server.metrics.sessions_opened.get("room", "zenoh") >= 2


def test_max_pending_keeps_the_newest_frames(world):
    """With max_pending 3, a burst is processed as its first frame plus (at least) the three
    newest; everything else is counted as dropped."""
    from sfmloc_client import FrameStreamer, PoseSubscriber

    ep = zenoh_endpoint()
    with running_server(server_config(world, ep, max_pending=3)), client_zenoh(ep) as z:
        got: list = []
        n = 30
        with (
            PoseSubscriber(z, "room", "burst3", callback=got.append) as poses,
            FrameStreamer(z, "room", "burst3", camera(world)) as fs,
        ):
            assert fs.wait_for_server(30)
            for k in range(n):
                fs.publish(data=world.png[k], encoding="png", stamp_ns=int(k * 1e9 / 30))
            assert poses.wait_for(n - 1, 60)
        seqs = [p.seq for p in got]
        assert seqs == sorted(seqs) and seqs[-3:] == [n - 3, n - 2, n - 1]
        assert len(got) + got[-1].dropped == n and got[-1].dropped > 0


# ----------------------------------------------------------------------------- isolation
def _nice(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[16])  # field 19: nice


def test_relocalizations_run_on_their_own_lane_beside_a_stream(world):
    """Single-image Relocalize runs on the relocalization lane (its own worker process, at a
    lower CPU priority), never on the worker a streaming session's frames wait on: with
    relocalizations in flight all the time, the stream gets every pose, and the stream
    worker did none of the relocalizations."""
    from sfmloc_client import FrameStreamer, PoseSubscriber

    ep = zenoh_endpoint()
    conf = server_config(world, ep, workers=1, worker_kind="process", relocalize_workers=1)
    with (
        running_server(conf) as srv,
        client_zenoh(ep) as z,
        LocalizationClient(f"127.0.0.1:{srv.grpc_port}", timeout=120) as c,
    ):
        pool = srv.server.pool
        stream_w, lane_w = pool.workers
        # relocalize_nice (+15), capped at 19 (the kernel's lowest priority: `nice -n 19 make
        # test` starts there)
        assert conf.relocalize_nice == 15
        assert _nice(lane_w.pid) == min(_nice(stream_w.pid) + 15, 19)
        busy0 = pool.busy_ms()
        first = c.relocalize(world.png[10], "room", camera(world), encoding="png")
        assert first.localized
        busy1 = pool.busy_ms()
        assert busy1[0] == busy0[0] and busy1[1] > busy0[1]  # the lane did it, not worker 0

        stop = threading.Event()
        answers: list = []

        def caller() -> None:  # keeps a relocalization in flight until the stream is done
            k = 0
            while not stop.is_set():
                image = world.png[k % 60]
                answers.append(c.relocalize(image, "room", camera(world), encoding="png"))
                k += 7

        callers = [threading.Thread(target=caller) for _ in range(2)]
        for t in callers:
            t.start()
        try:
            assert pool.wait_for(lambda: pool.workers[1].inflight > 0, 60)
            got: list = []
            during: list[int] = []  # lane requests in flight when each pose came back
            with (
                PoseSubscriber(z, "room", "beside", callback=got.append) as sub,
                FrameStreamer(z, "room", "beside", camera(world)) as fs,
            ):
                assert fs.wait_for_server(30)
                for k in range(20):
                    seq = fs.publish(
                        data=world.png[k], encoding="png", seq=k, stamp_ns=int(k * 1e9 / 30)
                    )
                    assert sub.wait_for(seq, 60)
                    during.append(pool.workers[1].inflight)
        finally:
            stop.set()
            for t in callers:
                t.join(120)
        assert [p.seq for p in got] == list(range(20)) and all(p.error is None for p in got)
        assert sum(p.localized for p in got) >= 18
        assert sum(n > 0 for n in during) >= 10  # the lane was busy while the stream was served
        assert answers and all(a.error is None for a in answers)


def _kernel_takes_slices() -> bool:
    """Whether this kernel sets a SCHED_OTHER task's slice (EEVDF, Linux 6.12+): tried on a
    child process, not on the test's own threads."""
    from sfmloc.server.sched import set_slice

    with subprocess.Popen(["sleep", "30"]) as child:
        try:
            return set_slice(child.pid, 7.0)
        finally:
            child.kill()


def test_stream_workers_get_frame_long_scheduler_slices_the_lane_does_not(world):
    """worker_slice_ms: the stream worker (and its replacement after a crash) runs with that
    scheduler slice, so workers sharing a core are not switched every 1.4 ms (the kernel's
    default on 2 cores) onto each other's caches; the niced relocalization lane keeps the
    default; its nice value is untouched; frames are served."""
    from sfmloc.server.sched import get_slice_ns

    if not _kernel_takes_slices():
        pytest.skip("this kernel does not take a per-task slice (sched_setattr, Linux 6.12+)")
    from sfmloc_client import FrameStreamer, PoseSubscriber

    default = get_slice_ns(0)
    ep = zenoh_endpoint()
    conf = server_config(
        world, ep, workers=1, worker_kind="process", relocalize_workers=1, worker_slice_ms=25
    )
    with running_server(conf) as srv, client_zenoh(ep) as z:
        pool = srv.server.pool
        stream_w, lane_w = pool.workers
        assert get_slice_ns(stream_w.pid) == 25_000_000
        assert get_slice_ns(lane_w.pid) == default != 25_000_000
        assert _nice(lane_w.pid) == min(_nice(stream_w.pid) + 15, 19)
        old = stream_w.pid
        os.kill(old, signal.SIGKILL)
        assert pool.wait_for(lambda: pool.workers[0].pid not in (0, old), 60)
        assert pool.wait_for(lambda: pool.workers[0].serving, 60)
        assert get_slice_ns(pool.workers[0].pid) == 25_000_000
        got: list = []
        with (
            PoseSubscriber(z, "room", "sliced", callback=got.append) as sub,
            FrameStreamer(z, "room", "sliced", camera(world)) as fs,
        ):
            assert fs.wait_for_server(30)
            for k in range(5):
                seq = fs.publish(
                    data=world.png[k], encoding="png", seq=k, stamp_ns=int(k * 1e9 / 30)
                )
                assert sub.wait_for(seq, 60)
        assert [p.seq for p in got] == list(range(5)) and all(p.error is None for p in got)
        assert sum(p.localized for p in got) >= 4


# ----------------------------------------------------------------------------- shutdown
def test_stop_finishes_in_flight_relocalizations(world):
    from sfmloc.testing import ServerThread

    s = ServerThread(
        server_config(world, zenoh_endpoint(), workers=1, worker_kind="process")
    ).start()
    results: list = []

    def call(k: int) -> None:
        with LocalizationClient(f"127.0.0.1:{s.grpc_port}") as c:
            try:
                results.append(c.relocalize(world.png[k], "room", camera(world), encoding="png"))
            except Exception as exc:  # noqa: BLE001 - recorded and asserted on
                results.append(exc)

    threads = [threading.Thread(target=call, args=(k,)) for k in (5, 25, 45, 15)]
    try:
        for t in threads:
            t.start()
        # every call has reached the server: queued or running in its worker, or answered
        assert wait_until(lambda: sum(s.server.pool.inflight()) + len(results) >= 4, 60)
        assert len(results) < 4  # some are still in the worker when the server stops
    finally:
        s.stop(grace=60)  # graceful: the requests queued or running are answered first
    for t in threads:
        t.join(60)
    assert len(results) == 4
    assert not any(isinstance(r, Exception) for r in results), results  # answered, not cancelled
    assert sum(r.status == "RELOCALIZED" for r in results) >= 3
    assert s.server.zenoh.z is None  # its Zenoh session was closed
    assert all(not h.runner.is_alive() for h in s.server.pool.workers)


def _children(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                        out.append(int(d))
            except (OSError, ValueError, IndexError):
                pass
    return out


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_cli_server_shuts_down_gracefully_on_signals(world, sig):
    ep, gport = zenoh_endpoint(), free_port()
    cmd = serve_command(
        world.maps_dir,
        ep,
        f"127.0.0.1:{gport}",
        1,
        quiet=False,
        extra_args=("--server-id", "cli-server"),
    )
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    try:
        with LocalizationClient(f"127.0.0.1:{gport}") as c:
            assert c.wait_ready(120)
        with client_zenoh(ep) as z:
            poses = stream_lockstep(z, "room", "till-the-end", world, n=5)
            assert [p.seq for p in poses] == list(range(5))
        workers = _children(proc.pid)
        assert workers  # the engine worker process
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err[-3000:]
    assert "event=server_stopped" in err and f"signal={signal.Signals(sig).name}" in err
    assert "Traceback" not in err
    assert wait_until(lambda: all(_gone(w) for w in workers), 30)


# ----------------------------------------------------------------------------- configuration
def test_config_precedence_defaults_file_environment_flags(tmp_path):
    from sfmloc.cli.main import build_parser
    from sfmloc.cli.serve import overrides_from_args
    from sfmloc.config import load_config
    from sfmloc.server.config import ServerConfig

    f = tmp_path / "server.json"
    f.write_text(
        json.dumps(
            {
                "workers": 2,
                "idle_timeout_s": 5,
                "zenoh": {"mode": "client", "connect": ["tcp/a:1"]},
                "engine": {"k": 40},
            }
        )
    )
    env = {"SFMLOC_WORKERS": "3", "SFMLOC_ZENOH__MODE": "router", "SFMLOC_ENGINE__K": "45"}
    args = build_parser().parse_args(
        [
            "serve",
            "--workers",
            "4",
            "--zenoh-listen",
            "tcp/0.0.0.0:7447",
            "--grpc",
            "127.0.0.1:0",
            "--no-multicast",
        ]
    )
    conf = load_config(ServerConfig, f, environ=env, overrides=overrides_from_args(args))
    assert conf.workers == 4  # flag > env > file
    assert conf.zenoh.mode == "router"  # env > file
    assert conf.zenoh.connect == ["tcp/a:1"] and conf.zenoh.listen == ["tcp/0.0.0.0:7447"]
    assert conf.zenoh.multicast is False and conf.grpc.address == "127.0.0.1:0"
    assert conf.idle_timeout_s == 5 and conf.engine.k == 45
    assert conf.maps == "maps" and conf.worker_kind == "process"  # defaults
    with pytest.raises(E.ConfigError) as e:
        load_config(ServerConfig, None, environ={"SFMLOC_WORKERZ": "1", "SFMLOC_WORKERS": "many"})
    assert "workers" in str(e.value)


# ----------------------------------------------------------------------------- status table
@pytest.mark.parametrize(
    "exc, code",
    [
        (E.MapNotFoundError("x"), "NOT_FOUND"),
        (E.SessionNotFoundError("x"), "NOT_FOUND"),
        (E.ImageDecodeError("x"), "INVALID_ARGUMENT"),
        (E.CameraModelError("x"), "INVALID_ARGUMENT"),
        (E.WireError("x"), "INVALID_ARGUMENT"),
        (E.MessageTooLargeError("x"), "RESOURCE_EXHAUSTED"),
        (E.ConfigError("x"), "INVALID_ARGUMENT"),
        (E.JobNotFoundError("x"), "NOT_FOUND"),
        (E.PermissionDeniedError("x"), "PERMISSION_DENIED"),
        (E.BuildError("x", stage="pca"), "FAILED_PRECONDITION"),
        (E.OverloadError("x"), "RESOURCE_EXHAUSTED"),
        (E.BundleError("x"), "FAILED_PRECONDITION"),
        (E.UnavailableError("x"), "UNAVAILABLE"),
        (E.SfmlocError("x"), "INTERNAL"),
        (ZeroDivisionError("x"), "INTERNAL"),
    ],
)
def test_status_table_and_worker_error_round_trip(exc, code):
    from sfmloc.server.status import error_from_wire, error_info, error_to_wire, status_of

    assert status_of(exc) == getattr(grpc.StatusCode, code)
    back = error_from_wire(error_to_wire(exc))  # how errors cross the worker boundary
    assert status_of(back).name == code and error_info(back).code == code
    assert str(exc) in str(back)
    assert type(back) is (type(exc) if isinstance(exc, E.SfmlocError) else E.InternalError)


def test_a_foreign_error_named_like_ours_crosses_the_worker_boundary_as_internal():
    from sfmloc.server.status import error_from_wire, error_to_wire

    class BundleError(Exception):  # not sfmloc's, same name
        pass

    back = error_from_wire(error_to_wire(BundleError("x")))
    assert type(back) is E.InternalError and back.code == "INTERNAL"


def test_log_lines_key_value_and_json():
    from sfmloc.server.logfmt import JsonFormatter, KeyValueFormatter, event

    log = logging.getLogger("sfmloc.test.logfmt")
    log.propagate = False
    log.setLevel(logging.INFO)
    for fmt, check in ((KeyValueFormatter(), "kv"), (JsonFormatter(), "json")):
        buf = io.StringIO()
        h = logging.StreamHandler(buf)
        h.setFormatter(fmt)
        log.addHandler(h)
        event(log, logging.INFO, "session_open", map="room", client="a b", worker=1)
        log.info("plain %s", "message")
        log.removeHandler(h)
        lines = buf.getvalue().splitlines()
        if check == "kv":
            assert "level=info" in lines[0] and "event=session_open" in lines[0]
            assert 'client="a b"' in lines[0] and "worker=1" in lines[0]
            assert 'msg="plain message"' in lines[1]
        else:
            d = json.loads(lines[0])
            assert d["event"] == "session_open" and d["client"] == "a b" and d["worker"] == 1
            assert json.loads(lines[1])["msg"] == "plain message"


def test_prometheus_text_format():
    from sfmloc.server.metrics import ServerMetrics

    m = ServerMetrics()
    m.frames_in.inc('we"ird', "zenoh")
    m.latency.observe("room", value=0.004)
    m.latency.observe("room", value=0.5)
    text = m.registry.render()
    assert 'sfmloc_frames_received_total{map="we\\"ird",transport="zenoh"} 1' in text
    assert 'sfmloc_frame_latency_seconds_bucket{map="room",le="0.005"} 1' in text
    assert 'sfmloc_frame_latency_seconds_bucket{map="room",le="+Inf"} 2' in text
    assert 'sfmloc_frame_latency_seconds_count{map="room"} 2' in text


# ----------------------------------------------------------------------------- worker start-up
def test_workers_start_from_a_folder_that_shadows_the_package(tmp_path, monkeypatch):
    """A server started where a folder named ``sfmloc`` exists (the parent of a clone): its
    worker processes still import the installed package (they drop the working directory from
    sys.path) and the pool starts."""
    from sfmloc.server.pool import WorkerPool

    (tmp_path / "sfmloc").mkdir()  # found first on sys.path when the working directory is on it
    (tmp_path / "sfmloc" / "__init__.py").write_text(
        "raise ImportError('the shadow was imported')\n"
    )
    monkeypatch.chdir(tmp_path)
    pool = WorkerPool(1, "process", "{}", on_result=lambda msg: None)
    try:
        pool.start(timeout=120)
        assert pool.workers[0].ready.is_set() and pool.fatal is None and pool.restarts == 0
    finally:
        pool.stop()


def test_a_worker_that_cannot_start_fails_the_pool_loudly(tmp_path, monkeypatch):
    """Workers that die before they are ready are retried a bounded number of times with
    back-off, then the pool gives up with the child's own error in one line; every dead
    child is reaped (no zombie)."""
    from sfmloc.server.pool import MAX_START_FAILURES, WorkerPool

    broken = tmp_path / "broken" / "sfmloc"
    broken.mkdir(parents=True)
    (broken / "__init__.py").write_text("raise ImportError('sfmloc is broken on purpose')\n")
    monkeypatch.setenv(
        "PYTHONPATH", f"{broken.parent}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"
    )
    pool = WorkerPool(1, "process", "{}", on_result=lambda msg: None)
    try:
        with pytest.raises(E.UnavailableError) as err:
            pool.start(timeout=120)
        assert f"exited {MAX_START_FAILURES} times" in str(err.value)
        assert "sfmloc is broken on purpose" in str(err.value)
        assert pool.restarts == MAX_START_FAILURES - 1
        assert all(h.runner.exitcode is not None for h in pool.workers)  # reaped
        out = subprocess.run(
            ["ps", "-o", "stat=", "--ppid", str(os.getpid())], capture_output=True, text=True
        )
        assert "Z" not in out.stdout.split()  # no zombie child
    finally:
        pool.stop()


def test_free_ports_are_distinct_free_and_outside_the_kernels_and_other_workers_ranges():
    """free_port() hands out ports below the ephemeral range (where a released bind(0) port
    could be taken by any connect before the server binds it), each xdist worker from its own
    block, never the same twice in a process, skipping ports someone listens on."""
    import socket
    import sys

    from sfmloc import testing

    block = testing.port_block()
    ports = [testing.free_port() for _ in range(100)]
    assert len(set(ports)) == 100 and all(p in block for p in ports)
    assert max(ports) < testing.ephemeral_low()
    # ports in use are skipped: hold the next three (the cursor goes in turn through the block)
    held = []
    for k in range(1, 4):
        s = socket.socket()
        s.bind(("127.0.0.1", block[(block.index(ports[-1]) + k) % len(block)]))
        s.listen()
        held.append(s)
    try:
        p = testing.free_port()
        assert p not in [s.getsockname()[1] for s in held] and p in block
        assert (block.index(p) - block.index(ports[-1])) % len(block) >= 4
    finally:
        for s in held:
            s.close()
    # two xdist workers' processes: disjoint blocks, whatever their random starts
    code = "from sfmloc.testing import free_port; print(*[free_port() for _ in range(50)])"
    got = []
    for worker in ("gw0", "gw1"):
        env = {**os.environ, "PYTEST_XDIST_WORKER": worker}
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        got.append({int(v) for v in out.stdout.split()})
    assert len(got[0]) == len(got[1]) == 50 and not got[0] & got[1]
    size = (testing.ephemeral_low() - testing.PORT_LOW) // testing.PORT_BLOCKS
    for i, ports_i in enumerate(got):
        assert all(
            testing.PORT_LOW + i * size <= p < testing.PORT_LOW + (i + 1) * size for p in ports_i
        )


def test_two_test_runs_side_by_side_never_get_the_same_port():
    """Two pytest runs at once on one machine both have a gw0 (the same block): a port one
    process handed out (and holds, its server not bound yet) is not handed to the other, even
    from the same random start; once the first process exits its ports are free again."""
    import sys

    from sfmloc import testing

    code = (
        "import random, sys; random.seed(7); from sfmloc.testing import free_port; "
        "print(*[free_port() for _ in range(50)], flush=True); sys.stdin.readline()"
    )
    env = {**os.environ, "PYTEST_XDIST_WORKER": "gw0"}

    def run() -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-c", code],
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    first = run()
    try:
        a = {int(v) for v in first.stdout.readline().split()}  # held: first waits on stdin
        second = run()
        b_out, _ = second.communicate("\n", timeout=60)
        b = {int(v) for v in b_out.split()}
        assert second.returncode == 0
    finally:
        first.communicate("\n", timeout=60)
    block = range(testing.PORT_LOW, testing.PORT_LOW + len(testing.port_block()))
    assert len(a) == len(b) == 50 and all(p in block for p in a | b)
    assert not a & b
    # the first process's reservations ended with it (another run may have taken a few since)
    import fcntl

    lockable = 0
    for p in a:
        fd = os.open(os.path.join(testing.PORT_LOCK_DIR, f"{p}.lock"), os.O_RDWR)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            lockable += 1
        except OSError:
            pass
        finally:
            os.close(fd)  # closing drops the lock
    assert lockable >= 45
