"""The ``map`` suite: build time, bundle size, load time and resident memory of a bundle.

Memory is measured in a fresh process (``python -m sfmloc.bench.mapstats BUNDLE CAMERA VERIFY
FRAME...``): the libraries the server uses are imported first, VmRSS (and its anonymous and
file-backed parts) is read from ``/proc/self/status``, the bundle is loaded as the server
loads it (checksums verified) and every array the engine reads is read through, with the
point -> images lookup built; VmRSS again: the difference is the bundle's resident cost. Then
a Localizer runs a few frames: what a worker adds on top (engine buffers, not per map). Load
time is also measured without checksum verification, in its own fresh process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def _status_kib() -> dict[str, int]:
    out = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        key = line.split(":", 1)[0]
        if key in ("VmRSS", "RssAnon", "RssFile"):
            out[key] = int(line.split()[1])
    return out


def probe(bundle: str, frames: list[str], camera: str, verify: bool = True) -> dict[str, Any]:
    """Run inside the fresh process: memory before/after loading, after touching what the
    engine reads, after localizing frames; load time."""
    from ..threads import pin_threads_env, pin_threads_runtime

    pin_threads_env()
    import cv2
    import numpy as np

    from ..io.frames import read_image

    pin_threads_runtime()
    from ..cameras import Camera
    from ..engine import Localizer
    from ..map.bundle import MapBundle

    cam = Camera.parse(camera)
    grays = [read_image(f, cv2.IMREAD_GRAYSCALE) for f in frames]
    before = _status_kib()
    t0 = time.perf_counter()
    b = MapBundle(bundle, verify=verify)
    load_s = time.perf_counter() - t0
    after_load = _status_kib()
    # What the engine reads (the ANN index is already in memory: it holds its own copy of the
    # descriptors, which the engine never reads from the bundle).
    for arr in (
        b.points_xyz,
        b.desc_point,
        b.desc_image,
        b.image_desc_ptr,
        b.image_points_ptr,
        b.image_points_idx,
        b.cluster_images_ptr,
        b.cluster_images_idx,
        b.point_clusters_ptr,
        b.point_clusters_idx,
        b.image_camera,
    ):
        float(np.asarray(arr, np.float64).sum())
    after_touch = _status_kib()
    loc = Localizer(b, cam)
    for k, g in enumerate(grays):
        loc.localize(g, k / 30.0)
    after_frames = _status_kib()
    return {
        "before_kib": before,
        "after_load_kib": after_load,
        "after_touch_kib": after_touch,
        "after_frames_kib": after_frames,
        "load_s": load_s,
        "verify": verify,
        "memory_bytes_estimate": int(b.memory_bytes()),
    }


def _fresh(bundle: Path, frames: list[Path], camera: str, verify: bool) -> dict[str, Any]:
    cmd = [
        sys.executable,
        "-m",
        "sfmloc.bench.mapstats",
        str(bundle),
        camera,
        "1" if verify else "0",
        *[str(f) for f in frames],
    ]
    out = subprocess.run(
        cmd, check=True, capture_output=True, text=True, env=dict(os.environ), timeout=600
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def map_stats(bundle: Path, frames: list[Path], camera: str) -> dict[str, Any]:
    from ..map.bundle import read_manifest

    m = read_manifest(bundle)
    size = sum(p.stat().st_size for p in bundle.iterdir() if p.is_file())
    v = _fresh(bundle, frames, camera, True)
    plain = _fresh(bundle, frames[:1], camera, False)
    d = m.counts.descriptors

    def mb(a: str, b: str = "before_kib", key: str = "VmRSS") -> float:
        return (v[a][key] - v[b][key]) / 1024.0

    rss_mb = mb("after_touch_kib")
    return {
        "map": m.name,
        "images": m.counts.images,
        "points": m.counts.points,
        "descriptors": d,
        "descriptors_per_point": d / max(1, m.counts.points),
        "clusters": m.counts.clusters,
        "build_s": m.timings_s.get("total", float("nan")),
        "build_stages_s": {k: val for k, val in m.timings_s.items() if k != "total"},
        "bundle_mb": size / 1e6,
        "load_s_verified": v["load_s"],
        "load_s": plain["load_s"],
        # The bundle: loaded (checksums verified, as the server does) and everything the engine
        # reads touched.
        "rss_mb": rss_mb,
        "rss_anon_mb": mb("after_touch_kib", key="RssAnon"),
        "rss_file_mb": mb("after_touch_kib", key="RssFile"),
        "rss_mb_after_load_only": mb("after_load_kib"),
        # A worker on top of that: the engine's own buffers after localizing the probe frames.
        "worker_extra_rss_mb": mb("after_frames_kib", "after_touch_kib"),
        "memory_mb_estimate": v["memory_bytes_estimate"] / 1e6,
        "rss_mb_per_million_descriptors": rss_mb / (d / 1e6) if d else float("nan"),
        "bundle_mb_per_million_descriptors": size / 1e6 / (d / 1e6) if d else float("nan"),
        "probe_frames": len(frames),
    }


def sift_map_stats(sift_map_path: Path, descriptors: str, hnsw_m: int) -> dict[str, Any]:
    """The SIFT peer's map for comparison: its descriptors and, for the layout the peer uses
    ("all" observations or one "mean" per point), the size of its faiss HNSW index."""
    from .sift_peer import SiftMap

    sm = SiftMap.load(sift_map_path)
    n = len(sm.desc)
    indexed = n if descriptors == "all" else sm.n_points
    # faiss keeps float32 vectors; HNSW adds 2*M neighbour ids (int32) per node at level 0.
    return {
        "points": sm.n_points,
        "descriptors": n,
        "descriptor_mb_uint8": n * 128 / 1e6,
        "layout": descriptors,
        "indexed_vectors": indexed,
        "faiss_hnsw_mb": (indexed * 128 * 4 + indexed * 2 * hnsw_m * 4) / 1e6,
    }


if __name__ == "__main__":
    bundle_arg, camera_arg, verify_arg, *frame_args = sys.argv[1:]
    print(json.dumps(probe(bundle_arg, frame_args, camera_arg, verify_arg == "1")))
