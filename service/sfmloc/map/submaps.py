"""Out-of-core maps: a large bundle split into overlapping sub-maps (issue 14, build 5; the
paper's Section 2 remark: "partitioned into overlapping sub-maps, kd-trees are built for each
of them and only a few relevant sub-maps need to be in memory at any time").

Design
------
**What a sub-map is.** A normal map bundle (``bundle.py``: same arrays, same checks, its own
faiss index), made of a group of the map's *camera clusters* (the overlapping clusters the
bundle already stores for place recognition, ``builder/clusters.py``): its images are those of
its clusters plus every image whose centre lies within ``overlap`` scene scales of one of them
(so a camera crossing from one sub-map into the next is inside both for a while), its points
are every point those images observe, its descriptors are those images' descriptors, and its
clusters are the map's clusters clipped to its images. A localizer can therefore run on one
sub-map exactly as on a whole map, with no change to the per-frame core.

**Global ids.** A sub-map's point rows are the *global* point rows of the whole map that it
holds, in increasing order (stored beside the set as ``part_points_K``, loaded with the part):
local row ``r`` is global row ``part_points[r]`` and global row ``g`` is local row
``searchsorted(part_points, g)`` when present. A session's track table holds point rows of the
sub-map it is on; when the session moves to another sub-map its rows go through the global
ids (``translate``): matches to points the new sub-map holds stay matches, the
others become pending, so tracking continues across the switch without a relocalization.
Images work the same way (``part_images``).

**How the map is cut.** Recursive bisection of the clusters by their mean camera centre, along
the axis of largest spread, at the median: each cut halves a part's clusters, the part holding
the most points is cut next, until there are ``parts`` parts (or every part holds at most
``max_points`` points). Spatially compact parts of similar size, and no cluster is ever split.

**The global index** (small: O(images + parts), plus a sample of descriptors), loaded once:

- ``image_centers`` / ``image_axes`` (I,3): every map image's camera centre and optical axis;
- ``part_images`` (CSR over parts): the images of each part (global rows);
- ``part_bbox`` (K,6): each part's bounding box (min xyz, max xyz) of its points and cameras;
- ``part_clusters`` (CSR over parts): the map's clusters each part holds (global ids);
- ``vote_desc`` (V,32) with ``vote_images`` (V,): a place-recognition sample, a random
  ``vote_fraction`` of every image's descriptors, each labelled with its image.

It answers two questions without any sub-map in memory: which parts a *pose prior* touches
(``parts_near``: parts ranked by how well their cameras cover it, weighting each camera by its
distance in position, in scene scales, and viewing direction), and which parts a *query* touches
(``vote``: the nearest sample descriptor of each of the frame's descriptors votes for the parts
holding the image it was seen in; a part scores its votes over their number by chance, its share
of the sample; parts are tried in that order). Measured: on two synthetic rooms with their own
textures in one map, a frame descriptor's nearest neighbour in the whole map lies in the frame's
room only 55-70% of the time (procedural textures look alike), so no single match tells the
place; the count over a frame's ~1000 keypoints, against chance, put a part of the right room
first for 16 of 16 frames. Counting once per part with the paper's strengths s_i0/s_ij over 10
neighbours (as global matching votes for clusters) saturated: every part scored about the same.
Labels are images, not points: neighbouring parts share most points (in the synthetic room split
in three, voting by points or by the points' clusters put a part holding the query image first
for 23 of 40 images, no better than always part 0), while a descriptor depends on the viewpoint
it was seen from. The sample's size is a trade: on 8 rooms in 24 parts (4 frames of each room),
the rank of the first part of the right room was 0 for 16/32 frames and at worst 20 with
``vote_fraction`` 0.02 (global index 1.7% of the map's memory), 20/32 and at worst 13 with 0.05,
20/32 and at worst 8 with 0.1 (about 7%); a lost session tries one part per frame in this order.
One descriptor per point instead: 6/32. Walking the 8 rooms (bench ``scale --parts submaps``,
budget = map/8.2), 0.02 localized 254/320 frames, 0.05 291/320 (the whole map 320): 0.05 is the
default, a global index of 4% of the map's memory.

**Where the switch happens** (``engine/submaps.py``): between frames, in a localizer that owns a
plain ``Localizer`` and swaps its ``bundle`` (the engine holds the map only as
``Localizer.bundle``, read-only and shared). The home part of a posed camera is the one whose
cameras cover its pose best, kept while it stays within a margin of the best (hysteresis);
the parts near the pose predicted ``lookahead_s`` ahead are loaded in a background thread, and
the least recently used parts are evicted to keep the resident parts' ``memory_bytes`` within
the budget. A lost camera relocalizes against the parts in order of its frame's vote, one part
per frame (a frame never pays for more than one global matching). The server (``MapRegistry``
/ ``worker.py``) would host such a localizer per session over a set shared by the worker.

Layout of ``maps/NAME/`` (a sub-map set)::

    submaps.json        ``SetManifest``: format, version, name, build id, the source bundle,
                        parameters, counts, the parts (folder, build id, counts, memory, and
                        the SHA-256 of each part's manifest), every global array's entry
    submaps.sha256      SHA-256 of submaps.json (``sha256sum -c`` works)
    <array>.npy         the global index and ``part_points_K`` arrays (plain .npy, no pickle)
    part-000/ ...       the sub-maps, each a complete bundle

Written atomically like a bundle (hidden temporary folder, then swapped into place).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from .. import __version__
from ..errors import BundleError, InputError
from ..features.daisy import Pca
from ..transforms import Rigid3d
from .bundle import (
    MANIFEST,
    MAX_MANIFEST_BYTES,
    PACKED_SPECS,
    ArrayEntry,
    MapBundle,
    MapData,
    _read_small_file,
    _sha256,
    load_array,
    load_npy,
    publish,
    read_manifest,
    validate_name,
    verify_bundle,
    write_bundle,
)
from .index import DescriptorIndex, IndexConf
from .keypoint_scales import coarsest_focal_px

SET_FORMAT = "sfmloc-submap-set"
SET_VERSION = 1
SET_MANIFEST = "submaps.json"
SET_SHA256 = "submaps.sha256"

# name -> (dtype, ndim) of the global arrays (``part_points_K`` are checked like these).
GLOBAL_SPECS: dict[str, tuple[str, int]] = {
    "image_centers": ("<f8", 2),
    "image_axes": ("<f8", 2),
    "part_images_ptr": ("<i8", 1),
    "part_images_idx": ("<i8", 1),
    "part_bbox": ("<f8", 2),
    "part_clusters_ptr": ("<i8", 1),
    "part_clusters_idx": ("<i8", 1),
    "vote_desc": ("<f2", 2),
    "vote_images": ("<i4", 1),
}
POINTS_SPEC = ("<i8", 1)
MIN_VOTES_PER_IMAGE = 8
PAGE_BYTES = 4096  # mapped arrays are resident in whole pages
VOTE_RATIO = 0.8  # SubmapSet.vote: the ratio test of a query's two nearest sample descriptors


def is_submap_set(path: str | Path) -> bool:
    """Whether ``path`` is a sub-map set folder (has ``submaps.json``)."""
    return (Path(path) / SET_MANIFEST).is_file()


def part_folder(k: int) -> str:
    return f"part-{k:03d}"


def points_array(k: int) -> str:
    return f"part_points_{k:03d}"


class PartEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    folder: str
    build_id: str
    manifest_sha256: str  # binds the part's bundle to this set
    points: int
    descriptors: int
    images: int
    clusters: int
    memory_bytes: int


class SetManifest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    format: str = SET_FORMAT
    version: int = SET_VERSION
    name: str
    build_id: str
    created_utc: str
    sfmloc_version: str = __version__
    source: dict[str, Any] = {}
    params: dict[str, Any] = {}
    scene_scale: float
    points: int
    images: int
    clusters: int
    parts: list[PartEntry]
    arrays: dict[str, ArrayEntry]


# ============================================================================ splitting
def _csr(groups: list[np.ndarray], dtype: Any = np.int64) -> tuple[np.ndarray, np.ndarray]:
    ptr = np.zeros(len(groups) + 1, np.int64)
    ptr[1:] = np.cumsum([len(g) for g in groups])
    idx = np.concatenate(groups).astype(dtype) if groups else np.zeros(0, dtype)
    return ptr, idx


def _gather(ptr: np.ndarray, idx: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The CSR entries of ``rows``, concatenated in row order."""
    if len(rows) == 0:
        return np.zeros(0, idx.dtype)
    return np.concatenate([idx[ptr[r] : ptr[r + 1]] for r in rows])


def _image_points(bundle: MapBundle, images: np.ndarray) -> np.ndarray:
    return np.unique(_gather(bundle.image_points_ptr, bundle.image_points_idx, images))


def _cluster_groups(
    bundle: MapBundle,
    centers: np.ndarray,
    parts: int | None,
    max_points: int | None,
) -> list[np.ndarray]:
    """Recursive median bisection of the clusters by their mean camera centre (module doc)."""
    L = bundle.n_clusters
    c_center = np.array([centers[bundle.cluster_images(c)].mean(axis=0) for c in range(L)])

    def n_points(group: np.ndarray) -> int:
        imgs = np.unique(_gather(bundle.cluster_images_ptr, bundle.cluster_images_idx, group))
        return len(_image_points(bundle, imgs))

    groups = [(np.arange(L), n_points(np.arange(L)))]
    while True:
        if parts is not None and len(groups) >= parts:
            break
        cand = [i for i, (g, n) in enumerate(groups) if len(g) > 1]
        if max_points is not None and parts is None:
            cand = [i for i in cand if groups[i][1] > max_points]
        if not cand:
            break
        i = max(cand, key=lambda j: groups[j][1])
        g = groups.pop(i)[0]
        xyz = c_center[g]
        axis = int(np.argmax(xyz.max(axis=0) - xyz.min(axis=0)))
        order = g[np.argsort(xyz[:, axis], kind="stable")]
        half = len(order) // 2
        for sub in (np.sort(order[:half]), np.sort(order[half:])):
            groups.append((sub, n_points(sub)))
    # Stable order of the parts: along the map's axis of largest spread of their centres.
    return [g for g, _ in groups]


def _part_data(
    bundle: MapBundle, images: np.ndarray, keypoint_scales: dict[str, Any]
) -> tuple[MapData, np.ndarray, dict[str, Any]]:
    """The bundle of the map's ``images`` (sorted global rows) and its global point rows."""
    a = bundle.array
    desc_rows = np.concatenate(
        [np.arange(bundle.image_desc_ptr[i], bundle.image_desc_ptr[i + 1]) for i in images]
    )
    gpts = np.union1d(_image_points(bundle, images), bundle.desc_point[desc_rows])
    local_img = np.full(bundle.n_images, -1, np.int64)
    local_img[images] = np.arange(len(images))
    local_pt = np.full(bundle.n_points, -1, np.int64)
    local_pt[gpts] = np.arange(len(gpts))
    # Clusters clipped to the part's images; a point belongs to every clipped cluster holding
    # one of its (part) images, as in the whole map.
    clusters: list[np.ndarray] = []
    in_part = local_img >= 0
    for c in range(bundle.n_clusters):
        ci = bundle.cluster_images(c)
        ci = ci[in_part[ci]]
        if len(ci):
            clusters.append(np.sort(local_img[ci]))
    cl_ptr, cl_idx = _csr(clusters, np.int32)
    img_pts = [local_pt[bundle.image_points(int(i))] for i in images]
    ip_ptr, ip_idx = _csr(img_pts, np.int32)
    owner_c = np.repeat(np.arange(len(clusters)), np.diff(cl_ptr))
    pairs = []
    for oc, li in zip(owner_c, cl_idx):
        pts = ip_idx[ip_ptr[li] : ip_ptr[li + 1]]
        pairs.append(np.stack([pts.astype(np.int64), np.full(len(pts), oc, np.int64)], 1))
    pc = np.unique(np.concatenate(pairs), axis=0) if pairs else np.zeros((0, 2), np.int64)
    pc_ptr = np.zeros(len(gpts) + 1, np.int64)
    np.add.at(pc_ptr, pc[:, 0] + 1, 1)
    pc_ptr = np.cumsum(pc_ptr)
    desc = np.asarray(a("descriptors")[desc_rows])
    counts = np.diff(bundle.image_desc_ptr)[images]
    desc_ptr = np.zeros(len(images) + 1, np.int64)
    desc_ptr[1:] = np.cumsum(counts)
    info = dict(bundle.manifest.index)
    iconf = IndexConf(kind=info.get("kind", "ivf-sq8"), nprobe=int(info.get("nprobe", 16)))
    index = DescriptorIndex.build(desc, iconf)
    data = MapData(
        points_xyz=bundle.points_xyz[gpts],
        point_ids=np.asarray(a("point_ids"))[gpts],
        point_rgb=np.asarray(a("point_rgb"))[gpts],
        descriptors=desc,
        desc_point=local_pt[bundle.desc_point[desc_rows]].astype(np.int32),
        desc_image=local_img[bundle.desc_image[desc_rows]].astype(np.int32),
        desc_level=np.asarray(a("desc_level"))[desc_rows],
        desc_xy=np.asarray(a("desc_xy"))[desc_rows],
        image_desc_ptr=desc_ptr,
        image_cam_from_world=np.asarray(a("image_cam_from_world"))[images],
        image_camera=bundle.image_camera[images],
        image_points_ptr=ip_ptr,
        image_points_idx=ip_idx,
        cluster_images_ptr=cl_ptr,
        cluster_images_idx=cl_idx,
        point_clusters_ptr=pc_ptr,
        point_clusters_idx=pc[:, 1].astype(np.int32),
        pca_mean=np.asarray(a("pca_mean")),
        pca_basis=np.asarray(a("pca_basis")),
        index_faiss=index.serialize(),
        cameras=list(bundle.cameras),
        image_names=[bundle.image_names[int(i)] for i in images],
        # The whole map's: every part then works at the same image scale (one Localizer).
        keypoint_scales=dict(keypoint_scales),
    )
    index_info = {"kind": index.kind, "nlist": index.nlist, "nprobe": index.nprobe}
    return data, gpts, index_info


def _vote_sample(
    bundle: MapBundle, fraction: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """A random ``fraction`` of every image's descriptors (at least ``MIN_VOTES_PER_IMAGE``),
    and the image each was extracted from: (vote_desc, vote_images). Every image is
    represented, so every place can win the vote."""
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(bundle.n_images):
        a, b = int(bundle.image_desc_ptr[i]), int(bundle.image_desc_ptr[i + 1])
        n = min(b - a, max(MIN_VOTES_PER_IMAGE, int(round(fraction * (b - a)))))
        rows.append(np.sort(rng.choice(np.arange(a, b), n, replace=False)))
    sel = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    return np.asarray(bundle.array("descriptors")[sel]), bundle.desc_image[sel].astype(np.int32)


def _save(tmp: Path, name: str, arr: np.ndarray, dtype: str) -> ArrayEntry:
    arr = np.ascontiguousarray(arr, dtype=np.dtype(dtype))
    path = tmp / f"{name}.npy"
    with open(path, "wb") as f:
        np.save(f, arr, allow_pickle=False)
        f.flush()
        os.fsync(f.fileno())
    return ArrayEntry(
        file=path.name,
        dtype=arr.dtype.str,
        shape=list(arr.shape),
        sha256=_sha256(path),
        bytes=path.stat().st_size,
    )


def split_bundle(
    bundle: MapBundle,
    out_dir: str | Path,
    name: str,
    *,
    parts: int | None = None,
    max_points: int | None = None,
    overlap: float = 0.25,
    vote_fraction: float = 0.05,
    progress: Callable[[str], None] | None = None,
    packed: bool = True,
) -> Path:
    """Split ``bundle`` into a sub-map set ``out_dir/name`` (module docstring), atomically.

    ``parts``: how many sub-maps; or ``max_points``: cut until each holds at most that many
    points (a single cluster is never cut). ``overlap``: images within this many scene scales
    of a part's own cameras join it. ``vote_fraction``: the share of each part's points whose
    descriptors go into the global place-recognition sample. ``packed``: parts as packed
    bundles (``map/bundle.py``: one mapped file, a load ~4x less CPU; False: one .npy per
    array, as sets written before them, which are still read)."""
    validate_name(name)
    if (parts is None) == (max_points is None):
        raise InputError("give the number of sub-maps (parts) or max_points, not both")
    if parts is not None and parts < 1:
        raise InputError(f"parts must be at least 1, got {parts}")
    if max_points is not None and max_points < 1:
        raise InputError(f"max_points must be at least 1, got {max_points}")
    if not (overlap >= 0 and np.isfinite(overlap)):
        raise InputError(f"overlap must be a non-negative number of scene scales, got {overlap}")
    if not 0 < vote_fraction <= 1:
        raise InputError(f"vote_fraction must be in (0, 1], got {vote_fraction}")
    say = progress or (lambda msg: None)
    centers = np.array([c.center for c in bundle.image_cam_from_world]).reshape(-1, 3)
    axes = np.array([c.rotation[2] for c in bundle.image_cam_from_world]).reshape(-1, 3)
    groups = _cluster_groups(bundle, centers, parts, max_points)
    clustered = np.zeros(bundle.n_images, bool)
    clustered[bundle.cluster_images_idx] = True
    reach = overlap * bundle.scene_scale
    part_images: list[np.ndarray] = []
    for g in groups:
        own = np.unique(_gather(bundle.cluster_images_ptr, bundle.cluster_images_idx, g))
        d = np.linalg.norm(centers[:, None, :] - centers[None, own, :], axis=2).min(axis=1)
        part_images.append(np.nonzero(d <= reach)[0])
    # An image in no cluster (none in builder maps) goes with its nearest part's cameras.
    for i in np.nonzero(~clustered)[0]:
        k = int(
            np.argmin([np.linalg.norm(centers[p] - centers[i], axis=1).min() for p in part_images])
        )
        part_images[k] = np.union1d(part_images[k], [i])

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    final = out_dir / name
    tmp = out_dir / f".{name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        entries: dict[str, ArrayEntry] = {}
        part_entries: list[PartEntry] = []
        part_points: list[np.ndarray] = []
        bboxes = []
        for k, images in enumerate(part_images):
            data, gpts, index_info = _part_data(bundle, images, bundle.keypoint_scales)
            pdir = write_bundle(
                data,
                tmp,
                part_folder(k),
                source={"submap_of": bundle.name, "build_id": bundle.build_id, "part": k},
                params=bundle.manifest.params,
                index_info=index_info,
                packed=packed,
            )
            part = MapBundle(pdir, verify=False)
            part_entries.append(
                PartEntry(
                    folder=part_folder(k),
                    build_id=part.build_id,
                    manifest_sha256=_sha256(pdir / MANIFEST),
                    points=part.n_points,
                    descriptors=part.n_descriptors,
                    images=part.n_images,
                    clusters=part.n_clusters,
                    memory_bytes=part.memory_bytes(),
                )
            )
            entries[points_array(k)] = _save(tmp, points_array(k), gpts, POINTS_SPEC[0])
            part_points.append(gpts)
            xyz = np.concatenate([bundle.points_xyz[gpts], centers[images]])
            bboxes.append(np.concatenate([xyz.min(axis=0), xyz.max(axis=0)]))
            say(
                f"part {k + 1}/{len(part_images)}: {len(images)} images, {len(gpts)} points, "
                f"{part.n_descriptors} descriptors"
            )
        vdesc, vimg = _vote_sample(bundle, vote_fraction)
        pi_ptr, pi_idx = _csr(part_images)
        pc_ptr, pc_idx = _csr([np.asarray(g) for g in groups])
        arrays = {
            "image_centers": centers,
            "image_axes": axes,
            "part_images_ptr": pi_ptr,
            "part_images_idx": pi_idx,
            "part_bbox": np.array(bboxes).reshape(-1, 6),
            "part_clusters_ptr": pc_ptr,
            "part_clusters_idx": pc_idx,
            "vote_desc": vdesc,
            "vote_images": vimg,
        }
        for aname, (dtype, _) in GLOBAL_SPECS.items():
            entries[aname] = _save(tmp, aname, arrays[aname], dtype)
        manifest = SetManifest(
            name=name,
            build_id=time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + uuid.uuid4().hex[:8],
            created_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            source={"bundle": bundle.name, "build_id": bundle.build_id, "path": str(bundle.path)},
            params={
                "parts": parts,
                "max_points": max_points,
                "overlap": overlap,
                "vote_fraction": vote_fraction,
            },
            scene_scale=bundle.scene_scale,
            points=bundle.n_points,
            images=bundle.n_images,
            clusters=bundle.n_clusters,
            parts=part_entries,
            arrays=entries,
        )
        publish(tmp, final, manifest, SET_MANIFEST, SET_SHA256)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


# ============================================================================ reading
def read_set_manifest(path: str | Path) -> SetManifest:
    """The set's manifest, after checking it against ``submaps.sha256``."""
    path = Path(path)
    if not (path / SET_MANIFEST).exists():
        raise BundleError(
            f"{path} is not a sub-map set: {SET_MANIFEST} is missing (make one with "
            "'sfmloc map split')"
        )
    text = _read_small_file(path / SET_MANIFEST, MAX_MANIFEST_BYTES)
    expect = _read_small_file(path / SET_SHA256, 4096).decode("ascii", "replace").split()
    if len(expect) != 2 or expect[1] != SET_MANIFEST:
        raise BundleError(f"{path / SET_SHA256}: not a checksum line for {SET_MANIFEST}")
    if hashlib.sha256(text).hexdigest() != expect[0].lower():
        raise BundleError(
            f"{path / SET_MANIFEST}: checksum mismatch (the manifest was edited or is corrupt)"
        )
    try:
        raw = json.loads(text.decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BundleError(f"{path / SET_MANIFEST}: unreadable manifest ({exc})") from None
    if not isinstance(raw, dict) or raw.get("format") != SET_FORMAT:
        raise BundleError(f"{path / SET_MANIFEST}: not an sfmloc sub-map set")
    if raw.get("version") != SET_VERSION:
        raise BundleError(
            f"{path / SET_MANIFEST}: sub-map set version {raw.get('version')} is not supported "
            f"(expects {SET_VERSION}); split the map again"
        )
    try:
        return SetManifest.model_validate(raw)
    except ValidationError as exc:
        raise BundleError(f"{path / SET_MANIFEST}: invalid manifest:\n{exc}") from None


def _array_problems(
    path: Path, aname: str, entry: ArrayEntry | None, spec: tuple[str, int], checksums: bool
) -> list[str]:
    if entry is None:
        return [f"array {aname} is not in the manifest"]
    apath = path / entry.file
    if apath.is_symlink() or not apath.is_file():
        return [f"{entry.file}: missing or not a regular file"]
    if apath.stat().st_size != entry.bytes:
        return [f"{entry.file}: size {apath.stat().st_size} B, manifest says {entry.bytes} B"]
    if checksums and _sha256(apath) != entry.sha256:
        return [f"{entry.file}: checksum mismatch (corrupt)"]
    try:
        arr = load_npy(apath, mmap_mode="r")
    except Exception as exc:  # noqa: BLE001 - any failure to parse the .npy is corruption
        return [f"{entry.file}: unreadable .npy ({exc})"]
    if (
        arr.dtype.str != np.dtype(spec[0]).str
        or arr.ndim != spec[1]
        or list(arr.shape) != entry.shape
    ):
        return [f"{entry.file}: dtype/shape {arr.dtype.str}{list(arr.shape)} do not match"]
    return []


def verify_submap_set(path: str | Path, checksums: bool = True) -> list[str]:
    """Every problem found in the set at ``path``: its manifest, its global arrays, and every
    part (a complete bundle whose manifest is the one the set recorded). Empty when intact."""
    path = Path(path)
    try:
        m = read_set_manifest(path)
    except BundleError as exc:
        return [str(exc)]
    problems: list[str] = []
    specs = dict(GLOBAL_SPECS)
    specs.update({points_array(k): POINTS_SPEC for k in range(len(m.parts))})
    for aname, spec in specs.items():
        problems += _array_problems(path, aname, m.arrays.get(aname), spec, checksums)
    for k, part in enumerate(m.parts):
        if part.folder != part_folder(k):
            problems.append(f"part {k}: folder {part.folder!r}, expected {part_folder(k)!r}")
            continue
        pdir = path / part.folder
        if pdir.is_symlink() or not pdir.is_dir():
            problems.append(f"{part.folder}: missing or not a folder")
            continue
        if (pdir / MANIFEST).is_file() and _sha256(pdir / MANIFEST) != part.manifest_sha256:
            problems.append(f"{part.folder}: its manifest is not the one this set recorded")
            continue
        problems += [f"{part.folder}: {p}" for p in verify_bundle(pdir, checksums)]
    return problems


class SubmapSet:
    """A sub-map set's global index (loaded once, small) and access to its parts, which are
    loaded on demand (``load_part``). Read-only and safe to share between threads."""

    def __init__(self, path: str | Path, *, verify: bool = True) -> None:
        self.path = Path(path)
        if verify:
            problems = verify_submap_set(self.path, checksums=True)
            if problems:
                raise BundleError(f"sub-map set {self.path} is corrupt: " + "; ".join(problems))
        self.manifest = read_set_manifest(self.path)
        m = self.manifest
        self.name = m.name
        self.build_id = m.build_id
        self.scene_scale = m.scene_scale
        a: dict[str, np.ndarray] = {}
        for aname, (dtype, ndim) in GLOBAL_SPECS.items():
            problems = _array_problems(self.path, aname, m.arrays.get(aname), (dtype, ndim), False)
            if problems:
                raise BundleError(f"sub-map set {self.path}: {problems[0]}")
            file = self.path / m.arrays[aname].file
            if aname == "vote_desc":  # only the index built from it stays in memory
                a[aname] = load_npy(file, mmap_mode="r")
            else:
                a[aname] = load_npy(file)
        K = len(m.parts)
        for aname, n in (
            ("part_images_ptr", K + 1),
            ("part_clusters_ptr", K + 1),
        ):
            ptr = a[aname]
            if len(ptr) != n or ptr[0] != 0 or np.any(np.diff(ptr) < 0):
                raise BundleError(f"sub-map set {self.path}: {aname} is not a valid offset array")
        L = m.clusters
        for aname, n in (
            ("part_clusters_idx", L),
            ("part_images_idx", m.images),
            ("vote_images", m.images),
        ):
            v = a[aname]
            if len(v) and (v.min() < 0 or v.max() >= n):
                raise BundleError(f"sub-map set {self.path}: {aname} refers outside 0..{n - 1}")
        if len(a["vote_images"]) != len(a["vote_desc"]) or len(a["image_centers"]) != m.images:
            raise BundleError(f"sub-map set {self.path}: global arrays disagree in length")
        self.image_centers = a["image_centers"]
        self.image_axes = a["image_axes"]
        self.part_images_ptr, self.part_images_idx = a["part_images_ptr"], a["part_images_idx"]
        self.part_bbox = a["part_bbox"]
        self.part_clusters_ptr = a["part_clusters_ptr"]
        self.part_clusters_idx = a["part_clusters_idx"]
        self.vote_images = a["vote_images"]
        # image -> parts holding it (images x parts booleans: small)
        self.image_parts = np.zeros((m.images, K), bool)
        for k in range(K):
            self.image_parts[self.part_images(k), k] = True
        self._vote_share = self.image_parts[self.vote_images].mean(axis=0)
        self.vote_desc = a["vote_desc"]
        # IVF-SQ8 like the parts' indexes (flat below a few hundred descriptors): 40 B per
        # sampled descriptor; the float16 copy stays on disk (memory-mapped).
        self._vote_index = (
            DescriptorIndex.build(self.vote_desc, IndexConf()) if len(self.vote_desc) else None
        )
        self._global_bytes = sum(int(v.nbytes) for n, v in a.items() if n != "vote_desc") + (
            self._vote_index.memory_bytes() if self._vote_index is not None else 0
        )

    @property
    def n_parts(self) -> int:
        return len(self.manifest.parts)

    def memory_bytes(self) -> int:
        """The global index's resident bytes (always in memory, outside the parts' budget)."""
        return self._global_bytes

    def part_memory_bytes(self, k: int) -> int:
        """What part ``k`` holds once loaded, as the kernel counts it: its ``memory_bytes``
        plus a page per array file (mapped arrays are resident in whole pages: on a 1.8 MB
        part the kernel counted 7 KB more than ``memory_bytes``)."""
        return part_resident_bytes(self.manifest.parts[k])

    def largest_part_bytes(self) -> int:
        return max((self.part_memory_bytes(k) for k in range(self.n_parts)), default=0)

    def part_images(self, k: int) -> np.ndarray:
        return self.part_images_idx[self.part_images_ptr[k] : self.part_images_ptr[k + 1]]

    def part_clusters(self, k: int) -> np.ndarray:
        return self.part_clusters_idx[self.part_clusters_ptr[k] : self.part_clusters_ptr[k + 1]]

    def part_points(self, k: int) -> np.ndarray:
        """Global point rows of part ``k``, sorted (its local row r is entry r)."""
        entry = self.manifest.arrays.get(points_array(k))
        if entry is None:
            raise BundleError(f"sub-map set {self.path}: no {points_array(k)} array")
        # One read of the whole .npy, its data being the file's last bytes: no header parsed
        # (the manifest says its dtype and shape, and the set's check at open compared them
        # with the header). ``np.load`` opened, parsed and read in ~10 syscalls, each a point
        # where the loader thread gave the GIL to the frame thread and waited for it back.
        n = entry.shape[0] if len(entry.shape) == 1 else -1
        itemsize = np.dtype(POINTS_SPEC[0]).itemsize
        try:
            with open(self.path / entry.file, "rb") as f:
                raw = f.read(entry.bytes + 1)
        except OSError as exc:
            raise BundleError(f"sub-map set {self.path}: {entry.file} ({exc.strerror})") from None
        start = len(raw) - n * itemsize
        if (
            entry.dtype != np.dtype(POINTS_SPEC[0]).str
            or n < 0
            or len(raw) != entry.bytes
            or start < 10
            or raw[:6] != b"\x93NUMPY"
        ):
            raise BundleError(f"sub-map set {self.path}: {entry.file} has the wrong dtype/shape")
        return np.frombuffer(raw, POINTS_SPEC[0], count=n, offset=start)

    def load_part(self, k: int, *, verify: bool = False) -> tuple[MapBundle, np.ndarray]:
        """Part ``k`` as a bundle and its global point rows (``verify``: checksums again; the
        set was verified when it was opened)."""
        if not 0 <= k < self.n_parts:
            raise InputError(f"sub-map {k} does not exist (the set has {self.n_parts})")
        bundle = MapBundle(self.path / self.manifest.parts[k].folder, verify=verify)
        gpts = self.part_points(k)
        if len(gpts) != bundle.n_points:
            raise BundleError(
                f"sub-map set {self.path}: part {k} has {bundle.n_points} points, its global "
                f"ids {len(gpts)}"
            )
        return bundle, gpts

    def pca(self) -> Pca:
        """The descriptors' PCA (one for the whole map: every part holds the same)."""
        pdir = self.path / self.manifest.parts[0].folder
        m = read_manifest(pdir)
        try:
            mean = load_array(pdir, m, "pca_mean")
            basis = load_array(pdir, m, "pca_basis")
        except (KeyError, OSError, ValueError) as exc:
            raise BundleError(f"sub-map set {self.path}: cannot read the PCA ({exc})") from None
        return Pca(np.asarray(mean, np.float32), np.asarray(basis, np.float32))

    def focal_scales(self) -> tuple[float, float]:
        """(native, coarsest) focal lengths in pixels the descriptors were computed at (the
        whole map's: a frame is resized once for every part)."""
        ks = read_manifest(self.path / self.manifest.parts[0].folder).keypoint_scales
        return float(ks.get("native_focal_px") or 0.0), coarsest_focal_px(ks)

    # ------------------------------------------------------------------ the global index
    def parts_near(
        self, cam_from_world: Rigid3d, angle_weight: float = 1.0, radius: float = 0.5
    ) -> np.ndarray:
        """Per part, how well its cameras cover a pose (higher is better): the sum over its
        cameras of exp(-(d / radius)^2), d = distance in scene scales plus ``angle_weight``
        times (1 - cos) of the angle between optical axes. A sum, not the nearest camera:
        overlapping parts share their boundary cameras, and the part holding more cameras
        around the pose holds more of what the camera sees (measured on the synthetic room in
        five parts: the nearest-camera rule kept a part whose poses were withheld on 13 frames
        of 60 beside a part that covered them)."""
        c = cam_from_world.center
        axis = cam_from_world.rotation[2]
        d = np.linalg.norm(self.image_centers - c, axis=1) / self.scene_scale
        d = d + angle_weight * (1.0 - self.image_axes @ axis)
        w = np.exp(-((d / radius) ** 2))
        return (w[:, None] * self.image_parts).sum(axis=0)

    def covered_by(self, parts: list[int]) -> np.ndarray:
        """Per part, the fraction of its images that ``parts`` hold (1 for those parts: their
        overlap tells how much of one place two parts are)."""
        if not parts:
            return np.zeros(self.n_parts)
        held = np.any(self.image_parts[:, list(parts)], axis=1)
        n = self.image_parts.sum(axis=0)
        return (self.image_parts & held[:, None]).sum(axis=0) / np.maximum(n, 1)

    def vote(self, desc: np.ndarray, ratio: float = VOTE_RATIO) -> np.ndarray:
        """Place-recognition scores of the parts for query descriptors ``desc``: each query's
        nearest descriptor in the sample votes for every part holding the image it was seen
        in, and a part scores its votes over their number by chance (its share of the
        sample): above 1, the frame looks like the part's images more than like the map's.
        Only distinctive queries vote: the nearest closer than ``ratio`` times the second
        (Lowe's test; 1 = every query). Measured on 8 rooms in 24 parts, 40 video frames (5
        per room): the rank of the first part covering the frame's true pose was at worst 12,
        first for 30/40, mean 1.85, with every query voting; at worst 3, first for 31/40, mean
        0.43 with 0.8 (procedural textures repeat across rooms: the ambiguous queries voted
        for the wrong rooms)."""
        scores = np.zeros(self.n_parts)
        if self._vote_index is None or len(desc) == 0:
            return scores
        k = 2 if 0 < ratio < 1 and self._vote_index.ntotal > 1 else 1
        D, I = self._vote_index.search(desc, k)
        ok = I[:, 0] >= 0
        if k == 2:  # faiss gives squared L2 distances
            ok &= (I[:, 1] < 0) | (D[:, 0] < ratio * ratio * D[:, 1])
        nn = I[ok, 0]
        if len(nn) == 0:
            return scores
        votes = self.image_parts[self.vote_images[nn]].sum(axis=0)
        return votes / (len(nn) * np.maximum(self._vote_share, 1e-12))


def part_resident_bytes(entry: PartEntry) -> int:
    """A part's bytes in memory (``SubmapSet.part_memory_bytes``) from its manifest entry."""
    # A page per array: a packed part's arrays each start on a page of their own (21 with the
    # derived rotations), as a .npy part's each have a file (20).
    return entry.memory_bytes + PAGE_BYTES * len(PACKED_SPECS)


def translate(rows: np.ndarray, from_points: np.ndarray, to_points: np.ndarray) -> np.ndarray:
    """Point rows of one part (``from_points``: its global ids) as rows of another: the same
    global point, or -1 where the other part does not hold it (or the row was -1)."""
    rows = np.asarray(rows)
    out = np.full(rows.shape, -1, np.int64)
    ok = rows >= 0
    g = from_points[rows[ok]]
    pos = np.searchsorted(to_points, g)
    pos_c = np.minimum(pos, max(len(to_points) - 1, 0))
    hit = (pos < len(to_points)) & (to_points[pos_c] == g) if len(to_points) else pos < 0
    vals = np.where(hit, pos_c, -1)
    out[ok] = vals
    return out
