"""COLMAP sparse models: text and binary read/write round trips, cross-format equality, and
clear errors for malformed files."""

from __future__ import annotations

import numpy as np
import pytest

from sfmloc.cameras import Camera
from sfmloc.errors import CameraModelError, ModelFormatError
from sfmloc.io.colmap import (
    Image,
    Point3D,
    Reconstruction,
    detect_model_format,
    read_model,
    write_model,
)
from sfmloc.transforms import Rigid3d, rotmat_from_rotvec


def random_model(seed=0, n_images=5, n_points=60) -> Reconstruction:
    rng = np.random.default_rng(seed)
    cams = {
        1: Camera("PINHOLE", 640, 480, [525.5, 525.5, 320, 240]),
        3: Camera("OPENCV", 800, 600, [600, 601, 400, 300, -0.1, 0.01, 0.001, 0.002]),
    }
    images = {}
    for i in range(n_images):
        iid = i * 2 + 1
        pose = Rigid3d(rotmat_from_rotvec(rng.normal(0, 0.5, 3)), rng.normal(0, 2, 3))
        images[iid] = Image(
            iid,
            f"sub/im {i}.png",
            1 if i % 2 == 0 else 3,
            pose,
            rng.uniform(0, 600, (20, 2)),
            np.full(20, -1),
        )
    pts = {}
    for p in range(n_points):
        pid = 100 + p
        obs = rng.choice(list(images), size=3, replace=False)
        idxs = []
        for iid in obs:
            im = images[iid]
            free = np.nonzero(im.point3D_ids < 0)[0]
            if len(free) == 0:
                continue
            j = int(free[0])
            im.point3D_ids[j] = pid
            idxs.append((iid, j))
        if not idxs:
            continue
        pts[pid] = Point3D(
            pid,
            rng.normal(0, 3, 3),
            rng.integers(0, 255, 3),
            float(rng.uniform(0, 2)),
            [a for a, _ in idxs],
            [b for _, b in idxs],
        )
    return Reconstruction(cams, images, pts)


def assert_same(a: Reconstruction, b: Reconstruction, atol=0.0):
    assert a.cameras == b.cameras
    assert set(a.images) == set(b.images)
    for iid, im in a.images.items():
        other = b.images[iid]
        assert other.name == im.name and other.camera_id == im.camera_id
        assert np.allclose(
            other.cam_from_world.matrix(), im.cam_from_world.matrix(), atol=1e-12 + atol
        )
        assert np.allclose(other.points2D, im.points2D, atol=atol)
        assert np.array_equal(other.point3D_ids, im.point3D_ids)
    assert set(a.points3D) == set(b.points3D)
    for pid, p in a.points3D.items():
        q = b.points3D[pid]
        assert np.allclose(q.xyz, p.xyz, atol=atol) and np.array_equal(q.rgb, p.rgb)
        assert q.error == pytest.approx(p.error)
        assert np.array_equal(q.track_image_ids, p.track_image_ids)
        assert np.array_equal(q.track_point2D_idxs, p.track_point2D_idxs)


@pytest.mark.parametrize("ext", [".txt", ".bin"])
def test_round_trip(tmp_path, ext):
    rec = random_model()
    write_model(rec, tmp_path, ext)
    assert detect_model_format(tmp_path) == ext
    back = read_model(tmp_path)
    assert_same(rec, back)


def test_text_and_binary_agree(tmp_path):
    rec = random_model(3)
    write_model(rec, tmp_path / "t", ".txt")
    write_model(rec, tmp_path / "b", ".bin")
    assert_same(read_model(tmp_path / "t"), read_model(tmp_path / "b"))


def test_binary_matches_pycolmap(tmp_path):
    """pycolmap reads what we write (and we read what it writes): the formats are COLMAP's."""
    pycolmap = pytest.importorskip("pycolmap")
    rec = random_model(5)
    write_model(rec, tmp_path / "ours", ".bin")
    prec = pycolmap.Reconstruction(str(tmp_path / "ours"))
    assert prec.num_images() == len(rec.images) and prec.num_points3D() == len(rec.points3D)
    (tmp_path / "theirs").mkdir()
    prec.write_binary(str(tmp_path / "theirs"))
    assert_same(rec, read_model(tmp_path / "theirs"))


def test_errors_name_file_and_line(tmp_path):
    with pytest.raises(ModelFormatError, match="does not exist"):
        read_model(tmp_path / "nope")
    (tmp_path / "m").mkdir()
    with pytest.raises(ModelFormatError, match="holds no COLMAP model"):
        read_model(tmp_path / "m")
    write_model(random_model(), tmp_path / "m", ".txt")
    (tmp_path / "m" / "cameras.txt").write_text("1 PINHOLE 640 480 525 525 320\n")
    with pytest.raises(CameraModelError, match=r"cameras.txt:1"):
        read_model(tmp_path / "m")
    write_model(random_model(), tmp_path / "m", ".txt")
    lines = (tmp_path / "m" / "points3D.txt").read_text().splitlines()
    lines[4] = "oops"
    (tmp_path / "m" / "points3D.txt").write_text("\n".join(lines))
    with pytest.raises(ModelFormatError, match=r"points3D.txt:5"):
        read_model(tmp_path / "m")
    write_model(random_model(), tmp_path / "b", ".bin")
    data = (tmp_path / "b" / "images.bin").read_bytes()
    (tmp_path / "b" / "images.bin").write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelFormatError, match="truncated"):
        read_model(tmp_path / "b")


def test_inconsistent_track_is_rejected(tmp_path):
    rec = random_model()
    pid = next(iter(rec.points3D))
    rec.points3D[pid].track_image_ids[0] = 999
    write_model(rec, tmp_path, ".txt")
    with pytest.raises(ModelFormatError, match="missing image 999"):
        read_model(tmp_path)
