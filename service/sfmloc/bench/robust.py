"""The ``robust`` suite (issue 9's test bed): our engine and the pycolmap-sift peer, on the same
frames, on the data users bring: other image sizes, sparser maps, other scene scales, other
motions and frame rates. One row per case, four groups:

- image size: the synthetic walk rendered at 640x480, 1280x960 and 3072x2048 (focal length
  scaled with the width) against the map of 640x480 mapping views; redkitchen frames upsampled
  3x to 1920x1440 (bicubic, intrinsics x3) against the map of 640x480 frames;
- map density: the synthetic map from every 1st, 3rd, 6th mapping view (1x, 3x, 6x the
  spacing); redkitchen maps from every 10th, 30th, 60th frame;
- scene scale: the synthetic room's model, map and ground truth scaled by 0.01 and 100 (points
  and camera centres; the images are the same files); the peer's map is its 1x map scaled
  (triangulation at scaled poses gives scaled points: its thresholds are in pixels and angles);
- motion: walk, flight and an orbit around the table (with a crate on it) at 30 Hz, and the
  same frames subsampled to 10 and 3 Hz (every 3rd / 10th frame, stamps kept); and the thin
  density-6x map at 3 Hz (walk, flight; in the map density group).

A low-rate row replays every offset of its step (every 10th frame starting at frame 0, 1, ...,
9: ten 3 Hz streams that together cover each 30 Hz frame once) and pools them: localized
share, wrong poses and median error are over all its streams' frames, and the peer's frames are
drawn from all of them. One offset hid the wrong poses: replaying all 10 offsets found 4 on the
density-6x walk at 3 Hz and 1 on its flight that the bench's offset 0 never showed (note-s5,
wrongpose; BenchConf.robust_offsets caps it, --quick runs 2 and the row says so).

Rows that are the same run (640x480 = 1x density = scale 1 = walk at 30 Hz) run once. Our
engine replays every frame of a row as a video; the peer runs on evenly strided frames (on
redkitchen, never a map image of the every-10th map); both are compared on those frames. A
crash of either method, or of a row's preparation, is recorded in the row and the suite goes
on; a method over the row's time budget stops and the row says so.

``run_robust(conf, work, progress, preps, sift_conf) -> dict`` is the suite's results entry.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import logging
import math
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..cameras import Camera
from ..errors import InputError
from ..eval.groundtruth import load_groundtruth
from ..eval.metrics import FrameRecord
from ..io.frames import FrameSource
from . import robust_data
from .config import OURS, BenchConf
from .stats import method_summary
from .suites import (
    Prepared,
    build_known_poses_maps,
    build_sift_map_of_model,
    cached,
    prepare_redkitchen,
    prepare_synthetic,
    stamp_cached,
    synth_conf,
)

if TYPE_CHECKING:
    from ..engine import EngineConf

log = logging.getLogger(__name__)

Progress = Callable[[str, float, str], None]
PEER = "pycolmap-sift"
GROUPS = ("image size", "map density", "scene scale", "motion")
# Targets per row: our median position error at most this multiple of the peer's.
MEDIAN_ERROR_FACTOR = 1.5
SIZES = ((1280, 960), (3072, 2048))
DENSITIES = (1, 3, 6)
REDKITCHEN_STRIDES = (10, 30, 60)
SCALES = (0.01, 100.0)
MOTIONS = ("walk", "flight", "orbit")
RATES_HZ = (30, 10, 3)
VIDEO_HZ = 30
# The thin map's low-rate rows (density-6x at 3 Hz): where the wrong poses at 3 Hz were found.
THIN_LOW_RATE = (6, 3, ("walk", "flight"))


@dataclass(frozen=True)
class RowSpec:
    name: str
    group: str
    text: str
    real: bool = False  # needs the redkitchen data


def ordinal(n: int) -> str:
    """'3rd', '10th', '21st': a row's step in words."""
    teen = n % 100 in (11, 12, 13)
    return f"{n}{'th' if teen else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')}"


def _scale_tag(s: float) -> str:
    return f"{s:g}".replace(".", "p")


def row_specs() -> list[RowSpec]:
    rows = [RowSpec("size-640x480", "image size", "synthetic walk at 640x480, the map's size")]
    rows += [
        RowSpec(f"size-{w}x{h}", "image size", f"the same walk rendered at {w}x{h}")
        for w, h in SIZES
    ]
    rows.append(
        RowSpec(
            "redkitchen-1920x1440",
            "image size",
            "redkitchen upsampled 3x, intrinsics x3; map from every 10th 640x480 frame",
            real=True,
        )
    )
    rows += [
        RowSpec(
            f"density-{k}x",
            "map density",
            f"synthetic map from every {k} of the 120 mapping views"
            if k > 1
            else "synthetic map from all mapping views",
        )
        for k in DENSITIES
    ]
    rows += [
        RowSpec(
            f"redkitchen-every-{k}th",
            "map density",
            f"redkitchen map from every {k}th frame",
            real=True,
        )
        for k in REDKITCHEN_STRIDES
    ]
    rows.append(RowSpec("scale-1", "scene scale", "the synthetic room as rendered (metres)"))
    rows += [
        RowSpec(
            f"scale-{s:g}",
            "scene scale",
            f"the room scaled by {s:g}: points and poses, images unchanged",
        )
        for s in SCALES
    ]
    rows += [
        RowSpec(
            f"{kind}-{hz}hz",
            "motion",
            f"synthetic {kind}"
            + (" around the table" if kind == "orbit" else "")
            + (
                f", every {ordinal(VIDEO_HZ // hz)} frame of the 30 Hz video"
                if hz != VIDEO_HZ
                else " at 30 Hz"
            ),
        )
        for kind in MOTIONS
        for hz in RATES_HZ
    ]
    k, hz, kinds = THIN_LOW_RATE
    rows += [
        RowSpec(
            f"density-{k}x-{kind}-{hz}hz",
            "map density",
            f"synthetic {kind} at {hz} Hz (every {ordinal(VIDEO_HZ // hz)} frame of the 30 Hz "
            f"video) on the map from every {k} of the 120 mapping views",
        )
        for kind in kinds
    ]
    return rows


def row_offsets(step: int, cap: int | None) -> list[int]:
    """The offsets a row of every ``step``-th frame replays: all ``step`` of them, or ``cap``
    evenly spread (always offset 0, the stream the bench ran before)."""
    n = step if cap is None else max(1, min(cap, step))
    return sorted({j * step // n for j in range(n)})


ROWS: tuple[RowSpec, ...] = tuple(row_specs())


def select_rows(patterns: list[str] | None) -> list[RowSpec]:
    """Rows whose name or group matches one of ``patterns`` (shell patterns); all for None."""
    if not patterns:
        return list(ROWS)
    out = [
        r
        for r in ROWS
        if any(fnmatch.fnmatch(r.name, p) or fnmatch.fnmatch(r.group, p) for p in patterns)
    ]
    unmatched = [
        p
        for p in patterns
        if not any(fnmatch.fnmatch(r.name, p) or fnmatch.fnmatch(r.group, p) for r in ROWS)
    ]
    if unmatched:
        raise InputError(
            f"--robust-rows: {', '.join(unmatched)} match no row; rows: "
            f"{', '.join(r.name for r in ROWS)}; groups: {', '.join(GROUPS)}"
        )
    return out


# Frames of the large-image rows: rendering, our engine while it relocalizes and SIFT all
# cost about in proportion to the pixels (a 3072x2048 frame takes ~20x a 640x480 one), so the
# 6 MP row gets 2/5 of the large-image frames and the peer a quarter of its frames there.
LARGE_PIXELS = 1.5 * 640 * 480
HUGE_PIXELS = 4_000_000


def large_row_frames(conf: BenchConf, pixels: int) -> int:
    n = conf.robust_large_frames
    return max(2, 2 * n // 5) if pixels > HUGE_PIXELS else n


def peer_row_frames(conf: BenchConf, pixels: int) -> int:
    n = conf.robust_peer_frames
    if pixels > HUGE_PIXELS:
        return max(1, n // 4)
    return max(1, n // 2) if pixels > LARGE_PIXELS else n


# --------------------------------------------------------------------------- the rows' data
class RobustData:
    """Builds each row's inputs once (maps, videos, derived frame folders) under ``work/robust``,
    reusing the other suites' data and maps when they ran in the same bench run; a failure is
    remembered and raised again for every row that needs the same input. ``read_only``: the
    inputs were built by ``sfmloc bench``'s prepare child (``prepare_robust``): a cached input
    missing raises instead of being built in this process, which times our engine
    (docs/development.md#bench-isolation)."""

    def __init__(
        self,
        conf: BenchConf,
        work: Path,
        progress: Progress,
        preps: dict[str, Prepared] | None = None,
        read_only: bool = False,
    ):
        self.conf, self.work, self.progress = conf, Path(work), progress
        self.read_only = read_only
        self.preps = dict(preps or {})
        self.root = self.work / "robust"
        self.root.mkdir(parents=True, exist_ok=True)
        self._memo: dict = {}

    def _once(self, key, fn):
        if key not in self._memo:
            try:
                self._memo[key] = (True, fn())
            except Exception as exc:  # noqa: BLE001 - remembered and raised again for every row
                self._memo[key] = (False, exc)
        ok, value = self._memo[key]
        if not ok:
            raise value
        return value

    def _cached(self, folder: Path, key: dict, make: Callable[[], object]) -> Path:
        """Run ``make`` (it fills ``folder``) unless --reuse and ``key`` made ``folder`` with
        today's builder (``suites.cached``)."""
        stamp = folder / "robust-source.json"
        if cached(stamp, key, self.conf.reuse, f"robust's {folder.name}"):
            return folder
        if self.read_only:
            from .prepare import PrepareError

            raise PrepareError(f"robust's {folder.name} was not prepared by the child process")
        folder.mkdir(parents=True, exist_ok=True)
        stamp.unlink(missing_ok=True)
        make()
        stamp_cached(stamp, key)
        return folder

    # ----------------------------------------------------------------- synthetic
    def base(self) -> Prepared:
        """The synthetic walk, its 120-view map and the peer's map (the synthetic-walk suite's)."""
        return self._once(
            "base",
            lambda: (
                self.preps.get("synthetic-walk")
                or prepare_synthetic(self.conf, self.work, "walk", self.progress)
            ),
        )

    def video(self, kind: str, size: tuple[int, int] | None = None) -> tuple[Path, Camera]:
        """Frames of trajectory ``kind`` at ``size`` (default 640x480): the synthetic suites'
        when they ran, else rendered (large sizes: only the large-image rows' frames)."""

        def make():
            if size is None and kind == "walk":
                b = self.base()
                return b.frames_dir, b.camera
            if size is None and f"synthetic-{kind}" in self.preps:
                p = self.preps[f"synthetic-{kind}"]
                return p.frames_dir, p.camera
            sconf = synth_conf(self.conf, kind)
            w, h = size or (sconf.width, sconf.height)
            n = (
                self.large_frames(size)
                if size
                else min(self.conf.robust_frames, sconf.trajectory.n_frames)
            )
            folder = self.root / f"video-{kind}-{w}x{h}"
            key = {"synth": sconf.model_dump(mode="json"), "size": [w, h], "frames": n}
            self.progress(f"robust: render {kind} {w}x{h}", 0.0, f"{n} frames")
            t0 = time.perf_counter()
            self._cached(
                folder, key, lambda: robust_data.render_video(sconf, folder / "frames", n, w, h)
            )
            log.info(
                "robust: %d %s frames at %dx%d in %.1f s", n, kind, w, h, time.perf_counter() - t0
            )
            return folder / "frames", Camera.from_json(folder / "frames" / "camera.json")

        return self._once(("video", kind, size), make)

    def large_frames(self, size: tuple[int, int]) -> int:
        return large_row_frames(self.conf, size[0] * size[1])

    def density_map(self, k: int) -> tuple[Path, Path]:
        """Our bundle and the peer's map from every ``k``-th synthetic mapping view."""

        def make():
            b = self.base()
            if k == 1:
                return b.bundle_path, b.sift_map_path
            data = b.frames_dir.parent
            folder = self.root / f"density-{k}x"
            name = f"robust-density-{k}x"
            sift = folder / "sift-map.npz"

            def build():
                from ..builder import build as builder

                model, names = robust_data.write_subset_model(data / "sparse", folder / "sparse", k)
                log.info("robust: density %dx: %d of the mapping views", k, len(names))
                builder.main(
                    builder.preset("default"),
                    name,
                    self.work / "maps",
                    colmap=model,
                    images=data / "images",
                    progress=self.progress,
                )
                # The peer's map failing (e.g. too few SIFT tracks) leaves our row to run.
                failed = folder / "sift-map-error.txt"
                failed.unlink(missing_ok=True)
                try:
                    build_sift_map_of_model(
                        model, data / "images", b.camera, folder, sift, self.progress
                    )
                except Exception as exc:  # noqa: BLE001 - recorded as the peer's failure
                    failed.write_text(f"building its map: {_error_text(exc)}")

            key = {"base": self._in_work(data), "k": k, "synth": self._synth_key()}
            self._cached(folder, key, build)
            return self.work / "maps" / name, sift

        return self._once(("density", k), make)

    def _in_work(self, path: Path) -> str:
        """``path`` as a cache key: relative to the work folder when inside it, so that a work
        folder copied or moved (``cp -r OUT/work OTHER/work``, then --reuse) keeps its rows
        (the absolute path rebuilt density and scale rows, 45 s each, in a copy)."""
        try:
            return Path(path).resolve().relative_to(self.work.resolve()).as_posix()
        except ValueError:
            return str(Path(path).resolve())

    def _synth_key(self) -> dict:
        return synth_conf(self.conf, "walk").model_dump(mode="json")

    def scaled(self, s: float) -> tuple[Path, Path, Path]:
        """Our bundle built from the room's model scaled by ``s``, the peer's map scaled, and the
        video's ground truth scaled (pose list)."""

        def make():
            b = self.base()
            data = b.frames_dir.parent
            tag = _scale_tag(s)
            folder = self.root / f"scale-{tag}"
            name = f"robust-scale-{tag}"

            def build():
                from ..builder import build as builder
                from .sift_peer import SiftMap

                model = robust_data.write_scaled_model(data / "sparse", folder / "sparse", s)
                builder.main(
                    builder.preset("default"),
                    name,
                    self.work / "maps",
                    colmap=model,
                    images=data / "images",
                    progress=self.progress,
                )
                sm = SiftMap.load(b.sift_map_path)
                SiftMap(sm.points_xyz * s, sm.point_ids, sm.desc, sm.desc_point, sm.sfm).save(
                    folder / "sift-map.npz"
                )
                robust_data.scale_pose_list(data / "video_poses.txt", folder / "video_poses.txt", s)

            key = {"base": self._in_work(data), "s": s, "synth": self._synth_key()}
            self._cached(folder, key, build)
            return self.work / "maps" / name, folder / "sift-map.npz", folder / "video_poses.txt"

        return self._once(("scale", s), make)

    def subsampled(self, kind: str, hz: int, offset: int = 0) -> Path:
        """Every (30 / ``hz``)-th frame of the row's 30 Hz span from frame ``offset`` (links)."""

        def make():
            frames, _cam = self.video(kind)
            files = FrameSource(frames).files[: self.conf.robust_frames]
            tag = f"-o{offset}" if offset else ""  # offset 0 keeps the folder it always had
            return robust_data.subsample_frames(
                files[offset:], VIDEO_HZ // hz, self.root / f"{kind}-{hz}hz{tag}"
            )

        return self._once(("sub", kind, hz, offset), make)

    # ----------------------------------------------------------------- redkitchen
    def has_redkitchen(self) -> bool:
        return (Path(self.conf.data) / self.conf.poses).is_file()

    def redkitchen(self) -> Prepared:
        return self._once(
            "rk",
            lambda: (
                self.preps.get("redkitchen")
                or prepare_redkitchen(self.conf, self.work, False, self.progress)
            ),
        )

    def redkitchen_map(self, stride: int) -> tuple[Path, Path]:
        def make():
            rk = self.redkitchen()
            if stride == rk.info.get("stride"):
                return rk.bundle_path, rk.sift_map_path
            folder = self.root / f"redkitchen-every-{stride}th"
            name = f"robust-redkitchen-every-{stride}th"
            sift = folder / "sift-map.npz"
            data = Path(self.conf.data)
            key = {"data": str(data.resolve()), "poses": self.conf.poses, "stride": stride}
            self._cached(
                folder,
                key,
                lambda: build_known_poses_maps(
                    name,
                    data,
                    data / self.conf.poses,
                    rk.camera,
                    stride,
                    self.work / "maps",
                    folder,
                    sift,
                    self.progress,
                ),
            )
            return self.work / "maps" / name, sift

        return self._once(("rkmap", stride), make)

    def redkitchen_upsampled(self, factor: int = 3) -> tuple[Path, Camera]:
        def make():
            rk = self.redkitchen()
            n = self.large_frames((rk.camera.width * factor, rk.camera.height * factor))
            files = FrameSource(rk.frames_dir).files[:n]
            folder = self.root / f"redkitchen-x{factor}"
            key = {"data": str(Path(self.conf.data).resolve()), "frames": n, "factor": factor}
            self._cached(
                folder,
                key,
                lambda: robust_data.upsample_frames(files, factor, folder / "frames", rk.camera),
            )
            return folder / "frames", rk.camera.scaled(factor)

        return self._once(("rkup", factor), make)


def _groundtruth(pose_file: Path, frames: Path, fps: float) -> list:
    src = FrameSource(frames, fps=fps)
    return load_groundtruth(pose_file, src.names(), [src.stamp(i) for i in range(len(src))], fps)


def prepare_row(spec: RowSpec, data: RobustData) -> Prepared:
    """The row's frames, camera, ground truth, our bundle and the peer's map."""
    conf = data.conf
    name = f"robust/{spec.name}"
    if spec.real:
        rk = data.redkitchen()
        # never compare on a map image of the every-10th map
        info: dict[str, Any] = {"exclude_every": 10}
        if spec.name == "redkitchen-1920x1440":
            frames, cam = data.redkitchen_upsampled()
            n = len(FrameSource(frames))
            return Prepared(
                name,
                "real",
                frames,
                cam,
                _groundtruth(Path(conf.data) / conf.poses, frames, VIDEO_HZ),
                0,
                n,
                rk.bundle_path,
                rk.sift_map_path,
                info,
            )
        stride = int(spec.name.split("-")[2].rstrip("th"))
        bundle, sift = data.redkitchen_map(stride)
        n = min(conf.robust_frames, len(rk.groundtruth))
        return Prepared(
            name,
            "real",
            rk.frames_dir,
            rk.camera,
            rk.groundtruth,
            0,
            n,
            bundle,
            sift,
            {**info, "map_stride": stride},
        )
    base = data.base()
    n30 = min(conf.robust_frames, base.count)
    if spec.name.startswith("size-") and spec.name != "size-640x480":
        w, h = (int(x) for x in spec.name[5:].split("x"))
        frames, cam = data.video("walk", (w, h))
        n = len(FrameSource(frames))
        return Prepared(
            name,
            "synthetic",
            frames,
            cam,
            _groundtruth(frames / "video_poses.txt", frames, VIDEO_HZ),
            0,
            n,
            base.bundle_path,
            base.sift_map_path,
            {},
        )
    if spec.name.startswith("density-") and spec.name.endswith("hz"):
        k, kind, rate = spec.name[8:].split("-")
        bundle, sift = data.density_map(int(k[:-1]))
        return _low_rate_row(name, data, kind, int(rate[:-2]), bundle, sift)
    if spec.name.startswith("density-"):
        bundle, sift = data.density_map(int(spec.name[8:-1]))
        failed = sift.parent / "sift-map-error.txt"
        info = {"peer_map_error": failed.read_text()} if failed.is_file() else {}
        return Prepared(
            name,
            "synthetic",
            base.frames_dir,
            base.camera,
            base.groundtruth,
            0,
            n30,
            bundle,
            sift,
            info,
        )
    if spec.name.startswith("scale-") and spec.name != "scale-1":
        bundle, sift, gt_file = data.scaled(float(spec.name[6:]))
        return Prepared(
            name,
            "synthetic",
            base.frames_dir,
            base.camera,
            _groundtruth(gt_file, base.frames_dir, VIDEO_HZ),
            0,
            n30,
            bundle,
            sift,
            {},
        )
    if spec.group == "motion":
        kind, rate = spec.name.split("-")
        hz = int(rate[:-2])
        if hz != VIDEO_HZ:
            return _low_rate_row(name, data, kind, hz, base.bundle_path, base.sift_map_path)
        frames, cam = data.video(kind)
        n = min(conf.robust_frames, len(FrameSource(frames)))
        gt = _groundtruth(_pose_file_of(data, kind), frames, hz)
        return Prepared(
            name,
            "synthetic",
            frames,
            cam,
            gt,
            0,
            n,
            base.bundle_path,
            base.sift_map_path,
            {},
            fps=hz,
        )
    # size-640x480, density-1x, scale-1: the synthetic walk as it is
    return Prepared(
        name,
        "synthetic",
        base.frames_dir,
        base.camera,
        base.groundtruth,
        0,
        n30,
        base.bundle_path,
        base.sift_map_path,
        {},
    )


def _low_rate_row(
    name: str, data: RobustData, kind: str, hz: int, bundle: Path, sift: Path
) -> Prepared:
    """A row of every (30 / ``hz``)-th frame of trajectory ``kind``, one stream per offset
    (``row_offsets``). The row's frames are the 30 Hz video's (the peer's frames and the
    per-frame records index them); ``info["offsets"]`` holds the step, the offsets run and
    each stream's folder, which ``run_ours`` replays at ``hz`` (stamps kept: frame k of a
    stream is 30 Hz frame offset + k * step)."""
    frames, cam = data.video(kind)
    n30 = min(data.conf.robust_frames, len(FrameSource(frames)))
    step = VIDEO_HZ // hz
    offsets = row_offsets(step, data.conf.robust_offsets)
    streams = [str(data.subsampled(kind, hz, o)) for o in offsets]
    return Prepared(
        name,
        "synthetic",
        frames,
        cam,
        _groundtruth(_pose_file_of(data, kind), frames, VIDEO_HZ),
        0,
        n30,
        bundle,
        sift,
        {"offsets": {"hz": hz, "step": step, "run": offsets, "streams": streams}},
    )


def pooled_indices(prep: Prepared) -> list[int]:
    """The row's frames our engine replays: all of ``prep.indices``, or for a low-rate row
    those of the offsets it runs."""
    off = prep.info.get("offsets")
    if not off:
        return prep.indices
    run = set(off["run"])
    return [i for i in prep.indices if i % off["step"] in run]


def _pose_file_of(data: RobustData, kind: str) -> Path:
    """The exact video poses of trajectory ``kind`` (COLMAP list, matched by name)."""
    frames, _ = data.video(kind)
    for p in (frames / "video_poses.txt", frames.parent / "video_poses.txt"):
        if p.is_file():
            return p
    raise InputError(f"no video_poses.txt next to {frames}")


# --------------------------------------------------------------------------- running a row
def peer_frames(prep: Prepared, n: int) -> list[int]:
    """``n`` frames evenly strided over the row (skipping excluded map images), centred."""
    every = prep.info.get("exclude_every")
    cand = [i for i in pooled_indices(prep) if not (every and i % every == 0)]
    if n >= len(cand):
        return cand
    stride = len(cand) / n
    return [cand[int(stride * (j + 0.5))] for j in range(n)]


class _OverBudget(Exception):
    pass


def _error_text(exc: BaseException) -> str:
    tb = traceback.extract_tb(exc.__traceback__)
    where = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""
    return f"{type(exc).__name__}: {exc}{where}"


def load_engine_conf(path: Path | None) -> EngineConf:
    """The EngineConf of ``--engine-config`` (the defaults without one): the file only, read
    by the loader of ``sfmloc replay --config``, not SFMLOC_ENGINE__* variables (a stray
    variable must not change a bench row unnoticed). An unknown key or a bad value raises
    ConfigError naming it."""
    from ..config import load_config
    from ..engine import EngineConf

    if path is None:
        return EngineConf()
    return load_config(EngineConf, path, prefix="SFMLOC_ENGINE__", environ={})


def _engine_config_doc(path: Path | None) -> dict | None:
    """What the report says about --engine-config: the file and the settings it gives."""
    if path is None:
        return None
    from ..config import read_config_file

    return {"file": str(path), "settings": read_config_file(path)}


def run_ours(
    prep: Prepared,
    bundle,
    budget_s: float,
    progress: Progress,
    engine_conf: EngineConf | None = None,
) -> tuple[list[FrameRecord], str | None, bool]:
    """Our engine on every frame of the row as a video: (records, error or None, stopped).
    A low-rate row's streams (one per offset) are replayed one after the other, each by a fresh
    engine, and pooled: each record's index is its frame's in the 30 Hz video. The time budget
    is the row's, over all streams. ``engine_conf``: an EngineConf (--engine-config), else the
    defaults."""
    from ..engine import EngineConf
    from ..eval.replay import replay

    recs: list[FrameRecord] = []
    total = len(pooled_indices(prep))
    t0 = time.perf_counter()

    try:
        for offset, step, source, gt, start, count in _streams(prep):

            def on_frame(r: FrameRecord, offset: int = offset, step: int = step) -> None:
                recs.append(dataclasses.replace(r, index=offset + r.index * step))
                progress(f"{prep.name}:{OURS}", len(recs) / total, f"{r.name} {r.status}")
                if time.perf_counter() - t0 > budget_s and len(recs) < total:
                    raise _OverBudget

            replay(
                bundle,
                source,
                prep.camera,
                engine_conf if engine_conf is not None else EngineConf(),
                gt,
                start=start,
                max_frames=count,
                on_frame=on_frame,
            )
    except _OverBudget:
        return _by_frame(recs), None, True
    except Exception as exc:  # noqa: BLE001 - a crash is a result of the row
        log.warning("%s: our engine failed: %s", prep.name, _error_text(exc))
        return _by_frame(recs), _error_text(exc), False
    return _by_frame(recs), None, False


def _by_frame(recs: list[FrameRecord]) -> list[FrameRecord]:
    """Pooled streams' records in the 30 Hz video's frame order (one stream: as replayed)."""
    return sorted(recs, key=lambda r: r.index)


def _streams(prep: Prepared) -> list[tuple[int, int, FrameSource, list, int, int]]:
    """What our engine replays for a row: (offset, step, frames, ground truth, start, count)
    per stream; one stream of the row's own frames unless it is a low-rate row."""
    off = prep.info.get("offsets")
    if not off:
        return [
            (
                0,
                1,
                FrameSource(prep.frames_dir, fps=prep.fps),
                prep.groundtruth,
                prep.start,
                prep.count,
            )
        ]
    step = off["step"]
    if prep.start != 0:
        raise ValueError(f"{prep.name}: a low-rate row starts at frame 0")
    gt30 = prep.groundtruth[prep.start : prep.start + prep.count]
    out = []
    for o, folder in zip(off["run"], off["streams"]):
        source = FrameSource(Path(folder), fps=off["hz"])
        out.append((o, step, source, gt30[o::step], 0, len(source)))
    return out


def run_sift(
    prep: Prepared, idx: list[int], sift_conf, budget_s: float, progress: Progress
) -> tuple[list[FrameRecord], str | None, bool]:
    """The peer on the frames ``idx`` (one untimed warm-up call first, as in every suite)."""
    from .peers import run_peer, sift_peer
    from .sift_peer import SiftLocalizer, SiftMap

    recs: list[FrameRecord] = []
    if prep.info.get("peer_map_error"):
        return recs, prep.info["peer_map_error"], False
    t0 = time.perf_counter()
    try:
        loc = SiftLocalizer(SiftMap.load(prep.sift_map_path), prep.camera, sift_conf)
        source = FrameSource(prep.frames_dir, fps=prep.fps)
        fn = sift_peer(loc)
        for k, i in enumerate(idx):
            recs += run_peer(PEER, fn, source, [i], prep.groundtruth, warmup=k == 0)
            progress(
                f"{prep.name}:{PEER}", (k + 1) / len(idx), f"{recs[-1].name} {recs[-1].status}"
            )
            if time.perf_counter() - t0 > budget_s and k + 1 < len(idx):
                return recs, None, True
    except Exception as exc:  # noqa: BLE001 - a crash is a result of the row
        log.warning("%s: the peer failed: %s", prep.name, _error_text(exc))
        return recs, _error_text(exc), False
    return recs, None, False


def _nan_le(a: float, b: float) -> bool:
    return not math.isnan(a) and a <= b


def row_targets(
    ours_same: dict, peer_same: dict, ours_all: dict, ours_error: str | None, ours_stopped: bool
) -> dict[str, bool]:
    """The issue's targets for one row: localized >= the peer's, median position error <= 1.5x
    the peer's (met when the peer has none), no wrong pose on any of our frames, no crash."""
    p_med = peer_same["median_position_error_m"]
    o_med = ours_same["median_position_error_m"]
    return {
        "localized": ours_same["F"] > 0 and ours_same["F_loc_pct"] >= peer_same["F_loc_pct"],
        "median_error": math.isnan(p_med) or _nan_le(o_med, MEDIAN_ERROR_FACTOR * p_med),
        "no_wrong_pose": ours_all["wrong_poses"] == 0,
        "no_crash": ours_error is None and not ours_stopped,
    }


def summarize_row(ours: list[FrameRecord], peer: list[FrameRecord], scene_scale: float) -> dict:
    """Ours on all its frames; ours and the peer on the frames both ran (all of ours when the
    peer ran on none, e.g. its map failed: then only our own targets can fail)."""
    both = {r.index for r in ours} & {r.index for r in peer} if peer else {r.index for r in ours}
    return {
        "ours": method_summary(ours, scene_scale),
        "ours_same": method_summary([r for r in ours if r.index in both], scene_scale),
        "peer_same": method_summary([r for r in peer if r.index in both], scene_scale),
        "peer": method_summary(peer, scene_scale),
        "same_frames": len(both),
    }


def _offsets_doc(prep: Prepared) -> dict:
    """A low-rate row's streams in its results: {"offsets": {step, run, of}} (else nothing)."""
    off = prep.info.get("offsets")
    if not off:
        return {}
    return {"offsets": {"step": off["step"], "run": list(off["run"]), "of": off["step"]}}


def _map_info(bundle) -> dict:
    return {
        "images": bundle.n_images,
        "points": bundle.n_points,
        "descriptors": bundle.n_descriptors,
        "scene_scale": bundle.scene_scale,
    }


def run_row(
    prep: Prepared,
    n_peer: int,
    sift_conf,
    budget_s: float,
    progress: Progress,
    files_dir: Path | None = None,
    engine_conf: EngineConf | None = None,
) -> dict:
    """Both methods on one prepared row; its summary, targets, errors and timings. With
    ``files_dir``, each method's per-frame records go to ``frames-METHOD.json`` there (to see
    which frames were lost or wrong). ``engine_conf``: our engine's EngineConf (the defaults
    when None); the peer is not affected."""
    from ..map.bundle import MapBundle

    t0 = time.perf_counter()
    idx = peer_frames(prep, n_peer)
    bundle = MapBundle(prep.bundle_path, verify=False)  # built by this run (or --reuse)
    mp = _map_info(bundle)
    log.info(
        "%s: our engine on %d frames, the peer on %d",
        prep.name,
        len(pooled_indices(prep)),
        len(idx),
    )
    ours, ours_err, ours_stop = run_ours(prep, bundle, budget_s, progress, engine_conf)
    peer, peer_err, peer_stop = run_sift(prep, idx, sift_conf, budget_s, progress)
    out = summarize_row(ours, peer, mp["scene_scale"])
    out.update(
        {
            "frames": len(pooled_indices(prep)),
            "fps": prep.info["offsets"]["hz"] if prep.info.get("offsets") else prep.fps,
            **_offsets_doc(prep),
            "peer_frames": len(idx),
            "image_size": f"{prep.camera.width}x{prep.camera.height}",
            "map": mp,
            "ours_error": ours_err,
            "ours_stopped": ours_stop,
            "peer_error": peer_err,
            "peer_stopped": peer_stop,
            "wall_s": time.perf_counter() - t0,
        }
    )
    out["targets"] = row_targets(
        out["ours_same"], out["peer_same"], out["ours"], ours_err, ours_stop
    )
    out["met"] = all(out["targets"].values())
    if files_dir is not None:
        from .report import frame_dicts, write_json

        files_dir.mkdir(parents=True, exist_ok=True)
        for method, recs in ((OURS, ours), (PEER, peer)):
            write_json(files_dir / f"frames-{method}.json", frame_dicts(recs))
    return out


def _run_key(p: Prepared) -> tuple:
    return (
        str(p.frames_dir),
        p.start,
        p.count,
        p.fps,
        str(p.info.get("offsets")),
        str(p.bundle_path),
        str(p.sift_map_path),
        p.camera.to_string(),
    )


PREPARE_ERRORS = "prepare-errors.json"  # under work/robust: rows the child could not prepare


def prepare_robust(
    conf: BenchConf, work: Path, progress: Progress, preps: dict[str, Prepared] | None = None
) -> dict[str, str]:
    """Build every selected row's inputs (maps, renders, frame folders; ``--reuse`` as in
    ``conf``) without running a row: ``sfmloc bench``'s prepare child does this, so that the
    process that times our engine builds nothing (bench.prepare). A row that cannot be prepared
    is not fatal: {row: reason}, also written to work/robust/prepare-errors.json, for
    ``run_robust(prepared=True)`` to record as the row's crash."""
    data = RobustData(conf, work, progress, preps)
    errors: dict[str, str] = {}
    for spec in select_rows(conf.robust_rows):
        if spec.real and not data.has_redkitchen():
            continue  # run_robust skips it, saying why
        log.info("robust/%s: preparing its data and maps", spec.name)
        try:
            prepare_row(spec, data)
        except Exception as exc:  # noqa: BLE001 - recorded in the row, the suite goes on
            errors[spec.name] = f"preparing the row: {_error_text(exc)}"
            log.warning("robust/%s: %s", spec.name, errors[spec.name])
    (data.root / PREPARE_ERRORS).write_text(json.dumps(errors, indent=1))
    return errors


def run_robust(
    conf: BenchConf,
    work: Path,
    progress: Progress,
    preps: dict[str, Prepared] | None = None,
    sift_conf=None,
    out: Path | None = None,
    prepared: bool = False,
) -> dict:
    """Every selected row; a row whose data are missing is skipped with the reason, a row whose
    preparation fails is recorded as a crash; the suite always goes on. With ``out``, per-frame
    records of each row go to ``out/robust/ROW/``. ``prepared``: ``prepare_robust`` ran (in
    the bench's prepare child) with this ``conf`` and ``work``: read its inputs, build none,
    and record the rows it could not prepare as their crash."""
    from .config import SiftPeerConf

    sift_conf = sift_conf or SiftPeerConf()
    # Only our engine's settings change with it. Row results are not cached (--reuse keeps
    # maps and rendered data, which the engine config does not touch), so every row runs
    # under this config.
    engine_conf = load_engine_conf(conf.robust_engine_config)
    engine_doc = _engine_config_doc(conf.robust_engine_config)
    data = RobustData(conf, work, progress, preps, read_only=prepared)
    prepare_errors: dict[str, str] = {}
    if prepared:
        prepare_errors = json.loads((data.root / PREPARE_ERRORS).read_text())
    t_start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    done: dict[tuple[Any, ...], dict[str, Any]] = {}  # run key -> the row that ran it

    def suite() -> dict:
        return {
            "kind": "robust",
            "rows": rows,
            "wall_s": time.perf_counter() - t_start,
            "frames": {
                "per_row": conf.robust_frames,
                "large_image_rows": conf.robust_large_frames,
                "peer_per_row": conf.robust_peer_frames,
                "budget_s": conf.robust_budget_s,
            },
            "sift_peer_conf": sift_conf.model_dump(),
            "engine_config": engine_doc,  # --engine-config (None: the defaults)
        }

    def save_partial() -> None:
        """The rows so far (a long run can be read before it ends)."""
        if out is not None:
            from .report import write_json

            (Path(out) / "robust").mkdir(parents=True, exist_ok=True)
            write_json(Path(out) / "robust" / "rows-so-far.json", suite())

    for spec in select_rows(conf.robust_rows):
        row: dict[str, Any] = {"name": spec.name, "group": spec.group, "text": spec.text}
        if spec.real and not data.has_redkitchen():
            row.update(
                status="skipped",
                reason=f"redkitchen data not found: {Path(conf.data) / conf.poses} (pass --data)",
            )
            log.info("robust/%s: skipped (%s)", spec.name, row["reason"])
            rows.append(row)
            save_partial()
            continue
        log.info("== robust/%s: %s", spec.name, spec.text)
        if spec.name in prepare_errors:  # the child's failure: not tried again here
            row.update(status="crash", reason=prepare_errors[spec.name])
            log.warning("robust/%s: %s", spec.name, row["reason"])
            rows.append(row)
            save_partial()
            continue
        try:
            prep = prepare_row(spec, data)
        except Exception as exc:  # noqa: BLE001 - recorded in the row, the suite goes on
            row.update(status="crash", reason=f"preparing the row: {_error_text(exc)}")
            log.warning("robust/%s: %s", spec.name, row["reason"])
            rows.append(row)
            save_partial()
            continue
        n_peer = peer_row_frames(conf, prep.camera.width * prep.camera.height)
        key = _run_key(prep) + (n_peer,)
        if key in done:
            same = done[key]
            row.update(
                same_as=same["name"],
                **{k: v for k, v in same.items() if k not in ("name", "group", "text")},
            )
        else:
            try:
                row.update(
                    status="ran",
                    **run_row(
                        prep,
                        n_peer,
                        sift_conf,
                        conf.robust_budget_s,
                        progress,
                        None if out is None else Path(out) / "robust" / spec.name,
                        engine_conf,
                    ),
                    engine_config=None if engine_doc is None else engine_doc["file"],
                )
                if out is not None:
                    row["files"] = f"robust/{spec.name}"  # relative to out
            except Exception as exc:  # noqa: BLE001 - e.g. the bundle does not load
                row.update(status="crash", reason=f"running the row: {_error_text(exc)}")
            done[key] = row
        rows.append(row)
        save_partial()
        log.info("robust/%s: %s", spec.name, row_line(row))
    return suite()


def row_line(row: dict, verdict: bool = True) -> str:
    """One line of a row's outcome (ours vs the peer), for the log and the targets."""
    if row["status"] != "ran":
        return f"{row['status']}: {row['reason']}"
    o, p = row["ours_same"], row["peer_same"]
    text = (
        (f"{offsets_text(row['offsets'])}: " if row.get("offsets") else "")
        + f"localized {o['F_loc_pct']:.0f}% vs {p['F_loc_pct']:.0f}%, median "
        f"{o['median_position_error_m']:.3g} vs {p['median_position_error_m']:.3g} units, "
        f"wrong poses {row['ours']['wrong_poses']}"
    )
    if row["ours_error"]:
        text += f"; our engine failed: {row['ours_error']}"
    if row["ours_stopped"]:
        text += "; our engine stopped at the time budget"
    if row["peer_error"]:
        text += f"; the peer failed: {row['peer_error']}"
    return text + (f", targets {'met' if row['met'] else 'MISSED'}" if verdict else "")


def offsets_text(off: dict) -> str:
    """A low-rate row's streams in words: 'offsets 0-9 of every 10th frame, pooled', or with
    fewer offsets than the step (--quick) which of how many."""
    run, step = off["run"], off["step"]
    every = f"every {ordinal(step)} frame"
    if len(run) == off["of"] and run == list(range(step)):
        return f"offsets 0-{step - 1} of {every}, pooled"
    return (
        f"offsets {', '.join(map(str, run))} of {every} ({len(run)} of its {off['of']} "
        "offsets only), pooled"
    )


def targets(suite: dict) -> list[dict]:
    """One acceptance entry per row (skipped rows say why)."""
    out = []
    for r in suite["rows"]:
        t = (
            f"robust/{r['name']}: localized >= peer, median error <= "
            f"{MEDIAN_ERROR_FACTOR:g}x peer, "
            "0 wrong poses, no crash"
        )
        if r["status"] != "ran":
            out.append(
                {
                    "target": t,
                    "met": False if r["status"] == "crash" else None,
                    "measured": f"{r['status']}: {r['reason']}",
                }
            )
            continue
        missed = [k for k, v in r["targets"].items() if not v]
        out.append(
            {
                "target": t,
                "met": r["met"],
                "measured": row_line(r, verdict=False)
                + (f" (missed: {', '.join(missed)})" if missed else ""),
            }
        )
    return out
