"""Time the SfM front-end on real frames: ``python -m sfmloc.bench.sfm [options]``.

Defaults: the 7-Scenes redkitchen seq-01 frames in ``../shared/data`` (beside the repo),
every 10th frame (0, 10, ..., 990), both paths (known poses from ``pgt_sfm_seq01.txt``, then
images only with the known camera). Prints per-stage seconds, point count, mean track length
and mean reprojection error; for images only also the camera-centre error against the known
poses after a similarity alignment (the SfM frame is arbitrary).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from ..builder import sfm
from ..io.poses import name_stem, read_poses
from ..transforms import align_umeyama

DEFAULT_DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "redkitchen-seq01"
DEFAULT_CAMERA = "PINHOLE 640 480 525.505 525.505 320 240"


def _sim3_residuals(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Distances after the least-squares similarity (Umeyama) est -> gt."""
    s, R, t = align_umeyama(est, gt)
    return np.linalg.norm(s * est @ R.T + t - gt, axis=1)


def run_one(
    mode: str, data: Path, names: list[str], conf: sfm.SfmConf, camera: str | None, poses: Path
) -> None:
    stages: dict[str, list[float]] = {}

    def progress(stage: str, fraction: float, message: str) -> None:
        now = time.perf_counter()
        stages.setdefault(stage, [now, now])[1] = now

    load = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    if mode == "poses":
        rec = sfm.triangulate_known_poses(
            data, poses, camera or DEFAULT_CAMERA, conf, progress=progress, image_names=names
        )
    else:
        rec = sfm.reconstruct_images_only(data, camera, conf, progress=progress, image_names=names)
    total, cpu = time.perf_counter() - t0, time.process_time() - c0
    st = sfm.reconstruction_stats(rec)
    per_stage = ", ".join(f"{k} {v[1] - v[0]:.1f}" for k, v in stages.items())
    line = (
        f"{mode:7s} {len(names)} images: total {total:.1f} s, cpu {cpu:.1f} s ({per_stage}; load "
        f"avg before {load:.1f}) | "
        f"{st['images']} images, {st['points3D']} points, mean track "
        f"{st['mean_track_length']:.2f}, "
        f"mean reproj {st['mean_reproj_error_px']:.3f} px"
    )
    if mode == "images" and poses.is_file():
        gt = read_poses(poses).by_stem()
        ims = [im for im in rec.images.values() if name_stem(im.name) in gt]
        if len(ims) >= 3:
            e = _sim3_residuals(
                np.array([im.cam_from_world.center for im in ims]),
                np.array([gt[name_stem(im.name)].center for im in ims]),
            )
            line += (
                f" | centres vs known poses after sim3: median {100 * np.median(e):.1f} cm, "
                f"max {100 * e.max():.1f} cm"
            )
    print(line, flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m sfmloc.bench.sfm", description=__doc__.split("\n")[0]
    )
    p.add_argument(
        "--data", type=Path, default=DEFAULT_DATA, help="image folder (default: redkitchen seq-01)"
    )
    p.add_argument(
        "--poses", type=Path, default=None, help="pose file (default: DATA/pgt_sfm_seq01.txt)"
    )
    p.add_argument(
        "--camera",
        default=DEFAULT_CAMERA,
        help="camera spec or camera.json ('none': guess, images only)",
    )
    p.add_argument("--stride", type=int, default=10, help="every n-th frame")
    p.add_argument("--count", type=int, default=100, help="number of frames")
    p.add_argument("--mode", choices=["poses", "images", "both"], default="both")
    p.add_argument("--preset", default="default", choices=list(sfm.SFM_PRESETS))
    p.add_argument(
        "--backend",
        choices=["opencv", "pycolmap"],
        default=None,
        help="SIFT extractor (default: the preset's)",
    )
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=JSON", help="override an SfmConf field"
    )
    p.add_argument("--threads", type=int, default=-1)
    p.add_argument("-v", "--verbose", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s"
    )
    poses = args.poses or args.data / "pgt_sfm_seq01.txt"
    names = [f"frame-{i:06d}.color.jpg" for i in range(0, args.stride * args.count, args.stride)]
    overrides = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    if args.backend:
        overrides["sift_backend"] = args.backend
    conf = sfm.sfm_conf(args.preset, num_threads=args.threads, **overrides)
    camera = None if args.camera.lower() == "none" else args.camera
    for mode in ["poses", "images"] if args.mode == "both" else [args.mode]:
        run_one(mode, args.data, names, conf, camera, poses)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
