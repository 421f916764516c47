"""The localization suites: their data and maps (prepared under ``OUT/work``), and the runs of
our engine and the SIFT peer on the suite's frames (``bench.reps`` repeats and orders them).

Maps:

- ``redkitchen``: ``build.main(images=DATA, poses=DATA/pgt_sfm_seq01.txt, stride=10)``, the
  builder's known-poses path; its SfM work folder is kept so the SIFT peer's map reuses the
  very same triangulated points (and their SIFT observations).
- ``redkitchen-split``: the same from frames 0-499 (a pose file restricted to them, written to
  the work folder), every 5th; frames 500-999 are replayed.
- ``synthetic-*``: ``sfmloc.synth`` renders; our bundle from the exact COLMAP model; the SIFT
  peer's map from the mapping images at their exact poses (known-poses triangulation).
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import re
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..errors import InputError
from ..eval.groundtruth import load_groundtruth
from ..eval.metrics import FrameRecord
from ..io.frames import FrameSource
from ..transforms import Rigid3d
from .config import BenchConf
from .sift_peer import SiftMap

log = logging.getLogger(__name__)

Progress = Callable[[str, float, str], None]

_FRAME_NO = re.compile(r"frame-(\d+)")


@dataclass
class Prepared:
    """A suite ready to run: frames, ground truth, our bundle and the SIFT peer's map."""

    name: str
    kind: str  # "real" or "synthetic"
    frames_dir: Path
    camera: Camera
    groundtruth: list[Rigid3d | None]
    start: int
    count: int
    bundle_path: Path
    sift_map_path: Path
    info: dict = field(default_factory=dict)
    fps: float = 30.0  # the frames' clock: frame k at k / fps seconds

    @property
    def indices(self) -> list[int]:
        return list(range(self.start, self.start + self.count))


def _sfm_conf():
    from ..builder.sfm import SfmConf

    # The front-end's defaults, with the work folder kept for the SIFT peer's map.
    return SfmConf(keep_workdir=True)


def _fresh_dir(path: Path) -> Path:
    if path.exists():
        shutil.rmtree(path)
    path.mkdir(parents=True)
    return path


def _kept_workdir(parent: Path) -> Path:
    found = sorted(parent.glob("sfmloc-sfm-*"), key=lambda p: p.stat().st_mtime)
    if not found:
        raise InputError(f"no kept SfM work folder under {parent}")
    return found[-1]


def _reusable(bundle: Path, sift: Path, reuse: bool) -> bool:
    return reuse and (bundle / "manifest.json").is_file() and sift.is_file()


# What a cached map depends on besides its input data: the code that renders, builds and writes
# it (the peer's map too), relative to the sfmloc package. A change anywhere here rebuilds under
# --reuse (a stale map once survived a builder change, keyed by its data path alone).
BUILDER_SOURCES = (
    "builder",
    "features",
    "map",
    "io",
    "synth",
    "cameras.py",
    "transforms.py",
    "config.py",
    "bench/sift_peer.py",
    "bench/robust_data.py",
    "bench/suites.py",
)


@functools.cache
def builder_identity() -> dict:
    """The bundle format version, the sfmloc version and a hash of ``BUILDER_SOURCES``: part of
    every --reuse cache key of a built map or rendered data."""
    from .. import __version__
    from ..map.bundle import BUNDLE_VERSION

    source = source_hash(Path(__file__).resolve().parent.parent)
    return {"bundle": BUNDLE_VERSION, "sfmloc": __version__, "source": source}


def source_hash(root: Path) -> str:
    """A hash of the ``BUILDER_SOURCES`` under package folder ``root`` (names and bytes)."""
    h = hashlib.sha256()
    for rel in BUILDER_SOURCES:
        p = root / rel
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def cached(stamp: Path, key: dict, reuse: bool, what: str) -> bool:
    """Whether ``what`` (built before, recorded in ``stamp`` with its ``key``) can be reused:
    --reuse, and the same key with the same ``builder_identity``. Says which, and why not."""
    key = {**key, "builder": builder_identity()}
    old = json.loads(stamp.read_text()) if stamp.is_file() else None
    if reuse and old == key:
        log.info("reusing %s (same input, builder %s)", what, key["builder"]["source"])
        return True
    if not reuse:
        log.info("building %s", what)
    elif old is None:
        log.info("building %s (nothing cached)", what)
    elif old.get("builder") != key["builder"]:
        log.info("rebuilding %s: built by another builder (%s)", what, old.get("builder"))
    else:
        log.info("rebuilding %s: another input", what)
    return False


def stamp_cached(stamp: Path, key: dict) -> None:
    """Record that ``key`` (and today's builder) made what ``stamp`` sits beside."""
    stamp.write_text(json.dumps({**key, "builder": builder_identity()}))


def _limit(n: int, conf: BenchConf) -> int:
    return n if conf.frames is None else min(n, conf.frames)


# --------------------------------------------------------------------------- redkitchen
def restrict_pose_file(src: Path, dst: Path, first: int, last: int) -> int:
    """Copy the pose lines of frames ``first..last`` (by the frame number in the name)."""
    lines = []
    for line in src.read_text().splitlines():
        m = _FRAME_NO.search(line)
        if (
            line.strip()
            and not line.lstrip().startswith("#")
            and m
            and first <= int(m.group(1)) <= last
        ):
            lines.append(line)
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text("\n".join(lines) + "\n")
    return len(lines)


def build_known_poses_maps(
    name: str,
    images: Path,
    poses: Path,
    camera: Camera,
    stride: int,
    maps: Path,
    work: Path,
    sift_path: Path,
    progress: Progress,
) -> Path:
    """Our bundle ``maps/name`` from every ``stride``-th posed image (the builder's known-poses
    path) and the SIFT peer's map of the very same triangulated points; the bundle's path."""
    from ..builder import build
    from ..map.bundle import MapBundle

    sfm_dir = _fresh_dir(work / "sfm")
    sfm_conf = _sfm_conf()
    t0 = time.perf_counter()
    path = build.main(
        build.preset("default"),
        name,
        maps,
        images=images,
        poses=poses,
        camera=camera,
        stride=stride,
        sfm_conf=sfm_conf,
        workdir=sfm_dir,
        progress=progress,
    )
    log.info("%s: bundle built in %.1f s", name, time.perf_counter() - t0)
    bundle = MapBundle(maps / name, verify=False)
    ids = bundle.array("point_ids")
    SiftMap.from_sfm_workdir(_kept_workdir(sfm_dir), ids, sfm_conf.model_dump()).save(sift_path)
    shutil.rmtree(sfm_dir, ignore_errors=True)  # the database is no longer needed
    return Path(path)


def prepare_redkitchen(conf: BenchConf, work: Path, split: bool, progress: Progress) -> Prepared:
    name = "redkitchen-split" if split else "redkitchen"
    data = Path(conf.data)
    poses = data / conf.poses
    if not poses.is_file():
        raise InputError(
            f"real data not found: {poses} (pass --data PATH to a folder of frame-NNNNNN.color.jpg "
            "and "
            f"{conf.poses}, or run only the synthetic suites: --suite synthetic-walk)"
        )
    camera = Camera.parse(conf.camera)
    source = FrameSource(data)
    n = len(source)
    suite_work = work / name
    bundle_path = work / "maps" / name
    sift_path = suite_work / "sift-map.npz"
    if split:
        half = n // 2
        map_poses = suite_work / f"poses-0-{half - 1}.txt"
        stride, start, count = 5, half, n - half
    else:
        map_poses, stride, start, count = poses, 10, 0, n
    info: dict = {
        "map_images": f"every {stride}th of frames "
        + (f"0-{n // 2 - 1}" if split else f"0-{n - 1}"),
        "stride": stride,
    }
    stamp = suite_work / "map-source.json"
    source_id = {
        "data": str(data.resolve()),
        "poses": conf.poses,
        "frames": n,
        "stride": stride,
        "split": split,
    }
    reuse = _reusable(bundle_path, sift_path, conf.reuse)
    if not cached(stamp, source_id, reuse, str(bundle_path)):
        if split:
            k = restrict_pose_file(poses, map_poses, 0, n // 2 - 1)
            log.info("%s: %d poses of frames 0-%d in %s", name, k, n // 2 - 1, map_poses)
        build_known_poses_maps(
            name, data, map_poses, camera, stride, work / "maps", suite_work, sift_path, progress
        )
        stamp_cached(stamp, source_id)
    gt = load_groundtruth(poses, source.names(), [source.stamp(i) for i in range(n)], source.fps)
    return Prepared(
        name, "real", data, camera, gt, start, _limit(count, conf), bundle_path, sift_path, info
    )


# --------------------------------------------------------------------------- synthetic
def synth_conf(conf: BenchConf, kind: str):
    """The bench's synthetic room (seed, mapping views, video length), trajectory ``kind``."""
    from ..synth.config import preset as synth_preset

    return synth_preset(
        kind if kind in ("flight", "orbit") else "default",
        seed=conf.seed,
        mapping_views=conf.synth_mapping_views,
        trajectory={"n_frames": conf.synth_frames},
    )


def prepare_synthetic(conf: BenchConf, work: Path, kind: str, progress: Progress) -> Prepared:
    from ..builder import build
    from ..synth.main import run as synth_run

    name = f"synthetic-{kind}"
    suite_work = work / name
    data = suite_work / "data"
    bundle_path = work / "maps" / name
    sift_path = suite_work / "sift-map.npz"
    sconf = synth_conf(conf, kind)
    stamp = suite_work / "synth-conf.json"
    key = {"synth": json.loads(json.dumps(sconf.model_dump()))}
    reuse = conf.reuse and (data / "scene.json").is_file()
    same_data = cached(stamp, key, reuse, f"{name}'s rendered data {data}")
    if not same_data:
        progress(name, 0.0, "rendering the synthetic data set")
        t0 = time.perf_counter()
        res = synth_run(sconf, data, overwrite=True)
        stamp_cached(stamp, key)
        log.info(
            "%s: rendered %d mapping views and %d frames in %.1f s",
            name,
            res.n_mapping,
            res.n_frames,
            time.perf_counter() - t0,
        )
    camera = Camera.from_json(data / "camera.json")
    map_stamp = suite_work / "map-source.json"
    reuse = same_data and _reusable(bundle_path, sift_path, True)
    if not cached(map_stamp, key, reuse, str(bundle_path)):
        build.main(
            build.preset("default"),
            name,
            work / "maps",
            colmap=data / "sparse",
            images=data / "images",
            progress=progress,
        )
        build_sift_map_of_model(
            data / "sparse", data / "images", camera, suite_work, sift_path, progress
        )
        stamp_cached(map_stamp, key)
    source = FrameSource(data / "video")
    n = len(source)
    gt = load_groundtruth(
        data / "groundtruth.tum", source.names(), [source.stamp(i) for i in range(n)], source.fps
    )
    info = {
        "map_images": f"{conf.synth_mapping_views} rendered mapping views (exact COLMAP model)",
        "trajectory": kind,
        "seed": conf.seed,
    }
    return Prepared(
        name,
        "synthetic",
        data / "video",
        camera,
        gt,
        0,
        _limit(n, conf),
        bundle_path,
        sift_path,
        info,
    )


def build_sift_map_of_model(
    model_dir: Path, images: Path, camera: Camera, work: Path, sift_path: Path, progress: Progress
) -> Path:
    """The SIFT peer's map: SIFT of the model's images triangulated at the model's exact poses."""
    from ..builder import sfm
    from ..io.colmap import read_model
    from ..io.poses import write_colmap_list

    model = read_model(model_dir)
    ims = sorted(model.images.values(), key=lambda im: im.name)
    pose_file = write_colmap_list(
        work / "map_poses.txt", [im.name for im in ims], [im.cam_from_world for im in ims]
    )
    sfm_dir = _fresh_dir(work / "sfm")
    sfm_conf = _sfm_conf()
    rec = sfm.triangulate_known_poses(
        images, pose_file, camera, conf=sfm_conf, workdir=sfm_dir, progress=progress
    )
    ids = np.array(sorted(rec.points3D), np.int64)
    SiftMap.from_sfm_workdir(_kept_workdir(sfm_dir), ids, sfm_conf.model_dump()).save(sift_path)
    shutil.rmtree(sfm_dir, ignore_errors=True)
    return sift_path


def prepare(name: str, conf: BenchConf, work: Path, progress: Progress) -> Prepared:
    if name == "redkitchen":
        return prepare_redkitchen(conf, work, False, progress)
    if name == "redkitchen-split":
        return prepare_redkitchen(conf, work, True, progress)
    if name.startswith("synthetic-"):
        return prepare_synthetic(conf, work, name.split("-", 1)[1], progress)
    raise InputError(f"unknown localization suite {name!r}")


# --------------------------------------------------------------------------- running
def peer_indices(prep: Prepared, peer_frames: int | None) -> tuple[list[int], int]:
    """The frames the peers run on: every ``stride``-th replayed frame; (indices, stride)."""
    idx = prep.indices
    if peer_frames is None or peer_frames >= len(idx):
        return idx, 1
    stride = int(np.ceil(len(idx) / peer_frames))
    return idx[::stride], stride


def replay_ours(
    prep: Prepared, bundle, source: FrameSource, progress: Progress, stage: str
) -> list[FrameRecord]:
    """Our engine (default config, a fresh ``Localizer``) on the suite's frames as a video,
    each frame reported to ``progress`` under ``stage``."""
    from ..engine import EngineConf
    from ..eval.replay import replay

    recs, _decode = replay(
        bundle,
        source,
        prep.camera,
        EngineConf(),
        prep.groundtruth,
        start=prep.start,
        max_frames=prep.count,
        on_frame=lambda r: progress(
            stage, (r.index - prep.start + 1) / prep.count, f"{r.name} {r.status}"
        ),
    )
    return recs


def run_sift_peer(
    prep: Prepared, conf: BenchConf, sift_conf, progress: Progress, index_cache: dict | None = None
) -> list[FrameRecord]:
    """The pycolmap-sift peer on the suite's peer frames (``peer_indices``). The bench runs it
    after every rep of our engine and global-every-frame (``bench.reps``), so that they run in
    a process that has done nothing but load maps, as a server worker
    (docs/development.md#bench-isolation)."""
    from .peers import run_peer, sift_peer
    from .sift_peer import SiftLocalizer

    source = FrameSource(prep.frames_dir, fps=prep.fps)
    idx, stride = peer_indices(prep, conf.peer_frames)
    log.info("%s: pycolmap-sift on %d frames (every %d)", prep.name, len(idx), stride)
    sift_map = SiftMap.load(prep.sift_map_path)
    loc = SiftLocalizer(sift_map, prep.camera, sift_conf, index_cache)
    return run_peer(
        "pycolmap-sift",
        sift_peer(loc),
        source,
        idx,
        prep.groundtruth,
        progress=lambda s, f, m: progress(f"{prep.name}:{s}", f, m),
    )
