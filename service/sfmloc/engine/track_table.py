"""The track table T of Algorithm 1: one row per tracked keypoint.

Per keypoint: its track (id, current position, age), its BRIEF descriptor (updated as it is
tracked), its verified 2D-3D match (reused as long as the keypoint is tracked), its one-to-many
3D hypotheses from the last matching attempt (re-verified against later poses), and whether its
matching is still pending (lazy: a keypoint that stops being tracked is never described).
Struct of arrays, compacted when tracks are lost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..features.brief import N_WORDS


@dataclass
class TrackTable:
    track_id: np.ndarray  # (N,) int64
    xy: np.ndarray  # (N, 2) float64, current image position (COLMAP convention)
    brief: np.ndarray  # (N, 4) uint64
    age: np.ndarray  # (N,) int32, frames tracked
    point: np.ndarray  # (N,) int64, verified 3D point row, -1 when none
    hyp: np.ndarray  # (N, H) int64, one-to-many 3D hypotheses, -1 padded
    pending: np.ndarray  # (N,) bool, guided matching not yet attempted
    n_hyp: int

    @classmethod
    def empty(cls, n_hyp: int) -> TrackTable:
        return cls(
            np.zeros(0, np.int64),
            np.zeros((0, 2)),
            np.zeros((0, N_WORDS), np.uint64),
            np.zeros(0, np.int32),
            np.zeros(0, np.int64),
            np.zeros((0, n_hyp), np.int64),
            np.zeros(0, bool),
            n_hyp,
        )

    def __len__(self) -> int:
        return len(self.track_id)

    def take(self, mask_or_index: np.ndarray) -> TrackTable:
        """A new table of the given rows (boolean mask or indices), in that order; this one is
        left as it is."""
        if mask_or_index.dtype == bool:  # one nonzero, not one per column (7 of them)
            mask_or_index = np.flatnonzero(mask_or_index)
        return TrackTable(
            self.track_id[mask_or_index],
            self.xy[mask_or_index],
            self.brief[mask_or_index],
            self.age[mask_or_index],
            self.point[mask_or_index],
            self.hyp[mask_or_index],
            self.pending[mask_or_index],
            self.n_hyp,
        )

    def tracked(self, rows: np.ndarray, xy: np.ndarray, brief: np.ndarray) -> TrackTable:
        """TRACK-2D's new table: the given rows (indices), in that order, moved to ``xy`` with
        the descriptors ``brief``, one frame older; this one is left as it is. (Not ``take``
        and then new positions: its two gathers of the old ones were thrown away.)"""
        return TrackTable(
            self.track_id[rows],
            xy,
            brief,
            self.age[rows] + 1,
            self.point[rows],
            self.hyp.take(rows, 0),  # (take: x3-8 faster than integer indexing of (n, k) rows)
            self.pending[rows],
            self.n_hyp,
        )

    def keep(self, mask_or_index: np.ndarray) -> None:
        """Keep only the given rows (boolean mask or indices), in that order."""
        for name in ("track_id", "xy", "brief", "age", "point", "hyp", "pending"):
            setattr(self, name, getattr(self, name)[mask_or_index])

    def append(self, track_id: np.ndarray, xy: np.ndarray, brief: np.ndarray) -> None:
        """New keypoints: no 3D match, matching pending."""
        n = len(track_id)
        self.track_id = np.concatenate([self.track_id, track_id])
        self.xy = np.concatenate([self.xy, xy])
        self.brief = np.concatenate([self.brief, brief])
        self.age = np.concatenate([self.age, np.zeros(n, np.int32)])
        self.point = np.concatenate([self.point, np.full(n, -1, np.int64)])
        self.hyp = np.concatenate([self.hyp, np.full((n, self.n_hyp), -1, np.int64)])
        self.pending = np.concatenate([self.pending, np.ones(n, bool)])

    @property
    def has_3d(self) -> np.ndarray:
        return self.point >= 0

    def n_3d(self) -> int:
        return int(np.count_nonzero(self.point >= 0))

    def matches(self) -> tuple[np.ndarray, np.ndarray]:
        """FETCH-2D-3D-MATCHES-FROM-TABLE: (rows, 3D point rows) of verified matches."""
        rows = np.nonzero(self.point >= 0)[0]
        return rows, self.point[rows]
