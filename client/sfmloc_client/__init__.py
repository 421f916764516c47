"""sfmloc_client: stream frames to an sfmloc server and get poses back.

Depends only on what a client needs (numpy, msgpack, zenoh, grpc); OpenCV is imported
lazily, only to encode JPEG/PNG or to read video files and cameras. It never imports the
server package (``sfmloc``).

Zenoh (streams at camera rate)::

    import zenoh
    from sfmloc_client import CameraSpec, FrameStreamer, PoseSubscriber, make_zenoh_config

    cam = CameraSpec.parse("PINHOLE 640 480 525 525 320 240")
    def on_pose(p):                       # PoseMessage: seq, status, world_from_cam, error...
        print(p.seq, p.status, p.world_from_cam)

    with zenoh.open(make_zenoh_config(connect=["tcp/server:7447"])) as z:
        with PoseSubscriber(z, "lab", "drone1", callback=on_pose) as poses, \
                FrameStreamer(z, "lab", "drone1", cam) as fs:
            fs.wait_for_server()
            stats = fs.run("frames/", fps=30, poses=poses)   # or an array stack, a video, 0
            poses.wait_for(stats.last_seq, timeout=5)

Without a callback, ``PoseSubscriber`` queues poses for ``get(timeout)`` or iteration (which
ends when it is closed).

gRPC (single images, map management, streams without Zenoh)::

    from sfmloc_client import LocalizationClient
    with LocalizationClient("server:50051") as c:
        pose = c.relocalize(image, "lab", cam)
        c.list_maps(); c.load_map("/maps/lab"); c.list_sessions()

The wire formats (``sfmloc_client.wire``) are the specification of the Zenoh messages; the
server uses the same functions.
"""

import logging

from .errors import (
    ClientError,
    ImageDataError,
    ImageDecodeError,
    InputError,
    MessageTooLargeError,
    RemoteError,
    SfmlocError,
    WireError,
)
from .grpc_client import AsyncLocalizationClient, LocalizationClient
from .images import decode_image, encode_image
from .sources import SourceFrame, open_source
from .streamer import FrameStreamer, StreamStats
from .subscriber import PoseSubscriber
from .trajectory import TumWriter
from .wire import (
    CameraSpec,
    ErrorInfo,
    Frame,
    MapAnnouncement,
    PoseMessage,
    ServerInfo,
    Transform,
    decode_frame,
    decode_map_announcement,
    decode_pose,
    encode_frame,
    encode_map_announcement,
    encode_pose,
)
from .zconfig import make_zenoh_config
from .discovery import list_server_ids, query_servers

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "AsyncLocalizationClient",
    "CameraSpec",
    "ClientError",
    "ErrorInfo",
    "Frame",
    "FrameStreamer",
    "ImageDataError",
    "ImageDecodeError",
    "InputError",
    "LocalizationClient",
    "MapAnnouncement",
    "MessageTooLargeError",
    "PoseMessage",
    "PoseSubscriber",
    "RemoteError",
    "ServerInfo",
    "SfmlocError",
    "SourceFrame",
    "StreamStats",
    "Transform",
    "TumWriter",
    "WireError",
    "decode_frame",
    "decode_image",
    "decode_map_announcement",
    "decode_pose",
    "encode_frame",
    "encode_image",
    "encode_map_announcement",
    "encode_pose",
    "list_server_ids",
    "make_zenoh_config",
    "open_source",
    "query_servers",
]
