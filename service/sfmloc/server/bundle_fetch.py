"""Fetch an announced bundle from the builder over Zenoh (no shared folder needed).

The builder answers ``sfmloc/bundles/<name>/<build-id>`` with the bundle's file list and
``.../<file>?offset=N;size=M`` with bytes (``builder_service/bundle_share.py``). The files are
written into a hidden temporary folder inside the server's maps folder (server start-up skips
hidden folders), verified with the bundle's own checksums (``manifest.sha256`` over the
manifest, the manifest over every array file) and the announced name and build id, and only
then put in place as ``<maps>/<name>`` in one atomic exchange. Any failure removes the
temporary folder: a half-fetched bundle is never seen.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sfmloc_client.wire import BundleFiles, bundle_file_key, bundle_key, decode_bundle_files

from ..errors import BundleError, UnavailableError, WireError
from ..map.bundle import read_manifest, swap_into_place, verify_bundle

CHUNK_BYTES = 1 << 20  # one query per MiB: Zenoh fragments it; progress and retries stay fine


def _get_one(z: Any, selector: str, timeout_s: float) -> bytes:
    """The first OK reply's payload for ``selector``; ``UnavailableError`` without one."""
    errors = []
    for reply in z.get(selector, timeout=timeout_s):
        if reply.ok is not None:
            return bytes(reply.ok.payload.to_bytes())
        errors.append(reply.err.payload.to_string())
    if errors:
        raise UnavailableError(f"builder refused {selector}: {errors[0]}")
    raise UnavailableError(f"no builder answered {selector} within {timeout_s:g} s")


def list_bundle(z: Any, name: str, build_id: str, timeout_s: float = 10.0) -> BundleFiles:
    """The announced bundle's files, as its builder lists them."""
    return decode_bundle_files(_get_one(z, bundle_key(name, build_id), timeout_s))


def fetch_bundle(
    z: Any,
    name: str,
    build_id: str,
    maps_dir: str | Path,
    *,
    max_bytes: int,
    timeout_s: float = 10.0,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Download bundle ``name`` at ``build_id`` into ``maps_dir/name``; returns that path.

    ``max_bytes`` caps the bundle's size (checked against the list before anything is written);
    ``progress(done, total)`` is called after each chunk. Raises ``BundleError`` when what
    arrived fails verification, ``UnavailableError`` when the builder does not answer."""
    maps_dir = Path(maps_dir)
    listing = list_bundle(z, name, build_id, timeout_s)
    total = listing.total_bytes
    if total > max_bytes:
        raise BundleError(
            f"bundle {name} ({build_id}) is {total / 2**20:.1f} MB, over this server's limit of "
            f"{max_bytes / 2**20:.1f} MB (max_fetch_mb)"
        )
    maps_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".fetch-{name}-", dir=maps_dir))
    try:
        done = 0
        for file, size in listing.files:
            with open(tmp / file, "wb") as f:
                offset = 0
                while offset < size:
                    n = min(CHUNK_BYTES, size - offset)
                    data = _get_one(
                        z,
                        f"{bundle_file_key(name, build_id, file)}?offset={offset};size={n}",
                        timeout_s,
                    )
                    if len(data) != n:
                        raise BundleError(
                            f"bundle {name}: {file} at {offset} gave {len(data)} bytes, asked {n}"
                        )
                    f.write(data)
                    offset += n
                    done += n
                    if progress is not None:
                        progress(done, total)
                f.flush()
                os.fsync(f.fileno())
        problems = verify_bundle(tmp)
        if problems:
            raise BundleError(
                f"bundle {name} ({build_id}) fetched from the builder fails verification: "
                + "; ".join(problems[:3])
            )
        manifest = read_manifest(tmp)
        if (manifest.name, manifest.build_id) != (name, build_id):
            raise BundleError(
                f"fetched bundle is {manifest.name} ({manifest.build_id}), announced as {name} "
                f"({build_id})"
            )
        final = maps_dir / name
        swap_into_place(tmp, final)
        return final
    except WireError as exc:
        raise BundleError(
            f"bundle {name} ({build_id}): bad answer from the builder: {exc}"
        ) from None
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
