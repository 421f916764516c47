"""Helpers for the server and client tests: a small synthetic world (rendered with
``sfmloc.synth``, its map built from the exact COLMAP model), free ports, Zenoh configs, and
servers on background threads. Everything is real: Zenoh sessions in peer mode on loopback
with multicast scouting off, gRPC on loopback, worker processes.

The world is built once per test session (cached by pytest's base temp folder; under xdist
one worker builds it and the others copy it), since both test_server*.py and test_client*.py
use it.
"""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sfmloc.testing import free_port

WIDTH, HEIGHT = 640, 480
N_MAPPING, N_FRAMES = 40, 60
_lock = threading.Lock()
_worlds: dict[Path, World] = {}
_scenes: dict[tuple[int, str], Any] = {}
_scenes_lock = threading.Lock()


@dataclass
class World:
    root: Path
    maps_dir: Path  # holds "room" and "room2" (the same scene under two names)
    spare_dir: Path  # other builds: "room" rebuilt (a new build_id), a corrupt copy
    camera_spec: str  # "PINHOLE w h fx fy cx cy"
    frames: list[Path]  # the video, PNG
    gt_cam_from_world: list[Any]  # Rigid3d per frame
    png: list[bytes] = field(default_factory=list)
    gray: list[np.ndarray] = field(default_factory=list)

    @property
    def room_rebuilt(self) -> Path:
        return self.spare_dir / "rebuilt" / "room"

    @property
    def corrupt(self) -> Path:
        return self.spare_dir / "corrupt" / "room"


def build_world(base: Path) -> World:
    """Render the scene, build the bundles (cached per base folder; under pytest-xdist the
    workers share one build, each working on its own copy: see ``_world_files``)."""
    with _lock:
        if base in _worlds:
            return _worlds[base]
        import cv2

        from sfmloc.cameras import Camera
        from sfmloc.io.poses import read_poses

        root = base / "sfmloc-world"
        maps_dir, spare = root / "maps", root / "spare"
        _world_files(root)
        cam = Camera.from_json(root / "synth" / "camera.json")
        frames = sorted((root / "synth" / "video").glob("frame-*.png"))
        gt = read_poses(root / "synth" / "video_poses.txt").by_stem()
        world = World(
            root=root,
            maps_dir=maps_dir,
            spare_dir=spare,
            camera_spec=f"PINHOLE {cam.width} {cam.height} "
            + " ".join(repr(float(p)) for p in cam.params),
            frames=frames,
            gt_cam_from_world=[gt[f.stem] for f in frames],
            png=[f.read_bytes() for f in frames],
            gray=[cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in frames],
        )
        _worlds[base] = world
        return world


def _render_and_build(root: Path) -> None:
    """The world's files under ``root``: the rendered room (``synth``), its bundle as "room" and
    "room2" (``maps``), and a rebuilt and a corrupt copy (``spare``)."""
    from sfmloc.builder.build import BuildConf, assemble
    from sfmloc.io.colmap import read_model
    from sfmloc.map.bundle import write_bundle
    from sfmloc.synth.main import run

    conf = world_synth_conf()
    run(conf, root / "synth", overwrite=True, scene=room_scene(conf.seed, conf.scene))
    rec = read_model(root / "synth" / "sparse")
    data, timings, info = assemble(rec, root / "synth" / "images", BuildConf())
    maps_dir, spare = root / "maps", root / "spare"
    for name in ("room", "room2"):
        write_bundle(data, maps_dir, name, timings_s=timings, index_info=info)
    write_bundle(data, spare / "rebuilt", "room", timings_s=timings, index_info=info)
    corrupt = write_bundle(data, spare / "corrupt", "room", timings_s=timings, index_info=info)
    with open(corrupt / "points_xyz.npy", "r+b") as f:  # flip bytes: checksum mismatch
        f.seek(200)
        f.write(b"\x00\xff" * 16)


def _world_files(root: Path) -> None:
    """Make the world's files under ``root``. Under pytest-xdist (``make test``: 2 workers) the
    first worker to need the world renders and builds it (~17 s of CPU at load 6; each worker
    built its own before) and leaves a copy beside the workers' folders, in the session's base
    folder; the others wait for it (a file lock) and copy it into their own folder (70 MB). A
    worker's tests keep their own files, as before: some add to them (a map folder symlink, a
    served share), and a copy keeps those to the worker. Without xdist the folder is the
    session's alone: built in place. The files hold no absolute path (checked: a copy serves)."""
    import fcntl
    import os
    import shutil

    if not os.environ.get("PYTEST_XDIST_WORKER"):
        _render_and_build(root)
        return
    # root is in the worker's base folder, pytest-N/popen-gwK; pytest-N is this session's alone
    session = root.parent.parent
    shared = session / "sfmloc-world-shared"
    with open(session / "sfmloc-world.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not shared.is_dir():
            _render_and_build(root)
            # copied whole, then renamed: a worker killed mid-copy leaves no half world
            tmp = session / f"sfmloc-world-shared.{os.getpid()}"
            shutil.copytree(root, tmp, symlinks=True)
            tmp.rename(shared)
            return
    shutil.copytree(shared, root, symlinks=True)


def world_synth_conf() -> Any:
    """The synthetic world's render settings: the small room at WIDTH x HEIGHT, N_MAPPING
    mapping views, an N_FRAMES walk."""
    from sfmloc.synth import preset

    return preset(
        "small",
        width=WIDTH,
        height=HEIGHT,
        mapping_views=N_MAPPING,
        trajectory={"n_frames": N_FRAMES},
    )


def room_scene(seed: int = 0, conf: Any = None) -> Any:
    """``sfmloc.synth.Scene.room(seed, conf)``, built once per test session and shared (~1.5 s
    CPU a build): the tests only read it (render, ray-cast, trajectories); the renderer's
    mipmaps are kept in its cache, built once too. The world, four other test data sets
    (``synth.main.run(scene=...)``) and thirteen tests in ten files render the world's room
    (seed 0, the default scene); test_synth's determinism test builds another to compare."""
    from sfmloc.synth import Scene
    from sfmloc.synth.scene import SceneConf

    conf = conf or SceneConf()
    key = (seed, conf.model_dump_json())
    with _scenes_lock:
        if key not in _scenes:
            _scenes[key] = Scene.room(seed, conf)
        return _scenes[key]


def zenoh_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def server_config(world: World, zenoh_listen: str, **changes: Any) -> Any:
    from sfmloc.config import merge_presets
    from sfmloc.server.config import ServerConfig

    base = ServerConfig(
        maps=str(world.maps_dir),
        workers=1,
        worker_kind="thread",
        idle_timeout_s=60.0,
        zenoh={"listen": [zenoh_listen], "multicast": False},
        grpc={"address": "127.0.0.1:0", "max_message_mb": 4.0},
        max_frame_bytes=4 * 1024 * 1024,
        grace_s=10.0,
    )
    return merge_presets(base, **changes) if changes else base


def client_zenoh(endpoint: str) -> Any:
    import zenoh

    from sfmloc_client import make_zenoh_config

    return zenoh.open(make_zenoh_config("peer", connect=[endpoint], multicast=False))


def camera(world: World) -> Any:
    from sfmloc_client import CameraSpec

    return CameraSpec.parse(world.camera_spec)


class Collected:
    """What a callback collects (e.g. ``PoseSubscriber(callback=poses.append)``), with a wait
    on a condition notified per item: no polling, no sleep."""

    def __init__(self) -> None:
        self.items: list[Any] = []
        self._cond = threading.Condition()

    def append(self, item: Any) -> None:
        with self._cond:
            self.items.append(item)
            self._cond.notify_all()

    def wait_for(self, pred: Any, timeout: float = 30.0) -> bool:
        """Wait until ``pred(items)`` holds (checked at each new item); False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: pred(self.items), timeout)

    def has_seq(self, seq: int, timeout: float = 60.0) -> bool:
        return self.wait_for(lambda items: any(p.seq == seq for p in items), timeout)

    def __iter__(self) -> Any:
        with self._cond:
            return iter(list(self.items))

    def __len__(self) -> int:
        return len(self.items)


@contextlib.contextmanager
def streaming_client(endpoint: str, world: World, client_id: str, map_name: str = "room"):
    """A client on its own Zenoh session to ``endpoint``: a ``FrameStreamer`` (yielded once a
    server takes its frames) and a ``Collected`` of its poses, ``(fs, got)``."""
    from sfmloc_client import FrameStreamer, PoseSubscriber

    got = Collected()
    with (
        client_zenoh(endpoint) as z,
        PoseSubscriber(z, map_name, client_id, callback=got.append),
        FrameStreamer(z, map_name, client_id, camera(world)) as fs,
    ):
        assert fs.wait_for_server(30), "no server subscribed to the frames"
        yield fs, got


def wait_until(pred: Any, timeout: float = 30.0, every: float = 0.02) -> bool:
    """Poll ``pred`` until true, for state with nothing to wait on (another process, a file,
    a remote health status); the tests assert on the outcome, never on the time taken."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(every)
    return bool(pred())


def stream_lockstep(
    z: Any,
    map_name: str,
    client_id: str,
    world: World,
    n: int | None = None,
    encoding: str = "png",
    timeout: float = 30.0,
    server: str | None = None,
) -> list[Any]:
    """Stream the video frame by frame (each after the previous pose) and return the poses
    (``server``: as ``FrameStreamer``'s, e.g. a server id to address the frames to)."""
    from sfmloc_client import FrameStreamer, PoseSubscriber, SourceFrame

    frames = world.png[: n or len(world.png)]
    got: list[Any] = []
    with (
        PoseSubscriber(z, map_name, client_id, callback=got.append) as poses,
        FrameStreamer(
            z, map_name, client_id, camera(world), encoding=encoding, server=server
        ) as fs,
    ):
        assert fs.wait_for_server(timeout), "no server subscribed to the frames"
        src = [
            SourceFrame(data=d, encoding="png", stamp_ns=int(k * 1e9 / 30))
            for k, d in enumerate(frames)
        ]
        stats = fs.run(src, lockstep=True, poses=poses, pose_timeout=timeout)
        poses.wait_for(stats.last_seq, timeout)
    return got


def position_errors(world: World, poses: list[Any]) -> np.ndarray:
    """Camera-centre errors (m) of localized poses against the exact ground truth."""
    errs = []
    for p in poses:
        if p.localized and p.seq is not None:
            gt = world.gt_cam_from_world[p.seq].inverse().translation
            errs.append(float(np.linalg.norm(np.asarray(p.world_from_cam.t) - gt)))
    return np.array(errs)


@contextlib.contextmanager
def running_server(conf: Any, load_maps: bool = True):
    from sfmloc.testing import ServerThread

    srv = ServerThread(conf, load_maps=load_maps).start()
    try:
        yield srv
    finally:
        srv.stop()
