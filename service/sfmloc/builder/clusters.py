"""Overlapping camera clusters for place recognition (paper Section 2, "Place recognition").

Like Furukawa et al.'s overlapping view clustering (CMVS), which the paper follows:

1. **Disjoint partition** of the covisibility graph (images are nodes, edge weight = number
   of 3D points two images share) by recursive normalized-cut bisection (the Fiedler vector
   of the normalized Laplacian) until every part has at most ``max_size`` images.
2. **Growth**: each cluster greedily takes images from outside that see the most of its
   *under-covered* 3D points (seen by fewer than ``coverage_views`` of its images), until it
   has grown by ``growth`` times its size or no outside image adds coverage. Clusters
   therefore overlap where the scene is seen from several places.

A 3D point belongs to every cluster that contains at least one image of its track (each point
"knows every cluster it belongs to"); global matching votes for all of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import eigsh

from ..config import StrictModel


class ClusterConf(StrictModel):
    max_size: int = 8  # images per disjoint part
    growth: float = 0.5  # a cluster may grow by this fraction of its size
    coverage_views: int = 2  # a point is covered when this many cluster images see it
    min_shared: int = 10  # an outside image must share this many points to be considered


@dataclass
class Clusters:
    images: list[np.ndarray]  # per cluster: sorted image indices

    def __len__(self) -> int:
        return len(self.images)

    def point_clusters(
        self, image_points: list[np.ndarray], n_points: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """CSR (ptr, idx): for each point, the clusters it belongs to."""
        rows, cols = [], []
        for c, imgs in enumerate(self.images):
            pts = (
                np.unique(np.concatenate([image_points[i] for i in imgs]))
                if len(imgs)
                else np.zeros(0, np.int64)
            )
            rows.append(pts)
            cols.append(np.full(len(pts), c, np.int64))
        r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
        col = np.concatenate(cols) if cols else np.zeros(0, np.int64)
        m = sp.csr_matrix((np.ones(len(r), np.int8), (r, col)), shape=(n_points, len(self.images)))
        m.sort_indices()
        return m.indptr.astype(np.int64), m.indices.astype(np.int32)


def visibility_matrix(image_points: list[np.ndarray], n_points: int) -> sp.csr_matrix:
    """Sparse (images x points) 0/1 matrix."""
    rows = (
        np.concatenate([np.full(len(p), i, np.int64) for i, p in enumerate(image_points)])
        if image_points
        else np.zeros(0, np.int64)
    )
    cols = np.concatenate(image_points) if image_points else np.zeros(0, np.int64)
    V = sp.csr_matrix(
        (np.ones(len(rows), np.float32), (rows, cols)), shape=(len(image_points), n_points)
    )
    V.data[:] = 1.0  # duplicates collapse to 1
    return V


def cluster_images(
    image_points: list[np.ndarray], n_points: int, conf: ClusterConf | None = None
) -> Clusters:
    """Overlapping clusters of images from their visible points."""
    conf = conf or ClusterConf()
    n = len(image_points)
    if n == 0:
        return Clusters([])
    V = visibility_matrix(image_points, n_points)
    W = (V @ V.T).tocsr().astype(np.float64)
    W.setdiag(0)
    W.eliminate_zeros()
    parts = _partition(W, np.arange(n), conf.max_size)
    grown = [_grow(p, V, W, conf) for p in parts]
    return Clusters([np.sort(g) for g in grown])


def _partition(W: sp.csr_matrix, nodes: np.ndarray, max_size: int) -> list[np.ndarray]:
    """Recursive normalized-cut bisection; disconnected components are always split first
    (images that share no point must never vote together)."""
    if len(nodes) <= 1:
        return [nodes]
    sub = W[nodes][:, nodes]
    n_comp, labels = sp.csgraph.connected_components(sub, directed=False)
    if n_comp > 1:
        out: list[np.ndarray] = []
        for c in range(n_comp):
            out.extend(_partition(W, nodes[labels == c], max_size))
        return out
    if len(nodes) <= max_size:
        return [nodes]
    side = _fiedler_split(sub)
    if side.all() or not side.any():  # degenerate: split in half by index
        side = np.arange(len(nodes)) < len(nodes) // 2
    return _partition(W, nodes[side], max_size) + _partition(W, nodes[~side], max_size)


def _fiedler_split(A: sp.csr_matrix) -> np.ndarray:
    """Sign of the second eigenvector of the normalized Laplacian (a relaxed normalized cut),
    thresholded at the median so the halves are balanced."""
    n = A.shape[0]
    d = np.asarray(A.sum(axis=1)).ravel()
    dinv = 1.0 / np.sqrt(np.maximum(d, 1e-12))
    Dm = sp.diags(dinv)
    M = (Dm @ A @ Dm).tocsr()  # eigenvectors of D^-1/2 A D^-1/2: largest <-> smallest of L
    if n <= 64:
        vals, vecs = np.linalg.eigh(M.toarray())
        f = vecs[:, -2]
    else:
        vals, vecs = eigsh(M, k=2, which="LA", v0=np.full(n, 1.0 / np.sqrt(n)))
        f = vecs[:, np.argsort(vals)[0]]
    f = f * dinv
    return f > np.median(f)


def _grow(part: np.ndarray, V: sp.csr_matrix, W: sp.csr_matrix, conf: ClusterConf) -> np.ndarray:
    members = set(int(i) for i in part)
    limit = len(part) + int(np.floor(conf.growth * len(part)))
    counts = np.asarray(V[list(members)].sum(axis=0)).ravel()  # per point: views in cluster
    while len(members) < limit:
        neigh = set(W[list(members)].indices.tolist()) - members
        if not neigh:
            break
        under = (counts > 0) & (counts < conf.coverage_views)
        if not under.any():
            break
        cand = np.array(sorted(neigh))
        gain = np.asarray(V[cand][:, under].sum(axis=1)).ravel()
        shared = np.asarray(V[cand][:, counts > 0].sum(axis=1)).ravel()
        gain[shared < conf.min_shared] = 0
        best = int(np.argmax(gain))
        if gain[best] <= 0:
            break
        members.add(int(cand[best]))
        counts += np.asarray(V[int(cand[best])].todense()).ravel()
    return np.array(sorted(members), dtype=np.int64)
