"""Is the reported pose covariance calibrated? Replays a sequence with exact (or pseudo) ground
truth and measures the normalized estimation error squared (NEES) of every non-LOST pose:
e^T C^-1 e over the 6 dof (expected 6), the centre alone (expected 3) and the rotation alone
(expected 3), and the per-axis z-scores of the centre (expected sd 1).

The replay runs the engine as configured (the default: the engine every interface runs) and
takes each frame's pose where the status rules judge it, before they withhold it, so the poses
that the limit withholds are measured too, and the limit can be judged: how many correct poses it
withholds, and whether every wrong pose (``metrics.wrong_poses``' rule) is among them. The limit
is not lifted for the replay: it also decides what the tracker does (an uncertain pose is
re-matched on the whole frame, ``densify_uncertain``; a prediction from a withheld pose rejects
no relocalization, ``contradiction_published_only``), so at infinity the replay would measure
another engine's poses. The ``sd_*`` keys are the centre sd
as that rule judges it (in % of the scene scale, at the bound of its noise estimate).

    python -m sfmloc.eval.calibration MAP FRAMES POSES [--fps 30] [--frames 150]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..engine import EngineConf, Localizer
from ..engine.certainty import position_sd, small_sample_factor
from ..engine.pose import PoseEstimate, pose_error_vector
from ..io.frames import FrameSource
from ..map.bundle import MapBundle, load_bundle
from ..transforms import Rigid3d, pose_errors
from .groundtruth import load_groundtruth
from .metrics import WRONG_POSITION_FRACTION, WRONG_ROTATION_DEG

# chi-square quantiles: the median and the 95th percentile for 3 and 6 dof
CHI2_MEDIAN = {3: 2.366, 6: 5.348}
CHI2_95 = {3: 7.815, 6: 12.592}


@dataclass
class Sample:
    """One posed frame: the estimate, its ground truth, the reported covariance."""

    index: int
    status: str
    est: Rigid3d
    gt: Rigid3d
    cov: np.ndarray
    inliers: int
    estimate: PoseEstimate | None = None  # the final refinement's (its inliers), for re-modelling

    @property
    def error(self) -> np.ndarray:
        return pose_error_vector(self.est, self.gt)


def nees(cov: np.ndarray, e: np.ndarray) -> float:
    return float(e @ np.linalg.solve(cov, e))


def replay_samples(
    bundle: MapBundle,
    source: FrameSource,
    camera: Camera,
    groundtruth: list[Rigid3d | None],
    conf: EngineConf | None = None,
    max_frames: int | None = None,
) -> tuple[list[Sample], int]:
    """Every pose the status rules judged in the replay (published or withheld; ``status`` the
    one they gave it) with its ground truth, and the number of frames."""
    loc = Localizer(bundle, camera, conf or EngineConf())
    out: list[Sample] = []
    n = 0
    for frame in source:
        if max_frames is not None and n >= max_frames:
            break
        n += 1
        r = loc.localize(frame.image, frame.stamp)
        gt = groundtruth[frame.index] if frame.index < len(groundtruth) else None
        if loc.judged is None or gt is None:
            continue
        est, cov = loc.judged  # the frame's final pose and covariance, as judged
        out.append(
            Sample(frame.index, str(r.status), est.cam_from_world, gt, cov, est.num_inliers, est)
        )
    return out, n


def summarize(
    samples: list[Sample], scene_scale: float, max_position_sd: float, noise_z: float = 0.0
) -> dict:
    """NEES statistics, and what the withholding rule (``certainty.withheld``: the centre sd at
    the ``noise_z`` bound of its noise estimate over ``max_position_sd``) does to right and
    wrong poses."""
    if not samples:
        return {"poses": 0}
    n6, npos, nrot, z, sds, wrong = [], [], [], [], [], []
    for s in samples:
        e, C = s.error, s.cov
        n6.append(nees(C, e))
        nrot.append(nees(C[:3, :3], e[:3]))
        npos.append(nees(C[3:, 3:], e[3:]))
        # centre error in the camera's axes, over its sd on each axis
        R = s.est.rotation
        Cc = R @ C[3:, 3:] @ R.T
        z.append((R @ e[3:]) / np.sqrt(np.diag(Cc)))
        sds.append(position_sd(C) / scene_scale * small_sample_factor(s.inliers, noise_z))
        dp, dr = pose_errors(s.est, s.gt)
        wrong.append(dp > WRONG_POSITION_FRACTION * scene_scale or dr > WRONG_ROTATION_DEG)
    n6a, npa, nra = np.array(n6), np.array(npos), np.array(nrot)
    za, sda, wa = np.array(z), np.array(sds), np.array(wrong)
    held = sda > max_position_sd
    right = ~wa
    return {
        "poses": len(samples),
        "nees6_mean": float(n6a[right].mean()) if right.any() else float("nan"),
        "nees6_median": float(np.median(n6a[right])) if right.any() else float("nan"),
        "nees_pos_mean": float(npa[right].mean()) if right.any() else float("nan"),
        "nees_pos_median": float(np.median(npa[right])) if right.any() else float("nan"),
        "nees_rot_mean": float(nra[right].mean()) if right.any() else float("nan"),
        "over_chi2_95": float(np.mean(n6a[right] > CHI2_95[6])) if right.any() else float("nan"),
        "z_sd_xyz_cam": [float(v) for v in za[right].std(axis=0)] if right.any() else [],
        "sd_median_pct": float(np.median(sda) * 100),
        "sd_max_right_pct": float(sda[right].max() * 100) if right.any() else float("nan"),
        "withheld": int(held.sum()),
        "withheld_right": int((held & right).sum()),
        "wrong": int(wa.sum()),
        "wrong_published": int((wa & ~held).sum()),
        "wrong_nees6": [round(float(v), 1) for v in n6a[wa]],
        "wrong_sd_pct": [round(float(v) * 100, 2) for v in sda[wa]],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m sfmloc.eval.calibration",
        description="Replay a sequence and measure the calibration of the reported pose "
        "covariance against ground truth (NEES: 6 dof expected 6, centre and rotation 3). "
        "The engine runs as configured; the poses it withholds are measured too.",
    )
    ap.add_argument("map", type=Path, help="map bundle folder")
    ap.add_argument("frames", type=Path, help="folder of frames (with camera.json, or --camera)")
    ap.add_argument("poses", type=Path, help="ground truth pose file (TUM or COLMAP list)")
    ap.add_argument("--camera", help="camera string (default: FRAMES/camera.json)")
    ap.add_argument("--fps", type=float, default=30.0, help="frame rate of FRAMES (default 30)")
    ap.add_argument(
        "--frames", dest="max_frames", type=int, default=150, help="frames to replay (default 150)"
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an EngineConf override (JSON value), e.g. --set map_noise_px=0",
    )
    a = ap.parse_args(argv)
    camera = Camera.parse(a.camera) if a.camera else Camera.from_json(a.frames / "camera.json")
    source = FrameSource(a.frames, fps=a.fps)
    n = len(source) if a.max_frames is None else min(a.max_frames, len(source))
    gt = load_groundtruth(
        a.poses, source.names(), [source.stamp(i) for i in range(len(source))], a.fps
    )
    overrides = {}
    for kv in a.set:
        k, _, v = kv.partition("=")
        overrides[k] = json.loads(v)
    conf = EngineConf(**overrides)
    bundle = load_bundle(a.map)
    samples, frames = replay_samples(bundle, source, camera, gt, conf, n)
    out = {
        "frames": frames,
        **summarize(samples, bundle.scene_scale, conf.max_position_sd, conf.withhold_noise_z),
    }
    json.dump(out, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
