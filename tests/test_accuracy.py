"""Pose accuracy against exact synthetic ground truth (issue 9: median error at most 1.5x the
SIFT peer's). The errors of consecutive tracked poses are correlated (the same map points and
tracks serve frame after frame), so accuracy comes from the number of points a pose rests on."""

from __future__ import annotations

import numpy as np

from sfmloc.engine import EngineConf, Localizer
from sfmloc.transforms import pose_errors


def _position_errors(world, bundle, cam, conf: EngineConf) -> tuple[np.ndarray, np.ndarray]:
    loc = Localizer(bundle, cam, conf)
    errs, inliers = [], []
    for i, (frame, gt) in enumerate(zip(world.gray, world.gt_cam_from_world)):
        res = loc.localize(frame, i / 30)
        if res.cam_from_world is not None:
            errs.append(pose_errors(res.cam_from_world, gt)[0])
            inliers.append(res.inliers)
    return np.array(errs), np.array(inliers)


def test_refilling_before_the_3d_tracks_run_low_keeps_the_poses_accurate(world, bundle, cam):
    """ADD-GOOD-FEATURES also runs while fewer than ``refill_3d`` tracked keypoints have a 3D
    match, or while those cover under ``refill_coverage`` of the image cells with keypoints: the
    poses of the 60-frame synthetic walk rest on more, better spread points and the upper errors
    fall. Measured (mean / 90th percentile): refill_3d 40 without the coverage rule (the code
    before) 0.83 / 1.92 cm; 60: 0.53 / 0.98 cm; 60 and coverage 0.6 (the defaults) 0.64 / 1.22
    cm (on this short video the coverage rule costs a little; over 100-600 frame videos it
    lowered the median 2-37%, see EngineConf.refill_coverage)."""
    conf = EngineConf()
    assert conf.refill_3d == 60 and conf.refill_coverage == 0.6
    errs, inliers = _position_errors(world, bundle, cam, conf)
    assert len(errs) == len(world.gray)  # every frame posed
    assert np.median(inliers) >= 60
    mean, p90 = float(np.mean(errs)), float(np.percentile(errs, 90))
    assert mean < 0.0075 and p90 < 0.015, (mean, p90)  # the code before missed both


def test_sparse_3d_matches_trigger_a_refill(world, bundle, cam):
    """The coverage rule: 3D matches bunched in one corner of the image call for new keypoints
    however many they are; spread over the image they do not."""
    from sfmloc.engine.track_table import TrackTable

    loc = Localizer(bundle, cam)
    kps = loc._extract_keypoints(world.gray[0], None)
    assert len(kps) > 100
    n = 80
    table = TrackTable.empty(loc.conf.max_hypotheses)
    rng = np.random.default_rng(0)
    corner = rng.uniform([0, 0], [cam.width / 4, cam.height / 4], (n, 2))
    table.append(np.arange(n), corner, np.zeros((n, 4), np.uint64))
    table.point[:] = np.arange(n)
    assert table.n_3d() >= loc.conf.refill_3d
    assert loc._uncovered(table, kps)
    table.xy = rng.uniform([0, 0], [cam.width, cam.height], (n, 2))
    assert not loc._uncovered(table, kps)
    off = Localizer(bundle, cam, EngineConf(refill_coverage=0))
    table.xy = corner
    assert not off._uncovered(table, kps)
