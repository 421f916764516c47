"""sfmloc relocalize: where was this photo taken (one gRPC call)."""

from __future__ import annotations

import argparse
import textwrap
from typing import TYPE_CHECKING

from ._clientopts import add_grpc_option, camera_spec, grpc_client

if TYPE_CHECKING:
    import numpy as np


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "relocalize",
        help="localize a single image on a server (gRPC)",
        description=textwrap.dedent(
            """\
            Send IMAGE to the server's Relocalize call and print its pose: world_from_cam
            (the camera's position and orientation in the map) and cam_from_world, as
            translation + quaternion (x, y, z, w), and how it was found: matching "global"
            (global matching over the whole map) or "guided" (around --prior). JPEG and PNG
            files are sent as they are; other formats are re-encoded. Exits 0 when
            localized, 1 when not (LOST), 2 on errors (unknown map, bad image or camera,
            server unreachable)."""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("image", metavar="IMAGE", help="image file")
    p.add_argument("--map", required=True, help="map name on the server")
    p.add_argument(
        "--camera", required=True, metavar="CAMERA", help="camera.json or 'MODEL w h params...'"
    )
    p.add_argument(
        "--prior",
        metavar="'qx qy qz qw tx ty tz'",
        help="approximate cam_from_world to search near first (then the whole map: a wrong "
        "prior costs time, not a wrong pose)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    add_grpc_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from sfmloc_client import RemoteError, Transform

    from ..errors import InputError

    cam = camera_spec(args.camera)
    path = Path(args.image)
    if not path.is_file():
        raise InputError(f"image {path} does not exist")
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg", ".png"):
        image: bytes | np.ndarray = path.read_bytes()
        encoding = "png" if suffix == ".png" else "jpeg"
    else:
        import cv2

        decoded = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if decoded is None:
            raise InputError(f"cannot read image {path}")
        image, encoding = decoded, "png"
    prior = None
    if args.prior:
        try:
            v = [float(x) for x in args.prior.split()]
        except ValueError:  # a word where a number goes: exit 2 with the rule, no traceback
            v = []
        if len(v) != 7:
            raise InputError(f"--prior takes 7 numbers: qx qy qz qw tx ty tz, got {args.prior!r}")
        prior = Transform((v[0], v[1], v[2], v[3]), (v[4], v[5], v[6]))
    with grpc_client(args) as c:
        try:
            pose = c.relocalize(image, args.map, cam, encoding=encoding, prior=prior)
        except RemoteError as exc:
            raise InputError(f"relocalize failed: {exc}") from None
    if args.json:
        print(
            json.dumps(
                {
                    "status": pose.status,
                    "inliers": pose.inliers,
                    "matching": pose.matching,
                    "latency_ms": round(pose.latency_ms, 2),
                    "world_from_cam": None
                    if pose.world_from_cam is None
                    else {"quat_xyzw": pose.world_from_cam.quat_xyzw, "t": pose.world_from_cam.t},
                    "cam_from_world": None
                    if pose.cam_from_world is None
                    else {"quat_xyzw": pose.cam_from_world.quat_xyzw, "t": pose.cam_from_world.t},
                    "message": pose.message,
                }
            )
        )
    else:
        print(
            f"{path.name}: {pose.status}  inliers {pose.inliers}  matching {pose.matching}  "
            f"{pose.latency_ms:.1f} ms"
        )
        if pose.world_from_cam is not None and pose.cam_from_world is not None:
            w, c_ = pose.world_from_cam, pose.cam_from_world
            print(
                "  world_from_cam  t "
                + " ".join(f"{v:.4f}" for v in w.t)
                + "  quat_xyzw "
                + " ".join(f"{v:.6f}" for v in w.quat_xyzw)
            )
            print(
                "  cam_from_world  t "
                + " ".join(f"{v:.4f}" for v in c_.t)
                + "  quat_xyzw "
                + " ".join(f"{v:.6f}" for v in c_.quat_xyzw)
            )
        elif pose.message:
            print(f"  {pose.message}")
    return 0 if pose.localized else 1
