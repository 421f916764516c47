"""sfmloc build: SfM model or images -> map bundle."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

DESCRIPTION = """\
Build a map bundle (the paper's offline stage): multi-scale Harris + oriented DAISY descriptors
for every 3D point, PCA to 32 dimensions, overlapping camera clusters, an ANN index and lookup
tables, written atomically to OUT/NAME.

Inputs (one of):
  --colmap MODEL --images DIR     a COLMAP sparse model (text or binary) and its images
  --images DIR --poses FILE --camera CAMERA
                                  images with known poses: points are triangulated with pycolmap
                                  (poses: COLMAP list 'name qw qx qy qz tx ty tz', cam_from_world,
                                  matched by file name or stem; or TUM, world_from_cam); the map
                                  is in the poses' world frame and units
  --images DIR [--camera CAMERA]  images only: full SfM with pycolmap first (arbitrary frame/scale)
  --video FILE [--poses TUM --camera CAMERA]
                                  a video (any format OpenCV decodes): keyframes chosen by motion
                                  and sharpness, then built like posed images (with a TUM pose log
                                  on the video's clock, world_from_cam, interpolated to each
                                  keyframe's time) or like images only (no --poses)

Video keyframes: a frame's time is the container's presentation time (CAP_PROP_POS_MSEC), or
index / fps when the container has none; the first frame is at 0 s. A frame becomes a keyframe
after enough motion since the last keyframe: with poses, --kf-rotation degrees or --kf-translation
times the scene depth (estimated from tracks triangulated with the poses); without poses,
--kf-flow of the image diagonal of median corner motion. The sharpest of that frame and its next
--kf-window - 1 frames is taken (blurry frames are dropped); with poses, a keyframe is also
due after --kf-interval seconds without one (a camera dwelling on a spot). The choice is
printed and stored in the bundle's manifest; keyframes go to a temporary folder removed
afterwards.

Extending a map: --extend BUNDLE with --images DIR and the new images' poses in the map's frame
(--poses FILE --camera CAMERA, or --colmap MODEL) adds them to the bundle: only the new images
are triangulated and described (their descriptors projected with the map's PCA, added to its
index), so the work is that of the new images; the map's points seen again in them get their
descriptors and are re-triangulated with them. The builder settings are the bundle's own.
The result OUT/NAME has a new build id; BUNDLE is not changed (NAME may be its own name, with
--replace: it is replaced only once the new bundle is complete).

CAMERA is a camera.json file or 'MODEL width height params...' in COLMAP order, e.g.
'PINHOLE 640 480 525.505 525.505 320 240'. An existing bundle of the same name is refused unless
--replace is given; it then stays intact until the new one is complete. A failed or cancelled
build leaves nothing behind.
"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "build",
        help="build a map bundle from a COLMAP model, posed images or images",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("name", help="map name (letters, digits, '_', '-', '.'); the bundle is OUT/NAME")
    p.add_argument("--out", default="maps", help="folder for bundles (default: maps)")
    p.add_argument(
        "--replace",
        action="store_true",
        help="replace an existing bundle OUT/NAME (without it, an existing name is refused "
        "before any work; the old bundle stays intact until the new one is complete)",
    )
    p.add_argument(
        "--colmap",
        metavar="MODEL_DIR",
        help="COLMAP sparse model folder (cameras/images/points3D .txt or .bin)",
    )
    p.add_argument("--images", metavar="DIR", help="image folder")
    p.add_argument(
        "--extend",
        metavar="BUNDLE",
        help="add the images to this map bundle (poses in its frame: --poses or --colmap)",
    )
    p.add_argument(
        "--poses", metavar="FILE", help="known poses (COLMAP list or TUM; with --video: TUM)"
    )
    p.add_argument("--video", metavar="FILE", help="a video instead of --images (keyframes chosen)")
    p.add_argument(
        "--kf-rotation",
        type=float,
        metavar="DEG",
        help="video with poses: keyframe after this rotation (default 5)",
    )
    p.add_argument(
        "--kf-translation",
        type=float,
        metavar="F",
        help="video with poses: keyframe after this translation, of the scene depth (default 0.05)",
    )
    p.add_argument(
        "--kf-flow",
        type=float,
        metavar="F",
        help="video without poses: keyframe after this image motion, of the diagonal "
        "(default 0.05)",
    )
    p.add_argument(
        "--kf-interval",
        type=float,
        metavar="S",
        help="video with poses: a keyframe also after S seconds without one (default 0.2; 0: off)",
    )
    p.add_argument(
        "--kf-window",
        type=int,
        metavar="N",
        help="video: the sharpest of N frames becomes the keyframe (default 5)",
    )
    p.add_argument("--camera", help="camera.json or 'MODEL w h params...'")
    p.add_argument(
        "--stride",
        type=int,
        default=1,
        help="posed/images-only inputs: use every N-th image (default 1)",
    )
    p.add_argument(
        "--preset",
        default="default",
        help="builder preset: default (2 octaves down, 2 sub-octaves up, points refined, "
        "Harris-corner "
        "points added to the SfM points), paper (the paper's map exactly), fast (SfM points only), "
        "dense "
        "(default: default)",
    )
    p.add_argument(
        "--sfm-preset",
        default="default",
        help="SfM preset: default, fast, accurate (default: default)",
    )
    p.add_argument(
        "--min-track-length",
        type=int,
        metavar="N",
        help="known poses: drop points seen in fewer than N images (default 3, or 2 where the "
        "median image "
        "would see fewer than 400 points with 3: the poses are given, so two views fix a point, "
        "and thin "
        "maps need them). Images-only SfM keeps its own rule: at least 3, since its poses are "
        "estimated "
        "from the same matches. Not used with --colmap",
    )
    p.add_argument(
        "--matching", choices=["sequential", "exhaustive"], help="images only: pair selection"
    )
    p.add_argument(
        "--pairs",
        choices=["geometric", "nearest"],
        help="known poses: pair selection. geometric (default): each image's 2 nearest cameras "
        "plus "
        "one per target triangulation angle among cameras that see the same part of the scene, a "
        "budget that does not grow with the frame rate; nearest: the 5 nearest cameras and the "
        "next "
        "2 images (in dense video these are too close to triangulate)",
    )
    p.add_argument(
        "--align-positions",
        metavar="FILE",
        help="align the map to known camera centres ('name x y z' lines or a pose file) before "
        "it is published (as 'sfmloc map align --positions'; for images-only maps)",
    )
    p.add_argument(
        "--align-points",
        metavar="FILE",
        help="align the map with 'x y z X Y Z' point pairs (as 'sfmloc map align --points')",
    )
    p.add_argument(
        "--align-up",
        nargs="+",
        metavar="X",
        help="the map's up direction (3 numbers or 'cameras') taken onto 0 0 1 by the alignment",
    )
    p.add_argument("--config", help="JSON/TOML file of builder settings merged over the preset")
    p.add_argument("--threads", type=int, help="threads for pycolmap (default: all cores)")
    p.add_argument("--workdir", help="parent folder for temporary SfM files (default: system temp)")
    p.add_argument("--keep-workdir", action="store_true", help="keep the temporary SfM files")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..threads import pin_threads_env

    pin_threads_env()
    import time

    from ..builder.build import main, preset
    from ..builder.sfm import sfm_conf
    from ..config import merge_presets, read_config_file
    from ..errors import InputError
    from ..map.bundle import MapBundle
    from ..map.report import report_lines
    from .progress import ProgressPrinter

    if args.colmap and args.poses:
        raise InputError("give either --colmap (a COLMAP model) or --poses (known poses), not both")
    if args.video and (args.images or args.colmap):
        raise InputError("give either --video or --images/--colmap, not both")
    if not args.images and not args.video:
        raise InputError("--images (an image folder) or --video (a video file) is required")
    if args.extend and (args.video or (not args.poses and not args.colmap)):
        raise InputError(
            "--extend needs --images with the new images' poses in the map's frame (--poses "
            "FILE --camera CAMERA, or --colmap MODEL)"
        )
    if args.extend and (args.preset != "default" or args.config):
        raise InputError("--extend uses the bundle's own builder settings: no --preset/--config")
    if args.poses and not args.camera:
        raise InputError("--poses needs --camera (camera.json or 'PINHOLE w h fx fy cx cy')")
    existing = Path(args.out) / args.name
    if not args.replace and (existing.exists() or existing.is_symlink()):
        raise InputError(
            f"{existing} exists: pass --replace to rebuild it (or choose another name)"
        )
    conf = preset(args.preset)
    if args.config:
        conf = merge_presets(conf, **read_config_file(args.config))
    overrides = {}
    if args.threads:
        overrides["num_threads"] = args.threads
    if args.matching:
        overrides["matching"] = args.matching
    if args.keep_workdir:
        overrides["keep_workdir"] = True
    if args.pairs:
        overrides["pair_selection"] = args.pairs
    if args.min_track_length is not None:
        if args.colmap:
            raise InputError(
                "--min-track-length applies to --poses or images-only builds, not to --colmap "
                "models"
            )
        low = 2 if args.poses else 3
        if args.min_track_length < low:
            raise InputError(
                f"--min-track-length must be >= {low} "
                + (
                    "with known poses"
                    if args.poses
                    else "for images-only SfM (its poses come from the same matches)"
                )
                + f", got {args.min_track_length}"
            )
        overrides["min_track_length"] = args.min_track_length
        overrides["two_view_below"] = 0  # the user's choice, whatever the density
    sconf = sfm_conf(args.sfm_preset, **overrides)
    if args.align_positions and args.align_points:
        raise InputError("give --align-positions or --align-points, not both")
    aligning = bool(args.align_positions or args.align_points or args.align_up)
    final_out = args.out
    if aligning:
        # Built into a hidden folder beside the final one, so that only the aligned map is ever
        # published under NAME (a server following the folder never sees the unaligned one).
        import tempfile

        Path(args.out).mkdir(parents=True, exist_ok=True)
        args.out = tempfile.mkdtemp(prefix=f".{args.name}.unaligned-", dir=args.out)
    bar = ProgressPrinter()
    t0 = time.perf_counter()
    try:
        if args.video:
            path = _build_video(args, conf, sconf, bar)
        else:
            # The same inputs either way: a new bundle, or the images added to --extend's.
            inputs: dict[str, Any] = {
                "images": args.images,
                "poses": args.poses,
                "camera": args.camera,
                "colmap": args.colmap,
                "sfm_conf": sconf,
                "stride": args.stride,
                "workdir": args.workdir,
                "progress": bar,
            }
            if args.extend:
                from ..builder.extend import extend

                path = extend(args.extend, args.name, args.out, **inputs)
            else:
                path = main(conf, args.name, args.out, **inputs)
        if aligning:
            path = _align_built(args, path, final_out)
    finally:
        bar.close()
        if aligning:
            import shutil

            shutil.rmtree(args.out, ignore_errors=True)
    dt = time.perf_counter() - t0
    bundle = MapBundle(path, verify=False)
    kf = bundle.manifest.source.get("keyframes")
    if kf:
        print(
            f"video: {kf['keyframes']} keyframes of {kf['frames']} frames ({kf['clock']} clock); "
            "dropped "
            f"{kf['dropped_motion']} (too little motion), {kf['dropped_blur']} (blurrier than a "
            "neighbour), "
            f"{kf['dropped_no_pose']} (no pose at their time)"
        )
    s = bundle.summary()
    print(
        f"built {path} in {dt:.1f} s: {s['points']} points, {s['descriptors']} descriptors "
        f"({s['descriptors_per_point']} per point), {s['images']} images, {s['clusters']} "
        "clusters, "
        f"{s['disk_mb']} MB on disk, {s['memory_mb']} MB in memory"
    )
    for line in report_lines(bundle.report()):
        print(line, file=sys.stderr if line.startswith("WARNING") else sys.stdout)
    return 0


def _build_video(args: argparse.Namespace, conf, sconf, bar):
    from pydantic import ValidationError

    from ..builder.video import VideoConf, build_from_video
    from ..errors import ConfigError

    flags = {
        "min_rotation_deg": ("--kf-rotation", args.kf_rotation),
        "min_translation": ("--kf-translation", args.kf_translation),
        "min_flow": ("--kf-flow", args.kf_flow),
        "sharpness_window": ("--kf-window", args.kf_window),
        "max_interval_s": ("--kf-interval", args.kf_interval),
    }
    changes = {k: v for k, (_, v) in flags.items() if v is not None}
    try:
        video_conf = VideoConf(**changes)
    except ValidationError as exc:
        bad = ", ".join(
            f"{flags[str(e['loc'][0])][0]} {e['input']}: {e['msg']}" for e in exc.errors()
        )
        raise ConfigError(f"invalid video keyframe option: {bad}") from None
    return build_from_video(
        conf,
        args.name,
        args.out,
        video=args.video,
        poses=args.poses,
        camera=args.camera,
        video_conf=video_conf,
        sfm_conf=sconf,
        workdir=args.workdir,
        progress=bar,
    )


def _align_built(args: argparse.Namespace, path, out_dir: str):
    """The freshly built bundle aligned as ``sfmloc map align`` would, written to OUT/NAME."""

    from ..map.align import write_aligned
    from .map import align_bundle_from_args, print_align_report

    opts = argparse.Namespace(
        positions=None,
        poses=args.align_positions,  # read_known_positions takes 'name x y z' or pose files
        points=args.align_points,
        up=args.align_up,
        up_target=[0.0, 0.0, 1.0],
        no_scale=False,
        check=None,
    )
    bundle, sim, report = align_bundle_from_args(opts, path)
    print_align_report(report)
    record = {k: report[k] for k in ("up_map", "up_target") if report[k] is not None}
    if "given" in report:
        record["given"] = {k: report["given"][k] for k in ("what", "count", "rms", "max")}
    return write_aligned(bundle, sim, out_dir, args.name, record=record)
