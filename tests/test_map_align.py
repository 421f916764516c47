"""sfmloc map align: a similarity applied to a bundle, recovered from correspondences.

Exact ground truth: the synthetic room's bundle transformed by a known similarity; the
transform is then recovered from image positions or point pairs (with and without an up
direction), and the engine localizes real frames of the room in the aligned map at the
transformed ground truth.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from sfmloc.cli.main import main as cli
from sfmloc.errors import InputError
from sfmloc.map import align as A
from sfmloc.map.bundle import MapBundle, read_manifest
from sfmloc.transforms import rotation_angle_deg, rotmat_from_rotvec

SIM = A.Sim3(0.37, rotmat_from_rotvec([0.3, -1.1, 0.7]), np.array([12.0, -3.5, 101.0]))


@pytest.fixture(scope="module")
def aligned(world, tmp_path_factory):
    """The room bundle copied to a scratch folder and aligned by SIM (the original kept)."""
    out = tmp_path_factory.mktemp("align")
    src = shutil.copytree(world.maps_dir / "room", out / "room")
    bundle = MapBundle(src)
    path = A.write_aligned(bundle, SIM, out, "room-sim", record={"test": True})
    return bundle, MapBundle(path)


def test_bundle_transformed_exactly(aligned, world):
    before, after = aligned
    assert after.build_id != before.build_id
    np.testing.assert_allclose(after.points_xyz, SIM.apply(before.points_xyz), atol=1e-9)
    for T0, T1 in zip(before.image_cam_from_world, after.image_cam_from_world):
        np.testing.assert_allclose(T1.center, SIM.apply(T0.center), atol=1e-9)
        # Projections are unchanged: the camera frame scales with the world.
        X = before.points_xyz[:50]
        cam = before.cameras[0]
        uv0, _ = cam.project(T0, X)
        uv1, _ = cam.project(T1, SIM.apply(X))
        np.testing.assert_allclose(uv1, uv0, atol=1e-6)
    assert after.scene_scale == pytest.approx(SIM.scale * before.scene_scale, rel=1e-9)
    # Everything the matcher uses is untouched.
    np.testing.assert_array_equal(after.array("descriptors"), before.array("descriptors"))
    np.testing.assert_array_equal(after.array("index_faiss"), before.array("index_faiss"))
    entry = after.manifest.source["alignments"][-1]
    assert entry["from_build_id"] == before.build_id
    assert entry["target_from_map"]["scale"] == pytest.approx(SIM.scale)


def test_engine_localizes_in_the_aligned_frame(aligned, world):
    """Real frames localize in the aligned map at the transformed ground truth (to the same
    fraction of the scene scale as in the original map)."""
    from sfmloc.cameras import Camera
    from sfmloc.engine import Localizer

    _, after = aligned
    cam = Camera.from_json(world.root / "synth" / "camera.json")
    loc = Localizer(after, cam)
    errs = []
    for k in range(0, 20):
        r = loc.localize(world.gray[k], k / 30.0)
        if r.localized:
            est = r.cam_from_world.center
            errs.append(np.linalg.norm(est - SIM.apply(world.gt_cam_from_world[k].center)))
    assert len(errs) >= 15
    assert np.median(errs) < 0.01 * after.scene_scale


@pytest.mark.parametrize("use_up", [False, True])
def test_similarity_recovered_from_image_positions(aligned, use_up):
    before, after = aligned
    # Known positions (the original frame) of 10 images: recover original_from_aligned.
    truth = A.image_centers(before)
    known = {k: truth[k] for k in sorted(truth)[::4][:10]}
    assert len(known) == 10
    corr = A.match_positions(A.image_centers(after), known)
    inv_R = SIM.rotation.T
    up_map = inv_R.T @ np.array([0.0, 0.0, 1.0]) if use_up else None  # aligned-frame up
    sim = A.estimate_sim3(corr, up_map=up_map, up_target=[0, 0, 1])
    assert sim.scale == pytest.approx(1 / SIM.scale, rel=1e-9)
    assert rotation_angle_deg(sim.rotation, inv_R) < 1e-6
    held = {k: v for k, v in truth.items() if k not in known}
    res = A.residuals(sim, A.match_positions(A.image_centers(after), held))
    assert len(res) == len(truth) - 10 and res.max() < 1e-8


def test_up_constrains_the_rotation_under_noise():
    """With noisy correspondences the fitted rotation takes the given up exactly onto the
    target's, and two correspondences suffice."""
    rng = np.random.default_rng(3)
    src = rng.normal(size=(8, 3)) * 5
    dst = SIM.apply(src) + rng.normal(scale=0.05, size=(8, 3))
    up_map = SIM.rotation.T @ np.array([0.0, 1.0, 0.0])  # maps onto +y under SIM
    sim = A.estimate_sim3(A.Correspondences(src, dst), up_map=up_map, up_target=[0, 1, 0])
    np.testing.assert_allclose(sim.rotation @ up_map, [0, 1, 0], atol=1e-12)
    assert rotation_angle_deg(sim.rotation, SIM.rotation) < 1.0
    assert sim.scale == pytest.approx(SIM.scale, rel=0.02)
    two = A.estimate_sim3(
        A.Correspondences(src[:2], SIM.apply(src[:2])), up_map=up_map, up_target=[0, 1, 0]
    )
    assert rotation_angle_deg(two.rotation, SIM.rotation) < 1e-6
    assert two.scale == pytest.approx(SIM.scale, rel=1e-9)


def test_degenerate_correspondences_are_refused():
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(InputError, match="collinear"):
        A.estimate_sim3(A.Correspondences(line, SIM.apply(line)))
    with pytest.raises(InputError, match="at least 3"):
        A.estimate_sim3(A.Correspondences(line[:2], SIM.apply(line[:2])))
    same = np.ones((4, 3))
    with pytest.raises(InputError, match="coincide"):
        A.estimate_sim3(A.Correspondences(same, same))
    with pytest.raises(InputError, match="not in the map"):
        A.match_positions({"a": np.zeros(3)}, {"b": np.zeros(3)})


def test_cli_align_check_and_refusal(world, tmp_path, capsys):
    src = shutil.copytree(world.maps_dir / "room", tmp_path / "room")
    b = MapBundle(src)
    centers = A.image_centers(b)
    keys = sorted(centers)
    target = {k: SIM.apply(c) for k, c in centers.items()}
    (tmp_path / "given.txt").write_text(
        "# name x y z\n"
        + "".join(f"{k}.png {' '.join(f'{v:.17g}' for v in target[k])}\n" for k in keys[:5])
    )
    (tmp_path / "check.txt").write_text(
        "".join(f"{k} {' '.join(f'{v:.17g}' for v in target[k])}\n" for k in keys)
    )
    old_id = b.build_id
    # A bad correspondence file: exit 2, the bundle untouched.
    (tmp_path / "bad.txt").write_text("frame 1 2\n")
    assert cli(["map", "align", str(src), "--positions", str(tmp_path / "bad.txt")]) == 2
    assert read_manifest(src).build_id == old_id
    # Refused by --max-residual: nothing written.
    (tmp_path / "off.txt").write_text((tmp_path / "given.txt").read_text() + f"{keys[7]} 0 0 0\n")
    rc = cli(
        [
            "map",
            "align",
            str(src),
            "--positions",
            str(tmp_path / "off.txt"),
            "--max-residual",
            "0.01",
        ]
    )
    assert rc == 1 and read_manifest(src).build_id == old_id
    capsys.readouterr()
    rc = cli(
        [
            "map",
            "align",
            str(src),
            "--positions",
            str(tmp_path / "given.txt"),
            "--check",
            str(tmp_path / "check.txt"),
            "--json",
        ]
    )
    assert rc == 0
    import json

    rep = json.loads(capsys.readouterr().out)
    assert rep["given"]["count"] == 5 and rep["held_out"]["count"] == len(keys) - 5
    assert rep["held_out"]["max"] < 1e-6
    new = MapBundle(src)
    assert new.build_id != old_id and new.build_id == rep["build_id"]
    np.testing.assert_allclose(new.points_xyz, SIM.apply(b.points_xyz), atol=1e-6)


def test_cli_up_only_rotates(world, tmp_path, capsys):
    src = shutil.copytree(world.maps_dir / "room", tmp_path / "room")
    b = MapBundle(src)
    rc = cli(
        [
            "map",
            "align",
            str(src),
            "--up",
            "cameras",
            "--up-target",
            "0",
            "0",
            "1",
            "--out-name",
            "room-up",
        ]
    )
    assert rc == 0
    up = A.cameras_up(b)
    new = MapBundle(tmp_path / "room-up")
    np.testing.assert_allclose(A.cameras_up(new), [0, 0, 1], atol=1e-9)
    assert new.scene_scale == pytest.approx(b.scene_scale, rel=1e-9)
    assert np.linalg.norm(up - [0, 0, 1]) > 1e-3  # the synthetic cameras are not z-up already
    assert MapBundle(src).build_id == b.build_id  # --out-name keeps the original


def test_build_option_publishes_only_the_aligned_map(world, tmp_path):
    """sfmloc build --align-points: the bundle under NAME is the aligned one, nothing else is
    left in the output folder."""
    synth = world.root / "synth"
    ref = MapBundle(world.maps_dir / "room")
    X = ref.points_xyz[:: max(1, ref.n_points // 20)][:20]
    (tmp_path / "pairs.txt").write_text(
        "".join(" ".join(f"{v:.17g}" for v in (*x, *SIM.apply(x))) + "\n" for x in X)
    )
    out = tmp_path / "maps"
    rc = cli(
        [
            "build",
            "room",
            "--out",
            str(out),
            "--colmap",
            str(synth / "sparse"),
            "--images",
            str(synth / "images"),
            "--preset",
            "fast",
            "--align-points",
            str(tmp_path / "pairs.txt"),
        ]
    )
    assert rc == 0
    assert sorted(p.name for p in out.iterdir()) == ["room"]
    b = MapBundle(out / "room")
    entry = b.manifest.source["alignments"][-1]
    assert entry["target_from_map"]["scale"] == pytest.approx(SIM.scale, rel=1e-9)
    # The fast preset keeps the model's SfM points: they land at SIM of the model's.
    for T0, T1 in zip(ref.image_cam_from_world, b.image_cam_from_world):
        np.testing.assert_allclose(T1.center, SIM.apply(T0.center), atol=1e-6)
