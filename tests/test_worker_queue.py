"""The worker queue (``ServerConfig.worker_queue``) with a real server, one engine worker
process and real Zenoh clients streaming faster than it serves: the frames in the worker at
once never exceed the limit (without it, one per session), every client is served, and every
frame is answered or counted dropped."""

from __future__ import annotations

import threading
import time

import pytest

from server_helpers import (
    camera,
    client_zenoh,
    running_server,
    server_config,
    zenoh_endpoint,
)
from sfmloc_client import FrameStreamer, PoseSubscriber

CLIENTS, FRAMES = 3, 30


def _flood(world, queue: int) -> tuple[int, dict[str, list]]:
    """CLIENTS clients send FRAMES frames each at 60 Hz to a 1-worker server; the most frames
    its worker held at once (sampled every ms from the pool's count of frames sent and not
    answered) and each client's poses."""
    zep = zenoh_endpoint()
    # no time budget: this is about order and counts, not the speed of a busy machine
    conf = server_config(
        world, zep, workers=1, worker_kind="process", worker_queue=queue, frame_budget_ms=0
    )
    poses: dict[str, list] = {f"flood-{i}": [] for i in range(CLIENTS)}
    with running_server(conf) as srv, client_zenoh(zep) as z:
        pool = srv.server.pool
        peak, stop = [0], threading.Event()

        def sample() -> None:
            while not stop.is_set():
                peak[0] = max(peak[0], pool.inflight()[0])
                time.sleep(0.001)

        def client(cid: str) -> None:
            with (
                PoseSubscriber(z, "room", cid, callback=poses[cid].append) as sub,
                FrameStreamer(z, "room", cid, camera(world)) as fs,
            ):
                assert fs.wait_for_server(30)
                fs.publish(data=world.png[0], encoding="png", seq=0)
                assert sub.wait_for(0, 60)  # a session on the worker, relocalized
                start.wait(30)
                for k in range(1, FRAMES + 1):
                    fs.publish(data=world.png[k % len(world.png)], encoding="png", seq=k)
                    time.sleep(1 / 60)
                assert sub.wait_for(FRAMES, 60)  # the last frame is always served

        start = threading.Barrier(CLIENTS + 1)
        threads = [threading.Thread(target=client, args=(c,)) for c in poses]
        for t in threads:
            t.start()
        start.wait(60)
        sampler = threading.Thread(target=sample)
        sampler.start()
        for t in threads:
            t.join(120)
        stop.set()
        sampler.join()
        # nothing is left in the worker once every client has its last pose
        assert srv.server.sessions.wait_idle(30)
    return peak[0], poses


@pytest.mark.parametrize("queue", [1, 0])
def test_frames_in_the_worker_stay_within_the_queue_and_every_client_is_served(world, queue):
    peak, poses = _flood(world, queue)
    if queue:
        assert peak == queue  # full while they flood, never beyond
    else:  # no limit: each busy session's frame waits in the worker's pipe
        assert peak >= 2
    for cid, got in poses.items():
        seqs = [p.seq for p in got]
        assert seqs == sorted(set(seqs)), cid  # in order, each at most once
        assert seqs[-1] == FRAMES and all(p.error is None for p in got), cid
        # a frame without a pose was dropped as stale, and the server says so
        assert got[-1].dropped == FRAMES + 1 - len(got), cid
