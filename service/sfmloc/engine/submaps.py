"""Localization over a sub-map set (out-of-core maps; design in ``map/submaps.py``).

``SubmapLocalizer`` owns one plain ``Localizer`` and swaps the sub-map it runs on between
frames: the per-frame core is unchanged, and a frame only ever meets one sub-map, which is
always resident (a tracked frame waits for a load only when the budget cannot hold two parts).

Per frame, before the ``Localizer`` runs:

1. **Tracked** (the last frame had a pose, published or withheld: the motion filter's): the
   home part is the one whose cameras cover that pose best (``SubmapSet.parts_near``: cameras
   weighted by their distance in position, in scene scales, and viewing direction). The camera
   stays on its part until another covers it better by the factor 1 + ``switch_margin``
   (hysteresis: no flapping along a boundary). When the home part is resident the session
   switches at once, its track table going through the global point ids
   (``map.submaps.translate``: matches to points the new part holds stay, the rest become
   pending); when it is not, it is loaded in the background and the session keeps running on
   its current part (the parts overlap) until it is; when the budget cannot hold both, the
   frame waits for the load (the old part is evicted first). The part covering the pose
   predicted ``lookahead_s`` ahead (the filter's velocity) is loaded in the background too,
   while the budget allows.
2. **Lost** (no pose on the last frame): the frame's keypoints are described and the parts
   ranked by their place-recognition vote (``SubmapSet.vote``); the session moves to the
   best-voted part not tried since it was lost, loading it now (a lost frame relocalizes
   anyway), so consecutive lost frames search the parts in order of their vote, one global
   matching per frame.

Memory: the resident parts' ``memory_bytes`` (as ``MapBundle.memory_bytes``: arrays touched by
the engine plus the ANN index; a part being loaded counts from the moment its load starts)
never exceed ``memory_budget``; the least recently used parts other than the current one are
evicted first, and a prefetch that does not fit is skipped. The global index is outside the
budget (``SubmapSet.memory_bytes``, small).
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cameras import Camera, as_camera
from ..errors import InputError
from ..features.daisy import DaisyExtractor, Pca
from ..features.harris import detect_corners
from ..map.bundle import MapBundle
from ..map.submaps import SubmapSet, translate
from ..transforms import Rigid3d
from .config import EngineConf
from .frame import to_gray, to_working, working_scale
from .localizer import Localizer
from .types import FrameResult

log = logging.getLogger(__name__)


@dataclass
class SubmapStats:
    """What the session did with the parts (for tests, benches and logs)."""

    switches: int = 0
    loads: int = 0
    sync_loads: int = 0  # loads a frame waited for (only lost frames do)
    evictions: int = 0
    skipped_prefetch: int = 0
    max_resident_bytes: int = 0
    parts_used: set[int] = field(default_factory=set)
    votes: int = 0  # lost frames ranked by the vote


class SubmapLocalizer:
    """A ``Localizer`` over a ``SubmapSet`` within ``memory_budget`` bytes of resident parts.

    ``localize(frame, stamp)`` as ``Localizer.localize``; ``part`` is the sub-map the last
    frame ran on. Not thread-safe (one frame at a time), like ``Localizer``; the set is shared.
    ``background``: load parts on a thread (False: load them in the frame, for measurements).
    """

    def __init__(
        self,
        submaps: SubmapSet,
        camera: Camera | str | Path,
        conf: EngineConf | None = None,
        *,
        memory_budget: int,
        lookahead_s: float = 1.0,
        switch_margin: float = 0.2,
        background: bool = True,
    ) -> None:
        self.set = submaps
        self.camera_in = as_camera(camera)
        self.conf = conf or EngineConf()
        biggest = max(p.memory_bytes for p in submaps.manifest.parts)
        if memory_budget < biggest:
            raise InputError(
                f"a memory budget of {memory_budget / 1e6:.1f} MB cannot hold the largest "
                f"sub-map ({biggest / 1e6:.1f} MB) of {submaps.path}: raise the budget or split "
                "the map into smaller parts"
            )
        self.memory_budget = int(memory_budget)
        self.lookahead_s = lookahead_s
        self.switch_margin = switch_margin
        self.stats = SubmapStats()
        self._resident: OrderedDict[int, tuple[MapBundle, np.ndarray]] = OrderedDict()
        self._loading: dict[int, Future] = {}
        self._lock = threading.Lock()  # guards the byte count shared with the loader
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="submap-load") if background else None
        self.inner: Localizer | None = None
        self.part: int | None = None
        self._part_points: np.ndarray | None = None  # global point rows of ``part``
        self._tried: list[int] = []
        self._prev_stamp: float | None = None  # parts tried since the session was lost
        self._extractor = DaisyExtractor()
        self._pca: Pca | None = None

    # ------------------------------------------------------------------ public
    def localize(self, frame: np.ndarray, stamp: float) -> FrameResult:
        self._collect_loads()
        known = self._known_pose(stamp)
        if known is not None:
            self._follow(*known)
        else:
            self._relocalize_order(frame)
        assert self.inner is not None
        res = self.inner.localize(frame, stamp)
        self._prev_stamp = stamp
        if self.inner.last_posed_stamp == stamp:
            self._tried = []  # a pose (published or withheld): the search is over
        self.stats.max_resident_bytes = max(self.stats.max_resident_bytes, self.resident_bytes())
        return res

    def _known_pose(self, stamp: float) -> tuple[Rigid3d, np.ndarray] | None:
        """The session's pose and centre velocity from its motion filter when the last frame
        had a pose (published or withheld: both update the filter), else None (lost: the
        parts are searched by their vote; a session whose frames fail on its part must not
        stay there on the strength of an old prediction: measured on two rooms 20 m apart,
        the camera moved to the second stayed LOST on the first room's part for 30 frames)."""
        inner = self.inner
        if inner is None or inner.last_posed_stamp is None or not inner.filter.initialized:
            return None
        if inner.last_posed_stamp != self._prev_stamp:
            return None
        if not 0 <= stamp - inner.last_posed_stamp <= self.conf.max_frame_gap_s:
            return None
        return inner.filter.current(), np.asarray(inner.filter.velocity, float)

    def resident_parts(self) -> list[int]:
        return list(self._resident)

    def loading_parts(self) -> list[int]:
        """Parts being loaded on the loader thread."""
        with self._lock:
            return [k for k, f in self._loading.items() if not f.done()]

    def resident_bytes(self) -> int:
        """Bytes of the resident parts plus those being loaded (what the budget bounds)."""
        with self._lock:
            parts = list(self._resident) + list(self._loading)
        return sum(self.set.part_memory_bytes(k) for k in parts)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
        self._collect_loads()

    # ------------------------------------------------------------------ tracked
    def _follow(self, pose: Rigid3d, velocity: np.ndarray) -> None:
        cover = self.set.parts_near(pose)
        best = int(np.argmax(cover))
        cur = self.part
        want = best
        if cur is not None and cover[best] <= cover[cur] * (1.0 + self.switch_margin):
            want = cur  # hysteresis: no flapping along a boundary
        if want != cur:
            if want in self._resident:
                self._switch(want)
            elif not self._request(want, keep={cur} if cur is not None else set()):
                # The budget cannot hold both: this frame waits for the load.
                self._load_now(want)
                self._switch(want)
        # Ahead of the camera: the part covering the pose ``lookahead_s`` from now best.
        ahead = pose.center + velocity * self.lookahead_s
        if np.all(np.isfinite(ahead)):
            ahead_pose = Rigid3d(pose.rotation, -pose.rotation @ ahead)
            nxt = int(np.argmax(self.set.parts_near(ahead_pose)))
            if nxt not in self._resident and nxt not in self._loading:
                keep = {k for k in (self.part, want) if k is not None}
                self._request(nxt, keep=keep, optional=True)

    # ------------------------------------------------------------------ lost
    def vote(self, frame: np.ndarray) -> np.ndarray:
        """The parts' place-recognition scores for ``frame`` (``SubmapSet.vote`` of its
        keypoints' descriptors): the order a lost session tries them in."""
        return self.set.vote(self._frame_descriptors(frame))

    def _relocalize_order(self, frame: np.ndarray) -> None:
        scores = self.vote(frame)
        self.stats.votes += 1
        order = [int(k) for k in np.argsort(-scores, kind="stable")]
        cand = [k for k in order if k not in self._tried]
        if not cand:
            self._tried, cand = [], order
        k = cand[0]
        self._tried.append(k)
        if k != self.part:
            if k not in self._resident:
                self._load_now(k)
            self._switch(k)

    def _frame_descriptors(self, frame: np.ndarray) -> np.ndarray:
        """The frame's keypoints described as global matching describes them."""
        c = self.conf
        if self._pca is None:
            self._pca = self.set.pca()
        native, coarsest = self.set.focal_scales()
        scale = working_scale(
            self.camera_in, native, c.working_scale, c.max_working_pixels, coarsest
        )
        gray = to_working(to_gray(frame, self.camera_in), scale)
        corners = detect_corners(
            gray,
            rel_threshold=c.gamma,
            max_corners=c.global_max_keypoints,
            border=c.mu // 2,
            subpixel=False,
        )
        if len(corners) == 0:
            return np.zeros((0, self._pca.basis.shape[1]), np.float32)
        prepared = self._extractor.prepare(gray)
        theta = self._extractor.orientations(prepared, corners.xy)
        return self._pca.project(self._extractor.describe(prepared, corners.xy, theta))

    # ------------------------------------------------------------------ parts
    def _switch(self, k: int) -> None:
        bundle, gpts = self._resident[k]
        self._resident.move_to_end(k)
        if self.inner is None:
            self.inner = Localizer(bundle, self.camera_in, self.conf)
        else:
            old_pts = self._part_points
            inner = self.inner
            if old_pts is not None:
                t = inner.table
                new_point = translate(t.point, old_pts, gpts)
                lost = (t.point >= 0) & (new_point < 0)
                t.point = new_point
                t.pending = t.pending | lost
                t.hyp = translate(t.hyp, old_pts, gpts)
                sp = translate(inner.scope_points, old_pts, gpts)
                inner.scope_points = sp[sp >= 0]
            else:
                inner.reset()  # nothing to translate from: start over on the new part
            inner.bundle = bundle
        if self.part != k:
            self.stats.switches += self.part is not None
            log.debug("sub-map %s -> %s", self.part, k)
        self.part = k
        self._part_points = gpts  # kept after an eviction: the table is translated from it
        self.stats.parts_used.add(k)

    def _room_for(self, k: int, keep: set[int], optional: bool) -> bool:
        """Evict least recently used parts (not ``keep``, not the current one) until part
        ``k`` fits in the budget; False when it cannot (nothing is evicted then)."""
        need = self.set.part_memory_bytes(k)
        protect = set(keep) | ({self.part} if self.part is not None else set())
        evictable = [j for j in self._resident if j not in protect]  # LRU first
        used = self.resident_bytes()
        free_up = []
        for j in evictable:
            if used + need <= self.memory_budget:
                break
            free_up.append(j)
            used -= self.set.part_memory_bytes(j)
        if used + need > self.memory_budget:
            if optional:
                self.stats.skipped_prefetch += 1
            return False
        for j in free_up:
            del self._resident[j]
            self.stats.evictions += 1
        return True

    def _request(self, k: int, keep: set[int], optional: bool = False) -> bool:
        """Start loading part ``k`` (in the background, or now without a loader thread);
        False when it does not fit the budget beside ``keep`` and the current part."""
        if k in self._loading or k in self._resident:
            return True
        if not self._room_for(k, keep, optional):
            return False
        if self._pool is None:
            self._resident[k] = self.set.load_part(k)
            self.stats.loads += 1
            return True
        with self._lock:
            self._loading[k] = self._pool.submit(self.set.load_part, k)
        return True

    def _load_now(self, k: int) -> None:
        fut = self._loading.get(k)
        if fut is not None:
            fut.result()
            self._collect_loads()
            return
        # The current part may go: the switch translates the table from its point ids.
        protect_current = self.part
        self.part = None
        ok = self._room_for(k, set(), optional=False)
        self.part = protect_current
        if not ok:
            raise InputError(f"sub-map {k} does not fit the memory budget")  # checked in init
        self._resident[k] = self.set.load_part(k)
        self.stats.loads += 1
        self.stats.sync_loads += 1

    def _collect_loads(self) -> None:
        for k, fut in list(self._loading.items()):
            if fut.done():
                with self._lock:
                    del self._loading[k]
                try:
                    self._resident[k] = fut.result()
                    self.stats.loads += 1
                except Exception as exc:  # noqa: BLE001 - a bad part must not stop the session
                    log.error("sub-map %d failed to load: %s", k, exc)
