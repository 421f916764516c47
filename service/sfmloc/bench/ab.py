"""Same-run A/B of the engine: two or more variants (a code tree, an engine config) replay
the same frames, interleaved and repeated, and are compared run by run and frame by frame.

On a shared machine only a ratio measured in one run is evidence: the load moves between runs.
Each variant runs ``sfmloc replay`` in its own process (its tree's ``service`` and ``client``
first on PYTHONPATH, one thread), in the order A B, then B A, ... so that drifts in the load
fall on both. Printed per variant: engine CPU per frame (mean, p99; process CPU time of
``localize``, which load changes less than wall clock), latency (mean, p99), the mean ms of
each stage (wall clock, as the engine's timers), the accuracy summary, and against the first
variant: CPU and latency ratios (median over the repetitions, with their range), the share
of frames whose pose is bit for bit the same (the trajectories' text) and the largest distance
between their camera centres. With two or more repetitions, each variant's later runs are
compared with its first the same way ("repeats: identical poses"): the engine is repeatable
(README, Conventions), so anything below 100% there is a fault, not noise, and a difference
between variants is theirs. The load average is printed before and after.

    python -m sfmloc.bench.ab MAP FRAMES --camera 'PINHOLE 640 480 525.5 525.5 320 240' \\
        --groundtruth FRAMES/pgt_sfm_seq01.txt --max-frames 300 --reps 3 \\
        --variant main=/work/main --variant mine=/work/wt-speed \\
        [--config mine=engine.json] [--fps 10] [--json ab.json]

``--map NAME=BUNDLE`` gives a variant its own map (the same frames): two maps compared in one
run, e.g. redkitchen from every frame against every 10th (issue 17's time target).

A tree whose ``sfmloc replay`` does not record per-frame CPU (before this tool) is compared on
latency only (said in the output).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..threads import single_thread_env


@dataclass
class Variant:
    name: str
    tree: Path
    config: Path | None = None
    map: Path | None = None
    runs: list[dict] = field(default_factory=list)


def parse_variants(
    specs: list[str], configs: list[str], maps: list[str] | None = None
) -> list[Variant]:
    """``NAME=TREE`` specs (a checkout with ``service/sfmloc``), ``NAME=FILE`` configs,
    ``NAME=BUNDLE`` maps (a variant replaying another map than the positional one)."""
    out: dict[str, Variant] = {}
    for spec in specs:
        name, sep, tree = spec.partition("=")
        if not sep or not name or not tree:
            raise InputError(f"--variant wants NAME=TREE, got {spec!r}")
        if name in out:
            raise InputError(f"variant {name!r} given twice")
        path = Path(tree).resolve()
        if not (path / "service" / "sfmloc" / "__init__.py").is_file():
            raise InputError(f"variant {name}: {path} has no service/sfmloc (not a checkout)")
        out[name] = Variant(name, path)
    for spec in configs:
        name, sep, file = spec.partition("=")
        if not sep or name not in out:
            raise InputError(f"--config wants NAME=FILE for a named variant, got {spec!r}")
        if not Path(file).is_file():
            raise InputError(f"variant {name}: config {file} not found")
        out[name].config = Path(file).resolve()
    for spec in maps or []:
        name, sep, bundle = spec.partition("=")
        if not sep or name not in out:
            raise InputError(f"--map wants NAME=BUNDLE for a named variant, got {spec!r}")
        if not (Path(bundle) / "manifest.json").is_file():
            raise InputError(f"variant {name}: {bundle} is not a map bundle (no manifest.json)")
        out[name].map = Path(bundle).resolve()
    if len(out) < 2:
        raise InputError(
            "give at least two --variant NAME=TREE (the same tree twice with different "
            "--config is fine)"
        )
    return list(out.values())


def _read_tum(path: Path) -> dict[str, tuple[str, np.ndarray]]:
    """stamp -> (the pose's text, camera centre) of a TUM trajectory (world_from_cam)."""
    out: dict[str, tuple[str, np.ndarray]] = {}
    if not path.is_file():
        return out
    for line in path.read_text().splitlines():
        f = line.split()
        if len(f) == 8 and not line.startswith("#"):
            out[f[0]] = (" ".join(f[1:]), np.array([float(v) for v in f[1:4]]))
    return out


def run_once(v: Variant, args: argparse.Namespace, work: Path, rep: int) -> dict:
    """One replay of variant ``v`` in its own process; its JSON summary, per-frame CPU (or
    latency) and trajectory."""
    js, traj = work / f"{v.name}-{rep}.json", work / f"{v.name}-{rep}.tum"
    bundle = v.map if v.map is not None else args.map
    cmd = [args.python, "-m", "sfmloc", "replay", str(bundle), str(args.frames)]
    cmd += ["--camera", args.camera, "--json", str(js), "--trajectory", str(traj)]
    cmd += ["--start", str(args.start), "--max-frames", str(args.max_frames), "--no-verify"]
    if args.fps is not None:  # else replay's own default clock (30 Hz), as before
        cmd += ["--fps", str(args.fps)]
    if args.groundtruth:
        cmd += ["--groundtruth", str(args.groundtruth)]
    if v.config is not None:
        cmd += ["--config", str(v.config)]
    env = single_thread_env()
    env["PYTHONPATH"] = os.pathsep.join(
        [str(v.tree / "service"), str(v.tree / "client")]
        + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])
    )
    t0 = time.perf_counter()
    res = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        tail = "\n".join((res.stderr or res.stdout).strip().splitlines()[-8:])
        raise InputError(f"variant {v.name}: sfmloc replay failed ({res.returncode}):\n{tail}")
    summary = json.loads(js.read_text())
    frames = summary.get("per_frame", [])
    has_cpu = bool(frames) and all("cpu_ms" in f for f in frames)
    key = "cpu_ms" if has_cpu else "latency_ms"
    return {
        "summary": summary,
        "ms": np.array([f[key] for f in frames], np.float64),
        "latency": np.array([f["latency_ms"] for f in frames], np.float64),
        "cpu": has_cpu,
        "traj": _read_tum(traj),
        "wall_s": wall,
    }


def _same_poses(a: dict, b: dict) -> tuple[float, float]:
    """Share of the frames posed by either run that both posed identically (as text), and the
    largest distance between the camera centres of frames both posed (map units)."""
    ta, tb = a["traj"], b["traj"]
    keys = set(ta) | set(tb)
    if not keys:
        return 1.0, 0.0
    same = sum(1 for k in keys if k in ta and k in tb and ta[k][0] == tb[k][0])
    both = [k for k in keys if k in ta and k in tb]
    far = max((float(np.linalg.norm(ta[k][1] - tb[k][1])) for k in both), default=0.0)
    return same / len(keys), far


def _accuracy(s: dict) -> str:
    med = s.get("median_position_error_m", float("nan"))
    w5 = s.get("within_5cm_5deg_fraction", float("nan"))
    return (
        f"localized {s.get('localized_frames', 0)}/{s.get('frames', 0)}, median "
        f"{med * 100:.3f} cm, within 5 cm/5 deg {w5 * 100:.1f}%, wrong "
        f"{s.get('confident_wrong', 0)}"
    )


def compare(variants: list[Variant]) -> dict:
    """Per variant: means over the repetitions; against the first: per-repetition ratios."""
    base = variants[0]
    out: dict = {}
    for v in variants:
        ms = [r["ms"] for r in v.runs]
        lat = [r["latency"] for r in v.runs]
        stages: dict[str, float] = {}
        stages_cpu: dict[str, float] = {}
        for r in v.runs:
            for k, st in r["summary"].get("stages_ms", {}).items():
                stages[k] = stages.get(k, 0.0) + st["mean"] / len(v.runs)
            for k, st in r["summary"].get("stages_cpu_ms", {}).items():
                stages_cpu[k] = stages_cpu.get(k, 0.0) + st["mean"] / len(v.runs)
        row: dict[str, Any] = {
            "tree": str(v.tree),
            "config": str(v.config) if v.config else None,
            "map": str(v.map) if v.map else None,
            "cpu_recorded": all(r["cpu"] for r in v.runs),
            "ms_mean": float(np.mean([m.mean() for m in ms])),
            "ms_p99": float(np.mean([np.percentile(m, 99) for m in ms])),
            "latency_mean": float(np.mean([x.mean() for x in lat])),
            "latency_p99": float(np.mean([np.percentile(x, 99) for x in lat])),
            "stages_ms": stages,
            # (trees from before the engine timed its stages on CPU have none)
            "stages_cpu_ms": stages_cpu
            if all("stages_cpu_ms" in r["summary"] for r in v.runs)
            else {},
            "accuracy": _accuracy(v.runs[0]["summary"]),
            # the replay's clock (frames/s): what --fps gave, or replay's default
            "clock_fps": v.runs[0]["summary"].get("clock_fps"),
        }
        if len(v.runs) > 1:
            # each repetition against the variant's first run: the replay's repeatability
            again = [_same_poses(r, v.runs[0]) for r in v.runs[1:]]
            row["repeats"] = {
                "identical_poses": min(s for s, _ in again),
                "max_centre_distance": max(f for _, f in again),
            }
        if v is not base:
            both_cpu = row["cpu_recorded"] and all(r["cpu"] for r in base.runs)
            key = "ms" if both_cpu else "latency"
            ratios = [r[key].mean() / b[key].mean() for r, b in zip(v.runs, base.runs)]
            p99s = [
                np.percentile(r[key], 99) / np.percentile(b[key], 99)
                for r, b in zip(v.runs, base.runs)
            ]
            same, far = _same_poses(v.runs[0], base.runs[0])
            row["vs_base"] = {
                "on": "cpu" if both_cpu else "latency",
                "mean_ratio": float(np.median(ratios)),
                "mean_ratio_range": [float(min(ratios)), float(max(ratios))],
                "p99_ratio": float(np.median(p99s)),
                "identical_poses": same,
                "max_centre_distance": far,
            }
        out[v.name] = row
    return out


def format_report(result: dict, load_before: str, load_after: str, reps: int) -> str:
    names = list(result)
    lines = [f"A/B, {reps} repetition(s) per variant, interleaved; load before {load_before}"]
    clocks = {result[n].get("clock_fps") for n in names} - {None}
    if clocks:
        lines.append("replay clock " + ", ".join(f"{c:g}" for c in sorted(clocks)) + " frames/s")
    for n in names:
        r = result[n]
        what = "CPU" if r["cpu_recorded"] else "latency (no per-frame CPU in this tree)"
        if r.get("map"):
            what = f"map {Path(r['map']).name}, {what}"
        lines.append(
            f"{n:12s} {what}: mean {r['ms_mean']:.2f} ms, p99 {r['ms_p99']:.2f} ms; latency "
            f"mean {r['latency_mean']:.2f}, p99 {r['latency_p99']:.2f} ms"
        )
        lines.append(
            f"{'':12s} stages (wall ms/frame): "
            + ", ".join(f"{k} {v:.2f}" for k, v in r["stages_ms"].items())
        )
        if r.get("stages_cpu_ms"):
            lines.append(
                f"{'':12s} stages (CPU ms/frame): "
                + ", ".join(f"{k} {v:.2f}" for k, v in r["stages_cpu_ms"].items())
            )
        lines.append(f"{'':12s} {r['accuracy']}")
        rep = r.get("repeats")
        if rep:
            lines.append(
                f"{'':12s} repeats against its first run: identical poses "
                f"{rep['identical_poses'] * 100:.1f}% (the least of them), centres at most "
                f"{rep['max_centre_distance']:.3g} apart"
            )
        vb = r.get("vs_base")
        if vb:
            lo, hi = vb["mean_ratio_range"]
            lines.append(
                f"{'':12s} vs {names[0]} ({vb['on']}): mean x{vb['mean_ratio']:.3f} "
                f"(x{lo:.3f}-x{hi:.3f}), p99 x{vb['p99_ratio']:.3f}; identical poses "
                f"{vb['identical_poses'] * 100:.1f}%, centres at most "
                f"{vb['max_centre_distance']:.3g} apart"
            )
    lines.append(f"load after {load_after}")
    return "\n".join(lines)


def _load() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "n/a"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m sfmloc.bench.ab",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("map", type=Path, help="map bundle folder")
    ap.add_argument("frames", type=Path, help="image folder or video (as sfmloc replay)")
    ap.add_argument("--camera", required=True, help="as sfmloc replay --camera")
    ap.add_argument("--groundtruth", type=Path, help="as sfmloc replay --groundtruth")
    ap.add_argument("--start", type=int, default=0, help="first frame (default 0)")
    ap.add_argument("--max-frames", type=int, default=300, help="frames per run (default 300)")
    ap.add_argument(
        "--fps",
        type=float,
        metavar="HZ",
        help="the replay clock, passed to sfmloc replay --fps: frame i is stamped i / HZ, so "
        "the engine sees a 1/HZ frame interval (the tracking window widens with it). Use the "
        "rate the frames were taken at, e.g. 10 or 3 for the robust suite's 10/3 Hz rows "
        "(their folders keep every 3rd/10th frame of a 30 Hz video). Default: replay's "
        "default, 30 Hz",
    )
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=TREE",
        help="a checkout to run (its service/ and client/); the first is the baseline",
    )
    ap.add_argument(
        "--config",
        action="append",
        default=[],
        metavar="NAME=FILE",
        help="an engine config (JSON/TOML) for the named variant",
    )
    ap.add_argument(
        "--map",
        dest="maps",
        action="append",
        default=[],
        metavar="NAME=BUNDLE",
        help="replay this map bundle for the named variant instead of MAP (to compare maps, "
        "e.g. from every frame against every 10th, in one run)",
    )
    ap.add_argument("--reps", type=int, default=2, help="repetitions per variant (default 2)")
    ap.add_argument("--json", type=Path, help="write the comparison here")
    ap.add_argument("--python", default=sys.executable, help="interpreter for the replays")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        variants = parse_variants(args.variant, args.config, args.maps)
        if args.reps < 1 or args.max_frames < 1:
            raise InputError("--reps and --max-frames must be at least 1")
        if args.fps is not None and not args.fps > 0:
            raise InputError(f"--fps must be positive, got {args.fps}")
        load_before = _load()
        with tempfile.TemporaryDirectory(prefix="sfmloc-ab-") as tmp:
            for rep in range(args.reps):
                order = variants if rep % 2 == 0 else variants[::-1]
                for v in order:
                    print(f"rep {rep + 1}/{args.reps}: {v.name} ...", file=sys.stderr, flush=True)
                    v.runs.append(run_once(v, args, Path(tmp), rep))
        result = compare(variants)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    load_after = _load()
    print(format_report(result, load_before, load_after, args.reps))
    if args.json:
        doc = {"load_before": load_before, "load_after": load_after, "variants": result}
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
