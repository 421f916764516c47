"""Engine configuration: the paper's parameters are the defaults, every one overridable
(``SFMLOC_ENGINE__K=64`` in the environment, a config file, or code)."""

from __future__ import annotations

import warnings
from typing import Any, Literal

from pydantic import Field, model_validator

from ..config import StrictModel
from .pose import RansacParams

# Settings renamed when the motion model became scale-free: an old config names the new unit.
RENAMED = {
    "max_speed_mps": "max_speed_scales_per_s (scene scales per second, not m/s)",
    "max_angular_speed_rps": "max_angular_speed_rad_s",
    "jump_tolerance_m": "jump_tolerance_scales (a fraction of the scene scale, not metres)",
    "accel_noise": "accel_noise_scales_per_s2 (scene scales per s^2, not m/s^2)",
    "angular_accel_noise": "angular_accel_noise_rad_s2",
    "position_noise": "position_noise_scales (a fraction of the scene scale, not metres)",
    "orientation_noise": "orientation_noise_rad",
}

# Settings removed: an old config naming one still loads (the key is dropped with a warning
# that says why), since bench results and saved confs hold every field.
REMOVED = {
    # Never read: the batch is rows[:batch_max] of whatever is pending, and the wait for more
    # pending keypoints is ``guided_min_pending`` (20, measured: see there). Making it mean
    # "wait for 100 pending" is ``guided_min_pending`` 100, which the lazy-matching
    # measurements argue against (batches of 40 on every frame already lost poses on the map
    # from every 60th frame: a thin map needs the matches now).
    "batch_min": "it was never read; guided_min_pending is the fewest pending keypoints "
    "guided matching waits for, batch_max the most it takes per frame",
}


class EngineConf(StrictModel):
    # ---- the paper's parameters (Sections 2.1, 2.2, 3)
    k: int = 50  # neighbours per k-ANN query
    sigma: float = 2.0  # neighbours farther than sigma * nearest distance do not vote
    beta: float = 0.8  # clusters scoring >= beta * best are selected
    mu: int = 32  # BRIEF patch size (pixels)
    rho: int = 48  # tracking search window (pixels, square)
    psi: float = 0.8  # best / second-best Hamming ratio for a track match
    # The tracking window widens with the frame interval: past wide_window_gap_s it is rho
    # times interval / wide_window_gap_s, at most wide_window_max times rho (0: always rho).
    # The motion prediction's error grows with the interval it extrapolates: redkitchen fed
    # every 12th frame (0.4 s) puts the tracked map points a median 20-80 px from their
    # keypoints, past rho / 2, and tracking decays to a relocalization every 3-4 frames.
    wide_window_gap_s: float = 0.1
    wide_window_max: float = 4.0
    kappa1: int = 25  # add new keypoints when fewer are tracked
    kappa2: int = 10  # relocalize when at most this many 2D-3D matches remain
    gamma: float = 0.001  # Harris threshold: gamma * previous frame's maximum cornerness
    # Guided matching batch (pending keypoints per frame; the paper: "usually 100-150"). The
    # frames that run a full batch are the slowest (the k-ANN search of 150 queries is ~60% of
    # them), so the p99 per frame is set by it. 150 -> 100, same run, 3 interleaved repetitions,
    # redkitchen 1000 frames (per-frame minimum CPU over the repetitions, load ~20): p99 18.1 ->
    # 15.3 ms (x0.85), p95 x0.88, mean x1.00; median error 0.326 -> 0.321 cm (perturbing the
    # batch by 1-2 moves it 0.325-0.334), within 5 cm / 5 deg 99.8 -> 99.7%, 0 wrong. Robust
    # suite's thin maps: every 30th frame 985 -> 989 localized (98.2 -> 98.5% within 5 cm), every
    # 60th 853 -> 851 (84.7 -> 84.3%), 0 wrong either way (before the thin-map changes of
    # 0a01d7f, 100 and 120 gave 5 wrong poses on the every-60th map; 140-151 none). The
    # paper's range is a consequence of how many keypoints are pending, not a setting: the
    # fewest a batch waits for is ``guided_min_pending`` (``batch_min`` was removed unread).
    batch_max: int = 100
    # Lazy guided matching: fewer pending keypoints than this wait for more (while the frame
    # holds at least refill_3d matches; with fewer, every one is tried at once). A batch pays
    # the whole frame's DAISY preparation and the search's fixed cost whatever its size, and
    # half of redkitchen's batches held 1-2 keypoints. 1 -> 20, cached-keypoint replay, load
    # ~60: redkitchen 1000 frames guided-matching frames 528 -> 175, match stage CPU x0.70,
    # median 0.278 -> 0.269 cm, mean 0.407 -> 0.403, within 5 cm / 5 deg 99.9 -> 99.8%, worst
    # 5.2 -> 6.9 cm, 0 wrong; synthetic walk 600 frames median 0.163 -> 0.160 cm, mean 0.200
    # -> 0.203 (better in 54% of the frames; frames 121-124 0.7 -> 1.7 cm), 0 wrong. 5: 227
    # guided frames.
    guided_min_pending: int = 20
    # Spread guided matching over frames where the map answers it readily: a frame takes at
    # most batch_spread pending keypoints (the rest wait, in order, for the next frames) while
    # the running share of queried keypoints guided matching matched (spread_yield_weight of
    # the last batch, the rest the earlier ones; 0 after a reset) is at least
    # spread_min_yield; otherwise batch_max at once (batch_spread 0: off). A full batch (its
    # k-ANN search, DAISY, verification: ~9 ms CPU on redkitchen) sets the p99 per frame. On
    # a thin map the pending keypoints are its future tracks and few of them match: spreading
    # every batch there lost poses (every 60th frame, 1000 frames, batches of 40 on every
    # frame: localized 992 -> 985; gated on the frame's 3D matches >= 40 / 60: 986 / 986),
    # and neither the 3D-match count (full batches on redkitchen at a median 66, every 60th
    # 46) nor the last pose's certainty tells the maps apart. The yield does: per batch a
    # median 0.50 on redkitchen (map every 10th) and 0.12 on the every-60th map. Even so the
    # every-60th map lost poses at 0.35 (997 -> 993 after 94518e5; a null change, k 51: 997):
    # batches spread only on maps whose median point is seen by at least
    # batch_spread_min_track map images (redkitchen every 10th, the synthetic walk: 4; every
    # 30th / 60th, density-3x / 6x: 2-3). With the 8-list scoped search (scope_nprobe),
    # `python -m sfmloc.bench.ab`, 1000 redkitchen frames, 2 reps, nice 19, load 3.5-4:
    # against main CPU mean x0.951 (x0.929-x0.972), p99 20.01 -> 18.11 ms (x0.905), 1000/1000,
    # 0 wrong, within 5 cm / 5 deg 99.8 -> 99.9%, median 0.278 -> 0.271 cm.
    # Off by default (lead, after the merge): the robust row orbit-3hz (a camera orbiting a
    # table at 3 Hz, map median track above 4) went from met to missed with it, median error
    # 0.00247 -> 0.00322 units against the peer's 0.00191 (1.69x, limit 1.5x; `sfmloc bench
    # --suites robust --robust-rows orbit-3hz`, 3d44647 vs ccfbb2f, nice 0, load ~0.8): a
    # deferred keypoint is a lost match when frames are far apart.
    # Gated (gate, issue 10): spread only while a short batch brings back more matches than
    # tracking loses. The running number of 3D matches a tracked frame loses against the
    # previous frame (tracking, re-verification; weight spread_yield_weight) must stay under
    # spread_keep_up x batch_spread x the running yield. Orbit-3hz lost ~30 matches a frame
    # at its full batches (3D tracks kept frame to frame 0.85) against ~25 a short batch
    # brings back: spread, its 3D matches fell from ~320 to 120-170 while ~500 keypoints
    # waited; redkitchen loses ~1.3 (its full batches follow refills, not losses). At 0.25
    # (replayed on main's decisions) redkitchen spreads 80 of its 91 eligible full batches,
    # orbit-3hz 0 of 14, orbit-10hz 3 of 20, walk-10hz 1 of 22, flight-10hz 2 of 12,
    # orbit-30hz 21 of 21 (unchanged there). spread_keep_up 0: no such gate. Still off: with
    # the gate orbit-3hz is main's (0 batches spread, median 0.00235 units), but one spread
    # batch on orbit-10hz moved its median 0.00222 -> 0.00238 against the peer's 0.00154
    # (1.55x, limit 1.5x; `sfmloc bench --suites robust --robust-rows orbit-10hz --reuse`,
    # nice 19): that row is 1.44x at main and moves by more than that with any change to its
    # tracks; redkitchen p99 with both gates x0.935 (and the 8-list gate's accuracy, below).
    batch_spread: int = 0
    batch_spread_min_track: float = 4.0
    spread_min_yield: float = 0.35
    spread_yield_weight: float = 0.3
    spread_keep_up: float = 0.25
    top_images: int = 30  # guided matching scope
    # An image counts for 1/n of the scope's top_images, n: the map images taken from within
    # scope_radius of the scene scale of it, looking the same way (engine/scope.py), on maps
    # from dense video only: where the median image has at least scope_min_duplicates such
    # images (itself included). The paper's 30 images are a place only at its maps' density:
    # on redkitchen from every frame they span ~30 frames, from every 10th ~300, and the narrow
    # scope sent more frames to global matching (every-frame map x1.27 the every-10th's CPU per
    # frame; top-100 images x1.12). At 0.02 the every-frame map's median image has 11 (its
    # 1,000 images count as 92 places), every 2nd 6, every 4th 3, every 10th 1: there it
    # counts every image 1 (the paper's scope), as do the synthetic maps at 1x-6x view spacing
    # and the robust suite's every-30th/60th maps. Weighting the every-10th map too (its 20% of
    # images with a neighbour within 0.02) cost it accuracy after the lazy guided matching
    # (df61e1b): median 0.301 vs 0.269 cm, interleaved, load 1.5. scope_radius 0: the paper's
    # scope on every map. Redkitchen 1000 frames, every-frame map against the every-10th
    # map's default, interleaved (bench.ab --map, 2 runs, load 4-18): the paper's scope
    # CPU per frame x1.296, 997/1000 localized, 1 wrong, median 0.429 cm; place-sized x1.163,
    # 1000/1000, 0 wrong, 0.273 cm (every-10th: 0.269 cm); the every-10th map's poses are
    # identical to the paper's scope (300 frames).
    scope_radius: float = 0.02
    scope_min_duplicates: float = 2.0
    # On those maps the guided (scoped) k-ANN search scans nprobe / sqrt(n) inverted lists, n
    # the median image's near-duplicates (engine/scope.py guided_nprobe; redkitchen every
    # frame: n 11, 5 lists; every 2nd 7, every 4th 9; every 10th and sparser: nprobe): the
    # lists of a map holding each place n times over are sqrt(n) times as long. Every-frame
    # map, 1000 frames (nice 19, load 10-16): against main b9ec1f9 CPU per frame x0.919, p99
    # x0.843, localized 1000 -> 999 (one LOST), median 0.273 -> 0.270 cm, 0 wrong (bench.ab);
    # against the every-10th map, interleaved frame by frame: x1.080 -> x1.044, p99 x1.41 ->
    # x1.16 (at 6 lists the search 1.82 -> 1.14 ms per frame). Off by default: the one LOST
    # frame makes the every-frame map's replay 99.9% against 100% from every 2nd frame (issue
    # 17: localized must never decrease as images are added), and without it the every-frame
    # map already runs at x1.080-1.096 the every-10th's (target x1.10).
    scope_dense_nprobe: bool = False
    ratio: float = 0.75  # ratio test on 3D point strengths
    # Guided matching on a frame holding fewer than few_matches_below 3D matches keeps as
    # hypotheses the points with at least few_matches_ratio of a keypoint's strongest point's
    # strength (``ratio`` otherwise; each still verified against the frame's pose, 6 px). On a
    # thin map the tracks run short where the view is poorly covered: redkitchen from every
    # 60th frame, frames 383-396 (tracking, guided matching every frame, 0-3 matches gained a
    # frame): 355-436 map points project into the frame at its true pose, a frame keypoint
    # lies within 3 px of 68-104 of them, 41-88 of those are tracked rows, 7-14 matched and
    # 22-38 guided-matched without that point among their hypotheses (in 14 frames, never);
    # the 3D matches fell to 11 by frame 392 and 393-396 were LOST. `python -m sfmloc.bench.ab`,
    # 1000 frames, nice 19, load 2-4, against main: every 60th 993 -> 997 posed, within 5 cm /
    # 5 deg 98.3 -> 98.9%, 0 wrong, p99 x0.74 (fewer relocalizations); 0.45 / 0.55 and below
    # 15 / 25 the same 997 and 98.9%; every 30th 999 -> 999, 99.9%; every 10th poses
    # identical (never fewer than 20 matches). Below 40 at 0.3: every 60th 998, but every 30th
    # 997 (99.4%) and one wrong pose on every 10th; below 40 at 0.5: every 10th 0.279 ->
    # 0.285 cm, every 30th 998; below 20 at 0.3: every 60th 989.
    few_matches_ratio: float = 0.5
    few_matches_below: int = 20  # (see few_matches_ratio; 0: never)
    # Inverted lists the guided (scoped) k-ANN search scans per query (0: nprobe) on maps whose
    # median point is seen by at least scope_nprobe_min_track map images, on frames holding at
    # least few_matches_below 3D matches (fewer matches, recovery, thinner maps: nprobe). A
    # full batch (100 queries) sets the p99 per frame and its search is half of it (4.9 ms per
    # batch at 16 lists, 2.8 at 8); a point seen by more images has more descriptors in more
    # lists, so fewer lists still reach one. 16 -> 8 (`python -m sfmloc.bench.ab`, nice 19,
    # against main, 1000 redkitchen frames, 2 reps, load 4-7): CPU mean x0.898, p99 x0.891,
    # match stage 1.47 -> 1.16 ms/frame, 1000/1000, 0 wrong, within 5 cm / 5 deg 99.8 ->
    # 99.9%, median 0.279 -> 0.285 cm; synthetic walk (median track 4) 300/300, 0.172 ->
    # 0.176 cm, p99 x0.81. Without the track gate, on every frame: redkitchen every 60th
    # (median track 2) 997 -> 998 posed, 98.9 -> 99.5% within 5 cm / 5 deg; every 30th (3)
    # 999 -> 999, 0 wrong; but density-6x (2) 237 -> 233 of 300 (issue 9's row). Without the
    # few_matches_below rule as well: every 60th 997 -> 997 at 8 lists, 987 at 12; every 30th
    # 1 wrong pose at 8; density-6x 234.
    # Off by default (lead, after the merge): robust orbit-10hz went from met to missed with
    # it, median error 0.00222 -> 0.00338 units against the peer's 0.00154 (2.2x, limit 1.5x;
    # `sfmloc bench --suites robust --robust-rows orbit-10hz`, d80246a vs 3d44647, nice 0,
    # load ~0.8): on an object-centred map the narrower search finds fewer of the matches
    # that pin the pose. The track gate does not separate it (its median track is above 4).
    # A second gate (gate, issue 10): the narrower search only on frames holding fewer than
    # scope_nprobe_max_3d 3D matches (0: no limit). Not a recall problem: on the orbit rows 8
    # lists find 98.5-99.2% of the 16 lists' guided matches (redkitchen 98.0%), but the
    # orbit's poses follow its tracks (every match an inlier, 270-320 matches at its full
    # batches): one match fewer at orbit-10hz's frame 3 moved its error 1.0 -> 3.9 mm, and
    # 3.9-8 mm held for the 7 frames those tracks lived. Redkitchen's full batches come at a
    # median 68 matches (88% under 150), the orbits' at 278-316 (6-12% under 150). With it
    # every robust motion row is met again (orbit-10hz 0.00222 units, main's) and redkitchen's
    # CPU p99 x0.947 / x0.945 (`python -m sfmloc.bench.ab`, 1000 frames, 2 reps, nice 19,
    # load 7-11), but redkitchen's hard stretch (frames 461-473, main 1.7-7 cm off) lost:
    # 1000 -> 999 localized, within 5 cm / 5 deg 99.8 -> 99.5% (null changes k 49 / 51: 99.8%,
    # 1000): still off (scope_nprobe 0); 8 turns it on with this gate.
    scope_nprobe: int = 0
    scope_nprobe_min_track: float = 4.0
    scope_nprobe_max_3d: int = 150
    min_inliers: int = 10  # a pose with fewer inliers is rejected
    # Global matching also needs this fraction of its ratio-test matches as inliers: 10 inliers
    # out of ~500 candidates is chance (a relocalization 3.7 m / 140 deg off had 1.9%; correct
    # ones on redkitchen have 12-63%).
    global_min_inlier_ratio: float = 0.05
    # A relocalization is re-matched by guided matching around its RANSAC pose (scope: the map
    # points the pose makes visible; the recovery's two passes and ``recover_min_inliers``);
    # when that succeeds the pose is accepted whatever the inlier ratio (of the two, the one
    # with more inliers: fewer widen the covariance, redkitchen frame 436 was withheld),
    # otherwise the ratio floor above decides. Off: the paper's single RANSAC. Measured with
    # ``python -m sfmloc.bench.sparse_maps`` (40 non-map frames per map, wrong = error over 5%
    # of scene_scale or 10 deg): redkitchen every 60th frame 27/40 localized, 2 wrong -> 28/40,
    # 0 wrong; every 30th 35/40, 1 wrong -> 35/40, 0 wrong; synthetic at 6x view spacing 24/40,
    # 2 wrong -> 25/40, 1 wrong (a repeated texture). The wrong RANSAC poses had 10-47 inliers
    # (2-13% of candidates); guided matching around the near-misses moved them within 5 cm, the
    # chance ones (10-18 inliers) found too few. Inliers / visible map points did not separate
    # right from wrong (wrong 1.3-8.2%, right from 4.3%). Cost: +27% CPU per relocalization.
    global_verify: bool = True
    # Where that verification's candidates come from: "reuse": global matching's k-ANN search
    # of the same descriptors, restricted to the verification's scope (its top-30 images);
    # "scoped": a second search within the scope (k neighbours among its images). Measured on
    # 60 single-image relocalizations of redkitchen non-map frames (map every 10th frame, one
    # run each, same load): scoped 60/60 posed, 0 wrong, median 0.41 cm, CPU per query 90 ms;
    # reuse 60/60, 0 wrong, 0.33 cm, x0.76 CPU (the second search was 16 of the 90 ms).
    global_verify_search: Literal["reuse", "scoped"] = "reuse"
    # ... but only for RANSAC poses with fewer than ``global_verify_min_inliers`` inliers or
    # under ``global_verify_min_ratio`` of the ratio-test matches (0: every pose is verified);
    # a stronger pose is refined on its inliers with the robust loss instead (the chance poses
    # the verification rejects had 10-47 inliers, 2-13%). Issue 10: the verification was 13% of
    # a relocalization. Redkitchen 100 non-map frames x 2 (map every 10th), with the pool stop
    # below, interleaved against main (load 28): CPU mean x0.77, p50 x0.78, p95 x0.74, 198/200
    # RELOCALIZED both, 0 wrong, median 0.262 -> 0.243 cm (the robust refinement).
    global_verify_min_inliers: int = 100
    global_verify_min_ratio: float = 0.25
    # A relocalization is also LOST when its inliers cover fewer than this fraction of the
    # image cells (4x4) that have keypoints (0: off): a chance pose rests on a patch of
    # repeated texture. 8 look-alike synthetic rooms (``bench.scale --parts submaps``, single
    # images, every 2nd frame): the 13 wrong poses spread over 0.06-0.375, the right ones from
    # 0.375 (1 UNVERIFIED), verified ones from 0.47; redkitchen non-map frames from 0.67, the
    # synthetic room from 0.56. Only poses on fewer than ``spread_max_inliers`` inliers are
    # judged (0: all): the wrong ones had 13-46; redkitchen frame 628, right (1.4 cm) on 113
    # inliers bunched in 38% of the cells, was lost to it (global-every-frame 499/500).
    min_inlier_spread: float = 0.4
    spread_max_inliers: int = 80
    # Which cells that fraction is of: "visible": the cells with keypoints where a map point
    # the pose makes visible projects (no pose can have an inlier in the others); "keypoints":
    # every cell with keypoints. A thin map covers part of the view: robust density-6x
    # (synthetic mapping views at 6x the spacing, 777 points) frames 218-285 were all lost,
    # right global poses (26 and 62 inliers, 1% and 0.1% of the scene scale off) covering 20%
    # and 27% of the cells with keypoints but 3 of 4 and 4 of 7 of those the map reaches.
    spread_cells: Literal["visible", "keypoints"] = "visible"
    # ... and when its inliers lie in fewer than this many of the 4x4 image cells, whatever
    # the fraction (0: off; as the fraction, only below ``spread_max_inliers`` inliers). A patch
    # within 2 cells spans at most half by a quarter of the image: on a far, nearly planar
    # patch a pose and its mirror both fit the matches, and a few wrong ones pick between
    # them. Robust density-6x (every frame a relocalization) frame 158: 53 inliers in 2
    # cells, 49 of them right matches on a patch 3.1 scene scales away that fit the true
    # pose too, plus 4 wrong matches to 3 near points that chose the mirror: published
    # UNVERIFIED 118% of the scene scale / 20 deg off, centre sd 2.3% (2.5% without 2
    # points: the leave-out rule's linearization sees one minimum); the true pose has 60
    # inliers in 4 cells. The "visible" fraction passed it.
    # Density-6x with a session reset every frame: all 38 global poses in 2 cells or fewer
    # were 7%-1000% of the scene scale off (37 withheld as too uncertain; 13 in 3 cells, 8
    # right); density-3x, redkitchen every 30th/60th: none in 2 cells. With a reset every 10
    # or 30 frames the next frame relocalizes instead of tracking on from a withheld wrong
    # pose: right poses 191 -> 207 and 212 -> 230 (docs/beyond-the-paper.md#min-inlier-cells).
    min_inlier_cells: int = 3
    # ... and when RANSAC, on the candidate matches the pose leaves unexplained, finds a pose at
    # another place (beyond the wrong-pose limits ``contradiction_*``) with at least this
    # fraction of its inliers (and ``recover_min_inliers``: places by chance gather 12-16)
    # (0: off): the frame fits two places. A square room with four identical walls (the
    # ``ambiguous_world`` of tests/test_engine.py), 60 single images: 24 were wrong, a pose
    # turned by 90 deg with 1-2.5x the right one's inliers (right ones' second places 0-0.4x);
    # with both tests 0 wrong, 19 right (0.15: 0 wrong, 12 right). Synthetic room: 60/60 right
    # either way (0.15: 54/60); redkitchen: no second place reaches 10 inliers.
    second_place_ratio: float = 0.25
    # The search sets aside the points of the images that see at least ``second_place_share``
    # of the pose's inliers (its place): there, frame 58's wrong pose (150 inliers) hid the right
    # one (63 pairs, but 20 of 337 in set 1, out of RANSAC's reach); without the wrong place's
    # points, 20 of 86. ``second_place_iterations``: the budget of each of its
    # ``second_place_rounds`` RANSAC searches (2 rounds: the same 0 wrong, 19 right).
    second_place_share: float = 0.25
    second_place_iterations: int = 300
    second_place_rounds: int = 1

    # ---- engineering choices the paper leaves open
    # Also ADD-GOOD-FEATURES when fewer tracked keypoints than this have a 3D match (0: only
    # the paper's kappa1 rule). Tracks with 3D matches decay faster than tracks overall, and
    # without refilling the engine falls back to costly global matching (kappa2) first.
    # Measured on redkitchen (300 frames): 0 -> 11 global frames, median 1.5 cm; 40 -> 3 global
    # frames, median 1.0 cm. 40 -> 60 (issue 9, accuracy: the pose rests on more points; the
    # errors are correlated from frame to frame, so more points, not more frames, average them
    # out), same run, interleaved, CPU per frame new/old: redkitchen frames 0-399 / 400-999
    # median 0.360 -> 0.336 / 0.343 -> 0.320 cm, inliers 71 -> 86 / 63 -> 86, CPU x1.06 /
    # x1.08; synthetic walk median 0.362 -> 0.250 cm, localized 98.7 -> 100%, x1.01; orbit
    # 0.282 -> 0.232 cm, x1.02; flight 0.306 -> 0.289 cm, x1.05; walk on the 3x map 0.381 ->
    # 0.406 cm (mean 0.86 -> 0.58 cm), x1.01; at 10 Hz (100 frames) mixed: flight 0.311 ->
    # 0.267, walk 0.264 -> 0.326, orbit 0.252 -> 0.323 cm. No wrong pose in any. 80:
    # redkitchen 0.317 cm but CPU x1.16. With the coverage rule below, over all 1000
    # redkitchen frames (one run, interleaved, CPU per frame against 40 without it): 60 median
    # 0.339 -> 0.313 cm but CPU x1.12, over issue 9's +10%; 50: 0.326 cm, x1.10; 40: 0.326 cm,
    # x1.06 (the synthetic walk: the same poses at 40, 50 and 60). So 40. Again at main
    # d1def86 (after the lazy guided matching), 60: redkitchen 1000 frames CPU x1.14 and
    # median 0.269 -> 0.279 cm (interleaved, load ~20); the every-30th map (300 frames)
    # 0.270 -> 0.255% of the scene scale (on the 20 frames the robust bench compares, 0.240
    # -> 0.220%, what its median-error target asks). Still 40.
    refill_3d: int = 40
    # ... and while the 3D matches cover fewer than this fraction of the 4x4 image cells that
    # have keypoints (0: off): a pose from points bunched in part of the image is poorly
    # constrained however many they are (on an orbit at 10 Hz the error grew 0.18 -> 0.74 cm
    # as the surviving matches fell from 217 to 75 and fell back at the refill). Measured
    # with refill_3d 40, all frames, one run, interleaved, 0 -> 0.6, median, CPU per frame:
    # redkitchen frames 0-999 0.339 -> 0.326 cm (mean 0.447 -> 0.444, p90 0.81 -> 0.80),
    # x1.06; frames 400-999 0.343 -> 0.332; synthetic walk 0.362 -> 0.236 (mean 0.56 ->
    # 0.32, localized 98.7 -> 100%), x1.06; flight 0.306 -> 0.221, x1.07; flight at 10 Hz
    # 0.311 -> 0.282, x0.97; walk on the 3x map 0.381 -> 0.321 (mean 0.86 -> 0.40), x1.05.
    # No wrong pose in any. 0.7: better still on some, CPU x1.05-1.14.
    refill_coverage: float = 0.6
    # A second start for a tracked frame whose motion prediction may be wrong: TRACK-2D and
    # ESTIMATE-POSE again from the last pose (no motion); more inliers win, two poses farther
    # apart than a wrong pose on similar support (second_start_tie) give no pose. It runs when
    # the prediction extrapolates over more than second_start_dt_ratio x the previous frame
    # interval (0: never), when the tracked pose failed, or when it kept fewer than
    # second_start_inliers x the last posed frame's inliers (0: not for that). The reliability
    # bench's lockstep canary (frames one video frame apart, stamped when sent) got wrong
    # TRACKING poses 5-19% of the scene scale off after slow answers: the prediction
    # overshot by 3-10 frames, and near-planar tracked matches allow a second pose near it
    # which the prior-seeded refinement kept (40 of 49 matches within 3 px, so RANSAC was
    # skipped; RANSAC's pose had 47). Same world, stalls of 0.1-0.35 s in 15% of the
    # intervals (seeds 1, 3, 5; 300 frames), main 889879b -> this: wrong 9/2/1 -> 0/0/0
    # (second_start_inliers 0.5 as well: also 0/0/0); 10% (seeds 1, 2; 600 frames, main
    # 1cdd020): 2/17 -> 0/0. Redkitchen at 30 Hz, 1000 frames: posed and within 5 cm / 5 deg
    # as main (968, 96.5% on the robust suite's map), CPU per frame x0.97-1.00 (300 frames);
    # with second_start_inliers 0.5 the runs diverge from frame 458 and 6 frames more are
    # withheld (962, 95.9%), so the inlier rule is off.
    second_start_dt_ratio: float = 1.5
    second_start_inliers: float = 0.0
    second_start_tie: float = 0.8
    # The second start's ESTIMATE-POSE is skipped when the first start found no pose and
    # tracking from the last pose kept fewer than second_start_min_tracked x the last posed
    # frame's inliers (0: never skipped): the camera also left the windows around the last
    # pose, and RANSAC on those few tracks, most of them wrong, runs its whole budget (1000
    # iterations, 14-25 ms) to find 4-7 inliers. Robust flight-3hz (issue 10): the 5 second
    # starts that failed kept 12-39 tracks of the last frame's 139-544 inliers (0.05-0.17)
    # and cost 26-43 ms each (tracking 3-10, the estimate 16-33); the one that succeeded
    # kept 142 of 281 (0.51). Walk-3hz 13 of 126 (0.10) failed too.
    second_start_min_tracked: float = 0.25
    # An unverified tracked pose is checked against RANSAC on its matches without the prior:
    # a pose farther away than a wrong pose, on >= second_start_tie of the inliers and nearer
    # the motion prediction, means the matches admit two solutions (near-planar points) and
    # the motion does not side with ours: the frame is LOST. Robust walk at 3 Hz (main
    # 1cdd020), frame 23: TRACKING 31.5 cm (11.6% of the scene scale) off on 31 inliers (30 of
    # its 33 matches true), refined from a wrong first estimate; RANSAC's pose 0.8 cm off on
    # 31. Without the "nearer the prediction" condition frame 13 (right, 63 inliers; RANSAC's
    # 57 for a pose 0.83 scene scales away) was lost too. False: off.
    ambiguity_check: bool = True
    # A tracked pose the ambiguity check rejects is checked by global matching on the frame
    # (adopted as RELOCALIZED when it passes the strict test, as collapse_ratio's check), so
    # the frame need not wait for the next to relocalize. Robust walk at 3 Hz (main d1def86),
    # frame 23: LOST (61 inliers from the motion prior, 60 for a pose 0.10 scene scales /
    # 4 deg away) -> RELOCALIZED; localized 29 -> 30 of 30. False: LOST, as before.
    ambiguity_relocalize: bool = True
    # Cluster voting: "sum" adds the strength of every neighbour (the literal reading of the
    # paper); "max" lets each query vote once per cluster, with its strongest neighbour there.
    # With PCA-32 DAISY the 50th neighbour is typically only 1.5x farther than the first, so
    # sigma = 2 prunes little and "sum" mostly counts cluster sizes. Measured on 40 redkitchen
    # frames: relocalization succeeds on 39/40 with "max", 29/40 with "sum".
    vote: Literal["max", "sum"] = "max"
    # Before global matching, try guided matching of the whole frame around the motion
    # filter's prediction (scope: images of the last matched points; verification threshold
    # below). Off: the paper's behaviour (global matching whenever matches run out).
    prior_recovery: bool = True
    # Where the recovery's candidates come from: "global": the search over the whole map that
    # global matching would make (made once per frame: when the recovery fails, global
    # matching uses it as is), restricted to the recovery's scope; "scoped": a search within
    # the scope (k neighbours among its images), then another for global matching. Redkitchen
    # replays (map every 10th frame, scoped -> global, same code otherwise): frames 0-999
    # localized 96.7 -> 97.6%, within 5 cm / 5 deg 96.3 -> 97.1%, median 0.47 -> 0.50 cm (over
    # more, harder frames), 0 wrong either way, relocalization p95 CPU 101 -> 94 ms; frames
    # 200-999: 96.1 -> 97.3%, 95.6 -> 96.6%, median 0.43 -> 0.46 cm, 0 wrong, p95 109 -> 98 ms.
    # Over the 972 frames both runs posed (frames 0-999): median 0.477 -> 0.501 cm, mean 0.699
    # -> 0.700 cm: the median is worse in both segments, so "scoped" stays the default.
    recovery_search: Literal["global", "scoped"] = "scoped"
    # With "scoped": a recovery around the motion prediction first counts the keypoints whose
    # hypotheses from the search global matching makes (restricted to the recovery's scope)
    # fall within prior_threshold_px of the prediction, the recovery's own first test; under
    # recover_min_inliers the recovery is skipped and global matching takes the frame with that
    # search (made once). A recovery fails on that test when the prediction is off by more than
    # the threshold, as it is when tracking lost a fast camera after a long interval: robust
    # flight-3hz, 7 failed recoveries with predictions 8-19 deg off, 0-16 such keypoints by
    # either search (0-17 scoped), 30-63 ms each before its global matching; the 5 recoveries
    # that succeeded on walk-3hz/10hz (0.02-2.6 deg off) counted 46-717 (41-696 scoped).
    recover_precheck: bool = True
    prior_threshold_px: float = 20.0
    # A recovered pose needs more inliers than a tracked one: verification within 20 px of a
    # prediction admits chance matches (an 11-inlier recovery on redkitchen was 0.65 m off).
    recover_min_inliers: int = 20
    # A tracked pose farther from the motion prediction than the camera can move in the frame
    # interval is rejected (the frame then recovers or relocalizes instead of reporting it).
    # Distances are in scene scales (MapBundle.scene_scale, the median camera-to-point depth in
    # map units: 1.90 m on redkitchen, 2.37 m in the synthetic room), so one setting holds for
    # a 0.2-unit object scan and a 500-unit street; the defaults are the former metric ones on
    # redkitchen (5 m/s, 0.10 m).
    max_speed_scales_per_s: float = 2.6
    max_angular_speed_rad_s: float = 6.0  # ~340 deg/s: beyond a quadrotor's fast yaw
    jump_tolerance_scales: float = 0.05
    jump_tolerance_deg: float = 5.0
    # ... and the speed term of that reach is capped (scene scales): at 3 Hz, 2.6 scales/s
    # alone allowed 0.92 scales, no gate at all, and a 12-inlier tracked pose 0.25 scales off
    # (0.25 from the prediction) was published. Correct tracked poses of the synthetic walk,
    # flight and orbit at 3 and 10 Hz lie within 0.11 scales of the prediction. At 30 Hz the
    # cap does not bind (2.6 / 30 = 0.087), so 30 Hz video (redkitchen) is unchanged.
    max_jump_scales: float = 0.15
    # Frames and queries finer than the map ("map"): processed at about the mapping images'
    # focal length (downscaled, never upsampled; see engine.frame.working_scale). "full": at
    # their own resolution, the paper's behaviour: Harris corners at 6 MP are fine detail no map
    # descriptor describes. Synthetic 3072x2048 queries of a map of 640x480 views: "full" 2/10
    # relocalized, both > 1 m off; "map" 10/10, median 0.5 cm (640x480 queries: 0.39 cm).
    working_scale: Literal["map", "full"] = "map"
    # ... and within a pixel budget (0: none), but never coarser than the map's coarsest
    # pyramid level: the engine's parameters (mu, rho, tau, the DAISY patch, 1000 keypoints)
    # are pixels of the paper's 640x480 video. 3072x2048 queries of a map of 3072x2048 images
    # (10 synthetic views): at full size 4/10 relocalized, median 33 cm off; at 2048 px wide
    # 10/10, 1.1 cm; 1280: 0.28 cm; 800: 0.21 cm; 640: 0.20 cm. Streaming 15 such frames:
    # 0/15 at full size (15x the time per frame), 15/15 at 768x512 (median 0.25 cm).
    max_working_pixels: int = 640 * 480
    # Sub-pixel keypoint localization (features/harris.py). "map": as the map's keypoints were
    # (the builder's descriptors.subpixel; "quadratic" for maps built before it was recorded):
    # points are triangulated at those keypoints, so frames must share their localization.
    subpixel: Literal["map", "forstner", "quadratic", "none"] = "map"
    max_keypoints: int = 1500  # strongest Harris corners kept per frame (bounds the latency)
    max_tracks: int = 1000  # track table capacity
    max_hamming: int = 80  # a track match must also be this close (of 256 bits)
    global_max_keypoints: int = 1000  # keypoints described for global matching
    nprobe: int = 16  # inverted lists scanned per ANN query
    # Single-image relocalization (``relocalize``; not the tracker's global matching): its
    # search over the whole map scans ``global_nprobe`` inverted lists (0: ``nprobe``) for the
    # ``relocalize_max_keypoints`` strongest corners (0: ``global_max_keypoints``). Issue 10
    # (relocalization p95 <= 40 ms). The search's flat quantizer (1000 queries x 1879 lists on
    # redkitchen) is a third of the search whatever nprobe; the tail is RANSAC's (and the
    # second-place test's). 100 redkitchen non-map frames (every 10th from 2, map every 10th),
    # interleaved per frame, CPU against main before this (16 / 1000, no distinctness tests;
    # load 40): 4 / 1000 mean x0.875, p95 x0.97 (the distinctness tests included), median
    # 0.262 vs 0.270 cm; 4 / 800 x0.87, x0.95; 4 / 600 x0.81, x0.90; all 100/100, 0 wrong.
    # Fewer corners cost elsewhere: the synthetic room (richer in corners than redkitchen's
    # ~850) median 0.35 cm at 16 / 1000 -> 0.37 (4 / 1000), 0.45 (4 / 800), 0.46 (4 / 600);
    # the 8 look-alike rooms: right RELOCALIZED 131 (4 / 1000), 132 (800), 124 (600). So 4 /
    # 1000. RANSAC capped at 500 iterations: no change.
    global_nprobe: int = 4
    # Global matching's RANSAC (and the second-place test's) also stops by PROSAC's rule: once
    # an all-inlier sample of the best pose would have been drawn from the ranked pools it
    # sampled (``estimate_pose_one_to_many(pool_stop=...)``). False: only the whole-set rule,
    # which ran 250-1000 iterations on redkitchen frames whose best pose was found within 32
    # (1/4 of the frames); RANSAC 14.5 -> 7.0 ms CPU mean per relocalization, p95 26 -> 9 ms.
    global_pool_stop: bool = True
    relocalize_max_keypoints: int = 0
    # Single-image relocalization in two stages (issue 10: the time goes to DAISY, the
    # search, matching and RANSAC, all per keypoint): first the ``relocalize_first_keypoints``
    # strongest corners spread over the image (``relocalize.spread_order``), RANSAC at most
    # ``relocalize_first_iterations`` iterations; a pose far above chance from them
    # (``global_verify_min_inliers`` inliers and ``global_verify_min_ratio`` of the
    # ratio-test matches), distinct, is the answer. Otherwise the other corners are described
    # and searched too, and global matching runs on all of them: the same result as in one
    # stage. 0: one stage.
    relocalize_first_keypoints: int = 300
    relocalize_first_iterations: int = 100
    # A first stage's RANSAC pose below the strong bar but with at least this many inliers
    # is verified by guided matching (as a one-stage pose is) and is the answer when it would
    # be published RELOCALIZED (certain, not withheld), after the distinctness tests; else the
    # second stage runs. 0: only strong first-stage poses. Issue 10 (reloc4): the failing
    # first stages (48-98 inliers of the 100 asked) paid both stages, ~74 ms, 15 of the 25
    # slowest calls. With ``relocalize_staged_from`` 500 -> 450, CPU per call interleaved
    # per frame against main 0617ea5 (nice 19, load 7-10): redkitchen 500 frames p95 x0.875,
    # p99 x0.83, mean x0.995 (both stages 17 -> 2 frames), 500/500, 0 wrong, median 0.245 cm
    # both; every 30th / 60th (200 frames) mean x0.82 / x0.80, p95 x0.63 / x0.91, posed
    # 198 / 188 -> 198 / 189, 0 wrong, median 0.390 -> 0.400 / 0.462 -> 0.470 cm;
    # redkitchen-split (250 frames) mean x0.66, p95 x0.55, posed 244 -> 247, 0 wrong, median
    # 0.447 -> 0.478 cm on the 244 common frames (poses on fewer corners, also from staging
    # at 450); density-6x (100 frames) the same poses, mean x1.01. Without the certainty
    # gate density-6x turned 8 RELOCALIZED to UNVERIFIED (median 0.0144 -> 0.0166 units).
    relocalize_first_min_inliers: int = 30
    # Frames with at least this many corners run the two stages (fewer: one stage). Issue 10,
    # redkitchen (map every 10th frame), 500 frames: from 600 the 500-600-corner frames (a
    # fifth, most of the p95 tail) ran one stage at ~47 ms; from 500 they take ~30 where the
    # first stage holds (99) and 63 -> 74 where it fails (17); with the cluster-bit votes,
    # CPU per call against 600 (nice 19, load ~13) mean x0.89, p95 x0.84-0.89, p99 x0.96,
    # 0 wrong, median 0.237 -> 0.245 cm. On the thin maps (every 30th / 60th frame) more
    # first stages fail: p95 x1.07 / x1.10, mean x0.96 / x0.99
    # (docs/measurements.md#relocalization-time). From 450
    # with ``relocalize_first_min_inliers`` (a failing first stage costs less): redkitchen's
    # 450-500-corner frames ~43 -> ~35 ms.
    relocalize_staged_from: int = 450
    max_hypotheses: int = 8  # one-to-many 3D hypotheses kept per keypoint
    ransac_threshold_px: float = 4.0  # inlier reprojection error in RANSAC
    ransac_confidence: float = 0.999
    ransac_max_iterations: int = 1000
    refine_threshold_px: float = 3.0  # inliers kept for the final refinement
    # The final refinement down-weights matches with a Cauchy loss of this scale (px; 0: plain
    # least squares on the inliers within refine_threshold_px). A wrong corner next to the
    # right one passes the 3 px threshold and pulls a least-squares pose. Measured against 0 in
    # the same run (CPU per frame new/old): redkitchen 1000 frames median 0.58 -> 0.48 cm, mean
    # 0.82 -> 0.73 cm, within 5 cm / 5 deg 94.1 -> 95.5%, CPU x1.01; synthetic walk median 0.50
    # -> 0.41 cm, flight 0.34 -> 0.26 cm (300 frames), CPU x1.02-1.04. Scale 0.5 px: no better;
    # refine_threshold_px 2 instead: similar accuracy but tracks lost to the tighter threshold
    # (3x the global-matching frames, CPU x1.18).
    refine_loss_scale_px: float = 1.0
    # The tracker's first estimate of a frame holding at least first_unrefined_from tracked 3D
    # matches stops before its robust final refinement (0: never): the second estimate, which
    # refines it robustly on the matches the re-verification and guided matching add, is that
    # refinement (issue 10: one Cauchy refinement a frame fewer). `python -m sfmloc.bench.ab`
    # against main 0617ea5, 1000 frames interleaved, nice 19, load 6-10: redkitchen pose stage
    # CPU 2.52 -> 2.34 ms/frame (x0.93; x 4 runs; x0.94 in another x 2), engine mean 9.62 ->
    # 9.60 ms (inside the load's noise), 1000/1000, 99.8% within 5 cm / 5 deg, 0 wrong, median
    # 0.279 -> 0.282 cm; map every 60th: pose 2.44 -> 2.25 ms, 997/997 posed, 98.9% both; every
    # 30th: 2.89 -> 2.68 ms, 999/999, 99.9%; density-6x 237/237, walk 300/300
    # (docs/beyond-the-paper.md#first-unrefined).
    # On every frame (0 matches up): every 60th 997 -> 992 posed (frames 393-396 and 465-466
    # lost), every 30th 999 -> 998; a hair's change of refine_loss_scale_px moved neither.
    # With few matches a near-outlier pulls the least-squares pose that then decides which
    # matches the frame keeps and verifies: those frames keep the refinement.
    first_unrefined_from: int = 40
    # The least-squares round from a prior (the tracker's first estimate from the motion
    # prediction; every estimate from a prior) stops after a Gauss-Newton step shorter than
    # this many of the pose's standard deviations at 0.3 px noise (0: at its 1e-8 rad
    # tolerance; pose.least_squares). Issue 10: Gauss-Newton on a least-squares pose converges
    # about quadratically; the tolerance took 3.87 steps a frame on redkitchen (1000 frames),
    # its last two moving the pose a median 3.5e-5 and 6e-8 sd; at 0.5 sd 2.24 steps. Published
    # poses within 2.7e-4 of their sd of the tolerance's (median 3e-8; 0 over 0.1 sd),
    # 1000/1000, the same statuses, covariances within 2e-4; `python -m sfmloc.bench.ab` (1000
    # frames x 2, nice 19, load 8.5-11): pose stage CPU 1.57 -> 1.47 ms/frame. Robust rows
    # density-6x, density-3x, redkitchen-every-60th, walk-3hz, flight-10hz, orbit-3hz (0 against
    # 0.5, `sfmloc bench --suites robust --reuse --engine-config`): every frame's status and
    # inlier count the same, errors within 2.6e-6 units, 0 wrong both.
    prior_refine_converged_sd: float = 0.5
    # A verified tracked pose is refined once more (projected_iterations Cauchy Gauss-Newton
    # steps) on its inliers and the map points projecting within projected_radius_px of one of
    # the frame's unmatched keypoints, with no other keypoint within projected_clear_px (the
    # closest point per keypoint), among the points of the projected_top_images images that see
    # most of its matches (engine/projected.py; issue 9: tracked poses rested on ~76 inliers,
    # the SIFT peer's on ~390). The status and the covariance stay the tracked matches'. False:
    # off. Redkitchen, 1000 frames, one run, interleaved frame by frame against main (99d662f,
    # c2b1955; load 8-45): median 0.326 -> 0.276 cm, mean 0.444 -> 0.403, p90 0.80 -> 0.75, 0
    # wrong, within 5 cm / 5 deg 99.8 -> 99.6%, NEES mean 9.5 -> 8.2 (median 6.8 -> 5.0), CPU
    # per frame x1.099, x1.109, x1.104 in three runs (the commit's faster covariance alone:
    # x0.972); against main adc34aa (guided batch 100, load ~10): 0.321 -> 0.281 cm, mean
    # 0.445 -> 0.410, 99.7% within 5 cm / 5 deg both, CPU x1.045-1.072 (three configurations
    # with the same poses). `sfmloc bench --suites redkitchen`: 0.27 cm vs the peer's 0.19
    # (1.42x; main 0.32, 1.69x), 99.6% within 5 cm / 5 deg, 0 wrong. Robust bench rows, ours /
    # peer median:
    # walk-30hz 0.231 -> 0.166 cm (peer 0.133), orbit-10hz 0.279 -> 0.228 cm (0.154). Synthetic
    # walk (test video) mean / p90: 30 Hz 0.83 / 1.92 -> 0.67 / 1.32 cm, 10 Hz 0.57 / 0.98 ->
    # 0.44 / 0.69. Measured alternatives (redkitchen median, CPU against off): radius 1 px
    # 0.397 vs 0.367 cm at 1.5 on frames 400-699 (an earlier, k-d tree association);
    # projected_clear_px 2: 0.271 cm, x1.17 vs x1.14; 1 iteration: 0.290 cm, x1.11 vs x1.12
    # for 2; top 3 images (1 iteration): 0.310 cm, x1.09.
    # The covariance from all the matches instead (their residuals are small by selection):
    # NEES mean 18.5, optimistic.
    projected_refine: bool = True
    projected_radius_px: float = 1.5
    projected_clear_px: float = 3.0
    projected_top_images: int = 5
    projected_iterations: int = 2
    guided_threshold_px: float = 6.0  # verification of guided hypotheses against the pose
    add_min_distance_px: float = 6.0  # new keypoints keep this far from tracked ones
    # Kalman filter. "se3": one constant-velocity model on SE(3) (pose and body-frame twist);
    # "paper": constant velocity and constant angular velocity filtered apart (Section 3.3).
    # Measured with python -m sfmloc.eval.motion (synthetic room; median one-step prediction
    # error of the tracked map points): an orbit at 3 Hz 3.9 px (paper) -> 0.2 px (se3), tracked
    # frames 87% -> 93%; at 30 Hz walk 2.3 -> 0.9 px, flight 1.0 -> 0.5 px, redkitchen 2.2 -> 2.5
    # px, the same localized fraction and errors.
    motion_model: Literal["se3", "paper"] = "se3"
    # A relocalized frame restarts the filter with the motion since the last posed frame (within
    # max_frame_gap_s) instead of none: at low frame rates a motionless prediction misses the
    # tracking window, tracking fails, the frame relocalizes and the cycle repeats. At 3 Hz
    # (synthetic room, 30 frames; both switches off -> on) tracked frames 37% -> 83% (orbit),
    # 20% -> 47% (walk), 33% -> 47% (flight); wrong poses 11 -> 1, 4 -> 1, 2 -> 0.
    relocalize_keeps_motion: bool = True
    # Noises with distances in scene scales as above (the former 4 m/s^2 and 0.02 m on redkitchen)
    accel_noise_scales_per_s2: float = 2.0  # white-noise acceleration
    angular_accel_noise_rad_s2: float = 8.0
    position_noise_scales: float = 0.01  # measurement noise of a pose
    orientation_noise_rad: float = 0.01
    # A gap between frames over max_frame_gap_s resets the tracker (motion filter and tracks:
    # the frame relocalizes); every gap test reads it (the engine's reset, the contradiction and
    # keep-motion windows, the sub-map prediction, the server's scheduling, replay's count).
    # 0.9 s, not 1 s: a 1 Hz camera sat on a 1 s limit, its stamps' float noise (index / 30 of
    # every 30th frame: 40 of 970 gaps over 1 s by 2e-16) or a few ms of jitter resetting some
    # frames and not others. Off the limit, 1 Hz could track (a 1.1 s limit) or relocalize
    # every frame (this one). Redkitchen every 30th frame at 1 Hz, all 30 offsets, +-5 ms of
    # jitter (1000 frames, map every 10th; docs/beyond-the-paper.md#frame-gap): the 1 s limit
    # reset 479 of 970 gaps, 999 localized, 997 within 5 cm / 5 deg, median 0.253 cm, 46.0 ms
    # CPU a frame; tracking every gap (1.1 s) 998, 994, 0.320 cm, 34.0 ms; relocalizing every
    # frame 1000, 998, 0.234 cm, 52.1 ms (measured with gaps of 1.1 s, which a 1 s limit
    # reset); 0 wrong in all. At 1 Hz the accuracy is worth the CPU.
    max_frame_gap_s: float = Field(0.9, gt=0.0)
    # ---- a pose is a promise (README, Conventions: "Pose covariance" and "Status"; their
    # evidence: docs/measurements.md#covariance-calibration, docs/measurements.md#status-rules)
    # Pixel noise of the map's keypoints, for the map points' own uncertainty in the pose
    # covariance (engine/point_uncertainty.py; 0: the frame's pixel noise only). Fitted on exact
    # synthetic ground truth with ``python -m sfmloc.eval.calibration`` (150 frames per video,
    # every pose published; mean NEES of the correct poses, expected 6, and of the centre alone,
    # expected 3; the frame's noise measured with the refinement's Cauchy weights):
    #   map_noise_px         0 (pixel only)  0.4            0.75 (before; noise from the RMS)
    #   walk, map 1x         8.0 / 2.8       6.2 / 2.2      5.2 / 1.8
    #   walk, map 6x         8.0 / 5.3       4.8 / 3.0      4.4 / 2.5 (held 62 -> 55 of 120)
    #   walk, map 3x         6.9 / 3.6       4.2 / 2.1      3.1 / 1.5
    #   flight, map 1x       3.8 / 2.5       2.2 / 1.5      1.8 / 1.1
    #   orbit, map 1x        3.0 / 1.4       2.3 / 1.0      2.0 / 0.8
    #   test video (60)      10.6 / 4.8      6.2 / 2.6      4.6 / 1.7
    #   redkitchen, 10th     26 / 10         3.7 / 1.2      3.3 / 1.0 (against pgt: its mm
    #   redkitchen, 60th     24 / 8.6        7.0 / 1.7      6.1 / 1.3  noise counts as ours)
    # 0.4: the largest synthetic mean near its expected value, none optimistic; 0 would promise
    # 4x too much on redkitchen, where NEES grows with the inlier count (an error that more
    # inliers do not average away: the map's points and the pseudo ground truth).
    # 0.4 -> 0.35 with projected_refine (its poses are more accurate than their tracked
    # matches' covariance says; guided batch 100): test video 4.85 / 2.39 -> 5.28 / 2.62 (0.3:
    # 5.76 / 2.88); redkitchen 1000 frames mean / median 8.1 / 5.2 -> 9.4 / 6.1 (main without
    # the refinement: 9.5 / 6.6; 0.3: 10.9 / 7.1). The 150-frame videos above not re-measured.
    map_noise_px: float = 0.35
    # A tracked pose whose centre sd without its most influential match (the one whose removal
    # widens it most; ``pose_covariances``) is over ``max_position_sd`` is re-matched on the
    # whole frame (``densify_uncertain``), replaced when the re-matched pose passes the strict
    # test: a certainty resting on one match cannot check that match, fitted by the pose. Synthetic
    # room, the reliability bench's gaps pattern (seed 1): after a 0.8 s gap, 20 right matches
    # on a far wall (sd 8.6% of the scene scale without the 21st) and one wrong on a near point
    # gave a TRACKING pose 5.1% off with sd 0.6%; re-matched, 97 inliers, 0.19% off. The
    # status rules and the reported covariance stay those of all the matches: judged
    # without it, redkitchen frame 462 (2.4% off, sd 1.4%, 5.8% without one) was withheld,
    # and the tracks that followed gave frame 468 6.0% off (main: 2.0%); so did replacing
    # frame 466 by a re-match only more certain (3.5% -> 2.9% off, sd 2.0%). False: all
    # matches (no re-match for it).
    covariance_leave_one_out: bool = True
    # A pose whose centre standard deviation (worst direction) exceeds this fraction of the
    # scene scale is withheld (LOST; the tracker still follows it). Redkitchen replay (1000
    # frames, map every 10th, map_noise_px 0.5, before the Cauchy refinement): the wrong poses
    # (> 5%) had sd 3.7-9.2%; limit 2%: 46 frames withheld (28 of them within 5 cm), 3%: 25
    # (10), 3.5%: 16 (3) with the wrong one at 3.7% close. Synthetic videos peak at 1.2%.
    max_position_sd: float = 0.03
    # ... judged at the upper bound of the pose's noise estimate (one-sided normal quantile;
    # 0: the sd as reported): the pixel noise comes from 2N - 6 residuals, and the poses that
    # calibration cannot catch (a consistent set of wrong matches) have few inliers. Measured
    # with sfmloc.eval.calibration (wrong poses published / right poses published), z 0 ->
    # 1.645: redkitchen map every 60th 1/289 -> 0/276, walk at 3 Hz 4/26 -> 3/26, walk on the 6x
    # map 0/85 -> 0/72 (the previous covariance model with z 0: 0/58 of 120 on an older map).
    withhold_noise_z: float = 1.645
    # A relocalization is RELOCALIZED (verified) only when its sd is at most this and it has at
    # least ``verified_min_inliers`` inliers, else UNVERIFIED, and the frames tracked from it
    # stay UNVERIFIED until one passes the same test. Redkitchen single-image relocalizations
    # (every 7th frame): correct ones sd <= 0.98% with >= 27 inliers, wrong ones >= 2.5%.
    verified_position_sd: float = 0.01
    verified_min_inliers: int = 20
    # ... and, for a relocalization (global matching, a prior's recovery: no earlier frame
    # checked its matches), only when its centre sd without its most influential map point (a
    # point matched by two keypoints counts once) would not be withheld (``max_position_sd``
    # at ``withhold_noise_z``): else it is judged as an unverified one (UNVERIFIED, and
    # rejected when it contradicts a recent motion prediction: ``contradiction_position``;
    # the leave-out rule still takes ``relocalize_leave_out_verified`` points for it).
    # Robust density-6x, the synthetic flight every 10th frame at 3 Hz, frame 286: RELOCALIZED
    # 17.9% of the scene scale off with sd 0.63% on 70 inliers, 68 of them on a far wall
    # (2.2-2.7 scene scales deep, a two-fold planar ambiguity) and 2 keypoints on one map
    # point 1.0 deep, matched wrongly (50 px off under the truth): without that point sd
    # 3.1%. The covariance's leave-one-out (a match) kept both keypoints: 0.91%; the
    # relocalization leave-out rule (4 points, 5%) 4.3%. False: the strict test alone.
    verified_without_one: bool = True
    # An UNVERIFIED pose (a relocalization failing the strict test, or a frame tracked from
    # one) on fewer inliers than this is withheld (LOST; the tracker still follows it, so a
    # later frame passing the strict test is published). Every robust bench row (main 42e50b9):
    # UNVERIFIED poses on < 20 inliers were 12 wrong (density-6x frames 249-260: 11-14
    # inliers, 1.4 scene scales / 99 deg off, a 13-inlier global match after a 1 s gap, so no
    # motion prediction to contradict it) and 1 right (redkitchen every 60th, 12 inliers);
    # none on >= 20 inliers. 0: off.
    unverified_min_inliers: int = 20
    # A single-image relocalization (``relocalize``: no next frame to check its matches) whose
    # centre sd without its ``relocalize_leave_out`` most influential map points
    # (``certainty.position_sd_without``; ``relocalize_leave_out_verified`` for a pose that
    # passes the strict test, which would be published RELOCALIZED) is over this fraction of
    # the scene scale (the wrong-pose limit: that many wrong matches could put it that far at
    # one sd) is withheld (LOST). Robust density-6x map, the 300 video frames one by one (main
    # e7bb8f6): the wrong poses (29-98% of the scene scale, 5-18 deg off, sd 0.4-2.5%, so
    # published RELOCALIZED or UNVERIFIED with a covariance 30-60 sd short of the error)
    # rested on two to four matches to map points near the camera (0.01-1.5 scene scales deep
    # against a median of 3) or on one map point matched by two keypoints a pixel apart (each
    # hides the other from the leave-one-out); without them the same inliers give sd 15-20%.
    # Measured (wrong RELOCALIZED / wrong UNVERIFIED / right posed, off -> on): density-6x
    # 1/9/190 -> 0/0/190, last session's density-6x map 3/11/171 -> 0/1/170 (the one: 5.2%
    # off with sd 2.7%, covered), redkitchen 500 frames 0/0/500 -> 0/0/500, every 60th
    # 0/0/189 -> 0/0/189. 2 for every pose: last session's map keeps a RELOCALIZED pose 29%
    # off (sd 7.6% without 4 points, 1.5% without 2); 4 for every pose: 1-2 right UNVERIFIED
    # poses lost per thin map. 0: off.
    relocalize_leave_out_sd: float = 0.05
    relocalize_leave_out: int = 2
    relocalize_leave_out_verified: int = 4
    # The same rule for the tracker's own relocalizations (``Localizer.localize``: global
    # matching, the prior recovery, a collapsed or ambiguous tracked pose re-checked): a
    # relocalization the status rules would publish is not adopted when it rests on a few
    # matches (LOST; the next frame relocalizes), and a pose tracked on from an unverified
    # (or withheld) relocalization is withheld when it does (its tracks keep the same
    # matches). Robust density-6x streamed with the session reset every 1 / 10 / 30 frames
    # (``sfmloc replay --reset-every``; main 641a3ba): 18 / 27 / 27 published poses 5-118%
    # of the scene scale off (UNVERIFIED with sd 1.3-2.5%: relocalizations, or frames
    # tracked on from a withheld one that gathered guided matches around itself) -> 2 / 1 /
    # 0; right poses published 190 / 192 / 213 -> 186 / 191 / 212. Without resets,
    # density-3x, redkitchen every 60th: unchanged.
    # False: only single-image relocalization has the rule.
    track_relocalize_leave_out: bool = True
    # A tracked pose failing the strict test on fewer inliers than this fraction of the last
    # posed frame's is checked by global matching (adopted as RELOCALIZED when verified, else
    # no pose). Robust walk at 3 Hz (main 59029bd): the 5 wrong TRACKING poses (5-16% of
    # the scene scale off) had 11-32 inliers after 306-625 and failed the strict test; the
    # right ones fall gradually (synthetic walk at 30 Hz: 64 -> 39 inliers, sd 1.0-1.8%).
    # 0: off.
    collapse_ratio: float = 0.2
    # A pose recovered around the motion prediction on a frame tracking found no pose for,
    # that fails the strict test, is checked by the frame's global matching: replaced by its
    # pose when that one passes the strict test (as a collapsed tracked pose is); else it
    # goes on unchanged. Robust walk at 3 Hz: frame 130 recovered 1.80 m off (67% of the scene
    # scale, 122 inliers), its global matching the right pose on 404 (without the check the
    # ambiguity check's global matching found it too; with neither, LOST). Before the wide
    # tracking window (2771732) frame 90: recovered 1.43 m off on 173 inliers, withheld only
    # by its centre sd 3.02% against the 3% limit (at a 3.5% limit published as TRACKING;
    # with the check RELOCALIZED, 590 inliers, 0.37 cm off). Redkitchen 1000 frames: recovery
    # 3 times, the check never (poses identical). False: off.
    recovered_global_check: bool = True
    # ... and when that global matching keeps no pose, the recovered pose is withheld (LOST)
    # if the strongest pose it found and did not keep (one failing the strict test, or an
    # ambiguous answer's best) has at least the recovered pose's inliers and lies farther
    # from it than a wrong pose (contradiction_position / contradiction_deg below); one near
    # it (the motion chose among an ambiguous answer's poses) supports it. Room of identical
    # walls (tests/test_engine.py), strict test at 100 inliers, frame 10's prediction turned
    # onto a twin wall: recovered 0.69 scene scales / 90 deg off on 51 inliers, centre sd
    # 0.34%; its global matching ambiguous, 165 inliers for the right pose, 64 where the
    # recovered one is: main 7eae836 published it as TRACKING, now LOST. Robust rows walk,
    # flight, orbit at 3 Hz, orbit 10/30 Hz, walk/flight 10 Hz, density 3x/6x, every 30th/60th,
    # and replays of redkitchen every 8th/12th frame, density-6x at 3/6 Hz, redkitchen 1000
    # frames (instrumented): this path ran 0 times (its one global check there, walk-3hz
    # frame 130, verified the right pose). False: the recovered pose goes on unchanged.
    recovered_rivals: bool = True
    # A recovered pose that passes the strict test is checked the same way: replaced by the
    # frame's global matching's pose when that passes the strict test and lies farther from
    # it than a wrong pose on at least its inliers, withheld when a pose global matching
    # found and did not keep does (``recovered_rivals``). A recovered pose 0.7 scene scales off
    # is as certain as a right one: on the room of identical walls (default configuration;
    # frames 10, 20, 25, 30, prediction turned by 90, 180, 270 deg, the recovery given the last
    # frame's scope or every map point) main 7eae836 published 7 of 24 frames as TRACKING
    # 0.69-1.25 scene scales off on 42-86 inliers, centre sd 0.1-0.4%: now 0 (5 RELOCALIZED
    # 0.2-0.5% off, 2 LOST, ambiguous); the one right recovered pose stays. Its price: one
    # global matching per verified recovered frame (robust walk-3hz frame 70, 532 inliers:
    # CPU 102 -> 155 ms, unchanged pose); on the rows and replays above every frame's status,
    # inliers and error are unchanged (redkitchen 1000 frames: no recovery). False: a
    # verified recovered pose is published unchecked.
    recovered_verified_check: bool = True
    # An unverified relocalization farther than this from the motion prediction (fraction of
    # scene_scale, degrees: the wrong-pose limits) is rejected (LOST) while the last pose is
    # at most max_frame_gap_s old: redkitchen frame 461, 10 inliers, 1.49 m / 33 deg off, was
    # 1.35 m from the prediction. The same limits at every interval: limits growing with it
    # (0.3 x speed x interval, capped at 0.15; 60 deg/s x interval) were measured and not
    # taken: on a thin map at 3 Hz, the only data where the check fires, they added wrong
    # poses (flight) and lost frames (walk) (docs/beyond-the-paper.md#rejected-contradiction-gap).
    contradiction_position: float = 0.05
    contradiction_deg: float = 10.0
    # ... and only while the last posed frame's pose was published: a prediction extrapolated
    # from a withheld pose (the filter follows it) is no evidence. Robust density-6x (300
    # frames, main 6caaf55): after withheld tracked poses (one 29% of the scene scale off) the
    # constant-velocity prediction drifted up to 2 scene scales / 177 deg within the 1 s window
    # and rejected right relocalizations (frames 97-103: 0.9-3.1% off). Off -> on (the switch
    # below off): localized 174 -> 185 of 300, wrong 0 -> 0. False: any recent prediction.
    contradiction_published_only: bool = True
    # A pose about to be withheld as too uncertain (``max_position_sd``) is re-matched on the
    # whole frame around itself (guided matching of every keypoint, scoped by the map points
    # it makes visible; the recovery's rules, ``recover_min_inliers``) and replaced when that
    # pose is more certain. On a thin map the tracks that survive bunch on a far wall: robust
    # density-6x frames 37-96 were tracked on 40-62 such matches (sd 3-7% of the scene scale,
    # error 2-14%) while the frame saw ~200 map points; re-matched, 103-118 inliers, sd 1.0-2.2%,
    # error 0.7-2.0% (the peer's 0.6-2.3%). Off -> on, 300 frames: localized 174 -> 234 (185 ->
    # 238 with the switch above), 0 wrong either way. Redkitchen (1000 frames, map every 10th)
    # and the synthetic walk, flight and orbit at 10 and 3 Hz: frame for frame the same (no
    # pose there is withheld for its sd). Cost: one whole-frame search (~35-50 ms at load 20)
    # per frame it runs on. False: off.
    densify_uncertain: bool = True
    # ... with the corners from this many pixels from the image edge on (the tracker keeps
    # mu // 2 = 16 clear for BRIEF; DAISY, which guided matching compares, needs less), and
    # also from the motion prediction when the last posed frame was published (its pose may
    # be the one that drifted). Robust density-6x frame 217: the points that fix the pose
    # lie 12-14 px from the right edge, the tracked pose is withheld (sd 7%); with both, a
    # re-match from the prediction gives TRACKING 0.3% off (sd 1.5%); either alone changed no
    # frame. 0 (or >= mu // 2) / False: off.
    densify_edge_px: int = Field(8, ge=0)
    densify_from_prediction: bool = True
    # ... and so is (replaced only by a verified re-match) a tracked pose whose inliers are
    # fewer than this fraction of the frame's tracked 2D-3D matches (0: never): most tracking
    # windows then held the wrong corner (a prediction far off: the first frame after a
    # relocalization, with no motion known yet), and a consensus of the rest can be one of
    # wrong matches. Robust walk at 10 Hz, frame 1: 31 of 131 tracked matches (25 right), 11
    # of the 31 wrong, a TRACKING pose 5.2% of the scene scale off with sd 0.6% -> 643
    # inliers, 0.02% off. Synthetic walk, flight, orbit at 10 and 3 Hz: 3 frames under 0.5.
    track_consensus: float = 0.5
    # A re-match of such a pose (uncertain, or suspect as above) that is more certain than it
    # but fails the strict test does not replace it; its difference from the tracked pose
    # (``pose_error_vector``, 6-vector e) is then added to the tracked pose's covariance
    # (C + e e^T) before the status rules judge it: two poses of one frame from its own
    # matches that lie apart say how far either can be off, whatever each one's covariance
    # claims (``certainty.with_disagreement``). Redkitchen frame 466 on the --extend map (motion
    # blur; 27 tracked inliers on one wall at 2.3-2.9 m, 6 of them drifted tracks 3.5-10 px
    # from their points at the true pose): TRACKING 8.6% of the scene scale off with sd 2.2%
    # (centre NEES 40, expected 3); its re-match 4.0% off, sd 1.9%, 4.7% from it -> sd 4.9%,
    # withheld. False: the tracked pose's own covariance.
    rematch_disagreement: bool = True
    # ... and such a pose (suspect, its re-match not replacing it) whose centre sd without its
    # most influential match (``covariance_leave_one_out``) exceeds relocalize_leave_out_sd
    # (the wrong-pose limit: that one unchecked match can put it a wrong pose away at one sd)
    # is judged at that sd: withheld, and the tracker follows it as any too uncertain pose
    # (odometry may pose the frame instead). Robust density-6x at 10 Hz (every 3rd frame,
    # main 86b8d11), frame 216: 48 right tracked matches on one far patch (sd 14%), guided
    # matching around that pose added one wrong match to a nearer point that fixed it:
    # TRACKING 15.9% of the scene scale off, sd 1.41% (13.5% without it), its re-match, from
    # that pose, 16.2% off; the next 6 frames were odometry on points triangulated from it,
    # 12.7-13.1% off. Now 216 TRACKING 0.67% off (odometry, then back on the map), 219-234
    # withheld: wrong 7 -> 0. False: the pose's own covariance (widened by the re-match).
    suspect_leave_out: bool = True
    # ... and (with suspect_leave_out) a tracked pose that no re-match checked judged the same
    # way: a suspect one whose re-match found no more certain pose (or none), and the
    # publishable re-match that replaced a pose too uncertain to publish, when it fails the
    # strict test (its own most influential match is as unchecked). Robust density-6x walk at
    # 3 Hz (every 10th frame, all 10 offsets): frames 213 (13.4% of the scene scale off, sd
    # 1.61%, 13.5% without its one wrong match) and 191 (13.1% off, sd 2.36%, 19.3% without
    # it) were published TRACKING, and 223 and 233 were odometry on points triangulated from
    # 213: 252 localized / 4 wrong -> 256 / 0. False: only the agreeing re-match's case.
    suspect_leave_out_unchecked: bool = True
    # ---- visual odometry beyond the map (engine/session_points.py)
    # A frame whose map matches give no publishable pose, after a published one, is posed on
    # session points (the tracker's unmatched tracks triangulated from two map-posed frames)
    # beside its map matches; its covariance carries the anchor frames' (compounded, never
    # averaged) and the status rules judge it as any other (TRACKING, matching "odometry").
    # Robust density-6x (20 mapping views 6 apart; frames 218-274 see one view over half of the
    # image, their map poses withheld at sd 6-15% of the scene scale, one 26% off): 300 frames
    # 237 -> 300 localized, 0 -> 0 wrong, the 20 compared with the peer 16 -> 20 (frame 232:
    # 0.97% off, sd 1.8%); odometry error at most 1.9% (the bench's rebuilt map: 3.3%), sd
    # 1.5-2.6%. Exact synthetic geometry: NEES 6.01 (expected 6). False: off.
    odometry: bool = True
    # triangulation: at least this parallax between the two rays (degrees), at most this
    # reprojection error on either (px), depth at most this many scene scales
    odometry_min_parallax_deg: float = Field(2.0, gt=0.0)
    odometry_max_reprojection_px: float = Field(2.0, gt=0.0)
    odometry_max_depth_scales: float = Field(10.0, gt=0.0)
    # a track's pixel noise over its life (tracked frame to frame; the point's sd is
    # sqrt(2) * depth * noise / focal / sin(parallax))
    odometry_noise_px: float = Field(1.0, gt=0.0)
    # session points among the pose's inliers, at least
    odometry_min_points: int = Field(20, ge=6)
    # the published frames kept for triangulation while the map poses every frame (their
    # tracks' first rays are at most this many frames back), and the map-posed frames after
    # odometry that keep the session points (then they go, and recording is lazy again)
    odometry_window: int = Field(60, ge=2)
    # An odometry pose whose inliers are fewer than this fraction of its candidate matches
    # (the frame's tracks with a session point, and its map matches) is no pose (0: off):
    # most tracks left the points they were triangulated on (at a low frame rate the
    # tracking windows around a prediction that is off sit on other corners, which can agree
    # on a wrong pose), and an odometry pose has no check but its matches (never verified;
    # the map path's ``track_consensus`` re-match cannot apply). Robust density-6x / 3x,
    # every 10th / 5th frame (3 / 6 Hz; main 86b8d11): the 4 wrong odometry poses (6x frames
    # 160 and 230, 3x 150 and 160: 7-11% of the scene scale off, centre sd 0.5-2.6%) had
    # 0.30-0.50 of their matches as inliers; the right ones 0.67-1.0 (at 30 Hz 0.89-1.0).
    odometry_min_consensus: float = Field(0.6, ge=0.0, le=1.0)
    # ---- out-of-core maps (engine/submaps.py; issue 14)
    # Resident sub-maps of a sub-map set, in MB, per engine worker (``sfmloc serve
    # --map-memory``): the worker's sessions on the set share its parts within it. None: sub-map
    # sets are refused (plain bundles are loaded whole either way).
    map_memory_mb: float | None = Field(None, gt=0)
    # Parts a frame without a pose is matched against (in the order of the vote) before it is
    # answered LOST. 8 rooms in 24 parts, 320 frames (scale bench, --parts submaps): one part
    # per frame from the next frame on, 291 localized (each room's first frames lost while the
    # search went part by part); 2 from the frame that lost its part on (with the vote's ratio
    # test), 313.
    submap_lost_parts: int = Field(2, ge=1, le=16)
    # CPU time (this thread's, ms) a frame without a pose may spend matching parts before it
    # is answered LOST: after ``submap_lost_parts`` parts, further parts in the order of the
    # vote while the frame's search has used less than this (0: ``submap_lost_parts`` only).
    # CPU, not wall time: on a shared machine the wall time of a try varies tenfold with the
    # load, and the number of parts a frame meets must not. A part that does not hold the
    # frame costs a full RANSAC (1000 iterations, no pose stops it early): 200-250 ms CPU per
    # part on the 24 rooms at load 20 (this 2-core Xeon). 24 rooms in 72 parts, the camera
    # teleported from room to room (the sub-map walk alone, with the search order of
    # ``engine/submaps.py``): 600 ms, the 11 rooms around the entries lost before 432/440;
    # 1000 ms, all 24 rooms 956/960 (3-4 parts a searching frame, ~370 ms CPU each, 0 wrong;
    # 940 before with 2 parts and the old order). Only frames of a session without a pose pay
    # it (room entries, a teleport): tracked frames never search.
    submap_search_cpu_ms: float = Field(1000.0, ge=0.0)
    # The hard cap on the parts one lost frame meets with the CPU budget above.
    submap_search_max_parts: int = Field(8, ge=1, le=64)
    # The longest a frame waits (wall ms, for all its loads together) for parts it wants that
    # the loader thread is loading; a part not resident by then is left to load, and the frame
    # matches the resident parts meanwhile (later frames get the rest). Issue 14 asks that no
    # load stall a frame by more than the speed issue's p99 target (15 ms). The parts a lost
    # frame needs load early instead (``engine/submaps.py``: the vote is taken as the frame's
    # tracking fails, and the next part loads while one is matched), so the frame seldom
    # needs to wait. 24 rooms in 72 parts at 10x the budget (scale bench --parts submaps
    # --rooms 24 --ratio 10): waiting as long as a load took (the old default, per part),
    # 956/960 localized, stall p99 55-63 ms; 0 (never), 922/960 before the early loads; 10
    # with them (load 12-18): 947/960 (98.65%, 4 frames under issue 14's 99%: room 13's first
    # frames stop at a part not loaded in time), stall p99 9.1 ms, 7 frames over 15 ms
    # (docs/measurements.md#submap-measurements).
    submap_load_wait_ms: float = Field(10.0, ge=0.0, le=60_000.0)

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data: Any) -> Any:
        if isinstance(data, dict):
            old = [k for k in data if k in RENAMED]
            if old:
                raise ValueError("; ".join(f"{k} was renamed {RENAMED[k]}" for k in old))
            gone = [k for k in data if k in REMOVED]
            if gone:
                for k in gone:
                    warnings.warn(
                        f"engine setting {k} is ignored: {REMOVED[k]}", UserWarning, stacklevel=2
                    )
                data = {k: v for k, v in data.items() if k not in REMOVED}
        return data

    def ransac(self, min_inliers: int | None = None) -> RansacParams:
        """The RANSAC settings of the pose estimators."""
        return RansacParams(
            threshold=self.ransac_threshold_px,
            refine_threshold=self.refine_threshold_px,
            min_inliers=self.min_inliers if min_inliers is None else min_inliers,
            confidence=self.ransac_confidence,
            max_iterations=self.ransac_max_iterations,
            loss_scale=self.refine_loss_scale_px,
            converged_sd=self.prior_refine_converged_sd,
        )
