"""The map bundle: one versioned folder the server loads and memory-maps.

Layout of ``maps/NAME/``::

    manifest.json        pydantic ``Manifest``: format, version, build id, counts, builder
                         parameters, cameras, image names, keypoint scales (the focal length
                         in pixels the descriptors were computed at, ``keypoint_scales``), and
                         for every array its file, dtype, shape and SHA-256
    manifest.sha256      SHA-256 of manifest.json in ``sha256sum`` format (``sha256sum -c``
                         works): the manifest is covered too, so no byte of a bundle can be
                         edited unnoticed (the manifest holds every array's SHA-256)
    <array>.npy          plain .npy arrays (no pickle), loadable with memory mapping; their
                         names in the manifest are plain file names inside the bundle folder
    arrays.bin           instead of the .npy files, in a *packed* bundle (format version 2,
                         ``write_bundle(packed=True)``, what ``map split`` writes for sub-maps):
                         every array's raw bytes in one file, each at a page boundary (its
                         offset, dtype, shape and SHA-256 in the manifest), plus the derived
                         ``image_rotations`` (I,3,3) f8, and the scene scale in the manifest

Arrays (P points, D descriptors, I images, L clusters, C cameras):

=======================  ============  =====================================================
name                     shape, dtype  meaning
=======================  ============  =====================================================
points_xyz               (P,3) f8      3D points, world frame of the SfM model
point_ids                (P,) i8       the source model's point3D ids
point_rgb                (P,3) u1      colours (for viewers)
descriptors              (D,32) f2     PCA-32 DAISY descriptors, sorted by image
desc_point               (D,) i4       descriptor -> point row
desc_image               (D,) i4       descriptor -> image row
desc_level               (D,) u1       pyramid level it was extracted at
desc_xy                  (D,2) f4      keypoint in the image (original pixels, COLMAP conv.)
image_desc_ptr           (I+1,) i8     image i owns descriptors [ptr[i], ptr[i+1])
image_cam_from_world     (I,7) f8      qw qx qy qz tx ty tz (cam_from_world)
image_camera             (I,) i4       image -> camera row (``manifest.cameras``)
image_points_ptr/_idx    CSR           image -> points it sees (its SfM track entries)
cluster_images_ptr/_idx  CSR           cluster -> images (overlapping clusters)
point_clusters_ptr/_idx  CSR           point -> clusters it belongs to
pca_mean                 (104,) f4     raw DAISY mean
pca_basis                (104,32) f4   PCA basis: desc = (raw - mean) @ basis
index_faiss              (B,) u1       the faiss index over ``descriptors`` (ids = rows)
=======================  ============  =====================================================

Why packed: a sub-map set loads parts while the camera moves (``engine/submaps.py``), on a
loader thread beside the frames, and a part's load was mostly Python work around its 20 .npy
files: of the CPU of 144 loads of the 24-room scale bench's parts (cProfile), opening,
parsing and mapping the .npy files took 48%, parsing the whole map's 24 cameras each part
holds 16%, the median depth and the per-image poses 15%; and each file's syscalls are points
where the loader gives the GIL to the frame thread and waits for it back. A packed part is
one manifest and one ``mmap``, the per-image tables written by the builder, the cameras
parsed on first use: a part load's CPU p50 6.3-6.8 ms -> 1.4-1.8 ms, wall 21-25 -> 6.1-6.4 ms
(the same 72 parts three times, alternating runs, nice 19, load 11-12). Version-1 bundles
(one .npy per array) are still read, and still what ``sfmloc build`` writes (a whole map
loads once).

Writing is atomic: everything goes to a hidden temporary folder next to the target, is
flushed to disk, and is then swapped into place (an atomic directory exchange where the OS has
one), so a failed or cancelled build leaves nothing behind and an existing bundle of the same
name stays intact until the new one is complete.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import functools
import hashlib
import json
import mmap
import os
import re
import shutil
import stat
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from sfmloc_client.keys import check_name

from .. import __version__
from ..cameras import Camera
from ..errors import BundleError
from ..features.daisy import RAW_DIM, Pca
from ..transforms import Rigid3d
from .index import DescriptorIndex
from .keypoint_scales import coarsest_focal_px, keypoint_scales, pyramid_level_scales

BUNDLE_FORMAT = "sfmloc-map-bundle"
BUNDLE_VERSION = 1  # one .npy file per array
PACKED_VERSION = 2  # every array in one file (PACKED_FILE), each at a page boundary
SUPPORTED_VERSIONS = (BUNDLE_VERSION, PACKED_VERSION)
PACKED_FILE = "arrays.bin"
PACKED_ALIGN = 4096  # mapped arrays start on their own page (resident pages are per array)
MANIFEST = "manifest.json"
MANIFEST_SHA256 = "manifest.sha256"
MAX_MANIFEST_BYTES = 64 << 20  # image names and cameras of a very large map fit many times over
_ARRAY_FILE_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}\.(npy|bin)")

# name -> (dtype, number of dimensions); shapes are checked against the counts on load.
ARRAY_SPECS: dict[str, tuple[str, int]] = {
    "points_xyz": ("<f8", 2),
    "point_ids": ("<i8", 1),
    "point_rgb": ("|u1", 2),
    "descriptors": ("<f2", 2),
    "desc_point": ("<i4", 1),
    "desc_image": ("<i4", 1),
    "desc_level": ("|u1", 1),
    "desc_xy": ("<f4", 2),
    "image_desc_ptr": ("<i8", 1),
    "image_cam_from_world": ("<f8", 2),
    "image_camera": ("<i4", 1),
    "image_points_ptr": ("<i8", 1),
    "image_points_idx": ("<i4", 1),
    "cluster_images_ptr": ("<i8", 1),
    "cluster_images_idx": ("<i4", 1),
    "point_clusters_ptr": ("<i8", 1),
    "point_clusters_idx": ("<i4", 1),
    "pca_mean": ("<f4", 1),
    "pca_basis": ("<f4", 2),
    "index_faiss": ("|u1", 1),
}
# A packed bundle (PACKED_VERSION) also holds what loading derived per image in Python:
# ``image_rotations`` (I,3,3), the rotation of each ``image_cam_from_world`` quaternion.
PACKED_SPECS: dict[str, tuple[str, int]] = {**ARRAY_SPECS, "image_rotations": ("<f8", 3)}


def _level_scales_of(params: dict[str, Any]) -> list[float] | None:
    """The pyramid of ``desc_level`` from the builder parameters, None when not recorded."""
    d = params.get("descriptors") if isinstance(params, dict) else None
    return pyramid_level_scales(d) if isinstance(d, dict) else None


def _computed_keypoint_scales(data: MapData, params: dict[str, Any]) -> dict[str, Any]:
    return keypoint_scales(
        data.desc_image, data.desc_level, data.image_camera, data.cameras, _level_scales_of(params)
    )


def validate_name(name: str) -> str:
    """Map names appear in file paths and Zenoh key expressions: the one name rule
    (``sfmloc_client.keys``; ``WireError``, an ``InputError``, names it)."""
    return check_name(name, "map name")


class ArrayEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    file: str
    dtype: str
    shape: list[int]
    sha256: str
    bytes: int
    offset: int | None = None  # packed bundles: where the array starts in PACKED_FILE

    @field_validator("file")
    @classmethod
    def _plain_name(cls, v: str) -> str:
        # A path that leaves the bundle ('../../etc/passwd', '/abs', a folder) is refused before
        # anything is opened; the error repeats only what the manifest says.
        if not _ARRAY_FILE_RE.fullmatch(v):
            raise ValueError("must be a plain .npy file name inside the bundle folder")
        return v


class Counts(BaseModel):
    model_config = ConfigDict(extra="forbid")
    points: int
    descriptors: int
    images: int
    cameras: int
    clusters: int
    observations: int  # image -> point visibility entries


class Manifest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    format: str = BUNDLE_FORMAT
    version: int = BUNDLE_VERSION
    name: str
    build_id: str
    created_utc: str
    sfmloc_version: str = __version__
    source: dict[str, Any] = {}
    params: dict[str, Any] = {}
    timings_s: dict[str, float] = {}
    counts: Counts
    index: dict[str, Any] = {}
    # Points per image, track lengths, coverage, sparse-map warnings (``map.report``).
    report: dict[str, Any] = {}
    cameras: list[dict[str, Any]]
    image_names: list[str]
    arrays: dict[str, ArrayEntry]
    # Focal lengths (px) the descriptors were computed at (``keypoint_scales``); absent in
    # bundles written before it, which get it computed at load.
    keypoint_scales: dict[str, Any] = {}
    # Packed bundles: ``MapBundle.scene_scale`` (the median depth of every observation),
    # computed by the writer with the loader's own function (``median_depth``).
    scene_scale: float | None = None


@dataclass
class MapData:
    """Everything a bundle holds, in memory (what the builder assembles)."""

    points_xyz: np.ndarray
    point_ids: np.ndarray
    point_rgb: np.ndarray
    descriptors: np.ndarray
    desc_point: np.ndarray
    desc_image: np.ndarray
    desc_level: np.ndarray
    desc_xy: np.ndarray
    image_desc_ptr: np.ndarray
    image_cam_from_world: np.ndarray
    image_camera: np.ndarray
    image_points_ptr: np.ndarray
    image_points_idx: np.ndarray
    cluster_images_ptr: np.ndarray
    cluster_images_idx: np.ndarray
    point_clusters_ptr: np.ndarray
    point_clusters_idx: np.ndarray
    pca_mean: np.ndarray
    pca_basis: np.ndarray
    index_faiss: np.ndarray
    cameras: list[Camera] = field(default_factory=list)
    image_names: list[str] = field(default_factory=list)
    keypoint_scales: dict[str, Any] = field(default_factory=dict)

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in ARRAY_SPECS}

    def counts(self) -> Counts:
        return Counts(
            points=len(self.points_xyz),
            descriptors=len(self.descriptors),
            images=len(self.image_names),
            cameras=len(self.cameras),
            clusters=len(self.cluster_images_ptr) - 1,
            observations=len(self.image_points_idx),
        )


# numpy parses a .npy header with ast.literal_eval, and CPython 3.11's AST constructor keeps its
# recursion depth in state shared by all threads: two threads parsing at once can fail one of
# them with "SystemError: AST constructor recursion depth mismatch" (CPython gh-106905). A test
# server (thread workers, in the test process) then failed to load a map in a clean-clone
# `make test` (room2: "cannot load image_camera.npy"). Every .npy this package reads goes
# through load_npy, one at a time.
_NPY_LOCK = threading.Lock()


def load_npy(path: str | Path, mmap_mode: Any = None) -> np.ndarray:
    """``np.load`` of a .npy (never pickles), serialized across threads (see _NPY_LOCK)."""
    with _NPY_LOCK:
        return np.load(path, mmap_mode=mmap_mode, allow_pickle=False)


# ============================================================================ writing
def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_bundle(
    data: MapData,
    out_dir: str | Path,
    name: str,
    *,
    source: dict[str, Any] | None = None,
    params: dict[str, Any] | None = None,
    timings_s: dict[str, float] | None = None,
    index_info: dict[str, Any] | None = None,
    report: dict[str, Any] | None = None,
    packed: bool = False,
) -> Path:
    """Write ``data`` as ``out_dir/name`` atomically and return the bundle's path.

    ``timings_s`` (seconds per build stage) is recorded in the manifest with the write stage
    added here, once the arrays are on disk: "write" (and "total", when given, grows by it).
    ``packed``: one file of arrays and the derived tables (format version 2, module doc)."""
    t_write = time.perf_counter()
    validate_name(name)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    final = out_dir / name
    # A full disk is named up front rather than discovered half-way.
    needed = sum(np.asarray(getattr(data, a)).nbytes for a in ARRAY_SPECS) + (1 << 20)
    free = shutil.disk_usage(out_dir).free
    if free < needed:
        raise OSError(
            errno.ENOSPC,
            f"No space left on device: the bundle needs {needed / 1e6:.1f} MB, {free / 1e6:.1f} MB "
            "free",
            str(out_dir),
        )
    tmp = out_dir / f".{name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        entries: dict[str, ArrayEntry] = {}
        scene_scale: float | None = None
        if packed:
            entries, scene_scale = _write_packed(tmp / PACKED_FILE, data)
        for aname, (dtype, ndim) in ({} if packed else ARRAY_SPECS).items():
            arr = np.ascontiguousarray(getattr(data, aname), dtype=np.dtype(dtype))
            if arr.ndim != ndim:
                raise BundleError(
                    f"array {aname} must have {ndim} dimensions, has shape {arr.shape}"
                )
            path = tmp / f"{aname}.npy"
            try:
                with open(path, "wb") as f:
                    np.save(f, arr, allow_pickle=False)
                    f.flush()
                    os.fsync(f.fileno())
            except OSError as exc:
                if exc.errno is None and "requested and" in str(exc):
                    # numpy reports a short write without an errno: the disk filled up.
                    raise OSError(
                        errno.ENOSPC, f"No space left on device ({exc})", str(path)
                    ) from None
                raise
            entries[aname] = ArrayEntry(
                file=path.name,
                dtype=arr.dtype.str,
                shape=list(arr.shape),
                sha256=_sha256(path),
                bytes=path.stat().st_size,
            )
        timings = dict(timings_s or {})
        if timings:
            # What is left to write (the manifest and its checksum) is a few kB.
            spent = time.perf_counter() - t_write
            timings["write"] = timings.get("write", 0.0) + spent
            if "total" in timings:
                timings["total"] += spent
        manifest = Manifest(
            name=name,
            build_id=time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + uuid.uuid4().hex[:8],
            created_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            source=source or {},
            params=params or {},
            timings_s=timings,
            counts=data.counts(),
            index=index_info or {},
            report=report or {},
            cameras=[c.to_dict() for c in data.cameras],
            image_names=list(data.image_names),
            arrays=entries,
            keypoint_scales=data.keypoint_scales or _computed_keypoint_scales(data, params or {}),
            version=PACKED_VERSION if packed else BUNDLE_VERSION,
            scene_scale=scene_scale,
        )
        publish(tmp, final, manifest, MANIFEST, MANIFEST_SHA256)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def _poses(quat_t: np.ndarray) -> list[Rigid3d]:
    """``image_cam_from_world`` rows (qw qx qy qz tx ty tz) as poses."""
    return [Rigid3d.from_quat_wxyz(r[:4], r[4:]) for r in quat_t]


def median_depth(
    points_xyz: np.ndarray,
    image_points_ptr: np.ndarray,
    image_points_idx: np.ndarray,
    cam_from_world: list[Rigid3d],
) -> float:
    """The scene's scale: median depth of every observed point in the camera that sees it
    (map units; 1 when nothing is in front of a camera). Thresholds that must mean the same
    in a 0.2-unit object scan and a 500-unit street (wrong-pose limits, motion tolerances)
    are fractions of it. The writer of a packed bundle stores it (the same function on the
    same arrays: the same number), so that loading one runs no loop over its images."""
    depths = []
    for i, cfw in enumerate(cam_from_world):
        idx = image_points_idx[image_points_ptr[i] : image_points_ptr[i + 1]]
        if len(idx):
            X = points_xyz[idx]
            depths.append(X @ cfw.rotation[2] + cfw.translation[2])
    d = np.concatenate(depths) if depths else np.zeros(0)
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if len(d) else 1.0


def _write_packed(path: Path, data: MapData) -> tuple[dict[str, ArrayEntry], float]:
    """Every array of ``data`` (and the derived ``image_rotations``) into the one file of a
    packed bundle, each at a ``PACKED_ALIGN`` boundary; their manifest entries and the scene
    scale."""
    q = np.asarray(data.image_cam_from_world, np.float64)
    poses = _poses(q)
    arrays = data.arrays()
    arrays["image_rotations"] = (
        np.stack([T.rotation for T in poses]) if poses else np.zeros((0, 3, 3))
    )
    scale = median_depth(
        np.asarray(data.points_xyz, np.float64),
        np.asarray(data.image_points_ptr),
        np.asarray(data.image_points_idx),
        poses,
    )
    entries: dict[str, ArrayEntry] = {}
    off = 0
    with open(path, "wb") as f:
        for aname, (dtype, ndim) in PACKED_SPECS.items():
            arr = np.ascontiguousarray(arrays[aname], dtype=np.dtype(dtype))
            if arr.ndim != ndim:
                raise BundleError(
                    f"array {aname} must have {ndim} dimensions, has shape {arr.shape}"
                )
            pad = -off % PACKED_ALIGN
            f.write(b"\0" * pad)
            off += pad
            raw = arr.tobytes()
            f.write(raw)
            entries[aname] = ArrayEntry(
                file=PACKED_FILE,
                dtype=arr.dtype.str,
                shape=list(arr.shape),
                sha256=hashlib.sha256(raw).hexdigest(),
                bytes=len(raw),
                offset=off,
            )
            off += len(raw)
        f.flush()
        os.fsync(f.fileno())
    return entries, scale


_RENAME_EXCHANGE = 2


def publish(tmp: Path, final: Path, manifest: BaseModel, name: str, sha_name: str) -> None:
    """Finish a folder written in ``tmp``: its manifest as ``name`` and the manifest's checksum
    as ``sha_name`` (``sha256sum -c`` format), everything on disk, then ``tmp`` swapped into
    ``final`` (bundles and sub-map sets)."""
    # exclude_none: fields that are None (an array's ``offset`` outside packed bundles) are
    # left out, so that a version-1 bundle's manifest is what readers before them accept.
    text = manifest.model_dump_json(indent=2, exclude_none=True).encode()
    for fname, content in (
        (name, text),
        (sha_name, f"{hashlib.sha256(text).hexdigest()}  {name}\n".encode()),
    ):
        with open(tmp / fname, "wb") as f:
            f.write(content)
            f.flush()
            os.fsync(f.fileno())
    _fsync_dir(tmp)
    swap_into_place(tmp, final)


def swap_into_place(tmp: Path, final: Path) -> None:
    """Move ``tmp`` to ``final``; an existing ``final`` is replaced in one atomic exchange
    (Linux ``renameat2(RENAME_EXCHANGE)``) or, where that is unavailable, by two renames."""
    if not final.exists():
        os.rename(tmp, final)
        _fsync_dir(final.parent)
        return
    if _rename_exchange(tmp, final):
        shutil.rmtree(tmp, ignore_errors=True)  # now holds the old bundle
        _fsync_dir(final.parent)
        return
    old = final.parent / f".{final.name}.old-{uuid.uuid4().hex[:8]}"
    os.rename(final, old)
    os.rename(tmp, final)
    shutil.rmtree(old, ignore_errors=True)
    _fsync_dir(final.parent)


def _rename_exchange(a: Path, b: Path) -> bool:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    AT_FDCWD = -100
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    rc = fn(AT_FDCWD, os.fsencode(a), AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    return rc == 0


# ============================================================================ reading
def _read_small_file(path: Path, limit: int) -> bytes:
    """A regular file of the bundle (not a symlink, device or FIFO), at most ``limit`` bytes."""
    try:
        st = path.lstat()
    except OSError:
        raise BundleError(f"{path.parent} is not a map bundle: {path.name} is missing") from None
    if not stat.S_ISREG(st.st_mode):
        raise BundleError(f"{path}: not a regular file (symlinks and devices are refused)")
    if st.st_size > limit:
        raise BundleError(f"{path}: {st.st_size} B, larger than the {limit} B allowed")
    try:
        with open(path, "rb") as f:
            return f.read(limit + 1)
    except OSError as exc:
        raise BundleError(f"{path}: unreadable ({exc.strerror})") from None


def read_manifest(path: str | Path) -> Manifest:
    """The bundle's manifest, after checking it against ``manifest.sha256``."""
    path = Path(path)
    mpath = path / MANIFEST
    if not path.is_dir():
        raise BundleError(f"no map bundle at {path}: not a folder")
    if not mpath.exists() and not mpath.is_symlink():
        raise BundleError(f"{path} is not a map bundle: {MANIFEST} is missing")
    text = _read_small_file(mpath, MAX_MANIFEST_BYTES)
    if not (path / MANIFEST_SHA256).exists() and not (path / MANIFEST_SHA256).is_symlink():
        raise BundleError(
            f"{path}: {MANIFEST_SHA256} is missing, so the manifest cannot be checked "
            "(bundles written before the manifest was checksummed have none: rebuild the map, "
            f"or for a bundle you trust run 'sha256sum {MANIFEST} > {MANIFEST_SHA256}' inside it)"
        )
    expect = _read_small_file(path / MANIFEST_SHA256, 4096).decode("ascii", "replace").split()
    if len(expect) != 2 or expect[1] != MANIFEST:
        raise BundleError(f"{path / MANIFEST_SHA256}: not a checksum line for {MANIFEST}")
    if hashlib.sha256(text).hexdigest() != expect[0].lower():
        raise BundleError(f"{mpath}: checksum mismatch (the manifest was edited or is corrupt)")
    try:
        raw = json.loads(text.decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BundleError(f"{mpath}: unreadable manifest ({exc})") from None
    if not isinstance(raw, dict):
        raise BundleError(f"{mpath}: unreadable manifest (not a JSON object)")
    if raw.get("format") != BUNDLE_FORMAT:
        raise BundleError(f"{mpath}: not an sfmloc map bundle (format {raw.get('format')!r})")
    if raw.get("version") not in SUPPORTED_VERSIONS:
        raise BundleError(
            f"{mpath}: bundle version {raw.get('version')} is not supported by sfmloc "
            f"{__version__} "
            f"(expects version {' or '.join(map(str, SUPPORTED_VERSIONS))}); rebuild the map"
        )
    try:
        m = Manifest.model_validate(raw)
    except ValidationError as exc:
        raise BundleError(f"{mpath}: invalid manifest:\n{exc}") from None
    packed = m.version == PACKED_VERSION
    for aname, e in m.arrays.items():
        if packed != (e.offset is not None) or (packed and e.file != PACKED_FILE):
            raise BundleError(
                f"{mpath}: array {aname} is not where a version-{m.version} bundle keeps it "
                f"({e.file}, offset {e.offset})"
            )
    return m


def _packed_problems(path: Path, manifest: Manifest, checksums: bool) -> list[str]:
    """``verify_bundle`` of a packed bundle: every array's entry against its spec and the
    file, and its bytes against their SHA-256 (``checksums``)."""
    bpath = path / PACKED_FILE
    try:
        st = bpath.lstat()
    except OSError:
        return [f"{PACKED_FILE}: missing"]
    if not stat.S_ISREG(st.st_mode):
        return [f"{PACKED_FILE}: not a regular file (symlinks and devices are refused)"]
    problems = []
    with open(bpath, "rb") as f:
        for aname in PACKED_SPECS:
            e = manifest.arrays.get(aname)
            if e is None:
                problems.append(f"array {aname} is not in the manifest")
                continue
            problem = _packed_entry_problem(aname, e, st.st_size)
            if problem is not None:
                problems.append(problem)
            elif checksums:
                assert e.offset is not None  # checked by _packed_entry_problem
                f.seek(e.offset)
                if hashlib.sha256(f.read(e.bytes)).hexdigest() != e.sha256:
                    problems.append(f"{PACKED_FILE}: {aname} checksum mismatch (corrupt)")
    return problems


def _packed_entry_problem(aname: str, e: ArrayEntry, file_size: int) -> str | None:
    """What is wrong with packed array ``aname``'s manifest entry ``e`` against its spec and a
    file of ``file_size`` bytes (None: it fits)."""
    dtype, ndim = PACKED_SPECS[aname]
    dt = np.dtype(dtype)
    n = int(np.prod(e.shape)) if e.shape else 1
    off = e.offset if e.offset is not None else -1
    if e.dtype != dt.str or len(e.shape) != ndim or min(e.shape, default=0) < 0:
        return f"{aname}: dtype/shape {e.dtype}{e.shape} do not match"
    if e.bytes != n * dt.itemsize or off < 0 or off % PACKED_ALIGN:
        return f"{aname}: {e.bytes} B at offset {off} do not match its shape"
    if off + e.bytes > file_size:
        return f"{PACKED_FILE}: {aname} ends at {off + e.bytes} B, the file has {file_size} B"
    return None


def _map_packed(path: Path, manifest: Manifest) -> tuple[dict[str, np.ndarray], mmap.mmap]:
    """The arrays of a packed bundle: views into one read-only map of its file (one open and
    one ``mmap``: what a sub-map's load costs in syscalls, each a point where a loader thread
    hands the GIL to the frame thread). Shapes and offsets are checked against the file."""
    bpath = path / PACKED_FILE
    try:
        if not stat.S_ISREG(bpath.lstat().st_mode):
            raise BundleError(f"map bundle {path}: {PACKED_FILE} is not a regular file")
        with open(bpath, "rb") as f:
            mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError) as exc:
        raise BundleError(f"map bundle {path}: cannot map {PACKED_FILE} ({exc})") from None
    a: dict[str, np.ndarray] = {}
    for aname, (dtype, _) in PACKED_SPECS.items():
        e = manifest.arrays.get(aname)
        if e is None:
            raise BundleError(f"map bundle {path}: array {aname} missing from the manifest")
        problem = _packed_entry_problem(aname, e, len(mm))
        if problem is not None:
            raise BundleError(
                f"map bundle {path}: {aname} does not fit its spec or {PACKED_FILE} ({problem})"
            )
        dt = np.dtype(dtype)
        n = int(np.prod(e.shape)) if e.shape else 1
        off = e.offset
        assert off is not None  # checked by _packed_entry_problem
        if n:
            a[aname] = np.frombuffer(mm, dt, count=n, offset=off).reshape(e.shape)
        else:
            a[aname] = np.zeros(e.shape, dt)
    return a, mm


def load_array(path: str | Path, manifest: Manifest, name: str) -> np.ndarray:
    """One array of the bundle at ``path`` (either layout), read into memory."""
    path = Path(path)
    e = manifest.arrays[name]
    if e.offset is None:
        return load_npy(path / e.file)
    dt = np.dtype(e.dtype)
    n = e.bytes // dt.itemsize
    with open(path / e.file, "rb") as f:
        f.seek(e.offset)
        raw = f.read(e.bytes)
    if len(raw) != e.bytes or n != (int(np.prod(e.shape)) if e.shape else 1):
        raise BundleError(f"map bundle {path}: {name} is shorter than its manifest says")
    return np.frombuffer(raw, dt).reshape(e.shape).copy()


def verify_bundle(path: str | Path, checksums: bool = True) -> list[str]:
    """Every problem found in the bundle at ``path`` (empty when it is intact)."""
    path = Path(path)
    try:
        manifest = read_manifest(path)
    except BundleError as exc:
        return [str(exc)]
    if manifest.version == PACKED_VERSION:
        return _packed_problems(path, manifest, checksums)
    problems = []
    for aname, (dtype, ndim) in ARRAY_SPECS.items():
        entry = manifest.arrays.get(aname)
        if entry is None:
            problems.append(f"array {aname} is not in the manifest")
            continue
        apath = path / entry.file
        try:
            st = apath.lstat()
        except OSError:
            problems.append(f"{apath.name}: missing")
            continue
        if not stat.S_ISREG(st.st_mode):
            problems.append(f"{apath.name}: not a regular file (symlinks and devices are refused)")
            continue
        if st.st_size != entry.bytes:
            problems.append(f"{apath.name}: size {st.st_size} B, manifest says {entry.bytes} B")
            continue
        if checksums and _sha256(apath) != entry.sha256:
            problems.append(f"{apath.name}: checksum mismatch (corrupt)")
            continue
        try:
            arr = load_npy(apath, mmap_mode="r")
        except Exception as exc:  # noqa: BLE001 - any failure to parse the .npy is corruption
            problems.append(f"{apath.name}: unreadable .npy ({exc})")
            continue
        if (
            arr.dtype.str != np.dtype(dtype).str
            or list(arr.shape) != entry.shape
            or arr.ndim != ndim
        ):
            problems.append(
                f"{apath.name}: dtype/shape {arr.dtype.str}{list(arr.shape)} do not match the "
                "manifest"
            )
    return problems


class MapBundle:
    """A loaded bundle: memory-mapped arrays, the PCA, the ANN index (read in place from its
    memory-mapped file), and the lookups the engine needs. Read-only and safe to share between
    threads."""

    def __init__(self, path: str | Path, *, verify: bool = True, nprobe: int | None = None) -> None:
        self.path = Path(path)
        self.manifest = read_manifest(self.path)
        if verify:
            problems = verify_bundle(self.path, checksums=True)
            if problems:
                raise BundleError(f"map bundle {self.path} is corrupt: " + "; ".join(problems))
        a: dict[str, np.ndarray] = {}
        self._packed: mmap.mmap | None = None
        if self.manifest.version == PACKED_VERSION:
            a, self._packed = _map_packed(self.path, self.manifest)
        for aname in () if self._packed is not None else ARRAY_SPECS:
            entry = self.manifest.arrays.get(aname)
            if entry is None:
                raise BundleError(
                    f"map bundle {self.path}: array {aname} missing from the manifest"
                )
            apath = self.path / entry.file
            if apath.is_symlink() or not apath.is_file():
                raise BundleError(
                    f"map bundle {self.path}: {entry.file} is missing or not a regular file"
                )
            try:
                a[aname] = load_npy(apath, mmap_mode="r")
            except Exception as exc:  # noqa: BLE001
                raise BundleError(
                    f"map bundle {self.path}: cannot load {entry.file} ({exc})"
                ) from None
        self._a = a
        self.name = self.manifest.name
        self.build_id = self.manifest.build_id
        self.image_names = list(self.manifest.image_names)
        self._check_consistency()
        self.points_xyz = np.asarray(a["points_xyz"])
        self.desc_point = np.asarray(a["desc_point"])
        self.desc_image = np.asarray(a["desc_image"])
        self.image_desc_ptr = np.asarray(a["image_desc_ptr"])
        self.image_points_ptr = np.asarray(a["image_points_ptr"])
        self.image_points_idx = np.asarray(a["image_points_idx"])
        self.cluster_images_ptr = np.asarray(a["cluster_images_ptr"])
        self.cluster_images_idx = np.asarray(a["cluster_images_idx"])
        self.point_clusters_ptr = np.asarray(a["point_clusters_ptr"])
        self.point_clusters_idx = np.asarray(a["point_clusters_idx"])
        self.image_camera = np.asarray(a["image_camera"])
        self.pca = Pca(np.array(a["pca_mean"]), np.array(a["pca_basis"]))
        try:
            # Read in place from the memory-mapped file: every process loading this bundle
            # shares one copy of the index (the page cache), not one each.
            self.index = DescriptorIndex.from_buffer(
                a["index_faiss"], nprobe or int(self.manifest.index.get("nprobe", 16))
            )
        except Exception as exc:  # noqa: BLE001 - faiss raises RuntimeError on garbage
            raise BundleError(
                f"map bundle {self.path}: the ANN index does not load ({exc})"
            ) from None
        if self.index.ntotal != len(self.desc_point):
            raise BundleError(
                f"map bundle {self.path}: index holds {self.index.ntotal} descriptors, bundle has "
                f"{len(self.desc_point)}"
            )
        # The inverse of image_points, built once here (O(observations)) so that the bundle stays
        # read-only and safe to share between threads.
        counts = np.diff(self.image_points_ptr)
        owner = np.repeat(np.arange(self.n_images, dtype=np.int32), counts)
        order = np.argsort(self.image_points_idx, kind="stable")
        ptr = np.zeros(self.n_points + 1, np.int64)
        np.add.at(ptr, np.asarray(self.image_points_idx, np.int64) + 1, 1)
        self._point_images = (np.cumsum(ptr), owner[order])
        q = np.asarray(a["image_cam_from_world"])
        if "image_rotations" in a:  # packed: the writer's rotations of the same quaternions
            R, t = np.array(a["image_rotations"]), np.array(q[:, 4:])
            self.image_cam_from_world = [Rigid3d(R[i], t[i]) for i in range(len(R))]
        else:
            self.image_cam_from_world = _poses(q)
        if self.manifest.scene_scale is not None:
            self.scene_scale = float(self.manifest.scene_scale)
        else:
            self.scene_scale = self._median_depth()
        self.keypoint_scales = dict(self.manifest.keypoint_scales) or keypoint_scales(
            np.asarray(a["desc_image"]),
            np.asarray(a["desc_level"]),
            self.image_camera,
            self.cameras,
            _level_scales_of(self.manifest.params),
        )
        try:
            self.native_focal_px = float(self.keypoint_scales.get("native_focal_px", float("nan")))
        except (TypeError, ValueError):
            self.native_focal_px = float("nan")
        if not np.isfinite(self.native_focal_px) or self.native_focal_px <= 0:
            raise BundleError(
                f"map bundle {self.path}: keypoint_scales.native_focal_px must be a positive "
                "number of "
                f"pixels, got {self.keypoint_scales.get('native_focal_px')!r}"
            )
        self.coarsest_focal_px = coarsest_focal_px(self.keypoint_scales)

    def _median_depth(self) -> float:
        """The scene's scale (``median_depth``; stored in a packed bundle's manifest)."""
        return median_depth(
            self.points_xyz,
            self.image_points_ptr,
            self.image_points_idx,
            self.image_cam_from_world,
        )

    @functools.cached_property
    def cameras(self) -> list[Camera]:
        """The manifest's cameras, parsed on first use: not at load (a sub-map part holds the
        whole map's cameras, and checking 24 of them was 16% of a part load's CPU), and the
        engine reads them only from the keypoint scales of bundles that lack them."""
        return [Camera.from_dict(c) for c in self.manifest.cameras]

    # ------------------------------------------------------------------ accessors
    def array(self, name: str) -> np.ndarray:
        return self._a[name]

    def mappings(self) -> list[Any]:
        """The memory maps (``mmap.mmap``) of its array files. A map stays mapped, and its
        touched pages resident, while anything holds a view of it, the bundle or not: a
        weak reference to each tells when the kernel has let the bundle's pages go
        (``engine.submaps.PartCache`` counts a part until then)."""
        if self._packed is not None:
            return [self._packed]  # every array is a view of it
        out: list[Any] = []
        for arr in self._a.values():
            m = getattr(arr, "_mmap", None)  # np.load(mmap_mode=...) gives an np.memmap
            if isinstance(m, mmap.mmap) and all(m is not o for o in out):
                out.append(m)
        return out

    @property
    def n_points(self) -> int:
        return len(self.points_xyz)

    @property
    def n_descriptors(self) -> int:
        return len(self.desc_point)

    @property
    def n_images(self) -> int:
        return len(self.image_names)

    @property
    def n_clusters(self) -> int:
        return len(self.cluster_images_ptr) - 1

    def image_points(self, i: int) -> np.ndarray:
        return self.image_points_idx[self.image_points_ptr[i] : self.image_points_ptr[i + 1]]

    def point_images(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR (ptr, idx): for each point, the images that see it (inverse of image_points)."""
        return self._point_images

    def cluster_images(self, c: int) -> np.ndarray:
        return self.cluster_images_idx[self.cluster_images_ptr[c] : self.cluster_images_ptr[c + 1]]

    def point_clusters(self, p: int) -> np.ndarray:
        return self.point_clusters_idx[self.point_clusters_ptr[p] : self.point_clusters_ptr[p + 1]]

    def memory_bytes(self) -> int:
        """Bytes of the arrays the engine touches plus the index (what stays resident)."""
        skip = {"index_faiss", "descriptors"}  # the index holds its own copy of both
        return (
            sum(int(v.nbytes) for k, v in self._a.items() if k not in skip)
            + self.index.memory_bytes()
        )

    def report(self) -> dict[str, Any]:
        """The map report written by the builder (computed now for bundles built before it)."""
        if self.manifest.report:
            return self.manifest.report
        from .report import map_report

        return map_report(
            self.points_xyz,
            self.image_points_ptr,
            self.image_points_idx,
            self.cameras,
            self.image_camera,
            self.image_cam_from_world,
        )

    def summary(self) -> dict[str, Any]:
        c = self.manifest.counts
        return {
            "name": self.name,
            "path": str(self.path),
            "build_id": self.build_id,
            "created_utc": self.manifest.created_utc,
            "points": c.points,
            "descriptors": c.descriptors,
            "descriptors_per_point": round(c.descriptors / max(1, c.points), 2),
            "images": c.images,
            "cameras": c.cameras,
            "clusters": c.clusters,
            "observations": c.observations,
            "index": {
                "kind": self.index.kind,
                "nlist": self.index.nlist,
                "nprobe": self.index.nprobe,
            },
            "memory_mb": round(self.memory_bytes() / 1e6, 1),
            "disk_mb": round(sum(e.bytes for e in self.manifest.arrays.values()) / 1e6, 1),
            "source": self.manifest.source,
            "params": self.manifest.params,
            "timings_s": self.manifest.timings_s,
            "report": self.manifest.report,  # as built; ``report()`` fills it for older bundles
        }

    def _check_consistency(self) -> None:
        a, c = self._a, self.manifest.counts
        P, D, I, L = c.points, c.descriptors, c.images, c.clusters
        expect = {
            "points_xyz": (P, 3),
            "point_ids": (P,),
            "point_rgb": (P, 3),
            "descriptors": (D, None),
            "desc_point": (D,),
            "desc_image": (D,),
            "desc_level": (D,),
            "desc_xy": (D, 2),
            "image_desc_ptr": (I + 1,),
            "image_cam_from_world": (I, 7),
            "image_camera": (I,),
            "image_points_ptr": (I + 1,),
            "cluster_images_ptr": (L + 1,),
            "point_clusters_ptr": (P + 1,),
            "pca_mean": (RAW_DIM,),
            "pca_basis": (RAW_DIM, None),
        }
        if "image_rotations" in a:
            expect["image_rotations"] = (I, 3, 3)
        for aname, shape in expect.items():
            got = a[aname].shape
            if len(got) != len(shape) or any(s is not None and s != g for s, g in zip(shape, got)):
                raise BundleError(
                    f"map bundle {self.path}: {aname} has shape {got}, expected {shape}"
                )
        if len(self.image_names) != I or len(self.manifest.cameras) != c.cameras:
            raise BundleError(
                f"map bundle {self.path}: manifest image/camera lists do not match its counts"
            )
        if a["descriptors"].shape[1] != a["pca_basis"].shape[1]:
            raise BundleError(f"map bundle {self.path}: descriptor and PCA dimensions differ")
        for ptr_name, idx_name, n_target in (
            ("image_points_ptr", "image_points_idx", P),
            ("cluster_images_ptr", "cluster_images_idx", I),
            ("point_clusters_ptr", "point_clusters_idx", L),
        ):
            ptr, idx = np.asarray(a[ptr_name]), np.asarray(a[idx_name])
            if ptr[0] != 0 or ptr[-1] != len(idx) or np.any(np.diff(ptr) < 0):
                raise BundleError(f"map bundle {self.path}: {ptr_name} is not a valid offset array")
            if len(idx) and (idx.min() < 0 or idx.max() >= n_target):
                raise BundleError(
                    f"map bundle {self.path}: {idx_name} refers outside 0..{n_target - 1}"
                )
        for name, n_target in (("desc_point", P), ("desc_image", I), ("image_camera", c.cameras)):
            v = np.asarray(a[name])
            if len(v) and (v.min() < 0 or v.max() >= n_target):
                raise BundleError(
                    f"map bundle {self.path}: {name} refers outside 0..{n_target - 1}"
                )
        ptr = np.asarray(a["image_desc_ptr"])
        if ptr[0] != 0 or ptr[-1] != D or np.any(np.diff(ptr) < 0):
            raise BundleError(f"map bundle {self.path}: image_desc_ptr is not a valid offset array")


def load_bundle(path: str | Path, verify: bool = True) -> MapBundle:
    return MapBundle(path, verify=verify)
