"""Server memory does not grow with the clients that came and went (issue 16, item 1).

Zenoh's shared-memory transport (on by default in zenoh) made a process keep every peer's
16 MiB segment mapped after that peer left: 10 short-lived client processes grew a server by
~200 MB and 20 /dev/shm mappings. sfmloc turns it off unless asked. Real processes throughout:
a `sfmloc serve` process, and one Python process per client that streams a few raw frames.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

from server_helpers import free_port, zenoh_endpoint
from sfmloc.testing import serve_command

N_WARMUP, N_CLIENTS, N_FRAMES = 3, 20, 3
# Measured (2-core machine, shared memory off): +6 MB over 20 clients after warm-up (allocator
# noise, session tables until idle expiry). With shared memory on: ~+20 MB per client, so one
# leaked 16 MiB segment in three clients would cross this bound.
MAX_RSS_GROWTH_MB = 48.0

CLIENT = """
import sys, zenoh
from sfmloc_client import CameraSpec, FrameStreamer, PoseSubscriber, make_zenoh_config
ep, cid, spec, *paths = sys.argv[1:]
with zenoh.open(make_zenoh_config("peer", connect=[ep], multicast=False)) as z, \\
        PoseSubscriber(z, "room", cid) as poses, \\
        FrameStreamer(z, "room", cid, CameraSpec.parse(spec)) as fs:
    if not fs.wait_for_server(30):
        sys.exit("no server")
    for k, path in enumerate(paths):
        with open(path, "rb") as f:
            fs.publish(data=f.read(), encoding="gray8", seq=k, stamp_ns=k * 33_000_000)
        if not poses.wait_for(k, 60):
            sys.exit(f"no pose for frame {k}")
"""


def _tree(pid: int) -> list[int]:
    """The server and its worker processes."""
    out = [pid]
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                        out += _tree(int(d))
            except (OSError, ValueError, IndexError):
                pass
    return out


def _rss_mb(pids: list[int]) -> float:
    total = 0
    for pid in pids:
        with open(f"/proc/{pid}/status") as f:
            total += next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))
    return total / 1024


def _shm_segments(pids: list[int]) -> set[str]:
    # Segments the server holds, not `ls /dev/shm`: other processes on the machine create
    # and remove their own there while the test runs.
    held = set()
    for pid in pids:
        with open(f"/proc/{pid}/maps") as f:
            held |= {line.split()[-1] for line in f if "/dev/shm/" in line}
    return held


def test_server_memory_does_not_grow_with_clients_that_come_and_go(world, tmp_path):
    from sfmloc_client import LocalizationClient

    frames = []
    for k in range(N_FRAMES):  # raw gray8 (307 kB): well above zenoh's shared-memory threshold
        frames.append(tmp_path / f"f{k}.gray8")
        frames[-1].write_bytes(world.gray[k].tobytes())
    ep, gport = zenoh_endpoint(), free_port()
    log = open(tmp_path / "server.log", "w+")
    server = subprocess.Popen(
        serve_command(
            world.maps_dir,
            ep,
            f"127.0.0.1:{gport}",
            1,
            quiet=False,
            extra_args=("--relocalize-workers", "0"),
        ),
        stderr=log,
    )

    def client(k: int) -> None:
        args = [ep, f"shm-{k}", world.camera_spec, *map(str, frames)]
        done = subprocess.run(
            [sys.executable, "-c", CLIENT, *args], capture_output=True, text=True, timeout=120
        )
        assert done.returncode == 0, done.stderr[-2000:]

    try:
        with LocalizationClient(f"127.0.0.1:{gport}") as c:
            assert c.wait_ready(120)
        for k in range(N_WARMUP):
            client(k)
        pids = _tree(server.pid)
        rss0, shm0 = _rss_mb(pids), _shm_segments(pids)
        for k in range(N_WARMUP, N_WARMUP + N_CLIENTS):
            client(k)
        pids = _tree(server.pid)
        rss1, shm1 = _rss_mb(pids), _shm_segments(pids)
    finally:
        server.terminate()
        server.wait(60)
        log.seek(0)
        text = log.read()
        log.close()
    assert shm1 == shm0 == set(), f"server holds shared-memory segments: {sorted(shm1)}"
    assert rss1 - rss0 < MAX_RSS_GROWTH_MB, (
        f"server RSS {rss0:.0f} -> {rss1:.0f} MB over {N_CLIENTS} clients"
    )
    opened = next(line for line in text.splitlines() if "event=zenoh_open" in line)
    assert "shared_memory=false" in opened


def test_shared_memory_is_off_unless_asked(tmp_path):
    from sfmloc_client import make_zenoh_config
    from sfmloc_client.zconfig import SHM_KEY

    def shm(**kw) -> bool:
        return json.loads(make_zenoh_config(**kw).get_json(SHM_KEY))

    assert shm() is False
    assert shm(shared_memory=True) is True
    on = tmp_path / "on.json5"
    on.write_text("{ transport: { shared_memory: { enabled: true } } }")
    assert shm(config_file=on) is True  # a file that sets it decides
    assert shm(config_file=on, shared_memory=False) is False  # an explicit setting goes over
    other = tmp_path / "other.json5"
    other.write_text('{ "scouting": { "multicast": { "enabled": false } } }')
    assert shm(config_file=other) is False


def test_serve_flag_turns_shared_memory_on():
    from sfmloc.cli.main import build_parser
    from sfmloc.cli.serve import overrides_from_args
    from sfmloc.config import load_config
    from sfmloc.server.config import ServerConfig

    def conf(*flags: str) -> ServerConfig:
        args = build_parser().parse_args(["serve", *flags])
        return load_config(ServerConfig, None, environ={}, overrides=overrides_from_args(args))

    assert conf().zenoh.shared_memory is None  # off, unless a --zenoh-config file sets it
    assert conf("--zenoh-shm").zenoh.shared_memory is True
