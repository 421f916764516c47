"""The ``pycolmap-sift`` peer: what a COLMAP or hloc-with-SIFT user runs to localize frames.

Map: the SIFT features of the map images, matched on pose-chosen pairs and triangulated with
pycolmap at the known poses (the builder's SfM front-end, ``sfmloc.builder.sfm``). Every 3D
point keeps the SIFT descriptors of its track's observations, read from the COLMAP database
the front-end leaves in its kept work folder (``SiftMap.from_sfm_workdir``).

Per frame (``SiftLocalizer.localize``): SIFT with the extractor and settings the map was built
with (``sfmloc.builder.sfm.stages.opencv_sift``: OpenCV's SIFT in COLMAP's keypoint convention,
RootSIFT), nearest neighbours among the map's descriptors (exact, or faiss HNSW at a recall
measured against exact search), Lowe's ratio test against the nearest *other* 3D point, and
``pycolmap.estimate_and_refine_absolute_pose`` (P3P LO-RANSAC + refinement). A pose with
fewer than ``min_inliers`` inliers is rejected, as in our engine.

Arrays are saved with ``np.savez`` and read with ``allow_pickle=False``; the faiss index is
stored as its serialized bytes.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..errors import InputError
from ..transforms import Rigid3d
from .config import SiftPeerConf

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- the map
@dataclass
class SiftMap:
    points_xyz: np.ndarray  # (P, 3) f8
    point_ids: np.ndarray  # (P,) i8, the COLMAP point ids
    desc: np.ndarray  # (N, 128) u1 RootSIFT, one per track observation
    desc_point: np.ndarray  # (N,) i4 -> row of points_xyz
    sfm: dict = field(default_factory=dict)  # SfmConf of the map (extraction settings)

    @property
    def n_points(self) -> int:
        return len(self.points_xyz)

    @classmethod
    def from_sfm_workdir(
        cls, workdir: str | Path, point_ids: np.ndarray | None = None, sfm: dict | None = None
    ) -> SiftMap:
        """Points (restricted to ``point_ids`` when given, in that order) and their observations'
        descriptors from a kept SfM work folder (``database.db`` + ``sparse/``). Ids the folder
        does not hold are skipped: a bundle's Harris points (``HARRIS_POINT_ID_BASE`` and up)
        have no SIFT observation, so the peer keeps the points SfM triangulated."""
        import pycolmap

        workdir = Path(workdir)
        if not (workdir / "database.db").is_file() or not (workdir / "sparse").is_dir():
            raise InputError(
                f"{workdir} is not a kept SfM work folder (database.db and sparse/ expected)"
            )
        rec = pycolmap.Reconstruction(str(workdir / "sparse"))
        db = pycolmap.Database.open(str(workdir / "database.db"))
        try:
            descs = {
                int(iid): np.asarray(db.read_descriptors(iid).data, np.uint8) for iid in rec.images
            }
        finally:
            db.close()
        if point_ids is None:
            ids = np.array(sorted(rec.points3D), np.int64)
        else:
            ids = np.array(
                [p for p in np.asarray(point_ids, np.int64).tolist() if p in rec.points3D], np.int64
            )
        xyz = np.empty((len(ids), 3), np.float64)
        rows: list[np.ndarray] = []
        owner: list[np.ndarray] = []
        for r, pid in enumerate(ids):
            p = rec.points3D[int(pid)]
            xyz[r] = p.xyz
            els = p.track.elements
            rows.append(np.stack([descs[int(e.image_id)][int(e.point2D_idx)] for e in els]))
            owner.append(np.full(len(els), r, np.int32))
        return cls(xyz, ids, np.concatenate(rows), np.concatenate(owner), dict(sfm or {}))

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(
            tmp,
            points_xyz=self.points_xyz,
            point_ids=self.point_ids,
            desc=self.desc,
            desc_point=self.desc_point,
            sfm=np.frombuffer(json.dumps(self.sfm).encode(), np.uint8),
        )
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> SiftMap:
        with np.load(path, allow_pickle=False) as z:
            return cls(
                z["points_xyz"],
                z["point_ids"],
                z["desc"],
                z["desc_point"],
                json.loads(z["sfm"].tobytes()),
            )

    def database(self, mode: str) -> tuple[np.ndarray, np.ndarray]:
        """(descriptors float32, point row of each) for ``mode`` "all" or "mean"."""
        if mode == "all":
            return self.desc.astype(np.float32), self.desc_point.astype(np.int64)
        n = np.bincount(self.desc_point, minlength=self.n_points).astype(np.float32)
        mean = np.zeros((self.n_points, self.desc.shape[1]), np.float32)
        np.add.at(mean, self.desc_point, self.desc.astype(np.float32))
        return mean / np.maximum(n, 1)[:, None], np.arange(self.n_points, dtype=np.int64)


# --------------------------------------------------------------------------- the localizer
@dataclass
class SiftResult:
    cam_from_world: Rigid3d | None
    inliers: int
    keypoints: int
    matches: int
    timings_ms: dict[str, float]


def sfm_conf_of(sift_map: SiftMap):
    """The SfmConf the map was built with (its SIFT settings are the query's)."""
    from ..builder.sfm import SfmConf

    return SfmConf.model_validate(sift_map.sfm) if sift_map.sfm else SfmConf()


class SiftLocalizer:
    """Single-image SIFT localization against a ``SiftMap`` (stateless per frame)."""

    def __init__(
        self,
        sift_map: SiftMap,
        camera: Camera,
        conf: SiftPeerConf | None = None,
        index_cache: dict | None = None,
    ) -> None:
        import pycolmap

        from ..builder.sfm.stages import to_pycolmap_camera

        self.map = sift_map
        self.conf = conf or SiftPeerConf()
        self.sfm_conf = sfm_conf_of(sift_map)
        if self.sfm_conf.sift_backend != "opencv":
            raise InputError(
                "the SIFT peer extracts query features with OpenCV: build its map with "
                "sift_backend='opencv'"
            )
        self.camera = camera
        self.pcam = to_pycolmap_camera(camera)
        self.data, self.label = sift_map.database(self.conf.descriptors)
        # One index per (descriptors, search, M) is enough: efSearch is a query-time setting.
        key = (self.conf.descriptors, self.conf.search, self.conf.hnsw_m)
        cache = index_cache if index_cache is not None else {}
        if key not in cache:
            cache[key] = build_index(self.data, self.conf.search, self.conf.hnsw_m)
        self.index = cache[key]
        if self.conf.search == "hnsw":
            self.index.hnsw.efSearch = self.conf.ef_search
        self.est_opts = pycolmap.AbsolutePoseEstimationOptions()
        self.est_opts.ransac.max_error = self.conf.ransac_max_error_px
        self.est_opts.ransac.random_seed = self.conf.seed
        self.est_opts.ransac.num_threads = 1
        self.ref_opts = pycolmap.AbsolutePoseRefinementOptions()

    # The three stages, separately callable (tuning reuses extraction and search across settings).
    def extract(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from ..builder.sfm.stages import opencv_sift

        kp, desc = opencv_sift(gray, self.sfm_conf)
        return kp[:, :2].astype(np.float64), desc

    def search(self, desc: np.ndarray, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        kk = min(k or (self.conf.k if self.conf.descriptors == "all" else 2), len(self.data))
        if len(desc) == 0:
            return np.zeros((0, kk), np.float32), np.zeros((0, kk), np.int64)
        return self.index.search(np.ascontiguousarray(desc, np.float32), kk)

    def ratio_matches(
        self, dist: np.ndarray, nn: np.ndarray, ratio: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        return ratio_test(dist, nn, self.label, self.conf.ratio if ratio is None else ratio)

    def pose(
        self, xy: np.ndarray, X: np.ndarray, max_error: float | None = None
    ) -> tuple[Rigid3d | None, int]:
        import pycolmap

        from ..builder.sfm.convert import rigid3d_from_pycolmap

        if len(xy) < max(4, self.conf.min_inliers):
            return None, 0
        opts = self.est_opts
        if max_error is not None and max_error != opts.ransac.max_error:
            opts = pycolmap.AbsolutePoseEstimationOptions()
            opts.ransac.max_error = max_error
            opts.ransac.random_seed = self.conf.seed
            opts.ransac.num_threads = 1
        r = pycolmap.estimate_and_refine_absolute_pose(
            np.ascontiguousarray(xy, np.float64),
            np.ascontiguousarray(X, np.float64),
            self.pcam,
            opts,
            self.ref_opts,
        )
        if r is None or int(r["num_inliers"]) < self.conf.min_inliers:
            return None, 0 if r is None else int(r["num_inliers"])
        return rigid3d_from_pycolmap(r["cam_from_world"]), int(r["num_inliers"])

    def localize(self, gray: np.ndarray) -> SiftResult:
        t0 = time.perf_counter()
        xy, desc = self.extract(gray)
        t1 = time.perf_counter()
        dist, nn = self.search(desc)
        q, p = self.ratio_matches(dist, nn)
        t2 = time.perf_counter()
        pose, inl = self.pose(xy[q], self.map.points_xyz[p])
        t3 = time.perf_counter()
        return SiftResult(
            pose,
            inl,
            len(xy),
            len(q),
            {
                "extract": (t1 - t0) * 1e3,
                "match": (t2 - t1) * 1e3,
                "pose": (t3 - t2) * 1e3,
                "total": (t3 - t0) * 1e3,
            },
        )


def build_index(data: np.ndarray, search: str, hnsw_m: int = 32):
    import faiss

    d = data.shape[1]
    if search == "exact":
        index: faiss.Index = faiss.IndexFlatL2(d)
    else:
        hnsw = faiss.IndexHNSWFlat(d, hnsw_m)
        hnsw.hnsw.efConstruction = 80
        index = hnsw
    index.add(np.ascontiguousarray(data, np.float32))
    return index


def ratio_test(
    dist: np.ndarray, nn: np.ndarray, label: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """(query rows, point rows) passing Lowe's test: nearest distance < ratio x the distance to
    the nearest descriptor of a *different* 3D point (several descriptors of one point are not
    ambiguity). A query whose k neighbours all belong to one point passes. faiss distances are
    squared L2."""
    if len(nn) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    valid = nn >= 0
    pts = np.where(valid, label[np.maximum(nn, 0)], -1)
    first = pts[:, 0]
    other = valid & (pts != first[:, None])
    has_other = other.any(axis=1)
    j = np.argmax(other, axis=1)
    d0 = np.sqrt(np.maximum(dist[:, 0], 0))
    d1 = np.sqrt(np.maximum(dist[np.arange(len(dist)), j], 0))
    ok = valid[:, 0] & (~has_other | (d0 < ratio * d1))
    q = np.nonzero(ok)[0]
    return q, first[q]
