"""sfmloc_client: stream frames to an sfmloc server and get poses back.

Depends only on what a client needs (numpy, msgpack, zenoh, grpc); OpenCV is imported
lazily, only to encode JPEG/PNG or to read video files and cameras.
"""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
