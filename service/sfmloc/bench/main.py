"""``sfmloc bench``: every suite, one ``results.json``, one ``report.md``, the figures.

``main(conf, out) -> Path`` (hloc style) runs the suites of ``conf`` and returns the path of
``OUT/results.json``. Layout of ``OUT``::

    results.json                summary numbers only (no per-frame arrays)
    report.md                   tables, figures, tuning, notes: all from results.json
    <suite>/fig-per-frame.png   the paper's Figure 2 for our engine
    <suite>/fig-trajectory.png  top view against ground truth, lost frames marked
    <suite>/fig-compare.png     ours vs the peers on the same frames
    <suite>/frames-<method>.json          per-frame records
    <suite>/<method>.tum, <method>.gt.tum  estimate and ground truth (TUM, same timestamps)
    throughput.png
    work/                       maps, synthetic data, SIFT maps (reused with --reuse)
"""

from __future__ import annotations

import importlib.metadata
import logging
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

from ..errors import InputError
from ..eval.metrics import WRONG_POSE_RULE, WRONG_POSITION_FRACTION, WRONG_ROTATION_DEG, FrameRecord
from ..io.frames import FrameSource
from . import figures, report
from .config import LOCALIZATION_SUITES, OURS, PEERS, SUITES, BenchConf
from .prepare import prepare_in_child
from .reps import SuiteRuns, run_reps, run_sift, summarize_repeated
from .sift_peer import SiftMap
from .stats import method_summary, ratios, relocalization_times, stage_times
from .suites import Prepared, peer_indices, prepare

RELOC_PEER = "global-every-frame"
RELOC_P95_MS = 40.0  # issue 10: relocalization p95 at most 40 ms (redkitchen, quiet machine)

log = logging.getLogger(__name__)

Progress = Callable[[str, float, str], None]


class LogProgress:
    """Progress as log lines (stderr), at most one per stage per 10%."""

    def __init__(self) -> None:
        self.last: dict[str, int] = {}

    def __call__(self, stage: str, fraction: float, message: str = "") -> None:
        decile = int(min(max(fraction, 0.0), 1.0) * 10)
        if self.last.get(stage) != decile:
            self.last[stage] = decile
            log.info("%-34s %5.1f%% %s", stage, 100 * fraction, message)


def machine_info() -> dict:
    model = platform.processor() or "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info = {
        "cpus": os.cpu_count(),
        "cpu_model": model,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "load_average_start": os.getloadavg()[0],
    }
    info["git"] = _git_describe()
    for dist in (
        "numpy",
        "opencv-contrib-python-headless",
        "pycolmap",
        "faiss-cpu",
        "eclipse-zenoh",
    ):
        try:
            info[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            info[dist] = "?"
    return info


def _git_describe() -> str:
    """The commit measured (engine and all), '+dirty' when the checkout has local changes."""
    from .config import REPO

    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        return (head + ("+dirty" if dirty else "")) if head else "?"
    except (OSError, subprocess.SubprocessError):
        return "?"


def _rel(path: Path, out: Path) -> str:
    return os.path.relpath(path, out)


def summarize_suite(
    recs: dict[str, list[FrameRecord]], peer_idx: list[int], stride: int, scene_scale: float
) -> dict:
    """Summaries of every method, ours again on the peers' frames, ratios and stage times.
    ``scene_scale`` (our map's median depth) sets every method's wrong-pose limit."""
    keep = set(peer_idx)
    ours = recs[OURS]
    methods = {m: method_summary(rs, scene_scale) for m, rs in recs.items()}
    same = {OURS: method_summary([r for r in ours if r.index in keep], scene_scale)}
    peers = [m for m in PEERS if m in recs]
    peer_stages = {}
    for m in peers:
        st = stage_times(recs[m])
        peer_stages[m] = {k: v["mean"] for k, v in st.items() if k != "total"}
    return {
        "kind": "localization",
        "scene_scale": scene_scale,
        "peer_frames": {"count": len(peer_idx), "stride": stride},
        "methods": methods,
        "same_frames": same,
        "ratios": {m: ratios(same[OURS], methods[m]) for m in peers},
        "stages_ms": stage_times(ours),
        "peer_stages_ms": peer_stages,
        # global-every-frame is ``engine.relocalize`` on every peer frame: its calls are the
        # single-image relocalization issue 10 times (map images among them, as replayed).
        **(
            {"relocalization_ms": relocalization_times(recs[RELOC_PEER])}
            if RELOC_PEER in recs
            else {}
        ),
    }


def write_suite_files(
    name: str,
    recs: dict[str, list[FrameRecord]],
    summary: dict,
    peer_idx: list[int],
    out: Path,
    points_xyz=None,
) -> dict:
    """Per-frame JSON, TUM pairs and the three figures of a suite; their paths (relative to out)."""
    d = out / name
    d.mkdir(parents=True, exist_ok=True)
    files: dict = {"tum": []}
    for m, rs in recs.items():
        report.write_json(d / f"frames-{m}.json", report.frame_dicts(rs))
        report.write_tum_pair(rs, d / f"{m}.tum", d / f"{m}.gt.tum")
        files["tum"] += [_rel(d / f"{m}.tum", out), _rel(d / f"{m}.gt.tum", out)]
    ours = recs[OURS]
    keep = set(peer_idx)
    files["fig_per_frame"] = _rel(
        figures.per_frame(ours, f"{name}: sfmloc, {len(ours)} frames", d / "fig-per-frame.png"), out
    )
    files["fig_trajectory"] = _rel(
        figures.trajectory(
            ours, f"{name}: top view (sfmloc)", d / "fig-trajectory.png", points_xyz
        ),
        out,
    )
    cmp_recs = {
        m: ([r for r in rs if r.index in keep] if m == OURS else rs) for m, rs in recs.items()
    }
    cmp_sum = {
        m: (summary["same_frames"][OURS] if m == OURS else summary["methods"][m]) for m in recs
    }
    files["fig_compare"] = _rel(
        figures.compare(
            cmp_recs, cmp_sum, f"{name}: the same {len(peer_idx)} frames", d / "fig-compare.png"
        ),
        out,
    )
    return files


def suite_results(
    prep: Prepared,
    runs: SuiteRuns,
    conf: BenchConf,
    out: Path,
    sift_map_info: dict,
) -> dict:
    """Summaries, ratios and files of one localization suite: timing numbers the median over
    its reps, accuracy, per-frame files and figures from rep 1 (``bench.reps``)."""
    from ..map.bundle import MapBundle, read_manifest

    idx, stride = peer_indices(prep, conf.peer_frames)
    man = read_manifest(prep.bundle_path)
    bundle = MapBundle(prep.bundle_path, verify=False)
    summary = summarize_repeated(
        runs, lambda recs: summarize_suite(recs, idx, stride, bundle.scene_scale)
    )
    rp = summary["reps"]["repeatable"]
    if not rp["identical"]:
        log.warning(
            "%s: the reps' poses differ from rep 1's (%s); accuracy is rep 1's",
            prep.name,
            ", ".join(
                f"{m}: {v['frames_differing_per_rep']} frames" for m, v in rp["methods"].items()
            ),
        )
    files = write_suite_files(prep.name, runs.first(), summary, idx, out, bundle.points_xyz)
    return {
        **summary,
        "data": prep.kind,
        "frames_replayed": prep.count,
        "start": prep.start,
        "map": {
            **prep.info,
            "images": man.counts.images,
            "points": man.counts.points,
            "descriptors": man.counts.descriptors,
            "build_s": man.timings_s.get("total"),
            **sift_map_info,
        },
        "files": files,
    }


def targets(results: dict) -> list[dict]:
    """The acceptance checks, computed from the measured numbers."""
    out = []
    s = results["suites"].get("redkitchen")
    if s:
        o = s["same_frames"][OURS]
        sift = s["methods"]["pycolmap-sift"]
        r = s["ratios"]
        rs = r["pycolmap-sift"]
        out.append(
            {
                "target": "redkitchen: our frame rate >= 10x pycolmap-sift's",
                "met": rs["rate_ratio"] >= 10,
                "measured": f"{rs['rate_ratio']:.1f}x (CPU time {rs['cpu_ratio']:.1f}x)"
                + _spread(s, "rate_ratio_sift", "x", "of ours against one pycolmap-sift run"),
            }
        )
        out.append(
            {
                "target": "redkitchen: our median position error <= pycolmap-sift's",
                "met": o["median_position_error_m"] <= sift["median_position_error_m"],
                "measured": f"ours {o['median_position_error_m'] * 100:.2f} cm / "
                f"{o['median_rotation_error_deg']:.2f} deg, "
                f"pycolmap-sift {sift['median_position_error_m'] * 100:.2f} cm / "
                f"{sift['median_rotation_error_deg']:.2f} deg",
            }
        )
        out.append(
            {
                "target": "redkitchen: >= 99.5% of frames within 5 cm / 5 deg",
                "met": s["methods"][OURS]["recall_5cm_5deg_pct"] >= 99.5,
                "measured": f"{s['methods'][OURS]['recall_5cm_5deg_pct']:.1f}% of "
                f"{s['methods'][OURS]['frames_with_groundtruth']} frames",
            }
        )
        out.append(
            {
                "target": "redkitchen: our frame rate >= 3x global-every-frame's",
                "met": r["global-every-frame"]["rate_ratio"] >= 3,
                "measured": f"{r['global-every-frame']['rate_ratio']:.1f}x (CPU time "
                f"{r['global-every-frame']['cpu_ratio']:.1f}x)"
                + _spread(s, "rate_ratio_gef", "x", "of both, back to back"),
            }
        )
        rl = s.get("relocalization_ms")
        if rl and rl["calls"]:
            w, c = rl["wall"], rl["cpu"]
            out.append(
                {
                    "target": f"redkitchen: relocalization p95 <= {RELOC_P95_MS:g} ms",
                    "met": w["p95"] <= RELOC_P95_MS,
                    "measured": f"p95 {w['p95']:.1f} ms (CPU {c['p95']:.1f}), mean "
                    f"{w['mean']:.1f}, p50 {w['p50']:.1f}, p99 {w['p99']:.1f} ms over "
                    f"{rl['calls']} calls of {RELOC_PEER}"
                    + _spread(s, "relocalization_p95_ms", " ms", prefix="p95 "),
                }
            )
    for name in LOCALIZATION_SUITES:
        s = results["suites"].get(name)
        if s:
            m = s["methods"][OURS]
            out.append(
                {
                    "target": f"{name}: mean time per frame <= 33.3 ms (the paper's 'over 30 Hz')",
                    "met": m["T_ms_mean"] <= 1000 / 30,
                    "measured": f"{m['T_ms_mean']:.1f} ms ({m['rate_hz']:.0f} Hz)"
                    + _spread(s, "ours_T_ms_mean", " ms"),
                }
            )
            rp = s.get("reps", {}).get("repeatable")
            if rp and s["reps"]["count"] > 1:
                out.append(
                    {
                        "target": f"{name}: the same poses in every rep (accuracy is rep 1's)",
                        "met": rp["identical"],
                        "measured": report.repeat_text(s["reps"]),
                    }
                )
            rule = (
                f"any status but LOST; > {WRONG_POSITION_FRACTION:.0%} of the scene scale or "
                f"> {WRONG_ROTATION_DEG:g} deg"
            )
            out.append(
                {
                    "target": f"{name}: no wrong pose ({rule})",
                    "met": m["wrong_poses"] == 0,
                    "measured": f"{m['wrong_poses']} frames (limit "
                    f"{m['wrong_position_limit']:.3g} map units"
                    f"{_by_status(m['wrong_statuses'])})",
                }
            )
    rb = results["suites"].get("robust")
    if rb:
        from .robust import targets as robust_targets

        out += robust_targets(rb)
    return out


def _spread(suite: dict, key: str, unit: str, what: str = "", prefix: str = "") -> str:
    """What a target's median was taken over, and its min-max (nothing for one rep)."""
    reps = suite.get("reps")
    if not reps or reps["count"] < 2:
        return ""
    sp = reps["spread"][key]
    return (
        f"; median of {reps['count']} reps{' ' + what if what else ''}, "
        f"{prefix}{sp['min']:.1f}-{sp['max']:.1f}{unit}"
    )


def _by_status(counts: dict[str, int]) -> str:
    return "; " + ", ".join(f"{k} {v}" for k, v in counts.items()) if counts else ""


def _notes(results: dict, conf: BenchConf) -> list[str]:
    n = []
    for name in report.localization_suites(results):
        pf = results["suites"][name]["peer_frames"]
        if pf["stride"] > 1:
            n.append(
                f"{name}: the peers ran on every {report.ordinal(pf['stride'])} replayed frame "
                f"({pf['count']} frames) to keep the run within its time budget (--peer-frames); "
                "the "
                "side-by-side rows summarise our engine on exactly those frames (it still "
                "processes every "
                "frame, as a video)."
            )
    if "redkitchen" in results["suites"] or "redkitchen-split" in results["suites"]:
        n.append(
            "redkitchen ground truth is pgt_sfm_seq01.txt, a pseudo ground truth from COLMAP SfM "
            "(SIFT) over "
            "all frames; such a reference favours SIFT/COLMAP-based estimates (Brachmann et al., "
            "ICCV 2021, "
            "'On the Limits of Pseudo Ground Truth in Visual Camera Re-localisation'). The "
            "synthetic suites "
            "have exact ground truth."
        )
        n.append(
            "redkitchen replays the map images too (every 10th frame is a map image); all methods "
            "see the "
            "same frames."
        )
    for name in report.localization_suites(results):
        reps = results["suites"][name].get("reps")
        if reps and reps["count"] > 1:
            n.append(
                f"{name}: our engine and global-every-frame ran {reps['count']} times each, "
                "interleaved (pycolmap-sift once, after the last rep): every time, rate and ratio "
                "published is the median over the reps (the targets read it), with the min-max "
                "beside it; accuracy, per-frame files and figures are rep 1's."
            )
    if conf.quick:
        n.append(
            "--quick: a smoke run with few frames and small synthetic maps (throughput and map "
            "serve the first suite's map); not the reference numbers."
        )
    return n


def real_suites_map(conf: BenchConf, loc: list[str]) -> str | None:
    """The localization suite whose map the map and throughput suites serve (None: neither
    runs). ``loc``: the localization suites of the run. Redkitchen's, except in a smoke run
    (``--quick``) with a localization suite but not redkitchen: its first suite's map (the
    synthetic room's) rather than building redkitchen's; the results name the map. The one
    place this is decided: the child prepares this map and the suites then read it."""
    if not any(s in conf.suites for s in ("map", "throughput")):
        return None
    if conf.quick and loc and "redkitchen" not in loc:
        return loc[0]
    return "redkitchen"


def main(
    conf: BenchConf,
    out: str | Path,
    *,
    progress: Progress | None = None,
    command: str | None = None,
) -> Path:
    """Run the suites of ``conf``; write results.json, report.md and figures under ``out``."""
    from ..threads import pin_threads_env, pin_threads_runtime

    pin_threads_env()
    pin_threads_runtime()
    bad = [s for s in conf.suites if s not in SUITES]
    if bad:
        raise InputError(f"unknown suite(s) {', '.join(bad)}; choose from {', '.join(SUITES)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    work = out / "work"
    progress = progress or LogProgress()
    t_start = time.perf_counter()
    results: dict = {
        "format": "sfmloc-bench-results",
        "version": 2,
        "wrong_pose_rule": WRONG_POSE_RULE,
        "created_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "command": command or "sfmloc bench",
        "machine": machine_info(),
        "conf": conf.model_dump(mode="json"),
        "suites": {},
    }
    loc = [s for s in SUITES if s in conf.suites and s in LOCALIZATION_SUITES]
    need_real = [s for s in ("map", "throughput") if s in conf.suites]
    real_map = real_suites_map(conf, loc)
    # The maps are built in a child process, and this one then only reads them (``reuse`` on:
    # the child has just made or checked them): the process that times our engine never builds
    # a map, as a server worker never does (bench.prepare, docs/development.md#bench-isolation).
    # The map and throughput suites' map too.
    to_prepare = loc + ([real_map] if real_map is not None and real_map not in loc else [])
    if "robust" in conf.suites:  # its rows' maps and frames, reusing the suites' above
        to_prepare.append("robust")
    results["prepare_child_s"] = prepare_in_child(to_prepare, conf, work)
    built = conf.model_copy(update={"reuse": True})
    preps: dict[str, Prepared] = {}
    for name in loc:
        preps[name] = prepare(name, built, work, progress)

    # Every suite's reps of our engine and global-every-frame first; the SIFT peer's tuning and
    # runs (SIFT extraction, HNSW indices: the heaviest allocations left in this process) after
    # them all (bench.reps).
    all_runs: dict[str, SuiteRuns] = {}
    for name in loc:
        log.info("== %s: sfmloc and global-every-frame, %d reps", name, conf.reps)
        all_runs[name] = run_reps(preps[name], conf, progress)

    sift_conf = conf.sift
    if loc and conf.tune:
        base = next((preps[n] for n in loc if preps[n].kind == "real"), preps[loc[0]])
        log.info("== tuning the pycolmap-sift peer on %d frames of %s", conf.tune_frames, base.name)
        from .tune import tune_sift

        sift_conf, results["sift_tuning"] = tune_sift(base, conf, progress)
    results["sift_peer_conf"] = sift_conf.model_dump()

    for name in loc:
        log.info("== %s: pycolmap-sift", name)
        prep, runs = preps[name], all_runs[name]
        run_sift(runs, prep, conf, sift_conf, progress)
        sm = SiftMap.load(prep.sift_map_path)
        results["suites"][name] = suite_results(
            prep,
            runs,
            conf,
            out,
            {"sift_points": sm.n_points, "sift_descriptors": int(len(sm.desc))},
        )
        log.info("%s done (%.0f s so far)", name, time.perf_counter() - t_start)

    if "robust" in conf.suites:
        from .robust import run_robust

        log.info("== robust: %s", ", ".join(conf.robust_rows) if conf.robust_rows else "every row")
        # ``built``: the child prepared every row's inputs (its failures are the rows' crashes)
        results["suites"]["robust"] = run_robust(
            built, work, progress, preps, sift_conf, out, prepared=True
        )
        results["suites"]["robust"]["sift_peer_tuned"] = "sift_tuning" in results
        log.info("robust done (%.0f s so far)", time.perf_counter() - t_start)

    if real_map is not None:
        # The child built it (to_prepare above).
        rk = preps[real_map] if real_map in preps else prepare(real_map, built, work, progress)
        if real_map != "redkitchen":
            log.info("== --quick: %s on the %s map", " and ".join(need_real), rk.name)
        camera = conf.camera if rk.kind == "real" else rk.camera.to_string()
        if "map" in conf.suites:
            from .mapstats import map_stats, sift_map_stats

            log.info("== map: size, load time, resident memory")
            frames = [rk.frames_dir / n for n in FrameSource(rk.frames_dir).names()[:5]]
            mp = map_stats(rk.bundle_path, frames, camera)
            mp["sift_peer_map"] = sift_map_stats(
                rk.sift_map_path, sift_conf.descriptors, sift_conf.hnsw_m
            )
            results["suites"]["map"] = {"kind": "map", **mp}
        if "throughput" in conf.suites:
            from .throughput import run_throughput

            log.info("== throughput: %s clients", ", ".join(map(str, conf.clients)))
            th = run_throughput(
                work,
                rk.bundle_path,
                rk.frames_dir,
                camera,
                conf.clients,
                conf.rate_hz,
                conf.duration_s,
                conf.workers,
                progress,
                memory_workers=tuple(conf.memory_workers),
                phases=conf.client_phases,
                frame_loop=conf.frame_loop,
                stress_clients=conf.stress_clients,
            )
            th["fig_throughput"] = _rel(
                figures.throughput(
                    th["rows"],
                    f"throughput: {th['workers']} server workers, {conf.rate_hz:g} Hz per client",
                    out / "throughput.png",
                ),
                out,
            )
            results["suites"]["throughput"] = {"kind": "throughput", **th}

    # The builder suite times builds, so it builds in this process, and last: after every timed
    # replay of our engine (localization suites, robust rows) and the throughput and map suites,
    # none of which then runs in a heap a build has left fragmented (bench.prepare).
    if "builder" in conf.suites:
        from .builder import run_builder

        log.info("== builder: %s", ", ".join(conf.builder_parts))
        results["suites"]["builder"] = {
            "kind": "builder",
            **run_builder(
                work / "builder",
                Path(conf.data),
                conf.builder_parts,
                views=conf.builder_views,
            ),
        }
        log.info("builder done (%.0f s so far)", time.perf_counter() - t_start)

    results["targets"] = targets(results)
    results["notes"] = _notes(results, conf)
    results["machine"]["load_average_end"] = os.getloadavg()[0]
    results["wall_s"] = time.perf_counter() - t_start
    path = report.write_json(out / "results.json", results)
    report.write_report(results, out)
    log.info("wrote %s and %s in %.0f s", path, out / "report.md", results["wall_s"])
    return path
