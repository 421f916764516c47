"""The ``builder`` measurements (issue 17): --extend against a build from all images at once,
build peak memory per descriptor, map quality per input density, and the video target.

Parts (``--parts``; each prints JSON lines and is stored in ``--out``):

- ``extend``: redkitchen, known poses, every ``--stride``-th of the first ``--frames`` frames.
  The map of the first half (frames 0 .. N/2-1) extended with the second half
  (``build.extend``), against the map built from all of them at once. Both replay the N
  frames at 30 Hz (localized %, median error, wrong poses) and relocalize ``--reloc`` single
  frames; build time as wall and CPU seconds of this process (pycolmap's threads included), the
  extension's without the first half's build (the map it extends exists).
- ``memory``: ``sfmloc.bench.build_memory`` on synthetic rooms of ``--views`` mapping views.
- ``density``: ``sfmloc.bench.density`` maps from every 10th, 4th, 2nd, 1st frame.
- ``video``: ``sfmloc.bench.density``'s every-10th map against a map built from a video of the
  same frames (encoded here with OpenCV, MJPG) with the TUM poses.

    python -m sfmloc.bench.builder --work /tmp/bb --parts extend --frames 1000 --stride 10
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from pathlib import Path
from typing import Any

from .config import DEFAULT_DATA, REDKITCHEN_CAMERA, REDKITCHEN_POSES


def _links(work: Path, data: Path, names: list[str], label: str) -> Path:
    """A folder of symlinks to ``names`` in ``data`` (the data are read in place)."""
    folder = work / f"frames-{label}"
    if not folder.is_dir():
        folder.mkdir(parents=True)
        for n in names:
            (folder / n).symlink_to((data / n).resolve())
    return folder


def _timed(fn, *args, **kwargs) -> tuple[Any, float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0, time.process_time() - c0


def extend_part(work: Path, data: Path, frames: int, stride: int, n_reloc: int) -> dict:
    from ..builder import build, sfm
    from ..builder.extend import extend
    from ..io.frames import FrameSource
    from .density import evaluate

    names = FrameSource(data).names()[:frames]
    half = len(names) // 2
    all_dir = _links(work, data, names, f"all{frames}")
    first_dir = _links(work, data, names[:half], f"first{frames}")
    second_dir = _links(work, data, names[half:], f"second{frames}")
    common = {
        "poses": data / REDKITCHEN_POSES,
        "camera": REDKITCHEN_CAMERA,
        "stride": stride,
        "workdir": work,
    }
    conf = build.preset("default")
    maps = work / "maps"
    row: dict[str, Any] = {"frames": frames, "stride": stride}
    # The first half's and the full map (and their build times) are reused when present.
    cache = work / f"builds-{frames}-{stride}.json"
    done = json.loads(cache.read_text()) if cache.is_file() else {}
    if (maps / "first" / "manifest.json").is_file() and "first_cpu_s" in done:
        row.update({k: done[k] for k in ("first_wall_s", "first_cpu_s")})
    else:
        _, row["first_wall_s"], row["first_cpu_s"] = _timed(
            build.main, conf, "first", maps, images=first_dir, sfm_conf=sfm.sfm_conf(), **common
        )
    _, row["extend_wall_s"], row["extend_cpu_s"] = _timed(
        extend,
        maps / "first",
        "extended",
        maps,
        images=second_dir,
        sfm_conf=sfm.sfm_conf(),
        **common,
    )
    if (maps / "full" / "manifest.json").is_file() and "full_cpu_s" in done:
        row.update({k: done[k] for k in ("full_wall_s", "full_cpu_s")})
        row["full_reused"] = True
    else:
        _, row["full_wall_s"], row["full_cpu_s"] = _timed(
            build.main, conf, "full", maps, images=all_dir, sfm_conf=sfm.sfm_conf(), **common
        )
    cache.write_text(json.dumps({k: v for k, v in row.items() if k.endswith("_s")}))
    row["extend_over_full_wall"] = round(row["extend_wall_s"] / row["full_wall_s"], 3)
    row["extend_over_full_cpu"] = round(row["extend_cpu_s"] / row["full_cpu_s"], 3)
    evals_path = work / "evaluations.json"  # per bundle build id: evaluated once
    evals = json.loads(evals_path.read_text()) if evals_path.is_file() else {}
    for label in ("full", "extended", "first"):
        bid = json.loads((maps / label / "manifest.json").read_text())["build_id"]
        if bid not in evals:
            evals[bid] = evaluate(maps / label, data, frames, n_reloc)
            evals_path.write_text(json.dumps(evals))
        row[label] = evals[bid]
    f, e = row["full"], row["extended"]
    row["meets_localized"] = e["replay_localized_pct"] >= f["replay_localized_pct"] - 0.5
    row["meets_median"] = e["median_position_error_cm"] <= 1.1 * f["median_position_error_cm"]
    row["meets_time"] = row["extend_over_full_cpu"] <= 0.5
    return row


def memory_part(work: Path, views: list[int]) -> dict:
    from .build_memory import TARGET_BYTES_PER_DESCRIPTOR, make_room, measure, table

    rows = []
    for v in views:
        room = make_room(work / "rooms", v, 640, 480)
        out = work / f"memory-maps-{v}"
        rows.append(measure(room, out, "default", {}))
        shutil.rmtree(out, ignore_errors=True)
        print(table(rows).splitlines()[-1], flush=True)
    return {
        "rows": rows,
        "table": table(rows),
        "target_bytes_per_descriptor": TARGET_BYTES_PER_DESCRIPTOR,
        "all_meet_target": all(r["meets_target"] for r in rows),
    }


def density_part(work: Path, data: Path, frames: int, strides: list[int], n_reloc: int) -> dict:
    """Maps from every n-th frame, densest last: points, replay, relocalization per map, and
    whether each never decreases as images are added."""
    from .density import build_map, evaluate, interleaved_cpu

    rows, bundles = [], []
    for stride in sorted(strides, reverse=True):
        bundle, secs = build_map(work / "density", data, frames, stride, "geometric")
        row = {"stride": stride, "build_s": round(secs), **evaluate(bundle, data, frames, n_reloc)}
        rows.append(row)
        bundles.append(bundle)
        print(json.dumps(row), flush=True)
    keys = ("points", "replay_localized_pct", "reloc_ok")
    monotone = {k: all(b[k] >= a[k] for a, b in zip(rows, rows[1:])) for k in keys}
    out: dict[str, Any] = {"rows": rows, "never_decreases": monotone}
    if len(rows) > 1:
        # The densest map's time against the sparsest's: replayed side by side (the rows'
        # times are each measured at another moment of a shared machine's load).
        dense, sparse = interleaved_cpu([bundles[-1], bundles[0]], data, frames)
        out["interleaved"] = {
            "densest": dense,
            "sparsest": sparse,
            "cpu_mean_ratio": round(dense["cpu_ms_mean"] / sparse["cpu_ms_mean"], 3),
            "cpu_p99_ratio": round(dense["cpu_ms_p99"] / sparse["cpu_ms_p99"], 3),
        }
        print(json.dumps(out["interleaved"]), flush=True)
    return out


def _encode_video(data: Path, names: list[str], path: Path, fps: float = 30.0) -> Path:
    import cv2

    from ..io.frames import read_image

    first = read_image(data / names[0])
    h, w = first.shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (w, h))
    try:
        for n in names:
            writer.write(read_image(data / n))
    finally:
        writer.release()
    return path


def video_part(work: Path, data: Path, frames: int, n_reloc: int) -> dict:
    """A video of the first ``frames`` frames (MJPG, 30 fps) with the pgt poses as a TUM log
    on the video's clock, built with ``--video --poses``; against the every-10th folder map."""
    from ..builder import build
    from ..builder.video import build_from_video
    from ..io.frames import FrameSource
    from ..io.poses import name_stem, read_poses, write_tum
    from .density import build_map, evaluate

    names = FrameSource(data).names()[:frames]
    video = work / f"redkitchen-{frames}.avi"
    if not video.is_file():
        _encode_video(data, names, video)
    by_name = read_poses(data / REDKITCHEN_POSES).by_stem()  # cam_from_world
    stamps, wfc = [], []
    for i, n in enumerate(names):
        T = by_name.get(name_stem(n))
        if T is not None:
            stamps.append(i / 30.0)
            wfc.append(T.inverse())
    tum = write_tum(work / f"redkitchen-{frames}.tum", stamps, wfc)
    maps = work / "video-maps"
    bundle = maps / "video"
    t0 = time.perf_counter()
    if not (bundle / "manifest.json").is_file():
        build_from_video(
            build.preset("default"),
            "video",
            maps,
            video=video,
            poses=tum,
            camera=REDKITCHEN_CAMERA,
            workdir=work,
        )
    secs = time.perf_counter() - t0
    folder, _ = build_map(work / "density", data, frames, 10, "geometric")
    v = {"build_s": round(secs), **evaluate(bundle, data, frames, n_reloc)}
    f = evaluate(folder, data, frames, n_reloc)
    return {
        "video": v,
        "every_10th": f,
        "localizes_as_well": v["replay_localized_pct"] >= f["replay_localized_pct"] - 0.5
        and v["reloc_ok"] >= f["reloc_ok"] - 1,
    }


PARTS = ("extend", "memory", "density", "video")


def run_builder(
    work: Path,
    data: Path,
    parts: list[str],
    frames: int = 1000,
    stride: int = 10,
    n_reloc: int = 40,
    views: list[int] | None = None,
    strides: list[int] | None = None,
) -> dict[str, Any]:
    """The parts asked for, as one dict (the ``builder`` suite of ``sfmloc bench``)."""
    work.mkdir(parents=True, exist_ok=True)
    out: dict[str, Any] = {}
    if "memory" in parts:
        out["memory"] = memory_part(work, views or [60, 240])
    if "extend" in parts:
        out["extend"] = extend_part(work, data, frames, stride, n_reloc)
        print(json.dumps(out["extend"]), flush=True)
    if "density" in parts:
        out["density"] = density_part(work, data, frames, strides or [10, 4, 2, 1], n_reloc)
    if "video" in parts:
        out["video"] = video_part(work, data, frames, n_reloc)
        print(json.dumps(out["video"]), flush=True)
    return out


def report_lines(res: dict[str, Any]) -> list[str]:
    """Plain-text lines of the suite's results (for report.md)."""
    L: list[str] = []
    m = res.get("memory")
    if m:
        L += [
            "build peak memory (synthetic rooms, default preset; target 1 GiB + "
            f"{m['target_bytes_per_descriptor']} B per descriptor):",
            "",
            "```",
            m["table"],
            "```",
            "",
        ]
    e = res.get("extend")
    if e:
        f, x = e["full"], e["extended"]
        L += [
            f"--extend (redkitchen, every {e['stride']}th of {e['frames']} frames; second half "
            "added to the first half's map, against all at once):",
            "",
            "| map | images | points | localized % | median cm | wrong | reloc | build s (CPU) |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for label, r, secs in (
            ("all at once", f, e["full_cpu_s"]),
            ("first half + extend", x, e["extend_cpu_s"]),
            ("first half", e["first"], e["first_cpu_s"]),
        ):
            L.append(
                f"| {label} | {r['images']} | {r['points']} | {r['replay_localized_pct']} | "
                f"{r['median_position_error_cm']} | {r['replay_wrong']} | "
                f"{r['reloc_ok']}/{r['reloc_of']} | {secs:.0f} |"
            )
        L += [
            "",
            f"extend / full build time: CPU x{e['extend_over_full_cpu']}, wall "
            f"x{e['extend_over_full_wall']}; targets: localized within 0.5 points "
            f"({e['meets_localized']}), median within 10% ({e['meets_median']}), time <= 0.5 "
            f"({e['meets_time']})",
            "",
        ]
    d = res.get("density")
    if d:
        L += [
            "maps per input density (redkitchen, known poses):",
            "",
            "| every | images | points | localized % | wrong | global frames | reloc | "
            "ms/frame mean | p99 | CPU ms mean |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in d["rows"]:
            L.append(
                f"| {r['stride']} | {r['images']} | {r['points']} | {r['replay_localized_pct']} | "
                f"{r['replay_wrong']} | {r['replay_global_frames']} | "
                f"{r['reloc_ok']}/{r['reloc_of']} | {r['mean_ms_per_frame']} | "
                f"{r.get('p99_ms_per_frame', '-')} | {r.get('mean_cpu_ms_per_frame', '-')} |"
            )
        L += ["", f"never decreases as images are added: {d['never_decreases']}", ""]
        il = d.get("interleaved")
        if il:
            L += [
                f"densest vs sparsest map, replayed interleaved frame by frame: CPU ms per frame "
                f"mean {il['densest']['cpu_ms_mean']} vs {il['sparsest']['cpu_ms_mean']} "
                f"(x{il['cpu_mean_ratio']}; target <= 1.1), p99 {il['densest']['cpu_ms_p99']} "
                f"vs {il['sparsest']['cpu_ms_p99']} (x{il['cpu_p99_ratio']})",
                "",
            ]
    v = res.get("video")
    if v:
        L += [
            f"video target: video map {v['video']['replay_localized_pct']}% localized, reloc "
            f"{v['video']['reloc_ok']}/{v['video']['reloc_of']}, {v['video']['images']} "
            f"keyframes; every-10th folder map {v['every_10th']['replay_localized_pct']}%, "
            f"{v['every_10th']['reloc_ok']}/{v['every_10th']['reloc_of']}: "
            f"{'met' if v['localizes_as_well'] else 'missed'}",
            "",
        ]
    return L


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--work", default="/tmp/sfmloc-builder-bench")
    p.add_argument("--data", default=str(DEFAULT_DATA))
    p.add_argument("--parts", nargs="+", default=["extend"], choices=PARTS)
    p.add_argument("--views", type=int, nargs="+", default=[60, 240], help="memory: room sizes")
    p.add_argument("--strides", type=int, nargs="+", default=[10, 4, 2, 1], help="density")
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--stride", type=int, default=10)
    p.add_argument("--reloc", type=int, default=40)
    p.add_argument("--out", help="write the results as JSON here")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    work, data = Path(a.work), Path(a.data)
    work.mkdir(parents=True, exist_ok=True)
    results = run_builder(work, data, a.parts, a.frames, a.stride, a.reloc, a.views, a.strides)
    print("\n".join(report_lines(results)))
    if a.out:
        Path(a.out).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
