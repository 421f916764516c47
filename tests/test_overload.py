"""An overloaded server sheds load instead of thrashing (issue 10): a real server with one
engine worker process and six real Zenoh clients streaming the synthetic walk.

First each client streams at 30 Hz (far more than one worker serves, 180 frames/s): every
client is answered, every frame without an answer was counted dropped and said so (no silent
frame), and the sessions took their turns as promised (tests/turn_promise.py, on the server's
own timeline: first turns in the order the clients came, each after no more tracked frames
than the relocalizations ahead of it allow). Equal poses per client in those 2 s are not
promised: on a loaded machine the first sessions track while the last new ones wait their
turns one relocalization apart (at load 8.6 one client got only its last frame, beside 12;
tests/test_overload_turns.py shows both on a simulated clock). Then each client sends its
frames in bursts of four (a camera at 30 Hz whose frames the server mostly skips) and waits
for the burst's last answer: the sessions keep tracking across the skipped frames, with right
poses against the world's exact ground truth, instead of relocalizing after every gap.

No timing is asserted: the second part runs on the camera's clock (stamps), whatever the
machine's speed, over the frames the engine worked on (a frame the 2 s time budget answered
DEADLINE_EXCEEDED on a starved machine was not); a slow machine only makes the first part
answer fewer frames, and the turns' promise is an order and a sum of the worker's own times,
not a duration."""

from __future__ import annotations

import threading
import time

import numpy as np

from server_helpers import camera, client_zenoh, running_server, server_config, zenoh_endpoint
from sfmloc.server.sessions import TIMELINE_ENV
from sfmloc_client import FrameStreamer, PoseSubscriber
from turn_promise import first_turn_breaches

CLIENTS = 6
FREE_FRAMES = 60  # per client, at 30 Hz
BURST, ROUNDS = 4, 12  # then: bursts of frames, one answer awaited per burst


def _walk(n: int):
    """Frame indices 0..n-1, n-2..1, 0.. (there and back: the camera moves continuously)."""
    k = 0
    while True:
        p = k % (2 * (n - 1))
        yield p if p < n else 2 * (n - 1) - p
        k += 1


def test_an_overloaded_server_answers_every_client_fairly_and_keeps_their_tracks(
    world, tmp_path, monkeypatch
):
    from sfmloc.map.bundle import MapBundle
    from sfmloc.transforms import Rigid3d

    scale = MapBundle(world.maps_dir / "room").scene_scale
    zep = zenoh_endpoint()
    # the server's defaults (worker queue, turns, frame budget), one engine worker
    conf = server_config(world, zep, workers=1, worker_kind="process")
    monkeypatch.setenv(TIMELINE_ENV, str(tmp_path))  # the turns as the server took them
    results: dict[str, dict] = {}
    with running_server(conf) as srv, client_zenoh(zep) as z:
        start, middle = threading.Barrier(CLIENTS), threading.Barrier(CLIENTS)

        def client(cid: str) -> None:
            poses: list = []
            cond = threading.Condition()

            def on_pose(p) -> None:
                with cond:
                    poses.append(p)
                    cond.notify_all()

            def answered(seq: int) -> bool:
                return any(p.seq == seq for p in reversed(poses))

            walk, frame_of, seq = _walk(len(world.png)), {}, 0

            def publish(fs: FrameStreamer) -> None:
                nonlocal seq
                frame_of[seq] = k = next(walk)
                # stamped on the camera's 30 Hz clock
                fs.publish(data=world.png[k], encoding="png", seq=seq, stamp_ns=seq * 10**9 // 30)
                seq += 1

            with (
                PoseSubscriber(z, "room", cid, callback=on_pose),
                FrameStreamer(z, "room", cid, camera(world)) as fs,
            ):
                assert fs.wait_for_server(30)
                start.wait(120)
                t0 = time.monotonic()
                for i in range(FREE_FRAMES):
                    time.sleep(max(0.0, t0 + i / 30 - time.monotonic()))
                    publish(fs)
                with cond:  # the last frame sent is always answered (latest frame wins)
                    assert cond.wait_for(lambda: answered(seq - 1), 120), cid
                    free = list(poses)
                middle.wait(120)
                for _ in range(ROUNDS):
                    for _ in range(BURST):
                        publish(fs)
                    with cond:
                        assert cond.wait_for(lambda: answered(seq - 1), 120), cid
                with cond:
                    bursts = poses[len(free) :]
            results[cid] = {"free": free, "bursts": bursts, "frame_of": frame_of}

        threads = [threading.Thread(target=client, args=(f"overload-{i}",)) for i in range(CLIENTS)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(600)
        assert srv.server.sessions.wait_idle(30)
        sessions = srv.server.sessions
        assert sessions.timeline is not None
        turns = first_turn_breaches(
            list(sessions.timeline), sessions.cold_gap_s, sessions.relocalize_share
        )
    assert len(results) == CLIENTS

    # 1. At 30 Hz each: every frame answered or counted dropped, every client served.
    for cid, r in results.items():
        seqs = [p.seq for p in r["free"]]
        assert seqs == sorted(set(seqs)), cid  # in order, each frame at most once
        # no silent frame: one without an answer was dropped as stale, and counted so
        assert r["free"][-1].dropped == FREE_FRAMES - len(seqs), cid
    assert sum(r["free"][-1].dropped for r in results.values()) > 0  # it was overloaded
    # fair: every client served (its last frame at least, above), and the new sessions got
    # their turns as promised, whatever the machine's speed (not equal counts in 2 s: above)
    served = {cid: len(r["free"]) for cid, r in results.items()}
    assert turns == [], (turns, served)

    # 2. Bursts: the frames skipped are a lower frame rate, not a reason to relocalize.
    for cid, r in results.items():
        poses = r["bursts"]
        total = FREE_FRAMES + BURST * ROUNDS
        assert poses[-1].dropped == total - len(r["free"]) - len(poses), cid  # none silent
        worked, tracked, dropped = [], [], r["free"][-1].dropped
        for p in poses:
            # A frame the time budget answered (DEADLINE_EXCEEDED: on a starved machine it
            # waited for the worker past frame_budget_ms, as promised) was not worked on: it
            # neither tracked nor relocalized (at load ~11, three busy loops beside, 6 of a
            # client's 12 bursts were so answered, and the check below counted them as lost).
            if p.dropped > dropped and not (p.error and p.error.code == "DEADLINE_EXCEEDED"):
                worked.append(p)  # worked on right after frames the server skipped
                if p.status == "TRACKING":
                    tracked.append(p)  # posed by tracking
            dropped = p.dropped
        # (the first bursts may relocalize: the free part may have left the session lost)
        assert len(tracked) >= min(ROUNDS, len(worked)) // 2, (
            cid,
            [(p.seq, p.status, p.error and p.error.code) for p in poses],
        )
        for p in tracked:
            gt = world.gt_cam_from_world[r["frame_of"][p.seq]]
            got = Rigid3d.from_transform(p.cam_from_world)
            assert np.linalg.norm(got.center - gt.center) < 0.05 * scale, (cid, p.seq)
