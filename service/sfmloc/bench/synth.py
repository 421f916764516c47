"""Render-speed benchmark: ``python -m sfmloc.bench.synth [--frames N] [--trajectory KIND] ...``.

Times ``render`` (colour, depth, noise; no disk I/O) along a trajectory and prints frames/s
(wall clock) and the CPU time per frame summed over OpenCV's threads, which other load on
the machine does not inflate. The scene is built and its mipmaps warmed up before timing.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def bench(
    kind: str = "walk",
    frames: int = 300,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    **render_kw,
) -> dict:
    from ..cameras import Camera
    from ..synth.config import RenderConf
    from ..synth.renderer import prepare, render
    from ..synth.scene import Scene
    from ..synth.trajectory import make_trajectory

    scene = Scene.room(seed)
    f = 525.0 * width / 640.0
    camera = Camera.pinhole(width, height, f, f, width / 2, height / 2)
    poses = make_trajectory(kind, frames, seed, scene)
    conf = RenderConf(**render_kw)
    prepare(scene)  # mipmaps
    render(scene, camera, poses[0], conf=conf)  # warm-up
    times = []
    cpu0 = time.process_time()
    for i, pose in enumerate(poses):
        t0 = time.perf_counter()
        render(scene, camera, pose, conf=conf, noise_seed=i)
        times.append(time.perf_counter() - t0)
    cpu = time.process_time() - cpu0
    t = np.array(times)
    return {
        "trajectory": kind,
        "frames": frames,
        "size": f"{width}x{height}",
        "fps": float(len(t) / t.sum()),
        "ms_mean": float(t.mean() * 1e3),
        "ms_p95": float(np.percentile(t, 95) * 1e3),
        "ms_max": float(t.max() * 1e3),
        "cpu_ms": float(cpu / len(t) * 1e3),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m sfmloc.bench.synth", description=__doc__.splitlines()[0]
    )
    p.add_argument("--trajectory", default="all", choices=["all", "walk", "flight", "orbit"])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--supersample", type=int, default=1)
    args = p.parse_args(argv)
    kinds = ["walk", "flight", "orbit"] if args.trajectory == "all" else [args.trajectory]
    for kind in kinds:
        r = bench(
            kind, args.frames, args.seed, args.width, args.height, supersample=args.supersample
        )
        print(
            f"{r['trajectory']:6s} {r['size']} {r['frames']} frames: {r['fps']:.1f} frames/s "
            f"(mean {r['ms_mean']:.1f} ms, p95 {r['ms_p95']:.1f} ms, max {r['ms_max']:.1f} ms; "
            f"CPU {r['cpu_ms']:.1f} ms/frame over all threads)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
