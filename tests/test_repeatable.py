"""The engine is repeatable (README, Conventions: "Repeatable poses"): the same map, the same
frames and the same config give bit-identical results, whatever else runs in the process
(other sessions on other maps and configs, single-image relocalizations, the global random
generators of numpy, Python and OpenCV) and in another process (another hash seed).

The streams here exercise the random parts: a camera that reverses at three times the speed
(recovery, relocalization), frames in a shuffled order (global matching on every frame), RANSAC
on each; a pose that depended on shared random state would move between the runs."""

from __future__ import annotations

import os
import random
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from sfmloc.engine import EngineConf, Localizer, relocalize
from sfmloc.engine.types import FrameResult, Status
from sfmloc.map.bundle import MapBundle
from sfmloc.transforms import Rigid3d

REPO = Path(__file__).resolve().parents[1]


def _fingerprint(r: FrameResult) -> tuple:
    """Everything a frame's answer carries that a client acts on, as exact bytes."""

    def pose(p: Rigid3d | None) -> bytes | None:
        return None if p is None else p.rotation.tobytes() + p.translation.tobytes()

    cov = None if r.covariance is None else np.asarray(r.covariance).tobytes()
    return (
        r.status,
        r.matching,
        r.inliers,
        r.tracked_3d,
        pose(r.cam_from_world),
        pose(r.filtered_cam_from_world),
        cov,
        r.message,
    )


def _stream_a(world) -> list[np.ndarray]:
    # forward at 15 Hz, then back at three times the speed: the prediction overshoots
    return list(world.gray[::2]) + list(world.gray[1::3][::-1])


def _disturb(seed: int) -> None:
    """Move every process-wide random generator the engine could use."""
    np.random.seed(seed)
    np.random.random(97)
    random.seed(seed)
    random.random()
    cv2.setRNGSeed(seed)
    cv2.randu(np.empty((7, 7), np.float32), 0, 1)


def test_interleaved_sessions_give_the_poses_of_a_session_alone(world, bundle, cam):
    frames = _stream_a(world)
    stamps = [i / 30 for i in range(len(frames))]
    alone = [_fingerprint(r) for r in map(Localizer(bundle, cam).localize, frames, stamps)]
    statuses = {f[0] for f in alone}
    # the stream reaches the random parts: it relocalizes, and it tracks
    assert Status.RELOCALIZED in statuses and Status.TRACKING in statuses

    # Two more replays of the same stream, interleaved frame by frame with each other and
    # with a session on another bundle object, another config and shuffled frames, a
    # single-image relocalization and the global generators moved between frames.
    other_bundle = MapBundle(world.maps_dir / "room2")
    a2, a3 = Localizer(bundle, cam), Localizer(bundle, cam)
    b = Localizer(other_bundle, cam, EngineConf(ransac_threshold_px=3.0))
    order = np.random.default_rng(5).permutation(len(world.gray))
    got2, got3, b_res = [], [], []
    for i, (f, t) in enumerate(zip(frames, stamps)):
        _disturb(i)
        got2.append(_fingerprint(a2.localize(f, t)))
        if i % 3 == 0:  # (every 3rd / 5th step: each of B's frames is a global matching)
            b_res.append(b.localize(world.gray[order[i % len(order)]], t))
        if i % 5 == 2:
            relocalize(world.gray[order[-1 - i % len(order)]], cam, other_bundle)
        _disturb(1000 + i)
        got3.append(_fingerprint(a3.localize(f, t)))
    assert sum(r.status is not Status.LOST for r in b_res) > 0  # B did work: it posed frames
    assert got2 == alone
    assert got3 == alone


def test_a_relocalization_asked_twice_gives_the_same_answer(world, bundle, cam):
    picks = [3, 31, 58]
    gt = world.gt_cam_from_world
    # a prior a little off the truth: the scoped search and its verification run too
    priors = [Rigid3d(gt[i].rotation, gt[i].translation + [0.04, -0.02, 0.03]) for i in picks]
    first = [_fingerprint(relocalize(world.gray[i], cam, bundle)) for i in picks]
    first_p = [
        _fingerprint(relocalize(world.gray[i], cam, bundle, prior=p)) for i, p in zip(picks, priors)
    ]
    assert sum(f[0] is Status.RELOCALIZED for f in first) >= 2
    # again, in the reverse order, with the generators moved and a session running between
    loc = Localizer(bundle, cam)
    again, again_p = [], []
    for j in reversed(range(len(picks))):
        _disturb(j)
        loc.localize(world.gray[(7 * j) % len(world.gray)], j / 30)
        again.append(_fingerprint(relocalize(world.gray[picks[j]], cam, bundle)))
        again_p.append(_fingerprint(relocalize(world.gray[picks[j]], cam, bundle, prior=priors[j])))
    assert again[::-1] == first
    assert again_p[::-1] == first_p


def test_two_processes_replay_the_same_trajectory_and_covariances(world, tmp_path):
    """``sfmloc replay`` in two processes with different hash seeds (set and dict order of
    strings, anything keyed by ``hash``): byte-identical trajectory and covariance files."""
    synth = world.root / "synth"
    outs = []
    for seed in ("0", "4242"):
        traj = tmp_path / f"traj-{seed}.tum"
        env = dict(os.environ, PYTHONHASHSEED=seed)
        env["PYTHONPATH"] = os.pathsep.join(
            [str(REPO / "service"), str(REPO / "client"), env.get("PYTHONPATH", "")]
        )
        cmd = [sys.executable, "-m", "sfmloc", "replay", str(world.maps_dir / "room")]
        cmd += [str(synth / "video"), "--camera", str(synth / "camera.json")]
        cmd += ["--trajectory", str(traj), "--no-verify", "--max-frames", "30"]
        res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stderr[-2000:]
        cov = Path(str(traj) + ".cov")
        outs.append((traj.read_bytes(), cov.read_bytes()))
    assert outs[0][0].count(b"\n") >= 25  # posed frames written
    assert outs[0] == outs[1]


def test_a_submap_session_without_a_clock_is_repeatable(world, bundle, tmp_path):
    """A sub-map set with room for one part (every switch evicts, loads and re-matches),
    loads in the caller (``background=False``) and no CPU budget on the lost search
    (``submap_search_cpu_ms`` 0): the README's recipe for a sub-map replay without a clock.
    Two sessions, each on its own cache, interleaved with the generators moved, give the
    poses of one alone."""
    from sfmloc.engine.submaps import SubmapLocalizer
    from sfmloc.map.submaps import SubmapSet, split_bundle

    sset = SubmapSet(split_bundle(bundle, tmp_path, "set", parts=3))
    budget = max(sset.part_memory_bytes(k) for k in range(sset.n_parts))
    conf = EngineConf(submap_search_cpu_ms=0.0)
    frames = _stream_a(world)
    stamps = [i / 30 for i in range(len(frames))]

    def session() -> SubmapLocalizer:
        return SubmapLocalizer(
            sset, world.camera_spec, conf, memory_budget=budget, background=False
        )

    one = session()
    alone = [_fingerprint(one.localize(f, t)) for f, t in zip(frames, stamps)]
    assert len(one.stats.parts_used) >= 2 and one.stats.switches >= 1  # it crossed parts
    one.close()
    a, b = session(), session()
    got_a, got_b = [], []
    for i, (f, t) in enumerate(zip(frames, stamps)):
        _disturb(i)
        got_a.append(_fingerprint(a.localize(f, t)))
        got_b.append(_fingerprint(b.localize(f, t)))
    a.close()
    b.close()
    assert got_a == alone
    assert got_b == alone
