"""Tables of a bench run, from ``results.json`` only: the printed summary, ``report.md`` and
the per-frame files (TUM trajectories, per-frame JSON) written next to them."""

from __future__ import annotations

import json
import math
from pathlib import Path

from ..eval.metrics import RECALL_POSITION_FRACTION, FrameRecord
from ..eval.stages import STAGE_COLUMNS, stage_rows
from ..io.poses import write_tum
from .config import OURS, PEERS, SUITE_HELP

# What "wrong poses" counted before results version 2 (any pose, > 0.5 m or 10 deg).
LEGACY_WRONG_POSE_RULE = "any status but LOST, position error > 0.5 m or rotation error > 10 deg"

METHOD_NOTE = {
    OURS: "our engine: tracking + guided/global 2D-3D matching (Algorithm 1), every frame as a 30 "
    "Hz video",
    "global-every-frame": "our single-image global matching (`sfmloc.engine.relocalize`) on every "
    "frame, no tracking",
    "pycolmap-sift": "SIFT map (same images, known poses, pycolmap triangulation) + per-frame "
    "SIFT, "
    "nearest-neighbour ratio test, `pycolmap.estimate_and_refine_absolute_pose`",
}


# --------------------------------------------------------------------------- number formatting
def _ok(x) -> bool:
    return x is not None and isinstance(x, (int, float)) and not math.isnan(x)


def f1(x, nd: int = 1) -> str:
    return f"{x:.{nd}f}" if _ok(x) else "n/a"


def cm(x) -> str:
    return f"{x * 100:.2f}" if _ok(x) else "n/a"


def pm(mean, std, nd: int = 0) -> str:
    return f"{mean:.{nd}f} ± {std:.{nd}f}" if _ok(mean) else "n/a"


def ordinal(n: int) -> str:
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def pct(x) -> str:
    return f"{x:.1f}%" if _ok(x) else "n/a"


def wrong_pose_rule(results: dict) -> str:
    """What "wrong poses" counts in ``results`` (version 1 predates the scene-relative rule)."""
    return results.get("wrong_pose_rule", LEGACY_WRONG_POSE_RULE)


def ratio(x) -> str:
    return f"{x:.1f}x" if _ok(x) else "n/a"


def localization_suites(results: dict) -> list[str]:
    return [k for k, v in results.get("suites", {}).items() if v.get("kind") == "localization"]


# --------------------------------------------------------------------------- tables
def table2_rows(results: dict) -> list[list[str]]:
    """The paper's Table 2 for our engine, one row per localization suite (all frames)."""
    rows = []
    for name in localization_suites(results):
        s = results["suites"][name]["methods"][OURS]
        rows.append(
            [
                name,
                str(s["F"]),
                f"{s['F_loc']} ({s['F_loc_pct']:.1f}%)",
                pm(s["T_ms_mean"], s["T_ms_std"]),
                f"{s['M']} ({s['M_pct']:.0f}%)",
                pm(s["T_M_ms_mean"], s["T_M_ms_std"]),
                f1(s["T_ms_p99"], 0),
                cm(s["median_position_error_m"]),
                f1(s["median_rotation_error_deg"], 2),
                cm(s["mean_position_error_m"]),
                f1(s["mean_rotation_error_deg"], 2),
                str(s["wrong_poses"]),
                cm(s["ate_m"]),
            ]
        )
    return rows


TABLE2_HEADER = [
    "Suite",
    "F",
    "F_loc",
    "T (ms)",
    "M",
    "T_M (ms)",
    "p99 (ms)",
    "med. pos (cm)",
    "med. rot (°)",
    "mean pos (cm)",
    "mean rot (°)",
    "wrong poses",
    "ATE (cm)",
]


def compare_rows(results: dict) -> list[list[str]]:
    """Ours and the peers on the same frames, per suite."""
    rows = []
    for name in localization_suites(results):
        suite = results["suites"][name]
        same = suite["same_frames"][OURS]
        for m in (OURS, *PEERS):
            s = same if m == OURS else suite["methods"][m]
            r = suite["ratios"].get(m, {})
            rows.append(
                [
                    name,
                    m,
                    str(s["F"]),
                    f"{s['F_loc_pct']:.1f}%",
                    pct(s["recall_5cm_5deg_pct"]),
                    pct(s.get("recall_relative_pct")),
                    f1(s["T_ms_mean"]),
                    f1(s["rate_hz"]),
                    f1(s["T_ms_p99"], 0),
                    f1(s["cpu_ms_mean"]),
                    cm(s["median_position_error_m"]),
                    f1(s["median_rotation_error_deg"], 2),
                    str(s["wrong_poses"]),
                    "—" if m == OURS else ratio(r.get("rate_ratio")),
                ]
            )
    return rows


COMPARE_HEADER = [
    "Suite",
    "Method",
    "frames",
    "localized",
    "≤5 cm/5°",
    f"≤{RECALL_POSITION_FRACTION:.1%} depth/5°",
    "T mean (ms)",
    "rate (Hz)",
    "p99 (ms)",
    "CPU (ms)",
    "med. pos (cm)",
    "med. rot (°)",
    "wrong poses",
    "ours faster by",
]


def verdict(t: dict) -> str:
    """A target's state: met, missed, or skipped (``met`` None: not measured, e.g. no data)."""
    return "skipped" if t.get("met") is None else ("met" if t["met"] else "missed")


def throughput_mode(t: dict) -> str:
    """How the suite's clients sent (results without the keys ran aligned, wrapping)."""
    ph, loop = t.get("client_phases", "aligned"), t.get("frame_loop", "wrap")
    words = {
        "spread": "Each client sends 1/n of a frame interval after the previous one (independent "
        "cameras)",
        "aligned": "All clients send at the same instants (a burst of one frame per client)",
        "pingpong": "each loops over its frames forwards, then backwards (no jump)",
        "wrap": "each jumps from its last frame to its first (a relocalization per client every "
        "loop)",
    }
    text = f"{words.get(ph, ph)}, and {words.get(loop, loop)}."
    if t.get("stress_rows"):
        text += (
            " Rows marked *aligned, wrap*: the same clients sending together and jumping from "
            "the last loaded frame to the first (a relocalization per client in each run): the "
            "suite's mode before issue 10's drop diagnosis, kept as a stress row."
        )
    return text


def _mode(d: dict) -> tuple[str | None, str | None]:
    return d.get("client_phases"), d.get("frame_loop")


def throughput_rows(results: dict) -> list[list[str]]:
    t = results.get("suites", {}).get("throughput")
    if not t:
        return []
    return [
        [
            str(r["clients"])
            # a row in another mode than the suite's (the stress row) says which
            + (f" ({r['client_phases']}, {r['frame_loop']})" if _mode(r) != _mode(t) else ""),
            f1(r["offered_hz"], 0),
            f1(r["delivered_hz_total"]),
            f1(r["delivered_hz_per_client"]),
            f1(r["dropped_pct"]) + "%",
            f1(r["latency_ms_p50"]),
            f1(r["latency_ms_p99"]),
            # Newer runs only (older results.json rows: n/a).
            f1(r.get("dropped_pct_worst_client"))
            + ("%" if "dropped_pct_worst_client" in r else ""),
            f1(_server_cpu_ms(r), 2),
            f1(r.get("engine_cpu_ms_mean"), 2),
            f1(r.get("outside_engine_ms"), 2),
            f1(r.get("capacity_hz"), 0),
            f1(r.get("delivered_hz_worst_client")),
            f1(r.get("relocalized_pct")) + ("%" if "relocalized_pct" in r else ""),
            # After the start's burst of relocalizations (every session's first frame).
            f1(r.get("relocalized_pct_after_1s"))
            + ("%" if "relocalized_pct_after_1s" in r else ""),
            # Answers without a pose (DEADLINE_EXCEEDED under overload), in "dropped" too.
            str(r["errors"]) if "error_codes" in r else "n/a",
        ]
        for r in [*t["rows"], *t.get("stress_rows", [])]
    ]


def server_thread_lines(results: dict, top: int = 8) -> list[str]:
    """Per client count, the server's CPU per frame sent and its ``top`` thread kinds by CPU
    per pose (``throughput.server_threads``); none for runs without them."""
    t = results.get("suites", {}).get("throughput") or {}
    out = []
    for r in t.get("rows", []):
        th = r.get("server_threads")
        if not th:
            continue
        kinds = ", ".join(
            f"{k} {v['cpu_ms_per_pose']:.2f} ({v['vcs_per_pose']:.1f})"
            for k, v in list(th.items())[:top]
        )
        per_frame = f1(r.get("server_cpu_ms_per_frame_sent"), 3)
        out.append(f"{r['clients']} clients: server {per_frame} ms per frame sent; {kinds}")
    return out


GAP_HEADER = [
    "clients",
    "after 1 frame",
    "2",
    "3",
    "4-7",
    "8+",
    "engine CPU per pose after 1-3 (ms)",
    "after 4+ (ms)",
]


def gap_rows(results: dict) -> list[list[str]]:
    """Per throughput row: the share of poses (and the engine's CPU per pose, ms) by the frames
    since their client's previous pose; rows of older runs (no gap records) are left out."""
    t = results.get("suites", {}).get("throughput")
    if not t:
        return []
    out = []
    for r in t["rows"]:
        g = r.get("gaps")
        if not g:
            continue
        out.append(
            [str(r["clients"])]
            + [f"{f1(v['pct'])}% ({f1(v['engine_cpu_ms'])})" for v in g.values()]
            + [f1(r["engine_cpu_ms_gap_1_3"], 2), f1(r["engine_cpu_ms_gap_4plus"], 2)]
        )
    return out


def _server_cpu_ms(row: dict) -> float:
    per = row.get("cpu_ms_per_pose")
    return per["server"] + per["workers"] if per else float("nan")


def memory_rows(results: dict) -> list[list[str]]:
    mem = results.get("suites", {}).get("throughput", {}).get("memory") or {}
    return [
        [
            str(r["workers"]),
            str(r["processes"]),
            f1(r["rss_mb"], 0),
            f1(r["pss_mb"], 0),
            f1(r["private_mb"], 0),
            f1(r["worker_pss_mb_max"], 0),
            f1(r["index_file_mb_per_worker"], 1),
        ]
        for r in mem.get("rows", [])
    ]


MEMORY_HEADER = [
    "workers",
    "processes",
    "RSS sum (MB)",
    "PSS sum (MB)",
    "private sum (MB)",
    "largest worker PSS (MB)",
    "index file resident per worker (MB)",
]


THROUGHPUT_HEADER = [
    "clients",
    "offered (Hz)",
    "delivered total (Hz)",
    "per client (Hz)",
    "dropped",
    "latency p50 (ms)",
    "latency p99 (ms)",
    "worst client dropped",
    "server CPU per pose (ms)",
    "engine CPU per pose (ms)",
    "server CPU beyond the engine (ms)",
    "capacity (Hz)",
    "worst client (Hz)",
    "poses relocalized",
    "relocalized after 1 s",
    "error answers",
]


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def text_table(header: list[str], rows: list[list[str]]) -> str:
    w = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)]
    out = ["  ".join(h.ljust(w[i]) for i, h in enumerate(header)), "  ".join("-" * x for x in w)]
    out += ["  ".join(c.ljust(w[i]) for i, c in enumerate(r)) for r in rows]
    return "\n".join(out)


def ratio_lines(results: dict) -> list[str]:
    out = []
    for name in localization_suites(results):
        r = results["suites"][name]["ratios"]
        parts = []
        for m in PEERS:
            if m in r:
                parts.append(
                    f"{ratio(r[m]['rate_ratio'])} the frame rate of {m} "
                    f"(CPU time: {ratio(r[m]['cpu_ratio'])}; "
                    f"its median position error is {f1(r[m]['median_position_error_ratio'], 2)}x "
                    "ours)"
                )
        out.append(f"{name}: ours runs at " + "; ".join(parts))
    return out


REPS_HEADER = [
    "rep",
    "load at start",
    "order",
    "ours T mean (ms)",
    "ours p99 (ms)",
    "ours CPU (ms)",
    "global-every-frame T mean (ms)",
    "ours faster than global-every-frame",
    "ours faster than pycolmap-sift",
    "relocalization p95 (ms)",
]


def reps_rows(reps: dict) -> list[list[str]]:
    """One row per rep of a suite (``bench.reps``), then the median and the min-max."""

    def row(n: dict) -> list[str]:
        return [
            f1(n["load_average"], 2),
            f1(n["ours_T_ms_mean"], 2),
            f1(n["ours_T_ms_p99"]),
            f1(n["ours_cpu_ms_mean"], 2),
            f1(n["gef_T_ms_mean"], 2),
            ratio2(n["rate_ratio_gef"]),
            ratio2(n["rate_ratio_sift"]),
            f1(n["relocalization_p95_ms"]),
        ]

    short = {OURS: "ours", "global-every-frame": "gef", "pycolmap-sift": "sift"}
    rows = []
    for k, n in enumerate(reps["per_rep"]):
        r = row(n)
        order = ", ".join(short.get(m, m) for m in reps["order"][k])
        rows.append([str(k + 1), r[0], order, *r[1:]])
    sp = reps["spread"]
    med = row({k: v["median"] for k, v in sp.items()})
    rows.append(["median", med[0], "", *med[1:]])
    lo, hi = row({k: v["min"] for k, v in sp.items()}), row({k: v["max"] for k, v in sp.items()})
    rows.append(["min-max", f"{lo[0]}-{hi[0]}", "", *(f"{a}-{b}" for a, b in zip(lo[1:], hi[1:]))])
    return rows


def ratio2(x) -> str:
    return f"{x:.2f}x" if _ok(x) else "n/a"


def reps_sentence(name: str, reps: dict) -> str:
    """What a suite's reps were and what the published numbers are (one line, for the README
    and the printed summary)."""
    sp = reps["spread"]

    def mm(key: str, fmt: str) -> str:
        return f"{fmt.format(sp[key]['median'])} ({fmt.format(sp[key]['min'])}-" + (
            f"{fmt.format(sp[key]['max'])})"
        )

    rp = reps["repeatable"]
    return (
        f"{name}: every time and ratio here and in the targets is the median of "
        f"{reps['count']} replays of our engine and of "
        "global-every-frame, interleaved (pycolmap-sift once), load average "
        f"{sp['load_average']['min']:.1f}-{sp['load_average']['max']:.1f} at their starts; "
        f"median (min-max): ours {mm('ours_T_ms_mean', '{:.2f}')} ms/frame, p99 "
        f"{mm('ours_T_ms_p99', '{:.1f}')} ms, {mm('rate_ratio_gef', '{:.2f}x')} "
        f"global-every-frame (same-run, rep by rep), {mm('rate_ratio_sift', '{:.1f}x')} "
        "pycolmap-sift; poses "
        + ("identical in every rep" if rp["identical"] else "**differ between reps**")
        + " (accuracy is rep 1's)"
    )


def repeat_text(reps: dict) -> str:
    """The repeatability check of a suite's reps, in words."""
    parts = []
    for m, v in reps["repeatable"]["methods"].items():
        d = v["frames_differing_per_rep"]
        parts.append(
            f"{m} {v['frames']} frames x {reps['count']}: "
            + (
                "identical"
                if not any(d)
                else f"{max(d)} frames differ (first {v['first_differing']})"
            )
        )
    return "; ".join(parts)


def reps_lines(s: dict) -> list[str]:
    """The report's section on a suite's reps (none for a single rep or older results)."""
    reps = s.get("reps")
    if not reps or reps["count"] < 2:
        return []
    return [
        "",
        f"Repeats: our engine and global-every-frame ran {reps['count']} times on the same "
        "frames, back to back, the order alternating from rep to rep (pycolmap-sift ran once, "
        "after the last rep). The times, rates, ratios and relocalization times above are the "
        "medians over the reps (the targets read them); the stage table is one rep's, rep "
        f"{reps.get('stage_table_rep', '?')} (the one whose mean per frame is the median), so "
        "its rows sum to its total; accuracy, per-frame files "
        "and figures are rep 1's. Ratios to pycolmap-sift: its one run against each rep of "
        "ours. Repeatability (every rep's poses against rep 1's, bit for bit): "
        f"{repeat_text(reps)}.",
        "",
        markdown_table(REPS_HEADER, reps_rows(reps)),
        "",
    ]


def summary_text(results: dict) -> str:
    """What ``sfmloc bench`` prints at the end."""
    parts = []
    if localization_suites(results):
        parts += [
            "Table 2 (our engine, all frames of each suite)",
            text_table(TABLE2_HEADER, table2_rows(results)),
            "",
            "Side by side on the same frames",
            text_table(COMPARE_HEADER, compare_rows(results)),
            "",
        ]
        parts += ratio_lines(results) + [""]
        for name in localization_suites(results):
            reps = results["suites"][name].get("reps")
            if reps and reps["count"] > 1:
                parts += [reps_sentence(name, reps), text_table(REPS_HEADER, reps_rows(reps)), ""]
        for name in localization_suites(results):
            st = results["suites"][name].get("stages_ms", {})
            if st and all(isinstance(v, dict) for v in st.values()):
                parts += [
                    f"Where our time goes, {name} "
                    f"({stage_rep_text(results['suites'][name].get('reps'))}ms; mean/frame over "
                    "all frames, the other columns over the frames the stage ran in)",
                    text_table(list(STAGE_COLUMNS), stage_rows(st)),
                    "",
                ]
            rl = results["suites"][name].get("relocalization_ms")
            if rl and rl.get("calls"):
                w, c = rl["wall"], rl["cpu"]
                parts += [
                    f"Relocalization, {name} ({rl['calls']} calls, ms): wall mean "
                    f"{f1(w['mean'])} p50 {f1(w['p50'])} p95 {f1(w['p95'])} p99 {f1(w['p99'])}; "
                    f"CPU mean {f1(c['mean'])} p50 {f1(c['p50'])} p95 {f1(c['p95'])} "
                    f"p99 {f1(c['p99'])}",
                    "",
                ]
    from .robust_report import ROBUST_HEADER, robust_rows

    if robust_rows(results):
        parts += [
            "Robust suite (ours / pycolmap-sift)",
            text_table(ROBUST_HEADER, robust_rows(results)),
            "",
        ]
    if throughput_rows(results):
        parts += [
            "Throughput (one sfmloc serve, Zenoh loopback)",
            text_table(THROUGHPUT_HEADER, throughput_rows(results)),
            "",
        ]
        if gap_rows(results):
            parts += [
                "Throughput: poses by frames since the client's previous pose, % (engine CPU "
                "ms per pose)",
                text_table(GAP_HEADER, gap_rows(results)),
                "",
            ]
        if server_thread_lines(results):
            parts += [
                "Throughput: CPU ms per pose of the server and its workers by thread kind "
                "(voluntary context switches per pose)",
                *server_thread_lines(results),
                "",
            ]
    m = results.get("suites", {}).get("map")
    if m:
        parts.append("map " + map_line(m))
    for t in results.get("targets", []):
        parts.append(f"target {verdict(t).upper():7s}{t['target']}: {t['measured']}")
    parts.append(f"wall time {results.get('wall_s', float('nan')):.0f} s")
    return "\n".join(parts)


def map_line(m: dict) -> str:
    return (
        f"{m['map']}: {m['images']} images, {m['points']} points, {m['descriptors']} descriptors "
        f"({m['descriptors_per_point']:.1f}/point); built in {m['build_s']:.1f} s; bundle "
        f"{m['bundle_mb']:.1f} MB; "
        f"loads in {m['load_s'] * 1e3:.0f} ms ({m['load_s_verified'] * 1e3:.0f} ms with "
        "checksums); resident "
        f"{m['rss_mb']:.1f} MB = {m['rss_mb_per_million_descriptors']:.0f} MB per million "
        "descriptors"
    )


# --------------------------------------------------------------------------- per-frame files
def frame_dicts(records: list[FrameRecord]) -> list[dict]:
    return [
        {
            "index": r.index,
            "name": r.name,
            "stamp": r.stamp,
            "status": r.status,
            "matching": r.matching,
            "latency_ms": r.latency_ms,
            "cpu_ms": r.cpu_ms,
            "inliers": r.inliers,
            "detected": r.detected,
            "tracked": r.tracked,
            "tracked_3d": r.tracked_3d,
            "position_error_m": r.position_error_m,
            "rotation_error_deg": r.rotation_error_deg,
            "timings_ms": r.timings_ms,
            "message": r.message,
        }
        for r in records
    ]


def write_tum_pair(records: list[FrameRecord], est_path: Path, gt_path: Path) -> int:
    """Estimate and ground truth (world_from_cam) at the same timestamps, for ``evo_ape tum``."""
    both = [
        (r.stamp, est, gt)
        for r in records
        if (est := r.cam_from_world) is not None and (gt := r.gt_cam_from_world) is not None
    ]
    write_tum(est_path, [s for s, _, _ in both], [est.inverse() for _, est, _ in both])
    write_tum(gt_path, [s for s, _, _ in both], [gt.inverse() for _, _, gt in both])
    return len(both)


# --------------------------------------------------------------------------- report.md
def _suite_section(name: str, s: dict) -> list[str]:
    o = s["methods"][OURS]
    lines = [f"## {name}", "", SUITE_HELP.get(name, ""), ""]
    mp = s.get("map", {})
    lines.append(
        f"Map: {mp.get('map_images', '')}: {mp.get('images', '?')} images, {mp.get('points', '?')} "
        "points, "
        f"{mp.get('descriptors', '?')} DAISY descriptors, built in {f1(mp.get('build_s'))} s. SIFT "
        "peer's map: "
        f"{mp.get('sift_points', '?')} points, {mp.get('sift_descriptors', '?')} SIFT descriptors. "
        f"Frames replayed: {s['frames_replayed']} (from frame {s['start']})."
        + (
            f" Scene scale (our map's median camera-to-point depth): {s['scene_scale']:.3g} map "
            f"units; a pose more than {o['wrong_position_limit']:.3g} units or 10° off is wrong."
            if "scene_scale" in s
            else ""
        )
    )
    lines += ["", f"Our engine on all {o['F']} frames (the paper's Table 2 columns and more):", ""]
    lines.append(markdown_table(TABLE2_HEADER, [r for r in table2_rows({"suites": {name: s}})]))
    pf = s["peer_frames"]
    every = (
        "every replayed frame"
        if pf["stride"] == 1
        else f"every {ordinal(pf['stride'])} replayed frame"
    )
    lines += [
        "",
        f"Side by side on the same {pf['count']} frames ({every}; our engine still runs every "
        "frame as "
        "video and is summarised on these frames):",
        "",
    ]
    lines.append(markdown_table(COMPARE_HEADER, [r for r in compare_rows({"suites": {name: s}})]))
    lines += [""] + ratio_lines({"suites": {name: s}})
    inl = [
        (
            m,
            (s["same_frames"][OURS] if m == OURS else s["methods"].get(m, {})).get(
                "inliers_median"
            ),
        )
        for m in (OURS, *PEERS)
    ]
    lines += [
        "",
        "Median pose inliers per localized frame (on the same frames): "
        + ", ".join(f"{m} {f1(v, 0)}" for m, v in inl)
        + ".",
    ]
    lines += stage_lines(s.get("stages_ms", {}), s.get("reps"))
    lines += relocalization_lines(s)
    lines += reps_lines(s)
    reps = s.get("reps") or {}
    peer_rep = reps.get("peer_stage_rep", {}) if reps.get("count", 1) > 1 else {}
    for m, st in s.get("peer_stages_ms", {}).items():
        if st:
            which = f" (rep {peer_rep[m]}, its median rep)" if m in peer_rep else ""
            lines.append(
                f"{m}{which}: "
                + ", ".join(f"{k} {v:.1f}" for k, v in st.items())
                + " ms per frame."
            )
    f = s.get("files", {})
    lines += [""]
    for key, cap in (
        ("fig_per_frame", "per frame (cf. the paper's Figures 2 and 4)"),
        ("fig_trajectory", "top view"),
        ("fig_compare", "ours vs the peers on the same frames"),
    ):
        if key in f:
            lines.append(f"![{name}: {cap}]({f[key]})")
            lines.append("")
    if "tum" in f:
        lines.append(
            "Trajectories (TUM, world_from_cam, estimate and ground truth at the same timestamps; "
            "`evo_ape tum GT EST -a`): " + ", ".join(f"`{p}`" for p in f["tum"]) + "."
        )
    return lines + [""]


def relocalization_lines(s: dict) -> list[str]:
    """The time distribution of the single-image relocalization calls (``global-every-frame``,
    ``engine.relocalize`` on every peer frame); results before it did not keep one."""
    rl = s.get("relocalization_ms")
    if not rl or not rl.get("calls"):
        return []
    rows = [
        [kind, *(f1(rl[kind][k]) for k in ("mean", "p50", "p95", "p99", "max"))]
        for kind in ("wall", "cpu")
    ]
    return [
        "",
        f"Single-image relocalization (`engine.relocalize`, the {rl['calls']} calls of "
        "global-every-frame; ms per call, wall clock and process CPU time):",
        "",
        markdown_table(["time", "mean", "p50", "p95", "p99", "max"], rows),
        "",
    ]


def stage_rep_text(reps: dict | None) -> str:
    """Which rep a repeated suite's stage table is (empty for one rep or older results, whose
    table is the single run's, or the per-cell medians of results before ``stage_table_rep``)."""
    if not reps or reps.get("count", 1) < 2 or "stage_table_rep" not in reps:
        return ""
    return (
        f"rep {reps['stage_table_rep']} of {reps['count']}, the one whose mean per frame is the "
        "median: its rows sum to its total; "
    )


def stage_lines(st: dict, reps: dict | None = None) -> list[str]:
    """Where our time goes: the per-stage table (``eval.stages``), one rep's (``reps``: which
    one); results before it kept only the mean per stage."""
    if not st:
        return []
    if all(isinstance(v, dict) for v in st.values()):
        return [
            "",
            f"Where our time goes ({stage_rep_text(reps)}ms; mean/frame over all frames, the "
            "other columns over the frames the stage ran in):",
            "",
            markdown_table(list(STAGE_COLUMNS), stage_rows(st)),
        ]
    tot = sum(st.values())
    return [
        "",
        "Where our time goes (mean ms per frame over all frames): "
        + ", ".join(f"{k} {v:.1f} ({100 * v / tot:.0f}%)" for k, v in st.items())
        + ".",
    ]


def write_report(results: dict, out: Path) -> Path:
    m = results.get("machine", {})
    L = [
        "# sfmloc bench report",
        "",
        f"Generated by `{results.get('command', 'sfmloc bench')}` on "
        f"{results.get('created_utc', '')} at commit "
        f"{m.get('git', '?')}, "
        f"{m.get('cpus', '?')} cores ({m.get('cpu_model', '?')}), load average "
        f"{f1(m.get('load_average_start'), 2)} at the start and {f1(m.get('load_average_end'), 2)} "
        "at the end "
        "(other processes share the machine: wall-clock times include their interference; the "
        "CPU-time "
        f"columns do not). Wall time of the run: {results.get('wall_s', float('nan')):.0f} s. "
        "Every number and "
        f"figure here was measured by this run.",
        "",
        "Methods:",
        "",
    ]
    L += [f"- **{k}**: {v}" for k, v in METHOD_NOTE.items()]
    L += [
        "",
        "Timing: T is the time of one call on an already decoded frame (wall clock; decoding "
        "excluded), "
        "OpenCV, BLAS, faiss and pycolmap's RANSAC on one thread; CPU is the process's CPU time "
        "for "
        "the same call. M counts frames in which 2D-3D matching ran (guided or global); T_M is "
        "their time. "
        "Errors are those of the raw per-frame pose against ground truth; rotation error is the "
        "angle of "
        f'R_est R_gt^T. "wrong poses" counts frames with a pose under '
        f"{wrong_pose_rule(results)} (every method on a suite is judged against our map's scene "
        "scale; a client acts on every pose it receives, whatever its status). "
        f'"≤{RECALL_POSITION_FRACTION:.1%} depth/5°" is the share of frames (LOST counting as '
        "misses) within that fraction of the scene scale and 5°, the scene-relative analogue of "
        "≤5 cm/5°. ATE is the RMSE of camera centres after SE(3) alignment. The peers get one "
        "untimed warm-up call; our engine does not (its first frame is a global matching).",
        "",
    ]
    targets = results.get("targets", [])
    if targets:
        L += ["## Targets", ""]
        L += [f"- **{verdict(t)}**: {t['target']}: {t['measured']}" for t in targets]
        L += [""]
    for name in localization_suites(results):
        L += _suite_section(name, results["suites"][name])
    from .robust_report import robust_section

    L += robust_section(results)
    tun = results.get("sift_tuning")
    if tun:
        L += _tuning_section(tun)
    t = results.get("suites", {}).get("throughput")
    if t:
        L += [
            "## throughput",
            "",
            SUITE_HELP["throughput"] + ".",
            "",
            f"Server: {t['server']}, {t['workers']} workers; {t['rate_hz']:g} Hz per client for "
            f"{t['duration_s']:g} s, JPEG frames. Delivered = poses received per second; dropped = "
            "frames "
            "without a pose (the server keeps only each client's newest frame when it falls "
            "behind); latency = "
            "frame published -> pose received, p50 of the median client and p99 of the worst "
            "client. " + throughput_mode(t),
            "",
            markdown_table(THROUGHPUT_HEADER, throughput_rows(results)),
            "",
            "Server CPU per pose: the server process and its workers together, CPU time (not "
            "wall) per pose delivered; engine CPU: the engine's own (its thread's CPU for the "
            "frame, reported by the worker), and the server's CPU per pose beyond it (JPEG "
            "decoding, Zenoh, the hand-off to and from the workers, scheduling; and the "
            "engine's CPU on frames answered without a pose); capacity: the pose rate that "
            "CPU per pose would sustain "
            "on all of this machine's cores with nothing else running (a bound from the "
            "measured CPU, not a measured rate: the benchmark's clients and other jobs share "
            "the cores). Worst client: the delivered rate of the client served least (fairness, "
            "against per client); poses relocalized: RELOCALIZED among the poses delivered (far "
            "above the 1-client row's: frames after gaps relocalize, at 5-20x a tracked frame's "
            "CPU).",
            "",
        ]
        if gap_rows(results):
            L += [
                "Poses by the frames since their client's previous pose (1: none dropped "
                "between), % of the poses (the engine's CPU per pose, ms). Under overload the "
                "server keeps only each client's newest frame, so the gaps widen with the "
                "client count, and a pose after a wide gap has more motion to track over and "
                "costs the engine more (one Localizer fed every k-th redkitchen frame: flat up "
                "to k = 4, x1.35 at 5-6, x2 at 8, x5 at 12): this is why the CPU per pose rises "
                "past the server's capacity.",
                "",
                markdown_table(GAP_HEADER, gap_rows(results)),
                "",
            ]
        if memory_rows(results):
            L += [
                "Resident memory of the server and its workers (the map loaded, one session per "
                "stream worker that streamed "
                f"{t['memory']['frames_per_session']} frames; the relocalization lane and, with "
                "forked workers, their zygote included). PSS divides shared pages among the "
                "processes that map them: the sum is what the server costs the machine.",
                "",
                markdown_table(MEMORY_HEADER, memory_rows(results)),
                "",
            ]
        if "fig_throughput" in t:
            L += [f"![throughput]({t['fig_throughput']})", ""]
    mp = results.get("suites", {}).get("map")
    if mp:
        L += [
            "## map",
            "",
            map_line(mp) + ".",
            "",
            "Build stages (s): "
            + ", ".join(f"{k} {v:.1f}" for k, v in mp["build_stages_s"].items())
            + ". "
            "Resident memory is VmRSS of a fresh process after loading the bundle (checksums "
            "verified, as the "
            "server loads it) and reading every array the engine reads (and building the point -> "
            "image "
            "lookup), minus VmRSS before (numpy, OpenCV, faiss already imported): "
            f"{mp['rss_anon_mb']:.1f} MB "
            f"anonymous (the ANN index and lookups) + {mp['rss_file_mb']:.1f} MB file-backed "
            "(memory-mapped "
            f"arrays, reclaimable page cache); {mp['rss_mb_after_load_only']:.1f} MB right after "
            "loading. A "
            f"worker adds {mp['worker_extra_rss_mb']:.1f} MB of engine buffers after localizing "
            f"{mp['probe_frames']} frames (per worker, not per map). The paper's Table 1 lists "
            "107-124 MB for "
            f"1.0-1.4 million descriptors (~90-120 MB per million).",
            "",
        ]
        sm = mp.get("sift_peer_map")
        if sm:
            L += [
                f"The SIFT peer's map of the same images: {sm['points']} points, "
                f"{sm['descriptors']} SIFT "
                f"descriptors ({sm['descriptor_mb_uint8']:.1f} MB as uint8); the peer indexes "
                f"{sm.get('indexed_vectors', sm['descriptors'])} vectors "
                f"({sm.get('layout', 'all')} layout) in a "
                f"faiss HNSW index of about {sm['faiss_hnsw_mb']:.0f} MB (float32 vectors plus "
                "graph links, "
                "computed from the sizes, not measured).",
                "",
            ]
    bl = results.get("suites", {}).get("builder")
    if bl:
        from .builder import report_lines

        L += ["## builder", "", SUITE_HELP["builder"] + ".", ""] + report_lines(bl)
    notes = results.get("notes", [])
    if notes:
        L += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    path = out / "report.md"
    path.write_text("\n".join(L))
    return path


def _tuning_section(t: dict) -> list[str]:
    c = t["chosen"]
    L = [
        "## Tuning the pycolmap-sift peer",
        "",
        f"On {len(t['frames'])} frames of {t['suite']} that are not map images (frames "
        f"{t['frames'][0]}-{t['frames'][-1]}), before the measured runs. Query SIFT uses the map's "
        "extractor and "
        "settings (OpenCV SIFT as COLMAP stores it, RootSIFT, up to 4000 features, contrast "
        "threshold 0.015: "
        f"{t['ms_extract_opencv_sift']:.0f} ms per frame here; pycolmap's own SIFT extractor, one "
        "thread, takes "
        f"{f1(t['ms_extract_pycolmap_sift'], 0)} ms on the same frames, so the faster one is what "
        "the peer uses). "
        f"Map: {t['map_points']} points, {t['map_descriptors']} descriptors. Criterion: "
        f"{t['criterion']}.",
        "",
        "| descriptors | ratio | RANSAC max error (px) | localized | ≤5 cm/5° | med. pos (cm) | "
        "med. rot (°) | "
        "exact search (ms) | ratio test + pose (ms) | per frame with the chosen search (ms) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in t["grid"]:
        L.append(
            f"| {r['descriptors']} | {r['ratio']:g} | {r['ransac_max_error_px']:g} | "
            f"{r['localized_pct']:.0f}% | "
            f"{r['recall_5cm_5deg_pct']:.0f}% | {cm(r['median_position_error_m'])} | "
            f"{f1(r['median_rotation_error_deg'], 2)} | {r['ms_search_exact']:.0f} | "
            f"{r['ms_match_pose']:.0f} | "
            f"{f1(r.get('ms_per_frame'), 0)} |"
        )
    L += [
        "",
        "| descriptors | HNSW efSearch | NN recall vs exact | search (ms) | exact (ms) |",
        "|---|---|---|---|---|",
    ]
    for r in t["search"]:
        L.append(
            f"| {r['descriptors']} | {r['ef_search']} | {r['recall_at_1'] * 100:.2f}% | "
            f"{r['ms_search']:.0f} | "
            f"{r['ms_search_exact']:.0f} |"
        )
    L += [
        "",
        f"Chosen: descriptors={c['descriptors']}, ratio={c['ratio']:g}, RANSAC max error "
        f"{c['ransac_max_error_px']:g} px, search={c['search']}"
        + (f" (HNSW M={c['hnsw_m']}, efSearch={c['ef_search']})" if c["search"] == "hnsw" else "")
        + f", at least {c['min_inliers']} inliers.",
        "",
    ]
    return L


def write_json(path: Path, obj) -> Path:
    path.write_text(json.dumps(obj, indent=1, allow_nan=True) + "\n")
    return path
