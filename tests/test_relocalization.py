"""Relocalization acceptance (``EngineConf.global_verify``) against exact ground truth on the
synthetic room: a RANSAC pose is re-matched by guided matching around it; right poses are
confirmed (with more inliers), chance poses (another scene, noise, a pose that is off) are not."""

from __future__ import annotations

import numpy as np

from sfmloc.cameras import Camera
from sfmloc.engine import EngineConf, Localizer, Matching, Status, relocalize
from sfmloc.engine.matching import global_matching, neighbour_strengths, restrict_neighbours
from sfmloc.engine.pose import estimate_pose_one_to_many
from sfmloc.engine.relocalize import describe, global_pose, match_near_prior, visible_points
from sfmloc.features.daisy import DaisyExtractor
from sfmloc.features.harris import detect_corners
from sfmloc.transforms import Rigid3d, pose_errors, rotmat_from_rotvec
from test_mapping_sfm import Corner, look_at


def _features(gray, bundle, conf):
    ex = DaisyExtractor()
    c = detect_corners(
        gray, rel_threshold=conf.gamma, max_corners=conf.global_max_keypoints, border=conf.mu // 2
    )
    return c.xy, describe(ex, bundle, ex.prepare(gray), c.xy)


def _ransac_pose(gray, bundle, cam, conf):
    """Global matching and one-to-many RANSAC alone (no acceptance rule beyond 10 inliers)."""
    xy, desc = _features(gray, bundle, conf)
    gm = global_matching(desc, bundle, conf)
    X = bundle.points_xyz
    if len(gm.set1_q) < 3:
        return xy, desc, None
    res = estimate_pose_one_to_many(
        xy[gm.set1_q], X[gm.set1_p], gm.set2_q, xy[gm.set2_q], X[gm.set2_p], cam.K, conf.ransac()
    )
    return xy, desc, None if res is None else res[0]


def test_verification_confirms_right_relocalizations_with_more_inliers(world, bundle, cam):
    # every pose verified (by default strong ones are not: the next test)
    on, off = EngineConf(global_verify_min_inliers=0), EngineConf(global_verify=False)
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
        # ... with a scoped search, and with global matching's search restricted to the scope
        for reuse in (None, global_matching(desc, bundle, on).neighbours):
            res = match_near_prior(desc, xy, bundle, cam, on, r0.cam_from_world, reuse)
            assert res is not None
            est, point = res
            q = np.nonzero(point >= 0)[0]
            assert len(q) >= on.recover_min_inliers
            uv, _ = cam.project(gt, bundle.points_xyz[point[q]])
            assert np.median(np.linalg.norm(uv - xy[q], axis=1)) < 2.0


def test_strong_relocalizations_skip_verification_and_stay_as_accurate(world, bundle, cam):
    """A RANSAC pose with ``global_verify_min_inliers`` inliers and ``global_verify_min_ratio``
    of the ratio-test matches is published on its own inliers (RANSAC's, not the guided
    matching's), refined with the robust loss, as close to the truth as the verified pose; a
    weaker one is still verified (the same answer as verifying every pose)."""
    # (the small synthetic world: 79-98 inliers, 17-19% of set 1; a lower bar than the default)
    skip = EngineConf(global_verify_min_inliers=90, global_verify_min_ratio=0.1)
    always = EngineConf(global_verify_min_inliers=0)
    scale = bundle.scene_scale
    strong = weak = 0
    for i in (5, 15, 25, 40, 50):
        gt = world.gt_cam_from_world[i]
        xy, desc = _features(world.gray[i], bundle, skip)
        nb = bundle.index.search(desc, skip.k, nprobe=skip.global_nprobe)  # global_pose's
        gm = global_matching(desc, bundle, skip, nb)
        X = bundle.points_xyz
        res = estimate_pose_one_to_many(
            xy[gm.set1_q],
            X[gm.set1_p],
            gm.set2_q,
            xy[gm.set2_q],
            X[gm.set2_p],
            cam.K,
            skip.ransac(),
            pool_stop=skip.global_pool_stop,
        )
        assert res is not None
        est, chosen = res
        got, _ = global_pose(desc, xy, bundle, cam, skip, nb)
        ver, _ = global_pose(desc, xy, bundle, cam, always, nb)
        assert got is not None and ver is not None
        e, e_ver = (
            pose_errors(got[0].cam_from_world, gt)[0],
            pose_errors(ver[0].cam_from_world, gt)[0],
        )
        if est.num_inliers >= max(90, 0.1 * len(gm.set1_q)):
            strong += 1
            assert got[0].num_inliers == est.num_inliers
            np.testing.assert_array_equal(got[1], gm.set2_q[chosen])
            assert e < 0.01 * scale and e < 2 * e_ver + 0.001 * scale, (i, e, e_ver)
        else:
            weak += 1
            assert got[0].num_inliers == ver[0].num_inliers
            np.testing.assert_array_equal(got[1], ver[1])
    assert strong >= 1 and weak >= 1, (strong, weak)  # both paths taken


def test_verification_rejects_chance_poses(world, bundle, cam):
    conf = EngineConf()
    # A pose at the right place but off by 1 m and 20 deg is not confirmed.
    i = 25
    gt = world.gt_cam_from_world[i]
    turn = rotmat_from_rotvec([0.0, np.radians(20.0), 0.0])
    off = Rigid3d(turn @ gt.rotation, gt.translation + [1.0, 0.0, 0.0])
    xy, desc = _features(world.gray[i], bundle, conf)
    assert match_near_prior(desc, xy, bundle, cam, conf, off) is None
    reuse = global_matching(desc, bundle, conf).neighbours
    assert match_near_prior(desc, xy, bundle, cam, conf, off, reuse) is None
    # Images of another scene and noise: whatever RANSAC finds (no inlier-ratio floor) is not
    # confirmed, and relocalization gives no pose.
    view = look_at(np.array([2.8, 2.2, 1.4]), (0.6, 0.8, 0.6))
    other_scene = Corner(seed=3).render(cam, view, ss=1)
    noise = np.random.default_rng(1).integers(0, 255, (cam.height, cam.width), dtype=np.uint8)
    no_floor = EngineConf(global_min_inlier_ratio=0.0)
    for img in (other_scene, noise):
        xy, desc, est = _ransac_pose(img, bundle, cam, no_floor)
        if est is not None:
            assert match_near_prior(desc, xy, bundle, cam, conf, est.cam_from_world) is None
            reuse = global_matching(desc, bundle, conf).neighbours
            assert match_near_prior(desc, xy, bundle, cam, conf, est.cam_from_world, reuse) is None
        for search in ("reuse", "scoped"):
            c = conf.model_copy(update={"global_verify_search": search})
            assert relocalize(img, cam, bundle, c).status is Status.LOST


def test_restricted_neighbours_keep_their_order_at_the_front():
    D = np.array([[1.0, 2.0, 3.0, 4.0], [1.0, 1.5, np.inf, np.inf]], np.float32)
    I = np.array([[10, 11, 12, 13], [11, 13, -1, -1]])
    allowed = np.zeros(20, bool)
    allowed[[11, 13]] = True
    D2, I2 = restrict_neighbours(D, I, allowed)
    assert I2.tolist() == [[11, 13, -1, -1], [11, 13, -1, -1]]
    assert D2[0, :2].tolist() == [2.0, 4.0] and np.isinf(D2[0, 2:]).all()
    assert D2.dtype == np.float32
    # nothing allowed: a row without neighbours has no strengths (and no warning)
    D3, I3 = restrict_neighbours(D, I, np.zeros(20, bool))
    assert (I3 == -1).all() and np.isinf(D3).all()
    with np.errstate(all="raise"):
        assert not neighbour_strengths(D3, I3, 2.0).any()


def test_matching_near_a_prior_covers_the_whole_frame_with_an_off_centre_principal_point(
    world, bundle, cam
):
    """The points visible from a prior are those inside the frame's own width x height, not
    inside 2*cx x 2*cy (the old rule): with the principal point at a third of the width, the
    old rule dropped the right third of the image from matching near a prior."""
    i = 30
    gt = world.gt_cam_from_world[i]
    fx, fy, cx, cy = (float(v) for v in cam.params)
    left = int(cx) // 2  # crop the left columns: cx moves to a third of the width
    crop = np.ascontiguousarray(world.gray[i][:, left:])
    ccam = Camera.parse(
        f"PINHOLE {cam.width - left} {cam.height} {fx!r} {fy!r} {cx - left!r} {cy!r}"
    )
    right = 2 * ccam.params[2]  # where the old rule cut the image
    assert right < ccam.width - 100
    vis = visible_points(ccam, gt, bundle.points_xyz)
    uv, z = ccam.project(gt, bundle.points_xyz[vis])
    assert np.all(z > 0) and np.all((uv >= 0) & (uv < [ccam.width, ccam.height]))
    assert np.count_nonzero(uv[:, 0] >= right) >= 50
    conf = EngineConf()
    xy, desc = _features(crop, bundle, conf)
    res = match_near_prior(desc, xy, bundle, ccam, conf, gt)
    assert res is not None
    est, point = res
    q = point >= 0
    assert np.count_nonzero(xy[q, 0] >= right) >= conf.min_inliers
    assert pose_errors(est.cam_from_world, gt)[0] < 0.05 * bundle.scene_scale
    r = relocalize(crop, ccam, bundle, conf, prior=gt)
    assert r.status is Status.RELOCALIZED
    assert pose_errors(r.cam_from_world, gt)[0] < 0.05 * bundle.scene_scale


def test_spread_order_takes_each_cells_strongest_first():
    from sfmloc.engine.relocalize import spread_order

    rng = np.random.default_rng(3)
    # a textured corner (cell 0 of the 8 x 6 grid over 640 x 480) holds most corners and the
    # strongest ones
    xy = np.vstack([rng.uniform(0, 80, (400, 2)), rng.uniform(0, [640, 480], (200, 2))])
    resp = np.r_[rng.uniform(10, 20, 400), rng.uniform(1, 5, 200)]
    order = spread_order(xy, resp, 640, 480)
    assert sorted(order.tolist()) == list(range(600))
    cell = np.minimum(xy[:, 1] // 80, 5) * 8 + np.minimum(xy[:, 0] // 80, 7)
    occupied = len(np.unique(cell))
    head = order[:occupied]
    assert len(np.unique(cell[head])) == occupied  # one per occupied cell first
    for c in np.unique(cell):  # ... its strongest
        assert resp[head[cell[head] == c][0]] == resp[cell == c].max()
    # by strength within a round: the strongest cell-best first
    assert np.all(np.diff(resp[head]) <= 0)


def test_two_stage_relocalization_is_one_stage_unless_the_first_is_strong(world, bundle, cam):
    """``relocalize_first_keypoints``: a first stage that finds no pose far above chance
    hands over to global matching on every corner, whose answer is the one-stage answer (the
    descriptors and the search of the first corners reused); a first-stage pose (the strongest
    corners spread over the image, ``global_pose(strong_only=True)``) is the answer when there
    is one."""
    from sfmloc.engine.relocalize import spread_order

    one = EngineConf(relocalize_first_keypoints=0)
    # Only strong first-stage poses (weak ones: the next test, ``relocalize_first_min_inliers``).
    default = EngineConf(relocalize_first_min_inliers=0)
    assert default.relocalize_first_keypoints == 300
    # A bar the synthetic room's first 300 corners reach (30-45 inliers against 85-106 from
    # 1000; the default asks 100): the accepting path taken.
    low = default.model_copy(
        update={"global_verify_min_inliers": 40, "global_verify_min_ratio": 0.2}
    )
    scale = bundle.scene_scale
    accepted = 0
    for i in (5, 15, 25, 40, 50):
        gt = world.gt_cam_from_world[i]
        r1 = relocalize(world.gray[i], cam, bundle, one)
        assert r1.status is Status.RELOCALIZED and r1.detected >= 600  # the stage applies
        c = detect_corners(
            world.gray[i], rel_threshold=one.gamma, max_corners=1000, border=one.mu // 2
        )
        sub = np.sort(spread_order(c.xy, c.response, cam.width, cam.height)[:300])
        ex = DaisyExtractor()
        desc = describe(ex, bundle, ex.prepare(world.gray[i]), c.xy[sub])
        # the default bar: no first-stage pose here, so exactly the one-stage answer
        assert global_pose(desc, c.xy[sub], bundle, cam, default, strong_only=True)[0] is None
        rd = relocalize(world.gray[i], cam, bundle, default)
        assert rd.status is r1.status and rd.inliers == r1.inliers, (i, rd.inliers, r1.inliers)
        np.testing.assert_allclose(
            rd.cam_from_world.matrix(), r1.cam_from_world.matrix(), atol=1e-9
        )
        first, _ = global_pose(desc, c.xy[sub], bundle, cam, low, strong_only=True)
        rl = relocalize(world.gray[i], cam, bundle, low)
        if first is None:
            ro = relocalize(
                world.gray[i], cam, bundle, low.model_copy(update={"relocalize_first_keypoints": 0})
            )
            assert rl.inliers == ro.inliers
            continue
        accepted += 1
        assert rl.status is not Status.LOST and rl.inliers == first[0].num_inliers
        np.testing.assert_allclose(
            rl.cam_from_world.matrix(), first[0].cam_from_world.matrix(), atol=1e-9
        )
        # Not a wrong pose, but a weak first stage is less accurate (frame 40: 41 inliers,
        # 1.8% of the scene scale off against 0.4% from every corner): why the default bar
        # is 100 inliers (redkitchen, 500 frames: median 0.218 -> 0.237 cm, 0 wrong).
        assert pose_errors(rl.cam_from_world, gt)[0] < 0.05 * scale
    assert accepted >= 1


def test_max_votes_from_cluster_bits_equal_the_entry_per_cluster_votes(
    world, bundle, cam, monkeypatch
):
    """``vote == "max"`` scored from each point's cluster bits (the clusters a neighbour
    reaches first in its query's row) gives the same matches as one entry per (neighbour,
    cluster) deduplicated per query: the same clusters, images and sets, on whole frames and
    on the first stage's 300 corners."""
    from sfmloc.engine import matching

    conf = EngineConf()
    assert conf.vote == "max"
    bits = matching._point_cluster_bits(bundle)
    assert bits is not None and bundle.n_clusters > 1
    # every point's bits are its clusters
    for p in range(0, bundle.n_points, max(1, bundle.n_points // 50)):
        want = sum(1 << int(c) for c in bundle.point_clusters(p))
        assert int(bits[p]) == want
    compared = 0
    for i in (3, 20, 37, 55):
        xy, desc = _features(world.gray[i], bundle, conf)
        for rows in (slice(None), slice(0, 300)):
            d = np.ascontiguousarray(desc[rows])
            nb = bundle.index.search(d, conf.k, nprobe=conf.global_nprobe)
            new = global_matching(d, bundle, conf, nb)
            with monkeypatch.context() as m:
                m.setattr(matching, "_MAX_BIT_CLUSTERS", -1)  # the entry-per-cluster votes
                assert matching._point_cluster_bits(bundle) is None
                old = global_matching(d, bundle, conf, nb)
            for f in ("set1_q", "set1_p", "set2_q", "set2_p", "clusters"):
                np.testing.assert_array_equal(getattr(new, f), getattr(old, f), err_msg=f)
            assert new.n_images == old.n_images and len(new.set1_q) > 0
            compared += 1
    assert compared == 8


def test_first_stage_gives_up_only_where_no_pose_could_be_strong(world, bundle, cam):
    """The first stage skips its RANSAC when the matches' distinct keypoints (the most inliers
    any pose can have) are below the strong bar: no RANSAC pose ever has more inliers than
    that bound. ``relocalize_staged_from``: frames with fewer corners run one stage (the
    one-stage answer)."""
    from sfmloc.engine.relocalize import _at_most_inliers, spread_order

    conf = EngineConf()
    for i in (5, 25, 50):
        c = detect_corners(
            world.gray[i], rel_threshold=conf.gamma, max_corners=1000, border=conf.mu // 2
        )
        sub = np.sort(spread_order(c.xy, c.response, cam.width, cam.height)[:300])
        ex = DaisyExtractor()
        desc = describe(ex, bundle, ex.prepare(world.gray[i]), c.xy[sub])
        # the first stage's search (``global_nprobe`` lists)
        nb = bundle.index.search(desc, conf.k, nprobe=conf.global_nprobe)
        gm = global_matching(desc, bundle, conf, nb)
        bound = _at_most_inliers(gm.set2_q)
        assert bound == len(np.unique(gm.set2_q))
        X = bundle.points_xyz
        res = estimate_pose_one_to_many(
            c.xy[sub][gm.set1_q],
            X[gm.set1_p],
            gm.set2_q,
            c.xy[sub][gm.set2_q],
            X[gm.set2_p],
            cam.K,
            conf.ransac(),
        )
        assert res is not None and 0 < res[0].num_inliers <= bound
        # a frame below ``relocalize_staged_from`` corners: the one-stage answer
        above = EngineConf(relocalize_staged_from=len(c.xy) + 1)
        one = EngineConf(relocalize_first_keypoints=0)
        ra = relocalize(world.gray[i], cam, bundle, above)
        r1 = relocalize(world.gray[i], cam, bundle, one)
        assert ra.status is r1.status and ra.inliers == r1.inliers
        np.testing.assert_allclose(ra.cam_from_world.matrix(), r1.cam_from_world.matrix(), atol=0)


def test_weak_first_stage_pose_is_the_answer_only_when_published_relocalized(world, bundle, cam):
    """``relocalize_first_min_inliers``: a first-stage RANSAC pose below the strong bar with
    that many inliers is verified by guided matching as a one-stage pose is, and is the answer
    only when it would be published RELOCALIZED (certain, not withheld); otherwise the second
    stage runs and gives the one-stage answer. The synthetic room's first 300 corners reach
    30-45 inliers (the strong bar asks 100): the weak path is taken."""
    from sfmloc.engine.certainty import certainty, withheld
    from sfmloc.engine.relocalize import spread_order

    conf = EngineConf()
    assert conf.relocalize_first_min_inliers > 0  # on by default
    off = conf.model_copy(update={"relocalize_first_min_inliers": 0})
    one = conf.model_copy(update={"relocalize_first_keypoints": 0})
    scale = bundle.scene_scale
    taken = handed = 0
    for i in (5, 15, 25, 40, 50, 58):
        c = detect_corners(
            world.gray[i], rel_threshold=conf.gamma, max_corners=1000, border=conf.mu // 2
        )
        assert len(c.xy) >= conf.relocalize_staged_from  # the two stages apply
        sub = np.sort(spread_order(c.xy, c.response, cam.width, cam.height)[:300])
        ex = DaisyExtractor()
        desc = describe(ex, bundle, ex.prepare(world.gray[i]), c.xy[sub])
        strong, _ = global_pose(desc, c.xy[sub], bundle, cam, conf, strong_only=True)
        first, why = global_pose(
            desc,
            c.xy[sub],
            bundle,
            cam,
            conf,
            strong_only=True,
            first_min_inliers=conf.relocalize_first_min_inliers,
        )
        r = relocalize(world.gray[i], cam, bundle, conf)
        if first is None:
            # handed over: the one-stage answer (as without the weak path)
            r1 = relocalize(world.gray[i], cam, bundle, one)
            ro = relocalize(world.gray[i], cam, bundle, off)
            assert r.status is r1.status and r.inliers == r1.inliers, (i, why)
            assert ro.inliers == r.inliers
            handed += 1
            continue
        est = first[0]
        assert strong is None or strong[0].num_inliers >= conf.global_verify_min_inliers
        if strong is None:
            taken += 1
            assert conf.relocalize_first_min_inliers <= est.num_inliers
        cert = certainty(est, cam.K, bundle, conf)
        assert cert.verified and withheld(cert.position_sd, est.num_inliers, conf) is None
        assert r.status is Status.RELOCALIZED and r.inliers == est.num_inliers
        np.testing.assert_allclose(
            r.cam_from_world.matrix(), est.cam_from_world.matrix(), atol=1e-9
        )
        gt = world.gt_cam_from_world[i]
        err_m, err_deg = pose_errors(r.cam_from_world, gt)
        assert err_m < 0.02 * scale and err_deg < 2.0, (i, err_m / scale, err_deg)
    assert taken >= 1 and handed + taken == 6


def _far_patch_and_near(bundle, cam, k, n_far=40):
    """Mapping view ``k``'s exact projections of the map points it sees: the ``n_far`` of the
    deepest quarter nearest (in the image) to their median, and the two nearest points."""
    from sfmloc.engine.pose import project

    gt = bundle.image_cam_from_world[k]
    xy, z = project(gt, cam.K, bundle.points_xyz)
    inside = (z > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < cam.width)
    inside &= (xy[:, 1] >= 0) & (xy[:, 1] < cam.height)
    idx = np.nonzero(inside)[0]
    far = idx[z[idx] > np.quantile(z[idx], 0.75)]
    mid = np.median(xy[far], axis=0)
    far = far[np.argsort(np.linalg.norm(xy[far] - mid, axis=1))[:n_far]]
    near = idx[np.argsort(z[idx])[:2]]
    return gt, xy, z, idx, far, near


def _wrong_pose_on(gt, K, obs, X, sel, conf, scene_scale):
    """The pose the Cauchy refinement settles on from ``gt`` with matches ``obs`` <-> ``X``
    (``sel`` their point ids), as a ``PoseEstimate`` on all of them, when every residual is
    within the refinement's threshold (one pose's inliers) and the pose is over the wrong-pose
    limit (5% of the scene scale from ``gt``); else None."""
    from sfmloc.engine.pose import PoseEstimate, reprojection_errors, robust_refine

    pose = gt
    for _ in range(6):
        pose = robust_refine(pose, K, obs, X, 0.0)
    if reprojection_errors(pose, K, obs, X).max() > conf.refine_threshold_px:
        return None  # not one pose's inliers
    if np.linalg.norm(pose.center - gt.center) <= 0.05 * scene_scale:
        return None  # not a wrong pose
    return PoseEstimate(pose, np.ones(len(sel), bool), len(sel), 0.0, obs, X, sel)


def _resting_on_few(bundle, cam, conf, rng):
    """Per mapping view whose far patch alone leaves the pose free (its own sd over 10% of the
    scene scale): the view, its ground truth and its wrong pose(s) resting on a few matches,
    each a ``PoseEstimate`` on exact projections (the patch with 0.5 px noise, the near
    point(s) seen 40 px off; ``twice``: one near point matched by two keypoints a pixel
    apart), every residual within the refinement's threshold and the pose over the wrong-pose
    limit. Yields (k, gt, xy, idx, [(twice, est), ...])."""
    from sfmloc.engine.certainty import position_sd
    from sfmloc.engine.pose import pose_covariances

    K, S = cam.K, bundle.scene_scale
    X = bundle.points_xyz
    for k in range(bundle.n_images):
        gt, xy, z, idx, far, near = _far_patch_and_near(bundle, cam, k)
        if len(far) < 30 or z[near].max() > 0.4 * np.median(z[far]):
            continue
        noisy = xy[far] + rng.normal(0, 0.5, (len(far), 2))
        if position_sd(pose_covariances(gt, K, noisy, X[far], leave_one_out=False)[0]) < 0.1 * S:
            continue  # the patch alone holds the pose
        wrong = []
        for twice in (False, True):
            sel = np.r_[far, near[:1], near[:1]] if twice else np.r_[far, near]
            obs = np.r_[noisy, xy[sel[len(far) :]] + [40.0, 0.0]]
            if twice:
                obs[-1] += [1.0, 0.0]
            est = _wrong_pose_on(gt, K, obs, X[sel], sel, conf, S)
            if est is not None:
                wrong.append((twice, est))
        yield k, gt, xy, idx, wrong


def test_a_relocalization_resting_on_two_wrong_matches_is_withheld(bundle, cam):
    """Issue 9 (a pose is a promise): a thin map's single-image relocalization 29-98% of the
    scene scale off was published RELOCALIZED or UNVERIFIED with a centre sd of 0.4-2.5%: its
    inliers on a far wall left the pose free (sd 15-20% without the rest), and two wrong
    matches to points near the camera (or one point matched by two keypoints a pixel apart,
    which hides each from the leave-one-out) pinned it. Built here on exact projections of the
    synthetic map, in the views whose far patch alone leaves the pose free (its own sd over
    10% of the scene scale): the patch (0.5 px noise) and the near point(s) seen 40 px off,
    every residual within the refinement's threshold. Each such pose over the wrong-pose limit
    that the covariance rules publish is withheld; the same view's right matches over the
    whole image are not."""
    from sfmloc.engine.certainty import certainty, rests_on_few, withheld
    from sfmloc.engine.pose import PoseEstimate, robust_refine

    conf = EngineConf()
    K = cam.K
    X = bundle.points_xyz
    rng = np.random.default_rng(0)
    caught = {False: 0, True: 0}  # by one point matched twice: wrong poses the rules published
    for k, gt, xy, idx, wrong in _resting_on_few(bundle, cam, conf, rng):
        for twice, est in wrong:
            cert = certainty(est, K, bundle, conf)
            if withheld(cert.position_sd, est.num_inliers, conf) is not None:
                continue  # already withheld for its covariance
            assert rests_on_few(est, K, bundle, conf, cert.verified) is not None, (k, twice)
            caught[twice] += 1
            if twice:
                # one point matched twice: the leave-one-out alone keeps it certain
                assert cert.position_sd_loo < conf.max_position_sd, k
        # the view's right matches over the whole image: published
        sel = idx[np.argsort(rng.random(len(idx)))[:150]]
        obs = xy[sel] + rng.normal(0, 0.5, (len(sel), 2))
        pose = robust_refine(gt, K, obs, X[sel], 0.0)
        est = PoseEstimate(pose, np.ones(len(sel), bool), len(sel), 0.0, obs, X[sel], sel)
        cert = certainty(est, K, bundle, conf)
        assert withheld(cert.position_sd, est.num_inliers, conf) is None, k
        assert rests_on_few(est, K, bundle, conf, cert.verified) is None, k
    assert caught[False] >= 1 and caught[True] >= 1, caught


def test_the_trackers_relocalization_resting_on_a_few_matches_is_not_adopted(
    world, bundle, cam, monkeypatch
):
    """The same rule for the tracker's own relocalizations (``track_relocalize_leave_out``):
    robust density-6x with every frame relocalizing in a stream (the session reset before
    each), the tracker published 18 poses 5-118% of the scene scale off (RELOCALIZED 8.7% off
    with sd 0.6%; UNVERIFIED 45-111% off with sd 1.3-2.4%): single-image relocalization
    withheld them, the stream did not. Here the first frame's global matching result is
    replaced by each wrong pose built above on exact projections (the test's only forced
    part; the status rules, the motion filter and the next frames run for real). On: that
    frame is LOST, its matches not adopted, and the next frame relocalizes again to the right
    pose, published; off: the wrong pose is published."""
    from sfmloc.engine.certainty import certainty, withheld

    conf = EngineConf()
    rng = np.random.default_rng(0)
    S = bundle.scene_scale
    cases = []
    for _k, gt, _xy, _idx, wrong in _resting_on_few(bundle, cam, conf, rng):
        for _twice, est in wrong:
            cert = certainty(est, cam.K, bundle, conf)
            if withheld(cert.position_sd, est.num_inliers, conf) is None:
                cases.append((gt, est, cert.verified))
    assert cases
    original = Localizer._global_matching
    for gt, wrong_est, verified in cases:

        def forced(self, kps, image):
            table, est, why = original(self, kps, image)
            if self.frames == 1 and est is not None:
                return table, wrong_est, why  # noqa: B023 (called within this iteration)
            return table, est, why

        monkeypatch.setattr(Localizer, "_global_matching", forced)
        for on in (True, False):
            loc = Localizer(bundle, cam, EngineConf(track_relocalize_leave_out=on))
            first = loc.localize(world.gray[0], 0.0)
            if not on:
                # before: the wrong pose published as a relocalization
                assert first.status is (Status.RELOCALIZED if verified else Status.UNVERIFIED)
                assert np.linalg.norm(first.cam_from_world.center - gt.center) > 0.05 * S
                continue
            assert first.status is Status.LOST and first.cam_from_world is None
            assert "rests on" in first.message, first.message
            assert loc.table.n_3d() == 0  # not adopted: the next frame relocalizes again
            nxt = loc.localize(world.gray[1], 1 / 30)
            assert nxt.status is Status.RELOCALIZED and nxt.matching is Matching.GLOBAL
            dp, dr = pose_errors(nxt.cam_from_world, world.gt_cam_from_world[1])
            assert dp < 0.01 * S and dr < 1.0, (dp / S, dr)
        monkeypatch.undo()
    # the frames tracked on from an unverified relocalization keep its matches (their tracks):
    # the same rule withholds such a pose (followed, as any withheld pose); off, it is published
    from functools import partial

    from sfmloc.engine.localizer import _status

    loc = Localizer(bundle, cam, conf)
    for _gt, est, verified in cases:
        if verified:
            continue  # a verified tracked pose ends the unverified state: TRACKING
        cert = certainty(est, loc.K, bundle, conf)
        rule = partial(loc._rests_on_few, est, cert)
        status, why, still = _status(est, cert, False, "", True, conf, rule)
        assert status is Status.LOST and "rests on" in why and still
        status, _, still = _status(est, cert, False, "", True, conf)
        assert status is Status.UNVERIFIED and still


def test_rests_on_few_bound_gives_the_greedy_answer(bundle, cam):
    """Issue 10: ``position_sd_without`` with ``sd_over`` (``rests_on_few``'s question) answers
    with the bound of ``pose.leave_out_sd_bound`` where it is within the limit, else with the
    greedy steps: never below them, and over the limit exactly when they are, on the views of
    the two-wrong-matches test (wrong poses, withheld) and their right matches (published).
    The bound is taken on the right matches (its value is not the greedy one: this fails
    without it) and the greedy steps decide the wrong poses."""
    from sfmloc.engine.certainty import certainty, position_sd_without
    from sfmloc.engine.pose import PoseEstimate, robust_refine

    conf = EngineConf()
    K = cam.K
    X = bundle.points_xyz
    limit = conf.relocalize_leave_out_sd
    rng = np.random.default_rng(0)
    took_bound = exact_over = 0
    for _k, gt, xy, idx, wrong in _resting_on_few(bundle, cam, conf, rng):
        sel = idx[np.argsort(rng.random(len(idx)))[:150]]
        obs = xy[sel] + rng.normal(0, 0.5, (len(sel), 2))
        pose = robust_refine(gt, K, obs, X[sel], 0.0)
        right = PoseEstimate(pose, np.ones(len(sel), bool), len(sel), 0.0, obs, X[sel], sel)
        for est in [right] + [e for _, e in wrong]:
            verified = certainty(est, K, bundle, conf).verified
            k = conf.relocalize_leave_out_verified if verified else conf.relocalize_leave_out
            exact = position_sd_without(est, K, bundle, conf, k)
            got = position_sd_without(est, K, bundle, conf, k, sd_over=limit)
            assert (got > limit) == (exact > limit)
            assert got >= exact * (1 - 1e-9)
            if got != exact:
                took_bound += 1
                assert got <= limit
            exact_over += exact > limit
    assert took_bound >= 1 and exact_over >= 2, (took_bound, exact_over)


def _pinned_by_one_point(bundle, cam, conf, rng, n_far=40):
    """Per mapping view: a wrong pose whose certainty rests on one map point, as robust
    density-6x frame 286 at 3 Hz (RELOCALIZED 17.9% of the scene scale off, sd 0.63%): the
    ``n_far`` exact projections (0.5 px noise) of the deeper half of the points the view sees
    nearest their median, and its nearest point matched by two keypoints a pixel apart, seen
    40 px off; every residual within the refinement's threshold, the pose over the wrong-pose
    limit. Yields (k, gt, xy, idx, est)."""
    from sfmloc.engine.pose import project

    K, S, X = cam.K, bundle.scene_scale, bundle.points_xyz
    for k in range(bundle.n_images):
        gt = bundle.image_cam_from_world[k]
        xy, z = project(gt, K, X)
        inside = (z > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < cam.width)
        inside &= (xy[:, 1] >= 0) & (xy[:, 1] < cam.height)
        idx = np.nonzero(inside)[0]
        far = idx[z[idx] > np.median(z[idx])]
        near = idx[np.argmin(z[idx])]
        if len(far) < n_far or z[near] > 0.5 * np.median(z[far]):
            continue
        mid = np.median(xy[far], axis=0)
        far = far[np.argsort(np.linalg.norm(xy[far] - mid, axis=1))[:n_far]]
        sel = np.r_[far, near, near]
        seen = xy[[near, near]] + [[40.0, 0.0], [41.0, 0.0]]
        obs = np.r_[xy[far] + rng.normal(0, 0.5, (n_far, 2)), seen]
        est = _wrong_pose_on(gt, K, obs, X[sel], sel, conf, S)
        if est is not None:
            yield k, gt, xy, idx, est


def test_a_relocalization_verified_on_one_map_point_is_not_verified(bundle, cam):
    """``verified_without_one``: a relocalization passes the strict test only when its centre
    sd without its most influential map point would not be withheld. Robust density-6x at 3 Hz,
    frame 286: RELOCALIZED 17.9% of the scene scale off with sd 0.63%, 68 inliers on a far wall
    and one near point matched wrongly by two keypoints (sd 3.1% without it; the covariance's
    leave-one-out 0.91%, four points left out 4.3%: under every other rule's limit). Built here
    on exact projections: each such wrong pose the other rules publish RELOCALIZED is not
    verified (off: verified); the same view's right matches over the whole image stay verified."""
    from sfmloc.engine.certainty import (
        certainty,
        relocalization_certainty,
        rests_on_few,
        withheld,
    )
    from sfmloc.engine.pose import PoseEstimate, robust_refine

    conf, off = EngineConf(), EngineConf(verified_without_one=False)
    K, X = cam.K, bundle.points_xyz
    rng = np.random.default_rng(0)
    caught = 0
    for k, gt, xy, idx, est in _pinned_by_one_point(bundle, cam, conf, rng):
        cert = certainty(est, K, bundle, conf)
        published = withheld(cert.position_sd, est.num_inliers, conf) is None
        if not (published and cert.verified and rests_on_few(est, K, bundle, conf, True) is None):
            continue  # not published RELOCALIZED by the other rules
        assert relocalization_certainty(est, K, bundle, off).verified, k
        if relocalization_certainty(est, K, bundle, conf).verified:
            continue  # the rest hold it (sd 1-2% without the point): not this rule's case
        caught += 1
        # the view's right matches over the whole image: verified
        sel = idx[np.argsort(rng.random(len(idx)))[:150]]
        obs = xy[sel] + rng.normal(0, 0.5, (len(sel), 2))
        right = robust_refine(gt, K, obs, X[sel], 0.0)
        r_est = PoseEstimate(right, np.ones(len(sel), bool), len(sel), 0.0, obs, X[sel], sel)
        assert relocalization_certainty(r_est, K, bundle, conf).verified, k
    assert caught >= 1


def test_the_trackers_relocalization_verified_on_one_point_meets_the_motion_prediction(
    world, bundle, cam, monkeypatch
):
    """The tracker's relocalization verified on one map point is judged as an unverified one:
    after ten published frames, a frame whose tracking finds no pose and whose global matching
    returns such a wrong pose (forced, built on exact projections as above; the status rules,
    the motion filter and the contradiction check run for real) is rejected against the motion
    prediction (LOST); off (``verified_without_one`` False), it is published RELOCALIZED. As
    the first frame of a session (no prediction) it is published UNVERIFIED, not RELOCALIZED."""
    from sfmloc.engine.certainty import certainty, relocalization_certainty, rests_on_few

    conf = EngineConf()
    rng = np.random.default_rng(0)
    S = bundle.scene_scale
    wrong = None
    for _k, _gt, _xy, _idx, est in _pinned_by_one_point(bundle, cam, conf, rng):
        cert = certainty(est, cam.K, bundle, conf)
        if cert.verified and not relocalization_certainty(est, cam.K, bundle, conf).verified:
            if rests_on_few(est, cam.K, bundle, conf, True) is None:
                wrong = est
                break
    assert wrong is not None
    forced = {"on": False}
    estimate, global_matching = Localizer._estimate_pose, Localizer._global_matching

    def no_tracked_pose(self, table, *a, **kw):
        if forced["on"]:
            return table, None
        return estimate(self, table, *a, **kw)

    def wrong_global(self, kps, image, *a):
        table, est, why = global_matching(self, kps, image, *a)
        return (table, wrong, "") if forced["on"] else (table, est, why)

    monkeypatch.setattr(Localizer, "_estimate_pose", no_tracked_pose)
    monkeypatch.setattr(Localizer, "_global_matching", wrong_global)
    # (no odometry and no recovery around the prediction: global matching takes the frame)
    base = dict(odometry=False, prior_recovery=False)
    for on in (True, False):
        loc = Localizer(bundle, cam, EngineConf(verified_without_one=on, **base))
        for i in range(10):
            assert loc.localize(world.gray[i], i / 30).localized
        forced["on"] = True
        r = loc.localize(world.gray[10], 10 / 30)
        forced["on"] = False
        assert r.matching is Matching.GLOBAL
        if on:
            assert r.status is Status.LOST and "weak relocalization" in r.message, r.message
        else:
            assert r.status is Status.RELOCALIZED
            gt = world.gt_cam_from_world[10]
            assert np.linalg.norm(r.cam_from_world.center - gt.center) > 0.05 * S
        # a session's first frame: no prediction to meet
        loc = Localizer(bundle, cam, EngineConf(verified_without_one=on, **base))
        forced["on"] = True
        first = loc.localize(world.gray[0], 0.0)
        forced["on"] = False
        assert first.status is (Status.UNVERIFIED if on else Status.RELOCALIZED), first.message
