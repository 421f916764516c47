"""Build peak memory against the map's size (issue 17: at most 1 GiB + 300 B per descriptor).

Synthetic rooms (``sfmloc.synth``, exact COLMAP models) with a growing number of mapping
views are built with the builder's ``--colmap`` input and a preset (default: ``default``,
Harris points on), each build in a child process. The child reports its peak resident set
(``VmHWM``) over the whole build and per stage: at every stage change it resets the peak
(``/proc/self/clear_refs`` 5), so each stage's peak is its own. ``over_GiB_per_desc`` is
(peak - 1 GiB) / descriptors, the issue's measure; ``growth`` is the peak's slope between
consecutive sizes, which does not depend on the interpreter's fixed memory.

    python -m sfmloc.bench.build_memory --work /tmp/bm --views 60 240 960 --out bm.json

Rooms are rendered under ``--work`` once and reused (about 0.5 MB of PNG per view); bundles are
removed after each measurement unless ``--keep``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

GIB = 1 << 30
TARGET_BYTES_PER_DESCRIPTOR = 300


def _status_kb(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1])
    raise RuntimeError(f"{key} not in /proc/self/status")


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def child(room: Path, out: Path, preset: str, over: dict[str, Any]) -> dict[str, Any]:
    """Build ``room`` into ``out`` in this process; the peaks (bytes) as a dict."""
    from ..builder import build
    from ..config import merge_presets

    conf = merge_presets(build.preset(preset), **over)
    base = _status_kb("VmRSS") * 1024
    stages: dict[str, int] = {}
    current = [""]
    overall = [0]
    resettable = _reset_peak()

    def progress(stage: str, fraction: float, message: str) -> None:
        if stage != current[0]:
            hwm = _status_kb("VmHWM") * 1024
            overall[0] = max(overall[0], hwm)
            if current[0]:
                stages[current[0]] = max(stages.get(current[0], 0), hwm)
            current[0] = stage
            _reset_peak()

    t0 = time.perf_counter()
    path = build.main(
        conf, "m", out, colmap=room / "sparse", images=room / "images", progress=progress
    )
    seconds = time.perf_counter() - t0
    hwm = _status_kb("VmHWM") * 1024
    overall[0] = max(overall[0], hwm)
    stages[current[0]] = max(stages.get(current[0], 0), hwm)
    manifest = json.loads((path / "manifest.json").read_text())
    return {
        "base": base,
        "peak": overall[0],
        "stage_peaks": stages,
        "per_stage": resettable,
        "descriptors": manifest["counts"]["descriptors"],
        "points": manifest["counts"]["points"],
        "images": manifest["counts"]["images"],
        "seconds": seconds,
    }


def make_room(work: Path, views: int, width: int, height: int) -> Path:
    from ..synth import preset
    from ..synth.main import run

    room = work / f"room-{views}-{width}x{height}"
    if not (room / "scene.json").is_file():
        conf = preset(
            "default",
            width=width,
            height=height,
            mapping_views=views,
            trajectory={"n_frames": 2},
        )
        run(conf, room)
    return room


def measure(room: Path, out: Path, preset: str, over: dict[str, Any]) -> dict[str, Any]:
    """One build of ``room`` in a child process."""
    cmd = [
        sys.executable,
        "-m",
        "sfmloc.bench.build_memory",
        "--child",
        str(room),
        str(out),
        "--preset",
        preset,
        "--set",
        json.dumps(over),
    ]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"build of {room} failed: {res.stderr[-2000:]}")
    row = json.loads(res.stdout.strip().splitlines()[-1])
    n = row["descriptors"]
    row["over_GiB_per_desc"] = (row["peak"] - GIB) / n
    row["peak_per_desc"] = row["peak"] / n
    row["meets_target"] = row["peak"] <= GIB + TARGET_BYTES_PER_DESCRIPTOR * n
    return row


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["views  descriptors  peak MB  B/desc  (peak-1GiB)/desc  growth B/desc  top stages"]
    prev = None
    for r in rows:
        growth = ""
        if prev is not None and r["descriptors"] > prev["descriptors"]:
            growth = f"{(r['peak'] - prev['peak']) / (r['descriptors'] - prev['descriptors']):.0f}"
        top = sorted(r["stage_peaks"].items(), key=lambda kv: -kv[1])[:3]
        lines.append(
            f"{r['images']:5d}  {r['descriptors']:11d}  {r['peak'] / 1e6:7.0f}  "
            f"{r['peak_per_desc']:6.0f}  {r['over_GiB_per_desc']:16.0f}  {growth:>13}  "
            + ", ".join(f"{k} {v / 1e6:.0f}" for k, v in top)
        )
        prev = r
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/sfmloc-build-memory"))
    ap.add_argument("--views", type=int, nargs="+", default=[60, 240])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--preset", default="default", help="builder preset (default: default)")
    ap.add_argument("--set", default="{}", help="JSON merged over the preset")
    ap.add_argument("--out", type=Path, help="write the rows as JSON here")
    ap.add_argument("--keep", action="store_true", help="keep the bundles")
    ap.add_argument("--child", nargs=2, metavar=("ROOM", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    over = json.loads(args.set)
    if args.child:
        row = child(Path(args.child[0]), Path(args.child[1]), args.preset, over)
        print(json.dumps(row))
        return 0
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for views in args.views:
        room = make_room(args.work, views, args.width, args.height)
        out = args.work / f"maps-{views}"
        row = measure(room, out, args.preset, over)
        if not args.keep:
            shutil.rmtree(out, ignore_errors=True)
        rows.append(row)
        print(table(rows).splitlines()[-1], flush=True)
    print(table(rows))
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
