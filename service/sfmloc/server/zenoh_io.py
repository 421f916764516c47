"""The Zenoh front-end: frames in, poses out, discovery, builder announcements.

- ``sfmloc/*/*/frame`` (one subscriber): envelopes are decoded and validated here
  (``sfmloc_client.wire.decode_frame``) and handed to the session manager; the callback does
  no engine work and never blocks on a worker.
- ``sfmloc/<map>/<client>/pose``: one publisher per session, priority REAL_TIME, express
  (no batching delay), congestion control DROP (a pose that cannot go out now is superseded
  by the next one; the server never blocks on a slow client). Error replies go the same way.
- liveliness token ``sfmloc/servers/<id>`` (declared once maps are loaded) and queryable
  ``sfmloc/servers/<id>/info`` (``ServerInfo``: maps, sessions, load).
- with ``follow_builder``: ``sfmloc/maps/*`` announcements load the announced bundle.
"""

from __future__ import annotations

import json
import logging
import re
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import zenoh

from sfmloc_client.wire import (
    FRAME_KEYEXPR,
    MAPS_KEYEXPR,
    Frame,
    MapAnnouncement,
    PoseMessage,
    ServerInfo,
    addressed_frame_keyexpr,
    check_name,
    decode_frame,
    decode_map_announcement,
    encode_pose,
    encode_server_info,
    parse_frame_key,
    peek_seq,
    pose_key,
    server_info_key,
    server_token_key,
)
from sfmloc_client.zconfig import make_zenoh_config

from ..errors import ConfigError, MapNotFoundError, OverloadError, UnavailableError, WireError
from .config import ServerConfig, ZenohConf
from .facade import Localization
from .limits import LogLimiter, RateLimiter
from .logfmt import event

log = logging.getLogger(__name__)

POSE_QUEUE_KEY = "transport/link/tx/queue/size/real_time"  # the poses' priority (POSE_QOS)
POSE_QOS: dict[str, Any] = {
    "priority": zenoh.Priority.REAL_TIME,
    "express": True,
    "congestion_control": zenoh.CongestionControl.DROP,
}


# A Zenoh config file that sets the links' transmission queues decides them itself.
_QUEUE_IN_FILE = re.compile(r"""["']?queue["']?\s*:""")


def server_zenoh_config(zc: ZenohConf) -> Any:
    """The server's ``zenoh.Config``: ``make_zenoh_config`` with the server's settings, and
    room for ``pose_queue`` poses per link (config.py, ``ZenohConf.pose_queue``: with Zenoh's
    default of 2, poses leaving at once towards one peer on a busy machine were dropped)."""
    zconf = make_zenoh_config(
        zc.mode,
        zc.listen,
        zc.connect,
        # A config file decides scouting itself unless turned off here (--no-multicast):
        # e.g. docker/zenoh-server-acl.json5 turns multicast and gossip off.
        multicast=None if zc.config_file and zc.multicast else zc.multicast,
        config_file=zc.config_file,
        shared_memory=zc.shared_memory,
    )
    text = Path(zc.config_file).read_text("utf-8", "replace") if zc.config_file else ""
    if not _QUEUE_IN_FILE.search(text):
        zconf.insert_json5(POSE_QUEUE_KEY, json.dumps(zc.pose_queue))
    return zconf


class ZenohPoseSink:
    """A session's pose publisher."""

    def __init__(self, z: zenoh.Session, key: str) -> None:
        self._pub = z.declare_publisher(key, **POSE_QOS)

    def send(self, pose: PoseMessage) -> None:
        self._pub.put(encode_pose(pose))

    def send_encoded(self, data: bytes) -> None:
        """A pose message already encoded (``encode_pose``'s bytes)."""
        self._pub.put(data)

    def close(self) -> None:
        try:
            self._pub.undeclare()
        except Exception:  # noqa: BLE001 - the Zenoh session may be closed already
            pass


class ZenohFrontend:
    def __init__(
        self,
        conf: ServerConfig,
        loc: Localization,
        server_id: str,
        info: Callable[[], ServerInfo],
        on_announcement: Callable[[MapAnnouncement], None] | None = None,
    ) -> None:
        self.conf = conf
        self.loc = loc
        self.server_id = server_id
        self.info = info
        self.on_announcement = on_announcement
        self.z: zenoh.Session | None = None
        self._frame_sub: Any = None
        self._addressed_sub: Any = None
        self._ros2_images: Any = None  # ros2_io.Ros2ImageIntake when ros2 images are on
        self._ros2_graph: Any = None  # ros2_io.Ros2Graph with ros2 on rmw_zenoh's keys
        self._token: Any = None
        self._others: list[Any] = []
        # Announcements load maps, which blocks on the workers: never on Zenoh's thread.
        self._loader = ThreadPoolExecutor(1, thread_name_prefix="sfmloc-announce")
        self.rate_limiter = RateLimiter(conf.max_client_fps, 2.0 * conf.max_client_fps)
        self.rejections = LogLimiter(log, "frame_rejected", conf.log_interval_s)

    def open(self) -> None:
        zc = self.conf.zenoh
        try:
            zconf = server_zenoh_config(zc)
        except Exception as exc:  # noqa: BLE001 - zenoh raises ZError/ValueError on bad settings
            raise ConfigError(f"invalid Zenoh configuration: {exc}") from None
        try:
            self.z = zenoh.open(zconf)
        except Exception as exc:  # noqa: BLE001 - e.g. the listen port is taken
            raise UnavailableError(f"cannot open the Zenoh session: {exc}") from None
        self._others.append(
            self.z.declare_queryable(server_info_key(self.server_id), self._on_info_query)
        )
        r2 = self.conf.ros2
        if r2.enabled and r2.key_format == "rmw_zenoh":
            from .ros2_io import Ros2Graph

            self._ros2_graph = Ros2Graph(self.z, r2, f"sfmloc_{self.server_id}")
        if self.conf.follow_builder and self.on_announcement is not None:
            self._others.append(self.z.declare_subscriber(MAPS_KEYEXPR, self._on_announcement))
        event(
            log,
            logging.INFO,
            "zenoh_open",
            zid=str(self.z.zid()),
            mode=zc.mode,
            listen=zc.listen,
            connect=zc.connect,
            multicast=zc.multicast,
            shared_memory=json.loads(zconf.get_json("transport/shared_memory/enabled")),
        )

    def start_intake(self) -> None:
        """Accept frames and become discoverable (once the maps are loaded)."""
        assert self.z is not None
        self._frame_sub = self.z.declare_subscriber(FRAME_KEYEXPR, self._on_frame)
        # frames addressed to this server (one owner per session): no other server gets them
        self._addressed_sub = self.z.declare_subscriber(
            addressed_frame_keyexpr(self.server_id), self._on_frame
        )
        if self.conf.ros2.enabled and self.conf.ros2.images:
            from .ros2_io import Ros2ImageIntake

            self._ros2_images = Ros2ImageIntake(
                self.z,
                self.conf.ros2,
                self._submit,
                self.conf.max_frame_bytes,
                lambda: [m.name for m in self.loc.list_maps()],
            )
        self._token = self.z.liveliness().declare_token(server_token_key(self.server_id))

    def stop_intake(self) -> None:
        if self._ros2_images is not None:
            self._ros2_images.close()
            self._ros2_images = None
        for obj in (self._frame_sub, self._addressed_sub, self._token):
            if obj is not None:
                try:
                    obj.undeclare()
                except Exception:  # noqa: BLE001
                    pass
        self._frame_sub = self._addressed_sub = self._token = None

    def close(self) -> None:
        self.stop_intake()
        self._loader.shutdown(wait=False, cancel_futures=True)
        for obj in self._others:
            try:
                obj.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self._others.clear()
        if self._ros2_graph is not None:
            self._ros2_graph.close()
            self._ros2_graph = None
        if self.z is not None:
            self.z.close()  # an open session would keep the process from exiting
            self.z = None

    # ------------------------------------------------------------------ frames
    def _on_frame(self, sample: zenoh.Sample) -> None:
        t_recv = time.perf_counter()
        key = str(sample.key_expr)
        try:
            map_name, client_id = parse_frame_key(key)
        except WireError:
            return  # cannot happen with our key expression; nothing to answer to
        payload = sample.payload.to_bytes()
        self._submit(
            map_name,
            client_id,
            lambda: decode_frame(payload, self.conf.max_frame_bytes),
            t_recv,
            payload,
        )

    def _submit(
        self,
        map_name: str,
        client_id: str,
        decode: Callable[[], Frame],
        t_recv: float,
        payload: bytes = b"",
    ) -> None:
        """Checks, decodes and hands on one frame (msgpack envelope or ROS 2 image); every
        refusal is answered on the client's pose key."""
        z = self.z
        if z is None:
            return
        try:
            check_name(map_name, "map name")
            check_name(client_id, "client id")
            if not self.rate_limiter.allow(f"{map_name}/{client_id}"):
                self.loc.count_refused("rate")
                raise OverloadError(
                    f"client {client_id!r} sends more than {self.conf.max_client_fps:g} frames/s: "
                    "frame refused"
                )
            frame = decode()
            if frame.server and frame.server != self.server_id:
                return  # addressed to another server hosting this map (one owner per session)
            self.loc.submit_frame(
                map_name,
                client_id,
                "zenoh",
                frame,
                t_recv,
                make_sink=lambda: self._pose_sink(z, map_name, client_id),
            )
        except MapNotFoundError as exc:
            self._reply_error(
                map_name, client_id, payload, exc, publish=self.conf.zenoh.reply_unknown_maps
            )
        except Exception as exc:  # noqa: BLE001 - every failure is answered, none is fatal
            self._reply_error(map_name, client_id, payload, exc)

    def _pose_sink(self, z: zenoh.Session, map_name: str, client_id: str) -> Any:
        sink = ZenohPoseSink(z, pose_key(map_name, client_id))
        if not self.conf.ros2.enabled:
            return sink
        from .ros2_io import Ros2PoseSink

        return Ros2PoseSink(sink, z, self.conf.ros2, map_name, client_id, self._ros2_graph)

    def _reply_error(
        self,
        map_name: str,
        client_id: str,
        payload: bytes,
        exc: BaseException,
        publish: bool = True,
    ) -> None:
        """Count the refused frame; log it (rate-limited) and publish its error pose."""
        seq = peek_seq(payload) if len(payload) <= self.conf.max_frame_bytes else None
        pose = self.loc.refuse_frame(map_name, client_id, seq, 0, exc)
        if not publish:
            return
        code = pose.error.code if pose.error else ""
        if self.rejections.allow(client_id, code):
            event(
                log,
                logging.INFO,
                "frame_rejected",
                map=map_name,
                client=client_id,
                seq=seq,
                code=code,
                error=pose.message,
            )
        if self.z is None:
            return
        try:
            # The frame key matched sfmloc/*/*/frame, so its pose key is a valid key too, even
            # when the names break the rule (pose_key would refuse them: that is the error).
            self.z.put(f"sfmloc/{map_name}/{client_id}/pose", encode_pose(pose), **POSE_QOS)
        except Exception as e:  # noqa: BLE001
            log.warning("cannot publish an error reply to %s/%s: %s", map_name, client_id, e)

    # ------------------------------------------------------------------ discovery, builder
    def _on_info_query(self, query: zenoh.Query) -> None:
        try:
            query.reply(server_info_key(self.server_id), encode_server_info(self.info()))
        except Exception as exc:  # noqa: BLE001
            log.warning("info query failed: %s", exc)

    def _on_announcement(self, sample: zenoh.Sample) -> None:
        try:
            ann = decode_map_announcement(sample.payload.to_bytes())
        except WireError as exc:
            event(
                log,
                logging.WARNING,
                "announcement_invalid",
                key=str(sample.key_expr),
                error=str(exc),
            )
            return
        assert self.on_announcement is not None
        self._loader.submit(self.on_announcement, ann)
