"""2D-to-3D matching against the map (paper Sections 2.1 and 2.2).

``global_matching``: k-ANN over all map descriptors; every neighbour within sigma times the
nearest distance votes, with strength s_i0 / s_ij, for every cluster its 3D point belongs to
(by default each query votes once per cluster, with its strongest neighbour there: see
``EngineConf.vote``);
clusters scoring at least beta times the best select the database images S; neighbours outside
S are dropped; per keypoint, 3D point strengths are the summed strengths of their descriptors;
set 1 holds each keypoint's best point when the best two pass the ratio test (0.75), set 2 every
point whose strength is within that ratio of the best (one-to-many).

``guided_matching``: the scope is the top-30 database images by number of already-matched 3D
points they see (an image counts for a fraction of one where the map holds near-duplicates of
it: ``scope.image_weights``); the k-ANN search is restricted to their descriptors (faiss rejects
the others before computing distances); the same strengths give one-to-many hypotheses, which
are verified geometrically against the pose from the known matches.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from ..map.bundle import MapBundle
from ..map.index import bitmap_from_ranges
from ..transforms import Rigid3d
from .config import EngineConf
from .pose import reprojection_errors
from .scope import guided_nprobe, image_weights


@dataclass
class PointCandidates:
    """Per query keypoint, its 3D points by decreasing strength (CSR: ``ptr``, ``point``,
    ``strength``)."""

    ptr: np.ndarray  # (Q+1,)
    point: np.ndarray
    strength: np.ndarray

    def best(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(query ids with any candidate, best strength, second-best strength or 0)."""
        n = np.diff(self.ptr)
        q = np.nonzero(n > 0)[0]
        s1 = self.strength[self.ptr[q]]
        s2 = np.where(
            n[q] > 1, self.strength[np.minimum(self.ptr[q] + 1, len(self.strength) - 1)], 0.0
        )
        return q, s1, s2


def neighbour_strengths(D: np.ndarray, I: np.ndarray, sigma: float) -> np.ndarray:
    """s_i0 / s_ij for neighbours within sigma * s_i0 (0 elsewhere, and for missing ones)."""
    s0 = np.broadcast_to(np.maximum(D[:, :1], 1e-6), D.shape)
    valid = (I >= 0) & np.isfinite(D) & (D < sigma * s0)
    w = np.zeros(D.shape, np.float64)
    w[valid] = s0[valid] / np.maximum(D[valid], 1e-6)
    return w


def search_all(
    desc: np.ndarray, bundle: MapBundle, conf: EngineConf
) -> tuple[np.ndarray, np.ndarray]:
    """The k-ANN search of ``desc`` over the whole map (global matching's)."""
    return bundle.index.search(desc, conf.k, nprobe=conf.nprobe)


def restrict_neighbours(
    D: np.ndarray, I: np.ndarray, allowed: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The neighbours whose descriptor is ``allowed`` (bool per descriptor row), in their order
    at the front of each row; the rest missing (id -1, distance inf): a scoped search's
    answer from an unscoped one, as far as its k neighbours reach."""
    ok = (I >= 0) & allowed[np.maximum(I, 0)]
    order = np.argsort(~ok, axis=1, kind="stable")
    D = np.where(ok, D, np.inf).astype(D.dtype, copy=False)
    I = np.where(ok, I, -1)
    return np.take_along_axis(D, order, 1), np.take_along_axis(I, order, 1)


def point_candidates(I: np.ndarray, w: np.ndarray, desc_point: np.ndarray) -> PointCandidates:
    """Sum descriptor strengths per (query, 3D point); sort each query's points by strength."""
    q_idx, j_idx = np.nonzero(w > 0)
    nq = len(I)
    if len(q_idx) == 0:
        return PointCandidates(np.zeros(nq + 1, np.int64), np.zeros(0, np.int64), np.zeros(0))
    pts = desc_point[I[q_idx, j_idx]].astype(np.int64)
    ws = w[q_idx, j_idx]
    # by (query, point): one stable sort of a combined key (q_idx is already sorted)
    order = np.argsort(q_idx * (int(pts.max()) + 1) + pts, kind="stable")
    q_s, p_s, w_s = q_idx[order], pts[order], ws[order]
    new = np.ones(len(q_s), bool)
    new[1:] = (q_s[1:] != q_s[:-1]) | (p_s[1:] != p_s[:-1])
    starts = np.nonzero(new)[0]
    sums = np.add.reduceat(w_s, starts)
    uq, up = q_s[starts], p_s[starts]
    order = np.lexsort((-sums, uq))
    uq, up, sums = uq[order], up[order], sums[order]
    ptr = np.zeros(nq + 1, np.int64)
    ptr[1:] = np.cumsum(np.bincount(uq, minlength=nq))
    return PointCandidates(ptr, up, sums)


def match_sets(
    cands: PointCandidates, ratio: float, max_hyp: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Set 1 (query, point) passing the ratio test, most distinctive first; set 2 (query, point)
    one-to-many, grouped by query."""
    q, s1, s2 = cands.best()
    pass1 = s2 < ratio * s1
    # Most distinctive first: RANSAC samples from the front (on redkitchen the first fifth is
    # 84% correct, the last fifth 17%).
    order = np.argsort((s2 / s1)[pass1], kind="stable")
    set1_q = q[pass1][order]
    set1_p = cands.point[cands.ptr[set1_q]]
    # set 2: per query, points with strength >= ratio * best, at most max_hyp
    n = np.diff(cands.ptr)
    owner = np.repeat(np.arange(len(n)), n)
    rank = np.arange(len(owner)) - cands.ptr[owner]
    best = np.zeros(len(n))
    best[q] = s1
    keep = (cands.strength >= ratio * best[owner]) & (rank < max_hyp)
    return set1_q, set1_p, owner[keep], cands.point[keep]


@dataclass
class GlobalMatches:
    set1_q: np.ndarray
    set1_p: np.ndarray
    set2_q: np.ndarray
    set2_p: np.ndarray
    clusters: np.ndarray  # selected clusters
    n_images: int  # |S|
    # The k-ANN search over the whole map behind them, (distances, ids) (N, k): verification
    # restricts it to its scope instead of searching again (``guided_matching``).
    neighbours: tuple[np.ndarray, np.ndarray] | None = None


def global_matching(
    desc: np.ndarray,
    bundle: MapBundle,
    conf: EngineConf,
    neighbours: tuple[np.ndarray, np.ndarray] | None = None,
) -> GlobalMatches:
    """GLOBAL-MATCHING of ``desc``; ``neighbours``: their k-ANN search over the whole map when
    already made (``search_all``), else it is made here."""
    D, I = neighbours if neighbours is not None else search_all(desc, bundle, conf)
    w = neighbour_strengths(D, I, conf.sigma)
    bits = _point_cluster_bits(bundle) if conf.vote == "max" else None
    if bits is not None:
        scores = _max_votes(w, I, bundle, bits)
        if not scores.any():
            empty = np.zeros(0, np.int64)
            return GlobalMatches(empty, empty, empty, empty, empty, 0, (D, I))
        return _select_and_match(scores, w, I, bundle, conf, (D, I))
    qi, ji = np.nonzero(w > 0)
    pts = bundle.desc_point[I[qi, ji]]
    ws = w[qi, ji]
    # cluster votes: each neighbour votes for every cluster of its 3D point
    ptr = bundle.point_clusters_ptr
    cnt = ptr[pts + 1] - ptr[pts]
    total = int(cnt.sum())
    empty = np.zeros(0, np.int64)
    if total == 0:
        return GlobalMatches(empty, empty, empty, empty, empty, 0, (D, I))
    offs = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    clus = bundle.point_clusters_idx[np.repeat(ptr[pts], cnt) + offs]
    votes = np.repeat(ws, cnt)
    if conf.vote == "max":
        # One vote per (query, cluster), with the query's strongest neighbour in it. Entries
        # come in (query, neighbour rank) order and strengths fall with rank, so the first
        # entry of each (query, cluster) is its strongest: O(n), no sort.
        key = np.repeat(qi, cnt) * bundle.n_clusters + clus
        first = np.full(len(desc) * bundle.n_clusters, len(key), np.int64)
        np.minimum.at(first, key, np.arange(len(key)))
        first = first[first < len(key)]
        clus, votes = clus[first], votes[first]
    scores = np.bincount(clus, weights=votes, minlength=bundle.n_clusters)
    return _select_and_match(scores, w, I, bundle, conf, (D, I))


# Clusters a point's bits can hold (more: the entry-per-cluster votes above).
_MAX_BIT_CLUSTERS = 64
_bits_cache: weakref.WeakKeyDictionary[MapBundle, np.ndarray] = weakref.WeakKeyDictionary()


def _point_cluster_bits(bundle: MapBundle) -> np.ndarray | None:
    """Per map point, the clusters it belongs to as bits (uint64; cached per bundle), or None
    when the map has more than ``_MAX_BIT_CLUSTERS`` clusters."""
    if bundle.n_clusters > _MAX_BIT_CLUSTERS:
        return None
    bits = _bits_cache.get(bundle)
    if bits is None:
        ptr, idx = bundle.point_clusters_ptr, bundle.point_clusters_idx
        owner = np.repeat(np.arange(len(ptr) - 1), np.diff(ptr))
        bits = np.zeros(len(ptr) - 1, np.uint64)
        np.bitwise_or.at(bits, owner, np.left_shift(np.uint64(1), idx.astype(np.uint64)))
        _bits_cache[bundle] = bits
    return bits


def _max_votes(w: np.ndarray, I: np.ndarray, bundle: MapBundle, bits: np.ndarray) -> np.ndarray:
    """Cluster scores of ``vote == "max"``: per query and cluster the strength of its first
    neighbour there (strengths fall with the rank: its strongest), summed over the queries.
    A neighbour votes for the clusters of its point that no better-ranked neighbour of its
    query reached (its bits less the running OR of the row); the votes in query order, as
    the entry-per-cluster bincount adds them: the same sums (issue 10: without expanding
    every neighbour over its clusters)."""
    b = np.where(w > 0, bits[bundle.desc_point[np.maximum(I, 0)]], np.uint64(0))  # (Q, k)
    seen = np.bitwise_or.accumulate(b, axis=1)
    fresh = b.copy()
    fresh[:, 1:] &= ~seen[:, :-1]
    q, j = np.nonzero(fresh)  # row-major: query order
    masks = np.uint64(1) << np.arange(bundle.n_clusters, dtype=np.uint64)
    e, c = np.nonzero((fresh[q, j][:, None] & masks) != 0)
    return np.bincount(c, weights=w[q, j][e], minlength=bundle.n_clusters)


def _select_and_match(
    scores: np.ndarray,
    w: np.ndarray,
    I: np.ndarray,
    bundle: MapBundle,
    conf: EngineConf,
    neighbours: tuple[np.ndarray, np.ndarray],
) -> GlobalMatches:
    """The clusters scoring at least ``beta`` x the best select the images S; the matches
    from the neighbours in S."""
    selected = np.nonzero(scores >= conf.beta * scores.max())[0]
    in_s = np.zeros(bundle.n_images, bool)
    for c in selected:
        in_s[bundle.cluster_images(int(c))] = True
    # keep neighbours whose descriptor comes from an image in S
    w = np.where(in_s[bundle.desc_image[np.maximum(I, 0)]] & (I >= 0), w, 0.0)
    cands = point_candidates(I, w, bundle.desc_point)
    s1q, s1p, s2q, s2p = match_sets(cands, conf.ratio, conf.max_hypotheses)
    return GlobalMatches(s1q, s1p, s2q, s2p, selected, int(in_s.sum()), neighbours)


def scope_images(
    bundle: MapBundle, matched_points: np.ndarray, top: int, weights: np.ndarray | None = None
) -> np.ndarray:
    """The ``top`` database images seeing the most of ``matched_points`` (at least one).
    ``weights``: per image, the fraction of a place it counts for (``scope.image_weights``):
    ranked images are taken until their weights add up to ``top``."""
    pi_ptr, pi_idx = bundle.point_images()
    p = matched_points
    cnt = pi_ptr[p + 1] - pi_ptr[p]
    total = int(cnt.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offs = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    imgs = pi_idx[np.repeat(pi_ptr[p], cnt) + offs]
    counts = np.bincount(imgs, minlength=bundle.n_images)
    order = np.argsort(-counts, kind="stable")
    order = order[: int(np.count_nonzero(counts))]
    if weights is None:
        return order[:top]
    # the first images whose weights reach top (a little slack for the float sum)
    return order[: int(np.searchsorted(np.cumsum(weights[order]), top - 1e-6)) + 1]


@dataclass
class GuidedMatches:
    point: np.ndarray  # (B,) verified point per query or -1
    hyp: np.ndarray  # (B, H) hypotheses, -1 padded
    n_images: int


def guided_matching(
    desc: np.ndarray,
    xy_u: np.ndarray,
    bundle: MapBundle,
    matched_points: np.ndarray,
    cam_from_world: Rigid3d,
    K: np.ndarray,
    conf: EngineConf,
    neighbours: tuple[np.ndarray, np.ndarray] | None = None,
    ratio: float | None = None,
    nprobe: int | None = None,
) -> GuidedMatches:
    """Match a batch of keypoints (descriptors ``desc``, undistorted positions ``xy_u``) within
    the scope of the already-matched points, verify against ``cam_from_world``.

    ``neighbours``: an unscoped k-ANN search of these same descriptors (global matching's),
    restricted to the scope instead of a second search (``restrict_neighbours``).
    ``ratio``: the hypotheses' strength ratio instead of ``conf.ratio``; ``nprobe``: the
    scoped search's inverted lists instead of ``conf.nprobe`` (``guided_nprobe``)."""
    nq = len(desc)
    H = conf.max_hypotheses
    out = GuidedMatches(np.full(nq, -1, np.int64), np.full((nq, H), -1, np.int64), 0)
    imgs = scope_images(
        bundle,
        matched_points,
        conf.top_images,
        image_weights(bundle, conf.scope_radius, conf.scope_min_duplicates),
    )
    if nq == 0 or len(imgs) == 0:
        return out
    out.n_images = len(imgs)
    if neighbours is not None:
        in_scope = np.zeros(bundle.n_images, bool)
        in_scope[imgs] = True
        D, I = restrict_neighbours(*neighbours, in_scope[bundle.desc_image])
    else:
        ptr = bundle.image_desc_ptr
        allowed = bitmap_from_ranges(bundle.n_descriptors, ptr[imgs], ptr[imgs + 1])
        npr = guided_nprobe(bundle, conf, nprobe)
        D, I = bundle.index.search(desc, conf.k, allowed=allowed, nprobe=npr)
    w = neighbour_strengths(D, I, conf.sigma)
    cands = point_candidates(I, w, bundle.desc_point)
    _, _, q2, p2 = match_sets(cands, conf.ratio if ratio is None else ratio, H)
    if len(q2) == 0:
        return out
    # hypotheses table
    rank = np.arange(len(q2)) - np.searchsorted(q2, q2)
    out.hyp[q2, rank] = p2
    verify_hypotheses(
        out.hyp, xy_u, bundle.points_xyz, cam_from_world, K, conf.guided_threshold_px, out.point
    )
    return out


def verify_hypotheses(
    hyp: np.ndarray,
    xy_u: np.ndarray,
    points_xyz: np.ndarray,
    cam_from_world: Rigid3d,
    K: np.ndarray,
    threshold: float,
    out_point: np.ndarray,
) -> np.ndarray:
    """For each row, the hypothesis reprojecting closest to ``xy_u`` within ``threshold`` is
    written to ``out_point`` (rows without one keep their value). Returns rows verified."""
    has = hyp >= 0
    rows, cols = has.nonzero()
    if len(rows) == 0:
        return np.zeros(0, np.int64)
    # (the mask, not ``hyp[rows, cols]``: the same values in the same C order, one boolean
    # pass instead of a two-array gather: 3.90 -> 3.38 us on 1001 recorded redkitchen calls)
    pts = hyp[has]
    # (take: row gathers, x3-8 faster than integer indexing of (n, 2) / (n, 3) arrays, issue 10)
    err = reprojection_errors(cam_from_world, K, xy_u.take(rows, 0), points_xyz.take(pts, 0))
    ok = err < threshold
    rows, pts, err = rows[ok], pts[ok], err[ok]
    if len(rows) == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort((err, rows))
    rows, pts = rows[order], pts[order]
    first = np.ones(len(rows), bool)
    first[1:] = rows[1:] != rows[:-1]
    out_point[rows[first]] = pts[first]
    return rows[first]
