"""Synthetic scenes with exact ground truth: the localization test bed.

A textured indoor room (walls, floor, ceiling, furniture boxes) made of planar quads is
rendered exactly (plane-induced homographies, analytic z-buffer) by any pinhole camera. Its
3D points sit at texture corners known analytically, so a COLMAP model of the mapping views
and the poses of a video are exact: errors measured against them are the estimator's.

Conventions: world frame in metres, **z up**, floor at ``z = 0``, the room spans
``[0, L] x [0, W] x [0, H]`` (default 8 x 5 x 3); cameras are COLMAP's (x right, y down,
z forward) and poses ``cam_from_world`` unless named ``world_from_cam``; image coordinates
are COLMAP's (centre of the upper-left pixel at (0.5, 0.5)).

Modules (one stage each)::

    config      SynthConf (+ SceneConf, RenderConf, VisibilityConf, TrajectoryConf), presets
    textures    procedural textures and corner verification
    scene       Scene.room(seed), faces, layout, features, raycast
    renderer    render(scene, camera, cam_from_world) -> (bgr, depth), render_full, render_geometry
    visibility  visible_points(scene, camera, cam_from_world) -> Observations
    trajectory  make_trajectory(kind, n_frames, seed, scene) -> [cam_from_world], mapping_views
    model       build_reconstruction(scene, camera, poses, names) -> Reconstruction
    main        main(conf, out) -> Path: the data set layout of ``sfmloc synth``
    bench       python -m sfmloc.bench.synth: render speed

Typical use::

    from sfmloc.synth import Scene, render, make_trajectory, visible_points
    scene = Scene.room(seed=0)
    camera = Camera.pinhole(640, 480, 525, 525, 320, 240)
    for T in make_trajectory("walk", 300, seed=0, scene=scene):
        bgr, depth = render(scene, camera, T)
"""

from .config import SynthConf, preset
from .model import build_reconstruction
from .renderer import Rendering, render, render_full, render_geometry
from .scene import Scene, raycast, room_layout
from .trajectory import check_trajectory, look_at, make_trajectory, mapping_views, pose_from_angles
from .visibility import Observations, visible_points

__all__ = [
    "Observations",
    "Rendering",
    "Scene",
    "SynthConf",
    "build_reconstruction",
    "check_trajectory",
    "look_at",
    "make_trajectory",
    "mapping_views",
    "pose_from_angles",
    "preset",
    "raycast",
    "render",
    "render_full",
    "render_geometry",
    "room_layout",
    "visible_points",
]
