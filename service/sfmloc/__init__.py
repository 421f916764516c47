"""sfmloc: real-time image-based 6-DOF localization against SfM maps (Lim et al., CVPR 2012).

Library code logs to the ``sfmloc`` logger and never configures logging itself; the
command-line entry point (``sfmloc.cli``) does.
"""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
