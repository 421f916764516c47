"""What ``sfmloc bench`` runs: suites, frame budgets, peers, throughput settings."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from ..config import StrictModel

REPO = Path(__file__).resolve().parents[3]
# The real data are read in place, never copied into the repo.
DEFAULT_DATA = REPO.parent / "shared" / "data" / "redkitchen-seq01"
REDKITCHEN_CAMERA = "PINHOLE 640 480 525.505 525.505 320 240"
REDKITCHEN_POSES = "pgt_sfm_seq01.txt"

LOCALIZATION_SUITES = ("redkitchen", "redkitchen-split", "synthetic-walk", "synthetic-flight")
SUITES = (*LOCALIZATION_SUITES, "robust", "throughput", "map", "builder")
# What `sfmloc bench` runs without --suite: the builder suite builds several redkitchen maps
# (tens of minutes), so it runs only when asked for.
DEFAULT_SUITES = tuple(s for s in SUITES if s != "builder")
# The peers run next to our engine in every localization suite.
PEERS = ("global-every-frame", "pycolmap-sift")
OURS = "sfmloc"

SUITE_HELP = {
    "redkitchen": "real: map from every 10th of the 1000 frames (pgt_sfm poses, known-poses "
    "builder); "
    "all frames replayed as 30 Hz video; errors against pgt_sfm_seq01.txt",
    "redkitchen-split": "real, harder: map from every 5th of frames 0-499 only; frames 500-999 "
    "replayed "
    "(parts seen from viewpoints the map covers poorly: how much is localized, and nothing "
    "confidently wrong)",
    "synthetic-walk": "exact ground truth: `sfmloc synth` room, walking video (seed fixed); map "
    "from the "
    "exact COLMAP model",
    "synthetic-flight": "exact ground truth: quadrotor-like flight with fast yaw bursts (seed "
    "fixed)",
    "robust": "the data users bring (issue 9's test bed), our engine and pycolmap-sift on the "
    "same frames of every row: image size (synthetic walk at 640x480, 1280x960, 3072x2048 "
    "against the 640x480 map; redkitchen upsampled to 1920x1440), map density (synthetic "
    "mapping views at 1x, 3x, 6x the spacing; redkitchen maps from every 10th, 30th, 60th "
    "frame), scene scale (the room x0.01, x1, x100) and motion (walk, flight, orbit around the "
    "table at 30, 10, 3 Hz; the 10 and 3 Hz rows replay every offset of their step, every "
    "3rd / 10th frame from frame 0, 1, 2, ..., and pool them), and the density-6x map at 3 Hz "
    "(walk, flight; all offsets). Targets per row: localized >= the peer's, median error <= "
    "1.5x the peer's, 0 wrong poses, no crash (--robust-rows to choose rows)",
    "throughput": "1, 2, 4, 8, 12, 16 clients streaming redkitchen JPEGs over Zenoh (loopback, "
    "no multicast) at 30 Hz each to one `sfmloc serve` process: delivered rate, dropped "
    "fraction (all and worst client), latency p50/p99, CPU per pose of the server and its "
    "workers; resident memory of the server with 1, 2 and 4 workers. Clients send spread over "
    "the frame interval and loop without a jump (streaming cameras); one more row at 8 clients "
    "sends aligned and jumps from the last frame to the first (a stress row)",
    "map": "build time, bundle size, load time and resident memory (fresh process) of the "
    "redkitchen "
    "bundle, per million descriptors",
    "builder": "the map builder (issue 17; only when named): build peak memory per descriptor "
    "on synthetic rooms, --extend (second half of redkitchen added to the first half's map) "
    "against the map from all at once, and (--builder-parts) maps per input density and the "
    "video target",
}


class SiftPeerConf(StrictModel):
    """Matching and pose settings of the peer (extraction follows the map's SfM settings)."""

    # Lowe's ratio test: nearest / nearest other 3D point, in descriptor distance.
    ratio: float = Field(0.8, gt=0.0, le=1.0)
    # "all": every observation's descriptor (multiple per point); "mean": one mean per point.
    descriptors: Literal["all", "mean"] = "all"
    # "exact": faiss flat L2; "hnsw": faiss HNSW (recall against exact is measured in tuning).
    search: Literal["exact", "hnsw"] = "hnsw"
    hnsw_m: int = Field(32, ge=4)
    ef_search: int = Field(64, ge=8)
    # Neighbours retrieved per keypoint ("all": to find the nearest descriptor of another point).
    k: int = Field(8, ge=2)
    # pycolmap RANSAC inlier threshold (px); pycolmap's default is 12.
    ransac_max_error_px: float = Field(12.0, gt=0.0)
    min_inliers: int = Field(10, ge=4)
    seed: int = 0


class BenchConf(StrictModel):
    suites: list[str] = Field(default_factory=lambda: list(DEFAULT_SUITES))
    data: Path = DEFAULT_DATA
    camera: str = REDKITCHEN_CAMERA
    poses: str = REDKITCHEN_POSES
    # Frames replayed per localization suite (None: all of the suite's frames).
    frames: int | None = Field(None, ge=2)
    # Frames per suite the peers run on, evenly strided over the replayed frames (our engine
    # is summarised on the same frames for the side-by-side); None: every frame.
    peer_frames: int | None = Field(500, ge=1)
    # Replays of our engine and of global-every-frame per localization suite, interleaved
    # (pycolmap-sift once): every timing number published is the median over them, with the
    # min-max (bench/reps.py). One replay read 5.4 or 5.8 ms on the same code, back to back.
    reps: int = Field(3, ge=1)
    seed: int = 0
    # Synthetic suites: frames of the video and mapping views.
    synth_frames: int = Field(300, ge=10)
    synth_mapping_views: int = Field(120, ge=10)
    # Peer tuning: frames (not map images) of the first real suite, then the grid below.
    tune: bool = True
    tune_frames: int = Field(40, ge=2)
    tune_ratios: list[float] = Field(default_factory=lambda: [0.7, 0.8, 0.9])
    tune_max_errors: list[float] = Field(default_factory=lambda: [4.0, 8.0, 12.0])
    tune_descriptors: list[str] = Field(default_factory=lambda: ["all", "mean"])
    tune_ef: list[int] = Field(default_factory=lambda: [32, 64, 128])
    # The recall (vs exact search) an HNSW setting must reach to be used instead of exact.
    tune_min_recall: float = Field(0.99, gt=0.0, le=1.0)
    sift: SiftPeerConf = SiftPeerConf()  # used as is when tune is off
    # Throughput.
    clients: list[int] = Field(default_factory=lambda: [1, 2, 4, 8, 12, 16])
    rate_hz: float = Field(30.0, gt=0)
    duration_s: float = Field(10.0, gt=0)
    workers: int = Field(0, ge=0)  # server workers (0: one per core)
    # Resident memory of the server measured with these worker counts (one server each).
    memory_workers: list[int] = Field(default_factory=lambda: [1, 2, 4])
    # When the clients send ("spread": client i of n i/n of a frame interval later, as
    # independent cameras; "aligned": all at the same instants after the warm-up barrier) and
    # how each loops over the loaded frames ("pingpong": forwards then backwards, no jump;
    # "wrap": back to the first, a jump every session that wraps relocalizes after). The
    # defaults are streaming cameras. Until issue 10's drop diagnosis (python -m
    # sfmloc.bench.droptimeline) the suite ran aligned + wrap: bursts of one frame per client
    # and a relocalization per client every 10 s, which made most of its 8-client drops.
    client_phases: Literal["aligned", "spread"] = "spread"
    frame_loop: Literal["wrap", "pingpong"] = "pingpong"
    # One more run at this many clients, aligned + wrap (that stress, kept comparable with
    # earlier benches; 0: none).
    stress_clients: int = Field(8, ge=0)
    # The robust suite: frames per row (30 Hz span of the synthetic and redkitchen rows; the
    # 10 and 3 Hz rows keep every 3rd / 10th of it), frames of the large-image rows (the
    # 3072x2048 row 2/5 of them), frames per row for the peer (evenly strided; half on the
    # 1280x960 and 1920x1440 rows, a quarter at 3072x2048), rows to run (names or groups, shell
    # patterns; None: all) and a time budget per method and row (over it a row stops, saying so).
    robust_frames: int = Field(300, ge=2)
    robust_large_frames: int = Field(20, ge=2)
    robust_peer_frames: int = Field(20, ge=1)
    robust_rows: list[str] | None = None
    robust_budget_s: float = Field(150.0, gt=0)
    # The low-rate rows (10 and 3 Hz: every 3rd / 10th frame) replay every offset (the streams
    # starting at frame 0, 1, ..., step - 1) and pool them: one offset saw none of the wrong
    # poses that all 10 showed at 3 Hz (robust.py, ``offsets``). At most this many offsets,
    # evenly spread (None: all of them; --quick runs 2).
    robust_offsets: int | None = Field(None, ge=1)
    # An engine config file (JSON/TOML, EngineConf fields) for our engine in the robust suite
    # (not the peers, not the other suites); None: the defaults.
    robust_engine_config: Path | None = None
    # The builder suite: its parts (extend, memory, density, video; see bench/builder.py) and
    # the synthetic room sizes (mapping views) of its memory part.
    builder_parts: list[str] = Field(default_factory=lambda: ["memory", "extend"])
    builder_views: list[int] = Field(default_factory=lambda: [60, 240])
    # reuse maps and data under OUT/work made from the same input by the same builder
    reuse: bool = False
    quick: bool = False


# --quick's suites: every kind of suite, on the synthetic room only (rendered by the run, no
# data needed); the throughput and map suites then serve its map. With the redkitchen suites
# (each builds its 100-image map whatever --frames is: 61 and 98 s) and every robust row (more
# maps) a quick run was stopped after 9.5 min, in its robust suite (nice 19, load 9-14): too
# slow for a smoke run or a test.
QUICK_SUITES = ("synthetic-walk", "robust", "throughput", "map")
# Robust rows of the same room: the one that reuses the suite's map, and a subsampled one.
QUICK_ROBUST_ROWS = ("size-640x480", "walk-10hz")


def quick_conf(**changes) -> BenchConf:
    """A smoke run: the synthetic suites (``QUICK_SUITES``), few frames, small synthetic scenes,
    short throughput runs, small grid; ``changes`` (e.g. ``suites``) override any of it."""
    base = {
        "suites": list(QUICK_SUITES),
        "robust_rows": list(QUICK_ROBUST_ROWS),
        "frames": 60,
        "peer_frames": 12,
        "reps": 2,
        "synth_frames": 40,
        "synth_mapping_views": 40,
        "tune_frames": 6,
        "tune_ratios": [0.8],
        "tune_max_errors": [12.0],
        "tune_ef": [64],
        "clients": [1, 2],
        "stress_clients": 2,
        # each count starts a server of its own: with 1, 2, 4 the memory part took 59 s of a
        # 252 s quick run (nice 19, load 14)
        "memory_workers": [1, 2],
        "tune_descriptors": ["mean"],
        "duration_s": 3.0,
        "robust_frames": 30,
        "robust_large_frames": 4,
        "robust_peer_frames": 4,
        "robust_offsets": 2,
        "quick": True,
    }
    base.update(changes)
    return BenchConf(**base)
