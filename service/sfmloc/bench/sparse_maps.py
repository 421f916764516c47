"""Localization against thin maps: ours against the ``pycolmap-sift`` peer on the same frames.

Maps (built under ``--work``, reused when present):

- ``rkN``: redkitchen seq-01, every N-th frame, known-poses triangulation (the builder's path,
  SfM work folder kept so the SIFT peer's map has the very same triangulated points);
- ``synN``: the synthetic room (walk) with 120 / N mapping views (N x the default view spacing,
  as the views spread over the same room), our bundle from the exact model; the peer's map from
  SIFT triangulated at the exact poses.

Per map: single-image relocalization of ``--reloc`` frames that are not map images, and (unless
``--replay 0``) our 30 Hz replay of the first ``--replay`` frames with the peer on every 10th.
A localized frame is *wrong* when its error exceeds 5% of the map's ``scene_scale`` or 10 deg.

    python -m sfmloc.bench.sparse_maps --work /tmp/sparse --maps rk30 rk60 syn6 --before-after
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..transforms import Rigid3d, pose_errors

log = logging.getLogger(__name__)

WRONG_FRACTION = 0.05  # of scene_scale
WRONG_DEG = 10.0


def _kept(parent: Path) -> Path:
    return sorted(parent.glob("sfmloc-sfm-*"), key=lambda p: p.stat().st_mtime)[-1]


def prepare(name: str, work: Path, data: Path, min_track: int, synth_ours: str = "exact") -> dict:
    """Build (or reuse) map ``name``; return paths, camera, ground truth and query frames.
    ``synth_ours``: our synthetic bundle from the exact model ("exact") or, like the peer's
    map, from SIFT triangulated at the exact poses ("triangulated")."""
    from ..builder import build, sfm
    from ..eval.groundtruth import load_groundtruth
    from ..io.frames import FrameSource
    from .config import REDKITCHEN_CAMERA, REDKITCHEN_POSES
    from .sift_peer import SiftMap

    tag = f"{name}-t{min_track}" + (
        "-tri" if name.startswith("syn") and synth_ours == "triangulated" else ""
    )
    mdir = work / tag
    bundle, sift_path = mdir / "map", mdir / "sift-map.npz"
    if name.startswith("rk"):
        stride = int(name[2:])
        camera = Camera.parse(REDKITCHEN_CAMERA)
        frames = data
        poses = data / REDKITCHEN_POSES
        source = FrameSource(data)
        n = len(source)
        gt = load_groundtruth(
            poses, source.names(), [source.stamp(i) for i in range(n)], source.fps
        )
        if not (bundle / "manifest.json").is_file() or not sift_path.is_file():
            sdir = mdir / "sfm"
            shutil.rmtree(sdir, ignore_errors=True)
            sdir.mkdir(parents=True)
            sconf = sfm.sfm_conf(
                "default", keep_workdir=True, min_track_length=min_track, two_view_below=0
            )
            build.main(
                build.preset("default"),
                "map",
                mdir,
                images=data,
                poses=poses,
                camera=camera,
                stride=stride,
                sfm_conf=sconf,
                workdir=sdir,
            )
            from ..map.bundle import MapBundle

            ids = MapBundle(bundle, verify=False).array("point_ids")
            SiftMap.from_sfm_workdir(_kept(sdir), ids, sconf.model_dump()).save(sift_path)
            shutil.rmtree(sdir, ignore_errors=True)
        # Queries: frames that are not map images, spread evenly over the sequence.
        cand = [i for i in range(n) if i % stride]
    else:
        from ..io.colmap import read_model
        from ..io.poses import write_colmap_list
        from ..synth.config import preset as synth_preset
        from ..synth.main import run as synth_run

        factor = int(name[3:])
        views = max(2, round(120 / factor))
        sdata = work / f"{name}-data"  # rendered once, shared by every map of this spacing
        if not (sdata / "scene.json").is_file():
            synth_run(
                synth_preset("default", mapping_views=views, trajectory={"n_frames": 300}),
                sdata,
                overwrite=True,
            )
        camera = Camera.from_json(sdata / "camera.json")
        frames = sdata / "video"
        source = FrameSource(frames)
        n = len(source)
        gt = load_groundtruth(
            sdata / "groundtruth.tum",
            source.names(),
            [source.stamp(i) for i in range(n)],
            source.fps,
        )
        if not (bundle / "manifest.json").is_file() or not sift_path.is_file():
            mdir.mkdir(parents=True, exist_ok=True)
            model = read_model(sdata / "sparse")
            ims = sorted(model.images.values(), key=lambda im: im.name)
            pf = write_colmap_list(
                mdir / "map_poses.txt", [im.name for im in ims], [im.cam_from_world for im in ims]
            )
            if synth_ours == "triangulated":
                build.main(
                    build.preset("default"),
                    "map",
                    mdir,
                    images=sdata / "images",
                    poses=pf,
                    camera=camera,
                    sfm_conf=sfm.sfm_conf("default", min_track_length=min_track, two_view_below=0),
                )
            else:
                build.main(
                    build.preset("default"),
                    "map",
                    mdir,
                    colmap=sdata / "sparse",
                    images=sdata / "images",
                )
            sdir = mdir / "sfm"
            shutil.rmtree(sdir, ignore_errors=True)
            sdir.mkdir(parents=True)
            sconf = sfm.sfm_conf(
                "default", keep_workdir=True, min_track_length=min_track, two_view_below=0
            )
            rec = sfm.triangulate_known_poses(
                sdata / "images", pf, camera, conf=sconf, workdir=sdir
            )
            ids = np.array(sorted(rec.points3D), np.int64)
            SiftMap.from_sfm_workdir(_kept(sdir), ids, sconf.model_dump()).save(sift_path)
            shutil.rmtree(sdir, ignore_errors=True)
        cand = list(range(n))
    return {
        "name": name,
        "bundle": bundle,
        "sift": sift_path,
        "camera": camera,
        "frames": frames,
        "gt": gt,
        "candidates": cand,
    }


def _classify(est: Rigid3d | None, gt: Rigid3d | None, scale: float) -> tuple[str, float | None]:
    if est is None:
        return "lost", None
    if gt is None:
        return "nogt", None
    dp, dr = pose_errors(est, gt)
    return ("wrong" if dp > WRONG_FRACTION * scale or dr > WRONG_DEG else "ok"), dp


def _summ(rows: list[tuple[str, float | None]]) -> dict:
    n = len(rows)
    loc = [r for r in rows if r[0] in ("ok", "wrong")]
    errs = [e for kind, e in rows if kind == "ok" and e is not None]  # "ok" rows have an error
    return {
        "frames": n,
        "localized": len(loc),
        "localized_pct": round(100.0 * len(loc) / max(1, n), 1),
        "wrong": sum(r[0] == "wrong" for r in rows),
        "median_cm": round(100 * float(np.median(errs)), 2) if errs else None,
    }


def evaluate(prep: dict, conf, n_reloc: int, n_replay: int, sift: bool) -> dict:
    from ..engine import relocalize
    from ..eval.replay import replay
    from ..io.frames import FrameSource
    from ..map.bundle import MapBundle
    from .peers import decode_frames
    from .sift_peer import SiftLocalizer, SiftMap

    bundle = MapBundle(prep["bundle"], verify=False)
    scale = bundle.scene_scale
    cam, gt = prep["camera"], prep["gt"]
    source = FrameSource(prep["frames"])
    cand = prep["candidates"]
    pick = [cand[int(round(k))] for k in np.linspace(0, len(cand) - 1, min(n_reloc, len(cand)))]
    sl = SiftLocalizer(SiftMap.load(prep["sift"]), cam) if sift else None
    ours, peer, inl = [], [], []
    for i, _name, _stamp, gray in decode_frames(source, pick):
        r = relocalize(gray, cam, bundle, conf)
        ours.append(_classify(r.cam_from_world, gt[i], scale))
        inl.append(r.inliers)
        if sl is not None:
            peer.append(_classify(sl.localize(gray).cam_from_world, gt[i], scale))
    ppi = np.diff(bundle.image_points_ptr)
    out = {
        "map": prep["name"],
        "images": bundle.n_images,
        "points": bundle.n_points,
        "points_per_image_median": float(np.median(ppi)),
        "scene_scale": round(scale, 3),
        "reloc": {"ours": _summ(ours), "sift": _summ(peer) if sift else None},
    }
    if n_replay:
        recs, _ = replay(bundle, source, cam, conf, gt, max_frames=n_replay)
        rows = [_classify(r.cam_from_world, r.gt_cam_from_world, scale) for r in recs]
        out["replay"] = {"ours": _summ(rows)}
        if sl is not None:
            idx = list(range(0, min(n_replay, len(source)), 10))
            prow = [
                _classify(sl.localize(g).cam_from_world, gt[i], scale)
                for i, _, _, g in decode_frames(source, idx)
            ]
            out["replay"]["sift_every10"] = _summ(prow)
            out["replay"]["ours_every10"] = _summ([rows[i] for i in idx if i < len(rows)])
    return out


def main(argv: list[str] | None = None) -> int:
    from ..engine import EngineConf

    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--work", default="/tmp/sfmloc-sparse")
    p.add_argument(
        "--data",
        default=str(Path(__file__).resolve().parents[3].parent / "shared/data/redkitchen-seq01"),
    )
    p.add_argument("--maps", nargs="+", default=["rk10", "rk30", "rk60", "syn1", "syn3", "syn6"])
    p.add_argument(
        "--min-track-length", type=int, default=3, help="known-poses maps (and the SIFT peer's)"
    )
    p.add_argument(
        "--synth-ours",
        choices=["exact", "triangulated"],
        default="exact",
        help="synthetic maps: our bundle from the exact model or from SIFT at the exact poses",
    )
    p.add_argument("--reloc", type=int, default=40)
    p.add_argument("--replay", type=int, default=300)
    p.add_argument("--no-sift", action="store_true")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="EngineConf overrides")
    p.add_argument("--json", help="append results as JSON lines here")
    p.add_argument(
        "--before-after",
        action="store_true",
        help="each map twice: tracks >= 3 without verification, then the defaults",
    )
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    over = {}
    for kv in a.set:
        k, v = kv.split("=", 1)
        over[k] = json.loads(v) if v[:1] in "0123456789-[{tf" else v
    EngineConf(**over)  # a bad --set fails here, before the long run
    work = Path(a.work)
    runs = [(a.min_track_length, over)]
    if a.before_after:
        # before: tracks >= 3, the paper's single RANSAC; after: the builder's rule (two-view
        # points where the median image would see < two_view_below points) and verification
        runs = [(3, {**over, "global_verify": False}), ("auto", {**over, "global_verify": True})]
    for name in a.maps:
        for mt, ov in runs:
            t0 = time.perf_counter()
            if mt == "auto":
                from ..builder.sfm import SfmConf
                from ..map.bundle import MapBundle

                b3 = MapBundle(
                    prepare(name, work, Path(a.data), 3, a.synth_ours)["bundle"], verify=False
                )
                ppi = float(np.median(np.diff(b3.image_points_ptr)))
                mt = 2 if ppi < SfmConf().two_view_below else 3
            prep = prepare(name, work, Path(a.data), mt, a.synth_ours)
            res = evaluate(prep, EngineConf(**ov), a.reloc, a.replay, not a.no_sift)
            res.update(
                {
                    "set": ov,
                    "min_track_length": mt,
                    "synth_ours": a.synth_ours,
                    "seconds": round(time.perf_counter() - t0),
                }
            )
            print(json.dumps(res), flush=True)
            if a.json:
                with open(a.json, "a") as f:
                    f.write(json.dumps(res) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
