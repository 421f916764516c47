"""``sfmloc.bench.droptimeline``'s classification of drops and late poses, on a constructed
timeline with exact causes (the recording itself: tests/test_server_timeline.py)."""

from __future__ import annotations

import json

from sfmloc.bench.droptimeline import analyze


def _write(d, rows, clients) -> None:
    (d / "timeline-1.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (d / "clients.json").write_text(json.dumps({"clients": clients}))


def test_drops_and_late_poses_are_put_down_to_what_their_worker_did(tmp_path):
    # Sessions 1 and 2 on worker 0, session 3 on worker 1; frames every 33 ms from t = 10.
    rows = [["open", 9.0, 1, "a", 0], ["open", 9.0, 2, "b", 0], ["open", 9.0, 3, "c", 1]]
    sent = {"a": {}, "b": {}, "c": {}}
    answers: dict[str, list] = {"a": [], "b": [], "c": []}

    def frame(sid, cid, seq, t_sent, t_end, worker_ms, cpu, reloc=False, w=0):
        sent[cid][str(seq)] = t_sent
        rows.append(["recv", t_sent, sid, seq, False, False])
        rows.append(["start", t_end - worker_ms / 1e3, sid, seq, w, seq, reloc])
        status, matching = ("RELOCALIZED", "global") if reloc else ("TRACKING", "none")
        rows.append(
            ["res", t_end, sid, seq, w, seq, status, matching, worker_ms, 0.8, worker_ms, reloc]
        )
        answers[cid].append([seq, t_end + 0.001, status, matching, worker_ms, cpu, 1.0, None])

    def drop(sid, cid, seq, t_sent, t_drop):
        sent[cid][str(seq)] = t_sent
        rows.append(["recv", t_sent, sid, seq, True, False])
        rows.append(["drop", t_drop, sid, seq, seq + 1])

    # a's frame 1 relocalizes for 100 ms on worker 0: b's frame 1 waits behind it, is dropped
    frame(1, "a", 1, 10.0, 10.1, 100.0, 95.0, reloc=True)
    drop(2, "b", 1, 10.0, 10.033)
    frame(2, "b", 2, 10.033, 10.115, 14.0, 6.0)  # and its next pose is late (82 ms)
    # c's worker 1: a frame took 40 ms of wall on 6 ms of CPU (waited for a core)
    frame(3, "c", 1, 10.0, 10.04, 40.0, 6.0, w=1)
    drop(3, "c", 2, 10.033, 10.066)
    frame(3, "c", 3, 10.066, 10.13, 60.0, 6.0, w=1)  # late too, preempted again
    # later, on worker 1 alone, a 20 ms-CPU frame (a guided batch) makes c drop a frame
    frame(3, "c", 10, 12.0, 12.025, 25.0, 20.0, w=1)
    drop(3, "c", 11, 12.001, 12.034)
    clients = [{"client": c, "timeline": {"sent": sent[c], "answers": answers[c]}} for c in "abc"]
    _write(tmp_path, rows, clients)
    a = analyze(tmp_path)
    assert a["drops"] == 3
    assert a["drop_causes"] == {"other-reloc": 1, "preempted": 1, "heavy-cpu": 1}
    # a's relocalization itself (100 ms) is late for its own reason; b's and c's poses
    assert a["late_poses"] == 3
    assert a["late_causes"] == {"own-reloc": 1, "other-reloc": 1, "preempted": 1}
    (r,) = a["relocalizations"]
    assert (r["client"], r["seq"], r["other_drops"], r["own_drops"]) == ("a", 1, 1, 0)
