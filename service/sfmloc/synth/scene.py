"""The synthetic ``room`` scene: planar textured quads and exact 3D points at texture corners.

World frame (metres): **z up**, the floor is ``z = 0``, the room spans
``[0, L] x [0, W] x [0, H]`` (default 8 x 5 x 3) with one floor corner at the origin.
Cameras follow COLMAP: x right, y down, z forward.

Every surface is a ``Face``: a rectangle ``origin + s/Ws * u_axis + t/Ht * v_axis`` for texel
corner coordinates ``(s, t)`` in ``[0, Ws] x [0, Ht]`` of its ``Ws x Ht`` texture (s to the
right and t downwards when the face is seen from its visible side, which ``normal`` points
to). Boxes (furniture) are oriented boxes on the floor, on other boxes, or on legs (the
table). ``Scene.features`` are the verified texture corners lifted to 3D: exact scene points
whose images are true corners.

Public API::

    scene = Scene.room(seed)                   # deterministic for a seed
    scene.faces, scene.features, scene.layout  # geometry, 3D points, boxes and free track
    raycast(scene, origins, dirs)              # first hit (distance, face index) per ray

A camera moving through the room stays on the *track*: an elliptical band around the room
centre that the layout keeps free of furniture (``RoomLayout.track``); trajectories use it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from . import textures as tx
from .config import SceneConf

# Light direction for the constant per-face shading (from above, slightly off-axis).
_LIGHT = np.array([0.35, 0.25, 1.0]) / np.linalg.norm([0.35, 0.25, 1.0])


# --------------------------------------------------------------------------- faces
@dataclass
class Quad:
    """A planar rectangle ``origin + a * u_axis + b * v_axis``, ``a, b`` in [0, 1].

    ``normal`` (``v_axis x u_axis``, normalized) points to the visible side; seen from there,
    ``u_axis`` goes right and ``v_axis`` down. ``recipe`` names what to texture it with.
    """

    index: int
    name: str
    origin: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray
    recipe: tuple = ()
    normal: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, np.float64)
        self.u_axis = np.asarray(self.u_axis, np.float64)
        self.v_axis = np.asarray(self.v_axis, np.float64)
        n = np.cross(self.v_axis, self.u_axis)
        self.normal = n / np.linalg.norm(n)

    @property
    def plane_d(self) -> float:
        """``normal . X = plane_d`` on the quad's plane."""
        return float(self.normal @ self.origin)

    @property
    def corners(self) -> np.ndarray:
        """(4, 3) corners: origin, +u, +u+v, +v."""
        o, u, v = self.origin, self.u_axis, self.v_axis
        return np.stack([o, o + u, o + u + v, o + v])


@dataclass
class Face(Quad):
    """A textured quad. Texel-corner coordinates ``(s, t)`` in ``[0, Ws] x [0, Ht]`` map to
    ``origin + s/Ws * u_axis + t/Ht * v_axis``."""

    texture: np.ndarray = field(
        default_factory=lambda: np.zeros((1, 1, 3), np.uint8)
    )  # BGR, unshaded
    shade: float = 1.0

    @property
    def tex_size(self) -> tuple[int, int]:
        """Texture ``(width, height)`` in texels."""
        return self.texture.shape[1], self.texture.shape[0]

    @property
    def texel_size(self) -> tuple[float, float]:
        w, h = self.tex_size
        return float(np.linalg.norm(self.u_axis)) / w, float(np.linalg.norm(self.v_axis)) / h

    def world_from_tex(self, st: np.ndarray) -> np.ndarray:
        """World points (N, 3) of texel-corner coordinates (N, 2)."""
        st = np.asarray(st, np.float64).reshape(-1, 2)
        w, h = self.tex_size
        return self.origin + (st[:, :1] / w) * self.u_axis + (st[:, 1:2] / h) * self.v_axis

    def tex_from_world(self, X: np.ndarray) -> np.ndarray:
        """Texel-corner coordinates (N, 2) of world points on the face's plane."""
        X = np.asarray(X, np.float64).reshape(-1, 3) - self.origin
        w, h = self.tex_size
        s = X @ self.u_axis / (self.u_axis @ self.u_axis) * w
        t = X @ self.v_axis / (self.v_axis @ self.v_axis) * h
        return np.stack([s, t], axis=1)


def vertical_face(
    center_xy, normal_xy, width: float, z0: float, z1: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin, u, v) of an upright rectangle seen from the ``normal_xy`` side, t downwards."""
    n = np.array([normal_xy[0], normal_xy[1], 0.0])
    n /= np.linalg.norm(n)
    right = np.array([-n[1], n[0], 0.0])  # camera right when looking along -n with z up
    origin = np.array([center_xy[0], center_xy[1], z1]) - 0.5 * width * right
    return origin, width * right, np.array([0.0, 0.0, -(z1 - z0)])


# --------------------------------------------------------------------------- layout
@dataclass(frozen=True)
class Box:
    """An oriented box: footprint centre, extents along its local axes, yaw, bottom height.

    Local +y is the *front* (for furniture against a wall it points into the room).
    """

    name: str
    kind: str  # shelf | cabinet | crate | table_top | table_leg
    center: tuple[float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0
    z0: float = 0.0
    bottom_visible: bool = False

    @property
    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([c, s]), np.array([-s, c])

    @property
    def z1(self) -> float:
        return self.z0 + self.size[2]

    def footprint(self) -> np.ndarray:
        """(4, 2) corners of the footprint."""
        ex, ey = self.axes
        hx, hy = self.size[0] / 2, self.size[1] / 2
        c = np.asarray(self.center)
        return np.stack(
            [
                c - hx * ex - hy * ey,
                c + hx * ex - hy * ey,
                c + hx * ex + hy * ey,
                c - hx * ex + hy * ey,
            ]
        )

    def distance_xy(self, pts: np.ndarray) -> np.ndarray:
        """Horizontal distance of points (N, 2) to the footprint (0 inside)."""
        p = np.asarray(pts, np.float64).reshape(-1, 2) - np.asarray(self.center)
        ex, ey = self.axes
        lx, ly = np.abs(p @ ex) - self.size[0] / 2, np.abs(p @ ey) - self.size[1] / 2
        return np.hypot(np.maximum(lx, 0), np.maximum(ly, 0))

    def contains(self, pts: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Points (N, 3) inside the box grown by ``margin``."""
        p = np.asarray(pts, np.float64).reshape(-1, 3)
        inside_z = (p[:, 2] >= self.z0 - margin) & (p[:, 2] <= self.z1 + margin)
        return inside_z & (self.distance_xy(p[:, :2]) <= margin)


@dataclass(frozen=True)
class Track:
    """The free band cameras move in: elliptical radius ``rho`` around ``center``.

    ``rho(p) = |((p - center) / semi_axes)|``; furniture stays ``clearance`` away from
    ``rho_band``, so any path with ``rho`` inside the band is collision-free. The orbit
    circle of radius ``orbit_radius`` lies inside the band.
    """

    center: tuple[float, float]
    semi_axes: tuple[float, float]
    rho_band: tuple[float, float] = (0.6, 1.12)
    clearance: float = 0.4

    @property
    def orbit_radius(self) -> float:
        return float(min(self.semi_axes))

    def rho(self, xy: np.ndarray) -> np.ndarray:
        d = (np.asarray(xy, np.float64).reshape(-1, 2) - np.asarray(self.center)) / np.asarray(
            self.semi_axes
        )
        return np.hypot(d[:, 0], d[:, 1])

    def point(self, theta: float | np.ndarray, rho: float | np.ndarray) -> np.ndarray:
        theta, rho = np.asarray(theta, np.float64), np.asarray(rho, np.float64)
        a, b = self.semi_axes
        x = self.center[0] + rho * a * np.cos(theta)
        return np.stack([x, self.center[1] + rho * b * np.sin(theta)], axis=-1)


@dataclass(frozen=True)
class RoomLayout:
    size: tuple[float, float, float]
    boxes: tuple[Box, ...]
    track: Track

    def wall_distance(self, xy: np.ndarray) -> np.ndarray:
        p = np.asarray(xy, np.float64).reshape(-1, 2)
        L, W, _ = self.size
        return np.min(np.stack([p[:, 0], L - p[:, 0], p[:, 1], W - p[:, 1]]), axis=0)

    def box_distance(self, xy: np.ndarray) -> np.ndarray:
        p = np.asarray(xy, np.float64).reshape(-1, 2)
        if not self.boxes:
            return np.full(len(p), np.inf)
        return np.min(np.stack([b.distance_xy(p) for b in self.boxes]), axis=0)

    @cached_property
    def quads(self) -> list[Quad]:
        """Every surface of the room and its furniture, untextured, in scene face order."""
        return _layout_quads(self)


def _layout_quads(layout: RoomLayout) -> list[Quad]:
    L, W, H = layout.size
    quads: list[Quad] = []

    def add(name: str, o, u, v, recipe: tuple) -> None:
        quads.append(Quad(len(quads), name, o, u, v, recipe))

    # Walls seen from inside: (name, centre, inward normal, width).
    walls = [
        ("wall_y0", (L / 2, 0.0), (0, 1), L),
        ("wall_xL", (L, W / 2), (-1, 0), W),
        ("wall_yW", (L / 2, W), (0, -1), L),
        ("wall_x0", (0.0, W / 2), (1, 0), W),
    ]
    for name, centre, n, width in walls:
        add(name, *vertical_face(centre, n, width, 0.0, H), ("wall",))
    # Floor seen from above: s along +x, t along -y. Ceiling seen from below: s +x, t +y.
    add("floor", (0.0, W, 0.0), (L, 0, 0), (0, -W, 0), ("floor",))
    add("ceiling", (0.0, 0.0, H), (L, 0, 0), (0, W, 0), ("ceiling",))
    for b in layout.boxes:
        ex2, ey2 = b.axes
        ex, ey = np.array([*ex2, 0.0]), np.array([*ey2, 0.0])
        c = np.array([*b.center, 0.0])
        sx, sy, _ = b.size
        for a, bb, role in ((0, 1, "front"), (0, -1, "back"), (1, 0, "side+x"), (-1, 0, "side-x")):
            n = a * ex + bb * ey
            fc = c + (a * sx / 2) * ex + (bb * sy / 2) * ey
            o, u, v = vertical_face(fc[:2], n[:2], sy if a else sx, b.z0, b.z1)
            add(
                f"{b.name}_{role}", o, u, v, ("box", b.kind, "front" if role == "front" else "side")
            )
        add(
            f"{b.name}_top",
            c + np.array([0, 0, b.z1]) - (sx / 2) * ex + (sy / 2) * ey,
            sx * ex,
            -sy * ey,
            ("box", b.kind, "top"),
        )
        if b.bottom_visible:
            add(
                f"{b.name}_bottom",
                c + np.array([0, 0, b.z0]) - (sx / 2) * ex - (sy / 2) * ey,
                sx * ex,
                sy * ey,
                ("box", b.kind, "bottom"),
            )
    return quads


def room_layout(seed: int, conf: SceneConf | None = None) -> RoomLayout:
    """Furniture placement for ``seed`` (cheap: no textures)."""
    conf = conf or SceneConf()
    L, W, H = conf.size
    if L < 5.0 or W < 3.5 or H < 2.4:
        raise ValueError(f"room {conf.size} too small: need at least 5 x 3.5 x 2.4 m")
    rng = np.random.default_rng([seed, 0])
    track = Track(center=(L / 2, W / 2), semi_axes=(L / 2 - 1.6, W / 2 - 1.0))
    # Distance (m) from every 2 cm cell to the track band, to keep furniture out of it.
    res = 0.02
    gx, gy = np.meshgrid(
        (np.arange(int(L / res)) + 0.5) * res, (np.arange(int(W / res)) + 0.5) * res
    )
    rho = track.rho(np.stack([gx.ravel(), gy.ravel()], 1)).reshape(gx.shape)
    band = (rho >= track.rho_band[0]) & (rho <= track.rho_band[1])
    dist = cv2.distanceTransform((~band).astype(np.uint8), cv2.DIST_L2, 5) * res

    def band_clear(b: Box) -> bool:
        ex, ey = b.axes
        u = np.linspace(-0.5, 0.5, max(2, int(b.size[0] / res)))
        v = np.linspace(-0.5, 0.5, max(2, int(b.size[1] / res)))
        uu, vv = np.meshgrid(u, v)
        pts = (
            np.asarray(b.center)
            + (uu.ravel()[:, None] * b.size[0]) * ex
            + (vv.ravel()[:, None] * b.size[1]) * ey
        )
        i = np.clip((pts[:, 0] / res).astype(int), 0, dist.shape[1] - 1)
        j = np.clip((pts[:, 1] / res).astype(int), 0, dist.shape[0] - 1)
        return bool(np.all(dist[j, i] >= track.clearance + res))

    def in_room(b: Box, gap: float = 0.03) -> bool:
        fp = b.footprint()
        return bool(
            np.all(fp >= gap) and np.all(fp[:, 0] <= L - gap) and np.all(fp[:, 1] <= W - gap)
        )

    placed: list[Box] = []

    def free(b: Box, sep: float = 0.08) -> bool:
        if not (in_room(b) and band_clear(b)):
            return False
        fp = b.footprint()
        for o in placed:
            if o.kind == "table_leg":
                continue
            if np.any(o.distance_xy(fp) < sep) or np.any(b.distance_xy(o.footprint()) < sep):
                return False
            # Footprints can cross without corners inside each other; test the centres too.
            if (
                o.distance_xy(np.asarray(b.center)[None])[0] < sep
                or b.distance_xy(np.asarray(o.center)[None])[0] < sep
            ):
                return False
        return True

    def try_place(make, tries: int = 300) -> Box | None:
        for _ in range(tries):
            b = make()
            if b is not None and free(b):
                placed.append(b)
                return b
        return None

    plan = ["table", "shelf", "cabinet", "crate", "under", "tall", "stack", "crate"][: conf.n_boxes]
    long_wall_y = int(rng.integers(2))  # shelf on y = 0 (0) or y = W (1)
    table: Box | None = None
    for kind in plan:
        n = len([b for b in placed if b.kind != "table_leg"])
        if kind == "table":
            for _ in range(100):
                cx, cy = (
                    track.center[0] + rng.uniform(-0.1, 0.1),
                    track.center[1] + rng.uniform(-0.05, 0.05),
                )
                sx, sy = rng.uniform(1.0, 1.3), rng.uniform(0.5, 0.62)
                yaw = np.radians(rng.uniform(-4, 4))
                top = Box(
                    "table", "table_top", (cx, cy), (sx, sy, 0.04), yaw, 0.72, bottom_visible=True
                )
                if in_room(top) and band_clear(top):
                    break
            else:
                continue
            placed.append(top)
            table = top
            ex, ey = top.axes
            for k, (a, b) in enumerate([(-1, -1), (1, -1), (1, 1), (-1, 1)]):
                c = np.asarray(top.center) + a * (sx / 2 - 0.06) * ex + b * (sy / 2 - 0.06) * ey
                placed.append(
                    Box(
                        f"table_leg{k}",
                        "table_leg",
                        (float(c[0]), float(c[1])),
                        (0.05, 0.05, 0.72),
                        yaw,
                    )
                )
        elif kind == "shelf":

            def make_shelf(n: int = n) -> Box:
                sx, sy, sz = rng.uniform(1.2, 1.8), 0.3, rng.uniform(1.6, 2.0)
                x = rng.uniform(0.2 + sx / 2, L - 0.2 - sx / 2)
                if long_wall_y == 0:
                    return Box(f"box{n}", "shelf", (x, 0.03 + sy / 2), (sx, sy, sz), 0.0)
                return Box(f"box{n}", "shelf", (x, W - 0.03 - sy / 2), (sx, sy, sz), np.pi)

            try_place(make_shelf)
        elif kind in ("cabinet", "tall"):

            def make_cab(kind: str = kind, n: int = n) -> Box:
                if kind == "cabinet":
                    sx, sy, sz = (
                        rng.uniform(0.8, 1.2),
                        rng.uniform(0.35, 0.5),
                        rng.uniform(0.8, 1.1),
                    )
                else:
                    sx, sy, sz = (
                        rng.uniform(0.5, 0.7),
                        rng.uniform(0.45, 0.55),
                        rng.uniform(1.8, 2.1),
                    )
                side = int(rng.integers(2))  # against x = 0 or x = L, front into the room
                y = rng.uniform(0.1 + sx / 2, W - 0.1 - sx / 2)
                if side == 0:
                    return Box(f"box{n}", "cabinet", (0.03 + sy / 2, y), (sx, sy, sz), -np.pi / 2)
                return Box(f"box{n}", "cabinet", (L - 0.03 - sy / 2, y), (sx, sy, sz), np.pi / 2)

            try_place(make_cab)
        elif kind == "crate":

            def make_crate(n: int = n) -> Box:
                sx, sy, sz = rng.uniform(0.45, 0.8), rng.uniform(0.45, 0.8), rng.uniform(0.4, 0.9)
                corner = rng.integers(4)
                cx = rng.uniform(0.45, 1.3) if corner % 2 == 0 else L - rng.uniform(0.45, 1.3)
                cy = rng.uniform(0.45, 1.0) if corner < 2 else W - rng.uniform(0.45, 1.0)
                return Box(
                    f"box{n}", "crate", (cx, cy), (sx, sy, sz), np.radians(rng.uniform(-35, 35))
                )

            try_place(make_crate)
        elif kind == "stack":
            bases = [
                b
                for b in placed
                if b.kind == "crate"
                and b.z0 == 0.0
                and (table is None or table.distance_xy(np.asarray(b.center)[None])[0] > 0)
            ]
            if bases:
                base = bases[int(rng.integers(len(bases)))]
                for _ in range(100):
                    sx, sy = (
                        rng.uniform(0.3, 0.8) * base.size[0],
                        rng.uniform(0.3, 0.8) * base.size[1],
                    )
                    yaw = base.yaw + np.radians(rng.uniform(-20, 20))
                    c = np.asarray(base.center) + rng.uniform(-0.1, 0.1, 2)
                    box = Box(
                        f"box{n}",
                        "crate",
                        (float(c[0]), float(c[1])),
                        (sx, sy, rng.uniform(0.25, 0.45)),
                        yaw,
                        base.z1,
                    )
                    if np.all(base.distance_xy(box.footprint()) == 0.0):
                        placed.append(box)
                        break
        elif kind == "under" and table is not None:
            for _ in range(100):
                sx, sy, sz = rng.uniform(0.3, 0.45), rng.uniform(0.25, 0.35), rng.uniform(0.25, 0.4)
                c = np.asarray(table.center) + rng.uniform(-0.25, 0.25, 2) * np.array([1, 0.3])
                yaw = table.yaw + np.radians(rng.uniform(-30, 30))
                box = Box(f"box{n}", "crate", (float(c[0]), float(c[1])), (sx, sy, sz), yaw)
                legs = [o for o in placed if o.kind == "table_leg"]
                if np.all(table.distance_xy(box.footprint()) == 0.0) and all(
                    np.all(o.distance_xy(box.footprint()) > 0.05)
                    and box.distance_xy(np.asarray(o.center)[None])[0] > 0.05
                    for o in legs
                ):
                    placed.append(box)
                    break
    return RoomLayout(size=(L, W, H), boxes=tuple(placed), track=track)


# --------------------------------------------------------------------------- scene
@dataclass
class Features:
    """Exact 3D points at verified texture corners."""

    xyz: np.ndarray  # (N, 3) world
    face: np.ndarray  # (N,) face index
    st: np.ndarray  # (N, 2) texel-corner coordinates on the face
    radius: np.ndarray  # (N,) clean neighbourhood half-size on the surface (m)
    rgb: np.ndarray  # (N, 3) uint8, shaded colour at the corner

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass
class Scene:
    name: str
    seed: int
    conf: SceneConf
    layout: RoomLayout
    faces: list[Face]
    features: Features
    # Derived data (mipmaps) the renderer builds once per scene.
    cache: dict = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def room(cls, seed: int = 0, conf: SceneConf | None = None) -> Scene:
        """The textured room for ``seed``: same seed, same scene, byte for byte."""
        conf = conf or SceneConf()
        layout = room_layout(seed, conf)
        return _build_room(seed, conf, layout)

    @property
    def size(self) -> tuple[float, float, float]:
        return self.layout.size

    def face_normals(self) -> np.ndarray:
        return np.stack([f.normal for f in self.faces])

    def summary(self) -> str:
        n_tex = sum(f.texture.shape[0] * f.texture.shape[1] for f in self.faces)
        return (
            f"scene {self.name} seed {self.seed}: {len(self.faces)} faces, "
            f"{len(self.layout.boxes)} boxes, "
            f"{len(self.features)} corner points, {n_tex / 1e6:.1f} Mtexels"
        )


def _shade(normal: np.ndarray, rng: np.random.Generator) -> float:
    return float(
        np.clip(0.62 + 0.33 * max(0.0, float(normal @ _LIGHT)) + rng.uniform(-0.04, 0.04), 0.5, 1.0)
    )


def _build_room(seed: int, conf: SceneConf, layout: RoomLayout) -> Scene:
    L, W, _ = layout.size
    p = conf.texel_size
    shared = np.random.default_rng([seed, 2])
    posters = tx.make_poster_designs(shared, p)
    labels = tx.make_labels(shared, p)
    table = next((b for b in layout.boxes if b.kind == "table_top"), None)
    rug = None
    if table is not None:  # a rug under the table, in floor texture metres (t runs along -y)
        cx, cy = table.center
        rug = (cx - 1.3, W - (cy + 0.85), cx + 1.3, W - (cy - 0.85))

    def texture(q: Quad, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        w, h = float(np.linalg.norm(q.u_axis)), float(np.linalg.norm(q.v_axis))
        if q.recipe[0] == "wall":
            return tx.compose_wall(w, h, rng, p, posters, conf.grain)
        if q.recipe[0] == "floor":
            return tx.compose_floor(w, h, rng, p, conf.grain, rug)
        if q.recipe[0] == "ceiling":
            return tx.compose_ceiling(w, h, rng, p, conf.grain)
        _, kind, role = q.recipe
        return tx.compose_box_face(kind, role, w, h, rng, p, conf.grain, labels)

    faces: list[Face] = []
    xyz, fidx, st, rad, rgb = [], [], [], [], []
    for q in layout.quads:
        # One stream per face: a face's texture does not depend on how many draws others made.
        rng = np.random.default_rng(
            [seed, 1, 0 if conf.repeat_walls and q.recipe[0] == "wall" else q.index]
        )
        img, cand = texture(q, rng)
        face = Face(q.index, q.name, q.origin, q.u_axis, q.v_axis, q.recipe, texture=img)
        face.shade = _shade(face.normal, rng)
        faces.append(face)
        cs = tx.verify_corners(img, cand)
        if len(cs.xy):
            xyz.append(face.world_from_tex(cs.xy))
            fidx.append(np.full(len(cs.xy), q.index))
            st.append(cs.xy.astype(np.float64))
            rad.append(cs.radius * min(face.texel_size))
            col = np.clip(cs.color.astype(np.float64) * face.shade, 0, 255).astype(np.uint8)
            rgb.append(col[:, ::-1])  # BGR -> RGB
    feats = Features(
        np.concatenate(xyz) if xyz else np.zeros((0, 3)),
        np.concatenate(fidx) if fidx else np.zeros(0, np.int64),
        np.concatenate(st) if st else np.zeros((0, 2)),
        np.concatenate(rad) if rad else np.zeros(0),
        np.concatenate(rgb) if rgb else np.zeros((0, 3), np.uint8),
    )
    return Scene("room", seed, conf, layout, faces, feats)


# --------------------------------------------------------------------------- ray casting
def raycast(
    scene: Scene | RoomLayout,
    origins: np.ndarray,
    dirs: np.ndarray,
    t_max: np.ndarray | float = np.inf,
    exclude_face: np.ndarray | None = None,
    eps: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray]:
    """First intersection of rays with any face of a scene or layout (both sides count).

    ``origins``/``dirs`` (N, 3); returns (t, face) with ``t = inf`` and ``face = -1`` where a
    ray hits nothing within ``(eps, t_max)``. ``exclude_face`` (N,) skips one face per ray
    (the face a point lies on, when testing whether the segment to it is blocked).
    """
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(dirs, np.float64).reshape(-1, 3)
    o = np.broadcast_to(o, d.shape) if len(o) == 1 else o
    n = len(d)
    best_t = np.full(n, np.inf)
    best_f = np.full(n, -1, np.int64)
    t_max = np.broadcast_to(np.asarray(t_max, np.float64), (n,))
    quads = scene.faces if isinstance(scene, Scene) else scene.quads
    for f in quads:
        denom = d @ f.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (f.plane_d - o @ f.normal) / denom
        hit = np.abs(denom) > 1e-12
        hit &= (t > eps) & (t < t_max) & (t < best_t)
        if exclude_face is not None:
            hit &= exclude_face != f.index
        if not hit.any():
            continue
        idx = np.nonzero(hit)[0]
        X = o[idx] + t[idx, None] * d[idx] - f.origin
        a = X @ f.u_axis / (f.u_axis @ f.u_axis)
        b = X @ f.v_axis / (f.v_axis @ f.v_axis)
        inside = (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        idx = idx[inside]
        best_t[idx] = t[idx]
        best_f[idx] = f.index
    return best_t, best_f
