"""Localization over a sub-map set (out-of-core maps; design in ``map/submaps.py``).

``SubmapLocalizer`` owns one plain ``Localizer`` and swaps the sub-map it runs on between
frames: the per-frame core is unchanged, and a frame only ever meets one sub-map, which is
always resident (a tracked frame waits for a load only when the budget cannot hold two parts).
The resident parts live in a ``PartCache``, one per set and thread, which sessions may share
(a server worker's sessions: ``server/submaps.py``).

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
2. **Lost** (no pose on the last frame, or none on this frame after tracking on its part: a
   jump, a teleport between rooms): the frame's keypoints are described and the parts ranked
   by their place-recognition vote (``SubmapSet.vote``, plus the earlier lost frames' votes:
   ``_lost_vote``); the frame is matched against the parts in that order until one gives a
   pose. The parts load before the search needs them (issue 14: no load may stall a frame by
   more than 15 ms): as a tracked frame's tracking fails, its vote is taken and the first
   part of its search starts loading while the frame is matched globally against its own
   part (``_early_vote``, through ``Localizer.before_global_matching``); while a part is
   matched, the next that fits beside it loads; a frame left without a pose loads the part
   the next frame starts with. A part of the order not resident even so is awaited at most
   what the frame may still wait (``EngineConf.submap_load_wait_ms`` for all its loads,
   10 ms), then left to load: the search goes on from it on the next frame (it spreads over
   frames, as the paper spreads global matching). When the budget cannot hold the part
   beside the session's own, the session lets go of its own for it. Scale bench (24 rooms,
   72 parts, 10x the budget): stall p99 55 ms -> 9 ms, 956/960 -> 947/960 localized (numbers
   in docs/measurements.md#submap-measurements). Which loads finish within that wait depends
   on a load's cost: parts are packed bundles (``map/bundle.py``: one mapped file, a load's
   CPU p50 ~7 -> ~2 ms, its wall on the loader thread ~29 -> ~2.4 ms), and the loads the
   walk waited for in vain, 4-9 frames a run, became 1-2
   (docs/measurements.md#submap-measurements). Parts are tried until one poses:
   ``lost_parts_per_frame`` parts (``EngineConf.submap_lost_parts``, 2) at least, then more
   while the frame's search has used less than ``EngineConf.submap_search_cpu_ms`` of its
   thread's CPU (at most ``submap_search_max_parts``). The vote is discounted by
   ``PLACE_DISCOUNT`` for each part of the same place (``SubmapSet.covered_by`` at least
   ``SAME_PLACE``) the frame met already, and by ``RETRY_DISCOUNT`` for each earlier lost
   frame the part failed on (``_next_part``), and the part to try next is loaded on the
   thread while the current one is matched.
   Measured on the scale bench (8 rooms, 24 parts, overlap 0.25, one camera teleported from
   room to room): one part per frame, starting on the next frame, localized 291/320 (the
   whole map 320); searching on the frame that lost its part, two parts per frame, with the
   vote's ratio test, 313/320 (not measured apart); with overlap 0.5 too, 318/320. 24 rooms,
   72 parts: 936/960; the vote put a look-alike room's three parts first for the first frames
   of rooms 11 and 15, and both tries went to that room: with other places first, 940/960.
   The parts tried since the session was lost then went after every other part: room 13's
   three parts voted 15, 14 and 7 against at most 3 for any other room; its best-voted part
   failed frames 0-5 on the second-place test, each frame's second try went to another room,
   and its third part, which poses frame 0, was met once (frame 1, which it does not pose).
   With the discounts and a CPU budget of 1000 ms (3-4 parts a searching frame), 956/960,
   0 wrong (the walk alone, load 23; bench numbers: docs/measurements.md#submap-measurements).

Memory: the resident parts' ``memory_bytes`` (as ``MapBundle.memory_bytes``: arrays touched by
the engine plus the ANN index; a part being loaded counts from the moment its load starts)
never exceed ``memory_budget``; the least recently used parts other than the current one are
evicted first, and a prefetch that does not fit is skipped. The global index is outside the
budget (``SubmapSet.memory_bytes``, small). An evicted part counts until the kernel has
unmapped it, not until the cache forgets it: its pages stay resident while anything holds a
view of its arrays (``MapBundle.mappings``, held weakly). A session whose part is evicted to
load the next in its place lets go of it first (``Localizer.detach_bundle``): before, it held
the old part through its ``Localizer`` while the new one loaded, and a server worker with room
for one part of the test world's three held 2,064,384 B of the set against a 1,860,596 B
budget (the kernel's count, sampled during a switch; 2,252,800 in-process right after the
load).
"""

from __future__ import annotations

import gc
import logging
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..cameras import Camera, as_camera
from ..errors import InputError, OverloadError
from ..features.daisy import DaisyExtractor, Pca
from ..features.harris import detect_corners
from ..map.bundle import MapBundle
from ..map.submaps import SubmapSet, translate
from ..transforms import Rigid3d
from .config import EngineConf
from .frame import to_gray, to_working, working_scale
from .localizer import Localizer
from .types import FrameResult, Status

log = logging.getLogger(__name__)


# ``_search``: a part of which at least this fraction of images belongs to parts a lost frame
# has tried is the same place (tried after the other places).
SAME_PLACE = 0.5
# ``_next_part``: a part's vote counts this much less for each part of its place a lost frame
# tried already.
PLACE_DISCOUNT = 0.5
# ``_next_part``: and this much less for each lost frame of the session it failed on.
RETRY_DISCOUNT = 0.5
# ``_early_vote``: the parts of the search's order it considers loading (the first that fits).
EARLY_CANDIDATES = 3
# ``_lost_vote``: the weight of the earlier lost frames' votes (decayed) in a lost frame's.
VOTE_MEMORY = 0.7
# ``_search``: the weight of a failure on the previous lost frame against one on this frame
# (decayed like the votes: the search's retry discount follows recent failures).
FAIL_MEMORY = VOTE_MEMORY


def _call_weak(method: weakref.WeakMethod) -> None:
    m = method()
    if m is not None:
        m()


@dataclass
class SubmapStats:
    """What the session (or, on a ``PartCache``, every session sharing it) did with the parts
    (for tests, benches, logs and the server's metrics)."""

    switches: int = 0
    loads: int = 0
    sync_loads: int = 0  # loads a frame waited for (only lost frames do, when one part fits)
    sync_load_ms: float = 0.0  # the time frames waited for those loads, in all
    evictions: int = 0
    skipped_prefetch: int = 0
    failed_loads: int = 0
    max_resident_bytes: int = 0
    parts_used: set[int] = field(default_factory=set)
    votes: int = 0  # lost frames ranked by the vote
    lost_tries: int = 0  # parts a lost frame was matched against
    prefetched_tries: int = 0  # of those, parts already loaded or loading when tried
    search_cpu_ms: float = 0.0  # this thread's CPU time lost frames spent searching, in all
    unready_lost: int = 0  # frames answered LOST because no part of their order was resident
    unready_parts: int = 0  # searches stopped at a part not resident in time (next frame on)
    early_loads: int = 0  # parts a frame's vote started loading before its search (tracked frames)


class PartCache:
    """The resident parts of one ``SubmapSet`` within ``memory_budget`` bytes, shared by the
    sessions of one thread (a server worker's: one copy of each part and one budget for all
    of them). A part a session is on is never evicted; the others go least recently used
    first. A session is forgotten when it is closed or garbage-collected (the cache holds it
    weakly: a server dropping a session cannot leave its part resident for good).
    ``background``: loads run on a loader thread (False: in the caller, for measurements).
    Not thread-safe apart from that thread."""

    def __init__(self, submaps: SubmapSet, memory_budget: int, *, background: bool = True):
        self.set = submaps
        biggest = submaps.largest_part_bytes()
        if memory_budget < biggest:
            raise InputError(
                f"a memory budget of {memory_budget / 1e6:.1f} MB cannot hold the largest "
                f"sub-map ({biggest / 1e6:.1f} MB) of {submaps.path}: raise the budget or split "
                "the map into smaller parts"
            )
        self.memory_budget = int(memory_budget)
        self.stats = SubmapStats()
        self._resident: OrderedDict[int, tuple[MapBundle, np.ndarray]] = OrderedDict()
        self._loading: dict[int, Future] = {}
        self._loading_now: int | None = None  # a part loading in the caller's thread
        # Evicted parts something may still map (weak references to their memory maps): they
        # count against the budget until the kernel has let them go.
        self._leaving: list[tuple[int, list[weakref.ref]]] = []
        self._evicted = 0  # evictions so far; ``_room_for`` collects cycles once per new one
        self._collected_at = -1
        self._users: weakref.WeakSet[SubmapLocalizer] = weakref.WeakSet()
        self._lock = threading.Lock()  # guards _loading, read by the byte count
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="submap-load") if background else None

    # ------------------------------------------------------------------ state
    def resident_parts(self) -> list[int]:
        return list(self._resident)

    def loading_parts(self) -> list[int]:
        """Parts being loaded on the loader thread."""
        with self._lock:
            return [k for k, f in self._loading.items() if not f.done()]

    def resident_bytes(self) -> int:
        """Bytes of the resident parts, those being loaded, and evicted ones something still
        maps (what the budget bounds: what the kernel holds of the set's parts)."""
        with self._lock:
            parts = list(self._resident) + list(self._loading)
            if self._loading_now is not None:
                parts.append(self._loading_now)
            parts += [k for k, refs in self._leaving if any(r() is not None for r in refs)]
        return sum(self.set.part_memory_bytes(k) for k in parts)

    def leaving_parts(self) -> list[int]:
        """Evicted parts still mapped (a session or a caller holds a view of them)."""
        self._prune()
        with self._lock:
            return [k for k, _ in self._leaving]

    def _prune(self) -> None:
        with self._lock:
            self._leaving = [
                (k, refs) for k, refs in self._leaving if any(r() is not None for r in refs)
            ]

    def _peak(self, stats: tuple = ()) -> None:
        used = self.resident_bytes()
        for st in (self.stats, *stats):
            st.max_resident_bytes = max(st.max_resident_bytes, used)

    def register(self, user: SubmapLocalizer) -> None:
        """A session whose part (``user.part``) must stay resident while it is on it."""
        self._users.add(user)

    def unregister(self, user: SubmapLocalizer) -> None:
        self._users.discard(user)

    def sessions(self) -> int:
        return len(self._users)

    def pinned(self, exclude: SubmapLocalizer | None = None) -> set[int]:
        """The parts sessions are on (but ``exclude``'s)."""
        return {u.part for u in list(self._users) if u is not exclude and u.part is not None}

    def get(self, k: int) -> tuple[MapBundle, np.ndarray] | None:
        """Part ``k`` when resident (it becomes the most recently used), else None."""
        part = self._resident.get(k)
        if part is not None:
            self._resident.move_to_end(k)
        return part

    def is_pending(self, k: int) -> bool:
        return k in self._resident or k in self._loading

    def is_resident(self, k: int) -> bool:
        """Part ``k`` resident (not made the most recently used, as ``get`` does)."""
        return k in self._resident

    def is_loading(self, k: int) -> bool:
        """Part ``k`` being loaded on the loader thread (or loaded, not adopted yet)."""
        return k in self._loading

    def note_early(self, stats: tuple = ()) -> None:
        self._note(*stats, early_loads=1)

    # ------------------------------------------------------------------ loading
    def _note(self, *stats: SubmapStats, **inc: float) -> None:
        for st in (self.stats, *stats):
            for name, v in inc.items():
                setattr(st, name, getattr(st, name) + v)

    def _room_for(
        self, k: int, keep: set[int], optional: bool, stats: tuple, release: Any = None
    ) -> bool:
        """Evict least recently used parts (no session's but ``release``'s, not ``keep``)
        until part ``k`` fits in the budget; False when it cannot (nothing is evicted then,
        or what was evicted is still mapped elsewhere and keeps counting). ``release``'s part,
        when evicted, is let go by its session before this returns (``_let_go``)."""
        need = self.set.part_memory_bytes(k)
        protect = set(keep) | self.pinned(exclude=release)
        free_up: list[int] = []
        for attempt in range(2):
            self._prune()
            used = self.resident_bytes()
            free_up = []
            for j in [j for j in self._resident if j not in protect]:  # LRU first
                if used + need <= self.memory_budget:
                    break
                free_up.append(j)
                used -= self.set.part_memory_bytes(j)
            if used + need <= self.memory_budget or attempt or not self._collect_cycles():
                break
        if used + need > self.memory_budget:
            return self._no_room(optional, stats)
        for j in free_up:
            self._evict(j)
            self._note(*stats, evictions=1)
        if release is not None and release.part in free_up:
            release._let_go()
        # The truth: an evicted part counts until nothing maps it (a reference cycle, or a
        # caller still holding the bundle ``load_now`` gave it).
        self._prune()
        if self.resident_bytes() + need > self.memory_budget:
            self._collect_cycles()
            self._prune()
            if self.resident_bytes() + need > self.memory_budget:
                return self._no_room(optional, stats)
        return True

    def _no_room(self, optional: bool, stats: tuple) -> bool:
        if optional:
            self._note(*stats, skipped_prefetch=1)
        return False

    def _evict(self, j: int) -> None:
        # A method of its own: no local name outlives the eviction holding the part.
        bundle = self._resident.pop(j)[0]
        refs = [weakref.ref(m) for m in bundle.mappings()]
        with self._lock:
            self._leaving.append((j, refs))
        self._evicted += 1

    def _collect_cycles(self) -> bool:
        """Collect garbage cycles when an evicted part is still mapped (once per eviction
        since the last collection: a part a caller really holds stays counted); True when
        something was left to collect."""
        self._prune()
        if not self._leaving or self._collected_at == self._evicted:
            return False
        self._collected_at = self._evicted
        gc.collect()
        return True

    def request(
        self,
        k: int,
        keep: set[int],
        optional: bool = False,
        stats: tuple = (),
        release: Any = None,
    ) -> bool:
        """Start loading part ``k`` (in the background, or now without a loader thread);
        False when it does not fit the budget beside the pinned parts and ``keep``
        (``release``: a session whose part may go to make room, as ``load_now``)."""
        if self.is_pending(k):
            return True
        if not self._room_for(k, keep, optional, stats, release):
            return False
        if self._pool is None:
            self._resident[k] = self._load(k)
            self._note(*stats, loads=1)
            self._peak(stats)
            return True
        with self._lock:
            self._loading[k] = self._pool.submit(self.set.load_part, k)
        self._peak(stats)
        return True

    def _load(self, k: int) -> tuple[MapBundle, np.ndarray]:
        """Part ``k`` loaded in the caller's thread (counted while it loads)."""
        with self._lock:
            self._loading_now = k
        try:
            return self.set.load_part(k)
        finally:
            with self._lock:
                self._loading_now = None

    def load_now(
        self, k: int, stats: tuple = (), release: Any = None
    ) -> tuple[MapBundle, np.ndarray]:
        """Part ``k``, loaded now if it is not resident (waiting for its background load if
        one runs); ``release``: a session about to leave its part (which may then be
        evicted). ``OverloadError`` when it does not fit beside the sessions' parts."""
        t0 = time.perf_counter()
        fut = self._loading.get(k)
        if fut is not None:
            fut.result()
            self.collect(stats)
        part = self.get(k)
        if part is None:
            if not self._room_for(k, set(), False, stats, release):
                raise OverloadError(
                    f"sub-map {k} of {self.set.name} does not fit the memory budget "
                    f"({self.memory_budget / 1e6:.1f} MB) beside the parts other sessions are "
                    "on: raise the map memory budget"
                )
            part = self._resident[k] = self._load(k)
            self._note(*stats, loads=1)
            self._peak(stats)
        self._note(*stats, sync_loads=1, sync_load_ms=(time.perf_counter() - t0) * 1e3)
        return part

    def wait_for(self, k: int, timeout_s: float, stats: tuple = ()) -> bool:
        """Wait at most ``timeout_s`` for part ``k``'s background load (the wait counts as a
        stall); True when it is resident."""
        fut = self._loading.get(k)
        if fut is not None and timeout_s > 0 and not fut.done():
            t0 = time.perf_counter()
            # futures.wait: no exception on a timeout (Python 3.10, which pyproject allows,
            # raises concurrent.futures.TimeoutError there, not the builtin TimeoutError)
            futures_wait([fut], timeout=timeout_s)
            self._note(*stats, sync_loads=1, sync_load_ms=(time.perf_counter() - t0) * 1e3)
        self.collect(stats)
        return k in self._resident

    def collect(self, stats: tuple = ()) -> None:
        """Adopt the parts the loader thread has finished."""
        for k, fut in list(self._loading.items()):
            if fut.done():
                with self._lock:
                    del self._loading[k]
                try:
                    self._resident[k] = fut.result()
                    self._note(*stats, loads=1)
                except Exception as exc:  # noqa: BLE001 - a bad part must not stop the session
                    self._note(*stats, failed_loads=1)
                    log.error("sub-map %d failed to load: %s", k, exc)
        self._prune()
        self._peak(stats)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
        self.collect()


class SubmapLocalizer:
    """A ``Localizer`` over a ``SubmapSet`` within ``memory_budget`` bytes of resident parts
    (its own ``PartCache``), or over a ``cache`` shared with other sessions.

    ``localize(frame, stamp)`` as ``Localizer.localize``; ``part`` is the sub-map the last
    frame ran on. Not thread-safe (one frame at a time), like ``Localizer``.
    ``lost_parts_per_frame``: parts a frame without a pose is matched against, in the order
    of the vote, before it is answered LOST (default ``conf.submap_lost_parts``).
    """

    def __init__(
        self,
        submaps: SubmapSet,
        camera: Camera | str | Path,
        conf: EngineConf | None = None,
        *,
        memory_budget: int | None = None,
        cache: PartCache | None = None,
        lookahead_s: float = 1.0,
        switch_margin: float = 0.2,
        lost_parts_per_frame: int | None = None,
        background: bool = True,
    ) -> None:
        if cache is None:
            if memory_budget is None:
                raise InputError("SubmapLocalizer needs a memory_budget or a shared cache")
            cache = PartCache(submaps, memory_budget, background=background)
            self._own_cache = True
        else:
            self._own_cache = False
        if cache.set is not submaps:
            raise InputError("the part cache belongs to another sub-map set")
        self.set = submaps
        self.cache = cache
        self.camera_in = as_camera(camera)
        self.conf = conf or EngineConf()
        self.memory_budget = cache.memory_budget
        self.lookahead_s = lookahead_s
        self.switch_margin = switch_margin
        self.lost_parts_per_frame = int(lost_parts_per_frame or self.conf.submap_lost_parts)
        self.stats = SubmapStats()
        self.inner: Localizer | None = None
        self.part: int | None = None
        self._left: int | None = None  # the part it let go of in a search (``_let_go``)
        self._part_points: np.ndarray | None = None  # global point rows of ``part``
        # lost frames each part failed since the session was lost (decayed, ``FAIL_MEMORY``)
        self._fails: dict[int, float] = {}
        self._withheld_on: list[int] = []  # parts with poses withheld since the last published
        self._prev_stamp: float | None = None
        # The frame being localized (for the vote ``_early_vote`` takes while the frame is
        # matched against its own part), its vote once taken, and what it may still wait for
        # loads (``EngineConf.submap_load_wait_ms``, for the whole frame).
        self._frame: np.ndarray | None = None
        self._stamp: float | None = None
        self._vote_of: tuple[float, np.ndarray] | None = None
        # The session's lost frames' votes since its last pose, decayed (``_lost_vote``).
        self._votes: np.ndarray | None = None
        self._wait_left = 0.0
        self._extractor = DaisyExtractor()
        self._pca: Pca | None = None
        cache.register(self)

    @property
    def _st(self) -> tuple[SubmapStats]:
        return (self.stats,)

    # ------------------------------------------------------------------ public
    def localize(
        self, frame: np.ndarray, stamp: float, prior: Rigid3d | None = None
    ) -> FrameResult:
        """``Localizer.localize`` over the parts; ``prior`` (an outside estimate of the pose,
        used when the session has no pose of its own) chooses the first part to search."""
        self._frame, self._stamp = frame, stamp
        self._wait_left = self.conf.submap_load_wait_ms / 1e3
        try:
            return self._localize(frame, stamp, prior)
        finally:
            self._frame = None  # not held beyond the frame

    def _localize(self, frame: np.ndarray, stamp: float, prior: Rigid3d | None) -> FrameResult:
        self.cache.collect(self._st)
        known = self._known_pose(stamp)
        if known is None and prior is not None and prior.is_finite():
            # Lost or new, with an outside estimate (a failover, GPS): first the part that
            # covers it best, searched around it; then the parts by their vote.
            k = int(np.argmax(self.set.parts_near(prior)))
            if k == self.part or self._ready(k):
                if k != self.part:
                    self._switch(k)
                assert self.inner is not None
                res = self.inner.localize(frame, stamp, prior)
                if self.inner.last_posed_stamp != stamp:
                    self._fails = {k: 1}
                    res = self._search(frame, stamp, res)
            else:  # its part loads for the next frames; the vote's resident parts meanwhile
                res = self._search(frame, stamp, None)
        elif known is not None:
            self._follow(*known)
            assert self.inner is not None
            res = self.inner.localize(frame, stamp)
            if self.inner.last_posed_stamp != stamp:
                # Tracked, then nothing on its part: the camera left it (a jump, a teleport
                # between rooms) or the frame is bad. The same frame searches the parts by
                # their vote now rather than from the next frame on.
                self._fails = {self.part: 1} if self.part is not None else {}
                res = self._search(frame, stamp, res)
            elif res.status is Status.LOST and self.part is not None:
                self._withheld_on.append(self.part)  # the next frame tries another part
            else:
                self._withheld_on = []
        else:
            res = self._search(frame, stamp, None)
        self._prev_stamp = stamp
        if self.inner is not None and self.inner.last_posed_stamp == stamp:
            self._fails = {}  # a pose (published or withheld): the search is over
            self._votes = None
        self.stats.max_resident_bytes = max(
            self.stats.max_resident_bytes, self.cache.resident_bytes()
        )
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
        if inner.bundle is None:  # it let its part go in a search: searching again
            return None
        if inner.last_posed_stamp != self._prev_stamp:
            return None
        if not 0 <= stamp - inner.last_posed_stamp <= self.conf.max_frame_gap_s:
            return None
        return inner.filter.current(), np.asarray(inner.filter.velocity, float)

    def resident_parts(self) -> list[int]:
        return self.cache.resident_parts()

    def loading_parts(self) -> list[int]:
        """Parts being loaded on the loader thread."""
        return self.cache.loading_parts()

    def resident_bytes(self) -> int:
        """Bytes of the resident parts plus those being loaded (what the budget bounds)."""
        return self.cache.resident_bytes()

    def close(self) -> None:
        """End the session: its part may be evicted (and its own cache is closed)."""
        self.cache.unregister(self)
        self.part = None
        self.inner = None
        if self._own_cache:
            self.cache.close()

    # ------------------------------------------------------------------ tracked
    def _follow(self, pose: Rigid3d, velocity: np.ndarray) -> None:
        cover = self.set.parts_near(pose)
        best = int(np.argmax(cover))
        cur = self.part
        want = best
        if cur is not None and cover[best] <= cover[cur] * (1.0 + self.switch_margin):
            want = cur  # hysteresis: no flapping along a boundary
        if self._withheld_on:
            # Poses withheld on the parts tried since the last published one: those parts lack
            # what the camera sees. The next part covering the pose nearly as well is tried
            # (24 rooms in 72 parts: three parts held the same cameras near a camera walking
            # away from them; on the first, 26 inliers fell to 12 and 10 frames were withheld
            # while the whole map kept 40-50).
            alt = [
                int(k)
                for k in np.argsort(-cover, kind="stable")
                if k not in self._withheld_on and cover[k] >= 0.5 * cover[best] > 0
            ]
            if alt:
                want = alt[0]
        if want != cur:
            if self.cache.get(want) is not None:
                self._switch(want)
            elif not self.cache.request(want, keep=set(), stats=self._st):
                # The budget cannot hold both: this frame waits for the load (the current
                # part may be evicted: the switch translates the table from its point ids).
                self._load_and_switch(want)
        # Ahead of the camera: the part covering the pose ``lookahead_s`` from now best.
        ahead = pose.center + velocity * self.lookahead_s
        if np.all(np.isfinite(ahead)):
            ahead_pose = Rigid3d(pose.rotation, -pose.rotation @ ahead)
            nxt = int(np.argmax(self.set.parts_near(ahead_pose)))
            if not self.cache.is_pending(nxt):
                self.cache.request(nxt, keep={want}, optional=True, stats=self._st)

    # ------------------------------------------------------------------ lost
    def vote(self, frame: np.ndarray) -> np.ndarray:
        """The parts' place-recognition scores for ``frame`` (``SubmapSet.vote`` of its
        keypoints' descriptors)."""
        return self.set.vote(self._frame_descriptors(frame))

    def _lost_vote(self, frame: np.ndarray, stamp: float) -> np.ndarray:
        """The order a lost frame tries the parts in: its vote plus ``VOTE_MEMORY`` times
        that of the session's lost frames before it (since its last pose; they are mostly of
        the same place). One frame's vote alone put the parts of one place in a different
        order from frame to frame (24 rooms, room 7: its first five parts changed on each of
        five frames), so the part a frame had loaded for the next was seldom the one the
        next frame wanted first, and that frame waited for a load or was answered LOST."""
        if self._vote_of is not None and self._vote_of[0] == stamp:
            return self._vote_of[1]
        scores = self.vote(frame)
        self.stats.votes += 1
        if self._votes is not None and len(self._votes) == len(scores):
            scores = scores + VOTE_MEMORY * self._votes
        self._votes = scores
        self._vote_of = (stamp, scores)
        return scores

    def _search(self, frame: np.ndarray, stamp: float, res: FrameResult | None) -> FrameResult:
        """Parts in the order of the frame's vote until one gives a pose (``res``: the frame's
        answer on the part it tracked on, not tried again in this frame): first the best-voted
        part, every frame (a part that failed on one frame may hold the next: 24 rooms, room
        8's first frame failed on the part that had its next 35 frames, and the session, which
        went on only to parts it had not tried, never came back to it), then the best-voted
        ones not tried since the session was lost (``_next_part``), so that consecutive lost
        frames go down the order. ``lost_parts_per_frame`` parts at least, then more while
        the frame's search has used less than ``conf.submap_search_cpu_ms`` of this thread's
        CPU (at most ``conf.submap_search_max_parts``)."""
        self._withheld_on = []  # lost: the parts are chosen by the vote again
        t_cpu = time.thread_time()
        budget_ms = self.conf.submap_search_cpu_ms
        cap = self.lost_parts_per_frame
        if budget_ms > 0:
            cap = max(cap, self.conf.submap_search_max_parts)
        scores = self._lost_vote(frame, stamp)  # (taken early when tracking failed)
        order = [int(k) for k in np.argsort(-scores, kind="stable")]
        here = [self.part] if res is not None and self.part is not None else []
        tries = 0
        for _ in range(cap):
            ahead = self._upcoming(order, here, scores)
            if not ahead:
                break  # this frame has met every part
            # The first of the next parts of the order that is resident (the one it loaded
            # while the last part was matched: the next may not fit beside that one), else
            # the next, loaded now.
            k = next((j for j in ahead if self.cache.is_resident(j)), ahead[0])
            if tries >= self.lost_parts_per_frame and (
                (time.thread_time() - t_cpu) * 1e3 >= budget_ms
            ):
                break
            self.cache.collect(self._st)
            pending = self.cache.is_pending(k)
            if k != self.part and not self._ready(k):
                # Not resident within what the frame may still wait (usually it is: the
                # frame's vote started it as its tracking failed, ``_early_vote``, or it loaded
                # while the part before it was matched): it loads on the thread for the next
                # frame, which goes on from it (the search spreads over frames, none stalls).
                self.stats.unready_parts += 1
                break
            here.append(k)
            self.stats.prefetched_tries += pending  # resident or loading when chosen
            if k != self.part:
                self._switch(k)
            # The part to try if this one fails loads on the thread while this one is matched
            # (it may evict the parts this frame has met: they failed it): the first of the
            # next ones that fits beside this one (~2 parts in the budget: the next often
            # does not, and the frame stopped there for its load).
            self._load_ahead(self._upcoming(order, here, scores), keep={k})
            assert self.inner is not None
            self.stats.lost_tries += 1
            tries += 1
            res = self.inner.localize(frame, stamp)
            if self.inner.last_posed_stamp == stamp:
                break
            self._fails[k] = self._fails.get(k, 0) + 1
        if self.inner is None or self.inner.last_posed_stamp != stamp:
            # An earlier frame's failure counts less with each lost frame, as its vote does
            # (``FAIL_MEMORY``): counted in full, a place the vote preferred by far but whose
            # parts pose only some of its frames (24 rooms, room 13: its three parts voted
            # ~10x any other, each failing frames 1-5 on the ambiguity test) sank below
            # places the vote hardly saw after four failures, and the frames' CPU went to
            # those: room 13 lost 30 frames in a row in one run of three.
            self._fails = {j: n * FAIL_MEMORY for j, n in self._fails.items()}
            # No pose: the part the next frame's search starts with (the order with this
            # frame's failures counted) loads now. Loading only the next part of this frame's
            # order, the last try's load evicted the part the next frame wanted first, which
            # then waited for it or was answered LOST (24 rooms: 13 frames "loading").
            self._load_ahead(self._upcoming(order, [], scores), keep=set(), release=True)
        self.stats.search_cpu_ms += (time.thread_time() - t_cpu) * 1e3
        if res is None:
            self.stats.unready_lost += 1
            return FrameResult(
                Status.LOST,
                stamp,
                message="sub-maps loading: the parts this frame's vote ranks first are not "
                "resident yet (tried from the next frame on)",
            )
        return res

    def _upcoming(self, order: list[int], here: list[int], scores: np.ndarray) -> list[int]:
        """The next ``EARLY_CANDIDATES`` parts a lost frame would meet after ``here``, in
        ``_next_part``'s order."""
        out: list[int] = []
        for _ in range(EARLY_CANDIDATES):
            k = self._next_part(order, here, scores, out)
            if k is None:
                break
            out.append(k)
        return out

    def _load_ahead(self, parts: list[int], keep: set[int], release: bool = False) -> None:
        """Load the first of ``parts`` (in order) that fits the budget beside ``keep``,
        unless one before it is resident or loading already."""
        for j in parts:
            if self.cache.is_pending(j):
                return
            if self.cache.request(
                j, keep=keep, optional=True, stats=self._st, release=self if release else None
            ):
                return

    def _ready(self, k: int) -> bool:
        """Part ``k`` resident now, or within what this frame may still wait
        (``EngineConf.submap_load_wait_ms`` for the whole frame: the wait counts as a stall)
        of its load on the thread, started here within the budget when not running. A lost
        frame's own part may go to make room (it has just failed the frame): when the budget
        cannot hold ``k`` beside it, the session lets go of it for ``k`` (it used to load
        ``k`` in the frame's thread then, a stall of the whole load)."""
        if self.cache.get(k) is not None:
            return True
        if not self.cache.is_pending(k):
            self.cache.request(k, keep=set(), optional=True, stats=self._st, release=self)
        if self.cache.is_resident(k):
            return True
        if self._wait_left <= 0 or not self.cache.is_loading(k):
            return False
        t0 = time.perf_counter()
        ok = self.cache.wait_for(k, self._wait_left, self._st)
        self._wait_left -= time.perf_counter() - t0
        return ok

    def _early_vote(self) -> None:
        """The frame being localized found no pose by tracking on its part and is about to be
        matched globally against it (``Localizer.before_global_matching``): its vote is taken
        now, and the part its search would try first starts loading while that matching
        runs (~200 ms CPU when the part does not hold the frame: a teleport, a room entry),
        instead of when the search asks for it (the search then waited for the load:
        issue 14's stalls). The vote is kept for the search (one per frame either way); a
        frame posed by its own part paid for a vote it did not need (rare: a tracked
        session meets global matching when its tracks are gone)."""
        frame, stamp = self._frame, self._stamp
        if (
            frame is None
            or stamp is None
            or (self._vote_of is not None and self._vote_of[0] == stamp)
        ):
            return
        scores = self._lost_vote(frame, stamp)
        order = [int(k) for k in np.argsort(-scores, kind="stable")]
        here = [self.part] if self.part is not None else []
        fails = self._fails
        self._fails = {**fails, **{p: fails.get(p, 0) + 1 for p in here}}  # as the search will
        try:
            # The first part of the search's order that fits beside the session's own (which
            # the frame is using), among the first ``EARLY_CANDIDATES``: with ~2 parts in
            # the budget the best-voted one often does not, and the next is mostly another
            # part of the same place.
            met = list(here)
            for _ in range(EARLY_CANDIDATES):
                k = self._next_part(order, met, scores)
                if k is None or self.cache.is_pending(k) or scores[k] <= 0:
                    return
                if self.cache.request(k, keep=set(here), optional=True, stats=self._st):
                    self.cache.note_early(self._st)
                    return
                met.append(k)
        finally:
            self._fails = fails

    def _next_part(
        self, order: list[int], here: list[int], scores: np.ndarray, skip: Sequence[int] = ()
    ) -> int | None:
        """The next part a lost frame tries (``order``: its vote's, ``scores`` the vote;
        ``here``: the parts it met already), None when it has met every part: the best by
        the vote discounted by ``PLACE_DISCOUNT`` for each part of the same place (at least
        ``SAME_PLACE`` of its images in that part) the frame met, and by ``RETRY_DISCOUNT``
        for each lost frame the part failed since the session was lost (equal ones: other
        places first, then the less tried, then the vote's order).

        Overlapping parts of one place often fail together on a frame (24 rooms, 3 parts each:
        the vote ranked a look-alike room's three parts before the right room's, and the first
        frames of rooms 11 and 15 spent both their tries on them), so another place comes
        next, unless the vote prefers this place by far: the right room's best-voted part may
        fail on the second-place or spread test where another part of the room poses the
        frame (rooms 8 and 13: room 13 voted 15, 14 and 7 against at most 3 for the other
        rooms; its first part failed 24 frames in a row, its third posed frame 0). A part
        that failed is tried again on later frames rather than never until every part was
        (the camera moves: room 8's first frame failed on the part that held its next 35
        frames), after the parts the vote prefers about as much and have not failed."""
        cand = np.asarray([k for k in order if k not in here and k not in skip], np.int64)
        if len(cand) == 0:
            return None
        same = np.zeros(self.set.n_parts)
        for t in here:
            same += self.set.covered_by([t]) >= SAME_PLACE
        fails = np.array([self._fails.get(int(k), 0) for k in cand], float)
        eff = np.maximum(scores[cand], 0.0) * PLACE_DISCOUNT ** same[cand]
        eff = eff * RETRY_DISCOUNT**fails
        key = np.lexsort((np.arange(len(cand)), fails, same[cand], -eff))
        return int(cand[key[0]])

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
    def _load_and_switch(self, k: int) -> None:
        # The current part may go to make room (unless another session is on it): the session
        # lets go of it before the load (``_let_go``), and the switch translates the table
        # from its point ids, kept in ``_part_points``.
        try:
            self.cache.load_now(k, self._st, release=self)
        except BaseException:
            if self.inner is not None and self.inner.bundle is None:
                # It let its part go and the load failed: the next frame starts afresh.
                self.inner = None
                self.part = None
                self._part_points = None
            raise
        self._switch(k)

    def _let_go(self) -> None:
        """The cache evicted this session's part to load another in its place: no reference
        to it may outlive this call (the kernel keeps a part's pages resident while anything
        maps it); the track table keeps the part's global ids (``_part_points``)."""
        if self.inner is not None:
            self.inner.detach_bundle()
        self._left = self.part
        self.part = None  # not pinned any more; ``_switch`` attaches the next part

    def _switch(self, k: int) -> None:
        part = self.cache.get(k)
        assert part is not None
        bundle, gpts = part
        if self.inner is None:
            self.inner = Localizer(bundle, self.camera_in, self.conf)
            # Weakly: the localizer must not keep its session alive (a reference cycle would
            # keep the session's part mapped until the garbage collector ran).
            early = weakref.WeakMethod(self._early_vote)
            self.inner.before_global_matching = lambda: _call_weak(early)
        else:
            old_pts = self._part_points  # set with ``inner``
            assert old_pts is not None
            self.inner.swap_bundle(bundle, lambda rows: translate(rows, old_pts, gpts))
        was = self.part if self.part is not None else self._left
        if was != k:
            self.stats.switches += was is not None
            log.debug("sub-map %s -> %s", was, k)
        self.part = k
        self._left = None
        self._part_points = gpts  # the table is translated from it at the next switch
        self.stats.parts_used.add(k)
