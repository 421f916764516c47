"""What the viewer draws of a map bundle: its points with their colours, its cameras, the
scene's scale and "up". Read from the bundle's arrays after checking their checksums; the ANN
index and descriptors are never loaded (the viewer does not localize)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..cameras import Camera
from ..errors import BundleError, MapNotFoundError
from ..map.bundle import MANIFEST, load_array, read_manifest, verify_bundle
from ..transforms import rotmat_from_quat_wxyz

# A browser draws a few hundred thousand points smoothly in software GL; larger maps are shown
# by a fixed random subset (the same on every load).
DEFAULT_MAX_POINTS = 300_000


@dataclass
class MapView:
    name: str
    build_id: str
    path: Path
    points_xyz: np.ndarray  # (N, 3) float64, the points shown
    point_rgb: np.ndarray  # (N, 3) uint8
    n_points_total: int
    cameras: list[dict[str, Any]]
    scene_scale: float  # median camera-to-point depth (map units), as MapBundle.scene_scale
    up: list[float]  # world "up": opposite the mapping cameras' mean image-down axis

    @property
    def origin(self) -> np.ndarray:
        """The points' median: the page draws everything relative to it, so that float32 (the
        GPU's precision) keeps millimetres in a map far from its frame's origin (a map aligned
        to UTM coordinates is 10^6 m away: float32 steps there are 6 cm)."""
        P = self.points_xyz
        return np.median(P, axis=0) if len(P) else np.zeros(3)

    def meta(self) -> dict[str, Any]:
        """The page's map description (JSON); the points come as binary (``points_bytes``)."""
        P = self.points_xyz
        centre = self.origin
        radius = float(np.percentile(np.linalg.norm(P - centre, axis=1), 90)) if len(P) else 1.0
        return {
            "name": self.name,
            "build_id": self.build_id,
            "n_points": self.n_points_total,
            "points_shown": len(self.points_xyz),
            "cameras": self.cameras,
            "scene_scale": self.scene_scale,
            "up": self.up,
            "origin": [float(v) for v in centre],
            "radius": max(radius, 1e-9),
        }

    def points_bytes(self) -> bytes:
        """N x 3 little-endian float32 positions relative to ``origin`` (meta), then N x 3
        uint8 colours (RGB)."""
        xyz = np.ascontiguousarray(self.points_xyz - self.origin, dtype="<f4")
        rgb = np.ascontiguousarray(self.point_rgb, dtype=np.uint8)
        return xyz.tobytes() + rgb.tobytes()


def find_maps(roots: Sequence[str | Path]) -> dict[str, Path]:
    """Bundle folders (holding a manifest) directly under each root, by folder name; the first
    root wins a name two roots share, as in the server's map roots."""
    found: dict[str, Path] = {}
    for root in roots:
        root = Path(root)
        if not root.is_dir():
            raise MapNotFoundError(f"maps folder {root} does not exist")
        for d in sorted(root.iterdir()):
            if d.is_dir() and not d.name.startswith(".") and (d / MANIFEST).is_file():
                found.setdefault(d.name, d)
    return found


def load_map_view(path: str | Path, max_points: int = DEFAULT_MAX_POINTS) -> MapView:
    path = Path(path)
    problems = verify_bundle(path, checksums=True)
    if problems:
        raise BundleError(f"map bundle {path} is corrupt: " + "; ".join(problems))
    manifest = read_manifest(path)

    def load(name: str) -> np.ndarray:
        return load_array(path, manifest, name)

    xyz = load("points_xyz")
    rgb = load("point_rgb")
    n_total = len(xyz)
    if n_total > max_points:
        keep = np.sort(np.random.default_rng(0).choice(n_total, max_points, replace=False))
        xyz_shown, rgb_shown = xyz[keep], rgb[keep]
    else:
        xyz_shown, rgb_shown = xyz, rgb
    poses = load("image_cam_from_world")  # qw qx qy qz tx ty tz
    cams = [Camera.from_dict(c) for c in manifest.cameras]
    image_camera = load("image_camera")
    R = (
        np.stack([rotmat_from_quat_wxyz(q[:4]) for q in poses])
        if len(poses)
        else np.zeros((0, 3, 3))
    )
    t = poses[:, 4:7] if len(poses) else np.zeros((0, 3))
    cameras = []
    for i, name in enumerate(manifest.image_names):
        cam = cams[int(image_camera[i])]
        fx, fy = cam.focal
        centre = -R[i].T @ t[i]
        cameras.append(
            {
                "name": name,
                "centre": [float(v) for v in centre],
                # Rows of cam_from_world's rotation: the camera's x (right), y (down) and z
                # (forward) axes in world coordinates.
                "axes": [[float(v) for v in row] for row in R[i]],
                "tan_half": [cam.width / (2 * fx), cam.height / (2 * fy)],
            }
        )
    down = R[:, 1, :].mean(0) if len(R) else np.array([0.0, 1.0, 0.0])
    up = -down / max(float(np.linalg.norm(down)), 1e-12)
    return MapView(
        name=manifest.name,
        build_id=manifest.build_id,
        path=path,
        points_xyz=np.asarray(xyz_shown, np.float64),
        point_rgb=np.asarray(rgb_shown, np.uint8),
        n_points_total=n_total,
        cameras=cameras,
        scene_scale=_median_depth(xyz, R, t, load("image_points_ptr"), load("image_points_idx")),
        up=[float(v) for v in up],
    )


def _median_depth(
    xyz: np.ndarray, R: np.ndarray, t: np.ndarray, ptr: np.ndarray, idx: np.ndarray
) -> float:
    """MapBundle.scene_scale without loading the bundle: the median depth of every observed
    point in the camera that sees it."""
    if len(idx) == 0:
        return 1.0
    owner = np.repeat(np.arange(len(R)), np.diff(ptr))
    depth = np.einsum("ij,ij->i", xyz[idx], R[owner, 2, :]) + t[owner, 2]
    depth = depth[np.isfinite(depth) & (depth > 0)]
    return float(np.median(depth)) if len(depth) else 1.0
