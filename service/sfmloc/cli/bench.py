"""sfmloc bench: the paper's tables on real and synthetic data, next to the alternatives."""

from __future__ import annotations

import argparse
import shlex
import sys
import textwrap
from pathlib import Path

SUITES_TEXT = """\
Suites (--suite, repeatable; default: all but builder):
{suites}

In every localization suite three methods run on the same frames and machine:
  sfmloc             our engine (tracking + guided/global matching), every frame as a 30 Hz video
  global-every-frame our single-image global matching (relocalize) on every frame, no tracking
  pycolmap-sift      a COLMAP/hloc-style SIFT pipeline: SIFT map of the same map images at the same
                     poses (pycolmap triangulation), per-frame SIFT, nearest-neighbour ratio test,
                     pycolmap.estimate_and_refine_absolute_pose; tuned first on frames that are not
                     map images (descriptor layout, ratio, RANSAC threshold, search recall)
The peers run on every k-th frame when --peer-frames caps them (our engine is then also
summarised on exactly those frames). Per-frame time is one call on a decoded frame, one thread.
Our engine and global-every-frame run --reps times (default 3), interleaved, pycolmap-sift
once: times, ratios and stage tables are the median over the reps, with the min-max.

Outputs (OUT):
  results.json   summary numbers (Table 2 columns, errors, p99, wrong frames, ATE, ratios, tuning,
                 throughput, map); report.md: tables, figures and notes, all from this run
  SUITE/fig-per-frame.png (the paper's Figure 2), SUITE/fig-trajectory.png (top view, lost
  frames marked), SUITE/fig-compare.png (the three methods), throughput.png
  SUITE/METHOD.tum + METHOD.gt.tum (TUM, same timestamps: evo_ape tum GT EST -a),
  SUITE/frames-METHOD.json (per-frame records); robust/ROW/frames-METHOD.json (per-frame
  records of each robust row); work/ (maps, synthetic data; --reuse)

Publish a run to the README: cp OUT/results.json docs/results.json &&
  python -m sfmloc.bench.readme docs/results.json README.md   (or: make bench-publish)
"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..bench.config import DEFAULT_DATA, SUITE_HELP, SUITES

    p = sub.add_parser(
        "bench",
        help="the paper's Table 2 / Figures 2 and 4 on real data, with peers, throughput and map "
        "size",
        description=textwrap.dedent("""\
            Reproduce the paper's evaluation (Table 2, Figures 2 and 4) on real and synthetic
            sequences, side by side with what users would pick instead, and measure the server's
            throughput and the map's footprint. Writes OUT/results.json, OUT/report.md and PNG
            figures, and prints the summary table. Progress goes to stderr.\n\n""")
        + SUITES_TEXT.format(
            suites="\n".join(
                textwrap.fill(text, 96, initial_indent=f"  {name:<19s}", subsequent_indent=" " * 21)
                for name, text in SUITE_HELP.items()
            )
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--suite",
        action="append",
        choices=SUITES,
        metavar="NAME",
        help="run this suite (repeatable; default all but builder): " + ", ".join(SUITES),
    )
    p.add_argument(
        "--suites",
        metavar="A,B",
        help="the same as --suite, comma-separated (e.g. --suites robust)",
    )
    p.add_argument(
        "--builder-parts",
        metavar="A,B",
        help="builder suite: its parts, comma-separated, of extend, memory, density, video "
        "(default extend,memory)",
    )
    p.add_argument(
        "--robust-rows",
        metavar="PATTERNS",
        help="robust suite: only these rows, comma-separated names or groups, shell "
        "patterns (e.g. 'size-*,motion'; default all)",
    )
    p.add_argument(
        "--robust-frames", type=int, help="robust suite: 30 Hz frames per row (default 300)"
    )
    p.add_argument(
        "--robust-peer-frames", type=int, help="robust suite: peer frames per row (default 20)"
    )
    p.add_argument("--out", default="bench-out", help="output folder (default bench-out)")
    p.add_argument(
        "--data",
        help="redkitchen-like folder (frame-NNNNNN.color.jpg + pgt_sfm_seq01.txt); "
        f"default {DEFAULT_DATA}",
    )
    p.add_argument(
        "--frames", type=int, help="replay at most this many frames per localization suite"
    )
    p.add_argument(
        "--peer-frames",
        type=int,
        help="frames per suite for the peers, strided (default 500; 0: all)",
    )
    p.add_argument(
        "--reps",
        type=int,
        help="replays of our engine and of global-every-frame per localization suite, "
        "interleaved (pycolmap-sift once); every timing number published is their median, with "
        "the min-max and the load beside it (default 3; --quick 2)",
    )
    p.add_argument("--synth-frames", type=int, help="frames of each synthetic video (default 300)")
    p.add_argument(
        "--clients", help="throughput client counts, comma-separated (default 1,2,4,8,12,16)"
    )
    p.add_argument("--duration", type=float, help="seconds per throughput run (default 10)")
    p.add_argument(
        "--client-phases",
        choices=("aligned", "spread"),
        help="throughput clients send each 1/n of a frame interval after the previous one "
        "(spread, default: independent cameras) or all at the same instants (aligned)",
    )
    p.add_argument(
        "--frame-loop",
        choices=("wrap", "pingpong"),
        help="throughput clients loop over the frames forwards then backwards (pingpong, "
        "default: no jump) or back to the first (wrap: a jump each session relocalizes after); "
        "either way one more run at 8 clients is aligned + wrap (--stress-clients)",
    )
    p.add_argument(
        "--stress-clients",
        type=int,
        help="throughput: clients of the extra aligned + wrap run (default 8; 0: none)",
    )
    p.add_argument(
        "--workers", type=int, help="server workers for throughput (default one per core)"
    )
    p.add_argument(
        "--no-tune", action="store_true", help="skip the SIFT peer's tuning (use its defaults)"
    )
    p.add_argument(
        "--engine-config",
        metavar="FILE",
        type=Path,
        help="robust suite: run OUR engine with this engine config (JSON/TOML, the EngineConf "
        "fields, read as sfmloc replay --config but without SFMLOC_ENGINE__* variables) "
        "instead of the defaults, to measure an engine variant without a code copy. The peers "
        "are unchanged; refused without --suites robust (no other suite reads it). Checked "
        "before any suite runs (an unknown key is an error naming it); the report names the "
        "file and its settings. --reuse still reuses maps and renders (the config does not "
        "make them); the rows always run again",
    )
    p.add_argument(
        "--reuse",
        action="store_true",
        help="reuse maps and synthetic data already under OUT/work when the same input and the "
        "same builder (bundle format, sfmloc version, builder source hash) made them; the log "
        "says which are reused or rebuilt, and why",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="smoke run (~1 min of CPU): the synthetic room only (synthetic-walk, two robust rows, "
        "throughput and map on its map; --suites to choose others), few frames, small scenes, "
        "short throughput runs, 2 reps",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..threads import pin_threads_env, pin_threads_runtime

    pin_threads_env()
    pin_threads_runtime()
    from ..bench.config import SUITES, BenchConf, quick_conf
    from ..bench.main import main
    from ..bench.report import summary_text
    from ..errors import InputError
    from .progress import ProgressPrinter

    changes: dict = {}
    listed = [s.strip() for s in (args.suites or "").split(",") if s.strip()]
    chosen = list(args.suite or []) + listed
    bad = [s for s in chosen if s not in SUITES]
    if bad:
        raise InputError(f"unknown suite(s) {', '.join(bad)}; choose from {', '.join(SUITES)}")
    if chosen:
        changes["suites"] = list(dict.fromkeys(chosen))
    if args.builder_parts:
        from ..bench.builder import PARTS

        parts = [s.strip() for s in args.builder_parts.split(",") if s.strip()]
        bad_parts = [s for s in parts if s not in PARTS]
        if bad_parts:
            raise InputError(
                f"unknown builder part(s) {', '.join(bad_parts)}; choose from {', '.join(PARTS)}"
            )
        changes["builder_parts"] = parts
    if args.robust_rows:
        changes["robust_rows"] = [s.strip() for s in args.robust_rows.split(",") if s.strip()]
    if args.robust_frames is not None:
        changes["robust_frames"] = args.robust_frames
    if args.robust_peer_frames is not None:
        changes["robust_peer_frames"] = args.robust_peer_frames
    if args.data:
        changes["data"] = args.data
    if args.frames is not None:
        changes["frames"] = args.frames
    if args.peer_frames is not None:
        changes["peer_frames"] = args.peer_frames or None
    if args.reps is not None:
        changes["reps"] = args.reps
    if args.synth_frames is not None:
        changes["synth_frames"] = args.synth_frames
    if args.clients:
        changes["clients"] = [int(c) for c in args.clients.split(",") if c.strip()]
    if args.duration is not None:
        changes["duration_s"] = args.duration
    if args.workers is not None:
        changes["workers"] = args.workers
    if args.client_phases:
        changes["client_phases"] = args.client_phases
    if args.frame_loop:
        changes["frame_loop"] = args.frame_loop
    if args.stress_clients is not None:
        changes["stress_clients"] = args.stress_clients
    if args.no_tune:
        changes["tune"] = False
    if args.reuse:
        changes["reuse"] = True
    if args.engine_config is not None:
        from ..bench.robust import load_engine_conf

        load_engine_conf(args.engine_config)  # a bad file fails now, not after other suites
        changes["robust_engine_config"] = args.engine_config.resolve()
    conf = quick_conf(**changes) if args.quick else BenchConf(**changes)
    command = (
        "sfmloc bench " + " ".join(shlex.quote(a) for a in sys.argv[2:])
        if len(sys.argv) > 2
        else "sfmloc bench"
    )
    if conf.robust_engine_config is not None and "robust" not in conf.suites:
        raise InputError("--engine-config applies to the robust suite only: add --suites robust")
    if conf.robust_rows and "robust" in conf.suites:
        from ..bench.robust import select_rows

        select_rows(conf.robust_rows)  # a bad pattern fails now, not after the other suites
    bar = ProgressPrinter()
    path = main(conf, args.out, progress=bar, command=command)
    bar.close()
    import json

    print(summary_text(json.loads(path.read_text())))
    print(f"\nresults {path}\nreport  {path.parent / 'report.md'}", file=sys.stderr)
    return 0
