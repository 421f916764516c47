"""The README's results block, generated from a ``results.json``.

    python -m sfmloc.bench.readme docs/results.json README.md

replaces what lies between ``<!-- results:begin -->`` and ``<!-- results:end -->`` (and nothing
else); when the markers are absent they go under the ``## Results`` heading (added at the end
when there is none).
``tests/test_bench.py`` regenerates the block from the committed results file and fails when the
README differs.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path

from .report import (
    COMPARE_HEADER,
    TABLE2_HEADER,
    THROUGHPUT_HEADER,
    compare_rows,
    localization_suites,
    map_line,
    markdown_table,
    ratio_lines,
    reps_sentence,
    table2_rows,
    throughput_mode,
    throughput_rows,
    verdict,
    wrong_pose_rule,
)
from .robust_report import ROBUST_HEADER, robust_note, robust_rows

BEGIN = "<!-- results:begin -->"
END = "<!-- results:end -->"


def _shared_note(load: float) -> str:
    """The benchmark keeps about one core busy itself; more than that at start means others."""
    return " (other processes shared the machine)" if load > 1.5 else ""


def render_block(results: dict, source: str = "docs/results.json") -> str:
    """The block's content (markers included) for ``results``."""
    m = results.get("machine", {})
    L = [
        BEGIN,
        "",
        f"_Generated from `{source}` by `python -m sfmloc.bench.readme {source} README.md`; do not "
        "edit by hand. "
        f"Measured by `{results.get('command', 'sfmloc bench')}` on "
        f"{results.get('created_utc', '?')} at commit "
        f"{m.get('git', '?')}: "
        f"{m.get('cpus', '?')} cores ({m.get('cpu_model', '?')}), load average "
        f"{m.get('load_average_start', 0):.1f} "
        f"at start{_shared_note(m.get('load_average_start', 0))}, wall time "
        f"{results.get('wall_s', 0):.0f} s. "
        f"Rerun with `make bench` (full report and figures in `bench-out/report.md`)._",
        "",
    ]
    if localization_suites(results):
        L += [
            "**Our engine, the paper's Table 2 columns** (F frames, F_loc localized, T time per "
            "frame mean ± std, "
            "M frames with 2D-3D matching, T_M their time; errors against ground truth):",
            "",
            markdown_table(TABLE2_HEADER, table2_rows(results)),
            "",
            "**Side by side on the same frames** (`global-every-frame`: our single-image global "
            "matching on every "
            'frame; `pycolmap-sift`: a tuned COLMAP/hloc-style SIFT pipeline; "ours faster by" is '
            "the ratio of "
            "mean times per frame):",
            "",
            markdown_table(COMPARE_HEADER, compare_rows(results)),
            "",
        ]
        L += [f"- {line}" for line in ratio_lines(results)]
        for name in localization_suites(results):
            reps = results["suites"][name].get("reps")
            if reps and reps["count"] > 1:
                L.append(f"- {reps_sentence(name, reps)}.")
        L += [""]
        L += [f"Wrong poses: frames with a pose under {wrong_pose_rule(results)}.", ""]
        if any(n.startswith("redkitchen") for n in localization_suites(results)):
            L += [
                "Ground truth: redkitchen's `pgt_sfm_seq01.txt` is a COLMAP (SIFT) SfM pseudo "
                "ground truth, which "
                "favours SIFT-based estimates; the synthetic suites have exact ground truth.",
                "",
            ]
    if robust_rows(results):
        L += [
            "**Robust suite** (the data users bring; ours / pycolmap-sift on the same frames):",
            "",
            markdown_table(ROBUST_HEADER, robust_rows(results)),
            "",
            robust_note(results),
            "",
        ]
    if throughput_rows(results):
        t = results["suites"]["throughput"]
        L += [
            f"**Throughput**: clients streaming at {t['rate_hz']:g} Hz each to one `sfmloc serve` "
            f"({t['workers']} workers, Zenoh on loopback). {throughput_mode(t)}",
            "",
            markdown_table(THROUGHPUT_HEADER, throughput_rows(results)),
            "",
        ]
    mp = results.get("suites", {}).get("map")
    if mp:
        L += [f"**Map**: {map_line(mp)}.", ""]
    tg = results.get("targets", [])
    if tg:
        L += ["**Targets**:", ""]
        for t in tg:
            v = verdict(t)
            L.append(f"- {v if v == 'met' else f'**{v}**'}: {t['target']}: {t['measured']}")
        L += [""]
    L.append(END)
    return "\n".join(L)


def update_text(readme: str, block: str) -> str:
    """``readme`` with its results block replaced by ``block``. Without markers, the block goes
    right under an existing ``## Results`` heading, else under a new one at the end."""
    i, j = readme.find(BEGIN), readme.find(END)
    if i >= 0 and j > i:
        return readme[:i] + block + readme[j + len(END) :]
    m = re.search(r"^## Results[ \t]*$", readme, flags=re.MULTILINE)
    if m:
        head, rest = readme[: m.end()], readme[m.end() :].lstrip("\n")
        return head + "\n\n" + block + "\n" + ("\n" + rest if rest else "")
    sep = "" if readme.endswith("\n") or not readme else "\n"
    return readme + sep + ("\n" if readme else "") + "## Results\n\n" + block + "\n"


def current_block(readme: str) -> str | None:
    i, j = readme.find(BEGIN), readme.find(END)
    return readme[i : j + len(END)] if i >= 0 and j > i else None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m sfmloc.bench.readme",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("results", help="results.json of a bench run (e.g. docs/results.json)")
    p.add_argument("readme", help="README.md to update in place")
    args = p.parse_args(argv)
    results = json.loads(Path(args.results).read_text())
    readme = Path(args.readme)
    text = readme.read_text() if readme.exists() else ""
    # Named relative to the README, so the block does not depend on where the command ran.
    source = Path(os.path.relpath(Path(args.results).resolve(), readme.resolve().parent)).as_posix()
    new = update_text(text, render_block(results, source))
    if new != text:
        readme.write_text(new)
        print(f"updated the results block of {readme}", file=sys.stderr)
    else:
        print(f"{readme} is up to date", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
