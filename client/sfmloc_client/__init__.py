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
from typing import Any

# Public name -> submodule. Loaded on first use (PEP 562), so that importing the contract
# modules (``errors``, ``enums``, ``cameras``, ``keys``, ``rotations``), as the service's
# per-frame core does, loads neither grpc nor zenoh.
# The names and their modules; __init__.pyi declares the same names with their types (the
# lazy __getattr__ below would leave them Any to type checkers).
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
