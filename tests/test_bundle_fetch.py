"""Bundles over the network: the builder's share (builder_service/bundle_share.py) and the
server's fetch (server/bundle_fetch.py) over two real Zenoh sessions on loopback."""

from __future__ import annotations

import contextlib
import hashlib
import shutil

import pytest
import zenoh

from server_helpers import wait_until, zenoh_endpoint
from sfmloc.builder_service.bundle_share import MAX_CHUNK_BYTES, BundleShare
from sfmloc.errors import BundleError, UnavailableError, WireError
from sfmloc.map.bundle import MapBundle, verify_bundle
from sfmloc.server import bundle_fetch
from sfmloc.server.bundle_fetch import fetch_bundle
from sfmloc_client import make_zenoh_config
from sfmloc_client.wire import BUNDLES_KEYEXPR, decode_bundle_files


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture()
def pair():
    """(builder session, server session), connected on a free loopback port."""
    ep = zenoh_endpoint()
    with zenoh.open(make_zenoh_config("peer", listen=[ep], multicast=False)) as a:
        with zenoh.open(make_zenoh_config("peer", connect=[ep], multicast=False)) as b:
            yield a, b


@contextlib.contextmanager
def shared(pair, folder):
    """``folder`` published as bundle "room" on the first session; yields its build id once
    the second reaches it (a declaration takes a moment to propagate; in service the
    announcement arrives long after)."""
    a, b = pair
    build_id = MapBundle(folder, verify=False).build_id
    share = BundleShare()
    share.publish("room", build_id, folder)
    q = a.declare_queryable(BUNDLES_KEYEXPR, share.on_query)
    key = f"sfmloc/bundles/room/{build_id}"
    try:
        assert wait_until(lambda: any(r.ok is not None for r in b.get(key, timeout=1)), 20)
        yield build_id
    finally:
        q.undeclare()


def test_share_answers_only_the_announced_build_and_its_plain_files(world, tmp_path):
    src = world.maps_dir / "room"
    b = MapBundle(src)
    share = BundleShare()
    share.publish("room", b.build_id, src)
    listing = decode_bundle_files(share.answer(f"sfmloc/bundles/room/{b.build_id}", {}))
    names = dict(listing.files)
    assert "manifest.json" in names and "manifest.sha256" in names
    assert names["manifest.json"] == (src / "manifest.json").stat().st_size
    data = share.answer(
        f"sfmloc/bundles/room/{b.build_id}/manifest.json", {"offset": "10", "size": "20"}
    )
    assert data == (src / "manifest.json").read_bytes()[10:30]
    with pytest.raises(WireError, match="no announced bundle"):
        share.answer("sfmloc/bundles/room/20000101T000000Z-00000000", {})
    with pytest.raises(WireError, match="no announced bundle"):
        share.answer(f"sfmloc/bundles/room2/{b.build_id}", {})
    with pytest.raises(WireError, match="no file"):
        share.answer(f"sfmloc/bundles/room/{b.build_id}/passwd", {})
    with pytest.raises(WireError, match="invalid"):  # '..' is not a name: nothing outside
        share.answer(f"sfmloc/bundles/room/{b.build_id}/..", {})
    with pytest.raises(WireError, match="bad range"):
        share.answer(
            f"sfmloc/bundles/room/{b.build_id}/manifest.json",
            {"size": str(MAX_CHUNK_BYTES + 1)},
        )


def test_a_symlink_in_a_shared_folder_is_not_served(world, tmp_path):
    src = tmp_path / "room"
    shutil.copytree(world.maps_dir / "room", src)
    (src / "secret").symlink_to("/etc/hostname")
    share = BundleShare()
    b = MapBundle(src)
    share.publish("room", b.build_id, src)
    assert "secret" not in dict(share.files(src).files)
    with pytest.raises(WireError, match="no file"):
        share.answer(f"sfmloc/bundles/room/{b.build_id}/secret", {})


def test_fetch_copies_verifies_and_installs_the_bundle(world, tmp_path, pair, monkeypatch):
    src = world.maps_dir / "room"
    # Small chunks: every file takes several queries (the offsets are exercised).
    monkeypatch.setattr(bundle_fetch, "CHUNK_BYTES", 64 * 1024)
    seen = []
    dest = tmp_path / "server-maps"
    with shared(pair, src) as build_id:
        path = fetch_bundle(
            pair[1],
            "room",
            build_id,
            dest,
            max_bytes=1 << 30,
            progress=lambda d, t: seen.append((d, t)),
        )
    assert path == dest / "room" and verify_bundle(path) == []
    assert MapBundle(path).build_id == build_id
    for f in src.iterdir():
        assert _sha(path / f.name) == _sha(f), f.name
    assert seen[-1][0] == seen[-1][1] and len(seen) > len(list(src.iterdir()))
    assert sorted(p.name for p in dest.iterdir()) == ["room"]  # no temporary folder left


def test_a_corrupt_transfer_is_refused_and_leaves_nothing(world, tmp_path, pair):
    bad = world.spare_dir / "corrupt" / "room"  # points_xyz.npy bytes flipped after writing
    dest = tmp_path / "server-maps"
    (dest / "room").mkdir(parents=True)  # an older bundle of that name stays as it was
    (dest / "room" / "marker").write_text("old")
    with shared(pair, bad) as build_id, pytest.raises(BundleError, match="verification.*points"):
        fetch_bundle(pair[1], "room", build_id, dest, max_bytes=1 << 30)
    assert sorted(p.name for p in dest.iterdir()) == ["room"]
    assert (dest / "room" / "marker").read_text() == "old"


def test_fetch_refuses_a_bundle_over_the_size_limit_before_writing(world, tmp_path, pair):
    dest = tmp_path / "server-maps"
    with shared(pair, world.maps_dir / "room") as build_id:
        with pytest.raises(BundleError, match="over this server's limit"):
            fetch_bundle(pair[1], "room", build_id, dest, max_bytes=1000)
    assert not dest.exists() or not any(dest.iterdir())


def test_no_builder_answering_is_unavailable(tmp_path, pair):
    _, b = pair
    with pytest.raises(UnavailableError, match="no builder answered"):
        fetch_bundle(b, "room", "20000101T000000Z-00000000", tmp_path, max_bytes=1, timeout_s=1)
