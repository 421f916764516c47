"""The server's per-frame timeline (``sessions.TIMELINE_ENV``, issue 10's drop diagnosis) with
a real ``sfmloc serve`` process and a real Zenoh client: every frame the client sent is in it,
either started in a worker and answered, or superseded (dropped) by a newer one of its session;
nothing is written without the variable. No assertion on any time taken."""

from __future__ import annotations

import json
import os

from server_helpers import Collected, camera, client_zenoh
from sfmloc.server.sessions import TIMELINE_ENV
from sfmloc.testing import ServerProcess


def test_timeline_records_every_frame_as_answered_or_dropped(world, tmp_path):
    from sfmloc_client import FrameStreamer, PoseSubscriber

    folder = tmp_path / "timeline"
    n = 30
    got = Collected()
    with ServerProcess(
        world.maps_dir, workers=1, env={**os.environ, TIMELINE_ENV: str(folder)}
    ) as srv:
        with (
            client_zenoh(srv.endpoint) as z,
            PoseSubscriber(z, "room", "tl", callback=got.append) as poses,
            FrameStreamer(z, "room", "tl", camera(world), congestion="block") as fs,
        ):
            assert fs.wait_for_server(30)
            for k in range(n):  # a burst: most frames are superseded while one is in the worker
                fs.publish(data=world.png[k], encoding="png", seq=k, stamp_ns=int(k * 1e9 / 30))
            assert poses.wait_for(n - 1, 60)
        assert srv.stop() == 0  # the timeline is written at the graceful shutdown
    files = list(folder.glob("timeline-*.jsonl"))
    assert len(files) == 1
    rows = [json.loads(line) for line in files[0].read_text().splitlines()]
    opened = [r for r in rows if r[0] == "open"]
    assert [r[3] for r in opened] == ["tl"]
    sid = opened[0][2]
    recv = {r[3] for r in rows if r[0] == "recv" and r[2] == sid}
    started = {r[3] for r in rows if r[0] == "start" and r[2] == sid}
    answered = {r[3]: r for r in rows if r[0] == "res" and r[2] == sid}
    dropped = {r[3] for r in rows if r[0] == "drop" and r[2] == sid}
    assert recv == set(range(n))
    assert started == set(answered) and not started & dropped
    assert started | dropped == set(range(n))  # each frame answered or superseded, never lost
    assert dropped and len(dropped) == max(p.dropped for p in got)
    poses_by_seq = {p.seq: p for p in got}
    assert set(poses_by_seq) == set(answered)
    for seq, r in answered.items():  # status and matching as the client got them
        assert (r[6], r[7]) == (poses_by_seq[seq].status, poses_by_seq[seq].matching)
