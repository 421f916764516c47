"""sfmloc synth: render a synthetic room with exact ground truth (map images, model, video)."""

from __future__ import annotations

import argparse

EPILOG = """\
output layout (OUT):
  images/map-0000.png ...   mapping views, 8-bit BGR PNG
  sparse/                   COLMAP text model of the mapping views (cameras.txt, images.txt,
                            points3D.txt): exact poses, 3D points at texture corners, exact
                            2D projections, tracks; image names relative to images/
  video/frame-000000.png    the trajectory, one PNG per frame at 30 Hz
  groundtruth.tum           video poses, TUM 'timestamp tx ty tz qx qy qz qw',
                            world_from_cam, timestamp = frame index / 30
  video_poses.txt           video poses, COLMAP list 'name qw qx qy qz tx ty tz',
                            cam_from_world, names like frame-000000.png
  camera.json               the PINHOLE camera (f = 525 at 640x480, principal point at the
                            image centre)
  scene.json                parameters used and counts; written last. OUT appears only when
                            complete (written as .OUT.partial-PID and renamed).

conventions:
  world frame   metres, z up, floor at z = 0, the room spans [0, 8] x [0, 5] x [0, 3]
                with a floor corner at the origin
  cameras       COLMAP: x right, y down, z forward; cam_from_world maps world points into
                the camera (x_cam = R x_world + t), world_from_cam is the camera pose
  pixels        COLMAP: the centre of the upper-left pixel is (0.5, 0.5)
  quaternions   COLMAP files qw qx qy qz, TUM qx qy qz qw

Same options and seed give byte-identical images and model. Render speed only (no disk
I/O): python -m sfmloc.bench.synth.
"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "synth",
        help="render a synthetic scene with exact ground truth",
        description=(
            "Render a textured indoor room with furniture by exact plane geometry: mapping views\n"
            "with their exact COLMAP model, and a 30 Hz video with ground-truth poses, for "
            "testing\n"
            "localization with known answers. Progress goes to stderr, a summary to stdout."
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "out", metavar="OUT", help="output folder (must not exist or be empty, unless --overwrite)"
    )
    p.add_argument(
        "--scene",
        default="room",
        choices=["room"],
        help="scene: 'room' is an 8 x 5 x 3 m room with textured walls and furniture "
        "(default room)",
    )
    p.add_argument(
        "--trajectory",
        choices=["walk", "flight", "orbit"],
        default=None,
        help="video motion: walk (a person at ~1.2 m/s, eyes at ~1.5 m), flight (quadrotor with "
        "fast yaw bursts up to ~120 deg/s), orbit (circle around the room centre looking "
        "inward) (default walk)",
    )
    p.add_argument(
        "--orbit-look",
        choices=["inward", "outward"],
        default=None,
        help="for --trajectory orbit: look at the room centre or at the walls (default inward)",
    )
    p.add_argument(
        "--frames", type=int, default=None, metavar="N", help="video frames at 30 Hz (default 300)"
    )
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        metavar="S",
        help="seed of the room layout, textures, paths and noise (default 0)",
    )
    p.add_argument("--width", type=int, default=None, help="image width in pixels (default 640)")
    p.add_argument("--height", type=int, default=None, help="image height in pixels (default 480)")
    p.add_argument(
        "--focal",
        type=float,
        default=None,
        metavar="F",
        help="focal length in pixels (default 525 * width / 640)",
    )
    p.add_argument(
        "--mapping-views",
        type=int,
        default=None,
        metavar="N",
        help="number of mapping views in images/ and sparse/ (default 120)",
    )
    p.add_argument(
        "--noise",
        type=float,
        default=None,
        metavar="SIGMA",
        help="Gaussian image noise, gray levels per channel; 0 for none (default 2)",
    )
    p.add_argument(
        "--preset",
        default="default",
        help="named configuration merged under the flags: default, small, clean, flight, orbit",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace OUT if it exists (only once complete)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..synth.config import preset
    from ..synth.main import run as synth_run

    changes: dict = {}
    for key, value in (
        ("seed", args.seed),
        ("width", args.width),
        ("height", args.height),
        ("focal", args.focal),
        ("mapping_views", args.mapping_views),
    ):
        if value is not None:
            changes[key] = value
    traj = {
        k: v
        for k, v in (
            ("kind", args.trajectory),
            ("n_frames", args.frames),
            ("orbit_look", args.orbit_look),
        )
        if v is not None
    }
    if traj:
        changes["trajectory"] = traj
    if args.noise is not None:
        changes["render"] = {"noise_sigma": args.noise}
    changes["scene"] = {"name": args.scene}
    from pydantic import ValidationError

    from ..errors import ConfigError

    try:
        conf = preset(args.preset, **changes)
    except ValidationError as exc:
        raise ConfigError(f"invalid synth options:\n{exc}") from None
    result = synth_run(conf, args.out, overwrite=args.overwrite)
    print(result.summary())
    return 0
