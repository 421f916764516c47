"""Input 3: images only -> full incremental SfM with pycolmap (CPU).

The result is in an arbitrary frame and scale of SfM's choosing (not metric, not gravity
aligned): poses estimated against it are in that frame too. Steps: SIFT; pairs in name order
(``sequential``: each image with the next ``sequential_overlap`` images and, with
``quadratic_overlap``, the next 2^k; no loop detection, which would need a vocabulary tree)
or all pairs (``exhaustive``); matching and verification; incremental mapping; the largest
model (most registered images) is kept. Global bundle adjustment runs when the model has
grown by ``global_ba_ratio`` (1.4; COLMAP's 1.1 took 16 instead of 11 CPU-s of mapping on 100
redkitchen frames for the same camera centres, 0.7 cm median from the known poses after a
similarity). With a given camera the intrinsics stay fixed
(``refine_given_intrinsics`` to refine them); without one, a SIMPLE_RADIAL camera is guessed
from the first image (EXIF focal length, else 1.2 x the larger side) and refined.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import pycolmap

from ...cameras import Camera
from ...errors import BuildError, ImageDecodeError
from ...io.colmap import Reconstruction
from .conf import SfmConf, incremental_options
from .convert import filter_points, reconstruction_from_pycolmap, reconstruction_stats
from .inputs import check_images, check_names, list_images, select_images
from .run import CancelCheck, Progress, Reporter, quiet_colmap, work_directory
from .stages import extract_features, match_pairs, to_pycolmap_camera

log = logging.getLogger(__name__)


def sequential_pairs(names: Sequence[str], overlap: int, quadratic: bool) -> list[tuple[str, str]]:
    """COLMAP's sequential pairing without loop detection: ``i`` with ``i+1..i+overlap`` and,
    when ``quadratic``, with ``i + 2^k`` for ``k < overlap``."""
    n = len(names)
    pairs: set[tuple[int, int]] = set()
    for i in range(n):
        for d in range(1, overlap + 1):
            if i + d < n:
                pairs.add((i, i + d))
        if quadratic:
            for k in range(overlap):
                if i + 2**k < n:
                    pairs.add((i, i + 2**k))
    return [(names[a], names[b]) for a, b in sorted(pairs)]


def exhaustive_pairs(names: Sequence[str]) -> list[tuple[str, str]]:
    return [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, len(names))]


def _guess_camera(path: Path) -> pycolmap.Camera:
    opts = pycolmap.ImageReaderOptions()
    opts.camera_model = "SIMPLE_RADIAL"
    try:
        return pycolmap.infer_camera_from_image(path, opts)
    except Exception as exc:  # noqa: BLE001 - pycolmap raises plain RuntimeError/ValueError
        raise ImageDecodeError(f"[input] cannot read image {path}: {exc}") from None


def reconstruct_images_only(
    image_dir: str | Path,
    camera: Camera | str | Path | None = None,
    conf: SfmConf | None = None,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    should_cancel: CancelCheck | None = None,
    *,
    image_names: Sequence[str] | None = None,
    stride: int = 1,
) -> Reconstruction:
    """Full SfM on the images of ``image_dir`` (optionally ``image_names``, every ``stride``-th
    in name order). All images share one camera and so must have one size. Progress stages:
    input, features, matching, mapping. The map's frame and scale are arbitrary."""
    conf = conf or SfmConf()
    rep = Reporter(progress, should_cancel)
    image_dir = Path(image_dir)
    cam = (
        None if camera is None else (camera if isinstance(camera, Camera) else Camera.parse(camera))
    )
    names = select_images(list_images(image_dir), image_names, stride, image_dir)
    check_names(names, image_dir)
    if len(names) < 2:
        raise BuildError(
            f"need at least two images for SfM, found {len(names)} in {image_dir}", stage="input"
        )
    with quiet_colmap():
        if cam is not None:
            pcam = to_pycolmap_camera(cam)
            pcam.has_prior_focal_length = True
            size = cam.size
            what = "the camera"
        else:
            pcam = _guess_camera(image_dir / names[0])
            size = (int(pcam.width), int(pcam.height))
            what = f"the first image ({names[0]})"
        check_images(image_dir, names, lambda _n: size, conf, rep, what=what)
        pycolmap.set_random_seed(conf.seed)
        with work_directory(workdir, conf.keep_workdir) as work:
            db_path = work / "database.db"
            extract_features(db_path, image_dir, names, pcam, conf, rep)
            rep.check("matching")
            if conf.matching == "exhaustive":
                pairs = exhaustive_pairs(names)
            else:
                pairs = sequential_pairs(names, conf.sequential_overlap, conf.quadratic_overlap)
            log.info("%s matching: %d image pairs", conf.matching, len(pairs))
            match_pairs(db_path, work, pairs, conf, rep)
            rep.check("mapping")
            opts = incremental_options(conf)
            fixed = cam is not None and not conf.refine_given_intrinsics
            opts.ba_refine_focal_length = not fixed
            opts.ba_refine_extra_params = not fixed
            opts.ba_refine_principal_point = False
            # Global BA less often (COLMAP: every 10% growth): a third less mapping time on
            # 100 redkitchen frames, same poses (final global BA still runs).
            opts.ba_global_frames_ratio = conf.global_ba_ratio
            opts.ba_global_points_ratio = conf.global_ba_ratio
            n_reg = [0]

            def next_image() -> None:
                n_reg[0] += 1
                rep.report(
                    "mapping", min(0.99, n_reg[0] / len(names)), f"registered {n_reg[0]} images"
                )

            rep.report("mapping", 0.0, f"incremental mapping of {len(names)} images")
            out_dir = work / "sparse"
            out_dir.mkdir()
            models = rep.run(
                "mapping",
                pycolmap.incremental_mapping,
                db_path,
                image_dir,
                out_dir,
                options=opts,
                next_image_callback=next_image,
            )
            if not models:
                raise BuildError(
                    f"incremental mapping found no model in {len(names)} images of {image_dir} "
                    "(too little overlap or texture?)",
                    stage="mapping",
                )
            best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
            if len(models) > 1:
                log.log(
                    logging.WARNING if best.num_reg_images() < len(names) else logging.INFO,
                    "SfM made %d models (%s images); keeping the largest",
                    len(models),
                    "+".join(str(m.num_reg_images()) for m in models.values()),
                )
            rec = reconstruction_from_pycolmap(best)
    dropped = filter_points(rec, conf.min_track_length, conf.max_reproj_error)
    st = reconstruction_stats(rec)
    if st["points3D"] == 0:
        raise BuildError(f"SfM of {image_dir} produced no 3D point", stage="mapping")
    n_unreg = len(names) - len(rec.images)
    if n_unreg:
        log.warning("%d of %d images could not be registered and are left out", n_unreg, len(names))
    msg = (
        f"{len(rec.images)}/{len(names)} images registered, {st['points3D']} points (dropped "
        f"{dropped}: "
        f"track < {conf.min_track_length} or error > {conf.max_reproj_error:g} px), "
        f"mean track {st['mean_track_length']:.2f}, "
        f"mean error {st['mean_reproj_error_px']:.2f} px; arbitrary SfM frame and scale"
    )
    log.info("images-only SfM: %s", msg)
    rep.report("mapping", 1.0, msg)
    return rec
