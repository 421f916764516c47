"""The first frames of a stream (issue 12, subscription timing), with real Zenoh sessions and a
real server: frames published while no server subscribes are lost by Zenoh without a word, so
the streamer counts and logs them and ``run()`` waits for a server before its first frame; a
pose subscription declared just before the first frame gets that frame's answer, an immediate
error reply included."""

from __future__ import annotations

import threading

import pytest
import zenoh

from server_helpers import camera, running_server, server_config, zenoh_endpoint
from sfmloc_client import FrameStreamer, PoseSubscriber, SourceFrame, make_zenoh_config


def test_a_client_started_before_its_server_loses_no_frame_silently(world, caplog):
    endpoint = zenoh_endpoint()
    # The client first: a peer session connecting to an endpoint nobody listens on yet.
    with zenoh.open(make_zenoh_config("peer", connect=[endpoint], multicast=False)) as z:
        got: list = []
        with (
            PoseSubscriber(z, "room", "early", callback=got.append) as poses,
            FrameStreamer(z, "room", "early", camera(world), encoding="png") as fs,
        ):
            with caplog.at_level("WARNING", logger="sfmloc_client.streamer"):
                assert fs.publish(data=world.png[0], encoding="png") == 0
            assert fs.undelivered == 1  # counted: Zenoh dropped it, no server subscribed
            assert any("not delivered" in r.getMessage() for r in caplog.records)
            with running_server(server_config(world, endpoint)):
                # run() waits for the server before its first frame: all three are answered.
                src = [SourceFrame(data=world.png[k], encoding="png") for k in (1, 2, 3)]
                stats = fs.run(src, lockstep=True, poses=poses, pose_timeout=30, wait_server=60)
                assert poses.wait_for(stats.last_seq, 30)
            assert stats.sent == 3 and stats.undelivered == 0 and fs.undelivered == 1
            assert sorted(p.seq for p in got) == [1, 2, 3]


@pytest.mark.parametrize("map_name", ["room", "nosuchmap"])
def test_a_pose_subscription_declared_just_before_the_first_frame_gets_its_answer(world, map_name):
    """Fresh client sessions, each declaring its pose subscription right before publishing its
    first frame: every one gets that frame's answer (a pose, or NOT_FOUND sent at once from the
    server's Zenoh callback). 300 such sessions missed none when measured."""
    endpoint = zenoh_endpoint()
    with running_server(server_config(world, endpoint)):
        for i in range(10):
            with zenoh.open(make_zenoh_config("peer", connect=[endpoint], multicast=False)) as z:
                answered = threading.Event()
                fs = FrameStreamer(z, map_name, f"first-{i}", camera(world), encoding="png")
                assert fs.wait_for_server(30)
                with PoseSubscriber(
                    z, map_name, f"first-{i}", callback=lambda p, a=answered: a.set()
                ):
                    fs.publish(data=world.png[0], encoding="png")
                    assert answered.wait(30), f"session {i}: no answer to its first frame"
                fs.close()


def test_a_frame_addressed_to_no_server_is_still_counted_lost(world):
    """The new addressed publisher waits (bounded) for its match status before its first frame
    (a frame through a router was counted lost while it arrived); a frame that names a server
    nobody runs is still counted: the count holds exactly the frames no server could get."""
    endpoint = zenoh_endpoint()
    with (
        running_server(server_config(world, endpoint, server_id="here")),
        zenoh.open(make_zenoh_config("peer", connect=[endpoint], multicast=False)) as z,
    ):
        with FrameStreamer(z, "room", "lonely", camera(world), encoding="png", server="gone") as fs:
            fs.match_wait_s = 0.2
            assert fs.wait_for_server(30)  # "here" subscribes to the map-wide key
            fs.publish(data=world.png[0], encoding="png")
            fs.publish(data=world.png[1], encoding="png")
            assert fs.undelivered == 2
        got: list = []
        with (
            PoseSubscriber(z, "room", "named", callback=got.append) as poses,
            FrameStreamer(z, "room", "named", camera(world), encoding="png", server="here") as fs,
        ):
            assert fs.wait_for_server(30)
            fs.publish(data=world.png[0], encoding="png")
            assert poses.wait_for(0, 30) and fs.undelivered == 0


def test_a_long_stream_keeps_a_bounded_record_of_its_send_times(world):
    """``StreamStats.send_ms`` holds the last SEND_MS_KEEP frames' send times, not one per frame
    of the whole stream (a client streams for hours: ~3 MB an hour at 30 Hz before)."""
    from sfmloc_client.streamer import SEND_MS_KEEP

    endpoint = zenoh_endpoint()
    n = SEND_MS_KEEP + 25
    with (
        zenoh.open(make_zenoh_config("peer", connect=[endpoint], multicast=False)) as z,
        FrameStreamer(z, "room", "long", camera(world), encoding="png") as fs,
    ):
        src = [SourceFrame(data=world.png[0], encoding="png")] * n
        stats = fs.run(src, wait_server=0)  # no server: every frame is counted lost, and timed
    assert stats.sent == n and stats.undelivered == n
    assert len(stats.send_ms) == SEND_MS_KEEP and all(t >= 0 for t in stats.send_ms)
