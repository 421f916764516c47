"""Type declarations of sfmloc_client's lazy exports (``__init__.py`` loads each on first use
through ``__getattr__``, which leaves type checkers only ``Any``). The same names as
``_EXPORTS`` there, as explicit re-exports; tests/test_client.py keeps the two equal. A stub,
not imports under TYPE_CHECKING in ``__init__.py``: those would make every module that imports
the package (the engine does, for its wire contract) appear to name zenoh and grpc.
"""

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

_EXPORTS: dict[str, str]
__version__: str
__all__: list[str]

def __dir__() -> list[str]: ...
