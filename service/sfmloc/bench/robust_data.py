"""The data of the ``robust`` suite's rows, derived from the synthetic room and redkitchen:
each function writes one derived input (a rendered video, a subset or scaled model, a
subsampled or upsampled frame folder) and is pure file work, so tests run them on tiny data.

- ``render_video``: the room along a trajectory at any image size (exact poses);
- ``subset_model``: every k-th mapping view of an exact COLMAP model (sparser maps);
- ``scale_model`` / ``scale_pose_list``: the scene scaled (points and poses; images unchanged);
- ``subsample_frames``: every k-th frame of a folder (lower frame rates, same stamps);
- ``upsample_frames``: frames resized by an integer factor, with the camera scaled to match.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..cameras import Camera
from ..errors import InputError
from ..io.colmap import INVALID_POINT3D_ID, Image, Point3D, Reconstruction, read_model, write_model
from ..io.poses import read_poses, write_colmap_list
from ..transforms import Rigid3d

# The synthetic video's noise stream (``sfmloc.synth.main``): same seed, same frames as a
# ``sfmloc synth`` data set of the same configuration.
_NOISE_VIDEO = 2


def _fresh(path: Path) -> Path:
    if path.exists():
        shutil.rmtree(path)
    path.mkdir(parents=True)
    return path


def render_video(
    sconf, out: str | Path, n_frames: int, width: int | None = None, height: int | None = None
) -> tuple[Path, Camera]:
    """The first ``n_frames`` of ``sconf``'s trajectory, rendered at ``width`` x ``height``
    (default: the configuration's) with the focal length scaled with the width, as
    ``frame-NNNNNN.png`` in ``out`` with ``video_poses.txt`` (exact cam_from_world) and
    ``camera.json``. The trajectory is made for ``sconf.trajectory.n_frames`` frames and cut,
    so every size sees the same poses."""
    from ..synth.main import make_camera
    from ..synth.renderer import prepare, render_full
    from ..synth.scene import Scene
    from ..synth.trajectory import make_trajectory

    out = _fresh(Path(out))
    conf = sconf.model_copy(
        update={"width": width or sconf.width, "height": height or sconf.height}
    )
    if conf.focal is not None:
        conf = conf.model_copy(update={"focal": sconf.focal * conf.width / sconf.width})
    t = sconf.trajectory
    scene = Scene.room(sconf.seed, sconf.scene)
    prepare(scene)
    extra = {"look": t.orbit_look} if t.kind == "orbit" else {}
    poses = make_trajectory(t.kind, t.n_frames, sconf.seed, scene, fps=t.fps, **extra)[:n_frames]
    camera = make_camera(conf)
    names = [f"frame-{i:06d}.png" for i in range(len(poses))]
    for i, (T, name) in enumerate(zip(poses, names)):
        r = render_full(
            scene, camera, T, noise_seed=(sconf.seed, _NOISE_VIDEO, i), conf=sconf.render
        )
        if not cv2.imwrite(str(out / name), r.bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OSError(f"cannot write {out / name}")
    write_colmap_list(out / "video_poses.txt", names, poses)
    camera.to_json(out / "camera.json")
    return out, camera


def subset_model(
    rec: Reconstruction, keep_names: Sequence[str], min_track: int = 2
) -> Reconstruction:
    """The model of the images ``keep_names`` only: their observations, and the points that
    keep at least ``min_track`` of them (the others are dropped and unlinked)."""
    keep = set(keep_names)
    images = {iid: im for iid, im in rec.images.items() if im.name in keep}
    if len(images) != len(keep):
        missing = sorted(keep - {im.name for im in images.values()})
        raise InputError(f"images not in the model: {', '.join(missing[:5])}")
    points: dict[int, Point3D] = {}
    for pid, p in rec.points3D.items():
        m = np.isin(p.track_image_ids, list(images))
        if m.sum() >= min_track:
            points[pid] = Point3D(
                pid,
                p.xyz.copy(),
                p.rgb.copy(),
                p.error,
                p.track_image_ids[m],
                p.track_point2D_idxs[m],
            )
    out = {}
    for iid, im in images.items():
        ids = im.point3D_ids.copy()
        ids[~np.isin(ids, list(points))] = INVALID_POINT3D_ID
        out[iid] = Image(iid, im.name, im.camera_id, im.cam_from_world, im.points2D.copy(), ids)
    used = {im.camera_id for im in out.values()}
    return Reconstruction({c: cam for c, cam in rec.cameras.items() if c in used}, out, points)


def every_kth_image(rec: Reconstruction, k: int) -> list[str]:
    """Names of every ``k``-th image in name order (the synthetic mapping views interleave
    aimed and walking-band views, so every k-th keeps both kinds)."""
    if k < 1:
        raise InputError(f"k must be >= 1, got {k}")
    return sorted(im.name for im in rec.images.values())[::k]


def scale_pose(T: Rigid3d, s: float) -> Rigid3d:
    """``cam_from_world`` of the same camera in a world scaled by ``s`` (x' = s x)."""
    return Rigid3d(T.rotation, s * np.asarray(T.translation))


def scale_model(rec: Reconstruction, s: float) -> Reconstruction:
    """The model with every point and camera centre scaled by ``s`` about the origin; the
    observations (pixels, tracks) and cameras are unchanged: the same images fit it exactly."""
    if not s > 0:
        raise InputError(f"scale must be positive, got {s}")
    images = {
        iid: Image(
            iid,
            im.name,
            im.camera_id,
            scale_pose(im.cam_from_world, s),
            im.points2D.copy(),
            im.point3D_ids.copy(),
        )
        for iid, im in rec.images.items()
    }
    points = {
        pid: Point3D(
            pid,
            s * p.xyz,
            p.rgb.copy(),
            p.error,
            p.track_image_ids.copy(),
            p.track_point2D_idxs.copy(),
        )
        for pid, p in rec.points3D.items()
    }
    return Reconstruction(dict(rec.cameras), images, points)


def scale_pose_list(src: str | Path, dst: str | Path, s: float) -> Path:
    """A COLMAP pose list (``name qw qx qy qz tx ty tz``) with the world scaled by ``s``."""
    poses = read_poses(src)
    return write_colmap_list(
        dst, [e.key for e in poses], [scale_pose(e.cam_from_world, s) for e in poses]
    )


def write_scaled_model(model_dir: str | Path, out_dir: str | Path, s: float) -> Path:
    out = _fresh(Path(out_dir))
    write_model(scale_model(read_model(model_dir), s), out, ".txt")
    return out


def write_subset_model(
    model_dir: str | Path, out_dir: str | Path, k: int
) -> tuple[Path, list[str]]:
    """Every ``k``-th image of the model at ``model_dir`` as a model in ``out_dir``."""
    rec = read_model(model_dir)
    names = every_kth_image(rec, k)
    out = _fresh(Path(out_dir))
    write_model(subset_model(rec, names), out, ".txt")
    return out, names


def subsample_frames(frames: Sequence[Path], step: int, out: str | Path) -> Path:
    """Every ``step``-th of ``frames`` (from the first) as links in ``out``, same names: a
    30 Hz sequence becomes a 30/step Hz one; read it with ``FrameSource(out, fps=30/step)``
    so frame k's stamp is that of original frame k * step."""
    if step < 1:
        raise InputError(f"step must be >= 1, got {step}")
    out = _fresh(Path(out))
    for p in list(frames)[::step]:
        os.symlink(Path(p).resolve(), out / Path(p).name)
    return out


def upsample_frames(
    frames: Sequence[Path], factor: int, out: str | Path, camera: Camera, jpeg_quality: int = 95
) -> tuple[Path, Camera]:
    """``frames`` resized by ``factor`` (bicubic), same names, as gray JPEG (PNG for .png
    names), with ``camera`` scaled to match: in COLMAP's pixel convention (upper-left pixel
    centre at 0.5) a resize by ``factor`` scales focal lengths and principal point by it."""
    out = _fresh(Path(out))
    for p in frames:
        p = Path(p)
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f"cannot decode frame {p}")
        big = cv2.resize(
            img, (img.shape[1] * factor, img.shape[0] * factor), interpolation=cv2.INTER_CUBIC
        )
        params = (
            [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]
            if p.suffix.lower() in (".jpg", ".jpeg")
            else []
        )
        if not cv2.imwrite(str(out / p.name), big, params):
            raise OSError(f"cannot write {out / p.name}")
    return out, camera.scaled(factor)
