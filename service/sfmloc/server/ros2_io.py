"""ROS 2 on the server's Zenoh session (``ServerConfig.ros2``; the messages and keys are
``sfmloc_client.ros2``'s).

- Poses: each session's pose sink also publishes ``PoseStamped`` and
  ``PoseWithCovarianceStamped`` for every localized frame (``Ros2PoseSink``), on the session's
  ROS topics, with rmw_zenoh's attachment.
- Frames: ``sensor_msgs/Image`` and ``CompressedImage`` on ``/<prefix>/<map>/<client>/image``
  and ``.../image/compressed`` become frames of the session ``<map>/<client>`` (the camera from
  the config: ROS images carry none), answered like any frame (msgpack pose + ROS poses).
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import time
from collections.abc import Callable
from typing import Any

import zenoh

from sfmloc_client import ros2
from sfmloc_client.images import encode_image
from sfmloc_client.wire import CameraSpec, Frame, PoseMessage

from ..cameras import Camera
from ..errors import ConfigError, WireError
from .config import Ros2Conf

log = logging.getLogger(__name__)

# Poses are superseded by the next one: never block the server on a slow subscriber (DROP).
# Their own priority queue, below the msgpack poses' REAL_TIME one: sharing it, 1-4 of 20 ROS
# poses were dropped on a loaded loopback (load ~10) while the msgpack ones all arrived.
_QOS: dict[str, Any] = {
    "priority": zenoh.Priority.DATA_HIGH,
    "express": True,
    "congestion_control": zenoh.CongestionControl.DROP,
}


def frame_id(conf: Ros2Conf, map_name: str) -> str:
    """The map's ROS frame (``frame_ids[map]`` or the template)."""
    return conf.frame_ids.get(map_name) or conf.frame_id_template.format(
        map=ros2.ros_name(map_name)
    )


class Ros2Graph:
    """The server as a node of rmw_zenoh's ROS graph (liveliness tokens): ``ros2 topic list``,
    ``ros2 node list`` and RViz's topic picker see the node and its pose publishers."""

    NODE_ID = 0

    def __init__(self, z: zenoh.Session, conf: Ros2Conf, node_name: str) -> None:
        self.z = z
        self.domain_id = conf.domain_id
        self.zid = str(z.zid())
        self.node = ros2.ros_name(node_name)
        self._ids = itertools.count(1)
        self._node = z.liveliness().declare_token(
            ros2.liveliness_key(
                self.domain_id, self.zid, self.NODE_ID, self.NODE_ID, "NN", self.node
            )
        )

    def publisher(self, ros_topic: str, ros_type: str) -> Any:
        """A publisher's token (undeclare it with the publisher)."""
        key = ros2.liveliness_key(
            self.domain_id,
            self.zid,
            self.NODE_ID,
            next(self._ids),
            "MP",
            self.node,
            ros_topic,
            ros_type,
        )
        return self.z.liveliness().declare_token(key)

    def close(self) -> None:
        _undeclare(self._node)


def _undeclare(obj: Any) -> None:
    try:
        obj.undeclare()
    except Exception:  # noqa: BLE001 - the Zenoh session may be closed already
        pass


class _RosPublisher:
    """One ROS 2 topic on Zenoh: key expression, rmw_zenoh attachment, sequence numbers, and
    its graph token when a ``Ros2Graph`` is given."""

    def __init__(
        self,
        z: zenoh.Session,
        conf: Ros2Conf,
        ros_topic: str,
        ros_type: str,
        graph: Ros2Graph | None = None,
    ) -> None:
        self.key = ros2.key_expr(ros_topic, ros_type, conf.domain_id, conf.key_format)
        self._rmw = conf.key_format == "rmw_zenoh"
        self._gid = hashlib.sha256(f"{z.zid()}/{self.key}".encode()).digest()[:16]
        self._seq = itertools.count(1)
        self._pub = z.declare_publisher(self.key, **_QOS)
        self._token = graph.publisher(ros_topic, ros_type) if graph is not None else None

    def put(self, payload: bytes) -> None:
        if self._rmw:
            att = ros2.rmw_attachment(next(self._seq), time.time_ns(), self._gid)
            self._pub.put(payload, attachment=att)
        else:
            self._pub.put(payload)

    def close(self) -> None:
        _undeclare(self._pub)
        if self._token is not None:
            _undeclare(self._token)


class Ros2PoseSink:
    """A session's sink (``send``/``close``) that also publishes its poses as ROS 2 messages."""

    def __init__(
        self,
        inner: Any,
        z: zenoh.Session,
        conf: Ros2Conf,
        map_name: str,
        client_id: str,
        graph: Ros2Graph | None = None,
    ) -> None:
        self.inner = inner
        self.frame_id = frame_id(conf, map_name)
        self._pose = _RosPublisher(
            z, conf, ros2.topic(map_name, client_id, "pose", conf.prefix), ros2.POSE, graph
        )
        self._cov = _RosPublisher(
            z,
            conf,
            ros2.topic(map_name, client_id, "pose_cov", conf.prefix),
            ros2.POSE_COV,
            graph,
        )

    def send(self, pose: PoseMessage) -> None:
        self.inner.send(pose)
        T = pose.world_from_cam
        if not pose.localized or T is None:
            return  # LOST: no pose to give (the msgpack pose says why)
        try:
            self._pose.put(ros2.encode_pose_stamped(pose.stamp_ns, self.frame_id, T.t, T.quat_xyzw))
            if pose.covariance is not None:
                self._cov.put(
                    ros2.encode_pose_with_covariance(
                        pose.stamp_ns, self.frame_id, T.t, T.quat_xyzw, pose.covariance
                    )
                )
        except Exception as exc:  # noqa: BLE001 - the msgpack pose went out; never fail a session
            log.warning("cannot publish the ROS 2 pose of %s: %s", self.frame_id, exc)

    def close(self) -> None:
        self.inner.close()
        self._pose.close()
        self._cov.close()


# Frames handed on: (map, client, decode -> Frame, t_recv).
Submit = Callable[[str, str, Callable[[], Frame], float], None]


class Ros2ImageIntake:
    """Subscribers for ``sensor_msgs`` images; each sample becomes a ``Frame`` for ``submit``."""

    def __init__(
        self,
        z: zenoh.Session,
        conf: Ros2Conf,
        submit: Submit,
        max_bytes: int,
        map_names: Callable[[], list[str]],
    ) -> None:
        self.conf = conf
        self.submit = submit
        self.max_bytes = max_bytes
        self.map_names = map_names
        self._cameras = {c: _camera(s, f"ros2.cameras[{c}]") for c, s in conf.cameras.items()}
        self._default = (
            _camera(conf.default_camera, "ros2.default_camera") if conf.default_camera else None
        )
        self._seq: dict[tuple[str, str], itertools.count] = {}
        self._subs = [
            z.declare_subscriber(self._wild("image", ros2.IMAGE), self._on_image),
            z.declare_subscriber(self._wild("image/compressed", ros2.COMPRESSED), self._on_jpeg),
        ]

    def _wild(self, leaf: str, ros_type: str) -> str:
        c = self.conf
        return ros2.key_expr(f"/{c.prefix}/*/*/{leaf}", ros_type, c.domain_id, c.key_format)

    def _names(self, key: str) -> tuple[str, str]:
        """(map, client) of a sample's key; a ROS token is mapped back to the loaded map whose
        ROS name it is (``lab-1`` is ``lab_1`` on ROS)."""
        parts = key.split("/")
        i = parts.index(self.conf.prefix) if self.conf.prefix in parts else -1
        if i < 0 or len(parts) < i + 3:
            raise WireError(f"not a sfmloc ROS 2 image key: {key!r}")
        map_tok, client_tok = parts[i + 1], parts[i + 2]
        map_name = next((m for m in self.map_names() if ros2.ros_name(m) == map_tok), map_tok)
        return map_name, client_tok.lstrip("_") or client_tok

    def _camera(self, client_id: str, width: int, height: int) -> CameraSpec:
        cam = self._cameras.get(client_id, self._default)
        if cam is None:
            raise WireError(
                f"no camera for ROS 2 client {client_id!r}: set ros2.cameras.{client_id} or "
                "ros2.default_camera ('MODEL w h params...')"
            )
        if (width, height) != (0, 0) and (cam.width, cam.height) != (width, height):
            raise WireError(
                f"ROS 2 image of {width}x{height} for client {client_id!r}, whose camera is "
                f"{cam.width}x{cam.height}"
            )
        return cam

    def _next_seq(self, map_name: str, client_id: str) -> int:
        return next(self._seq.setdefault((map_name, client_id), itertools.count()))

    def _on_image(self, sample: zenoh.Sample) -> None:
        self._handle(sample, compressed=False)

    def _on_jpeg(self, sample: zenoh.Sample) -> None:
        self._handle(sample, compressed=True)

    def _handle(self, sample: zenoh.Sample, compressed: bool) -> None:
        t_recv = time.perf_counter()
        try:
            map_name, client_id = self._names(str(sample.key_expr))
        except WireError as exc:
            log.info("ROS 2 image refused: %s", exc)
            return
        payload = sample.payload.to_bytes()

        def decode() -> Frame:
            if compressed:
                img = ros2.decode_compressed_image(payload, self.max_bytes)
                cam = self._camera(client_id, 0, 0)  # checked when decoded by the worker
                assert img.data is not None
                data, enc = img.data, img.encoding
            else:
                img = ros2.decode_image(payload, self.max_bytes)
                assert img.image is not None
                h, w = img.image.shape[:2]
                cam = self._camera(client_id, w, h)
                enc = "gray8" if img.image.ndim == 2 else "bgr8"
                data = encode_image(img.image, enc)
            seq = self._next_seq(map_name, client_id)
            return Frame(seq, img.stamp_ns, cam, enc, data).validate()

        self.submit(map_name, client_id, decode, t_recv)

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self._subs.clear()


def _camera(spec: str, what: str) -> CameraSpec:
    try:
        cam = Camera.parse(spec)
    except Exception as exc:  # noqa: BLE001 - any parse failure is a config error
        raise ConfigError(f"{what}: {exc}") from None
    return CameraSpec(cam.model, cam.width, cam.height, tuple(float(v) for v in cam.params))
