"""Camera models as COLMAP defines them, with projection and undistortion.

Pixel convention (COLMAP's): the image plane spans ``[0, width] x [0, height]`` and the
center of the upper-left pixel is at ``(0.5, 0.5)``. Array index ``(row j, col i)`` is the
pixel centered at ``(i + 0.5, j + 0.5)``. Every keypoint, projection and principal point in
sfmloc is in this convention; ``PIXEL_CENTER_OFFSET`` converts from OpenCV's array-index
coordinates where a detector returns them.

Normalized camera coordinates are ``(X/Z, Y/Z)`` of a point in the camera frame (x right,
y down, z forward), before distortion.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sfmloc_client.cameras import (
    CAMERA_MODELS,
    MODEL_NAME_FROM_ID,
    SINGLE_FOCAL_MODELS,
    camera_from_dict,
    camera_to_string,
    check_camera,
    parse_camera,
)

from .transforms import Rigid3d

__all__ = ["CAMERA_MODELS", "MODEL_NAME_FROM_ID", "PIXEL_CENTER_OFFSET", "Camera"]

# Add to OpenCV array-index coordinates to get COLMAP image coordinates.
PIXEL_CENTER_OFFSET = 0.5


@dataclass(frozen=True)
class Camera:
    """An intrinsic camera: COLMAP model name, image size and parameters (COLMAP order)."""

    model: str
    width: int
    height: int
    params: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        # The one validation shared with the client's CameraSpec (sfmloc_client.cameras).
        params = np.asarray(self.params, dtype=np.float64).reshape(-1)
        model, width, height, _ = check_camera(self.model, self.width, self.height, params)
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)
        object.__setattr__(self, "params", params)

    # ----- construction -------------------------------------------------------------------
    @classmethod
    def pinhole(cls, width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> Camera:
        return cls("PINHOLE", width, height, np.array([fx, fy, cx, cy]))

    @classmethod
    def from_string(cls, spec: str) -> Camera:
        """Parse ``"MODEL width height p1 p2 ..."`` (COLMAP cameras.txt order, without the id)."""
        return cls.parse(spec)

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        model, width, height, params = camera_from_dict(d)
        return cls(model, width, height, np.asarray(params))

    @classmethod
    def from_json(cls, path: str | Path) -> Camera:
        return cls.parse(Path(path))

    @classmethod
    def parse(cls, spec: str | Path) -> Camera:
        """A camera from a ``camera.json`` path or a ``"MODEL w h params..."`` string."""
        model, width, height, params = parse_camera(spec)
        return cls(model, width, height, np.asarray(params))

    def to_dict(self) -> dict:
        names = CAMERA_MODELS[self.model][1]
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "params": [float(p) for p in self.params],
            "param_names": list(names),
        }

    def to_json(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    def to_string(self) -> str:
        return camera_to_string(self.model, self.width, self.height, self.params)

    # ----- properties ---------------------------------------------------------------------
    @property
    def model_id(self) -> int:
        return CAMERA_MODELS[self.model][0]

    @property
    def focal(self) -> tuple[float, float]:
        p = self.params
        if self.model in SINGLE_FOCAL_MODELS:
            return float(p[0]), float(p[0])
        return float(p[0]), float(p[1])

    @property
    def principal_point(self) -> tuple[float, float]:
        p = self.params
        if self.model in SINGLE_FOCAL_MODELS:
            return float(p[1]), float(p[2])
        return float(p[2]), float(p[3])

    @property
    def K(self) -> np.ndarray:
        """3x3 calibration matrix of the pinhole part (COLMAP pixel convention)."""
        fx, fy = self.focal
        cx, cy = self.principal_point
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """Distortion coefficients in OpenCV order ``(k1, k2, p1, p2[, k3, k4, k5, k6])``."""
        p = self.params
        if self.model in ("SIMPLE_PINHOLE", "PINHOLE"):
            return np.zeros(4)
        if self.model == "SIMPLE_RADIAL":
            return np.array([p[3], 0.0, 0.0, 0.0])
        if self.model == "RADIAL":
            return np.array([p[3], p[4], 0.0, 0.0])
        if self.model == "OPENCV":
            return p[4:8].copy()
        # FULL_OPENCV: OpenCV's rational model (k1 k2 p1 p2 k3 k4 k5 k6).
        return p[4:12].copy()

    @property
    def is_distorted(self) -> bool:
        # (a pinhole model has no coefficients: no array built; several calls a frame)
        return self.model not in ("SIMPLE_PINHOLE", "PINHOLE") and bool(
            np.any(self.dist_coeffs != 0)
        )

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (pyramid levels).

        Focal and principal point scale with the image plane (valid in COLMAP's
        pixel-corner convention); distortion is in normalized coordinates and does not change.
        """
        p = self.params.copy()
        n_lin = 3 if self.model in SINGLE_FOCAL_MODELS else 4
        p[:n_lin] *= factor
        return Camera(
            self.model, max(1, round(self.width * factor)), max(1, round(self.height * factor)), p
        )

    # ----- distortion ---------------------------------------------------------------------
    def _distortion(self, uv: np.ndarray) -> np.ndarray:
        """COLMAP's distortion displacement ``delta(u, v)`` in normalized coordinates."""
        u, v = uv[:, 0], uv[:, 1]
        d = self.dist_coeffs
        u2, v2, uv_ = u * u, v * v, u * v
        r2 = u2 + v2
        if self.model == "FULL_OPENCV":
            k1, k2, p1, p2, k3, k4, k5, k6 = d
            r4, r6 = r2 * r2, r2 * r2 * r2
            radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6) - 1.0
        else:
            k1, k2, p1, p2 = d
            radial = k1 * r2 + k2 * r2 * r2
        du = u * radial + 2 * p1 * uv_ + p2 * (r2 + 2 * u2)
        dv = v * radial + 2 * p2 * uv_ + p1 * (r2 + 2 * v2)
        return np.stack([du, dv], axis=1)

    def distort_normalized(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if not self.is_distorted:
            return uv.copy()
        return uv + self._distortion(uv)

    def undistort_normalized(self, uv_d: np.ndarray, iterations: int = 100) -> np.ndarray:
        """Invert ``distort_normalized`` with Newton steps (numeric Jacobian), as COLMAP does."""
        uv_d = np.asarray(uv_d, dtype=np.float64).reshape(-1, 2)
        if not self.is_distorted:
            return uv_d.copy()
        x = uv_d.copy()
        eps = 1e-9
        for _ in range(iterations):
            f = x + self._distortion(x) - uv_d
            ex = np.array([eps, 0.0])
            ey = np.array([0.0, eps])
            # Jacobian of x + delta(x), by central differences.
            jx = (2 * ex + self._distortion(x + ex) - self._distortion(x - ex)) / (2 * eps)
            jy = (2 * ey + self._distortion(x + ey) - self._distortion(x - ey)) / (2 * eps)
            a, c = jx[:, 0], jx[:, 1]
            b, d = jy[:, 0], jy[:, 1]
            det = a * d - b * c
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            step = np.stack(
                [(d * f[:, 0] - b * f[:, 1]) / det, (-c * f[:, 0] + a * f[:, 1]) / det], axis=1
            )
            x = x - step
            if np.max(np.abs(step), initial=0.0) < 1e-14:
                break
        return x

    # ----- projection ---------------------------------------------------------------------
    def img_from_cam(self, points_cam: np.ndarray) -> np.ndarray:
        """Project camera-frame 3D points (N, 3) to image coordinates (N, 2). Z must be > 0."""
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        uv = p[:, :2] / p[:, 2:3]
        return self.img_from_normalized(uv)

    def img_from_normalized(self, uv: np.ndarray) -> np.ndarray:
        # (K in place on distort_normalized's new array: fx u + cx and fy v + cy, the same
        # products and sums as column by column, without np.stack's layers; the tracker
        # projects its map points through this every frame)
        uv = self.distort_normalized(uv)
        uv *= self.focal
        uv += self.principal_point
        return uv

    def cam_from_img(self, points2D: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates (N, 2) of image points (N, 2)."""
        p = np.asarray(points2D, dtype=np.float64).reshape(-1, 2)
        fx, fy = self.focal
        cx, cy = self.principal_point
        uv_d = np.stack([(p[:, 0] - cx) / fx, (p[:, 1] - cy) / fy], axis=1)
        return self.undistort_normalized(uv_d)

    def undistort_points(self, points2D: np.ndarray) -> np.ndarray:
        """Image points of this camera mapped to the undistorted pinhole image with the same K."""
        uv = self.cam_from_img(points2D)
        fx, fy = self.focal
        cx, cy = self.principal_point
        return np.stack([fx * uv[:, 0] + cx, fy * uv[:, 1] + cy], axis=1)

    def project(
        self, cam_from_world: Rigid3d, points3D: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates (N, 2) and depths (N,) of world points; depth <= 0 is behind."""
        p = np.asarray(points3D, dtype=np.float64).reshape(-1, 3)
        if len(p) > 1:
            # (Rigid3d.apply written out with R^T contiguous: the same product and bits, without
            # OpenBLAS's transposed-operand path; the tracker projects its map points through
            # this every frame. One point: a matrix-vector product, whose bits differ)
            pc = p @ np.ascontiguousarray(cam_from_world.rotation.T)
            pc += cam_from_world.translation
        else:
            pc = cam_from_world.apply(p)
        z = pc[:, 2]
        safe = np.where(np.abs(z) < 1e-12, 1e-12, z)
        uv = pc[:, :2] / safe[:, None]
        if self.is_distorted:
            return self.img_from_normalized(uv), z
        # (K applied in place on the division's new array: distort_normalized's copy of it
        # for a pinhole camera skipped, the same products and sums)
        uv *= self.focal
        uv += self.principal_point
        return uv, z

    def in_image(self, points2D: np.ndarray, margin: float = 0.0) -> np.ndarray:
        p = np.asarray(points2D).reshape(-1, 2)
        return (
            (p[:, 0] >= margin)
            & (p[:, 1] >= margin)
            & (p[:, 0] <= self.width - margin)
            & (p[:, 1] <= self.height - margin)
        )

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, Camera)
            and self.model == other.model
            and self.width == other.width
            and self.height == other.height
            and np.array_equal(self.params, other.params)
        )

    def __hash__(self) -> int:
        return hash((self.model, self.width, self.height, tuple(self.params.tolist())))

    def __repr__(self) -> str:
        return f"Camera({self.to_string()!r})"


def as_camera(camera: Camera | str | Path) -> Camera:
    """``camera`` itself, or parsed from a ``camera.json`` path or a ``"MODEL w h params..."``
    string (every API that takes a camera takes these)."""
    if isinstance(camera, Camera):
        return camera
    if isinstance(camera, (str, Path)):
        return Camera.parse(camera)
    raise TypeError(
        f"camera must be a Camera, a camera.json path or 'MODEL w h params...', got "
        f"{type(camera).__name__}"
    )
