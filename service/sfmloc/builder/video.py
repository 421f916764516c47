"""Video in: decode a video, choose keyframes, and build a map from them.

A drone or phone user has a video (and maybe a pose log), not an image folder. This module
turns the video into keyframes and feeds them to the existing pipelines (``build.main``):

1. **Analysis pass** (bounded memory: one frame at a time). Each frame is decoded with OpenCV
   (``cv2.VideoCapture``) and gets a **time**: the container's presentation time
   (``CAP_PROP_POS_MSEC``, which follows variable frame rates) when the backend reports
   increasing times, else ``index / CAP_PROP_FPS``; the TUM pose log must be on this clock
   (first frame at 0 s). On a copy scaled to at most ``analysis_width`` pixels wide it gets a
   **sharpness** (variance of the Laplacian) and an **image motion**: corners
   (``goodFeaturesToTrack``) tracked from frame to frame by pyramidal Lucas-Kanade, the median
   displacement as a fraction of the image diagonal. With poses, tracks followed over
   ``depth_segment`` frames are triangulated with the known poses to estimate the **scene
   depth** (median camera-to-point depth, as ``MapBundle.scene_scale``).
2. **Selection**. A frame needs enough motion since the last keyframe: with poses, a rotation
   of ``min_rotation_deg`` or a camera translation of ``min_translation`` times the scene
   depth (scale-free); without poses (or when no depth could be estimated), accumulated
   image motion of ``min_flow`` of the image diagonal. When a frame has enough motion, the
   sharpest of it and the next ``sharpness_window - 1`` frames becomes the keyframe (the
   blurrier neighbours are dropped). With poses, a frame ``max_interval_s`` after the last
   keyframe has enough motion whatever its motion (a dwelling camera still gets keyframes;
   images only, a still video stays one keyframe, a clear error). The first
   keyframe is the sharpest of the first window.
3. **Write pass**: the keyframes are decoded again and written as PNG (lossless) to a
   temporary folder, with their poses (TUM interpolated to the keyframe's time: slerp of the
   rotation, lerp of the camera centre, between poses at most ``max_pose_gap_s`` apart) as a
   COLMAP list; the build runs on that folder, which is removed afterwards.

The choice is reported (``KeyframeReport``): frames decoded, keyframes, and why the other
frames were dropped (no pose at their time, too little motion, blurrier than a neighbour).
"""

from __future__ import annotations

import bisect
import logging
import math
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import Field

from ..cameras import Camera
from ..config import StrictModel
from ..errors import BuildCancelled, BuildError, ImageDecodeError, InputError
from ..io.poses import PoseList, read_poses, write_colmap_list
from ..transforms import Rigid3d, rotation_angle_deg

log = logging.getLogger(__name__)


class VideoConf(StrictModel):
    # Posed: a keyframe after this much rotation or translation (relative to the scene depth)
    # since the last one. On redkitchen (30 Hz, handheld) 5 deg / 5% of the depth keep about
    # one frame in ten, the spacing of the every-10th folder map. These three are refused below
    # 0 (a negative threshold silently meant 0: every frame has enough motion).
    min_rotation_deg: float = Field(5.0, ge=0)
    min_translation: float = Field(0.05, ge=0)
    # Images only (or no depth estimate): accumulated median corner motion, of the diagonal.
    min_flow: float = Field(0.05, ge=0)
    # Posed: ... or after this long without one (0: motion only). A camera that dwells (slow motion,
    # a look around one spot) gets keyframes there too: that is where most of the frames a
    # tracker will see are taken. Redkitchen, 1,000 frames as MJPG with their poses, replay of
    # the 1,000 frames (median error; every 10th frame as a folder map: 0.279 cm, the frames
    # 5, 15, ...: 0.264 cm): motion only 73 keyframes 0.307 cm, at 3.5 deg / 3.5% 95
    # keyframes 0.310 cm (so not the count alone); with 0.33 s 87 keyframes 0.311 cm; with
    # 0.2 s 116 keyframes 0.263 cm (17,952 points; 100% localized, 0 wrong, 40/40
    # relocalized). Not the decoding: every 10th frame decoded from the video, 0.275 cm; the
    # original JPEGs of the 73 motion keyframes, 0.317 cm.
    max_interval_s: float = Field(0.2, ge=0)  # refused below 0 (it would silently mean off)
    # frames: the sharpest of a trigger frame and the next ones (refused below 1: 0 or less
    # silently meant 1)
    sharpness_window: int = Field(5, ge=1)
    max_pose_gap_s: float = 0.2  # interpolate only between poses at most this far apart
    max_time_diff_s: float = 0.02  # frames this close beyond the log's ends take its end pose
    analysis_width: int = 640  # px: motion and sharpness on a copy at most this wide
    max_corners: int = 300
    depth_segment: int = 10  # frames a track set is followed before triangulating it
    min_parallax_deg: float = 1.0  # tracks triangulated with less parallax are ignored


@dataclass
class KeyframeReport:
    frames: int = 0  # decoded
    keyframes: int = 0
    dropped_no_pose: int = 0  # no pose at the frame's time (outside the log or in a gap)
    dropped_motion: int = 0  # too little motion since the last keyframe
    dropped_blur: int = 0  # a sharper neighbour was chosen
    clock: str = "pos_msec"  # or "index/fps"
    fps: float = 0.0
    scene_depth: float | None = None  # posed: the estimated median depth, in pose units
    keyframe_indices: list[int] = field(default_factory=list)

    def summary(self) -> str:
        depth = f", scene depth {self.scene_depth:.3g}" if self.scene_depth else ""
        return (
            f"{self.keyframes} keyframes of {self.frames} frames ({self.clock} clock{depth}); "
            f"dropped: {self.dropped_motion} too little motion, {self.dropped_blur} blurrier "
            f"than a neighbour, {self.dropped_no_pose} without a pose"
        )

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d.pop("keyframe_indices")
        return d


@dataclass
class FrameStats:
    times: np.ndarray  # (N,) seconds
    sharpness: np.ndarray  # (N,) variance of the Laplacian
    flow: np.ndarray  # (N,) median displacement from the previous frame, of the diagonal
    clock: str
    fps: float
    scene_depth: float | None


# --------------------------------------------------------------------------- poses in time
def interpolate_pose(
    times: np.ndarray,
    world_from_cams: list[Rigid3d],
    t: float,
    max_gap_s: float,
    max_time_diff_s: float,
) -> Rigid3d | None:
    """``cam_from_world`` at time ``t`` from a sorted pose log, or None when ``t`` is outside
    it or in a gap wider than ``max_gap_s``. Slerp of the rotation, lerp of the centre."""
    n = len(times)
    j = bisect.bisect_left(times, t)
    if j < n and abs(times[j] - t) <= 1e-9:
        return world_from_cams[j].inverse()
    if j == 0 or j == n:
        k = 0 if j == 0 else n - 1
        return world_from_cams[k].inverse() if abs(times[k] - t) <= max_time_diff_s else None
    t0, t1 = times[j - 1], times[j]
    if t1 - t0 > max_gap_s:
        return None
    a = (t - t0) / (t1 - t0)
    A, B = world_from_cams[j - 1], world_from_cams[j]
    q = _slerp(A.quat_wxyz, B.quat_wxyz, a)
    c = (1 - a) * A.translation + a * B.translation
    return Rigid3d.from_quat_wxyz(q, c).inverse()


def _slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = float(q0 @ q1)
    if d < 0:  # the shorter arc
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    th = math.acos(d)
    return (math.sin((1 - a) * th) * q0 + math.sin(a * th) * q1) / math.sin(th)


def read_pose_log(path: str | Path) -> tuple[np.ndarray, list[Rigid3d]]:
    """A TUM pose log sorted by time: (times, world_from_cam)."""
    poses: PoseList = read_poses(path)
    if poses.format != "tum":
        raise InputError(
            "with --video, --poses must be a TUM file 'timestamp tx ty tz qx qy qz qw' on the "
            f"video's clock (first frame at 0 s); {path} looks like a COLMAP list"
        )
    entries = sorted(poses.entries, key=lambda e: e.stamp)
    return np.array([e.stamp for e in entries]), [e.world_from_cam for e in entries]


# --------------------------------------------------------------------------- decoding
def open_video(path: str | Path) -> cv2.VideoCapture:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"video {path} does not exist")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise ImageDecodeError(
            f"video {path} cannot be opened by OpenCV (no video backend reads it)"
        )
    return cap


def iter_frames(path: str | Path):
    """(index, position in ms from the container, BGR frame) for every decodable frame."""
    cap = open_video(path)
    try:
        i = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            yield i, float(cap.get(cv2.CAP_PROP_POS_MSEC)), frame
            i += 1
    finally:
        cap.release()


def video_fps(path: str | Path) -> float:
    cap = open_video(path)
    try:
        return float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()


def _sharpness(gray: np.ndarray) -> float:
    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def analyze_video(
    path: str | Path,
    conf: VideoConf,
    cam_from_world_at: Any = None,
    camera: Camera | None = None,
    progress: Any = None,
    should_cancel: Any = None,
) -> FrameStats:
    """The analysis pass (module docstring, step 1). ``cam_from_world_at(t)`` gives a frame's
    pose (or None) when there are poses; ``camera`` is then needed for the depth estimate."""
    fps = video_fps(path)
    pos_ms: list[float] = []
    sharp: list[float] = []
    flow: list[float] = []
    depths: list[float] = []
    prev: np.ndarray | None = None
    pts: np.ndarray | None = None  # tracked corners in the previous frame (analysis pixels)
    anchor_pts: np.ndarray | None = None  # the same tracks where the segment started
    anchor_i = 0
    anchor_count = 0
    increasing = True  # container times so far strictly increasing (the clock, see _clock)
    times: list[float] = []
    scale = 1.0
    diag = 1.0
    n_est = None
    # Corners are in OpenCV pixels of the scaled copy; (p + 0.5) / scale is COLMAP's convention.
    for i, ms, frame in iter_frames(path):
        if should_cancel and should_cancel():
            raise BuildCancelled("cancelled", stage="video")
        if i == 0:
            h, w = frame.shape[:2]
            scale = min(1.0, conf.analysis_width / w)
            diag = math.hypot(w * scale, h * scale)
            cap = cv2.VideoCapture(str(path))
            n_est = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            cap.release()
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
        if scale < 1.0:
            gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        increasing = increasing and (not pos_ms or ms > pos_ms[-1])
        pos_ms.append(ms)
        times.append(ms / 1000.0 if increasing or fps <= 0 else i / fps)
        sharp.append(_sharpness(gray))
        step = 0.0
        if prev is not None and pts is not None and anchor_pts is not None and len(pts) > 0:
            # nextPts is only an output here (no OPTFLOW_USE_INITIAL_FLOW): its values are unused.
            nxt, st, _ = cv2.calcOpticalFlowPyrLK(
                prev, gray, pts, np.empty_like(pts), winSize=(21, 21), maxLevel=3
            )
            ok = st.ravel() == 1
            if ok.sum() >= 8:
                step = float(np.median(np.linalg.norm(nxt[ok] - pts[ok], axis=-1))) / diag
                pts, anchor_pts = nxt[ok], anchor_pts[ok]
            else:
                step = math.inf  # a cut or a textureless view: motion unknown, count it large
                pts = None
        elif prev is not None:
            step = math.inf
        flow.append(step)
        # Segment end: triangulate the tracks with the known poses; restart the tracks.
        seg_end = pts is None or i - anchor_i >= conf.depth_segment or 2 * len(pts) < anchor_count
        if seg_end:
            if (
                cam_from_world_at is not None
                and camera is not None
                and pts is not None
                and anchor_pts is not None
                and i > anchor_i
            ):
                d = _segment_depth(
                    (anchor_pts + 0.5) / scale,
                    (pts + 0.5) / scale,
                    times[anchor_i],
                    times[i],
                    cam_from_world_at,
                    camera,
                    conf.min_parallax_deg,
                )
                if d is not None:
                    depths.append(d)
            c = cv2.goodFeaturesToTrack(gray, conf.max_corners, 0.01, 8)
            pts = c.astype(np.float32) if c is not None else None
            anchor_pts = pts.copy() if pts is not None else None
            anchor_count = len(pts) if pts is not None else 0
            anchor_i = i
        prev = gray
        if progress and (i % 30 == 0):
            frac = min(0.99, (i + 1) / n_est) if n_est else 0.0
            of = f" of {n_est}" if n_est else ""
            progress("video", 0.5 * frac, f"analysing frame {i + 1}{of}")
    if not pos_ms:
        raise ImageDecodeError(f"video {path}: no frame could be decoded")
    frame_times, clock = _clock(np.array(pos_ms) / 1000.0, fps)
    depth = float(np.median(depths)) if depths else None
    return FrameStats(frame_times, np.array(sharp), np.array(flow), clock, fps, depth)


def _clock(pos_s: np.ndarray, fps: float) -> tuple[np.ndarray, str]:
    """Container times when they increase strictly, else index / fps."""
    if len(pos_s) == 1 or np.all(np.diff(pos_s) > 0) or fps <= 0:
        if len(pos_s) > 1 and not np.all(np.diff(pos_s) > 0):
            raise ImageDecodeError(
                "the video reports neither increasing frame times nor a frame rate"
            )
        return pos_s, "pos_msec"
    return np.arange(len(pos_s)) / fps, "index/fps"


def _segment_depth(
    uv0: np.ndarray,
    uv1: np.ndarray,
    t0: float,
    t1: float,
    pose_at: Any,
    camera: Camera,
    min_parallax_deg: float,
) -> float | None:
    """Median depth (in the first camera) of tracks triangulated with the known poses."""
    P0, P1 = pose_at(t0), pose_at(t1)
    if P0 is None or P1 is None:
        return None
    x0 = camera.cam_from_img(uv0.reshape(-1, 2))
    x1 = camera.cam_from_img(uv1.reshape(-1, 2))
    X = cv2.triangulatePoints(P0.matrix(), P1.matrix(), x0.T, x1.T)
    w = X[3]
    good = np.abs(w) > 1e-12
    X = (X[:3, good] / w[good]).T
    if len(X) < 8:
        return None
    z0 = P0.apply(X)[:, 2]
    z1 = P1.apply(X)[:, 2]
    r0 = X - P0.center
    r1 = X - P1.center
    norms = np.linalg.norm(r0, axis=1) * np.linalg.norm(r1, axis=1)
    cosang = np.sum(r0 * r1, axis=1) / np.maximum(norms, 1e-12)
    parallax = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    ok = (z0 > 0) & (z1 > 0) & (parallax >= min_parallax_deg)
    if ok.sum() < 8:
        return None
    return float(np.median(z0[ok]))


# --------------------------------------------------------------------------- selection
def select_keyframes(
    stats: FrameStats, conf: VideoConf, poses: list[Rigid3d | None] | None = None
) -> tuple[list[int], KeyframeReport]:
    """Keyframe indices (module docstring, step 2) and the report."""
    n = len(stats.times)
    rep = KeyframeReport(frames=n, clock=stats.clock, fps=stats.fps, scene_depth=stats.scene_depth)
    valid = np.ones(n, bool) if poses is None else np.array([p is not None for p in poses])
    rep.dropped_no_pose = int((~valid).sum())
    w = max(1, conf.sharpness_window)
    depth = stats.scene_depth

    def sharpest(start: int) -> int:
        # start itself is valid (both callers check), so there is a candidate
        cand = [j for j in range(start, min(n, start + w)) if valid[j]]
        return max(cand, key=lambda j: stats.sharpness[j])

    def enough_motion(k: int, i: int) -> bool:
        if poses is not None and depth is not None:
            if conf.max_interval_s > 0 and stats.times[i] - stats.times[k] >= conf.max_interval_s:
                return True
            A, B = poses[k], poses[i]
            assert A is not None and B is not None  # keyframes are valid[], i.e. posed frames
            if rotation_angle_deg(A.rotation, B.rotation) >= conf.min_rotation_deg:
                return True
            moved = float(np.linalg.norm(A.center - B.center))
            return moved >= conf.min_translation * depth
        return float(np.sum(stats.flow[k + 1 : i + 1])) >= conf.min_flow

    keys: list[int] = []
    first = next((j for j in range(n) if valid[j]), None)
    if first is not None:
        keys.append(sharpest(first))
        rep.dropped_blur += sum(1 for j in range(first, keys[0]) if valid[j])
    i = keys[0] + 1 if keys else n
    while i < n:
        if valid[i] and enough_motion(keys[-1], i):
            j = sharpest(i)
            rep.dropped_blur += sum(1 for m in range(i, j) if valid[m])
            keys.append(j)
            i = j + 1
        else:
            i += 1
    rep.keyframes = len(keys)
    rep.keyframe_indices = keys
    rep.dropped_motion = n - rep.keyframes - rep.dropped_no_pose - rep.dropped_blur
    return keys, rep


# --------------------------------------------------------------------------- extraction
@dataclass
class VideoKeyframes:
    image_dir: Path
    poses_file: Path | None
    report: KeyframeReport


def extract_keyframes(
    video: str | Path,
    out_dir: str | Path,
    conf: VideoConf | None = None,
    poses: str | Path | None = None,
    camera: Camera | None = None,
    progress: Any = None,
    should_cancel: Any = None,
) -> VideoKeyframes:
    """Analyse ``video``, choose keyframes and write them to ``out_dir/images`` (PNG, named
    ``frame-NNNNNN.png`` by frame index), with ``out_dir/poses.txt`` (COLMAP list,
    cam_from_world) when ``poses`` (TUM, world_from_cam) is given."""
    conf = conf or VideoConf()
    out_dir = Path(out_dir)
    pose_at = None
    if poses is not None:
        if camera is None:
            raise InputError(
                "--video with --poses needs --camera (camera.json or 'PINHOLE w h fx fy cx cy')"
            )
        ptimes, world_from_cams = read_pose_log(poses)

        def pose_at(t: float) -> Rigid3d | None:
            return interpolate_pose(
                ptimes, world_from_cams, t, conf.max_pose_gap_s, conf.max_time_diff_s
            )

    stats = analyze_video(video, conf, pose_at, camera, progress, should_cancel)
    frame_poses = [pose_at(float(t)) for t in stats.times] if pose_at is not None else None
    if frame_poses is not None and not any(p is not None for p in frame_poses):
        raise InputError(
            f"no frame of {video} ({stats.times[0]:.3f}-{stats.times[-1]:.3f} s, {stats.clock} "
            f"clock) has a pose in {poses} ({ptimes[0]:.3f}-{ptimes[-1]:.3f} s): the pose log "
            "must be on the video's clock"
        )
    keys, rep = select_keyframes(stats, conf, frame_poses)
    if len(keys) < 2:
        raise BuildError(
            f"video {video}: only {len(keys)} keyframe(s): {rep.summary()}", stage="video"
        )
    image_dir = out_dir / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    wanted = set(keys)
    names, written = [], 0
    for i, _, frame in iter_frames(video):
        if should_cancel and should_cancel():
            raise BuildCancelled("cancelled", stage="video")
        if i in wanted:
            name = f"frame-{i:06d}.png"
            size = (frame.shape[1], frame.shape[0])
            if camera is not None and size != (camera.width, camera.height):
                raise ImageDecodeError(
                    f"video {video} is {frame.shape[1]}x{frame.shape[0]}, the camera says "
                    f"{camera.width}x{camera.height}"
                )
            if not cv2.imwrite(str(image_dir / name), frame):
                raise BuildError(f"cannot write keyframe {image_dir / name}", stage="video")
            names.append(name)
            written += 1
            if progress:
                progress("video", 0.5 + 0.5 * written / len(keys), f"keyframe {name}")
        if i >= keys[-1]:
            break
    if written != len(keys):
        raise ImageDecodeError(
            f"video {video} decoded differently the second time "
            f"({written} of {len(keys)} keyframes)"
        )
    poses_file = None
    if frame_poses is not None:
        poses_file = out_dir / "poses.txt"
        key_poses = [p for i in keys if (p := frame_poses[i]) is not None]
        assert len(key_poses) == len(keys)  # select_keyframes keeps posed frames only
        write_colmap_list(poses_file, names, key_poses)
    log.info("video %s: %s", video, rep.summary())
    if progress:
        progress("video", 1.0, rep.summary())
    return VideoKeyframes(image_dir, poses_file, rep)


def build_from_video(
    conf: Any,
    name: str,
    out_dir: str | Path,
    *,
    video: str | Path,
    poses: str | Path | None = None,
    camera: str | Camera | None = None,
    video_conf: VideoConf | None = None,
    sfm_conf: Any = None,
    workdir: str | Path | None = None,
    progress: Any = None,
    should_cancel: Any = None,
) -> Path:
    """Keyframes of ``video`` (with TUM ``poses`` on its clock, or none for SfM) -> the bundle
    ``out_dir/name`` via ``build.main``; the keyframe folder is removed afterwards."""
    from .build import main

    cam = Camera.parse(camera) if isinstance(camera, (str, Path)) else camera
    if workdir is not None:
        Path(workdir).mkdir(parents=True, exist_ok=True)
    parent = None if workdir is None else str(workdir)
    tmp = Path(tempfile.mkdtemp(prefix="sfmloc-video-", dir=parent))
    try:
        kf = extract_keyframes(video, tmp, video_conf, poses, cam, progress, should_cancel)
        source = {"kind": "video", "video": str(video), "keyframes": kf.report.to_dict()}
        if poses is not None:
            source["poses"] = str(poses)
        return main(
            conf,
            name,
            out_dir,
            images=kf.image_dir,
            poses=kf.poses_file,
            camera=cam,
            sfm_conf=sfm_conf,
            workdir=workdir,
            progress=progress,
            should_cancel=should_cancel,
            source_extra=source,
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
