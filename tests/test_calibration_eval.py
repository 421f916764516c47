"""The covariance calibration measurement (``sfmloc.eval.calibration``) on poses whose errors
are drawn from a known covariance: it must find the NEES at its expected value, and count the
wrong and withheld poses by the rules it states."""

from __future__ import annotations

import numpy as np

from sfmloc.engine import EngineConf, Localizer, Matching, Status
from sfmloc.eval.calibration import Sample, replay_samples, summarize
from sfmloc.io.frames import FrameSource
from sfmloc.transforms import Rigid3d, rotmat_from_rotvec


def perturbed(gt: Rigid3d, e: np.ndarray) -> Rigid3d:
    """gt moved by ``e`` in the covariance's parameterization (world-side rotation, centre)."""
    wfc = gt.inverse()
    R_wc = rotmat_from_rotvec(e[:3]) @ wfc.rotation
    return Rigid3d(R_wc, wfc.translation + e[3:]).inverse()


def samples(rng, n: int, scale: float) -> list[Sample]:
    out = []
    for i in range(n):
        gt = Rigid3d(rotmat_from_rotvec(rng.normal(0, 0.5, 3)), rng.normal(0, 1, 3))
        A = rng.normal(0, 1, (6, 6))
        cov = A @ A.T * 1e-4 + np.diag([1e-6] * 3 + [1e-4] * 3)
        e = rng.multivariate_normal(np.zeros(6), cov)
        out.append(Sample(i, "TRACKING", perturbed(gt, e), gt, cov / scale, 50))
    return out


def test_nees_of_a_calibrated_covariance_is_its_expected_value():
    rng = np.random.default_rng(0)
    s = summarize(samples(rng, 2000, 1.0), scene_scale=10.0, max_position_sd=1.0)
    # standard errors of the means: sqrt(12/2000) = 0.08 and sqrt(6/2000) = 0.05
    assert abs(s["nees6_mean"] - 6) < 0.3 and abs(s["nees_pos_mean"] - 3) < 0.2
    assert abs(s["nees_rot_mean"] - 3) < 0.2
    assert np.allclose(s["z_sd_xyz_cam"], 1.0, atol=0.06)
    assert s["wrong"] == 0 and s["withheld"] == 0
    # the same errors with a covariance 4x too large (pessimistic) or too small (optimistic)
    assert (
        abs(summarize(samples(np.random.default_rng(0), 2000, 0.25), 10.0, 1.0)["nees6_mean"] - 1.5)
        < 0.1
    )
    assert (
        abs(summarize(samples(np.random.default_rng(0), 2000, 4.0), 10.0, 1.0)["nees6_mean"] - 24)
        < 1.5
    )


def test_wrong_and_withheld_poses_are_counted_by_the_stated_rules():
    gt = Rigid3d(np.eye(3), np.zeros(3))
    cov = np.diag([1e-6] * 3 + [0.04**2] * 3)  # centre sd 0.04 = 4% of a scene scale of 1
    far = perturbed(gt, np.array([0, 0, 0, 0.06, 0, 0]))  # 6% off: wrong
    near = perturbed(gt, np.array([0, 0, 0, 0.01, 0, 0]))
    s = summarize(
        [Sample(0, "TRACKING", far, gt, cov, 20), Sample(1, "TRACKING", near, gt, cov * 0.25, 20)],
        scene_scale=1.0,
        max_position_sd=0.03,
    )
    assert s["wrong"] == 1 and s["wrong_published"] == 0 and s["wrong_sd_pct"] == [4.0]
    assert s["withheld"] == 1 and s["withheld_right"] == 0
    s = summarize([Sample(0, "TRACKING", far, gt, cov * 0.25, 20)], 1.0, 0.03)
    assert s["wrong_published"] == 1  # sd 2%: published, and wrong


def test_the_replay_is_the_configured_engine_and_sees_the_withheld_poses(world, bundle, cam):
    """The calibration replay measures the engine's own poses: every pose the engine publishes
    (with a tight limit, so that ``densify_uncertain`` re-matches and the limit withholds some on
    the synthetic video) is a sample with the same pose, covariance and status, and every pose
    it withholds for its sd is a sample too, counted as withheld by ``summarize``. (With the limit
    lifted for the replay, 12 of 48 published poses differed: no re-matching.)"""
    conf = EngineConf(max_position_sd=0.005)
    loc = Localizer(bundle, cam, conf)
    results = [loc.localize(g, i / 30) for i, g in enumerate(world.gray)]
    source = FrameSource(world.frames[0].parent)
    samples, n = replay_samples(bundle, source, cam, world.gt_cam_from_world, conf)
    assert n == len(world.gray)
    by_index = {s.index: s for s in samples}
    published = [i for i, r in enumerate(results) if r.cam_from_world is not None]
    held = [i for i, r in enumerate(results) if r.message.startswith("pose withheld: centre sd")]
    assert held and any(results[i].matching is Matching.GUIDED for i in published)
    for i in published:
        s, r = by_index[i], results[i]
        assert s.status == str(r.status) and s.inliers == r.inliers
        assert np.array_equal(s.est.matrix(), r.cam_from_world.matrix())
        assert np.array_equal(s.cov, r.covariance)
    assert all(by_index[i].status == str(Status.LOST) for i in held)
    assert sorted(by_index) == sorted(published + held)
    summary = summarize(samples, bundle.scene_scale, conf.max_position_sd, conf.withhold_noise_z)
    assert summary["withheld"] == len(held)
