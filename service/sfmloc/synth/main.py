"""Write a synthetic data set: mapping images + exact COLMAP model, and a 30 Hz video.

Layout of ``OUT`` (all poses exact, see ``sfmloc.synth`` for the frames)::

    images/map-0000.png ...     mapping views (8-bit BGR PNG)
    sparse/cameras.txt          COLMAP text model of the mapping views: one PINHOLE camera,
    sparse/images.txt             cam_from_world poses, names relative to images/, points2D =
    sparse/points3D.txt           exact projections of the observed texture corners
    video/frame-000000.png ...  the trajectory at ``fps`` (default 30 Hz)
    groundtruth.tum             TUM 'timestamp tx ty tz qx qy qz qw', world_from_cam,
                                  timestamp = frame index / fps
    video_poses.txt             COLMAP list 'name qw qx qy qz tx ty tz', cam_from_world
    camera.json                 Camera.to_json of the shared camera
    scene.json                  parameters used and counts; written last

Everything is written into ``.OUT.partial-PID`` next to ``OUT`` and renamed at the end, so
an interrupted run never leaves an ``OUT`` that looks complete. Same configuration, same
bytes: noise and all randomness derive from the seed.

Public API::

    main(conf: SynthConf, out) -> Path          # hloc style
    run(conf, out, overwrite=False) -> SynthResult   # with counts and timings
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .. import __version__
from ..cameras import Camera
from ..errors import InputError
from ..io.colmap import write_model
from ..io.poses import write_colmap_list, write_tum
from .config import SynthConf
from .model import build_reconstruction
from .renderer import prepare, render_full
from .scene import Scene
from .trajectory import check_trajectory, make_trajectory, mapping_views
from .visibility import visible_points

log = logging.getLogger(__name__)

# Noise streams per image kind, so mapping image i and video frame i get different noise.
_NOISE_MAPPING, _NOISE_VIDEO = 1, 2
WORLD_FRAME = (
    "metres; z up, floor z = 0, room [0, L] x [0, W] x [0, H]; cameras x right, y down, z forward"
)


@dataclass
class SynthResult:
    path: Path
    n_mapping: int = 0
    n_frames: int = 0
    n_points3D: int = 0
    n_observations: int = 0
    render_seconds: float = 0.0
    rendered: int = 0
    total_seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def render_fps(self) -> float:
        return self.rendered / self.render_seconds if self.render_seconds > 0 else float("nan")

    def summary(self) -> str:
        p = self.path
        lines = [
            f"wrote {p}",
            f"  images/      {self.n_mapping} mapping views",
            f"  sparse/      COLMAP text model: {self.n_points3D} points3D, {self.n_observations} "
            "observations "
            f"({self.n_observations / max(1, self.n_mapping):.0f} per image)",
            f"  video/       {self.n_frames} frames",
            "  groundtruth.tum (world_from_cam), video_poses.txt (cam_from_world), camera.json, "
            "scene.json",
            f"  render speed {self.render_fps:.1f} frames/s (render only, {self.rendered} images), "
            f"total {self.total_seconds:.1f} s",
        ]
        return "\n".join(lines + [f"  note: {n}" for n in self.notes])


def make_camera(conf: SynthConf) -> Camera:
    """PINHOLE camera with the principal point at the image centre (COLMAP convention)."""
    f = conf.focal if conf.focal is not None else 525.0 * conf.width / 640.0
    return Camera.pinhole(conf.width, conf.height, f, f, conf.width / 2.0, conf.height / 2.0)


class _Progress:
    """Log ``label i/n`` at most every ``every`` seconds (stderr via logging)."""

    def __init__(self, label: str, total: int, every: float = 2.0) -> None:
        self.label, self.total, self.every = label, total, every
        self.t0 = self.last = time.perf_counter()

    def step(self, i: int) -> None:
        now = time.perf_counter()
        if now - self.last >= self.every or i == self.total:
            self.last = now
            rate = i / max(1e-9, now - self.t0)
            log.info("%s %d/%d (%.1f/s)", self.label, i, self.total, rate)


def _write_png(path: Path, bgr: np.ndarray) -> None:
    # Level 1 (OpenCV's default), as bench.robust_data writes: the same pixels (lossless), 2%
    # larger files, 2.3x less CPU to write than level 3 (640x480 views: 60 -> 27 ms each; the
    # tests' world of 100 views: 6.0 -> 2.7 s).
    if not cv2.imwrite(str(path), bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise OSError(f"cannot write {path}")


def run(
    conf: SynthConf, out: str | Path, overwrite: bool = False, scene: Scene | None = None
) -> SynthResult:
    """Render and write the data set for ``conf`` to ``out``. ``scene``: its room when the
    caller holds it already (``Scene.room(conf.seed, conf.scene)``, ~1.5 s CPU to build; the
    tests share one), else built here."""
    if scene is not None and (scene.seed, scene.conf) != (conf.seed, conf.scene):
        raise ValueError(
            f"scene of seed {scene.seed} and {scene.conf} given for seed {conf.seed} and "
            f"{conf.scene}"
        )
    t_start = time.perf_counter()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} is a file, not a folder")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise InputError(f"{out} exists and is not empty; choose another OUT or pass --overwrite")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    (tmp / "images").mkdir(parents=True)
    (tmp / "video").mkdir()
    result = SynthResult(out)
    try:
        _generate(conf, tmp, result, scene)
        if out.exists():
            trash = out.parent / f".{out.name}.old-{os.getpid()}"
            out.rename(trash)
            tmp.rename(out)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    result.total_seconds = time.perf_counter() - t_start
    return result


def main(conf: SynthConf, out: str | Path) -> Path:
    """hloc-style entry point: write the data set and return its path."""
    return run(conf, out).path


def _generate(conf: SynthConf, root: Path, result: SynthResult, scene: Scene | None) -> None:
    t0 = time.perf_counter()
    if scene is None:
        scene = Scene.room(conf.seed, conf.scene)
    log.info("%s (%.1f s)", scene.summary(), time.perf_counter() - t0)
    camera = make_camera(conf)
    prepare(scene)  # mipmaps, outside the timed renders

    # Mapping views and their exact model.
    map_poses = mapping_views(scene, conf.mapping_views, conf.seed)
    names = [f"map-{i:04d}.png" for i in range(len(map_poses))]
    observations = []
    prog = _Progress("mapping views", len(map_poses))
    for i, (T, name) in enumerate(zip(map_poses, names)):
        t = time.perf_counter()
        r = render_full(
            scene, camera, T, noise_seed=(conf.seed, _NOISE_MAPPING, i), conf=conf.render
        )
        result.render_seconds += time.perf_counter() - t
        result.rendered += 1
        observations.append(
            visible_points(
                scene, camera, T, face_id=r.face_id, conf=conf.visibility, render_conf=conf.render
            )
        )
        _write_png(root / "images" / name, r.bgr)
        prog.step(i + 1)
    rec = build_reconstruction(
        scene, camera, map_poses, names, conf=conf.visibility, observations=observations
    )
    write_model(rec, root / "sparse", ".txt")
    result.n_mapping = len(map_poses)
    result.n_points3D = len(rec.points3D)
    result.n_observations = int(sum(len(im.point3D_ids) for im in rec.images.values()))
    log.info("model: %s", rec.summary())

    # The video.
    tconf = conf.trajectory
    extra = {"look": tconf.orbit_look} if tconf.kind == "orbit" else {}
    poses = make_trajectory(tconf.kind, tconf.n_frames, conf.seed, scene, fps=tconf.fps, **extra)
    problems = check_trajectory(scene.layout, poses)
    if problems:  # generation keeps clear of these; report rather than fail if a custom room is odd
        result.notes += problems[:3]
    frame_names = [f"frame-{i:06d}.png" for i in range(len(poses))]
    prog = _Progress(f"{tconf.kind} frames", len(poses))
    for i, (T, name) in enumerate(zip(poses, frame_names)):
        t = time.perf_counter()
        r = render_full(scene, camera, T, noise_seed=(conf.seed, _NOISE_VIDEO, i), conf=conf.render)
        result.render_seconds += time.perf_counter() - t
        result.rendered += 1
        _write_png(root / "video" / name, r.bgr)
        prog.step(i + 1)
    result.n_frames = len(poses)
    write_tum(
        root / "groundtruth.tum",
        [i / tconf.fps for i in range(len(poses))],
        [T.inverse() for T in poses],
    )
    write_colmap_list(root / "video_poses.txt", frame_names, poses)
    camera.to_json(root / "camera.json")

    info = {
        "generator": f"sfmloc synth {__version__}",
        "scene": conf.scene.name,
        "seed": conf.seed,
        "trajectory": tconf.kind,
        "fps": tconf.fps,
        "frames": result.n_frames,
        "mapping_views": result.n_mapping,
        "points3D": result.n_points3D,
        "observations": result.n_observations,
        "room_size": list(scene.layout.size),
        "boxes": [
            {
                "name": b.name,
                "kind": b.kind,
                "center": [round(float(c), 6) for c in b.center],
                "size": [round(float(s), 6) for s in b.size],
                "yaw_deg": round(float(np.degrees(b.yaw)), 6),
                "z0": round(float(b.z0), 6),
            }
            for b in scene.layout.boxes
        ],
        "world_frame": WORLD_FRAME,
        "pixel_convention": "COLMAP: centre of the upper-left pixel at (0.5, 0.5)",
        "files": {
            "images": "images/ mapping views",
            "sparse": "COLMAP text model of images/ (cam_from_world, exact points and tracks)",
            "video": "video/ frames at fps",
            "groundtruth.tum": "timestamp tx ty tz qx qy qz qw, world_from_cam, timestamp = index "
            "/ fps",
            "video_poses.txt": "name qw qx qy qz tx ty tz, cam_from_world",
            "camera.json": "the camera of every image",
        },
        "config": conf.model_dump(mode="json"),
    }
    # Last: its presence marks a complete data set.
    (root / "scene.json").write_text(json.dumps(info, indent=2) + "\n")
