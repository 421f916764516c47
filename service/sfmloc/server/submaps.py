"""Sub-map sets in the server (issue 14, build 5): ``sfmloc serve --map-memory MB``.

A sub-map set (``sfmloc map split``; ``map/submaps.py``) in the maps folder is hosted by every
engine worker as a ``SubmapHost``: the set's global index (small, loaded once) and one
``PartCache`` holding at most ``map_memory_mb`` of parts for all the worker's sessions on the
set. Each session runs a ``SubmapLocalizer`` on that cache: its part follows its pose, the
part ahead of it is loaded in the background, a lost session searches the parts by their
place-recognition vote. Single-image relocalization runs on the part the prior covers best, or
else on the best-voted parts (``relocalize_part``).

The budget is **per engine worker** (stream and relocalization workers alike): a worker's
resident parts never exceed it, so the server's map memory is at most ``workers`` times it
(less when workers are on the same parts: the arrays are memory-mapped, so the page cache
holds one copy). Per worker because a worker is where the memory is used and where a frame
must not wait: a server-wide budget would make one worker's sessions wait for another's
evictions. The sessions on one worker must fit beside each other: a part a session is on is
never evicted, and a frame whose part cannot fit gets RESOURCE_EXHAUSTED (raise the budget).

``resident_map_bytes`` measures what a worker process really holds of a set: the resident
pages of its mappings of the set's files (``/proc/PID/smaps``), for the metrics and ListMaps.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..engine.config import EngineConf
from ..engine.submaps import PartCache, SubmapLocalizer
from ..errors import BundleError, ConfigError
from ..map.bundle import MapBundle
from ..map.submaps import (
    SetManifest,
    SubmapSet,
    is_submap_set,
    part_resident_bytes,
    read_set_manifest,
    verify_submap_set,
)
from ..transforms import Rigid3d

log = logging.getLogger(__name__)

__all__ = [
    "SubmapHost",
    "check_set",
    "verify_submap_set",
    "is_submap_set",
    "make_localizer",
    "relocalize_bundle",
    "resident_map_bytes",
]


def budget_bytes(conf: EngineConf, path: str | Path) -> int:
    """The per-worker budget for the set at ``path`` (``ConfigError`` when none is set)."""
    if conf.map_memory_mb is None:
        raise ConfigError(
            f"{path} is a sub-map set: serve it with a memory budget (sfmloc serve --map-memory "
            "MB, per engine worker), or load the whole bundle it was split from"
        )
    return int(conf.map_memory_mb * 1e6)


class SubmapHost:
    """A worker's copy of a sub-map set: its global index and the parts resident for all the
    worker's sessions on it, within the budget (``PartCache``)."""

    def __init__(self, path: str | Path, build_id: str, conf: EngineConf) -> None:
        self.set = SubmapSet(path, verify=False)  # the registry verified the checksums once
        if build_id and self.set.build_id != build_id:
            raise BundleError(
                f"sub-map set {path} changed while loading (build {self.set.build_id}, expected "
                f"{build_id}); retry"
            )
        self.conf = conf
        self.cache = PartCache(self.set, budget_bytes(conf, path))
        self.build_id = self.set.build_id
        self.name = self.set.name

    def summary(self) -> dict[str, Any]:
        m = self.set.manifest
        return {
            "points": m.points,
            "descriptors": sum(p.descriptors for p in m.parts),
            "images": m.images,
            "clusters": m.clusters,
            # What this worker may hold: the global index plus the parts' budget.
            "memory_mb": round((self.set.memory_bytes() + self.cache.memory_budget) / 1e6, 2),
            "build_id": self.build_id,
        }

    def localizer(self, camera: Any, conf: EngineConf) -> SubmapLocalizer:
        return SubmapLocalizer(self.set, camera, conf, cache=self.cache)

    def relocalize_part(self, frame: np.ndarray, camera: Any, prior: Rigid3d | None) -> MapBundle:
        """The part a single image is relocalized on: the one covering ``prior`` best, else
        the best-voted one (loaded now if it is not resident: a relocalization pays for it)."""
        if prior is not None:
            k = int(np.argmax(self.set.parts_near(prior)))
        else:
            probe = SubmapLocalizer(self.set, camera, self.conf, cache=self.cache)
            k = int(np.argmax(probe.vote(frame)))
            probe.close()
        return self.cache.load_now(k)[0]

    def close(self) -> None:
        self.cache.close()


def make_localizer(bundle: Any, camera: Any, conf: EngineConf) -> Any:
    """A session's localizer on what a worker holds for a map: a ``Localizer`` on a bundle, a
    ``SubmapLocalizer`` on a sub-map set."""
    if isinstance(bundle, SubmapHost):
        return bundle.localizer(camera, conf)
    from ..engine import Localizer

    return Localizer(bundle, camera, conf)


def relocalize_bundle(bundle: Any, frame: np.ndarray, camera: Any, prior: Any) -> Any:
    """The bundle a single image is relocalized against (a set's part, or the bundle)."""
    if isinstance(bundle, SubmapHost):
        return bundle.relocalize_part(frame, camera, prior)
    return bundle


def release(bundle: Any) -> None:
    """A map dropped from a worker: a set's loader thread ends."""
    if isinstance(bundle, SubmapHost):
        bundle.close()


def resident_map_bytes(pid: int, folder: str | Path, per_file: dict[str, int] | None = None) -> int:
    """Resident bytes of process ``pid``'s mappings of files under ``folder`` (the map's
    memory-mapped arrays and index as the kernel counts them); 0 when unreadable.
    ``per_file``: filled with the bytes of each file (its path relative to ``folder``)."""
    root = str(Path(folder).resolve()) + "/"
    total = 0
    inside: str | None = None
    try:
        with open(f"/proc/{pid}/smaps", encoding="utf-8", errors="replace") as f:
            for line in f:
                first = line.split(None, 1)[0] if line.strip() else ""
                if "-" in first and not first.endswith(":"):  # a mapping's header line
                    parts = line.split(None, 5)
                    name = parts[5].strip() if len(parts) == 6 else ""
                    inside = name[len(root) :] if name.startswith(root) else None
                elif inside is not None and first == "Rss:":
                    b = int(line.split()[1]) * 1024
                    total += b
                    if per_file is not None:
                        per_file[inside] = per_file.get(inside, 0) + b
    except (OSError, ValueError, IndexError):
        return 0
    return total


def check_set(path: Path, map_memory_mb: float | None) -> SetManifest | None:
    """The manifest of the sub-map set at ``path`` (None when it is not a set), after checking
    that the budget can hold its largest part: clear errors before any worker loads it."""
    if not is_submap_set(path):
        return None
    if map_memory_mb is None:
        budget_bytes(EngineConf(), path)  # raises: sets need a budget
    m = read_set_manifest(path)
    biggest = max((part_resident_bytes(p) for p in m.parts), default=0)
    if map_memory_mb is not None and biggest > map_memory_mb * 1e6:
        raise ConfigError(
            f"the map memory budget ({map_memory_mb:g} MB per worker) cannot hold the largest "
            f"sub-map of {path} ({biggest / 1e6:.1f} MB): raise --map-memory or split the map "
            "into more parts"
        )
    return m


def add_submap_metrics(registry: Any, maps: Any) -> None:
    """Gauges of the sub-map sets a server hosts (``maps``: its ``MapRegistry``)."""
    from .metrics import Gauge

    def sets() -> list[Any]:
        return [e for e in maps.list() if e.submaps]

    def resident() -> dict[tuple[str, ...], float]:
        out: dict[tuple[str, ...], float] = {}
        for e in sets():
            for h in maps.pool.workers:
                if h.pid:
                    out[(e.name, str(h.index))] = float(resident_map_bytes(h.pid, e.path))
        return out

    registry.add(
        Gauge(
            "sfmloc_map_resident_bytes",
            "Resident bytes of a sub-map set's files in each engine worker (kernel's count).",
            ("map", "worker"),
            collect=resident,
        )
    )
    registry.add(
        Gauge(
            "sfmloc_map_memory_budget_bytes",
            "A sub-map set's budget of resident parts per engine worker (--map-memory).",
            ("map",),
            collect=lambda: {(e.name,): e.map_memory_mb * 1e6 for e in sets()},
        )
    )
