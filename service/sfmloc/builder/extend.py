"""Add images to an existing map bundle (``sfmloc build NAME --extend BUNDLE``, issue 17).

The new images come with poses in the map's frame (known poses or a COLMAP model). Only they
go through the builder's stages: points triangulated among them (SfM and Harris points, as in a
full build) and their descriptors. A new image's corners may also describe the map's points
seen by its nearest map images (``BuildConf.extend_neighbors``, looking the same way within
``extend_max_angle_deg``): the map's points seen again get observations and descriptors from
the new images, and are re-triangulated at their full-resolution keypoints in old and new
images together (the refine stage, over the new points and those). Raw descriptors are
projected with the map's own PCA, so the old descriptors stay valid as they are; the new ones
are added to the map's ANN index (retrained over all descriptors only when the map has grown
past what its inverted lists were sized for); clusters and lookups are recomputed over all
images. The work is that of the new images, not of the whole map again.

The map's points seen again move (refine): on redkitchen (map of every 10th of frames 0-499,
extended with 500-999; the extend bench's maps of 16:40) 1,432 of 7,565 moved, 425 by more than
1 cm (median 2.5 cm, max 31 cm). Checked to be corrections: the moves lie along the first map's
viewing rays (the component across them a median 7% of the move), where its narrow baselines left
the depth loose (widest ray angle median 2.7 deg, with the new images 7.7 deg); the new images'
keypoints are the same features (nearest old-new DAISY distance median 0.113, unmoved re-observed
points 0.111, unrelated points 0.54); the mean reprojection error over all their keypoints
0.85 -> 0.59 px (old images alone 0.49 -> 0.52 px); and the 1,000 frames replayed on the extended
map against the same map with those points put back: median 0.247 / 0.267 cm, mean 0.416 / 0.429
cm, 0 wrong each (frame 466, 5.7 cm off with them put back, is withheld with the moves).

What a build from all the images at once has and this has not: new points are triangulated
from the new images alone (a surface seen from both gets a point from each side). The builder
settings are the bundle's own (``manifest.params``), so old and new descriptors come from the
same pyramid and detector.

The result is a new bundle (a new build id) written atomically: the base bundle is untouched,
also when NAME is its own name (replaced only once the new one is complete).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..cameras import Camera
from ..errors import BuildError, SfmlocError
from ..features.daisy import RAW_DIM, Pca
from ..io.colmap import Reconstruction
from ..map.bundle import MapBundle, MapData, validate_name, write_bundle
from ..map.index import DescriptorIndex, choose_nlist
from ..map.report import map_report
from ..transforms import Rigid3d
from .build import (
    BuildConf,
    CancelCheck,
    Progress,
    StageProgress,
    _clusters,
    _describe,
    _lookups,
    _map_data,
    _Part,
    build_errors,
)
from .desc_store import RawStore
from .refine import refine_points


def bundle_conf(params: dict[str, Any]) -> BuildConf:
    """The builder settings a bundle was built with (its manifest's params)."""
    known = {k: v for k, v in params.items() if k in BuildConf.model_fields}
    try:
        return BuildConf.model_validate(known)
    except ValueError as exc:
        raise BuildError(
            f"the base map's builder settings do not parse: {exc}", stage="input"
        ) from None


def extend(
    base: str | Path,
    name: str,
    out_dir: str | Path,
    *,
    images: str | Path,
    poses: str | Path | None = None,
    camera: str | Camera | None = None,
    colmap: str | Path | None = None,
    sfm_conf: Any = None,
    stride: int = 1,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    should_cancel: CancelCheck | None = None,
) -> Path:
    """The bundle ``base`` plus the images of ``images`` (posed by ``poses`` + ``camera`` or by
    the COLMAP model ``colmap``, in the map's frame) as ``out_dir/name``; returns its path."""
    from . import sfm

    validate_name(name)
    report = StageProgress(progress)  # names the running stage in errors
    t_all = time.perf_counter()
    image_dir = Path(images)
    if not image_dir.is_dir():
        raise BuildError(f"image folder {image_dir} does not exist", stage="input")
    if (poses is None) == (colmap is None):
        raise BuildError(
            "--extend needs the new images' poses in the map's frame: --poses with --camera, "
            "or --colmap (not both; images-only SfM would be in a frame of its own)",
            stage="input",
        )
    try:
        old = MapBundle(base, verify=True)
    except SfmlocError as exc:
        raise BuildError(f"base map: {exc}", stage="input") from None
    conf = bundle_conf(old.manifest.params)
    cam = Camera.parse(camera) if isinstance(camera, (str, Path)) else camera
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    with build_errors(report, out_dir):
        if colmap is not None:
            source: dict[str, Any] = {"kind": "colmap", "model": str(colmap)}
            rec = sfm.load_colmap_input(
                colmap, image_dir, conf=sfm_conf, progress=report, should_cancel=should_cancel
            )
        else:
            if cam is None:
                raise BuildError("--poses needs --camera", stage="input")
            source = {"kind": "known-poses", "poses": str(poses), "camera": cam.to_dict()}
            rec = sfm.triangulate_known_poses(
                image_dir,
                poses,  # type: ignore[arg-type]
                cam,
                conf=sfm_conf,
                workdir=workdir,
                progress=report,
                should_cancel=should_cancel,
                stride=stride,
            )
        source.update(images=str(image_dir), stride=stride)
        timings["sfm"] = time.perf_counter() - t0
        report("sfm", 1.0, rec.summary())
        dup = sorted({im.name for im in rec.images.values()} & set(old.image_names))
        if dup:
            raise BuildError(
                f"{len(dup)} new images have names already in the map (e.g. {dup[0]}); "
                "give only images that are not in it",
                stage="input",
            )
        folder = None
        if conf.stream_descriptors:
            folder = Path(workdir) if workdir is not None else Path(tempfile.gettempdir())
        near = _nearby_points(old, rec, conf.extend_neighbors, conf.extend_max_angle_deg)
        with RawStore(RAW_DIM, folder, conf.chunk_rows) as store:
            part = _describe(
                rec,
                image_dir,
                conf,
                store,
                report,
                should_cancel,
                folder,
                extra_xyz=np.asarray(old.points_xyz),
                extra_rows=near,
                refine=False,
            )
            timings.update(part.timings)
            t0 = time.perf_counter()
            report("pca", 0.0, f"projecting {len(store)} descriptors with the map's PCA")
            desc_new = np.empty((len(store), old.pca.basis.shape[1]), np.float16)
            for start, chunk in store.chunks():
                desc_new[start : start + len(chunk)] = old.pca.project(chunk)
            timings["pca"] = time.perf_counter() - t0
        data, index_info = _merge(old, part, desc_new, conf, report, timings)
        del desc_new
        t0 = time.perf_counter()
        report("write", 0.0, f"writing {Path(out_dir) / name}")
        rep = map_report(
            data.points_xyz,
            data.image_points_ptr,
            data.image_points_idx,
            data.cameras,
            data.image_camera,
            [Rigid3d.from_quat_wxyz(q[:4], q[4:]) for q in data.image_cam_from_world],
        )
        timings["write"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - t_all
        base_source = {
            "kind": "extend",
            "base": {
                "path": str(Path(base)),
                "name": old.name,
                "build_id": old.build_id,
                "source": old.manifest.source,
                "images": old.n_images,
                "points": old.n_points,
                "descriptors": old.n_descriptors,
            },
            "added": source,
        }
        path = write_bundle(
            data,
            out_dir,
            name,
            source=base_source,
            params=old.manifest.params,
            timings_s=timings,
            index_info=index_info,
            report=rep,
        )
        report("write", 1.0, str(path) + "".join(f"; WARNING: {w}" for w in rep["warnings"]))
        return path


def _nearby_points(
    old: MapBundle, rec: Reconstruction, k: int, max_angle_deg: float
) -> dict[str, np.ndarray]:
    """Per new image: the map's points seen by its ``k`` nearest map images (camera centres)
    that look within ``max_angle_deg`` of its direction; candidates for its descriptors, so
    that old points seen again get observations and descriptors from the new images."""
    if k <= 0 or old.n_images == 0:
        return {}
    poses = old.image_cam_from_world
    centres = np.stack([T.center for T in poses])
    dirs = np.stack([T.rotation[2] for T in poses])  # optical axes in the world
    cos_min = np.cos(np.radians(max_angle_deg))
    out = {}
    for im in rec.images.values():
        T = im.cam_from_world
        ok = np.nonzero(dirs @ T.rotation[2] >= cos_min)[0]
        if len(ok) == 0:
            continue
        near = ok[np.argsort(np.linalg.norm(centres[ok] - T.center, axis=1))[:k]]
        out[im.name] = np.unique(np.concatenate([old.image_points(int(i)) for i in near]))
    return out


def _merge(
    old: MapBundle,
    part: _Part,
    desc_new: np.ndarray,
    conf: BuildConf,
    progress: Progress,
    timings: dict[str, float],
) -> tuple[MapData, dict[str, Any]]:
    """The old map's arrays with the new part appended (points, images, descriptors), clusters
    over all images, the index extended."""
    P0, I0, D0 = old.n_points, old.n_images, old.n_descriptors
    a = old.array
    # New points get ids after the map's largest, in their own (sorted) order.
    first_id = int(np.max(a("point_ids"))) + 1 if P0 else 1
    point_ids = np.concatenate([a("point_ids"), first_id + np.arange(len(part.point_ids))])
    # Cameras: the map's, then any new camera not equal to one of them.
    cameras = list(old.cameras)
    cam_of_new = []
    for c in part.cameras:
        same = [k for k, o in enumerate(cameras) if o.to_dict() == c.to_dict()]
        if not same:
            cameras.append(c)
        cam_of_new.append(same[0] if same else len(cameras) - 1)
    old_ptr = np.asarray(a("image_points_ptr"))
    old_idx = np.asarray(a("image_points_idx"), np.int64)
    image_points = [old_idx[old_ptr[i] : old_ptr[i + 1]] for i in range(I0)]
    # The part's rows: its own points, then the map's (extra candidates, row - n_new).
    n_new = len(part.point_ids)
    row_map = np.concatenate([P0 + np.arange(n_new), np.arange(P0)])
    new_desc_point = row_map[part.desc_point]
    ptr = part.image_desc_ptr
    for i, p in enumerate(part.image_points):
        seen_old = np.unique(new_desc_point[ptr[i] : ptr[i + 1]])
        image_points.append(np.union1d(p + P0, seen_old[seen_old < P0]))
    lookups = _lookups(part)
    lookups = {
        "desc_point": np.concatenate([a("desc_point"), new_desc_point]),
        "desc_image": np.concatenate([a("desc_image"), lookups["desc_image"] + I0]),
        "desc_level": np.concatenate([a("desc_level"), lookups["desc_level"]]),
        "desc_xy": np.concatenate([a("desc_xy"), lookups["desc_xy"]]),
        "image_desc_ptr": np.concatenate([a("image_desc_ptr"), lookups["image_desc_ptr"][1:] + D0]),
    }
    desc = np.concatenate([a("descriptors"), desc_new])
    t0 = time.perf_counter()
    clusters = _clusters(image_points, P0 + len(part.point_ids), conf, progress)
    timings["clusters"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    n = len(desc)
    progress("index", 0.0, f"adding {len(desc_new)} descriptors to the map's index")
    index = DescriptorIndex.deserialize(np.asarray(a("index_faiss")), old.index.nprobe)
    # Lists sized for the old map serve one twice its size (each list scanned holds more, the
    # recall is not lower); past that the index is trained again over a sample of all.
    if index.kind == "flat" or choose_nlist(n) >= 2 * index.nlist:
        index = DescriptorIndex.build(
            desc, conf.index.model_copy(update={"nlist": None}), chunk_rows=conf.chunk_rows
        )
        how = "retrained"
    else:
        index.add(desc_new, conf.chunk_rows)
        how = "extended"
    index_faiss = index.serialize()
    index_info = {"kind": index.kind, "nlist": index.nlist, "nprobe": index.nprobe, "how": how}
    del index
    timings["index"] = time.perf_counter() - t0
    progress("index", 1.0, f"{index_info['kind']}, {index_info['nlist']} lists ({how})")

    new_poses = [
        np.concatenate([im.cam_from_world.quat_wxyz, im.cam_from_world.translation])
        for im in part.images
    ]
    image_cam_from_world = np.concatenate([a("image_cam_from_world"), np.stack(new_poses)])
    image_camera = np.concatenate(
        [a("image_camera"), np.asarray(cam_of_new, np.int32)[part.image_camera]]
    ).astype(np.int32)
    # Points re-triangulated at their full-resolution keypoints in every image (as a build
    # from all images does): the new points, and the map's points seen again in new images.
    t0 = time.perf_counter()
    progress("refine", 0.0, "re-triangulating points at their Harris keypoints")
    xyz = np.concatenate([a("points_xyz"), part.points_xyz])
    touched = np.zeros(len(xyz), bool)
    touched[P0:] = True
    touched[new_desc_point] = True
    refined, moved = refine_points(
        xyz,
        lookups["desc_point"],
        lookups["desc_image"],
        lookups["desc_level"],
        lookups["desc_xy"],
        [cameras[c] for c in image_camera],
        list(old.image_cam_from_world) + [im.cam_from_world for im in part.images],
        conf.refine,
        full_resolution_level=conf.descriptors.up_levels,
        chunk_points=conf.chunk_points,
    )
    moved &= touched
    xyz[moved] = refined[moved]
    timings["refine"] = time.perf_counter() - t0
    progress("refine", 1.0, f"{int(moved.sum())} of {int(touched.sum())} points refined")
    data = _map_data(
        xyz,
        point_ids,
        np.concatenate([a("point_rgb"), part.point_rgb]),
        desc,
        lookups,
        image_cam_from_world,
        list(old.image_names) + [im.name for im in part.images],
        image_camera,
        cameras,
        image_points,
        clusters,
        Pca(old.pca.mean, old.pca.basis),
        index_faiss,
        conf,
    )
    info = {
        **index_info,
        **{f"added_{k}": v for k, v in part.info.items()},
        "added_points_refined": int(moved.sum()),
        "map_points_seen_again": int(touched[:P0].sum()),
        "map_points_moved": int(moved[:P0].sum()),
    }
    return data, info
