"""The online localization engine: the paper's Algorithm 1 for one camera.

Plain numpy/OpenCV/scipy; no transport imports. The data flow of one frame follows the
files: ``frame`` (validation) -> ``tracker`` (Harris + BRIEF, TRACK-2D, ADD-GOOD-FEATURES)
-> ``track_table`` -> ``matching`` (global and guided 2D-to-3D matching) -> ``pose``
(P3P RANSAC + refinement) -> ``motion_filter`` (Kalman) -> ``certainty`` (covariance, the
verified test) -> ``localizer`` (Algorithm 1, the ``FrameResult``). ``relocalize``: an image
from scratch (global matching, or matching near a prior), for the tracker and single images.
"""

from .config import EngineConf
from .localizer import Localizer
from .relocalize import relocalize  # the function (it shadows its module's name here)
from .types import FrameResult, Matching, Status

__all__ = ["EngineConf", "FrameResult", "Localizer", "Matching", "Status", "relocalize"]
