"""The camera model table and parser shared by client, server and builder.

A camera is a COLMAP model name, an image size and the model's parameters in COLMAP order.
``check_camera`` is the one validation (the wire's ``CameraSpec`` and the service's ``Camera``
both call it); ``parse_camera`` reads the two forms users write: a ``camera.json`` path or a
``"MODEL width height params..."`` string (COLMAP ``cameras.txt`` order without the id).
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from .errors import CameraModelError

# name -> (COLMAP model id, parameter names)
CAMERA_MODELS: dict[str, tuple[int, tuple[str, ...]]] = {
    "SIMPLE_PINHOLE": (0, ("f", "cx", "cy")),
    "PINHOLE": (1, ("fx", "fy", "cx", "cy")),
    "SIMPLE_RADIAL": (2, ("f", "cx", "cy", "k")),
    "RADIAL": (3, ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": (4, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    "FULL_OPENCV": (6, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
}
MODEL_NAME_FROM_ID = {mid: name for name, (mid, _) in CAMERA_MODELS.items()}
# Models whose first parameter is the one focal length (the others have fx, fy).
SINGLE_FOCAL_MODELS = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
MAX_IMAGE_SIDE = 16384

CameraFields = tuple[str, int, int, tuple[float, ...]]


def _side(v: Any, name: str) -> int:
    # 640.0 (a JSON file written by another tool) is 640; 640.5 and True are refused.
    whole = isinstance(v, numbers.Integral) or (isinstance(v, float) and v.is_integer())
    if isinstance(v, bool) or not whole:
        raise CameraModelError(f"camera {name} must be an integer, got {v!r}")
    return int(v)


MIN_FOCAL_PER_SIDE = 1e-3


def check_camera(model: Any, width: Any, height: Any, params: Any) -> CameraFields:
    """``(model, width, height, params)`` validated: a known model (any case), the model's
    number of finite parameters, a size in 1..MAX_IMAGE_SIDE and a positive focal length;
    ``CameraModelError`` names the problem."""
    if not isinstance(model, str) or model.upper() not in CAMERA_MODELS:
        raise CameraModelError(
            f"unsupported camera model {model!r}; supported: {', '.join(CAMERA_MODELS)}"
        )
    model = model.upper()
    w, h = _side(width, "width"), _side(height, "height")
    if not (0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE):
        raise CameraModelError(f"camera size {w}x{h} is out of range (1..{MAX_IMAGE_SIDE})")
    try:
        if isinstance(params, (str, bytes)) or not all(
            isinstance(p, numbers.Real) and not isinstance(p, bool) for p in params
        ):
            raise TypeError
        values = tuple(float(p) for p in params)
    except TypeError:
        raise CameraModelError(
            f"camera params must be a list of numbers, got {params!r:.80}"
        ) from None
    names = CAMERA_MODELS[model][1]
    if len(values) != len(names):
        raise CameraModelError(
            f"camera model {model} takes {len(names)} parameters ({' '.join(names)}), "
            f"got {len(values)}"
        )
    if not all(math.isfinite(p) for p in values):
        raise CameraModelError(f"camera parameters must be finite, got {list(values)}")
    fx, fy = (values[0], values[0]) if model in SINGLE_FOCAL_MODELS else values[:2]
    if fx <= 0 or fy <= 0:
        raise CameraModelError(f"focal length must be positive, got {fx}, {fy}")
    # Below this a pinhole image would span more than 179.9 degrees: no camera, and a focal
    # of 1e-300 px made the engine divide by zero (INTERNAL; issue 16).
    if min(fx, fy) < MIN_FOCAL_PER_SIDE * max(w, h):
        raise CameraModelError(
            f"focal length {min(fx, fy):g} px is too small for a {w}x{h} image (at least "
            f"{MIN_FOCAL_PER_SIDE:g} x its larger side, {MIN_FOCAL_PER_SIDE * max(w, h):g} px)"
        )
    return model, w, h, values


def camera_from_dict(d: Mapping[str, Any]) -> CameraFields:
    """Validated fields of a camera JSON object (``model``, ``width``, ``height``, ``params``;
    other keys such as ``param_names`` are ignored)."""
    if not isinstance(d, Mapping) or not all(
        k in d for k in ("model", "width", "height", "params")
    ):
        raise CameraModelError("camera JSON needs 'model', 'width', 'height' and 'params'")
    return check_camera(d["model"], d["width"], d["height"], d["params"])


def parse_camera(spec: str | Path) -> CameraFields:
    """Validated fields of a camera given as a ``camera.json`` path or a
    ``"MODEL width height params..."`` string."""
    s = str(spec).strip()
    if s.lower().endswith(".json") or Path(s).is_file():
        try:
            d = json.loads(Path(s).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise CameraModelError(f"cannot read camera file {s}: {exc}") from None
        return camera_from_dict(d)
    parts = s.split()
    if len(parts) < 4:
        raise CameraModelError(
            f"camera spec {s!r} must be 'MODEL width height params...', "
            "e.g. 'PINHOLE 640 480 525 525 320 240'"
        )
    try:
        width, height = int(parts[1]), int(parts[2])
        params = [float(p) for p in parts[3:]]
    except ValueError as exc:
        raise CameraModelError(f"camera spec {s!r}: {exc}") from None
    return check_camera(parts[0], width, height, params)


def camera_to_string(model: str, width: int, height: int, params: Iterable[float]) -> str:
    """The ``"MODEL width height params..."`` form (``parse_camera`` reads it back exactly)."""
    return " ".join([model, str(width), str(height), *(repr(float(p)) for p in params)])
