"""The session manager's promise to sessions waiting for their first turn on a full worker,
checked on its per-frame timeline (``sessions.TIMELINE_ENV``: rows in the order the manager
took its decisions). Shared by the real server's overload test (tests/test_overload.py) and
the simulated clock's (tests/test_overload_turns.py), which shows the check fails on a
manager that starves such sessions.

The promise (README, "Worker queue"; ``server/sessions.py``): a session's first frame will
relocalize, so the session waits as a relocalizing one, due ``cold_gap_s`` after its first
frame's receipt;

1. the sessions waiting for their first turn get it in the order their first frames came
   (first come, first served: nobody is overtaken by a later one);
2. once due, a session waits only for the relocalizations of the worker's queue: the worker's
   time on tracked frames handed over between its due moment and its turn is at most as much
   as its relocalizations in that span (and the one before it, whose debt may still be owed)
   take, times (1 - ``relocalize_share``) / ``relocalize_share``, give or take one tracked
   frame per relocalization and one per session (a tracked session due before it goes once).

Both are orders and sums of the worker's own times, not wall-clock durations: they hold on a
machine of any speed. A session whose frame the time budget answered (DEADLINE_EXCEEDED,
``frame_budget_ms``) before its first turn is left out: its wait was cut, as promised too.
How many poses each client gets in a fixed wall-clock window is not promised: a
relocalization costs 5-20 tracked frames, so on a loaded machine the last of several new
sessions waits behind the others' relocalizations for more than a second of wall time while
the first ones track."""

from __future__ import annotations

from typing import Any


def first_turn_breaches(
    rows: list[tuple[Any, ...]], cold_gap_s: float = 1.0, share: float = 0.5
) -> list[str]:
    """What of the promise above the timeline ``rows`` break (empty: none). Rows as the
    manager records them: ("recv", t, sid, seq, ...), ("start", t, sid, seq, worker, ticket,
    cold), ("res", t, sid, seq, worker, ticket, status, matching, worker_ms, decode_ms,
    engine_ms, relocalized), with one worker's sessions."""
    res = {r[5]: r for r in rows if r[0] == "res"}
    first_recv: dict[int, tuple[int, float]] = {}  # sid -> (row, receipt time)
    first_start: dict[int, int] = {}  # sid -> row
    start_row: dict[int, int] = {}  # ticket -> row
    direct: set[int] = set()  # sessions whose first frame went to the worker at once
    for i, r in enumerate(rows):
        if r[0] == "recv" and r[2] not in first_recv:
            first_recv[r[2]] = (i, r[1])
            # started in the same hold of the manager's lock: the worker had room, no wait
            if i + 1 < len(rows) and rows[i + 1][0] == "start" and rows[i + 1][2] == r[2]:
                direct.add(r[2])
        elif r[0] == "start":
            first_start.setdefault(r[2], i)
            start_row[r[5]] = i
    # A frame received, then neither superseded ("drop") nor handed over ("start"), was
    # answered by the time budget (``frame_budget_ms``: DEADLINE_EXCEEDED, as promised on a
    # starved machine): a session whose frame went so before its first turn had its wait cut,
    # and waits anew from its next frame. The promise is about waits the budget did not cut.
    handled = {(r[2], r[3]) for r in rows if r[0] in ("drop", "start")}
    cut = {
        r[2]
        for i, r in enumerate(rows)
        if r[0] == "recv" and i < first_start.get(r[2], len(rows)) and (r[2], r[3]) not in handled
    }
    waited = [s for s in first_recv if s not in direct and s not in cut]
    out = [f"session {s} never had a turn" for s in waited if s not in first_start]
    if out:
        return out
    by_receipt = sorted(waited, key=lambda s: first_recv[s][1])
    by_turn = sorted(waited, key=lambda s: first_start[s])
    if by_receipt != by_turn:
        out.append(f"first turns out of order: came {by_receipt}, served {by_turn}")

    def worker_ms(ticket: int) -> float:
        return float(res[ticket][8])

    def relocalized(ticket: int) -> bool:
        return bool(res[ticket][11])

    for s in waited:
        due = first_recv[s][1] + cold_gap_s
        turn = first_start[s]
        span = [r for r in rows[:turn] if r[0] == "start" and r[1] > due and r[5] in res]
        if not span:
            continue  # its turn came before it was due
        begin = start_row[span[0][5]]
        tracked = [worker_ms(r[5]) for r in span if not relocalized(r[5])]
        reloc = [worker_ms(r[5]) for r in span if relocalized(r[5])]
        # relocalizations handed over before the span whose debt may be owed in it: the last
        # one before it, and those whose result came in it
        before = [r[5] for r in rows[:begin] if r[0] == "start" and r[5] in res]
        owed = [t for t in before if relocalized(t)][-1:]
        owed += [
            r[5]
            for r in rows[begin:turn]
            if r[0] == "res" and r[11] and start_row.get(r[5], turn) < begin and r[5] not in owed
        ]
        allowed = (1 - share) / share * (sum(reloc) + sum(map(worker_ms, owed)))
        allowed += (len(reloc) + len(owed) + len(first_recv)) * max(tracked, default=0.0)
        if sum(tracked) > allowed:
            out.append(
                f"session {s} waited past its due moment behind {sum(tracked):.0f} ms of "
                f"tracked frames ({len(tracked)}), over the {allowed:.0f} ms its share allows"
            )
    return out
