"""Building a ``zenoh.Config`` from the few settings people change."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

MODES = ("peer", "client", "router")


def make_zenoh_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast: bool | None = None,
    config_file: str | Path | None = None,
) -> Any:
    """A ``zenoh.Config``: ``config_file`` (JSON5, anything zenoh accepts) first, then the
    explicit settings over it. ``multicast=None`` keeps zenoh's default (or the file's);
    ``False`` turns multicast scouting off (explicit ``connect`` endpoints only), which is what
    tests and locked-down networks want."""
    import zenoh

    if mode not in MODES:
        raise ValueError(f"zenoh mode must be one of {', '.join(MODES)}, got {mode!r}")
    conf = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if multicast is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    return conf
