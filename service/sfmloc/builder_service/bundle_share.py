"""The builder serves the files of the bundles it announced, so that a server on another
machine (no shared folder) can fetch them over Zenoh.

``sfmloc/bundles/<name>/<build-id>``         -> ``BundleFiles`` (plain file names and sizes)
``sfmloc/bundles/<name>/<build-id>/<file>``  with ``?offset=N;size=M`` -> those bytes

Only the current announced build of each name is served, and only regular files directly in
its folder: a query cannot reach anything else on the builder's disk. Integrity is checked by
the fetching server against the bundle's own checksums (``manifest.sha256`` over the manifest,
the manifest over every array file).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

from sfmloc_client.wire import (
    ROOT,
    BundleFiles,
    check_name,
    encode_bundle_files,
)

from ..errors import WireError

log = logging.getLogger(__name__)

# Largest chunk one query may ask for: Zenoh fragments it; a cap keeps one query's memory small.
MAX_CHUNK_BYTES = 4 << 20


class BundleShare:
    """Announced bundles by name (``publish``), answered by ``on_query`` (a Zenoh queryable
    callback on ``BUNDLES_KEYEXPR``)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._bundles: dict[str, tuple[str, Path]] = {}  # name -> (build id, folder)

    def publish(self, name: str, build_id: str, folder: str | Path) -> None:
        with self._lock:
            self._bundles[name] = (build_id, Path(folder))

    def _folder(self, name: str, build_id: str) -> Path:
        with self._lock:
            current = self._bundles.get(name)
        if current is None or current[0] != build_id:
            raise WireError(f"no announced bundle {name!r} at build {build_id!r}")
        return current[1]

    @staticmethod
    def files(folder: Path) -> BundleFiles:
        rows = []
        for p in sorted(folder.iterdir()):
            if p.is_symlink() or not p.is_file():
                continue  # a bundle is plain files; anything else is not ours to serve
            rows.append((check_name(p.name, "bundle file name"), p.stat().st_size))
        return BundleFiles(tuple(rows))

    def answer(self, key: str, parameters: dict[str, str]) -> bytes:
        """The reply payload for a query on ``key`` (``WireError`` saying why there is none)."""
        parts = key.split("/")
        if len(parts) not in (4, 5) or parts[:2] != [ROOT, "bundles"]:
            raise WireError(f"not a bundle key: {key!r} (sfmloc/bundles/<name>/<build-id>[/file])")
        name = check_name(parts[2], "map name")
        folder = self._folder(name, check_name(parts[3], "build id"))
        if len(parts) == 4:
            return encode_bundle_files(self.files(folder))
        file = check_name(parts[4], "bundle file name")
        listed = dict(self.files(folder).files)
        if file not in listed:
            raise WireError(f"bundle {name!r} has no file {file!r}")
        try:
            offset = int(parameters.get("offset", "0"))
            size = int(parameters.get("size", str(MAX_CHUNK_BYTES)))
        except ValueError:
            raise WireError("offset and size must be integers") from None
        if offset < 0 or size <= 0 or size > MAX_CHUNK_BYTES or offset > listed[file]:
            raise WireError(
                f"bad range offset={offset} size={size} for {file} ({listed[file]} bytes; "
                f"chunks up to {MAX_CHUNK_BYTES})"
            )
        with open(folder / file, "rb") as f:
            f.seek(offset)
            return f.read(size)

    def on_query(self, query: Any) -> None:  # a zenoh.Query
        key = str(query.key_expr)
        try:
            payload = self.answer(key, dict(query.parameters))  # Parameters iterates (k, v)
        except (WireError, OSError) as exc:
            log.warning("bundle query %s refused: %s", key, exc)
            query.reply_err(str(exc).encode())
            return
        query.reply(key, payload)
