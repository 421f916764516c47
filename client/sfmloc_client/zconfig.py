"""Building a ``zenoh.Config`` from the few settings people change."""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

MODES = ("peer", "client", "router")
SHM_KEY = "transport/shared_memory/enabled"
# A config file that names the key decides shared memory itself (JSON5: quoted or not).
_SHM_IN_FILE = re.compile(r"""["']?shared_memory["']?\s*:""")
_RETRY_IN_FILE = re.compile(r"""["']?retry["']?\s*:""")
# How often a lost connection to a ``connect`` endpoint (the server) is tried again. Zenoh's
# default backs off to 4 s: a server down for 5 s was reached again 2.0 s after it was back;
# with retries every 0.1-0.5 s, 0.4 s (loopback, one run each; issue 16, server restart).
CONNECT_RETRY = {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}


def make_zenoh_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast: bool | None = None,
    config_file: str | Path | None = None,
    shared_memory: bool | None = None,
) -> Any:
    """A ``zenoh.Config``: ``config_file`` (JSON5, anything zenoh accepts) first, then the
    explicit settings over it. ``multicast=None`` keeps zenoh's default (or the file's);
    ``False`` turns multicast scouting off (explicit ``connect`` endpoints only), which is what
    tests and locked-down networks want.

    ``shared_memory``: Zenoh's shared-memory transport, which zenoh turns on by default. We
    turn it off unless asked (``True``, or a config file that sets ``transport/shared_memory``):
    with it on, a process keeps every peer's 16 MiB segment mapped after that peer leaves
    (zenoh 1.10; eclipse-zenoh/zenoh#2787, #1700), so a server grew ~20 MB per short-lived
    client process that ever connected. Off costs copies over loopback only (README, Zenoh;
    docs/measurements.md#zenoh-shm).

    A lost ``connect`` endpoint (a restarted server) is tried again every 0.1-0.5 s
    (``CONNECT_RETRY``) unless the config file sets ``retry`` itself."""
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
    if not _file_sets(config_file, _RETRY_IN_FILE):
        conf.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
    if shared_memory is None and not _file_sets(config_file, _SHM_IN_FILE):
        shared_memory = False
    if shared_memory is not None:
        conf.insert_json5(SHM_KEY, json.dumps(bool(shared_memory)))
    return conf


def _file_sets(config_file: str | Path | None, pattern: re.Pattern[str]) -> bool:
    if not config_file:
        return False
    text = Path(config_file).read_text(encoding="utf-8", errors="replace")
    return bool(pattern.search(text))
