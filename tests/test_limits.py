"""Per-client limits: the token bucket and the log limiter (exact counts on a controlled clock),
and both inside a running server (real Zenoh, real worker) beside a well-behaved client."""

from __future__ import annotations

import logging

from server_helpers import (
    client_zenoh,
    running_server,
    server_config,
    stream_lockstep,
    wait_until,
    zenoh_endpoint,
)
from sfmloc.server.limits import LogLimiter, RateLimiter


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_rate_limiter_allows_rate_and_burst_per_key():
    clk = Clock()
    rl = RateLimiter(rate=10.0, burst=5.0, clock=clk)
    assert [rl.allow("a") for _ in range(7)] == [True] * 5 + [False] * 2  # the burst, then refused
    assert rl.allow("b")  # another key has its own bucket
    clk.t = 0.1  # one token back (10/s)
    assert rl.allow("a") and not rl.allow("a")
    clk.t = 100.0  # refills only up to the burst
    assert sum(rl.allow("a") for _ in range(10)) == 5


def test_rate_limiter_tracks_a_bounded_number_of_keys():
    rl = RateLimiter(rate=1.0, burst=1.0, max_keys=100, clock=Clock())
    for k in range(10_000):
        rl.allow(f"client-{k}")
    assert len(rl._buckets) == 100


def test_rate_limiter_forgets_clients_whose_bucket_is_full_again():
    """Clients that came and went leave nothing behind once their bucket would be full again
    (forgetting it then changes no answer); a client still refilling is kept."""
    clk = Clock()
    rl = RateLimiter(rate=10.0, burst=5.0, clock=clk)
    for k in range(1000):
        rl.allow(f"gone-{k}")
    clk.t = 0.3
    for _ in range(5):
        rl.allow("busy")  # empties its bucket
    clk.t = 0.6  # the others' buckets are full again (0.5 s at 10/s); busy's is not
    assert rl.allow("new")
    assert list(rl._buckets) == ["busy", "new"]
    assert sum(rl.allow("busy") for _ in range(5)) == 3  # busy's state was kept: 3 tokens back
    clk.t = 10.0  # everyone gone: the table empties without another frame
    assert rl.prune() == 2 and len(rl) == 0


def test_log_limiter_caps_lines_and_summarizes(caplog):
    clk = Clock()
    log = logging.getLogger("sfmloc.test.limits")
    lim = LogLimiter(log, "frame_rejected", interval_s=10.0, per_key=3, total=50, clock=clk)
    allowed = sum(lim.allow("loud", "INVALID_ARGUMENT") for _ in range(1000))
    assert allowed == 3
    allowed = sum(lim.allow(f"id-{k}", "INVALID_ARGUMENT") for k in range(1000))  # random ids
    assert allowed == 47  # the overall cap: 50 lines per interval
    with caplog.at_level(logging.WARNING, logger="sfmloc.test.limits"):
        lim.flush()  # the interval is not over: nothing yet
        assert not caplog.records
        clk.t = 10.0
        assert lim.allow("loud", "INVALID_ARGUMENT")  # a new interval; the summary comes first
    summary = [r for r in caplog.records if getattr(r, "event", "") == "frame_rejected_suppressed"]
    assert len(summary) == 1
    f = summary[0].fields
    assert f["count"] == 997 + 953 and f["codes"] == {"INVALID_ARGUMENT": 1950}
    assert f["top_clients"][0] == "loud"


def test_a_flood_is_refused_logged_in_summary_and_others_are_served(world, caplog):
    """2000 malformed frames under random client ids and a client far over its frame rate:
    every rejection is either logged or counted in a summary line (exactly), the log stays
    short, over-rate frames are refused with RESOURCE_EXHAUSTED and counted in the metric, and
    a well-behaved client gets every pose."""
    from sfmloc_client import PoseSubscriber
    from sfmloc_client.wire import frame_key

    def logged() -> tuple[int, int]:
        recs = list(caplog.records)
        lines = sum(getattr(r, "event", "") == "frame_rejected" for r in recs)
        held = sum(
            r.fields["count"]
            for r in recs
            if getattr(r, "event", "") == "frame_rejected_suppressed"
        )
        return lines, held

    ep = zenoh_endpoint()
    conf = server_config(world, ep, max_client_fps=50.0, log_interval_s=0.5)
    with (
        caplog.at_level(logging.INFO, logger="sfmloc.server"),
        running_server(conf) as srv,
        client_zenoh(ep) as z,
    ):
        for k in range(2000):
            z.put(frame_key("room", f"garbage-{k}"), b"\x93\x01\x02" + bytes(k % 7))
        replies: list = []
        m = srv.server.metrics
        with PoseSubscriber(z, "room", "flooder", callback=replies.append):
            for _ in range(400):  # far beyond 50/s with a burst of 100
                z.put(frame_key("room", "flooder"), b"\x00not a frame")
            # Every frame is answered on the server's side; error replies go out with congestion
            # control DROP, so under load not all of them need to reach us.
            assert wait_until(
                lambda: (
                    m.frame_errors.get("room", "INVALID_ARGUMENT")
                    + m.frame_errors.get("room", "RESOURCE_EXHAUSTED")
                    == 2400
                ),
                60,
            )
            assert wait_until(
                lambda: any(p.error.code == "RESOURCE_EXHAUSTED" for p in replies), 30
            )
        assert {p.error.code for p in replies} <= {"INVALID_ARGUMENT", "RESOURCE_EXHAUSTED"}
        refused = m.frames_refused.get("rate")
        assert (
            refused == m.frame_errors.get("room", "RESOURCE_EXHAUSTED") and refused >= 200
        )  # burst of 100
        poses = stream_lockstep(z, "room", "canary", world, n=30)
        assert [p.seq for p in poses] == list(range(30)) and all(p.error is None for p in poses)
        assert wait_until(lambda: sum(logged()) == 2400, 30)  # every rejection accounted for
    lines, held = logged()
    assert lines <= 250 and held >= 2150  # before: one line per rejected frame (2400)
