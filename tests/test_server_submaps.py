"""``sfmloc serve --map-memory``: a sub-map set hosted by a real server process, a real Zenoh
client walking across its parts (issue 14, build 5), on the synthetic world (exact ground
truth). The worker's resident map memory is measured by the kernel (``/proc/PID/smaps``)."""

from __future__ import annotations

import os
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from server_helpers import camera, client_zenoh, wait_until
from sfmloc.errors import ConfigError
from sfmloc.map.bundle import MapBundle
from sfmloc.map.submaps import SubmapSet, part_folder, split_bundle
from sfmloc.server.grpc_service import SERVICE_NAME
from sfmloc.server.submaps import check_set, resident_map_bytes
from sfmloc.testing import ServerProcess, free_port


@pytest.fixture(scope="module")
def set_dir(world, tmp_path_factory) -> Path:
    maps = tmp_path_factory.mktemp("setmaps")
    return split_bundle(MapBundle(world.maps_dir / "room"), maps, "roomparts", parts=3)


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (workers may be forked by a zygote, a child of the server)."""
    parent: dict[int, int] = {}
    for d in os.listdir("/proc"):
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
    return out


def _held(pid: int, folder: Path, n_parts: int) -> tuple[int, set[int]]:
    """What process ``pid`` maps of the set at ``folder`` (the kernel's count, as
    ``resident_map_bytes``) and the parts of which it holds pages, from one read of its
    smaps (a read per part and worker after every pose was most of this file's time)."""
    by_file: dict[str, int] = {}
    total = resident_map_bytes(pid, folder, per_file=by_file)
    parts = {
        k for k in range(n_parts)
        if any(f.startswith(part_folder(k) + "/") and b > 0 for f, b in by_file.items())
    }  # fmt: skip
    return total, parts


def test_a_set_needs_a_budget_that_holds_its_largest_part(set_dir):
    with pytest.raises(ConfigError, match="--map-memory"):
        check_set(set_dir, None)
    biggest = SubmapSet(set_dir).largest_part_bytes()
    with pytest.raises(ConfigError, match="largest sub-map"):
        check_set(set_dir, (biggest - 1) / 1e6)
    assert check_set(set_dir, (biggest + 1) / 1e6) is not None
    assert check_set(set_dir.parent / "nothing", None) is None  # not a set: a bundle's business


def test_server_walks_a_client_across_submaps_under_the_budget(world, set_dir):
    """A budget that holds one part of three: the client walks the synthetic
    video across parts over Zenoh; the worker never holds more than the budget of the set's
    files (kernel's count, sampled after every pose), the parts it holds change along the walk,
    the client stays localized with poses as good as a whole-map run's, and ListMaps and the
    metrics show the set."""
    from sfmloc_client import FrameStreamer, LocalizationClient, PoseSubscriber

    s = SubmapSet(set_dir)
    sizes = [s.part_memory_bytes(k) for k in range(s.n_parts)]
    budget = max(sizes) + 1000  # one part at a time: a switch evicts
    assert budget < sum(sizes) - min(sizes)  # two parts never fit
    metrics_port = free_port()
    extra = (
        "--map-memory", f"{budget / 1e6:.6f}", "--relocalize-workers", "1",
        "--metrics-port", str(metrics_port),
    )  # fmt: skip
    with ServerProcess(set_dir.parent, workers=1, extra_args=extra) as srv:
        with LocalizationClient(srv.grpc) as c:
            (info,) = c.list_maps()
        assert (info.name, info.submaps, info.points) == ("roomparts", 3, s.manifest.points)
        assert info.map_memory_mb == pytest.approx(budget / 1e6, rel=1e-6)
        # The stream worker and the relocalization worker (and a zygote, no maps): each holds
        # at most the budget (the walking session's part stays pinned on the stream worker).
        workers = _descendants(srv.proc.pid)
        assert workers
        resident: list[int] = []
        parts_seen: set[int] = set()
        poses: list = []

        def on_pose(p) -> None:  # noqa: ANN001 - a PoseMessage
            poses.append(p)
            held = [_held(w, set_dir, s.n_parts) for w in workers]
            resident.append(max(b for b, _ in held))
            for _, ks in held:
                parts_seen.update(ks)

        with client_zenoh(srv.endpoint) as z:
            with (
                PoseSubscriber(z, "roomparts", "walker", callback=on_pose) as sub,
                FrameStreamer(z, "roomparts", "walker", camera(world), encoding="gray8") as fs,
            ):
                assert fs.wait_for_server(30)
                stats = fs.run(np.stack(world.gray), lockstep=True, poses=sub, pose_timeout=30)
                assert sub.wait_for(stats.last_seq, 60)
        body = urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics").read().decode()
        with LocalizationClient(srv.grpc) as c:
            (info,) = c.list_maps()
            assert c.health(f"{SERVICE_NAME}/roomparts") == "SERVING"
            # Single images: on the best-voted part (no prior), within the same budget.
            single = [c.relocalize(world.gray[k], "roomparts", camera(world), encoding="gray8")
                      for k in (5, 30, 55)]  # fmt: skip
        resident.append(max(resident_map_bytes(w, set_dir) for w in workers))
    n = len(world.gray)
    assert len(poses) == n
    errors = []
    for p in poses:
        if p.localized:
            gt = world.gt_cam_from_world[p.seq]
            errors.append(np.linalg.norm(np.asarray(p.world_from_cam.t) - gt.center))
    assert len(errors) >= n - 2, f"{len(errors)}/{n} localized"
    assert max(errors) < 0.02 * s.scene_scale  # a pose is a promise: no wrong pose
    for k, p in zip((5, 30, 55), single):
        if p.localized:
            gt = world.gt_cam_from_world[k]
            assert np.linalg.norm(np.asarray(p.world_from_cam.t) - gt.center) < 0.02 * s.scene_scale
    assert sum(p.localized for p in single) >= 2
    assert max(resident) <= budget, (max(resident), budget)
    assert min(resident) > 0  # the kernel's count sees the part the session is on
    assert len(parts_seen) >= 2, parts_seen  # the walk crossed parts: one was evicted
    assert 0 < info.resident_mb <= budget / 1e6
    assert f'sfmloc_map_memory_budget_bytes{{map="roomparts"}} {budget}' in body
    line = next(ln for ln in body.splitlines() if ln.startswith("sfmloc_map_resident_bytes{"))
    assert 'map="roomparts"' in line and 0 < float(line.split()[-1]) <= budget


def test_server_refuses_a_set_without_a_budget(world, set_dir):
    """Without --map-memory, a set in the maps folder is not loaded (a clear log line; the
    server starts with what else it has) and LoadMap says why."""
    from sfmloc_client import LocalizationClient
    from sfmloc_client.errors import SfmlocError

    with ServerProcess(set_dir.parent, workers=1, extra_args=("--allow-empty",)) as srv:
        with LocalizationClient(srv.grpc) as c:
            assert c.list_maps() == []
            with pytest.raises(SfmlocError, match="--map-memory"):
                c.load_map("roomparts")
        assert wait_until(lambda: srv.proc.poll() is None, 1)
