"""ANN index, camera clusters and the bundle format (atomic writes, verification, loading)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from sfmloc.builder.clusters import ClusterConf, cluster_images
from sfmloc.cameras import Camera
from sfmloc.errors import BundleError, InputError
from sfmloc.map.bundle import MapBundle, MapData, read_manifest, verify_bundle, write_bundle
from sfmloc.map.index import DescriptorIndex, IndexConf, bitmap_from_ranges


# ----------------------------------------------------------------------------- index
def clustered_data(n=20000, d=32, seed=0):
    rng = np.random.default_rng(seed)
    centers = rng.standard_normal((200, d)) * 3
    x = centers[rng.integers(0, 200, n)] + rng.standard_normal((n, d))
    return x.astype(np.float32)


def exact_knn(db, q, k):
    d = ((q[:, None, :] - db[None]) ** 2).sum(-1)
    return np.argsort(d, axis=1)[:, :k]


@pytest.mark.parametrize("kind", ["ivf-sq8", "ivf-flat", "flat"])
def test_index_recall_at_50(kind):
    db = clustered_data()
    q = db[:200] + 0.05 * np.random.default_rng(1).standard_normal((200, 32)).astype(np.float32)
    ix = DescriptorIndex.build(db, IndexConf(kind=kind, nprobe=16))
    D, I = ix.search(q, 50)
    gt = exact_knn(db, q, 50)
    recall = np.mean([len(set(a) & set(b)) / 50 for a, b in zip(I, gt)])
    assert recall > (0.99 if kind == "flat" else 0.8), recall
    assert np.mean(I[:, 0] == np.arange(200)) > 0.95  # the perturbed point itself first
    assert np.all(np.diff(D, axis=1) >= -1e-5)  # sorted
    # distances are Euclidean (not squared)
    d0 = np.linalg.norm(q[0] - db[I[0, 0]])
    assert abs(D[0, 0] - d0) < 0.05 * max(d0, 0.1) + 0.02


@pytest.mark.parametrize("nprobe", [1, 4, 16])
def test_coarse_assigner_chooses_the_flat_quantizers_lists(nprobe):
    """The lists ``CoarseAssigner`` picks are the flat quantizer's (its nprobe nearest
    centroids, same order, same distances), whatever its group size, and the search through
    them returns faiss's own neighbours (measured on redkitchen's 1,879 lists, 23,748 real
    queries, nprobe 4 and 16: every row identical)."""
    import faiss

    from sfmloc.map import index as index_mod

    db = clustered_data(30000)
    ix = DescriptorIndex.build(db, IndexConf(kind="ivf-sq8"))
    assert ix.nlist >= index_mod.COARSE_MIN_LISTS
    rng = np.random.default_rng(2)
    q = (db[rng.choice(len(db), 500, replace=False)] + rng.standard_normal((500, 32))).astype(
        np.float32
    )
    ivf = faiss.extract_index_ivf(ix._index)
    Dq, Iq = ivf.quantizer.search(q, nprobe)
    centroids = ivf.quantizer.reconstruct_n(0, ivf.nlist)
    first = None
    for size in (4, 8, 16, 32):
        Da, Ia = index_mod.CoarseAssigner(centroids, size).assign(q, nprobe)
        assert np.mean(np.all(Ia == Iq, axis=1)) >= 0.998  # ties between equal distances aside
        assert all(set(a) == set(b) for a, b in zip(Ia, Iq))
        np.testing.assert_allclose(Da, Dq, rtol=1e-4, atol=1e-3)
        if first is None:
            first = (Da, Ia)
        else:  # the group size changes the cost only: the same lists, in the same order
            np.testing.assert_array_equal(Ia, first[1])
            np.testing.assert_array_equal(Da, first[0])
    D, I = ix.search(q, 50, nprobe=nprobe)  # through the assigner (500 queries)
    assert list(ix._coarse) == [index_mod.coarse_group_size(ix.nlist, nprobe)]
    D0, I0 = ix._index.search(q, 50, params=faiss.SearchParametersIVF(nprobe=nprobe))
    assert np.mean(np.all(I == I0, axis=1)) >= 0.998
    found = I0 >= 0  # (faiss gives missing neighbours FLT_MAX, the index inf and id -1)
    np.testing.assert_array_equal(I >= 0, found)
    np.testing.assert_allclose(D[found] ** 2, D0[found], rtol=1e-4, atol=1e-3)


def test_coarse_group_size_is_the_power_of_two_nearest_the_balance():
    """sqrt(lists / nprobe) to the nearest power of two, within [4, 64]: redkitchen's 1,879
    lists give 8 at guided matching's nprobe 16 and 16 at global matching's 4."""
    from sfmloc.map.index import coarse_group_size

    assert coarse_group_size(1879, 16) == 8
    assert coarse_group_size(1879, 4) == 16
    assert coarse_group_size(1879, 1) == 32  # sqrt(1879) = 43.3: log2 5.44
    assert coarse_group_size(256, 64) == 4
    assert coarse_group_size(10**7, 1) == 64


def test_coarse_group_sizes_give_the_same_neighbours_on_redkitchen_frames(redkitchen):
    """Real DAISY descriptors, PCA-32 as the bundle stores them (Harris corners of 40
    redkitchen frames as the database, of 4 others as queries): the assigner of the size the
    index now picks and the one of size 32 it replaces choose the same lists, and the index's
    search through it returns faiss's own neighbours, at guided (16) and global (4) nprobe."""
    import cv2
    import faiss

    from sfmloc.features.daisy import DaisyExtractor, Pca
    from sfmloc.features.harris import detect_corners
    from sfmloc.map import index as index_mod

    ex = DaisyExtractor()

    def raw(frames):
        out = []
        for i in frames:
            path = redkitchen / f"frame-{i:06d}.color.jpg"
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            xy = detect_corners(gray, rel_threshold=0.001, max_corners=1000, border=4).xy
            out.append(ex.compute(gray, xy)[1])
        return np.concatenate(out)

    db_raw = raw(range(0, 1000, 25))
    pca = Pca.fit(db_raw)
    db = pca.project(db_raw)
    q = np.ascontiguousarray(pca.project(raw([12, 262, 512, 762])), dtype=np.float32)
    assert len(db) > 20000 and len(q) > 2000
    ix = DescriptorIndex.build(db, IndexConf(kind="ivf-sq8"))
    assert ix.nlist >= index_mod.COARSE_MIN_LISTS
    ivf = faiss.extract_index_ivf(ix._index)
    centroids = ivf.quantizer.reconstruct_n(0, ivf.nlist)
    for nprobe in (4, 16):
        size = index_mod.coarse_group_size(ix.nlist, nprobe)
        assert size != 32
        Da, Ia = index_mod.CoarseAssigner(centroids, size).assign(q, nprobe)
        Db, Ib = index_mod.CoarseAssigner(centroids, 32).assign(q, nprobe)
        np.testing.assert_array_equal(Ia, Ib)
        np.testing.assert_array_equal(Da, Db)
        D, I = ix.search(q, 50, nprobe=nprobe)
        D0, I0 = ix._index.search(q, 50, params=faiss.SearchParametersIVF(nprobe=nprobe))
        assert np.mean(np.all(I == I0, axis=1)) >= 0.998  # ties between equal distances aside
        found = I0 >= 0
        np.testing.assert_array_equal(I >= 0, found)
        np.testing.assert_allclose(D[found] ** 2, D0[found], rtol=1e-4, atol=1e-3)


def test_index_restricted_search_only_returns_allowed_ids():
    db = clustered_data()
    ix = DescriptorIndex.build(db)
    bm = bitmap_from_ranges(len(db), np.array([1000, 5000]), np.array([2000, 5500]))
    D, I = ix.search(db[:50], 20, allowed=bm)
    got = I[I >= 0]
    assert len(got) > 0
    assert np.all(((got >= 1000) & (got < 2000)) | ((got >= 5000) & (got < 5500)))
    # An allowed query point finds itself.
    D, I = ix.search(db[1500:1510], 1, allowed=bm)
    assert np.all(I[:, 0] == np.arange(1500, 1510))


def test_bitmap_from_ranges_is_the_packed_mask():
    """The byte-wise bitmap (ranges merged, bytes filled) holds exactly the ids of the ranges,
    as the packed bool mask of them does: unsorted, touching, overlapping, empty ranges, ranges
    inside one byte and at the ends."""
    rng = np.random.default_rng(5)
    cases = [(16, [0, 8], [8, 16]), (13, [3, 5, 0], [4, 13, 0]), (9, [9], [9]), (1, [0], [1])]
    for _ in range(500):
        n = int(rng.integers(1, 150))
        a, b = rng.integers(0, n + 1, (2, int(rng.integers(0, 8))))
        cases.append((n, list(np.minimum(a, b)), list(np.maximum(a, b))))
    for n, starts, ends in cases:
        mask = np.zeros(n, bool)
        for s, e in zip(starts, ends, strict=True):
            mask[s:e] = True
        got = bitmap_from_ranges(n, np.array(starts, np.int64), np.array(ends, np.int64))
        assert got.dtype == np.uint8
        np.testing.assert_array_equal(got, np.packbits(mask, bitorder="little"))


def test_index_serialization_round_trip():
    db = clustered_data(5000)
    ix = DescriptorIndex.build(db)
    back = DescriptorIndex.deserialize(ix.serialize(), nprobe=ix.nprobe)
    assert back.kind == ix.kind and back.ntotal == 5000 and back.nlist == ix.nlist
    a = ix.search(db[:30], 10)[1]
    b = back.search(db[:30], 10)[1]
    assert np.array_equal(a, b)


def _storage_addresses(ix: DescriptorIndex) -> list[int]:
    """Where the index's data lives: every inverted list's codes and the centroids (IVF), or
    the stored vectors (flat)."""
    import faiss

    if ix._ivf is None:
        return [int(faiss.downcast_index(ix._index).get_xb())]
    il = ix._ivf.invlists
    out = [int(il.get_codes(i)) for i in range(ix.nlist) if il.list_size(i)]
    out += [int(il.get_ids(i)) for i in range(ix.nlist) if il.list_size(i)]
    return out + [int(faiss.downcast_index(ix._ivf.quantizer).get_xb())]


@pytest.mark.parametrize("kind", ["ivf-sq8", "ivf-flat", "flat"])
def test_index_read_in_place_from_a_memory_mapped_file(tmp_path, kind):
    """Worker processes share one copy of a map's index: read from the memory-mapped .npy,
    the index's lists and centroids are views into the file mapping, not copies, and it
    answers exactly as the index it was written from."""
    db = clustered_data(5000)
    ix = DescriptorIndex.build(db, IndexConf(kind=kind))
    np.save(tmp_path / "index.npy", ix.serialize())
    mapped = np.load(tmp_path / "index.npy", mmap_mode="r")
    lo, hi = mapped.ctypes.data, mapped.ctypes.data + mapped.nbytes
    shared = DescriptorIndex.from_buffer(mapped, nprobe=ix.nprobe)
    copied = DescriptorIndex.deserialize(mapped, nprobe=ix.nprobe)
    assert shared.kind == ix.kind == kind and shared.ntotal == 5000
    assert shared.shared_buffer is not None and copied.shared_buffer is None
    assert all(lo <= p < hi for p in _storage_addresses(shared))
    assert not any(lo <= p < hi for p in _storage_addresses(copied))  # the contrast: a private copy
    bm = bitmap_from_ranges(5000, np.array([1000]), np.array([3000]))
    for allowed in (None, bm):
        want = ix.search(db[:40], 10, allowed=allowed)
        got = shared.search(db[:40], 10, allowed=allowed)
        assert np.array_equal(want[1], got[1]) and np.allclose(want[0], got[0])
    del mapped  # the index keeps the mapping alive
    assert np.array_equal(shared.search(db[:5], 3)[1], ix.search(db[:5], 3)[1])


# ----------------------------------------------------------------------------- clusters
def corridor_visibility(n_images=40, pts_per_image=200, overlap=0.6, seed=0):
    """Images along a corridor: image i sees a window of points shared with its neighbours."""
    step = int(pts_per_image * (1 - overlap))
    return [np.arange(i * step, i * step + pts_per_image) for i in range(n_images)], (
        n_images - 1
    ) * step + pts_per_image


def test_clusters_partition_grow_and_cover():
    image_points, n_points = corridor_visibility()
    conf = ClusterConf(max_size=6, growth=0.5)
    cl = cluster_images(image_points, n_points, conf)
    covered = np.unique(np.concatenate(cl.images))
    assert np.array_equal(covered, np.arange(40))  # every image in some cluster
    assert all(len(c) <= 6 + 3 for c in cl.images)
    assert 40 / 6 <= len(cl) <= 40  # about n / max_size parts
    # Clusters are contiguous stretches of the corridor (covisibility respected).
    for c in cl.images:
        assert c.max() - c.min() < 2 * len(c)
    # Growth made them overlap.
    sizes = sum(len(c) for c in cl.images)
    assert sizes > 40
    # Point membership: every point seen by some image belongs to a cluster holding one of them.
    ptr, idx = cl.point_clusters(image_points, n_points)
    assert len(ptr) == n_points + 1
    for p in (0, 123, n_points - 1):
        clusters_of_p = set(idx[ptr[p] : ptr[p + 1]].tolist())
        viewers = {i for i, pts in enumerate(image_points) if p in set(pts.tolist())}
        expected = {c for c, imgs in enumerate(cl.images) if viewers & set(imgs.tolist())}
        assert clusters_of_p == expected


def test_clusters_split_disconnected_components():
    a, na = corridor_visibility(8)
    b = [p + na for p in a]
    cl = cluster_images(a + b, 2 * na, ClusterConf(max_size=20))
    for c in cl.images:
        assert np.all(c < 8) or np.all(c >= 8)


# ----------------------------------------------------------------------------- bundle
def small_map(seed=0, n_images=6, n_points=300, per_point=4) -> MapData:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-2, 2, (n_points, 3))
    desc = rng.standard_normal((n_points * per_point, 32)).astype(np.float16)
    desc_image = np.sort(rng.integers(0, n_images, len(desc))).astype(np.int32)
    ptr = np.searchsorted(desc_image, np.arange(n_images + 1)).astype(np.int64)
    image_points = [np.unique(rng.integers(0, n_points, 80)) for _ in range(n_images)]
    ip_ptr = np.concatenate([[0], np.cumsum([len(p) for p in image_points])])
    cl = cluster_images(image_points, n_points, ClusterConf(max_size=3))
    pc_ptr, pc_idx = cl.point_clusters(image_points, n_points)
    ci_ptr = np.concatenate([[0], np.cumsum([len(c) for c in cl.images])])
    ix = DescriptorIndex.build(desc.astype(np.float32))
    return MapData(
        points_xyz=pts,
        point_ids=np.arange(n_points) + 1,
        point_rgb=np.zeros((n_points, 3), np.uint8),
        descriptors=desc,
        desc_point=rng.integers(0, n_points, len(desc)).astype(np.int32),
        desc_image=desc_image,
        desc_level=np.zeros(len(desc), np.uint8),
        desc_xy=rng.uniform(0, 100, (len(desc), 2)).astype(np.float32),
        image_desc_ptr=ptr,
        image_cam_from_world=np.tile([1.0, 0, 0, 0, 0, 0, 0], (n_images, 1)),
        image_camera=np.zeros(n_images, np.int32),
        image_points_ptr=ip_ptr.astype(np.int64),
        image_points_idx=np.concatenate(image_points).astype(np.int32),
        cluster_images_ptr=ci_ptr.astype(np.int64),
        cluster_images_idx=np.concatenate(cl.images).astype(np.int32),
        point_clusters_ptr=pc_ptr,
        point_clusters_idx=pc_idx,
        pca_mean=np.zeros(104, np.float32),
        pca_basis=np.eye(104, 32, dtype=np.float32),
        index_faiss=ix.serialize(),
        cameras=[Camera.pinhole(640, 480, 500, 500, 320, 240)],
        image_names=[f"im{i}.png" for i in range(n_images)],
    )


def test_bundle_round_trip(tmp_path):
    data = small_map()
    path = write_bundle(data, tmp_path, "lab", params={"tau": 2.0})
    assert path == tmp_path / "lab"
    assert verify_bundle(path) == []
    b = MapBundle(path)
    assert b.name == "lab" and b.n_points == 300 and b.n_descriptors == 1200 and b.n_images == 6
    assert np.array_equal(np.asarray(b.array("descriptors")), data.descriptors)
    assert np.array_equal(b.desc_point, data.desc_point)
    assert b.cameras == data.cameras and b.image_names == data.image_names
    assert b.manifest.params == {"tau": 2.0}
    # arrays are memory-mapped, not copied
    assert isinstance(b.array("descriptors"), np.memmap)
    # the index answers for the stored descriptors, read in place from its mapped file
    D, I = b.index.search(data.descriptors[:5].astype(np.float32), 1)
    assert np.array_equal(I[:, 0], np.arange(5))
    mapped = b.array("index_faiss")
    assert isinstance(mapped, np.memmap) and b.index.shared_buffer is not None
    lo, hi = mapped.ctypes.data, mapped.ctypes.data + mapped.nbytes
    assert all(lo <= p < hi for p in _storage_addresses(b.index))
    # no pickle anywhere: every array loads with allow_pickle=False
    for entry in b.manifest.arrays.values():
        np.load(path / entry.file, allow_pickle=False)


def test_bundle_timings_include_the_write_itself(tmp_path):
    """The write stage is timed once the arrays are on disk (the builder used to record it
    before writing): "write" grows by the write and so does "total"."""
    import time

    data = small_map()
    given = {"sfm": 2.0, "write": 0.25, "total": 3.0}
    t0 = time.perf_counter()
    path = write_bundle(data, tmp_path, "lab", timings_s=given)
    wall = time.perf_counter() - t0
    t = read_manifest(path).timings_s
    spent = t["write"] - 0.25
    assert 0 < spent <= wall, (spent, wall)
    assert t["total"] == pytest.approx(3.0 + spent) and t["sfm"] == 2.0
    assert given == {"sfm": 2.0, "write": 0.25, "total": 3.0}  # the caller's dict is not changed
    assert read_manifest(write_bundle(small_map(), tmp_path, "none")).timings_s == {}


def test_bundle_detects_corruption(tmp_path):
    path = write_bundle(small_map(), tmp_path, "lab")
    f = path / "desc_point.npy"
    raw = bytearray(f.read_bytes())
    raw[-3] ^= 0xFF
    f.write_bytes(bytes(raw))
    problems = verify_bundle(path)
    assert any("desc_point.npy" in p and "checksum" in p for p in problems)
    with pytest.raises(BundleError, match="desc_point"):
        MapBundle(path)


def test_bundle_detects_missing_truncated_and_bad_manifest(tmp_path):
    path = write_bundle(small_map(), tmp_path, "lab")
    (path / "pca_basis.npy").unlink()
    assert any("pca_basis.npy: missing" in p for p in verify_bundle(path))
    path = write_bundle(small_map(), tmp_path, "lab2")
    f = path / "points_xyz.npy"
    f.write_bytes(f.read_bytes()[:-16])
    assert any("points_xyz.npy" in p for p in verify_bundle(path))
    path = write_bundle(small_map(), tmp_path, "lab3")
    m = json.loads((path / "manifest.json").read_text())
    m["version"] = 99
    _reseal(path, json.dumps(m))
    with pytest.raises(BundleError, match="version 99"):
        MapBundle(path)
    _reseal(path, "{not json")
    with pytest.raises(BundleError, match="unreadable manifest"):
        read_manifest(path)
    with pytest.raises(BundleError, match="not a folder"):
        MapBundle(tmp_path / "nothing-here")


def test_bundle_inconsistent_lookup_is_rejected(tmp_path):
    data = small_map()
    data.desc_point = data.desc_point.copy()
    data.desc_point[7] = 10_000  # refers past the last point
    path = write_bundle(data, tmp_path, "bad")
    assert verify_bundle(path) == []  # checksums are fine: it was written like that
    with pytest.raises(BundleError, match="desc_point refers outside"):
        MapBundle(path)


def test_bundle_replace_is_atomic_and_failures_leave_nothing(tmp_path):
    first = write_bundle(small_map(0), tmp_path, "lab")
    old_id = read_manifest(first).build_id
    # A failing write (an array of the wrong rank) leaves the old bundle intact, no temp dirs.
    bad = small_map(1)
    bad.points_xyz = bad.points_xyz.ravel()
    with pytest.raises(BundleError):
        write_bundle(bad, tmp_path, "lab")
    assert read_manifest(first).build_id == old_id and verify_bundle(first) == []
    assert sorted(os.listdir(tmp_path)) == ["lab"]
    # A successful rebuild replaces it, again with no leftovers.
    write_bundle(small_map(2), tmp_path, "lab")
    assert read_manifest(tmp_path / "lab").build_id != old_id
    assert verify_bundle(tmp_path / "lab") == []
    assert sorted(os.listdir(tmp_path)) == ["lab"]


@pytest.mark.parametrize("name", ["", "a/b", "../x", "with space", "star*", "-lead", "x" * 65])
def test_bundle_rejects_bad_names(tmp_path, name):
    with pytest.raises(InputError, match="invalid map name"):
        write_bundle(small_map(), tmp_path, name)


def test_bundle_scene_scale_is_median_observed_depth(tmp_path):
    """scene_scale is the median depth of observed points in their cameras: scaling the
    scene by s scales it by s (thresholds built on it are unit-free)."""
    import dataclasses

    for s in (0.01, 1.0, 100.0):
        data = small_map()
        data = dataclasses.replace(
            data,
            points_xyz=data.points_xyz * s,
            image_cam_from_world=np.tile([1.0, 0, 0, 0, 0, 0, 10.0 * s], (6, 1)),
        )
        b = MapBundle(write_bundle(data, tmp_path / str(s), "lab"))
        idx = np.asarray(data.image_points_idx)
        expect = np.median(data.points_xyz[idx, 2] + 10.0 * s)
        assert b.scene_scale == pytest.approx(expect, rel=1e-9)
        assert 9.0 * s < b.scene_scale < 11.0 * s


def _reseal(path, text: str) -> None:
    """Rewrite the manifest *and* its checksum (what a deliberate edit would do), so the checks
    behind the checksum can be tested."""
    import hashlib

    (path / "manifest.json").write_text(text)
    digest = hashlib.sha256(text.encode()).hexdigest()
    (path / "manifest.sha256").write_text(f"{digest}  manifest.json\n")


def test_bundle_one_byte_change_anywhere_is_refused(tmp_path):
    """Any single changed byte of any file of a bundle, the manifest included (e.g. fx
    525.505 -> 925.505), is refused by verify and by loading."""
    base = write_bundle(small_map(), tmp_path, "lab")
    files = sorted(p.name for p in base.iterdir())
    assert "manifest.json" in files and "manifest.sha256" in files
    for k, fname in enumerate(files):
        path = write_bundle(small_map(), tmp_path, f"edit{k}")
        f = path / fname
        raw = bytearray(f.read_bytes())
        pos = len(raw) // 2 if fname != "manifest.json" else raw.index(b'"fx"') + 1
        raw[pos] ^= 0x01
        f.write_bytes(bytes(raw))
        assert verify_bundle(path), fname
        with pytest.raises(BundleError):
            MapBundle(path)
    # an edited intrinsic is named as a manifest edit
    path = write_bundle(small_map(), tmp_path, "fx")
    text = (path / "manifest.json").read_text()
    (path / "manifest.json").write_text(text.replace("500.0", "900.0", 1))
    with pytest.raises(BundleError, match="manifest.json: checksum mismatch"):
        MapBundle(path)


def test_bundle_checksum_file_is_sha256sum_format(tmp_path):
    import subprocess

    path = write_bundle(small_map(), tmp_path, "lab")
    out = subprocess.run(
        ["sha256sum", "-c", "manifest.sha256"], cwd=path, capture_output=True, text=True
    )
    assert out.returncode == 0 and "manifest.json: OK" in out.stdout


@pytest.mark.parametrize(
    "bad", ["../../etc/passwd", "/etc/passwd", "sub/points_xyz.npy", "..npy", "x.txt"]
)
def test_bundle_array_paths_stay_inside(tmp_path, bad):
    """An array file named outside the bundle is refused before anything is opened, and the
    error says nothing about the outside file (whether it exists, its size)."""
    path = write_bundle(small_map(), tmp_path, "lab")
    m = json.loads((path / "manifest.json").read_text())
    m["arrays"]["points_xyz"]["file"] = bad
    _reseal(path, json.dumps(m))
    with pytest.raises(BundleError, match="plain .npy file name") as err:
        MapBundle(path)
    assert "No such file" not in str(err.value) and "size" not in str(err.value)
    assert any("plain .npy file name" in p for p in verify_bundle(path))


def test_bundle_refuses_symlinks_and_a_missing_checksum(tmp_path):
    outside = tmp_path / "outside.npy"
    np.save(outside, np.zeros((300, 3)))
    path = write_bundle(small_map(), tmp_path, "lab")
    (path / "points_xyz.npy").unlink()
    (path / "points_xyz.npy").symlink_to(outside)
    assert any("not a regular file" in p for p in verify_bundle(path))
    with pytest.raises(BundleError, match="not a regular file"):
        MapBundle(path, verify=False)
    path = write_bundle(small_map(), tmp_path, "lab2")
    (path / "manifest.sha256").unlink()
    with pytest.raises(BundleError, match="manifest.sha256 is missing"):
        MapBundle(path)
    path = write_bundle(small_map(), tmp_path, "lab3")
    (path / "manifest.json").rename(tmp_path / "m.json")
    (path / "manifest.json").symlink_to(tmp_path / "m.json")
    with pytest.raises(BundleError, match="not a regular file"):
        read_manifest(path)


def _nested(depth: int, fn):
    return fn() if depth == 0 else _nested(depth - 1, fn)


def test_npy_loads_on_two_threads_at_once_both_succeed(tmp_path):
    """numpy parses a .npy header with ast.literal_eval, and CPython 3.11's AST constructor
    keeps its recursion depth in state all threads share: one thread's parse inside another's
    failed the other with SystemError "AST constructor recursion depth mismatch" (a test
    server's worker threads loading a map together: room2 did not load). Forced here: each
    time the collector runs while thread A is in ast.parse, thread B loads (from a deeper
    stack) before A goes on. With plain np.load, A fails on Python 3.11.7; load_npy serializes
    the loads (B waits for A), and both succeed."""
    import gc
    import sys
    import threading

    from sfmloc.map.bundle import load_npy

    p = tmp_path / "a.npy"
    np.save(p, np.arange(12, dtype=np.float32).reshape(3, 4))
    go, done = threading.Event(), threading.Event()
    errors: list[BaseException] = []
    loaded: list[np.ndarray] = []
    b_waited = threading.Event()

    def on_gc(phase: str, info: dict) -> None:
        in_parse = sys._getframe(1).f_code.co_name == "parse"  # the frame calling compile()
        if threading.current_thread() is a and phase == "start" and in_parse:
            if not b_waited.is_set():
                done.clear()
                go.set()
                if not done.wait(1.0):
                    b_waited.set()  # B is held until A's load is done

    def load(depth: int) -> None:
        try:
            loaded.append(_nested(depth, lambda: np.asarray(load_npy(p, mmap_mode="r"))))
        except Exception as exc:  # noqa: BLE001 - the failure the test is about
            errors.append(exc)

    def b_loop() -> None:
        while go.wait(10.0) and len(loaded) < 50:
            go.clear()
            load(7)
            done.set()
            if not a.is_alive():
                return

    a = threading.Thread(target=load, args=(0,))
    b = threading.Thread(target=b_loop)
    threshold = gc.get_threshold()
    gc.callbacks.append(on_gc)
    gc.set_threshold(1)  # the collector runs at (nearly) every allocation, in A's parse too
    try:
        b.start()
        a.start()
        a.join(60)
        go.set()
        b.join(60)
    finally:
        gc.set_threshold(*threshold)
        gc.callbacks.remove(on_gc)
    assert not errors, errors
    assert len(loaded) >= 2 and all(np.array_equal(x, loaded[0]) for x in loaded)


# ----------------------------------------------------------------------------- packed bundles
def _posed_map() -> MapData:
    """``small_map`` with distinct, non-unit camera quaternions (rotations to compare)."""
    import dataclasses

    data = small_map()
    rng = np.random.default_rng(3)
    q = rng.standard_normal((6, 4)) * 2.0
    t = rng.standard_normal((6, 3))
    t[:, 2] += 10.0
    return dataclasses.replace(data, image_cam_from_world=np.hstack([q, t]))


def test_packed_bundle_loads_exactly_as_the_npy_one(tmp_path):
    """A packed bundle (format 2: every array in one mapped file, the rotations and scene
    scale written by the writer) loads the same arrays, poses, scene scale, cameras and index
    as the .npy bundle of the same data, from one file mapping."""
    from sfmloc.map.bundle import ARRAY_SPECS, PACKED_FILE

    data = _posed_map()
    a = MapBundle(write_bundle(data, tmp_path, "npy"))
    path = write_bundle(data, tmp_path, "packed", packed=True)
    assert verify_bundle(path) == []
    assert sorted(p.name for p in path.iterdir()) == [
        PACKED_FILE,
        "manifest.json",
        "manifest.sha256",
    ]
    b = MapBundle(path)
    assert a.manifest.version == 1 and b.manifest.version == 2
    for name in ARRAY_SPECS:
        assert np.array_equal(np.asarray(b.array(name)), np.asarray(a.array(name))), name
        assert b.array(name).dtype == a.array(name).dtype
    assert b.scene_scale == a.scene_scale  # stored by the writer, the same function's value
    for ta, tb in zip(a.image_cam_from_world, b.image_cam_from_world):
        assert np.array_equal(ta.rotation, tb.rotation)
        assert np.array_equal(ta.translation, tb.translation)
    assert b.cameras == a.cameras == data.cameras and b.image_names == a.image_names
    assert b.keypoint_scales == a.keypoint_scales
    assert np.array_equal(b.point_images()[0], a.point_images()[0])
    assert np.array_equal(b.point_images()[1], a.point_images()[1])
    # one mapping holds every array, the index read in place from it
    (m,) = b.mappings()
    blob = b.array("index_faiss")
    assert b.index.shared_buffer is not None
    lo, hi = blob.ctypes.data, blob.ctypes.data + blob.nbytes
    assert all(lo <= p < hi for p in _storage_addresses(b.index))
    q = data.descriptors[:7].astype(np.float32)
    assert np.array_equal(b.index.search(q, 3)[1], a.index.search(q, 3)[1])
    # the derived rotations (72 B an image) are all the memory it adds
    assert b.memory_bytes() == a.memory_bytes() + 72 * a.n_images
    # every array starts on its own page, read-only
    for e in b.manifest.arrays.values():
        assert e.file == PACKED_FILE and e.offset is not None and e.offset % 4096 == 0
    assert not b.points_xyz.flags.writeable
    # a version-1 manifest carries no offsets: readers before version 2 still accept it
    assert '"offset"' not in (tmp_path / "npy" / "manifest.json").read_text()
    del b, blob
    import gc
    import weakref

    ref = weakref.ref(m)
    del m
    gc.collect()
    assert ref() is None  # nothing else keeps the file mapped once the bundle is gone


def test_packed_bundle_refuses_corruption_truncation_and_bad_offsets(tmp_path):
    """Any changed byte of an array is named by verify (its own checksum) and refused by a
    verified load; a truncated file or an edited offset is refused by any load."""
    from sfmloc.map.bundle import PACKED_FILE

    base = write_bundle(_posed_map(), tmp_path, "base", packed=True)
    m = read_manifest(base)
    for k, (name, e) in enumerate(m.arrays.items()):
        path = write_bundle(_posed_map(), tmp_path, f"edit{k}", packed=True)
        raw = bytearray((path / PACKED_FILE).read_bytes())
        raw[e.offset + e.bytes // 2] ^= 0x01
        (path / PACKED_FILE).write_bytes(bytes(raw))
        assert verify_bundle(path) == [f"{PACKED_FILE}: {name} checksum mismatch (corrupt)"]
        with pytest.raises(BundleError, match="checksum mismatch"):
            MapBundle(path)
    path = write_bundle(_posed_map(), tmp_path, "short", packed=True)
    f = path / PACKED_FILE
    f.write_bytes(f.read_bytes()[:-10])
    assert any("ends at" in p for p in verify_bundle(path, checksums=False))
    with pytest.raises(BundleError, match="does not fit"):
        MapBundle(path, verify=False)
    # an offset moved (manifest resealed): off its page, or past the file
    for bad in (4, 1 << 30):
        path = write_bundle(_posed_map(), tmp_path, f"off{bad}", packed=True)
        raw = json.loads((path / "manifest.json").read_text())
        raw["arrays"]["points_xyz"]["offset"] = bad
        _reseal(path, json.dumps(raw))
        assert verify_bundle(path, checksums=False), bad
        with pytest.raises(BundleError):
            MapBundle(path, verify=False)
    # offsets in a version-1 bundle, or none in a version-2 one: refused as a bad layout
    path = write_bundle(_posed_map(), tmp_path, "mixed", packed=True)
    raw = json.loads((path / "manifest.json").read_text())
    raw["version"] = 1
    _reseal(path, json.dumps(raw))
    with pytest.raises(BundleError, match="not where a version-1 bundle keeps it"):
        MapBundle(path, verify=False)
