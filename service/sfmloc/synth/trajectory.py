"""Camera paths through the room: mapping views and 30 Hz walk / flight / orbit sequences.

World frame: z up, floor at z = 0 (see ``scene``). Poses are returned as ``cam_from_world``
(COLMAP camera: x right, y down, z forward). Angles: *yaw* is the heading of the optical axis
in the floor plane, counter-clockwise from +x; *pitch* lifts it (positive looks up); *roll*
turns the image about the optical axis.

Every moving camera stays on the layout's *track* (``RoomLayout.track``), a band around the
room centre that the furniture keeps clear of, so paths stay inside the room, off the boxes
and away from the walls; ``check_trajectory`` verifies it, and that no view stares at a
surface closer than ``min_view_depth``.

- ``walk``: a person walking a loop around the table at 1.05-1.35 m/s, eyes at ~1.5 m, with
  step bob, sway, and looking around.
- ``flight``: a small quadrotor: smooth loop with speed and altitude changes, holds on a
  heading then turns in fast yaw bursts (peak 95-120 deg/s), roll/pitch from acceleration.
- ``orbit``: a circle around the room centre (radius ``track.orbit_radius``) at 0.6 m/s,
  looking inward (default) or outward.
- ``mapping_views``: stills for building the SfM map: aimed at points on every wall, box,
  floor and ceiling from 1-3.5 m, plus all-around views from the track.

Public API::

    make_trajectory(kind, n_frames, seed, scene=None, fps=30.0) -> list[Rigid3d]
    mapping_views(scene_or_layout, n, seed) -> list[Rigid3d]
    look_at(eye, target, roll=0.0) -> Rigid3d                # cam_from_world
    pose_from_angles(position, yaw, pitch, roll) -> Rigid3d  # cam_from_world
    check_trajectory(layout, poses, ...) -> list[str]          # problems, empty when fine
"""

from __future__ import annotations

import numpy as np

from ..transforms import Rigid3d
from .scene import RoomLayout, Scene, raycast, room_layout

G = 9.81
_SEED_TAGS = {"walk": 11, "flight": 12, "orbit": 13, "mapping": 14}

# Clearances every trajectory keeps (metres).
WALL_CLEARANCE = 0.5
BOX_CLEARANCE = 0.3
MIN_VIEW_DEPTH = 0.5


# --------------------------------------------------------------------------- rotations
def rotation_from_angles(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """``world_from_cam`` rotation of a camera with these angles (radians), z up."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    fwd = np.array([cp * cy, cp * sy, sp])
    right = np.array([sy, -cy, 0.0])  # horizontal: no roll before the roll term
    down = np.cross(fwd, right)
    cr, sr = np.cos(roll), np.sin(roll)
    # Roll about the optical axis: positive turns the image clockwise.
    r2 = cr * right + sr * down
    d2 = -sr * right + cr * down
    return np.column_stack([r2, d2, fwd])


def pose_from_angles(position, yaw: float, pitch: float, roll: float = 0.0) -> Rigid3d:
    """``cam_from_world`` of a camera at ``position`` with these angles (radians)."""
    return Rigid3d(rotation_from_angles(yaw, pitch, roll), position).inverse()


def look_at(eye, target, roll: float = 0.0) -> Rigid3d:
    """``cam_from_world`` of a camera at ``eye`` whose optical axis passes through ``target``."""
    d = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    yaw = float(np.arctan2(d[1], d[0]))
    pitch = float(np.arctan2(d[2], np.hypot(d[0], d[1])))
    return pose_from_angles(eye, yaw, pitch, roll)


# --------------------------------------------------------------------------- helpers
def _smooth(
    rng: np.random.Generator, t: np.ndarray, f_lo: float, f_hi: float, n: int = 4
) -> np.ndarray:
    """A smooth random signal in [-1, 1]: a few sinusoids of frequencies in [f_lo, f_hi] Hz."""
    f = rng.uniform(f_lo, f_hi, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    a = rng.uniform(0.5, 1.0, n)
    s = np.sum(a[:, None] * np.sin(2 * np.pi * f[:, None] * t[None, :] + ph[:, None]), axis=0)
    return s / np.sum(a)


def _periodic(rng: np.random.Generator, kmax: int = 3):
    """A smooth random 2*pi-periodic function in [-1, 1] (harmonics 1..kmax), drawn once."""
    k = np.arange(1, kmax + 1)
    a = rng.uniform(0.3, 1.0, kmax) / k
    ph = rng.uniform(0, 2 * np.pi, kmax)

    def f(theta: np.ndarray) -> np.ndarray:
        theta = np.asarray(theta, np.float64)
        s = np.sum(a[:, None] * np.sin(k[:, None] * theta.reshape(1, -1) + ph[:, None]), axis=0)
        return (s / np.sum(a)).reshape(theta.shape)

    return f


class _Loop:
    """A closed curve ``track.point(theta, rho(theta))`` with an arc-length table."""

    def __init__(self, layout: RoomLayout, rho_fn, direction: float, theta0: float) -> None:
        self.track = layout.track
        self.rho_fn = rho_fn
        self.direction = direction
        self.theta0 = theta0
        th = np.linspace(0.0, 2 * np.pi, 4097)
        p = self.xy(th)
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        self.s_tab = np.r_[0.0, np.cumsum(seg)]
        self.th_tab = th
        self.length = float(self.s_tab[-1])

    def xy(self, theta_rel: np.ndarray) -> np.ndarray:
        th = self.theta0 + self.direction * np.asarray(theta_rel)
        return self.track.point(th, self.rho_fn(th))

    def at(self, s: np.ndarray) -> np.ndarray:
        """Positions (N, 2) at arc lengths ``s`` (any length: the loop repeats)."""
        s = np.asarray(s, np.float64)
        laps, rem = np.divmod(s, self.length)
        th = np.interp(rem, self.s_tab, self.th_tab)
        return self.xy(th)


def _integrate(v: np.ndarray, dt: float) -> np.ndarray:
    """Cumulative integral of samples ``v`` (trapezoid), starting at 0."""
    return np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)]


def _unwrap_heading(d: np.ndarray) -> np.ndarray:
    return np.unwrap(np.arctan2(d[:, 1], d[:, 0]))


def _layout_of(scene: Scene | RoomLayout | None, seed: int) -> RoomLayout:
    if scene is None:
        return room_layout(seed)
    return scene.layout if isinstance(scene, Scene) else scene


# --------------------------------------------------------------------------- trajectories
def walk(layout: RoomLayout, n_frames: int, seed: int, fps: float = 30.0) -> list[Rigid3d]:
    rng = np.random.default_rng([seed, _SEED_TAGS["walk"]])
    t = np.arange(n_frames) / fps
    wobble = _periodic(rng)
    rho_fn = lambda th: 0.93 + 0.11 * wobble(th)  # noqa: E731 - elliptical radius along the loop
    loop = _Loop(layout, rho_fn, float(rng.choice([-1.0, 1.0])), float(rng.uniform(0, 2 * np.pi)))
    speed = 1.2 + 0.12 * _smooth(rng, t, 0.03, 0.15)  # m/s
    s = _integrate(speed, 1 / fps)
    xy = loop.at(s)
    ahead = loop.at(s + 1.5)  # people look where they go, ~1.5 m ahead
    tangent = loop.at(s + 0.05) - xy
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    step_f = speed / 1.4  # two steps of ~0.7 m per stride cycle (Hz of the stride)
    phase = 2 * np.pi * _integrate(step_f, 1 / fps) + rng.uniform(0, 2 * np.pi)
    xy = xy + normal * (0.015 * np.sin(phase))[:, None]  # lateral sway once per stride
    eye = rng.uniform(1.45, 1.6)
    z = eye + 0.02 * np.sin(2 * phase) + 0.02 * _smooth(rng, t, 0.05, 0.2)  # bob twice per stride
    yaw = _unwrap_heading(ahead - xy) + np.radians(18) * _smooth(rng, t, 0.04, 0.12)
    pitch = np.radians(-7 + 5 * _smooth(rng, t, 0.05, 0.25) + 0.4 * np.sin(2 * phase))
    roll = np.radians(1.2 * np.sin(phase) + 0.8 * _smooth(rng, t, 0.1, 0.4))
    P = np.column_stack([xy, z])
    return [pose_from_angles(P[i], yaw[i], pitch[i], roll[i]) for i in range(n_frames)]


def flight(layout: RoomLayout, n_frames: int, seed: int, fps: float = 30.0) -> list[Rigid3d]:
    rng = np.random.default_rng([seed, _SEED_TAGS["flight"]])
    dt = 1 / fps
    t = np.arange(n_frames) * dt
    wobble = _periodic(rng)
    rho_fn = lambda th: 0.91 + 0.17 * wobble(th)  # noqa: E731
    loop = _Loop(layout, rho_fn, float(rng.choice([-1.0, 1.0])), float(rng.uniform(0, 2 * np.pi)))
    # Speed 0.15-1.25 m/s: cruising with slow-downs to near hover.
    speed = 0.7 + 0.55 * _smooth(rng, t, 0.03, 0.12)
    s = _integrate(speed, dt)
    xy = loop.at(s)
    H = layout.size[2]
    z = 1.5 + min(0.65, H / 2 - 0.8) * _smooth(rng, t, 0.03, 0.12)
    P = np.column_stack([xy, z])
    yaw = _flight_yaw(layout, P, rng, fps)
    # Tilt follows acceleration (a quadrotor leans into it): pitch from forward, roll from
    # lateral acceleration in the heading frame; the camera is mounted 8 deg down.
    acc = np.gradient(np.gradient(P, dt, axis=0), dt, axis=0) if n_frames > 2 else np.zeros_like(P)
    fwd = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    left = np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)
    a_fwd, a_left = np.sum(acc[:, :2] * fwd, 1), np.sum(acc[:, :2] * left, 1)
    pitch = np.radians(-8.0) - np.arctan2(a_fwd, G) + np.radians(1.0) * _smooth(rng, t, 0.3, 1.0)
    roll = np.arctan2(a_left, G) + np.radians(1.0) * _smooth(rng, t, 0.3, 1.0)
    return [pose_from_angles(P[i], yaw[i], pitch[i], roll[i]) for i in range(n_frames)]


def _free_distance(layout: RoomLayout, P: np.ndarray, yaw: float) -> float:
    """Smallest distance to a surface straight ahead (level) from any of the positions."""
    d = np.tile([np.cos(yaw), np.sin(yaw), 0.0], (len(P), 1))
    dist, _ = raycast(layout, P, d)
    return float(np.min(dist))


def _flight_yaw(
    layout: RoomLayout, P: np.ndarray, rng: np.random.Generator, fps: float
) -> np.ndarray:
    """Hold a heading with slow drift, then turn in a burst with a raised-cosine rate profile.

    Each new heading is chosen so the camera sees at least ~1.6 m of free space ahead over
    the next hold, and bursts turn 70-180 deg at a peak rate of 95-120 deg/s.
    """
    n = len(P)
    yaw = np.zeros(n)
    cur = float(np.arctan2(*(np.r_[layout.track.center] - P[0, :2])[::-1]))  # face the room centre
    i = 0
    while i < n:
        hold = int(rng.uniform(0.8, 2.5) * fps)
        drift = np.radians(8.0) * _smooth(rng, np.arange(hold) / fps, 0.1, 0.3)
        drift -= drift[0]  # continuous with the end of the last burst
        yaw[i : i + hold] = cur + drift[: max(0, min(hold, n - i))]
        i += hold
        if i >= n:
            break
        cur += drift[-1]
        # Next heading: a burst of 70-180 deg either way, towards open space.
        cands = [cur + sgn * np.radians(d) for sgn in (1, -1) for d in range(70, 181, 10)]
        seg = P[i : min(n, i + int(4 * fps))]
        free = np.array([_free_distance(layout, seg, c) for c in cands])
        good = np.flatnonzero(free >= 1.6)
        pick = int(rng.choice(good)) if len(good) else int(np.argmax(free))
        target = cands[pick]
        peak = np.radians(rng.uniform(95, 120))
        delta = target - cur
        T = 2 * abs(delta) / peak  # raised cosine: mean rate = peak / 2
        m = max(2, int(round(T * fps)))
        tau = np.arange(1, m + 1) / m
        prof = tau - np.sin(2 * np.pi * tau) / (2 * np.pi)  # integral of (1 - cos), 0 -> 1
        k = min(m, n - i)
        yaw[i : i + k] = cur + delta * prof[:k]
        i += m
        cur = target
    return yaw


def orbit(
    layout: RoomLayout, n_frames: int, seed: int, fps: float = 30.0, look: str = "inward"
) -> list[Rigid3d]:
    if look not in ("inward", "outward"):
        raise ValueError(f"orbit look must be 'inward' or 'outward', got {look!r}")
    rng = np.random.default_rng([seed, _SEED_TAGS["orbit"]])
    t = np.arange(n_frames) / fps
    R = layout.track.orbit_radius
    c = np.asarray(layout.track.center)
    direction = float(rng.choice([-1.0, 1.0]))
    phi = rng.uniform(0, 2 * np.pi) + direction * 0.6 / R * t  # 0.6 m/s
    xy = c + R * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    z = 1.45 + 0.1 * _smooth(rng, t, 0.03, 0.1)
    yaw = phi + (np.pi if look == "inward" else 0.0)
    pitch = np.radians(-12.0 if look == "inward" else -4.0) * np.ones(n_frames)
    return [
        pose_from_angles([xy[i, 0], xy[i, 1], z[i]], yaw[i], pitch[i], 0.0) for i in range(n_frames)
    ]


def make_trajectory(
    kind: str,
    n_frames: int,
    seed: int = 0,
    scene: Scene | RoomLayout | None = None,
    fps: float = 30.0,
    **kwargs,
) -> list[Rigid3d]:
    """``cam_from_world`` of ``n_frames`` frames at ``fps`` of a ``walk``, ``flight`` or ``orbit``.

    ``scene`` (a ``Scene`` or its ``RoomLayout``) defaults to the room of ``seed``; an orbit
    takes ``look="inward"`` (default) or ``"outward"``.
    """
    layout = _layout_of(scene, seed)
    if n_frames < 1:
        raise ValueError("n_frames must be at least 1")
    if kind == "walk":
        return walk(layout, n_frames, seed, fps)
    if kind == "flight":
        return flight(layout, n_frames, seed, fps)
    if kind == "orbit":
        return orbit(layout, n_frames, seed, fps, **kwargs)
    raise ValueError(f"unknown trajectory {kind!r}; choose walk, flight or orbit")


# --------------------------------------------------------------------------- mapping views
def mapping_views(scene: Scene | RoomLayout, n: int, seed: int = 0) -> list[Rigid3d]:
    """``n`` still views for the SfM map: half aimed at surface points, half from the track.

    Aimed views pick a face (weighted by area, small furniture faces boosted), a point on it
    and a camera 1-3.5 m in front of it within 55 deg of its normal; track views stand on the
    walking band and look in evenly spread directions. Every view passes ``check_trajectory``
    and sees its target (aimed views).
    """
    layout = _layout_of(scene, seed)
    rng = np.random.default_rng([seed, _SEED_TAGS["mapping"]])
    L, W, H = layout.size
    quads = layout.quads
    area = np.array([np.linalg.norm(q.u_axis) * np.linalg.norm(q.v_axis) for q in quads])
    is_box = np.array([q.recipe[:1] == ("box",) for q in quads])
    weight = np.where(is_box, np.maximum(area, 0.3) * 3.0, area)
    # Floor and ceiling are large but less useful to a camera that mostly looks ahead.
    weight[[i for i, q in enumerate(quads) if q.recipe[:1] == ("floor",)]] *= 0.25
    weight[[i for i, q in enumerate(quads) if q.recipe[:1] == ("ceiling",)]] *= 0.1
    # Faces no camera can see well: downward faces (table bottom) and faces against a wall.
    for i, q in enumerate(quads):
        if q.normal[2] < -0.5 and q.recipe[0] != "ceiling":
            weight[i] = 0
        if q.recipe[:1] == ("box",) and q.normal[2] == 0:
            c = q.origin + 0.5 * (q.u_axis + q.v_axis)
            probe = c[:2] + 0.6 * q.normal[:2]
            if layout.wall_distance(probe[None])[0] < 0.45:
                weight[i] = 0
    weight /= weight.sum()
    n_aimed = n // 2
    poses: list[Rigid3d] = []
    tries = 0
    while len(poses) < n_aimed and tries < 50 * n:
        tries += 1
        qi = int(rng.choice(len(quads), p=weight))
        q = quads[qi]
        a, b = rng.uniform(0.15, 0.85, 2)
        target = q.origin + a * q.u_axis + b * q.v_axis
        if q.recipe[0] == "wall" and not 0.3 <= target[2] <= 2.6:
            continue
        dist = rng.uniform(1.0, 3.5)
        # Direction from the target towards the camera: within 55 deg of the normal.
        n_ = q.normal
        tmp = np.array([0.0, 0.0, 1.0]) if abs(n_[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        e1 = np.cross(n_, tmp)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n_, e1)
        ang = np.radians(rng.uniform(0, 55))
        az = rng.uniform(0, 2 * np.pi)
        d = np.cos(ang) * n_ + np.sin(ang) * (np.cos(az) * e1 + np.sin(az) * e2)
        eye = target + dist * d
        if not 0.5 <= eye[2] <= min(2.3, H - 0.4):
            continue
        pose = look_at(eye, target, np.radians(rng.uniform(-5, 5)))
        if check_trajectory(layout, [pose], min_view_depth=0.8):
            continue
        # The target must be what the camera sees.
        t_hit, f_hit = raycast(
            layout, eye[None], (target - eye)[None] / np.linalg.norm(target - eye)
        )
        if f_hit[0] != qi:
            continue
        poses.append(pose)
    tries = 0
    track = layout.track
    n_track = n - len(poses)
    yaws = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n_track) / max(1, n_track) * 7.0 / 3.0
    k = 0
    while k < n_track and tries < 50 * n:
        tries += 1
        th = rng.uniform(0, 2 * np.pi)
        xy = track.point(th, rng.uniform(0.65, 1.08))
        eye = np.array([xy[0], xy[1], rng.uniform(1.0, 1.9)])
        pose = pose_from_angles(
            eye,
            yaws[k] + rng.uniform(-0.2, 0.2),
            np.radians(rng.uniform(-22, 8)),
            np.radians(rng.uniform(-4, 4)),
        )
        if check_trajectory(layout, [pose], min_view_depth=0.8):
            continue
        poses.append(pose)
        k += 1
    if len(poses) < n:
        raise RuntimeError(f"could only place {len(poses)} of {n} mapping views")
    # Interleave aimed and track views so a prefix is a usable smaller map.
    aimed, ring = poses[:n_aimed], poses[n_aimed:]
    out: list[Rigid3d] = []
    for i in range(max(len(aimed), len(ring))):
        out += aimed[i : i + 1] + ring[i : i + 1]
    return out


# --------------------------------------------------------------------------- checks
def view_depth(layout: RoomLayout | Scene, poses: list[Rigid3d]) -> np.ndarray:
    """Distance (m) along each optical axis to the first surface."""
    layout = layout.layout if isinstance(layout, Scene) else layout
    C = np.stack([p.center for p in poses])
    d = np.stack([p.rotation[2] for p in poses])  # optical axis in world = third row of R
    dist, _ = raycast(layout, C, d)
    return dist


def check_trajectory(
    layout: RoomLayout | Scene,
    poses: list[Rigid3d],
    wall_clearance: float = WALL_CLEARANCE,
    box_clearance: float = BOX_CLEARANCE,
    min_view_depth: float = MIN_VIEW_DEPTH,
) -> list[str]:
    """Problems of a list of ``cam_from_world`` poses (empty when all is fine)."""
    layout = layout.layout if isinstance(layout, Scene) else layout
    C = np.stack([p.center for p in poses])
    L, W, H = layout.size
    out = []
    wd = layout.wall_distance(C[:, :2])
    if wd.min() < wall_clearance:
        out.append(f"frame {int(wd.argmin())} is {wd.min():.2f} m from a wall")
    if C[:, 2].min() < 0.3 or C[:, 2].max() > H - 0.3:
        out.append("camera height leaves [0.3, H - 0.3]")
    # Boxes are checked in 3D: a camera may be above a low box only with clearance too.
    for b in layout.boxes:
        bd = b.distance_xy(C[:, :2])
        below_top = C[:, 2] < b.z1 + box_clearance
        bad = (bd < box_clearance) & below_top
        if bad.any():
            out.append(
                f"frame {int(np.flatnonzero(bad)[0])} is within {box_clearance} m of {b.name}"
            )
    vd = view_depth(layout, poses)
    if vd.min() < min_view_depth:
        out.append(f"frame {int(vd.argmin())} looks at a surface {vd.min():.2f} m away")
    return out
