"""The map registry: which maps the server hosts, loaded on every worker.

A map is identified by name; each load gets a new *generation*. Loading is: verify the bundle
once here (manifest, checksums, shapes), load it on every worker (memory-mapped arrays, the
faiss index read in place from its mapped file, lookups precomputed), then swap the registry
entry in one step.
Until the swap, frames keep going to the previous generation; after it, the next frame of each
session goes to the new one and its worker starts a fresh ``Localizer`` there (a frame in
flight on the old map finishes on it). The old generation is then dropped from the workers.
"""

from __future__ import annotations

import builtins
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import BundleError, MapNotFoundError, PermissionDeniedError, WireError
from ..map.bundle import MANIFEST, read_manifest, validate_name, verify_bundle
from . import submaps
from .logfmt import event
from .pool import WorkerPool

log = logging.getLogger(__name__)


def resolve_bundle_path(spec: str, roots: list[str | Path]) -> Path:
    """Where ``spec`` (a map name, or a path) is allowed to load a bundle from.

    A name (no ``/``) is looked up in the roots in order; a path must lead, after symlinks and
    ``..`` are resolved, to a folder strictly inside one of the roots (a relative path is taken
    from the first root). Anything else is ``PermissionDeniedError``, decided from the path
    alone: nothing outside the roots is opened, and the message does not say whether it exists.
    """
    if not spec or "\x00" in spec:
        raise WireError(
            "LoadMap needs a map name or the path of a bundle folder in the maps folders"
        )
    real_roots = [Path(os.path.realpath(r)) for r in roots]
    if "/" not in spec:
        validate_name(spec)
        for root in real_roots:
            if (root / spec).is_dir():
                return root / spec
        raise BundleError(f"no bundle named {spec!r} in the maps folders")
    p = Path(spec)
    real = Path(os.path.realpath(p if p.is_absolute() else Path(roots[0]) / p))
    if not any(real != root and real.is_relative_to(root) for root in real_roots):
        raise PermissionDeniedError(
            f"{spec!r} is outside the server's maps folders: give a map name, or a path inside "
            "them (folders are added with the server's map_roots setting)"
        )
    if not real.is_dir():
        raise BundleError(f"no map bundle at {spec}: not a folder")
    return real


@dataclass(frozen=True)
class MapEntry:
    name: str
    path: str
    build_id: str
    generation: int
    points: int
    descriptors: int
    images: int
    clusters: int
    memory_mb: float
    loaded_utc: str
    submaps: int = 0  # parts of a sub-map set (0: a whole bundle)
    map_memory_mb: float = 0.0  # a set's budget of resident parts per worker

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name,
            "build_id": self.build_id,
            "points": self.points,
            "images": self.images,
            "memory_mb": self.memory_mb,
            "path": self.path,
        }
        if self.submaps:
            out.update(submaps=self.submaps, map_memory_mb=self.map_memory_mb)
        return out


class MapRegistry:
    def __init__(
        self,
        pool: WorkerPool,
        on_change: Callable[[str, MapEntry | None, MapEntry | None], None] | None = None,
        map_memory_mb: float | None = None,
    ) -> None:
        self.pool = pool
        self.map_memory_mb = map_memory_mb  # sub-map sets' budget per worker (None: refused)
        self.on_change = on_change or (lambda name, old, new: None)
        self._maps: dict[str, MapEntry] = {}
        self._lock = threading.Lock()  # guards _maps (reads are a dict lookup)
        self._load_locks: dict[str, threading.Lock] = {}  # one load at a time per name
        self._gen = 0

    def get(self, name: str) -> MapEntry:
        entry = self._maps.get(name)
        if entry is None:
            raise MapNotFoundError(f"map {name!r} is not loaded on this server" + self._hint())
        return entry

    def _hint(self) -> str:
        names = sorted(self._maps)
        return f" (loaded: {', '.join(names)})" if names else " (no maps are loaded)"

    def find(self, name: str) -> MapEntry | None:
        return self._maps.get(name)

    def list(self) -> list[MapEntry]:
        with self._lock:
            return sorted(self._maps.values(), key=lambda e: e.name)

    def load(self, path: str | Path, name: str | None = None) -> MapEntry:
        """Load (or atomically replace) the bundle at ``path`` as ``name`` (default: the
        bundle's own name). Raises ``BundleError`` for a missing or corrupt bundle."""
        path = Path(path).resolve()
        subset = submaps.check_set(path, self.map_memory_mb)  # None: a bundle
        manifest = subset or read_manifest(path)
        name = validate_name(name or manifest.name)
        with self._lock:
            lock = self._load_locks.setdefault(name, threading.Lock())
        with lock:
            t0 = time.perf_counter()
            if subset is not None:
                problems = submaps.verify_submap_set(path, checksums=True)
            else:
                problems = verify_bundle(path, checksums=True)
            if problems:
                raise BundleError(f"map bundle {path} is corrupt: " + "; ".join(problems))
            with self._lock:
                self._gen += 1
                gen = self._gen
            summary = self.pool.load_map(name, gen, str(path), manifest.build_id)
            entry = MapEntry(
                name=name,
                path=str(path),
                build_id=manifest.build_id,
                generation=gen,
                points=summary.points,
                descriptors=summary.descriptors,
                images=summary.images,
                clusters=summary.clusters,
                memory_mb=summary.memory_mb,
                loaded_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                submaps=len(subset.parts) if subset is not None else 0,
                map_memory_mb=(self.map_memory_mb or 0.0) if subset is not None else 0.0,
            )
            with self._lock:
                old = self._maps.get(name)
                self._maps[name] = entry  # the swap: new frames go to the new generation
            if old is not None:
                self.pool.drop_map(name, old.generation)
            event(
                log,
                logging.INFO,
                "map_replaced" if old else "map_loaded",
                map=name,
                build_id=entry.build_id,
                generation=gen,
                points=entry.points,
                memory_mb=entry.memory_mb,
                ms=round((time.perf_counter() - t0) * 1e3, 1),
                path=str(path),
            )
            self.on_change(name, old, entry)
            return entry

    def resident_mb(self, entry: MapEntry) -> float:
        """The most any engine worker holds of a sub-map set now (its mapped files' resident
        pages, as the kernel counts them); 0 for a bundle."""
        if not entry.submaps:
            return 0.0
        pids = {h.pid for h in self.pool.workers if h.pid}
        return max((submaps.resident_map_bytes(p, entry.path) for p in pids), default=0) / 1e6

    def unload(self, name: str) -> MapEntry:
        with self._lock:
            entry = self._maps.pop(name, None)
        if entry is None:
            raise MapNotFoundError(f"map {name!r} is not loaded on this server" + self._hint())
        self.pool.drop_map(name, entry.generation)
        event(log, logging.INFO, "map_unloaded", map=name, build_id=entry.build_id)
        self.on_change(name, entry, None)
        return entry

    # builtins.list: inside this class `list` is the method below
    def load_dir(self, folder: str | Path) -> tuple[builtins.list[MapEntry], builtins.list[str]]:
        """Every bundle directly inside ``folder`` (hidden and temporary folders skipped).
        A broken bundle is reported and skipped: the others still load."""
        folder = Path(folder)
        loaded: builtins.list[MapEntry] = []
        failed: builtins.list[str] = []
        if not folder.is_dir():
            log.warning("maps folder %s does not exist: starting without maps", folder)
            return loaded, failed
        for p in sorted(folder.iterdir()):
            if p.name.startswith(".") or not p.is_dir():
                continue
            if not (p / MANIFEST).is_file() and not submaps.is_submap_set(p):
                continue
            try:
                loaded.append(self.load(p))
            except Exception as exc:  # noqa: BLE001 - one bad bundle must not keep the others out
                event(log, logging.ERROR, "map_load_failed", path=str(p), error=str(exc))
                failed.append(f"{p}: {exc}")
        return loaded, failed
