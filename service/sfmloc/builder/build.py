"""The builder pipeline: an SfM reconstruction -> a map bundle (paper Section 2.3).

Stages, each reported through ``progress(stage, fraction, message)``:

``sfm``          the input: a COLMAP model, images + known poses (triangulated with pycolmap),
                 or images only (full SfM with pycolmap) -> a reconstruction
``harris_points`` points triangulated from Harris corners matched across the posed images,
                 beside (or instead of) the SfM points (``harris_points``; preset default)
``descriptors``  per image: Gaussian pyramid, Harris in every level, oriented DAISY at corners
                 within tau of a projected 3D point of the image
``refine``       points re-triangulated at their full-resolution Harris keypoints (``refine``)
``pca``          PCA of the raw descriptors to 32 dimensions
``clusters``     overlapping camera clusters for place recognition
``index``        the ANN index over all descriptors
``write``        the bundle, atomically

``main(conf, name, out_dir, ...)`` returns the bundle's path. Configuration is a pydantic
``BuildConf``; named ``PRESETS`` are merged over the defaults (hloc style).
"""

from __future__ import annotations

import ctypes
import logging
import os
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..cameras import Camera
from ..config import StrictModel, merge_presets
from ..errors import BuildCancelled, BuildError, ImageDecodeError
from ..features.daisy import RAW_DIM, DaisyExtractor, Pca
from ..features.harris import release_buffers
from ..features.pyramid import level_scales
from ..io.colmap import Image, Reconstruction
from ..map.bundle import MapData, validate_name, write_bundle
from ..map.index import DescriptorIndex, IndexConf
from ..map.keypoint_scales import keypoint_scales
from ..map.report import map_report
from ..transforms import Rigid3d
from .clusters import ClusterConf, cluster_images
from .desc_store import RawStore
from .descriptors import DescriptorConf, extract_image_descriptors
from .harris_points import HarrisPointsConf, harris_points
from .pca import project_store
from .refine import RefineConf, refine_points

log = logging.getLogger(__name__)

Progress = Callable[[str, float, str], None]
CancelCheck = Callable[[], bool]


class BuildConf(StrictModel):
    descriptors: DescriptorConf = DescriptorConf()
    harris_points: HarrisPointsConf = HarrisPointsConf()
    refine: RefineConf = RefineConf()
    clusters: ClusterConf = ClusterConf()
    index: IndexConf = IndexConf()
    pca_dim: int = 32
    # Build memory (issue 17): raw descriptors go to a file in the build's temporary folder
    # and come back chunk_rows at a time (27 MB of raw DAISY); PCA is fitted on a random
    # sample of pca_samples. False keeps every raw vector in memory (the old path, 1.7 KB per
    # descriptor at peak; see desc_store).
    stream_descriptors: bool = True
    chunk_rows: int = 65536
    pca_samples: int = 200_000
    # Points (refine) and tracks (harris_points) solved at a time: their padded arrays and
    # temporaries take up to 70 KB per track (synthetic 240 views: 300 MB per 4096 tracks;
    # unchunked, 1.7 GB for 23,702 tracks), so unchunked they were the build's largest
    # transient (issue 17).
    chunk_points: int = 1024
    # --extend: a new image's descriptors may also go to the map's points seen by its
    # extend_neighbors nearest map images looking within extend_max_angle_deg of it (0: the
    # new images' own points only).
    extend_neighbors: int = 5
    extend_max_angle_deg: float = 45.0


PRESETS: dict[str, dict[str, Any]] = {
    # Two octaves down and two sub-octaves up (see DescriptorConf.up_levels), points refined,
    # and points triangulated from matched Harris corners beside the SfM points (see
    # HarrisPointsConf: more accurate on dense and thin maps alike; builds about x5 slower).
    "default": {"harris_points": {"enabled": True}},
    # Exactly the paper's map: two octaves down only, points where SfM put them.
    "paper": {"descriptors": {"up_levels": 0}, "refine": {"enabled": False}},
    # Fewer pyramid levels and corners, SfM points only: quicker builds for large image sets.
    "fast": {"descriptors": {"octaves": 1, "up_levels": 1, "max_corners_per_level": 3000}},
    # Even more scales: four sub-octaves above the original resolution too.
    "dense": {"descriptors": {"up_levels": 4}, "harris_points": {"enabled": True}},
}


def preset(name: str) -> BuildConf:
    if name not in PRESETS:
        raise BuildError(
            f"unknown preset {name!r}; choose from {', '.join(PRESETS)}", stage="config"
        )
    return merge_presets(BuildConf(), **PRESETS[name])


def _noop(stage: str, fraction: float, message: str) -> None:
    pass


class StageProgress:
    """A progress callback that passes reports on and remembers the stage running now, so
    that an error can name it."""

    def __init__(self, progress: Progress | None = None, stage: str = "input") -> None:
        self.stage = stage
        self._user = progress or _noop

    def __call__(self, stage: str, fraction: float, message: str) -> None:
        self.stage = stage
        self._user(stage, fraction, message)


@contextmanager
def build_errors(stages: StageProgress, out_dir: str | Path) -> Iterator[None]:
    """System and OpenCV failures inside as a ``BuildError`` naming the stage (not a
    traceback): a full disk or permissions (``OSError``, with the file), an OpenCV limit or
    assertion (e.g. an image too large for one call), running out of memory. One mapping for
    every builder entry point (``main``, ``extend.extend``)."""
    try:
        yield
    except OSError as exc:
        raise BuildError(
            f"{exc.strerror or exc} ({exc.filename or out_dir})", stage=stages.stage
        ) from None
    except cv2.error as exc:
        # The detail is in the message's last line.
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else repr(exc)
        raise BuildError(f"OpenCV failed: {detail}", stage=stages.stage) from None
    except MemoryError:
        raise BuildError(
            "out of memory (fewer or smaller images, --preset fast, or a machine with more memory)",
            stage=stages.stage,
        ) from None


def release_freed_memory() -> None:
    """Hand freed heap pages back to the system between stages: once glibc's mmap threshold
    has grown, large freed arrays stay in the heap and the resident set keeps an earlier
    stage's peak (the Harris detector's buffers too). A no-op where there is no glibc."""
    release_buffers()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def load_gray(path: Path, camera: Camera) -> np.ndarray:
    """An image as uint8 grayscale, checked against its camera's size."""
    if not path.is_file():
        raise ImageDecodeError(f"image {path} is missing")
    data = np.fromfile(str(path), dtype=np.uint8)
    # Stored pixels, no EXIF rotation: the SfM model (COLMAP) describes the stored image.
    img = (
        cv2.imdecode(data, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
        if data.size
        else None
    )
    if img is None:
        raise ImageDecodeError(f"image {path} cannot be decoded")
    if img.shape != (camera.height, camera.width):
        raise ImageDecodeError(
            f"image {path} is {img.shape[1]}x{img.shape[0]}, its camera says "
            f"{camera.width}x{camera.height}"
        )
    return img


def assemble(
    rec: Reconstruction,
    image_dir: Path,
    conf: BuildConf,
    progress: Progress = _noop,
    should_cancel: CancelCheck | None = None,
    workdir: str | Path | None = None,
) -> tuple[MapData, dict[str, float], dict[str, Any]]:
    """Descriptors, PCA, clusters and index for a reconstruction -> ``MapData``. Raw
    descriptors are streamed to a file under ``workdir`` (default: the system's temporary
    folder), removed afterwards."""
    folder = None
    if conf.stream_descriptors:
        folder = Path(workdir) if workdir is not None else Path(tempfile.gettempdir())
    with RawStore(RAW_DIM, folder, conf.chunk_rows) as store:
        return _assemble(rec, image_dir, conf, store, progress, should_cancel, folder)


@dataclass
class _Part:
    """A reconstruction described (stages harris_points, descriptors, refine): its points,
    images, cameras and the lookups of its descriptors, whose raw vectors are in the store."""

    points_xyz: np.ndarray
    point_ids: np.ndarray
    point_rgb: np.ndarray
    images: list[Image]
    cameras: list[Camera]
    image_camera: np.ndarray  # (images,) row in ``cameras``
    image_points: list[np.ndarray]  # per image: point rows it sees
    image_desc_ptr: np.ndarray
    desc_point: np.ndarray
    desc_image: np.ndarray
    desc_level: np.ndarray
    desc_xy: np.ndarray
    info: dict[str, Any]
    timings: dict[str, float]


def _describe(
    rec: Reconstruction,
    image_dir: Path,
    conf: BuildConf,
    store: RawStore,
    progress: Progress,
    should_cancel: CancelCheck | None,
    folder: Path | None,
    extra_xyz: np.ndarray | None = None,
    extra_rows: dict[str, np.ndarray] | None = None,
    refine: bool = True,
) -> _Part:
    """``extra_xyz`` (E, 3) and ``extra_rows`` (image name -> rows of it): more candidate
    points per image (``--extend``: the map's points seen near the image); a descriptor of
    extra row e has ``desc_point`` len(points_xyz) + e. ``refine`` False leaves the points
    where they are (the caller refines)."""
    timings: dict[str, float] = {}
    if not rec.points3D:
        raise BuildError("the reconstruction has no 3D points", stage="sfm")
    hp_stats: dict[str, int] = {}
    if conf.harris_points.enabled:
        t0 = time.perf_counter()
        dc = conf.descriptors
        detector = {
            "rel_threshold": dc.harris_rel_threshold,
            "border": dc.border,
            "subpixel": dc.subpixel,
        }
        rec, hp_stats = harris_points(
            rec,
            image_dir,
            load_gray,
            conf.harris_points,
            detector,
            progress,
            should_cancel,
            workdir=folder,
            chunk_tracks=conf.chunk_points,
        )
        timings["harris_points"] = time.perf_counter() - t0
        release_freed_memory()
        log.info("Harris points: %s", hp_stats)
        if not rec.points3D:
            raise BuildError("no Harris point could be triangulated", stage="harris_points")
    # Stable row order: points by id, images by name (so bundles are deterministic).
    point_ids = np.array(sorted(rec.points3D), dtype=np.int64)
    row_of_point = {int(pid): r for r, pid in enumerate(point_ids)}
    points_xyz = np.stack([rec.points3D[int(p)].xyz for p in point_ids])
    point_rgb = np.stack([rec.points3D[int(p)].rgb for p in point_ids]).astype(np.uint8)
    images = sorted(rec.images.values(), key=lambda im: im.name)
    cam_ids = sorted(rec.cameras)
    cam_row = {cid: r for r, cid in enumerate(cam_ids)}

    # Visibility from the SfM tracks.
    image_points: list[np.ndarray] = []
    for im in images:
        ids = im.point3D_ids[im.point3D_ids >= 0]
        rows = np.array(
            sorted({row_of_point[int(p)] for p in ids if int(p) in row_of_point}), dtype=np.int64
        )
        image_points.append(rows)

    # ---- descriptors
    t0 = time.perf_counter()
    extractor = DaisyExtractor()
    counts, dpoint, dimage, dlevel, dxy = [], [], [], [], []
    n_corners = 0
    for i, im in enumerate(images):
        if should_cancel and should_cancel():
            raise BuildCancelled("cancelled", stage="descriptors")
        cam = rec.cameras[im.camera_id]
        gray = load_gray(image_dir / im.name, cam)
        pts, cand_xyz = image_points[i], points_xyz[image_points[i]]
        if extra_xyz is not None and extra_rows is not None and im.name in extra_rows:
            e = extra_rows[im.name]
            pts = np.concatenate([pts, len(points_xyz) + e])
            cand_xyz = np.concatenate([cand_xyz, extra_xyz[e]])
        d = extract_image_descriptors(
            gray, cam, im.cam_from_world, cand_xyz, conf.descriptors, extractor
        )
        store.append(d.raw)
        counts.append(len(d.raw))
        dpoint.append(pts[d.point_index].astype(np.int32))
        dimage.append(np.full(len(d.raw), i, np.int32))
        dlevel.append(d.level)
        dxy.append(d.xy)
        n_corners += d.n_corners
        progress("descriptors", (i + 1) / len(images), f"{im.name}: {len(d.raw)} descriptors")
    if len(store) == 0:
        raise BuildError(
            "no descriptors: no Harris corner lies within tau of a projected 3D point in any image "
            "(are the poses and the camera right?)",
            stage="descriptors",
        )
    timings["descriptors"] = time.perf_counter() - t0
    image_desc_ptr = np.zeros(len(images) + 1, np.int64)
    image_desc_ptr[1:] = np.cumsum(counts)
    # Per-descriptor lookups, concatenated once (17 B per descriptor, kept in the map).
    desc_point, desc_image = np.concatenate(dpoint), np.concatenate(dimage)
    desc_level, desc_xy = np.concatenate(dlevel), np.concatenate(dxy)
    del dpoint, dimage, dlevel, dxy

    # ---- points moved to where their own full-resolution Harris keypoints triangulate
    moved = np.zeros(len(points_xyz), bool)
    if refine:
        t0 = time.perf_counter()
        progress("refine", 0.0, "re-triangulating points at their Harris keypoints")
        points_xyz, moved = refine_points(
            points_xyz,
            desc_point,
            desc_image,
            desc_level,
            desc_xy,
            [rec.cameras[im.camera_id] for im in images],
            [im.cam_from_world for im in images],
            conf.refine,
            full_resolution_level=conf.descriptors.up_levels,
            chunk_points=conf.chunk_points,
        )
        timings["refine"] = time.perf_counter() - t0
        progress("refine", 1.0, f"{int(moved.sum())} of {len(moved)} points refined")
    info = {
        "corners_detected": n_corners,
        "points_refined": int(moved.sum()),
        **{f"harris_{k}": v for k, v in hp_stats.items()},
    }
    return _Part(
        points_xyz=points_xyz,
        point_ids=point_ids,
        point_rgb=point_rgb,
        images=images,
        cameras=[rec.cameras[cid] for cid in cam_ids],
        image_camera=np.array([cam_row[im.camera_id] for im in images], np.int32),
        image_points=image_points,
        image_desc_ptr=image_desc_ptr,
        desc_point=desc_point,
        desc_image=desc_image,
        desc_level=desc_level,
        desc_xy=desc_xy,
        info=info,
        timings=timings,
    )


def _clusters(
    image_points: list[np.ndarray], n_points: int, conf: BuildConf, progress: Progress
) -> dict[str, np.ndarray]:
    progress("clusters", 0.0, f"clustering {len(image_points)} images")
    clusters = cluster_images(image_points, n_points, conf.clusters)
    pc_ptr, pc_idx = clusters.point_clusters(image_points, n_points)
    ci_ptr = np.zeros(len(clusters) + 1, np.int64)
    ci_ptr[1:] = np.cumsum([len(c) for c in clusters.images])
    ci_idx = (
        np.concatenate(clusters.images).astype(np.int32) if len(clusters) else np.zeros(0, np.int32)
    )
    progress("clusters", 1.0, f"{len(clusters)} clusters")
    return {
        "cluster_images_ptr": ci_ptr,
        "cluster_images_idx": ci_idx,
        "point_clusters_ptr": pc_ptr,
        "point_clusters_idx": pc_idx,
    }


def _map_data(
    points_xyz: np.ndarray,
    point_ids: np.ndarray,
    point_rgb: np.ndarray,
    desc: np.ndarray,
    lookups: dict[str, np.ndarray],
    image_cam_from_world: np.ndarray,
    image_names: list[str],
    image_camera: np.ndarray,
    cameras: list[Camera],
    image_points: list[np.ndarray],
    clusters: dict[str, np.ndarray],
    pca: Pca,
    index_faiss: np.ndarray,
    conf: BuildConf,
) -> MapData:
    ip_ptr = np.zeros(len(image_points) + 1, np.int64)
    ip_ptr[1:] = np.cumsum([len(p) for p in image_points])
    data = MapData(
        points_xyz=points_xyz,
        point_ids=point_ids,
        point_rgb=point_rgb,
        descriptors=desc,
        desc_point=lookups["desc_point"],
        desc_image=lookups["desc_image"],
        desc_level=lookups["desc_level"],
        desc_xy=lookups["desc_xy"],
        image_desc_ptr=lookups["image_desc_ptr"],
        image_cam_from_world=image_cam_from_world,
        image_camera=image_camera,
        image_points_ptr=ip_ptr,
        image_points_idx=np.concatenate(image_points).astype(np.int32),
        pca_mean=pca.mean,
        pca_basis=pca.basis,
        index_faiss=index_faiss,
        cameras=cameras,
        image_names=image_names,
        cluster_images_ptr=clusters["cluster_images_ptr"],
        cluster_images_idx=clusters["cluster_images_idx"],
        point_clusters_ptr=clusters["point_clusters_ptr"],
        point_clusters_idx=clusters["point_clusters_idx"],
    )
    data.keypoint_scales = keypoint_scales(
        data.desc_image,
        data.desc_level,
        data.image_camera,
        cameras,
        level_scales(
            conf.descriptors.octaves, conf.descriptors.per_octave, conf.descriptors.up_levels
        ),
    )
    return data


def _lookups(part: _Part) -> dict[str, np.ndarray]:
    return {
        k: getattr(part, k)
        for k in ("desc_point", "desc_image", "desc_level", "desc_xy", "image_desc_ptr")
    }


def _assemble(
    rec: Reconstruction,
    image_dir: Path,
    conf: BuildConf,
    store: RawStore,
    progress: Progress,
    should_cancel: CancelCheck | None,
    folder: Path | None,
) -> tuple[MapData, dict[str, float], dict[str, Any]]:
    part = _describe(rec, image_dir, conf, store, progress, should_cancel, folder)
    release_freed_memory()
    timings = part.timings
    n_desc = len(store)

    # ---- PCA
    t0 = time.perf_counter()
    progress("pca", 0.0, f"PCA of {n_desc} descriptors to {conf.pca_dim} dimensions")
    try:
        desc, pca = project_store(store, conf.pca_dim, conf.pca_samples, progress=progress)
    except ValueError as exc:
        raise BuildError(str(exc), stage="pca") from None
    store.close()  # the raw descriptors are no longer needed
    release_freed_memory()
    timings["pca"] = time.perf_counter() - t0
    progress("pca", 1.0, "done")

    # ---- clusters
    t0 = time.perf_counter()
    clusters = _clusters(part.image_points, len(part.point_ids), conf, progress)
    timings["clusters"] = time.perf_counter() - t0

    # ---- index (built from exactly the stored float16 values)
    t0 = time.perf_counter()
    progress("index", 0.0, f"indexing {len(desc)} descriptors")
    index = DescriptorIndex.build(desc, conf.index, chunk_rows=conf.chunk_rows)
    index_info = {"kind": index.kind, "nlist": index.nlist, "nprobe": index.nprobe}
    if folder is None:
        index_faiss = index.serialize()
        del index  # the serialized copy is what the bundle stores
    else:
        # Through a file: serialize() holds the index, faiss's byte vector and the array at
        # once (3 x 40 B per IVF-SQ8 descriptor); this way one copy at a time. Same bytes.
        fd, index_path = tempfile.mkstemp(prefix="index-", suffix=".faiss", dir=str(folder))
        os.close(fd)
        try:
            index.write(index_path)
            del index
            release_freed_memory()
            index_faiss = np.fromfile(index_path, dtype=np.uint8)
        finally:
            Path(index_path).unlink(missing_ok=True)
    release_freed_memory()
    timings["index"] = time.perf_counter() - t0
    progress("index", 1.0, f"{index_info['kind']}, {index_info['nlist']} lists")

    data = _map_data(
        part.points_xyz,
        part.point_ids,
        part.point_rgb,
        desc,
        _lookups(part),
        np.stack(
            [
                np.concatenate([im.cam_from_world.quat_wxyz, im.cam_from_world.translation])
                for im in part.images
            ]
        ),
        [im.name for im in part.images],
        part.image_camera,
        part.cameras,
        part.image_points,
        clusters,
        pca,
        index_faiss,
        conf,
    )
    return data, timings, {**index_info, **part.info}


def main(
    conf: BuildConf,
    name: str,
    out_dir: str | Path,
    *,
    colmap: str | Path | None = None,
    images: str | Path | None = None,
    poses: str | Path | None = None,
    camera: str | Camera | None = None,
    sfm_conf: Any = None,
    stride: int = 1,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    should_cancel: CancelCheck | None = None,
    source_extra: dict[str, Any] | None = None,
) -> Path:
    """Build the bundle ``out_dir/name`` from one of the three inputs; return its path.

    - ``colmap`` + ``images``: a COLMAP sparse model (text or binary) and its image folder;
    - ``images`` + ``poses`` + ``camera``: posed images, points triangulated with pycolmap;
    - ``images`` (+ optional ``camera``): full SfM with pycolmap first.

    ``stride`` keeps every n-th posed image (or image) for the last two inputs.
    ``source_extra`` is merged into the manifest's ``source`` (``video.build_from_video``).
    """
    from . import sfm  # pycolmap is only needed here

    validate_name(name)
    stages = StageProgress(progress)  # names the running stage in errors
    if images is None:
        raise BuildError("an image folder is required (--images)", stage="input")
    image_dir = Path(images)
    if not image_dir.is_dir():
        raise BuildError(f"image folder {image_dir} does not exist", stage="input")
    cam = Camera.parse(camera) if isinstance(camera, (str, Path)) else camera
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    t0 = t_all
    with build_errors(stages, out_dir):
        if colmap is not None:
            if poses is not None:
                raise BuildError("give either --colmap or --poses, not both", stage="input")
            source: dict[str, Any] = {
                "kind": "colmap",
                "model": str(colmap),
                "images": str(image_dir),
            }
            stages("sfm", 0.0, f"reading COLMAP model {colmap}")
            rec = sfm.load_colmap_input(
                colmap, image_dir, conf=sfm_conf, progress=stages, should_cancel=should_cancel
            )
        elif poses is not None:
            if cam is None:
                raise BuildError(
                    "--poses needs --camera (camera.json or 'MODEL w h params...')", stage="input"
                )
            source = {
                "kind": "known-poses",
                "poses": str(poses),
                "images": str(image_dir),
                "camera": cam.to_dict(),
                "stride": stride,
            }
            rec = sfm.triangulate_known_poses(
                image_dir,
                poses,
                cam,
                conf=sfm_conf,
                workdir=workdir,
                progress=stages,
                should_cancel=should_cancel,
                stride=stride,
            )
            if conf.harris_points.follow_sfm_two_view and any(
                len(p.track_image_ids) == 2 for p in rec.points3D.values()
            ):
                # the SfM kept two-view points (its tracks are filtered to its minimum length)
                conf = merge_presets(conf, harris_points={"keep_two_view": True})
        else:
            source = {"kind": "images-only", "images": str(image_dir), "stride": stride}
            rec = sfm.reconstruct_images_only(
                image_dir,
                cam,
                conf=sfm_conf,
                workdir=workdir,
                progress=stages,
                should_cancel=should_cancel,
                stride=stride,
            )
        source.update(source_extra or {})
        stages("sfm", 1.0, rec.summary())
        timings["sfm"] = time.perf_counter() - t0
        log.info("reconstruction: %s", rec.summary())
        data, t_stages, index_info = assemble(
            rec, image_dir, conf, stages, should_cancel, workdir=workdir
        )
        timings.update(t_stages)
        if should_cancel and should_cancel():
            raise BuildCancelled("cancelled", stage="write")
        t0 = time.perf_counter()
        stages("write", 0.0, f"writing {Path(out_dir) / name}")
        params = conf.model_dump()
        if sfm_conf is not None and hasattr(sfm_conf, "model_dump"):
            params["sfm"] = sfm_conf.model_dump()
        report = map_report(
            data.points_xyz,
            data.image_points_ptr,
            data.image_points_idx,
            data.cameras,
            data.image_camera,
            [Rigid3d.from_quat_wxyz(q[:4], q[4:]) for q in data.image_cam_from_world],
        )
        for w in report["warnings"]:
            log.warning("%s: %s", name, w)
        # The write stage so far (the map report); write_bundle adds the write itself to
        # "write" and "total" once the arrays are on disk (both were recorded here, before).
        timings["write"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - t_all
        path = write_bundle(
            data,
            out_dir,
            name,
            source=source,
            params=params,
            timings_s=timings,
            index_info=index_info,
            report=report,
        )
        stages("write", 1.0, str(path) + "".join(f"; WARNING: {w}" for w in report["warnings"]))
        return path
