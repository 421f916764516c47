"""How well the motion model predicts: replay a sequence with ground truth and measure, per
frame, where the filter's prediction puts the map points the track table follows, against
where the ground-truth pose puts them (pixels), next to what the run achieved (tracks kept,
localized fraction, pose error). ``--scale`` multiplies the map's points and camera positions
and the ground truth (images unchanged): a scale-free engine behaves the same at any scale.

    python -m sfmloc.eval.motion MAP FRAMES --camera CAMERA --groundtruth GT [--frames N]
        [--scale S] [--stride K]

Uses only the engine's public behaviour (a ``Localizer`` subclass observes the prediction), so
the same script measures older versions of the engine too.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from sfmloc.cameras import Camera
from sfmloc.engine import EngineConf, Localizer, Matching, Status
from sfmloc.eval.groundtruth import load_groundtruth
from sfmloc.io.frames import FrameSource
from sfmloc.map.bundle import MapBundle
from sfmloc.transforms import Rigid3d, pose_errors


class ProbedLocalizer(Localizer):
    """Records the prediction and the 3D points tracked into each frame."""

    def _predict_positions(self, table, pred):  # noqa: ANN001, ANN202 - the engine's signature
        rows = np.nonzero(table.point >= 0)[0]
        self.probe = (pred, self.bundle.points_xyz[table.point[rows]])
        return super()._predict_positions(table, pred)


def scale_bundle(bundle: MapBundle, s: float) -> MapBundle:
    """The same map ``s`` times larger (points and camera positions; descriptors unchanged)."""
    bundle.points_xyz = np.asarray(bundle.points_xyz) * s
    bundle.image_cam_from_world = [
        Rigid3d(T.rotation, T.translation * s) for T in bundle.image_cam_from_world
    ]
    if hasattr(bundle, "_median_depth"):
        bundle.scene_scale = bundle._median_depth()
    return bundle


def _px(camera: Camera, pose: Rigid3d, gt: Rigid3d, X: np.ndarray) -> float | None:
    if len(X) == 0:
        return None
    uv_gt, z_gt = camera.project(gt, X)
    uv, z = camera.project(pose, X)
    ok = (z_gt > 0) & (z > 0) & np.all(np.isfinite(uv), axis=1)
    if not ok.any():
        return None
    return float(np.median(np.linalg.norm(uv[ok] - uv_gt[ok], axis=1)))


def run(
    bundle: MapBundle,
    source: FrameSource,
    camera: Camera,
    gt: list,
    conf: EngineConf,
    start: int = 0,
    frames: int | None = None,
    stride: int = 1,
) -> dict:
    loc = ProbedLocalizer(bundle, camera, conf)
    pred_px: list[float] = []
    still_px: list[float] = []
    statuses: list[str] = []
    errs: list[tuple[float, float]] = []
    tracked: list[int] = []
    tracked_3d: list[int] = []
    matching: list[Matching] = []
    prev_pose = None
    lat: list[float] = []
    worst: list[tuple[float, int, str, Matching, int]] = []
    for fr in source:
        if fr.index < start or (fr.index - start) % stride:
            continue
        if frames is not None and len(statuses) >= frames:
            break
        loc.probe = (None, np.zeros((0, 3)))
        t0 = time.perf_counter()
        res = loc.localize(fr.image, fr.stamp)
        lat.append((time.perf_counter() - t0) * 1e3)
        pred, X = loc.probe
        g = gt[fr.index]
        if g is not None and pred is not None and len(X):
            e = _px(camera, pred, g, X)
            if e is not None:
                pred_px.append(e)
                if prev_pose is not None:
                    e0 = _px(camera, prev_pose, g, X)
                    if e0 is not None:
                        still_px.append(e0)
        prev_pose = res.cam_from_world
        statuses.append(res.status.value)
        tracked.append(res.tracked)
        tracked_3d.append(res.tracked_3d)
        matching.append(res.matching)
        if res.cam_from_world is not None and g is not None:
            errs.append(pose_errors(res.cam_from_world, g))
            worst.append((errs[-1][0], fr.index, res.status.value, res.matching, res.inliers))
    errs_a = np.array(errs) if errs else np.full((1, 2), np.nan)
    n = len(statuses)
    scale = float(getattr(bundle, "scene_scale", 1.0))
    # wrong: any pose reported (not LOST) off by over 5% of the scene scale or 10 deg
    wrong = int(np.sum((errs_a[:, 0] > 0.05 * scale) | (errs_a[:, 1] > 10.0))) if errs else 0
    return {
        "frames": n,
        "scene_scale": float(getattr(bundle, "scene_scale", float("nan"))),
        "pred_px_median": float(np.median(pred_px)) if pred_px else float("nan"),
        "pred_px_p90": float(np.percentile(pred_px, 90)) if pred_px else float("nan"),
        "still_px_median": float(np.median(still_px)) if still_px else float("nan"),
        "tracked_mean": float(np.mean(tracked)),
        "tracked_3d_mean": float(np.mean(tracked_3d)),
        "localized": sum(s != Status.LOST for s in statuses) / max(1, n),
        "tracking": sum(s == Status.TRACKING for s in statuses) / max(1, n),
        "global_frames": sum(m == Matching.GLOBAL for m in matching),
        "median_pos_err": float(np.median(errs_a[:, 0])),
        "median_rot_err_deg": float(np.median(errs_a[:, 1])),
        "max_pos_err": float(np.max(errs_a[:, 0])),
        "wrong": wrong,
        "mean_ms": float(np.mean(lat)),
        "statuses": statuses,
        # (position error, frame, status, matching, inliers) of the worst five
        "worst": sorted(worst, reverse=True)[:5],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("map")
    p.add_argument("frames")
    p.add_argument("--camera", required=True)
    p.add_argument("--groundtruth", required=True)
    p.add_argument("--start", type=int, default=0)
    p.add_argument("--frames", dest="n", type=int)
    p.add_argument(
        "--scale", type=float, default=1.0, help="scale the map and ground truth by this"
    )
    p.add_argument("--fps", type=float, default=30.0, help="the recording's frame rate")
    p.add_argument("--stride", type=int, default=1, help="every k-th frame (30 Hz -> 30/k Hz)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an EngineConf setting (e.g. motion_model=paper)",
    )
    p.add_argument("--json", help="write the result here (with per-frame statuses)")
    args = p.parse_args(argv)
    bundle = scale_bundle(MapBundle(args.map, verify=False), args.scale)
    source = FrameSource(args.frames, fps=args.fps)
    camera = Camera.parse(args.camera)
    stamps = [source.stamp(i) for i in range(len(source))]
    gt = load_groundtruth(args.groundtruth, source.names(), stamps, args.fps)
    gt = [None if g is None else Rigid3d(g.rotation, g.translation * args.scale) for g in gt]
    conf = EngineConf(**dict(kv.split("=", 1) for kv in args.set))
    out = run(bundle, source, camera, gt, conf, args.start, args.n, args.stride)
    s = out["scene_scale"]
    cm = 100 / args.scale  # errors in cm of the unscaled scene
    print(
        f"frames {out['frames']}  scene_scale {s:.4g}  prediction median "
        f"{out['pred_px_median']:.1f} px (p90 {out['pred_px_p90']:.1f}; no-motion "
        f"{out['still_px_median']:.1f})  tracks/frame {out['tracked_mean']:.0f} "
        f"(3D {out['tracked_3d_mean']:.0f})  localized {out['localized'] * 100:.1f}% "
        f"(tracking {out['tracking'] * 100:.1f}%, global {out['global_frames']})  median error "
        f"{out['median_pos_err'] * cm:.2f} cm-equiv, {out['median_rot_err_deg']:.2f} deg  "
        f"max {out['max_pos_err'] * cm:.1f} cm-equiv  wrong {out['wrong']}"
    )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
