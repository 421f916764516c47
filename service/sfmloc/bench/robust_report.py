"""The robust suite's table (``sfmloc bench --suites robust``): one line per row, ours / the
pycolmap-sift peer on the same frames, for the printed summary, report.md and the README."""

from __future__ import annotations

from .config import SUITE_HELP
from .report import _ok, f1, markdown_table, pct


def _g(x, nd: int = 3) -> str:
    return f"{x:.{nd}g}" if _ok(x) else "n/a"


def _rel(x) -> str:
    """A fraction as a percentage, two significant digits (no exponent: 140%, 0.05%)."""
    if not _ok(x):
        return "n/a"
    return f"{100 * x:.0f}%" if 100 * x >= 10 else f"{100 * x:.2g}%"


def _pair(a: str, b: str) -> str:
    return f"{a} / {b}"


def right_pct(summary: dict) -> float:
    """Localized and not wrong, as a percentage of the frames: a method's localized fraction
    counts its wrong poses too (the peer's reach 5 of 20 on a thin map), ours are LOST."""
    n = summary["F"]
    return float("nan") if not n else 100.0 * (summary["F_loc"] - summary["wrong_poses"]) / n


def _hz(row: dict) -> str:
    """The row's frame rate; a low-rate row's offsets pooled (how many of how many)."""
    off = row.get("offsets")
    if not off:
        return f"{row['fps']:g}"
    n = len(off["run"])
    return (
        f"{row['fps']:g} ({n} offsets)"
        if n == off["of"]
        else f"{row['fps']:g} ({n} of {off['of']} offsets)"
    )


def robust_rows(results: dict) -> list[list[str]]:
    """The robust suite: one line per row, ours / the peer on the same frames."""
    rb = results.get("suites", {}).get("robust")
    if not rb:
        return []
    out = []
    for r in rb["rows"]:
        if r["status"] != "ran":
            out.append(
                [r["group"], r["name"]]
                + ["—"] * (len(ROBUST_HEADER) - 3)
                + [f"{r['status']}: {r['reason']}"]
            )
            continue
        o, p, oa = r["ours_same"], r["peer_same"], r["ours"]
        rel = [x["median_position_error_m"] / r["map"]["scene_scale"] for x in (o, p)]
        if r.get("ours_error"):
            verdict_text = f"crash (ours): {r['ours_error']}"
        elif r.get("ours_stopped"):
            verdict_text = f"over the {rb['frames']['budget_s']:g} s budget (ours)"
        else:
            missed = [k for k, v in r["targets"].items() if not v]
            verdict_text = "met" if not missed else "missed: " + ", ".join(missed)
        if r.get("peer_error"):
            verdict_text += f"; peer crashed: {r['peer_error']}"
        out.append(
            [
                r["group"],
                r["name"],
                r["image_size"],
                _hz(r),
                _pair(str(oa["F"]), str(r["same_frames"])),
                _pair(pct(o["F_loc_pct"]), pct(p["F_loc_pct"])),
                _pair(pct(right_pct(o)), pct(right_pct(p))),
                _pair(_g(o["median_position_error_m"]), _g(p["median_position_error_m"])),
                _pair(_rel(rel[0]), _rel(rel[1])),
                _pair(f1(o["median_rotation_error_deg"], 2), f1(p["median_rotation_error_deg"], 2)),
                _pair(str(oa["wrong_poses"]), str(r["peer"]["wrong_poses"])),
                _pair(f1(o["T_ms_mean"]), f1(p["T_ms_mean"])),
                verdict_text,
            ]
        )
    return out


ROBUST_HEADER = [
    "Group",
    "Row",
    "image",
    "Hz",
    "frames (ours / compared)",
    "localized",
    "localized, not wrong",
    "med. pos (units)",
    "med. pos / scale",
    "med. rot (°)",
    "wrong poses",
    "T (ms)",
    "targets",
]


def robust_section(results: dict) -> list[str]:
    """The report.md section (nothing when the run has no robust suite)."""
    if not robust_rows(results):
        return []
    rb = results["suites"]["robust"]
    return [
        "## robust",
        "",
        SUITE_HELP["robust"] + ".",
        "",
        robust_note(results),
        "",
        markdown_table(ROBUST_HEADER, robust_rows(results)),
        "",
        f"Wall time of the suite: {rb['wall_s']:.0f} s (maps, renders and both methods).",
        "",
    ]


def robust_note(results: dict) -> str:
    rb = results["suites"]["robust"]
    f = rb["frames"]
    tuned = "tuned in this run." if rb.get("sift_peer_tuned") else "its defaults (not tuned here)."
    return (
        "Each cell is ours / pycolmap-sift. Our engine replays every frame of a row as a video "
        f'("frames": {f["per_row"]} at 30 Hz on the synthetic and redkitchen rows, every 3rd / '
        f"10th of them at 10 / 3 Hz, {f['large_image_rows']} on the 1280x960 and 1920x1440 rows, "
        f"2/5 of that at 3072x2048); the peer runs on {f['peer_per_row']} evenly strided frames "
        "per row (half on the 1280x960 and 1920x1440 rows, a quarter at 3072x2048; on redkitchen "
        "never a map image), and localized, median errors and times compare both on exactly "
        'those frames ("localized, not wrong": without the wrong poses among them). Wrong '
        "poses count every frame each method ran. Median position error in "
        "map units and as a fraction of the scene scale (our map's median depth). The peer's "
        "settings were "
        + tuned
        + " Per-frame records: robust/ROW/frames-METHOD.json."
        + _offsets_note(rb)
        + _engine_config_text(rb)
    )


def _offsets_note(rb: dict) -> str:
    """How the low-rate rows pool their offsets (nothing for a run from before they did)."""
    offs = [r["offsets"] for r in rb["rows"] if r.get("offsets")]
    if not offs:
        return ""
    fewer = any(len(o["run"]) < o["of"] for o in offs)
    return (
        " The 10 and 3 Hz rows (Hz: 'N offsets') replay every offset of their step, the streams "
        "of every 3rd / 10th frame starting at frame 0, 1, 2, ... (a fresh engine each), and pool "
        "them: together each 30 Hz frame once, localized, errors and wrong poses over all of "
        "them, the peer's frames drawn from all."
        + (
            " Rows reading 'N of M offsets' ran only N (BenchConf.robust_offsets; --quick runs 2)."
            if fewer
            else ""
        )
    )


def _engine_config_text(rb: dict) -> str:
    """--engine-config: which file our engine ran with and what it sets (else nothing)."""
    ec = rb.get("engine_config")
    if not ec:
        return ""
    import json

    return (
        f" Our engine ran with the engine config {ec['file']} (--engine-config; the peer "
        f"unchanged): {json.dumps(ec['settings'], sort_keys=True)}."
    )


def main(argv: list[str] | None = None) -> int:
    """Print the robust table of a bench run: OUT/results.json, or OUT/robust/rows-so-far.json
    while the run is still going."""
    import argparse
    import json
    import sys
    from pathlib import Path

    from .report import text_table

    p = argparse.ArgumentParser(
        prog="python -m sfmloc.bench.robust_report", description=main.__doc__
    )
    p.add_argument("results", help="results.json or robust/rows-so-far.json of a bench run")
    p.add_argument("--markdown", action="store_true", help="a Markdown table")
    args = p.parse_args(argv)
    try:
        data = json.loads(Path(args.results).read_text())
    except (OSError, ValueError) as exc:
        print(f"cannot read {args.results}: {exc}", file=sys.stderr)
        return 2
    results = data if "suites" in data else {"suites": {"robust": data}}
    rows = robust_rows(results)
    if not rows:
        print(f"{args.results} has no robust rows")
        return 1
    print((markdown_table if args.markdown else text_table)(ROBUST_HEADER, rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
