"""The reliability measurement end to end in a tiny configuration: a real ``sfmloc serve``
subprocess, fuzzed Zenoh and gRPC inputs beside a canary, one worker killed under one client,
one-byte flips of a bundle. Asserts that every summary field is computed, not the targets."""

from __future__ import annotations

import math

import numpy as np
import pytest


@pytest.fixture(scope="module")
def w(world):
    """The synthetic world as the reliability measurement takes it."""
    from sfmloc.bench import reliability as rel
    from sfmloc.map.bundle import MapBundle

    return rel.World(
        maps_dir=world.maps_dir,
        camera=world.camera_spec,
        gray=world.gray,
        gt_cam_from_world=[np.asarray(g.matrix()) for g in world.gt_cam_from_world],
        scene_scale=MapBundle(world.maps_dir / "room", verify=False).scene_scale,
    )


def test_reliability_tiny_run_computes_every_field(world, w, tmp_path):
    from sfmloc.bench import reliability as rel

    # The exact ground truth scores itself as right, and a pose 10% of the scene off as wrong.
    assert not rel.pose_is_wrong(0.0, 0.0) and rel.pose_is_wrong(0.1, 0.0)
    assert [rel.pingpong(4, k) for k in range(8)] == [0, 1, 2, 3, 2, 1, 0, 1]
    args = rel.parser().parse_args(
        [
            "--fuzz",
            "200",
            "--kills",
            "2",  # one of a worker, one of its replacement while it loads
            "--clients",
            "1",
            "--interval",
            "2.5",
            "--rate",
            "5",
            "--baseline",
            "3",  # > the 2 s frame budget: the lockstep canary sends at least once, any load
            "--flips-per-file",
            "2",
            "--every-byte-under",
            "0",
            "--no-all-manifest-bytes",
            "--header-bytes",
            "0",
            "--cli-checks",
            "0",
            "--work",
            str(tmp_path),
        ]
    )
    res = rel.run(args, world=w)

    f = res["fuzz"]
    assert f["inputs"] == 200 and f["duration_s"] > 0
    assert sum(v for k, v in f["kinds"].items() if k.startswith("zenoh")) == 100
    grpc_calls = sum(v for k, v in f["kinds"].items() if k.startswith("grpc"))
    assert grpc_calls == 100 and sum(f["grpc_codes"].values()) == grpc_calls
    assert f["internal"] == f["grpc_codes"].get("INTERNAL", 0)
    assert isinstance(f["crashes"], int) and isinstance(f["hangs"], int)
    c = f["canary"]
    assert c["sent"] >= 1 and 0 <= c["answered"] <= c["sent"] + 1
    assert c["localized"] <= c["answered"] and c["wrong"] <= c["localized"]
    assert 0.0 <= f["canary_lost_pct"] <= 100.0
    cb = f["canary_baseline"]
    assert cb["sent"] >= 1 and cb["localized"] <= cb["answered"] <= cb["sent"]

    k = res["kill"]
    assert k["kills"] == 2 and k["loading_kills"] == 1 and k["clients"] == 1 and k["sent"] >= 1
    assert k["log"]["worker_lost"] == 2 and isinstance(k["log"]["problems"], list)
    assert k["answered"] + k["dropped_stale"] + k["unanswered"] >= k["answered"]
    assert math.isfinite(k["max_gap_s"]) and k["max_gap_s"] > 0
    assert isinstance(k["zombies_after_1s_max"], int) and isinstance(k["restarts"], int)
    assert k["recovery_s_max"] is None or k["recovery_s_max"] > 0
    # the server's counts at shutdown, read back from its log (at info level)
    assert k["exact"]["sessions_not_closed"] == [] and k["exact"]["lost"] >= 0
    assert k["exact"]["silent"] >= 0  # more answers than frames kept would be a miscount
    kb = k["baseline"]
    assert kb["sent"] >= 1 and kb["answered"] <= kb["sent"] and kb["wrong"] <= kb["localized"]

    b = res["bundle"]
    files = sorted(p.name for p in (world.maps_dir / "room").iterdir())
    assert b["files"] == len(files) and "manifest.json" in {r["file"] for r in b["rows"]}
    assert b["flips"] >= len(files) and 0 <= b["verify_refused"] <= b["flips"]
    assert b["restored_intact"]  # the copy was put back byte for byte after each flip
    lines = rel.table(res)
    assert any(line.startswith("fuzz: crashes / hangs") for line in lines)
    assert any(line.startswith("bundle: refused by verify / load") for line in lines)


def test_reliability_reloc_part_computes_every_field(w, tmp_path):
    """The isolation part (issue 16): streams alone, then beside Relocalize callers."""
    from sfmloc.bench import reliability as rel

    images = rel.reloc_images(w, 256)
    assert [(k, e) for k, e, _, _ in images] == [("blank", "png"), ("textured", "jpeg")]
    assert all(c.split()[1:3] == ["256", "256"] for *_, c in images)
    args = rel.parser().parse_args(
        [
            "--parts",
            "reloc",
            "--clients",
            "1",
            "--reloc-callers",
            "1",
            "--reloc-rate",
            "5",
            "--reloc-duration",
            "3",
            "--reloc-side",
            "1024",
            "--baseline",
            "1.5",
            "--work",
            str(tmp_path),
        ]
    )
    res = rel.run(args, world=w)
    r = res["reloc"]
    assert r["server_alive"] and r["clients"] == 1 and r["side"] == 1024
    assert sum(r["reloc_codes"].values()) >= 1  # the caller got answers (or refusals)
    for p in (*r["clients_detail"], *r["clients_alone"]):
        assert p["sent"] >= 1 and p["localized"] <= p["answered"] <= p["sent"]
    assert 0.0 < r["poses_frac_min_alone"] <= 1.0 and 0.0 <= r["poses_frac_min"] <= 1.0
    assert r["p99_ms_max_alone"] > 0
    assert any(line.startswith("reloc: p99 latency") for line in rel.table(res))


def test_reliability_restart_and_soak_parts_compute_every_field(w, tmp_path):
    """Server kill -9 and restart under a client and an `sfmloc stream` process; a short soak
    with short-lived `sfmloc stream` processes (issues 12 and 16): the fields, not the targets."""
    from sfmloc.bench import reliability as rel

    args = rel.parser().parse_args(
        [
            "--parts",
            "restart,soak",
            "--restarts",
            "1",
            "--clients",
            "1",
            "--rate",
            "5",
            "--restart-interval",
            "4",
            "--workers",
            "1",
            "--soak-minutes",
            "0.15",
            "--soak-clients",
            "2",
            "--soak-streams",
            "1",
            "--soak-rate",
            "5",
            "--soak-sample",
            "2",
            "--soak-idle-timeout",
            "2",
            "--work",
            str(tmp_path),
        ]  # fmt: skip
    )
    res = rel.run(args, world=w)
    r = res["restart"]
    assert r["restarts"] == 1 and len(r["serving_s"]) == 1 and r["serving_s"][0] > 0
    assert r["first_start_s"] > 0 and r["old_workers_alive_max"] == 0
    assert r["sent"] >= 1 and r["localized"] <= r["answered"] <= r["sent"]
    assert "poses received for" in r["cli_summary"] and r["cli_exit"] in (0, 1)
    s = res["soak"]
    assert s["short_clients"] == 2 and sum(s["short_exit_codes"].values()) == 2
    assert s["samples"] and all(x["server_rss_mb"] > 0 and x["workers"] >= 1 for x in s["samples"])
    assert s["rss_mb_warm"] > 0 and s["rss_mb_peak"] >= s["rss_mb_warm"]
    # Every session ended by itself after the idle timeout (the short clients' and the stream's).
    assert s["short_sessions_left"] == 0 and s["sessions_left"] == 0 and s["server_alive"]
    lines = rel.table(res)
    assert any(ln.startswith("restart: SERVING after") for ln in lines)
    assert any(ln.startswith("soak: sessions max / left") for ln in lines)


def test_gaps_part_feeds_the_engine_an_overloaded_pattern_and_scores_it(w):
    """The gaps part (no server): every pose it scores, wrong ones with their context."""
    from sfmloc.bench import reliability as rel

    g = rel.run_gaps(w, frames=25, seed=3, restart_p=0.2)
    assert g["frames"] == 25 and g["restarts"] >= 1
    assert 0 < g["posed"] <= 25 and g["wrong"] == len(g["wrong_detail"])
    assert any(line.startswith("gaps") for line in rel.table({"gaps": g}))


def test_kill_log_check_reads_what_the_log_says():
    from sfmloc.bench.reliability import kill_log_check

    def lost(pid, gen, start, code="-9", worker="0"):
        return {
            "pid": str(pid),
            "worker": worker,
            "gen": str(gen),
            "exitcode": code,
            "during_start": "true" if start else "false",
        }

    killed = [(10, False), (11, True)]
    restarted = [{"worker": "0", "gen": "3"}]
    ok = kill_log_check(killed, [lost(10, 1, False), lost(11, 2, True)], restarted, [])
    assert ok["ok"] and ok["during_start"] == 1 and ok["worker_lost"] == 2
    # a replacement logged as if it had served; a kill the log never mentions
    bad = kill_log_check(killed, [lost(10, 1, False), lost(11, 2, False)], restarted, [])
    assert not bad["ok"] and "pid 11: during_start=false" in bad["problems"][0]
    assert not kill_log_check(killed, [lost(10, 1, False)], restarted, [])["ok"]
    # the last generation lost was never followed by a restart that served
    assert not kill_log_check(killed, [lost(10, 1, False), lost(11, 2, True)], [], [])["ok"]
    # exit codes other than the kill's, generations out of order, a given-up worker
    assert not kill_log_check([(10, False)], [lost(10, 1, False, code="null")], restarted, [])["ok"]
    assert not kill_log_check(killed, [lost(11, 2, True), lost(10, 1, False)], restarted, [])["ok"]
    assert not kill_log_check(killed, [lost(10, 1, False), lost(11, 2, True)], restarted, [{}])[
        "ok"
    ]


def test_drops_are_counted_in_their_window_from_the_answers_around_it():
    """Frames 0-9 sent at t=0-9; the answers carry the session's drop count so far. Frame 6
    was dropped after the window's last answer (frame 5): it is a drop, not silence."""
    from sfmloc.bench.reliability import ClientLog, _dropped_within

    lg = ClientLog("c", sent={q: float(q) for q in range(10)})
    lg.dropped_by_seq = {0: 0, 2: 1, 3: 1, 5: 2, 8: 4}  # 1 dropped, then 4, then 6 and 7
    lg.answered = {q: q + 0.5 for q in lg.dropped_by_seq}
    assert _dropped_within(lg, 3.0, 6.0) == 2  # frames 4 and 6 (7: after the window)
    assert _dropped_within(lg, 0.0, 9.0) == 4  # 1, 4, 6, 7
    assert _dropped_within(lg, 8.5, 9.5) == 0  # nothing answered there or after


def test_a_restart_that_leaves_a_client_without_a_pose_is_counted_not_warned():
    """After a restart the time until every client posed is the last client's, nan when one
    never posed (whatever its place in the list: Python's max of [1.0, nan] is 1.0), and a run
    where no restart posed every client summarizes to nan without numpy's All-NaN warning."""
    import warnings

    from sfmloc.bench.reliability import _nanmax, every_client_posed_s

    assert every_client_posed_s([0.4, 1.2, 0.7]) == 1.2
    nan = float("nan")
    for rec in ([1.0, nan], [nan, 1.0], [nan, nan], []):
        assert math.isnan(every_client_posed_s(rec)), rec
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert math.isnan(_nanmax([every_client_posed_s([nan])] * 2))
        assert _nanmax([nan, 2.5, 1.0]) == 2.5
