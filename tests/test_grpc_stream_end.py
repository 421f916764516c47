"""A gRPC stream ends only after each of its frames is answered or counted skipped.

The stream's end waited for "no frame of its session in a worker". A session whose frames wait
for their turn at a full worker (``worker_queue``) has none there: the stream ended at once, and
its waiting frame was dropped at the session's close, with no answer and no later answer to
count it in (a silent frame). Forced here: a real server with one real worker process and a
one-frame worker queue; another client's frame holds the worker (stopped with SIGSTOP) while a
gRPC stream sends its frames and ends."""

from __future__ import annotations

import os
import signal

import pytest

from server_helpers import (
    running_server,
    server_config,
    streaming_client,
    wait_until,
    zenoh_endpoint,
)

BUDGET_MS = 3000.0  # a frame waiting for its turn this long is answered DEADLINE_EXCEEDED


@pytest.fixture(scope="module")
def zep():
    return zenoh_endpoint()


@pytest.fixture(scope="module")
def srv(world, zep):
    conf = server_config(
        world,
        zep,
        workers=1,
        worker_kind="process",
        relocalize_workers=0,
        worker_queue=1,
        frame_budget_ms=BUDGET_MS,
        frame_hang_ms=20000.0,  # the holder's frame is not answered while the test runs
    )
    with running_server(conf) as s:
        yield s


def test_a_stream_ending_while_its_frames_wait_for_a_full_worker_answers_them(world, zep, srv):
    """Three frames sent at once while the worker is full: the first two are superseded (each
    counted in ``dropped``), the newest waits for its turn and is answered DEADLINE_EXCEEDED at
    its time budget (the worker never frees): one answer, two counted, none silent. Before,
    the stream ended with no answer at all."""
    from sfmloc_client import LocalizationClient

    sessions, pool = srv.server.sessions, srv.server.pool
    with (
        streaming_client(zep, world, "holder") as (fs, got),
        LocalizationClient(f"127.0.0.1:{srv.grpc_port}", timeout=60) as c,
    ):
        fs.publish(data=world.png[0], encoding="png", seq=0, stamp_ns=0)
        assert got.has_seq(0, 60)
        pid = pool.workers[0].pid
        os.kill(pid, signal.SIGSTOP)
        try:
            fs.publish(data=world.png[1], encoding="png", seq=1, stamp_ns=1)
            # The holder's frame takes the worker's one slot (and stays: the worker is stopped).
            assert wait_until(
                lambda: any(s.client_id == "holder" and s.busy for s in sessions.list()), 30
            )
            poses = list(c.stream(world.png[:3], "room", world.camera_spec, encoding="png"))
        finally:
            os.kill(pid, signal.SIGCONT)
    assert [p.seq for p in poses] == [2], [(p.seq, p.status, p.message) for p in poses]
    assert len(poses) + poses[-1].dropped == 3
    last = poses[-1]
    assert last.error is not None and last.error.code == "DEADLINE_EXCEEDED", last
    assert "time budget" in last.message
