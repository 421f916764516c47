"""pycolmap.Reconstruction <-> ``sfmloc.io.colmap.Reconstruction``.

Poses go through rotation matrices only, never quaternions: pycolmap's ``Rotation3d.quat``
is ``xyzw`` while COLMAP files (and ``Rigid3d.quat_wxyz``) are ``wxyz``, and a matrix has no
order to get wrong. pycolmap 4 keeps poses on frames (``rig_from_world``); an image's
``cam_from_world()`` composes them and is what we store. Only registered images (with a pose)
are converted; their ids, the camera ids and the point ids are kept.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import pycolmap

from ...cameras import CAMERA_MODELS, Camera
from ...errors import CameraModelError
from ...io.colmap import INVALID_POINT3D_ID, Image, Point3D, Reconstruction
from ...transforms import Rigid3d

_PYCOLMAP_INVALID = int(pycolmap.INVALID_POINT3D_ID)


def _value(x):
    """pycolmap exposes some accessors as methods in one version and properties in another."""
    return x() if callable(x) else x


def rigid3d_from_pycolmap(T: pycolmap.Rigid3d) -> Rigid3d:
    M = np.asarray(T.matrix(), dtype=np.float64)
    return Rigid3d(M[:, :3], M[:, 3])


def rigid3d_to_pycolmap(T: Rigid3d) -> pycolmap.Rigid3d:
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(T.rotation)), np.asarray(T.translation))


def camera_from_pycolmap(cam: pycolmap.Camera) -> Camera:
    name = str(cam.model_name)
    if name not in CAMERA_MODELS:
        raise CameraModelError(
            f"camera {cam.camera_id} has COLMAP model {name}, which sfmloc does not support "
            f"(supported: {', '.join(CAMERA_MODELS)})"
        )
    return Camera(
        name, int(cam.width), int(cam.height), np.asarray(cam.params, dtype=np.float64).copy()
    )


def camera_to_pycolmap(camera: Camera, camera_id: int) -> pycolmap.Camera:
    return pycolmap.Camera(
        model=camera.model,
        width=camera.width,
        height=camera.height,
        params=np.asarray(camera.params, dtype=np.float64),
        camera_id=int(camera_id),
    )


def reconstruction_from_pycolmap(rec: pycolmap.Reconstruction) -> Reconstruction:
    """Our ``Reconstruction`` from a pycolmap one: cameras, registered images with their
    keypoints and point ids, points with tracks, colors and errors."""
    out = Reconstruction()
    for cid, cam in rec.cameras.items():
        out.cameras[int(cid)] = camera_from_pycolmap(cam)
    for iid, im in rec.images.items():
        if not _value(im.has_pose):
            continue
        pts = im.points2D
        n = len(pts)
        xy = np.empty((n, 2), dtype=np.float64)
        ids = np.empty(n, dtype=np.int64)
        for k, p in enumerate(pts):
            xy[k] = p.xy
            pid = int(p.point3D_id)
            ids[k] = INVALID_POINT3D_ID if pid == _PYCOLMAP_INVALID else pid
        out.images[int(iid)] = Image(
            int(iid),
            str(im.name),
            int(im.camera_id),
            rigid3d_from_pycolmap(_value(im.cam_from_world)),
            xy,
            ids,
        )
    for pid, p in rec.points3D.items():
        els = p.track.elements
        out.points3D[int(pid)] = Point3D(
            int(pid),
            np.asarray(p.xyz, dtype=np.float64),
            np.asarray(p.color, dtype=np.uint8),
            float(p.error),
            np.array([e.image_id for e in els], dtype=np.int64),
            np.array([e.point2D_idx for e in els], dtype=np.int64),
        )
    return out


def reconstruction_to_pycolmap(rec: Reconstruction) -> pycolmap.Reconstruction:
    """A pycolmap ``Reconstruction`` of ours: one trivial rig per camera (rig id = camera id),
    one trivial frame per image (frame id = image id), same ids for everything."""
    out = pycolmap.Reconstruction()
    for cid, cam in sorted(rec.cameras.items()):
        out.add_camera_with_trivial_rig(camera_to_pycolmap(cam, cid))
    for iid, im in sorted(rec.images.items()):
        pim = pycolmap.Image(
            name=im.name,
            keypoints=np.asarray(im.points2D, dtype=np.float64).reshape(-1, 2),
            camera_id=int(im.camera_id),
            image_id=int(iid),
        )
        out.add_image_with_trivial_frame(pim, rigid3d_to_pycolmap(im.cam_from_world))
    for pid, p in sorted(rec.points3D.items()):
        track = pycolmap.Track(
            [
                pycolmap.TrackElement(int(i), int(j))
                for i, j in zip(p.track_image_ids, p.track_point2D_idxs)
            ]
        )
        out.add_point3D_with_id(
            int(pid),
            pycolmap.Point3D(
                xyz=np.asarray(p.xyz, dtype=np.float64),
                color=np.asarray(p.rgb, np.uint8),
                error=float(p.error),
                track=track,
            ),
        )
    return out


def filter_points(
    rec: Reconstruction, min_track_length: int = 2, max_error: float | None = None
) -> int:
    """Drop points with a shorter track or a larger mean reprojection error (in place; the
    images' ``point3D_ids`` of their observations become -1). Returns how many were dropped."""
    drop = [
        pid
        for pid, p in rec.points3D.items()
        if len(p.track_image_ids) < min_track_length
        or (max_error is not None and p.error > max_error)
    ]
    _delete_points(rec, drop)
    return len(drop)


def _delete_points(rec: Reconstruction, pids: Iterable[int]) -> None:
    pids = list(pids)
    if not pids:
        return
    gone = np.array(sorted(pids), dtype=np.int64)
    for pid in pids:
        del rec.points3D[pid]
    for im in rec.images.values():
        if len(im.point3D_ids):
            im.point3D_ids[np.isin(im.point3D_ids, gone)] = INVALID_POINT3D_ID


def reconstruction_stats(rec: Reconstruction) -> dict[str, float]:
    """Counts and means to log and report: points, observations, track length, error."""
    tl = np.array([len(p.track_image_ids) for p in rec.points3D.values()], dtype=np.float64)
    err = np.array([p.error for p in rec.points3D.values()], dtype=np.float64)
    return {
        "images": len(rec.images),
        "points3D": len(rec.points3D),
        "observations": int(tl.sum()),
        "mean_track_length": float(tl.mean()) if tl.size else 0.0,
        "mean_reproj_error_px": float(err.mean()) if err.size else 0.0,
    }
