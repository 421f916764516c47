"""COLMAP sparse models (cameras, images, points3D) in text and binary form.

Plain numpy, no pycolmap needed to read: a server or a test can load a model without the
SfM stack. The formats are COLMAP's own (https://colmap.github.io/format.html):
``images`` store ``cam_from_world`` as ``qw qx qy qz tx ty tz``; 2D points use COLMAP's
pixel convention (see ``sfmloc.cameras``); ``point3D_id == -1`` marks an unmatched keypoint.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..cameras import CAMERA_MODELS, MODEL_NAME_FROM_ID, Camera
from ..errors import CameraModelError, ModelFormatError
from ..transforms import Rigid3d

INVALID_POINT3D_ID = -1
# COLMAP writes 2^64-1 for "no 3D point" in binary files.
_BIN_INVALID_ID = np.uint64(0xFFFFFFFFFFFFFFFF)


@dataclass
class Image:
    image_id: int
    name: str
    camera_id: int
    cam_from_world: Rigid3d
    points2D: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    point3D_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self) -> None:
        self.points2D = np.asarray(self.points2D, dtype=np.float64).reshape(-1, 2)
        self.point3D_ids = np.asarray(self.point3D_ids, dtype=np.int64).reshape(-1)
        if len(self.points2D) != len(self.point3D_ids):
            raise ModelFormatError(
                f"image {self.name}: {len(self.points2D)} points2D but {len(self.point3D_ids)} ids"
            )


@dataclass
class Point3D:
    point3D_id: int
    xyz: np.ndarray
    rgb: np.ndarray = field(default_factory=lambda: np.zeros(3, dtype=np.uint8))
    error: float = 0.0
    track_image_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    track_point2D_idxs: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(3)
        self.rgb = np.asarray(self.rgb, dtype=np.uint8).reshape(3)
        self.track_image_ids = np.asarray(self.track_image_ids, dtype=np.int64).reshape(-1)
        self.track_point2D_idxs = np.asarray(self.track_point2D_idxs, dtype=np.int64).reshape(-1)


@dataclass
class Reconstruction:
    cameras: dict[int, Camera] = field(default_factory=dict)
    images: dict[int, Image] = field(default_factory=dict)
    points3D: dict[int, Point3D] = field(default_factory=dict)

    def summary(self) -> str:
        n_obs = sum(len(p.track_image_ids) for p in self.points3D.values())
        mean_track = n_obs / max(1, len(self.points3D))
        return (
            f"{len(self.cameras)} cameras, {len(self.images)} images, {len(self.points3D)} "
            "points3D "
            f"(mean track length {mean_track:.2f})"
        )

    def image_by_name(self) -> dict[str, Image]:
        return {im.name: im for im in self.images.values()}

    def check(self) -> None:
        """Raise ``ModelFormatError`` when ids do not refer to each other consistently."""
        for im in self.images.values():
            if im.camera_id not in self.cameras:
                raise ModelFormatError(f"image {im.name} refers to missing camera {im.camera_id}")
        for pid, p in self.points3D.items():
            for iid, idx in zip(p.track_image_ids, p.track_point2D_idxs):
                seen_in = self.images.get(int(iid))
                if seen_in is None:
                    raise ModelFormatError(f"point3D {pid} track refers to missing image {iid}")
                if not 0 <= idx < len(seen_in.points2D):
                    raise ModelFormatError(
                        f"point3D {pid} track refers to point2D {idx} of image {seen_in.name}"
                    )


# --------------------------------------------------------------------------- detection
def detect_model_format(path: str | Path) -> str:
    """``".bin"`` or ``".txt"``, whichever complete model is in ``path``."""
    path = Path(path)
    if not path.is_dir():
        raise ModelFormatError(f"COLMAP model folder {path} does not exist")
    for ext in (".bin", ".txt"):
        if all((path / f"{n}{ext}").is_file() for n in ("cameras", "images", "points3D")):
            return ext
    raise ModelFormatError(
        f"{path} holds no COLMAP model: expected cameras, images and points3D as .bin or .txt"
    )


def read_model(path: str | Path, ext: str | None = None) -> Reconstruction:
    """Read a COLMAP sparse model folder (text or binary, detected when ``ext`` is None)."""
    path = Path(path)
    ext = ext or detect_model_format(path)
    if ext == ".txt":
        rec = Reconstruction(
            read_cameras_text(path / "cameras.txt"),
            read_images_text(path / "images.txt"),
            read_points3D_text(path / "points3D.txt"),
        )
    elif ext == ".bin":
        rec = Reconstruction(
            read_cameras_binary(path / "cameras.bin"),
            read_images_binary(path / "images.bin"),
            read_points3D_binary(path / "points3D.bin"),
        )
    else:
        raise ModelFormatError(f"unknown COLMAP model extension {ext!r}")
    rec.check()
    return rec


def write_model(rec: Reconstruction, path: str | Path, ext: str = ".txt") -> Path:
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    if ext == ".txt":
        write_cameras_text(rec.cameras, path / "cameras.txt")
        write_images_text(rec.images, path / "images.txt")
        write_points3D_text(rec.points3D, path / "points3D.txt")
    elif ext == ".bin":
        write_cameras_binary(rec.cameras, path / "cameras.bin")
        write_images_binary(rec.images, path / "images.bin")
        write_points3D_binary(rec.points3D, path / "points3D.bin")
    else:
        raise ValueError(f"ext must be '.txt' or '.bin', got {ext!r}")
    return path


# --------------------------------------------------------------------------- text
def _data_lines(path: Path):
    try:
        with open(path) as f:
            for lineno, line in enumerate(f, 1):
                s = line.strip()
                if s and not s.startswith("#"):
                    yield lineno, s
    except OSError as exc:
        raise ModelFormatError(f"cannot read {path}: {exc}") from None


def read_cameras_text(path: str | Path) -> dict[int, Camera]:
    path = Path(path)
    cams: dict[int, Camera] = {}
    for lineno, line in _data_lines(path):
        parts = line.split()
        try:
            cid = int(parts[0])
            cams[cid] = Camera(
                parts[1], int(parts[2]), int(parts[3]), np.array([float(x) for x in parts[4:]])
            )
        except CameraModelError as exc:
            raise CameraModelError(f"{path}:{lineno}: {exc}") from None
        except (ValueError, IndexError) as exc:
            raise ModelFormatError(f"{path}:{lineno}: malformed camera line ({exc})") from None
    return cams


def read_images_text(path: str | Path) -> dict[int, Image]:
    path = Path(path)
    images: dict[int, Image] = {}
    lines = list(_data_lines_keep_empty(path))
    i = 0
    while i < len(lines):
        lineno, header = lines[i]
        if not header:
            i += 1
            continue
        parts = header.split()
        try:
            iid = int(parts[0])
            q = np.array([float(x) for x in parts[1:5]])
            t = np.array([float(x) for x in parts[5:8]])
            cid = int(parts[8])
            name = " ".join(parts[9:])
            if not name:
                raise ValueError("missing image name")
        except (ValueError, IndexError) as exc:
            raise ModelFormatError(f"{path}:{lineno}: malformed image line ({exc})") from None
        pts_line = lines[i + 1][1] if i + 1 < len(lines) else ""
        vals = pts_line.split()
        if len(vals) % 3:
            raise ModelFormatError(
                f"{path}:{lineno + 1}: POINTS2D line must hold triples X Y POINT3D_ID"
            )
        try:
            arr = np.array([float(v) for v in vals]).reshape(-1, 3)
        except ValueError as exc:
            raise ModelFormatError(f"{path}:{lineno + 1}: {exc}") from None
        images[iid] = Image(
            iid, name, cid, Rigid3d.from_quat_wxyz(q, t), arr[:, :2], arr[:, 2].astype(np.int64)
        )
        i += 2
    return images


def _data_lines_keep_empty(path: Path):
    """images.txt pairs a header line with a points line that may be empty."""
    try:
        with open(path) as f:
            for lineno, line in enumerate(f, 1):
                if line.startswith("#"):
                    continue
                yield lineno, line.strip()
    except OSError as exc:
        raise ModelFormatError(f"cannot read {path}: {exc}") from None


def read_points3D_text(path: str | Path) -> dict[int, Point3D]:
    path = Path(path)
    pts: dict[int, Point3D] = {}
    for lineno, line in _data_lines(path):
        parts = line.split()
        try:
            pid = int(parts[0])
            xyz = np.array([float(x) for x in parts[1:4]])
            rgb = np.array([int(x) for x in parts[4:7]], dtype=np.uint8)
            err = float(parts[7])
            track = np.array([int(x) for x in parts[8:]], dtype=np.int64).reshape(-1, 2)
        except (ValueError, IndexError) as exc:
            raise ModelFormatError(f"{path}:{lineno}: malformed point3D line ({exc})") from None
        pts[pid] = Point3D(pid, xyz, rgb, err, track[:, 0], track[:, 1])
    return pts


def write_cameras_text(cameras: dict[int, Camera], path: str | Path) -> None:
    with open(path, "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write(f"# Number of cameras: {len(cameras)}\n")
        for cid, cam in sorted(cameras.items()):
            params = " ".join(repr(float(p)) for p in cam.params)
            f.write(f"{cid} {cam.model} {cam.width} {cam.height} {params}\n")


def write_images_text(images: dict[int, Image], path: str | Path) -> None:
    n_obs = sum(int((im.point3D_ids >= 0).sum()) for im in images.values())
    mean_obs = n_obs / max(1, len(images))
    with open(path, "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f.write(f"# Number of images: {len(images)}, mean observations per image: {mean_obs:.6f}\n")
        for iid, im in sorted(images.items()):
            q = im.cam_from_world.quat_wxyz
            t = im.cam_from_world.translation
            vals = " ".join(repr(float(v)) for v in (*q, *t))
            f.write(f"{iid} {vals} {im.camera_id} {im.name}\n")
            f.write(
                " ".join(
                    f"{float(x)!r} {float(y)!r} {int(pid)}"
                    for (x, y), pid in zip(im.points2D, im.point3D_ids)
                )
                + "\n"
            )


def write_points3D_text(points3D: dict[int, Point3D], path: str | Path) -> None:
    mean_track = sum(len(p.track_image_ids) for p in points3D.values()) / max(1, len(points3D))
    with open(path, "w") as f:
        f.write("# 3D point list with one line of data per point:\n")
        f.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        f.write(f"# Number of points: {len(points3D)}, mean track length: {mean_track:.6f}\n")
        for pid, p in sorted(points3D.items()):
            xyz = " ".join(repr(float(v)) for v in p.xyz)
            rgb = " ".join(str(int(v)) for v in p.rgb)
            track = " ".join(
                f"{int(i)} {int(j)}" for i, j in zip(p.track_image_ids, p.track_point2D_idxs)
            )
            f.write(f"{pid} {xyz} {rgb} {float(p.error)!r} {track}\n")


# --------------------------------------------------------------------------- binary
class _Reader:
    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.data = path.read_bytes()
        except OSError as exc:
            raise ModelFormatError(f"cannot read {path}: {exc}") from None
        self.pos = 0

    def take(self, fmt: str):
        size = struct.calcsize(
            "<" + fmt
        )  # packed little-endian, as unpacked below (no native padding)
        if self.pos + size > len(self.data):
            raise ModelFormatError(f"{self.path}: truncated at byte {self.pos}")
        vals = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return vals

    def array(self, dtype: npt.DTypeLike, count: int) -> np.ndarray:
        le = np.dtype(dtype).newbyteorder("<")
        size = le.itemsize * count
        if self.pos + size > len(self.data):
            raise ModelFormatError(f"{self.path}: truncated at byte {self.pos}")
        arr = np.frombuffer(self.data, dtype=le, count=count, offset=self.pos)
        self.pos += size
        return arr

    def cstring(self) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise ModelFormatError(f"{self.path}: unterminated string at byte {self.pos}")
        s = self.data[self.pos : end].decode("utf-8")
        self.pos = end + 1
        return s


def read_cameras_binary(path: str | Path) -> dict[int, Camera]:
    r = _Reader(Path(path))
    (n,) = r.take("Q")
    cams: dict[int, Camera] = {}
    for _ in range(n):
        cid, model_id, w, h = r.take("iiQQ")
        name = MODEL_NAME_FROM_ID.get(model_id)
        if name is None:
            raise CameraModelError(
                f"{path}: camera {cid} has unsupported COLMAP model id {model_id}"
            )
        params = r.array(np.float64, len(CAMERA_MODELS[name][1]))
        cams[cid] = Camera(name, w, h, params.copy())
    return cams


def read_images_binary(path: str | Path) -> dict[int, Image]:
    r = _Reader(Path(path))
    (n,) = r.take("Q")
    images: dict[int, Image] = {}
    rec = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<u8")])
    for _ in range(n):
        iid, qw, qx, qy, qz, tx, ty, tz, cid = r.take("idddddddi")
        name = r.cstring()
        (n2d,) = r.take("Q")
        size = rec.itemsize * n2d
        if r.pos + size > len(r.data):
            raise ModelFormatError(f"{path}: truncated in image {name}")
        arr = np.frombuffer(r.data, dtype=rec, count=n2d, offset=r.pos)
        r.pos += size
        ids = arr["id"].astype(np.int64)  # 2^64-1 wraps to -1
        images[iid] = Image(
            iid,
            name,
            cid,
            Rigid3d.from_quat_wxyz(np.array([qw, qx, qy, qz]), np.array([tx, ty, tz])),
            np.stack([arr["x"], arr["y"]], axis=1),
            ids,
        )
    return images


def read_points3D_binary(path: str | Path) -> dict[int, Point3D]:
    r = _Reader(Path(path))
    (n,) = r.take("Q")
    pts: dict[int, Point3D] = {}
    for _ in range(n):
        pid, x, y, z, cr, cg, cb, err, tlen = r.take("QdddBBBdQ")
        track = r.array(np.int32, 2 * tlen).reshape(-1, 2).astype(np.int64)
        pts[pid] = Point3D(
            pid, np.array([x, y, z]), np.array([cr, cg, cb]), err, track[:, 0], track[:, 1]
        )
    return pts


def write_cameras_binary(cameras: dict[int, Camera], path: str | Path) -> None:
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(cameras)))
        for cid, cam in sorted(cameras.items()):
            f.write(struct.pack("<iiQQ", cid, cam.model_id, cam.width, cam.height))
            f.write(np.asarray(cam.params, dtype="<f8").tobytes())


def write_images_binary(images: dict[int, Image], path: str | Path) -> None:
    rec = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<u8")])
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for iid, im in sorted(images.items()):
            q = im.cam_from_world.quat_wxyz
            t = im.cam_from_world.translation
            f.write(struct.pack("<idddddddi", iid, *q, *t, im.camera_id))
            f.write(im.name.encode("utf-8") + b"\x00")
            f.write(struct.pack("<Q", len(im.points2D)))
            arr = np.empty(len(im.points2D), dtype=rec)
            arr["x"], arr["y"] = im.points2D[:, 0], im.points2D[:, 1]
            ids = im.point3D_ids.astype(np.int64)
            arr["id"] = np.where(ids < 0, _BIN_INVALID_ID, ids.astype(np.uint64))
            f.write(arr.tobytes())


def write_points3D_binary(points3D: dict[int, Point3D], path: str | Path) -> None:
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(points3D)))
        for pid, p in sorted(points3D.items()):
            f.write(
                struct.pack(
                    "<QdddBBBdQ",
                    pid,
                    *p.xyz,
                    *(int(c) for c in p.rgb),
                    p.error,
                    len(p.track_image_ids),
                )
            )
            track = np.stack([p.track_image_ids, p.track_point2D_idxs], axis=1).astype("<i4")
            f.write(track.tobytes())
