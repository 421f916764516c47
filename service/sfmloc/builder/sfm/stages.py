"""pycolmap's feature and matching stages: SIFT (OpenCV's in COLMAP's convention, or
pycolmap's), the database, pair matching and geometric verification."""

from __future__ import annotations

import logging
import math
import sqlite3
import threading
from collections.abc import Sequence
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from contextlib import closing
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap

from ...cameras import Camera
from ...errors import BuildError, ImageDecodeError
from .conf import SfmConf, num_threads
from .run import Reporter

log = logging.getLogger(__name__)


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
            "%d image(s) have no SIFT features (blank or textureless?): %s",
            len(empty),
            ", ".join(empty[:5]),
        )
    total = sum(counts.values())
    rep.report(
        "features", 1.0, f"{total} SIFT features, {total / max(1, len(names)):.0f} per image"
    )
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
        gray = cv2.resize(
            gray, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA
        )
    sift = cv2.SIFT.create(nfeatures=conf.max_features, contrastThreshold=conf.contrast_threshold)
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None or not kps:
        return np.zeros((0, 6), np.float32), np.zeros((0, 128), np.uint8)
    xy = (np.array([k.pt for k in kps], np.float64) + OPENCV_SIFT_OFFSET) / scale
    size = np.array([k.size for k in kps], np.float64) / (2.0 * scale)
    ang = -np.radians(
        [k.angle for k in kps]
    )  # OpenCV: degrees, counter-clockwise in a y-down image
    c, s = size * np.cos(ang), size * np.sin(ang)
    kp = np.stack([xy[:, 0], xy[:, 1], c, -s, s, c], axis=1).astype(np.float32)
    d = desc.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
    d = np.minimum(np.round(512.0 * np.sqrt(d)), 255).astype(np.uint8)
    return kp, d


def _read_gray(path: Path) -> np.ndarray:
    """The stored pixels, as COLMAP reads them: no EXIF rotation (OpenCV applies it by default)."""
    data = np.fromfile(str(path), dtype=np.uint8)
    img = (
        cv2.imdecode(data, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
        if data.size
        else None
    )
    if img is None:
        raise ImageDecodeError(f"[features] cannot decode image {path}")
    return img


def _extract_opencv(
    database_path: Path,
    image_dir: Path,
    names: Sequence[str],
    camera: pycolmap.Camera,
    conf: SfmConf,
    rep: Reporter,
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
            futures = [
                pool.submit(lambda nm: opencv_sift(_read_gray(image_dir / nm), conf), nm)
                for nm in names
            ]
            try:
                for i, (name, fut) in enumerate(zip(names, futures)):
                    kp, desc = fut.result()
                    image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
                    frame = pycolmap.Frame()
                    frame.rig_id = rig_id
                    frame.add_data_id(pycolmap.data_t(sensor_id=sensor, id=image_id))
                    db.write_frame(frame)
                    db.write_keypoints(image_id, kp)
                    db.write_descriptors(
                        image_id,
                        pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, desc),
                    )
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
    database_path: Path,
    image_dir: Path,
    names: Sequence[str],
    camera: pycolmap.Camera,
    conf: SfmConf,
    rep: Reporter,
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


# Pairs per concurrent matching block at least (not tuned): each block's calls load their
# images' features and build their FAISS indices themselves, so a few pairs stay in one.
MIN_PAIRS_PER_WORKER = 32


def match_pairs(
    database_path: Path,
    workdir: Path,
    pairs: Sequence[tuple[str, str]],
    conf: SfmConf,
    rep: Reporter,
) -> int:
    """Match and geometrically verify the given image pairs (by name); return the number of
    verified pairs.

    Reproducible whatever the thread count: every ``pycolmap.match_image_pairs`` call runs
    single-threaded (one matcher, one verifier, FAISS on one thread), so a pair's matches and
    two-view geometry depend on its two images and the seed alone (RANSAC is seeded per pair:
    the same pairs in reverse order give the same bytes). With ``num_threads`` > 1 the pairs
    are cut into contiguous blocks, each matched by its own single-threaded call into its own
    copy of the database, and the blocks' rows are copied back (``_merge_matches``): the same
    rows as one call over all pairs, at the multi-threaded wall time. Why not COLMAP's own
    threads: one of eleven ``make bench`` redkitchen builds (6c17bca, 15:16) verified 86,086
    instead of 86,097 inlier matches in the same 374 pairs and gave another map (README,
    Conventions, "Reproducible builds")."""
    n = len(pairs)
    if n == 0:
        raise BuildError("no image pairs to match (need at least two images)", stage="matching")
    workers = max(1, min(num_threads(conf), n // MIN_PAIRS_PER_WORKER))
    bounds = [round(w * n / workers) for w in range(workers + 1)]
    blocks = [list(pairs[bounds[w] : bounds[w + 1]]) for w in range(workers)]
    chunk = max(64, math.ceil(n / 10))  # pairs per call: progress and cancellation in between
    rep.report("matching", 0.0, f"matching {n} image pairs")
    if workers == 1:
        for start in range(0, n, chunk):
            part = pairs[start : start + chunk]
            _match_chunk(database_path, workdir, "0", start // chunk, part, conf, rep)
            done = min(n, start + chunk)
            rep.report("matching", done / n, f"matched {done}/{n} pairs")
    else:
        copies = [workdir / f"match-{w}.db" for w in range(workers)]
        try:
            _match_blocks(database_path, copies, blocks, workdir, chunk, conf, rep)
        finally:
            for path in copies:
                path.unlink(missing_ok=True)
    db = pycolmap.Database.open(database_path)
    try:
        verified = db.num_verified_image_pairs()
        inliers = db.num_inlier_matches()
    finally:
        db.close()
    rep.report("matching", 1.0, f"{verified}/{n} pairs verified, {inliers} inlier matches")
    if verified == 0:
        raise BuildError(
            f"no image pair passed geometric verification ({n} pairs tried): too little overlap or "
            "texture",
            stage="matching",
        )
    return verified


def _match_blocks(
    database_path: Path,
    copies: Sequence[Path],
    blocks: Sequence[Sequence[tuple[str, str]]],
    workdir: Path,
    chunk: int,
    conf: SfmConf,
    rep: Reporter,
) -> None:
    """``blocks[w]`` matched into ``copies[w]`` (a copy of ``database_path``) by concurrent
    single-threaded calls, then merged into ``database_path``."""
    n = sum(len(b) for b in blocks)
    for path in copies:
        _copy_database(database_path, path)
    done_pairs = [0] * len(blocks)
    stop = threading.Event()  # a block failed or the caller left: the others stop too

    def run_block(w: int) -> None:
        block = blocks[w]
        # Calls of equal size (132 pairs: 66 + 66, not 64 + 64 + 4): every call builds the
        # FAISS indices of its images anew.
        size = math.ceil(len(block) / math.ceil(len(block) / chunk))
        for start in range(0, len(block), size):
            if stop.is_set():
                return
            part = block[start : start + size]
            _match_chunk(copies[w], workdir, str(w), start // size, part, conf, rep)
            done_pairs[w] += len(part)

    with ThreadPoolExecutor(max_workers=len(blocks), thread_name_prefix="match") as pool:
        futures = [pool.submit(run_block, w) for w in range(len(blocks))]
        try:
            reported, pending = 0, set(futures)
            while pending and not stop.is_set():
                _, pending = wait(pending, timeout=0.2, return_when=FIRST_EXCEPTION)
                if any(f.done() and f.exception() is not None for f in futures):
                    stop.set()
                elif sum(done_pairs) != reported:
                    reported = sum(done_pairs)
                    rep.report("matching", reported / n, f"matched {reported}/{n} pairs")
        finally:
            stop.set()  # also on Ctrl-C: no new chunk starts; the pool waits for the running
    for f in futures:
        exc = f.exception()
        if exc is not None:
            raise exc
    _merge_matches(database_path, copies)


def _match_chunk(
    database_path: Path,
    workdir: Path,
    worker: str,
    k: int,
    part: Sequence[tuple[str, str]],
    conf: SfmConf,
    rep: Reporter,
) -> None:
    """One single-threaded ``pycolmap.match_image_pairs`` call over ``part``."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1  # see match_pairs: one thread per call, calls side by side
    matching.sift.max_ratio = conf.max_ratio
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = conf.min_num_inliers
    verification.ransac.random_seed = conf.seed
    pairs_file = workdir / f"pairs-{worker}-{k:03d}.txt"
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


def _copy_database(src: Path, dst: Path) -> None:
    """A consistent copy of a COLMAP database (WAL journal included: sqlite's backup)."""
    dst.unlink(missing_ok=True)
    with closing(sqlite3.connect(str(src))) as a, closing(sqlite3.connect(str(dst))) as b:
        a.backup(b)


def _merge_matches(database_path: Path, copies: Sequence[Path]) -> None:
    """The matches and two-view geometries of ``copies`` into ``database_path``: rows it lacks
    are added (pairs it had are in every copy, unchanged); both tables are keyed by pair id,
    so the result does not depend on the order of the copies."""
    with closing(sqlite3.connect(str(database_path))) as con:
        for path in copies:
            con.execute("ATTACH DATABASE ? AS part", (str(path),))
            for table in ("matches", "two_view_geometries"):
                con.execute(f"INSERT OR IGNORE INTO main.{table} SELECT * FROM part.{table}")
            con.commit()
            con.execute("DETACH DATABASE part")
