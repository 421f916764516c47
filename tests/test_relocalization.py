"""Relocalization acceptance (``EngineConf.global_verify``) against exact ground truth on the
synthetic room: a RANSAC pose is re-matched by guided matching around it; right poses are
confirmed (with more inliers), chance poses (another scene, noise, a pose that is off) are not."""

from __future__ import annotations

import numpy as np
from test_mapping_sfm import Corner, look_at

from sfmloc.engine import EngineConf, Status, relocalize
from sfmloc.engine.localizer import _match_near_prior, describe
from sfmloc.engine.matching import global_matching
from sfmloc.engine.pose import estimate_pose_one_to_many
from sfmloc.features.daisy import DaisyExtractor
from sfmloc.features.harris import detect_corners
from sfmloc.transforms import Rigid3d, pose_errors, rotmat_from_rotvec


def _features(gray, bundle, conf):
    ex = DaisyExtractor()
    c = detect_corners(gray, rel_threshold=conf.gamma, max_corners=conf.global_max_keypoints,
                       border=conf.mu // 2)
    return c.xy, describe(ex, bundle, ex.prepare(gray), c.xy)


def _ransac_pose(gray, bundle, cam, conf):
    """Global matching and one-to-many RANSAC alone (no acceptance rule beyond 10 inliers)."""
    xy, desc = _features(gray, bundle, conf)
    gm = global_matching(desc, bundle, conf)
    X = bundle.points_xyz
    if len(gm.set1_q) < 3:
        return xy, desc, None
    res = estimate_pose_one_to_many(xy[gm.set1_q], X[gm.set1_p], gm.set2_q, xy[gm.set2_q],
                                    X[gm.set2_p], cam.K, conf.ransac())
    return xy, desc, None if res is None else res[0]


def test_verification_confirms_right_relocalizations_with_more_inliers(world, bundle, cam):
    on, off = EngineConf(), EngineConf(global_verify=False)
    limit = 0.05 * bundle.scene_scale  # the wrong-pose threshold
    for i in (5, 25, 50):
        gt = world.gt_cam_from_world[i]
        r = relocalize(world.gray[i], cam, bundle, on)
        r0 = relocalize(world.gray[i], cam, bundle, off)
        assert r.status is Status.RELOCALIZED and r0.status is Status.RELOCALIZED
        dp, dr = pose_errors(r.cam_from_world, gt)
        assert dp < limit and dr < 1.0, (i, dp, dr)
        assert r.inliers >= r0.inliers, (i, r.inliers, r0.inliers)
        # every verified match reprojects within the guided threshold under the exact pose
        xy, desc = _features(world.gray[i], bundle, on)
        res = _match_near_prior(desc, xy, bundle, cam.K, on, r0.cam_from_world)
        assert res is not None
        est, point = res
        q = np.nonzero(point >= 0)[0]
        assert len(q) >= on.recover_min_inliers
        uv, _ = cam.project(gt, bundle.points_xyz[point[q]])
        assert np.median(np.linalg.norm(uv - xy[q], axis=1)) < 2.0


def test_verification_rejects_chance_poses(world, bundle, cam):
    conf = EngineConf()
    # A pose at the right place but off by 1 m and 20 deg is not confirmed.
    i = 25
    gt = world.gt_cam_from_world[i]
    turn = rotmat_from_rotvec([0.0, np.radians(20.0), 0.0])
    off = Rigid3d(turn @ gt.rotation, gt.translation + [1.0, 0.0, 0.0])
    xy, desc = _features(world.gray[i], bundle, conf)
    assert _match_near_prior(desc, xy, bundle, cam.K, conf, off) is None
    # Images of another scene and noise: whatever RANSAC finds (no inlier-ratio floor) is not
    # confirmed, and relocalization gives no pose.
    view = look_at(np.array([2.8, 2.2, 1.4]), (0.6, 0.8, 0.6))
    other_scene = Corner(seed=3).render(cam, view, ss=1)
    noise = np.random.default_rng(1).integers(0, 255, (cam.height, cam.width), dtype=np.uint8)
    no_floor = EngineConf(global_min_inlier_ratio=0.0)
    for img in (other_scene, noise):
        xy, desc, est = _ransac_pose(img, bundle, cam, no_floor)
        if est is not None:
            assert _match_near_prior(desc, xy, bundle, cam.K, conf, est.cam_from_world) is None
        assert relocalize(img, cam, bundle, conf).status is Status.LOST
