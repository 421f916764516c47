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

import importlib
import logging
from typing import TYPE_CHECKING, Any

# Public name -> submodule. Loaded on first use (PEP 562), so that importing the contract
# modules (``errors``, ``enums``, ``cameras``, ``keys``, ``rotations``), as the service's
# per-frame core does, loads neither grpc nor zenoh.
_EXPORTS = {
    "Matching": "enums",
    "Status": "enums",
    "ClientError": "errors",
    "ImageDataError": "errors",
    "ImageDecodeError": "errors",
    "InputError": "errors",
    "MessageTooLargeError": "errors",
    "RemoteError": "errors",
    "SfmlocError": "errors",
    "WireError": "errors",
    "AsyncLocalizationClient": "grpc_client",
    "LocalizationClient": "grpc_client",
    "decode_image": "images",
    "encode_image": "images",
    "SourceFrame": "sources",
    "open_source": "sources",
    "Placement": "placement",
    "FrameStreamer": "streamer",
    "StreamStats": "streamer",
    "PoseSubscriber": "subscriber",
    "TumWriter": "trajectory",
    "FramesWriter": "trajectory",
    "CameraSpec": "wire",
    "ErrorInfo": "wire",
    "Frame": "wire",
    "MapAnnouncement": "wire",
    "PoseMessage": "wire",
    "ServerInfo": "wire",
    "Transform": "wire",
    "decode_frame": "wire",
    "decode_map_announcement": "wire",
    "decode_pose": "wire",
    "encode_frame": "wire",
    "encode_map_announcement": "wire",
    "encode_pose": "wire",
    "make_zenoh_config": "zconfig",
    "list_server_ids": "discovery",
    "query_servers": "discovery",
}


# The real types for type checkers, as explicit re-exports (`X as X`: __all__ is built from
# _EXPORTS, which linters cannot read). Without them mypy saw every export as Any, and the
# demo's report passed a PoseMessage where a Transform belongs unnoticed. At run time the
# exports still load lazily (__getattr__).
if TYPE_CHECKING:
    from .discovery import list_server_ids as list_server_ids
    from .discovery import query_servers as query_servers
    from .enums import Matching as Matching
    from .enums import Status as Status
    from .errors import ClientError as ClientError
    from .errors import ImageDataError as ImageDataError
    from .errors import ImageDecodeError as ImageDecodeError
    from .errors import InputError as InputError
    from .errors import MessageTooLargeError as MessageTooLargeError
    from .errors import RemoteError as RemoteError
    from .errors import SfmlocError as SfmlocError
    from .errors import WireError as WireError
    from .grpc_client import AsyncLocalizationClient as AsyncLocalizationClient
    from .grpc_client import LocalizationClient as LocalizationClient
    from .images import decode_image as decode_image
    from .images import encode_image as encode_image
    from .placement import Placement as Placement
    from .sources import SourceFrame as SourceFrame
    from .sources import open_source as open_source
    from .streamer import FrameStreamer as FrameStreamer
    from .streamer import StreamStats as StreamStats
    from .subscriber import PoseSubscriber as PoseSubscriber
    from .trajectory import FramesWriter as FramesWriter
    from .trajectory import TumWriter as TumWriter
    from .wire import CameraSpec as CameraSpec
    from .wire import ErrorInfo as ErrorInfo
    from .wire import Frame as Frame
    from .wire import MapAnnouncement as MapAnnouncement
    from .wire import PoseMessage as PoseMessage
    from .wire import ServerInfo as ServerInfo
    from .wire import Transform as Transform
    from .wire import decode_frame as decode_frame
    from .wire import decode_map_announcement as decode_map_announcement
    from .wire import decode_pose as decode_pose
    from .wire import encode_frame as encode_frame
    from .wire import encode_map_announcement as encode_map_announcement
    from .wire import encode_pose as encode_pose
    from .zconfig import make_zenoh_config as make_zenoh_config


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # once loaded, a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = list(_EXPORTS)
