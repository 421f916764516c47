"""``ServerConfig``: defaults < ``--config FILE`` (JSON/TOML) < ``SFMLOC_...`` environment <
command-line flags (``sfmloc.config.load_config``). Nested sections use ``__`` in the
environment: ``SFMLOC_ZENOH__MODE=client``, ``SFMLOC_GRPC__ADDRESS=0.0.0.0:50051``,
``SFMLOC_ENGINE__K=64``."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from ..config import StrictModel
from ..engine.config import EngineConf


class ZenohConf(StrictModel):
    enabled: bool = True
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = []  # e.g. tcp/0.0.0.0:7447
    connect: list[str] = []
    # Multicast scouting (zenoh's default: on); off = explicit endpoints only.
    multicast: bool = True
    config_file: str | None = None  # a zenoh JSON5 config; the settings above go over it
    # Zenoh's shared-memory transport. None: off unless config_file sets it. Off by default:
    # with it on, the server kept each client's 16 MiB segment mapped after the client left
    # (10 short-lived clients: +207 MB RSS, +20 /dev/shm files; off: +13 MB, +0;
    # docs/measurements.md#zenoh-shm).
    shared_memory: bool | None = None
    # Batches Zenoh queues per link for REAL_TIME messages: the poses (express, one batch
    # each, congestion control DROP). Zenoh's default is 2, and a put finding the queue full
    # waits 1 ms for the link's tx thread, then the pose is dropped without a word: on a busy
    # machine, poses leaving at once towards one peer (the time budget answering several
    # sessions' late frames, clients sharing a Zenoh session or a router) were lost, and a
    # client waiting for its last frame's answer waited forever (tests/test_overload.py at
    # load 11-16, 3 of 10 runs). Six express puts at once, 200 times, two busy loops beside
    # (nice 19): 2: 20 and 58 of 1200 lost; 16: 0 and 0. Not used when config_file sets
    # Zenoh's queue itself.
    pose_queue: int = Field(16, ge=1, le=16)
    # Reply NOT_FOUND to frames for maps this server does not host. Turn off when several
    # servers share a Zenoh network, each hosting different maps.
    reply_unknown_maps: bool = True


class Ros2Conf(StrictModel):
    """ROS 2 messages beside the msgpack poses (``sfmloc_client.ros2``). Off by default: every
    pose then costs two more CDR messages, and the topics belong to whoever runs ROS 2 there."""

    enabled: bool = False
    domain_id: int = Field(0, ge=0, le=232)  # ROS_DOMAIN_ID
    key_format: Literal["rmw_zenoh", "ros2dds"] = "rmw_zenoh"
    prefix: str = "sfmloc"  # topics /<prefix>/<map>/<client>/pose, pose_cov, image[/compressed]
    # header.frame_id of each map's poses; a map not listed uses frame_id_template.
    frame_ids: dict[str, str] = {}
    frame_id_template: str = "sfmloc_{map}"
    # Frames also come in as sensor_msgs/Image and CompressedImage; their camera (no
    # CameraInfo is read) is cameras[client] or default_camera ("MODEL w h params...").
    images: bool = True
    cameras: dict[str, str] = {}
    default_camera: str = ""


class GrpcConf(StrictModel):
    # host:port; port 0 picks a free one; "" disables gRPC.
    address: str = "0.0.0.0:50051"
    # Requests and responses larger than this are refused with RESOURCE_EXHAUSTED.
    max_message_mb: float = Field(16.0, gt=0)
    threads: int = Field(4, ge=1)  # executor for blocking calls (LoadMap)
    # TLS: PEM files of the server's certificate chain and key; with client_ca, clients must
    # present a certificate signed by it (mutual TLS).
    tls_cert: str = ""
    tls_key: str = ""
    tls_client_ca: str = ""
    # Bearer tokens and roles (a JSON file, see sfmloc.server.auth; `sfmloc auth add-token`).
    # Off when empty. Tokens travel in the clear without TLS: allowed only on loopback.
    tokens_file: str = ""


class ServerConfig(StrictModel):
    maps: str = "maps"  # every bundle folder in here is loaded at start
    # Further folders LoadMap and builder announcements may load bundles from (``maps`` always
    # is one). A bundle anywhere else on the machine is refused (PERMISSION_DENIED).
    map_roots: list[str] = []
    server_id: str = ""  # default: <hostname>-<pid>
    # Engine workers; 0 = one per core. "process" (default) or "thread" (measurements only:
    # the GIL serializes the engine's Python-level work, see the report in app.py).
    workers: int = Field(0, ge=0)
    worker_kind: Literal["process", "thread"] = "process"
    # "fork": process workers are forked from one interpreter that imported the engine once
    # (server/zygote.py: start and restart without re-importing, imported pages shared);
    # "exec": a fresh interpreter per worker (the measured baseline, and the fallback).
    worker_start: Literal["fork", "exec"] = "fork"
    idle_timeout_s: float = Field(30.0, gt=0)  # a Zenoh session without frames this long ends
    # Frames of a session that may wait while its previous one is processed; older ones are
    # dropped. 1 = latest-frame-only (the default: the freshest pose, soonest).
    max_pending: int = Field(1, ge=1, le=8)
    # Stream frames in one engine worker at once (running + queued in its pipe); a session
    # whose worker is full waits in the server with its newest frame, and the waiting sessions
    # of a worker take turns, tracked ones before relocalizing ones (sessions.py): under
    # overload poses stay fresh and sessions keep their tracks. 0: no limit, each session's
    # frame goes to its worker at once, where it waits behind the other sessions' frames while
    # newer ones arrive, and no turns are chosen (16 clients on 2 workers collapsed into
    # relocalizations, docs/measurements.md#throughput). 2 (default): one frame waits in the
    # pipe while one runs, so the worker never idles for a round trip through the server.
    # Measured (nice 0, quiet, sfmloc bench --suites throughput, 2 and 0 alternating): 16
    # clients 28.4 / 65.8 Hz, then 54.8 / 41.8 Hz: no gain beyond run-to-run variance; 16
    # clients collapse with either.
    worker_queue: int = Field(2, ge=0, le=64)
    # The most of a stream worker's time that relocalizing frames (a session's first frame,
    # after LOST or past the engine's frame gap: global matching, ~6x a tracked frame) take
    # while tracked sessions of that worker have frames waiting (sessions.py): after a
    # relocalization, the worker's tracked sessions get their turns first until they had as
    # much again (0.5). 1: no cap, earliest deadline only (16 clients on 2 workers collapsed:
    # every session relocalized, one round of relocalizations took past the frame gap, so each
    # next frame relocalized again). Only with worker_queue > 0 (turns are chosen).
    # Lead's A/B at 9cf2735, nice 0, quiet (load 1.6-2.7; `SFMLOC_RELOCALIZE_SHARE=S sfmloc
    # bench --suites throughput --clients 8,16 --duration 10`), 16 clients, poses/s for 1 / 0.5:
    # 100.9 / 83.5, 109.1 / 87.4, then (order swapped) 95.6 / 104.2; relocalized 5-8% with
    # either: the one run first in a pair did better, no difference beyond that. With
    # relocalization at ~35 ms (12eb289) the collapse no longer shows with either value; 0.5
    # kept for the simulated slow-relocalization case (tests/test_overload_turns.py).
    relocalize_share: float = Field(0.5, gt=0, le=1)
    max_sessions: int = Field(256, ge=1)
    # Zenoh frame envelopes larger than this are refused (RESOURCE_EXHAUSTED).
    max_frame_bytes: int = Field(16 * 1024 * 1024, ge=1024)
    # Frames per second one Zenoh client (map/client id) may send on average, in bursts of up
    # to 2 s; beyond, frames are refused (RESOURCE_EXHAUSTED) before they are decoded.
    max_client_fps: float = Field(240.0, gt=0)
    # Rejected frames are logged at most 3 lines per client and 50 in all per interval; the
    # rest is summed up in one line per interval (a flood must not fill the disk).
    log_interval_s: float = Field(10.0, gt=0)
    # A stream frame's time budget, wall time from its receipt: a frame not answered by then
    # (a worker starved of CPU, a huge image) is answered DEADLINE_EXCEEDED, and its session's
    # next frame goes on; a frame whose budget passed before its work started is not worked
    # on. Before this, at load 20+, 1-2 of 20k fuzz inputs got a stream frame answered after
    # ~21 s (issue 12). 0: no budget. Healthy frames take 8-80 ms of CPU.
    frame_budget_ms: float = Field(2000.0, ge=0)
    # The most CPU one stream frame may use once started (the worker stops it there: the
    # session relocalizes next frame); a 4096x4096 frame must not hold its worker's other
    # sessions for seconds. 0: no limit.
    frame_cpu_budget_ms: float = Field(1000.0, ge=0)
    # A frame its worker has started is not cut at frame_budget_ms (its CPU budget bounds it;
    # cutting it threw the CPU spent away and queued the next frame behind it): only a worker
    # that has not answered it this long after its receipt (stopped, stuck in native code)
    # costs it its answer (DEADLINE_EXCEEDED). Below the 10 s a caller counts as a hang.
    frame_hang_ms: float = Field(8000.0, ge=0)
    max_pending_relocalize: int = Field(16, ge=1)  # queued single-image requests, all workers
    # Queued or running single-image requests of one caller (its token's name, else its
    # connection); beyond, RESOURCE_EXHAUSTED: one caller cannot fill the queue for all.
    max_relocalize_per_client: int = Field(4, ge=1)
    # Most CPU time one Relocalize may take on a worker (CPU, not wall: waiting for a busy
    # machine's cores does not count), checked between the engine's stages (decoding,
    # detection, description, search, RANSAC); past it the answer is LOST, "time budget
    # exceeded". The caller's gRPC deadline bounds the wall time. 0: no limit. A 640x480
    # relocalization takes 70-120 ms; a 4096x4096 image 0.5-2.7 s under load ~13 (measured
    # with `python -m sfmloc.bench.reliability --parts reloc`), blank or absurd intrinsics
    # 4-4.6 s before this budget (issue 16).
    relocalize_budget_ms: float = Field(2000.0, ge=0)
    # Worker processes only for single-image Relocalize, besides ``workers`` (at a lower CPU
    # priority, ``relocalize_nice``): one client's relocalization (70-120 ms, seconds for a
    # huge image) never holds a worker that streaming sessions' frames wait on. 0: Relocalize
    # runs on the stream workers (the least busy one), delaying its sessions' frames by 2-3
    # frames.
    relocalize_workers: int = Field(1, ge=0, le=16)
    # How much lower the relocalization lane's CPU priority is than the stream workers' (nice
    # increment, capped at 19 by the kernel). Streams are real time, a single image is not:
    # with callers keeping the lane busy, +5 (the kernel's weight 335 against a stream
    # worker's 1024) still took a quarter of the core it shares with a stream worker; +15
    # (weight 36) takes 3%, and an idle machine still gives the lane all it wants.
    relocalize_nice: int = Field(15, ge=0, le=19)
    # The stream workers' scheduler time slice in ms (Linux 6.12+, ``sched.py``; 0: the
    # kernel's default, 1.4 ms on 2 cores). A frame is ~12-14 ms of CPU: with the default,
    # workers sharing a core (co-located servers, other CPU-bound tenants) were switched ~10
    # times per frame, each switch onto another process's caches.
    worker_slice_ms: float = Field(0.0, ge=0, le=100)
    # Largest camera (width x height) accepted; also caps what OpenCV decodes in a worker, so a
    # small JPEG claiming a huge image cannot exhaust its memory.
    max_image_pixels: int = Field(4096 * 4096, ge=1)
    follow_builder: bool = False  # load bundles the builder announces on sfmloc/maps/*
    # An announced bundle this server cannot see in its maps folders (another machine, no
    # shared storage) is fetched from the builder over Zenoh into ``maps``, verified, then
    # loaded; at most this size.
    fetch_bundles: bool = True
    max_fetch_mb: float = Field(16384.0, gt=0)
    # Health says SERVING only while at least one map is loaded (a server that can localize
    # nothing fails its container health check). True: SERVING with no map too (a server that
    # waits for LoadMap or the builder).
    allow_empty: bool = False
    grace_s: float = Field(5.0, ge=0)  # shutdown: time for in-flight frames and calls
    metrics_port: int | None = Field(None, ge=0, le=65535)
    metrics_host: str = "0.0.0.0"
    log_format: Literal["kv", "json"] = "kv"
    engine: EngineConf = EngineConf()
    zenoh: ZenohConf = ZenohConf()
    ros2: Ros2Conf = Ros2Conf()
    grpc: GrpcConf = GrpcConf()
