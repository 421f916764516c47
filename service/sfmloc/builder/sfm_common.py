"""Shared machinery of the SfM front-end: configuration, image listing and checking, the
pycolmap feature/matching stages, progress, cancellation and the work directory.

The three inputs (``sfm_colmap``, ``sfm_poses``, ``sfm_images``) build on this; ``sfm`` is the
public facade. pycolmap's own (glog) chatter is turned down to warnings while we run and our
messages go to the ``sfmloc.builder.sfm`` logger.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import tempfile
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import pycolmap
from pydantic import Field

from ..cameras import Camera
from ..config import StrictModel, merge_presets
from ..errors import BuildCancelled, BuildError, ConfigError, ImageDecodeError, InputError

log = logging.getLogger("sfmloc.builder.sfm")

Progress = Callable[[str, float, str], None]
CancelCheck = Callable[[], bool]

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")


# --------------------------------------------------------------------------- configuration
class SfmConf(StrictModel):
    """Parameters of the SfM front-end (known-poses triangulation and images-only SfM).

    Defaults were chosen on 100 redkitchen frames (every 10th of seq-01, 640x480) on a
    2-core machine (table above ``SFM_PRESETS``; module docstrings of ``sfm_poses`` and
    ``sfm_images``) and checked against exact geometry on synthetic scenes (the tests).
    """

    # SIFT (CPU): OpenCV's (~3x less CPU per image) or pycolmap's own, both into COLMAP's database
    sift_backend: Literal["opencv", "pycolmap"] = "opencv"
    max_features: int = Field(4000, ge=64, description="max SIFT features per image")
    first_octave: int = Field(
        -1, ge=-1, le=2, description="pycolmap: -1 upsamples 2x first: ~3x the features on VGA, ~3x slower"
    )
    peak_threshold: float = Field(0.02 / 3, gt=0, description="pycolmap SIFT DoG peak threshold (COLMAP default)")
    contrast_threshold: float = Field(0.015, gt=0, description="OpenCV SIFT contrastThreshold (OpenCV default 0.04)")
    max_image_size: int = Field(1600, ge=64, description="images larger than this are downscaled for SIFT")
    # matching
    max_ratio: float = Field(0.8, gt=0, le=1, description="Lowe ratio test")
    min_num_inliers: int = Field(15, ge=5, description="min verified matches per image pair")
    # pairs for known poses: k nearest cameras (centre distance) that look the same way
    pair_neighbors: int = Field(5, ge=0, description="known poses: nearest views matched per image")
    pair_sequential: int = Field(2, ge=0, description="known poses: also match this many next images in order")
    pair_max_angle_deg: float = Field(45.0, gt=0, le=180, description="known poses: max viewing-direction angle")
    # pairs for images only
    matching: Literal["sequential", "exhaustive"] = "sequential"
    sequential_overlap: int = Field(5, ge=1, description="images only: match each image with the next N")
    quadratic_overlap: bool = Field(True, description="images only: and with the next 2^k, k < overlap")
    # triangulation and point filtering
    min_track_length: int = Field(3, ge=2, description="drop points seen in fewer images")
    # Known poses: when the median image would see fewer points than this with tracks of
    # min_track_length, triangulate again keeping two-view tracks (the poses are given, so two
    # views fix a point). 0: never. Measured with ``python -m sfmloc.bench.sparse_maps`` (40
    # non-map frames relocalized, 300 replayed at 30 Hz): redkitchen every 60th frame, 158 ->
    # 320 points/image, 28/40 -> 35/40 relocalized, replay 65% -> 96%; every 30th, 312 -> 540,
    # 35/40 -> 39/40, median 0.70 -> 0.57 cm; no wrong relocalization either way. Every 10th
    # (the default map, 574 points/image) is left as it is.
    two_view_below: int = Field(
        400, ge=0, description="known poses: keep two-view points when the median image sees fewer"
    )
    max_reproj_error: float = Field(4.0, gt=0, description="px; COLMAP's filter_max_reproj_error")
    min_tri_angle_deg: float = Field(1.5, gt=0, description="deg; COLMAP's filter_min_tri_angle")
    # images only: intrinsics refinement when a camera is given (always refined otherwise)
    refine_given_intrinsics: bool = False
    global_ba_ratio: float = Field(
        1.4, ge=1.0, description="images only: global BA when the model grew by this factor (COLMAP 1.1)"
    )
    # execution
    num_threads: int = Field(-1, description="-1: all cores")
    seed: int = Field(0, ge=0, description="random seed of RANSAC and the mapper")
    check_images: bool = Field(True, description="decode every image first to name bad ones")
    keep_workdir: bool = False


# Known-poses path on 100 redkitchen frames (every 10th of seq-01, VGA), CPU seconds of the
# whole stage (wall time is about half on an idle 2-core machine):
#   default   OpenCV SIFT, contrast 0.015, k=5      ~21 CPU-s  ~11.0k points  0.71 px  track 5.5
#   fast      OpenCV SIFT, contrast 0.03, 2000, k=4 ~13 CPU-s   ~7.3k points  0.69 px  track 5.5
#   accurate  pycolmap SIFT, 8192 features, k=8     ~40 CPU-s  ~10.5k points  0.81 px  track 6.6
# (pycolmap SIFT with the default pairs: ~34 CPU-s, 10.2k points, 0.72 px.)
SFM_PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "fast": {"contrast_threshold": 0.03, "max_features": 2000, "pair_neighbors": 4},
    "accurate": {
        "sift_backend": "pycolmap",
        "max_features": 8192,
        "pair_neighbors": 8,
        "pair_sequential": 3,
        "sequential_overlap": 8,
    },
}


def sfm_conf(preset: str = "default", **overrides: Any) -> SfmConf:
    """A named preset merged over the defaults, then explicit overrides (hloc style)."""
    if preset not in SFM_PRESETS:
        raise ConfigError(f"unknown SfM preset {preset!r}; known: {', '.join(SFM_PRESETS)}")
    return merge_presets(SfmConf(), **{**SFM_PRESETS[preset], **overrides})


def num_threads(conf: SfmConf) -> int:
    return conf.num_threads if conf.num_threads > 0 else (os.cpu_count() or 1)


# --------------------------------------------------------------------------- progress / cancel
class Reporter:
    """Progress and cancellation for one run: ``report(stage, fraction, message)``, ``check(stage)``."""

    def __init__(self, progress: Progress | None, should_cancel: CancelCheck | None) -> None:
        self.progress = progress
        self.should_cancel = should_cancel

    def report(self, stage: str, fraction: float, message: str = "") -> None:
        if message:
            log.debug("[%s] %.0f%% %s", stage, 100 * fraction, message)
        if self.progress is not None:
            self.progress(stage, float(min(1.0, max(0.0, fraction))), message)

    def check(self, stage: str) -> None:
        if self.should_cancel is not None and self.should_cancel():
            raise BuildCancelled("cancelled", stage=stage)

    def run(self, stage: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """Call a pycolmap function that takes ``cancellation_token``; cancel it when asked.

        pycolmap releases the GIL, so the call runs in a worker thread while this one polls
        ``should_cancel``. Its failures become ``BuildError`` naming the stage.
        """
        self.check(stage)
        token = pycolmap.CancellationToken()
        out: dict[str, Any] = {}

        def target() -> None:
            try:
                out["value"] = fn(*args, cancellation_token=token, **kwargs)
            except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
                out["error"] = exc

        if self.should_cancel is None:
            target()
        else:
            th = threading.Thread(target=target, name=f"pycolmap-{stage}", daemon=True)
            th.start()
            try:
                while th.is_alive():
                    th.join(0.05)
                    if th.is_alive() and self.should_cancel():
                        raise BuildCancelled("cancelled", stage=stage)
            except BaseException:
                # Cancelled, Ctrl-C or a failing check: stop pycolmap before the work
                # directory it writes to is removed.
                token.cancel()
                th.join()
                raise
        exc = out.get("error")
        if exc is not None:
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise exc
            if isinstance(exc, InterruptedError) or token_cancelled(token):
                raise BuildCancelled("cancelled", stage=stage) from None
            name = getattr(fn, "__name__", "pycolmap")
            raise BuildError(f"pycolmap {name} failed: {exc}", stage=stage) from exc
        return out.get("value")


def token_cancelled(token: Any) -> bool:
    """Whether a pycolmap ``CancellationToken`` was cancelled: a method in some pycolmap
    releases, a property in others (4.2: calling it raised ``TypeError: 'bool' object is not
    callable`` and hid the stage's real error)."""
    flag = token.is_cancelled
    return bool(flag() if callable(flag) else flag)


@contextlib.contextmanager
def quiet_colmap() -> Iterator[None]:
    """Keep pycolmap's INFO log lines off stderr unless our logger is at DEBUG."""
    if log.isEnabledFor(logging.DEBUG):
        yield
        return
    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(before, 1)  # 0 INFO, 1 WARNING, 2 ERROR
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


@contextlib.contextmanager
def work_directory(parent: str | Path | None, keep: bool) -> Iterator[Path]:
    """A fresh directory (inside ``parent`` when given) for the database and intermediate
    files, removed afterwards, on success and failure, unless ``keep``."""
    if parent is not None:
        Path(parent).mkdir(parents=True, exist_ok=True)
    path = Path(tempfile.mkdtemp(prefix="sfmloc-sfm-", dir=None if parent is None else str(parent)))
    try:
        yield path
    finally:
        if keep:
            log.info("kept SfM work directory %s", path)
        else:
            shutil.rmtree(path, ignore_errors=True)


# --------------------------------------------------------------------------- images
def list_images(image_dir: str | Path) -> list[str]:
    """Image files under ``image_dir`` (recursive, hidden entries skipped) as sorted relative
    POSIX names, the way COLMAP names images."""
    root = Path(image_dir)
    if not root.is_dir():
        raise InputError(f"[input] image folder {root} does not exist or is not a folder")
    names = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for fn in filenames:
            if not fn.startswith(".") and fn.lower().endswith(IMAGE_EXTENSIONS):
                names.append((Path(dirpath) / fn).relative_to(root).as_posix())
    return sorted(names)


def select_images(names: list[str], image_names: Sequence[str] | None, stride: int, image_dir: Path) -> list[str]:
    """Restrict to ``image_names`` (relative names) when given, then keep every ``stride``-th."""
    if stride < 1:
        raise InputError(f"[input] stride must be >= 1, got {stride}")
    if image_names is not None:
        have = set(names)
        wanted = [str(n).replace("\\", "/") for n in image_names]
        missing = [n for n in wanted if n not in have]
        if missing:
            raise InputError(
                f"[input] {len(missing)} of the {len(wanted)} requested images are not in {image_dir}: "
                + ", ".join(missing[:5])
                + (" ..." if len(missing) > 5 else "")
            )
        names = wanted
    return names[::stride]


def check_names(names: Sequence[str], image_dir: Path) -> None:
    """COLMAP's pair lists are whitespace-separated: such names cannot be matched."""
    spaced = [n for n in names if any(c.isspace() for c in n)]
    if spaced:
        raise InputError(
            f"[input] {len(spaced)} image name(s) in {image_dir} contain whitespace, which COLMAP's pair "
            f"lists cannot hold, e.g. {spaced[0]!r}; rename them"
        )


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file as stored (no EXIF rotation, as COLMAP), decoding it;
    ``ImageDecodeError`` naming the file."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise ImageDecodeError(f"[input] cannot read image {path}: {exc.strerror or exc}") from None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise ImageDecodeError(f"[input] cannot decode image {path} (not an image, or corrupt)")
    return int(img.shape[1]), int(img.shape[0])


def check_images(
    image_dir: Path,
    names: Sequence[str],
    expected_size: Callable[[str], tuple[int, int] | None],
    conf: SfmConf,
    rep: Reporter,
    what: str = "the camera",
) -> dict[str, tuple[int, int]]:
    """Decode every image (threaded); raise ``ImageDecodeError`` naming the first unreadable
    one or the first whose size differs from ``expected_size(name)`` (None: no constraint)."""
    sizes: dict[str, tuple[int, int]] = {}
    if not conf.check_images:
        return sizes
    rep.report("input", 0.0, f"checking {len(names)} images in {image_dir}")
    with ThreadPoolExecutor(max_workers=num_threads(conf)) as pool:
        futures = [(n, pool.submit(image_size, image_dir / n)) for n in names]
        try:
            for i, (name, fut) in enumerate(futures):
                sizes[name] = fut.result()
                want = expected_size(name)
                if want is not None and sizes[name] != tuple(want):
                    w, h = sizes[name]
                    raise ImageDecodeError(
                        f"[input] image {image_dir / name} is {w}x{h} but {what} is {want[0]}x{want[1]}"
                    )
                if (i + 1) % 50 == 0:
                    rep.check("input")
                    rep.report("input", (i + 1) / len(names), f"checked {i + 1}/{len(names)} images")
        except BaseException:
            for _, f in futures:  # fail now, not after decoding the rest
                f.cancel()
            raise
    rep.report("input", 1.0, f"{len(names)} images readable")
    return sizes


# --------------------------------------------------------------------------- pycolmap stages
def to_pycolmap_camera(camera: Camera, camera_id: int | None = None) -> pycolmap.Camera:
    kw: dict[str, Any] = {
        "model": camera.model,
        "width": camera.width,
        "height": camera.height,
        "params": np.asarray(camera.params, dtype=np.float64),
    }
    if camera_id is not None:
        kw["camera_id"] = int(camera_id)
    return pycolmap.Camera(**kw)


def extract_features(
    database_path: Path,
    image_dir: Path,
    names: Sequence[str],
    camera: pycolmap.Camera,
    conf: SfmConf,
    rep: Reporter,
) -> dict[str, int]:
    """SIFT features of ``names`` into a new COLMAP database, all sharing ``camera``;
    returns name -> database image id. ``conf.sift_backend`` picks the extractor."""
    if conf.sift_backend == "opencv":
        ids = _extract_opencv(database_path, image_dir, names, camera, conf, rep)
    else:
        ids = _extract_pycolmap(database_path, image_dir, names, camera, conf, rep)
    db = pycolmap.Database.open(database_path)
    try:
        counts = {nm: db.num_keypoints_for_image(ids[nm]) for nm in names}
    finally:
        db.close()
    empty = [nm for nm, c in counts.items() if c == 0]
    if empty:
        log.warning(
            "%d image(s) have no SIFT features (blank or textureless?): %s", len(empty), ", ".join(empty[:5])
        )
    total = sum(counts.values())
    rep.report("features", 1.0, f"{total} SIFT features, {total / max(1, len(names)):.0f} per image")
    return ids


# OpenCV's SIFT upsamples the image 2x first and reports ``upsampled_index / 2``: in COLMAP's
# convention a keypoint is at ``pt + 0.25`` (not ``+ 0.5``); measured on Gaussian blobs at
# known positions, where pycolmap's SIFT is unbiased (tests/test_mapping_sfm.py).
OPENCV_SIFT_OFFSET = 0.25


def opencv_sift(gray: np.ndarray, conf: SfmConf) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV SIFT as COLMAP stores it: (N, 6) float32 keypoints ``x y a11 a12 a21 a22`` in
    COLMAP's pixel convention and (N, 128) uint8 RootSIFT descriptors (L1, sqrt, x512).
    Images larger than ``conf.max_image_size`` are downscaled first (coordinates are not)."""
    scale = 1.0
    h, w = gray.shape[:2]
    if max(h, w) > conf.max_image_size:
        scale = conf.max_image_size / max(h, w)
        gray = cv2.resize(gray, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    sift = cv2.SIFT_create(nfeatures=conf.max_features, contrastThreshold=conf.contrast_threshold)
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None or not kps:
        return np.zeros((0, 6), np.float32), np.zeros((0, 128), np.uint8)
    xy = (np.array([k.pt for k in kps], np.float64) + OPENCV_SIFT_OFFSET) / scale
    size = np.array([k.size for k in kps], np.float64) / (2.0 * scale)
    ang = -np.radians([k.angle for k in kps])  # OpenCV: degrees, counter-clockwise in a y-down image
    c, s = size * np.cos(ang), size * np.sin(ang)
    kp = np.stack([xy[:, 0], xy[:, 1], c, -s, s, c], axis=1).astype(np.float32)
    d = desc.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
    d = np.minimum(np.round(512.0 * np.sqrt(d)), 255).astype(np.uint8)
    return kp, d


def _read_gray(path: Path) -> np.ndarray:
    """The stored pixels, as COLMAP reads them: no EXIF rotation (OpenCV applies it by default)."""
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION) if data.size else None
    if img is None:
        raise ImageDecodeError(f"[features] cannot decode image {path}")
    return img


def _extract_opencv(
    database_path: Path, image_dir: Path, names: Sequence[str], camera: pycolmap.Camera, conf: SfmConf, rep: Reporter
) -> dict[str, int]:
    """OpenCV SIFT in a thread pool (it releases the GIL); the database is written here, in
    pycolmap 4's layout: one camera, its trivial rig, one frame per image."""
    n = len(names)
    rep.report("features", 0.0, f"SIFT (OpenCV) on {n} images")
    db = pycolmap.Database.open(database_path)
    ids: dict[str, int] = {}
    try:
        camera_id = db.write_camera(camera)
        sensor = pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=camera_id)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(sensor)
        rig_id = db.write_rig(rig)
        with ThreadPoolExecutor(max_workers=num_threads(conf)) as pool:
            futures = [pool.submit(lambda nm: opencv_sift(_read_gray(image_dir / nm), conf), nm) for nm in names]
            try:
                for i, (name, fut) in enumerate(zip(names, futures)):
                    kp, desc = fut.result()
                    image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
                    frame = pycolmap.Frame()
                    frame.rig_id = rig_id
                    frame.add_data_id(pycolmap.data_t(sensor_id=sensor, id=image_id))
                    db.write_frame(frame)
                    db.write_keypoints(image_id, kp)
                    db.write_descriptors(image_id, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, desc))
                    ids[name] = int(image_id)
                    rep.check("features")
                    if (i + 1) % 10 == 0 or i + 1 == n:
                        rep.report("features", (i + 1) / n, f"SIFT {i + 1}/{n} images")
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
    finally:
        db.close()
    return ids


def _extract_pycolmap(
    database_path: Path, image_dir: Path, names: Sequence[str], camera: pycolmap.Camera, conf: SfmConf, rep: Reporter
) -> dict[str, int]:
    """pycolmap's extractor, run in chunks so progress and cancellation happen per chunk; the
    camera is written first and reused by every chunk."""
    db = pycolmap.Database.open(database_path)
    try:
        camera_id = db.write_camera(camera)
    finally:
        db.close()
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = conf.num_threads
    opts.max_image_size = conf.max_image_size
    opts.sift.max_num_features = conf.max_features
    opts.sift.first_octave = conf.first_octave
    opts.sift.peak_threshold = conf.peak_threshold
    reader = pycolmap.ImageReaderOptions()
    reader.existing_camera_id = camera_id
    n = len(names)
    chunk = max(8 * num_threads(conf), math.ceil(n / 10))
    rep.report("features", 0.0, f"SIFT on {n} images")
    for start in range(0, n, chunk):
        part = list(names[start : start + chunk])
        rep.run(
            "features",
            pycolmap.extract_features,
            database_path,
            image_dir,
            image_names=part,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=opts,
        )
        done = min(n, start + chunk)
        rep.report("features", done / n, f"SIFT {done}/{n} images")
    db = pycolmap.Database.open(database_path)
    try:
        ids = {im.name: int(im.image_id) for im in db.read_all_images()}
        missing = [nm for nm in names if nm not in ids]
        if missing:
            raise ImageDecodeError(
                f"[features] pycolmap could not read {len(missing)} image(s) of {image_dir}: "
                + ", ".join(missing[:5])
                + (" ..." if len(missing) > 5 else "")
            )
    finally:
        db.close()
    return ids


def match_pairs(
    database_path: Path,
    workdir: Path,
    pairs: Sequence[tuple[str, str]],
    conf: SfmConf,
    rep: Reporter,
) -> int:
    """Match and geometrically verify the given image pairs (by name); return the number of
    verified pairs. Chunks of pairs go to ``pycolmap.match_image_pairs`` one after another."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = conf.num_threads
    matching.sift.max_ratio = conf.max_ratio
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = conf.min_num_inliers
    verification.ransac.random_seed = conf.seed
    n = len(pairs)
    if n == 0:
        raise BuildError("no image pairs to match (need at least two images)", stage="matching")
    chunk = max(64, math.ceil(n / 10))
    rep.report("matching", 0.0, f"matching {n} image pairs")
    for k, start in enumerate(range(0, n, chunk)):
        part = pairs[start : start + chunk]
        pairs_file = workdir / f"pairs-{k:03d}.txt"
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in part))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pairs_file)
        rep.run(
            "matching",
            pycolmap.match_image_pairs,
            database_path,
            matching_options=matching,
            pairing_options=pairing,
            verification_options=verification,
        )
        done = min(n, start + chunk)
        rep.report("matching", done / n, f"matched {done}/{n} pairs")
    db = pycolmap.Database.open(database_path)
    try:
        verified = db.num_verified_image_pairs()
        inliers = db.num_inlier_matches()
    finally:
        db.close()
    rep.report("matching", 1.0, f"{verified}/{n} pairs verified, {inliers} inlier matches")
    if verified == 0:
        raise BuildError(
            f"no image pair passed geometric verification ({n} pairs tried): too little overlap or texture",
            stage="matching",
        )
    return verified


def incremental_options(conf: SfmConf) -> pycolmap.IncrementalPipelineOptions:
    """Mapper/triangulator options with our filtering thresholds and thread count."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = conf.num_threads
    opts.random_seed = conf.seed
    opts.mapper.num_threads = conf.num_threads
    opts.mapper.random_seed = conf.seed
    opts.mapper.filter_max_reproj_error = conf.max_reproj_error
    opts.mapper.filter_min_tri_angle = conf.min_tri_angle_deg
    tri = opts.triangulation
    tri.random_seed = conf.seed
    tri.min_angle = conf.min_tri_angle_deg
    tri.complete_max_reproj_error = conf.max_reproj_error
    tri.merge_max_reproj_error = conf.max_reproj_error
    # Two-view tracks are only worth triangulating when we keep them.
    tri.ignore_two_view_tracks = conf.min_track_length > 2
    return opts
