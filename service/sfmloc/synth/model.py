"""The ground-truth COLMAP model of a set of views: exact poses, points and tracks.

Each view's observations come from ``visibility.visible_points``; a point enters the model
when at least ``min_track_length`` views observe it. Point ids are 1..N in feature order,
image ids 1..M in view order; an image's ``points2D`` are its observations sorted by point id
(exact projections, COLMAP pixel convention), so track ``(image_id, point2D_idx)`` pairs
index them directly. Nothing else is stored in ``points2D`` (no unmatched keypoints).

Public API::

    rec = build_reconstruction(scene, camera, cam_from_worlds, names, face_ids=None, conf=None)
"""

from __future__ import annotations

import numpy as np

from ..cameras import Camera
from ..io.colmap import Image, Point3D, Reconstruction
from ..transforms import Rigid3d
from .config import VisibilityConf
from .scene import Scene
from .visibility import Observations, visible_points

CAMERA_ID = 1


def build_reconstruction(
    scene: Scene,
    camera: Camera,
    cam_from_worlds: list[Rigid3d],
    names: list[str],
    face_ids: list[np.ndarray] | None = None,
    conf: VisibilityConf | None = None,
    observations: list[Observations] | None = None,
) -> Reconstruction:
    """A ``Reconstruction`` of the views (one shared camera, id 1).

    ``face_ids`` (the renderer's face-id images of the views) or ``observations`` (already
    computed) avoid recomputing visibility.
    """
    conf = conf or VisibilityConf()
    if len(names) != len(cam_from_worlds):
        raise ValueError("one name per view")
    if observations is None:
        observations = [
            visible_points(
                scene, camera, T, face_id=None if face_ids is None else face_ids[i], conf=conf
            )
            for i, T in enumerate(cam_from_worlds)
        ]
    n_feat = len(scene.features)
    count = np.zeros(n_feat, np.int64)
    for obs in observations:
        count[obs.point_idx] += 1
    kept = np.flatnonzero(count >= conf.min_track_length)
    pid_of = np.full(n_feat, -1, np.int64)
    pid_of[kept] = np.arange(1, len(kept) + 1)
    rec = Reconstruction(cameras={CAMERA_ID: camera})
    tracks: dict[int, list[tuple[int, int]]] = {int(p): [] for p in pid_of[kept]}
    for i, (T, name, obs) in enumerate(zip(cam_from_worlds, names, observations)):
        image_id = i + 1
        sel = pid_of[obs.point_idx] > 0  # point_idx is increasing, so ids are too
        pids = pid_of[obs.point_idx[sel]]
        rec.images[image_id] = Image(image_id, name, CAMERA_ID, T, obs.xy[sel], pids)
        for k, pid in enumerate(pids):
            tracks[int(pid)].append((image_id, k))
    F = scene.features
    for fi in kept:
        pid = int(pid_of[fi])
        tr = np.array(tracks[pid], np.int64).reshape(-1, 2)
        rec.points3D[pid] = Point3D(pid, F.xyz[fi], F.rgb[fi], 0.0, tr[:, 0], tr[:, 1])
    return rec


def feature_index_of_points(scene: Scene, rec: Reconstruction) -> dict[int, int]:
    """``point3D_id -> index into scene.features`` (points are features, matched by position)."""
    lut = {tuple(np.round(x, 9)): i for i, x in enumerate(scene.features.xyz)}
    return {pid: lut[tuple(np.round(p.xyz, 9))] for pid, p in rec.points3D.items()}
