"""The approximate nearest-neighbour index over all map descriptors (paper Sections 2.1-2.2).

**Choice, by measurement** (150k real PCA-32 DAISY descriptors from the redkitchen map frames
at all pyramid levels, 2000 real query descriptors, k = 50, one thread; recall against exact
search; see the commit that introduced this file for the full table):

=================================  ==========  =========  =====  ===========
index                              us/query    recall@50  1-NN   bytes/desc
=================================  ==========  =========  =====  ===========
cv2.flann kd-forest (4), 256 chk   183         0.59       0.965  160
numpy IVF1024, nprobe 16           180         0.93       0.987  136
faiss IVF1024,SQ8, nprobe 16       30          0.93       0.976  40
faiss HNSW16,SQ8, ef 64            57          0.97       0.975  173
hnswlib M16, ef 64                 58          0.99       0.999  256
=================================  ==========  =========  =====  ===========

The paper's kd-tree priority search (FLANN) has poor recall at k = 50 and does not fit the
memory budget (130 MB per million descriptors, index included); graph indexes cost more
memory and cannot reject out-of-scope images *before* computing distances. An inverted file
with 8-bit scalar quantization (faiss ``IVF,SQ8``) is fast, compact, and its ``IDSelector``
rejects descriptors of images outside the guided-matching scope while scanning the lists,
before any distance is computed, which is exactly the paper's "rejected early rather than after
the search".

Distances returned are Euclidean (not squared), as the paper's voting ratios expect.
"""

from __future__ import annotations

import math
from typing import Literal

import faiss
import numpy as np

from ..config import StrictModel


class IndexConf(StrictModel):
    kind: Literal["ivf-sq8", "ivf-flat", "flat"] = "ivf-sq8"
    nlist: int | None = None  # inverted lists; None: about 4 sqrt(N), at least 39 points each
    nprobe: int = 16  # lists scanned per query (default; the engine may override)
    train_samples: int = 200_000


def choose_nlist(n: int) -> int:
    return max(1, min(int(4 * math.sqrt(n)), n // 39))


class DescriptorIndex:
    """A faiss index over descriptors whose ids are the descriptor rows of the bundle."""

    def __init__(self, index: faiss.Index, nprobe: int = 16) -> None:
        self._index = index
        self._ivf = _ivf_or_none(index)
        self.nprobe = nprobe
        self._buffer: np.ndarray | None = None
        # made on the first search that uses them, one per group size (``coarse_group_size``)
        self._coarse: dict[int, CoarseAssigner] = {}
        self._coarse_ok: bool | None = None  # whether the assigner applies (its first check)

    # ----------------------------------------------------------------- building / storage
    @classmethod
    def build(
        cls,
        descriptors: np.ndarray,
        conf: IndexConf | None = None,
        seed: int = 0,
        chunk_rows: int = 65536,
    ) -> DescriptorIndex:
        """Trained on a sample (``conf.train_samples``), filled ``chunk_rows`` at a time, so
        float16 descriptors are never all converted to float32 at once (build memory)."""
        conf = conf or IndexConf()
        x = descriptors
        n, d = x.shape
        kind = conf.kind
        nlist = conf.nlist or choose_nlist(n)
        if kind != "flat" and nlist < 4:
            kind = "flat"  # too few descriptors for an inverted file
        index: faiss.Index
        if kind == "flat":
            index = faiss.IndexFlatL2(d)
        else:
            quantizer = faiss.IndexFlatL2(d)
            ivf: faiss.IndexIVF
            if kind == "ivf-sq8":
                ivf = faiss.IndexIVFScalarQuantizer(
                    quantizer, d, nlist, faiss.ScalarQuantizer.QT_8bit
                )
            else:
                ivf = faiss.IndexIVFFlat(quantizer, d, nlist)
            ivf.cp.seed = seed  # deterministic k-means
            train = x
            if n > conf.train_samples:
                train = x[np.random.default_rng(seed).choice(n, conf.train_samples, replace=False)]
            ivf.train(np.ascontiguousarray(train, dtype=np.float32))
            ivf.own_fields = True
            # the IVF index owns its quantizer from here on (`this`: SWIG's proxy, not in stubs)
            quantizer.this.disown()  # type: ignore[attr-defined]
            index = ivf
        for start in range(0, n, max(1, chunk_rows)):
            index.add(np.ascontiguousarray(x[start : start + chunk_rows], dtype=np.float32))
        return cls(index, conf.nprobe)

    def add(self, descriptors: np.ndarray, chunk_rows: int = 65536) -> None:
        """Append descriptors (their ids continue from ``ntotal``), ``chunk_rows`` at a time;
        the index must be trained and private (not ``from_buffer``). For ``sfmloc build
        --extend``."""
        if self._buffer is not None:
            raise ValueError("an index read in place from a buffer is read-only")
        for start in range(0, len(descriptors), max(1, chunk_rows)):
            chunk = descriptors[start : start + chunk_rows]
            self._index.add(np.ascontiguousarray(chunk, dtype=np.float32))

    def write(self, path: str) -> None:
        """The bytes ``serialize`` returns, written to ``path`` (no copy in memory: the
        builder reads them back once the index is gone)."""
        faiss.write_index(self._index, str(path))

    def serialize(self) -> np.ndarray:
        """The index as a uint8 array (faiss's own stable binary format), to store as .npy."""
        return faiss.serialize_index(self._index)

    @classmethod
    def deserialize(cls, data: np.ndarray, nprobe: int = 16) -> DescriptorIndex:
        """A private copy of the index stored in ``data`` (see ``from_buffer`` to share it)."""
        return cls(faiss.deserialize_index(np.ascontiguousarray(data, dtype=np.uint8)), nprobe)

    @classmethod
    def from_buffer(cls, data: np.ndarray, nprobe: int = 16) -> DescriptorIndex:
        """The index read in place from ``data`` (the serialized bytes, typically the bundle's
        memory-mapped ``index_faiss.npy``): its inverted lists and centroids are views into
        ``data``, not copies (faiss's ``ZeroCopyIOReader``). Worker processes that map the same
        file then share one copy of the index in the page cache instead of holding one each
        (measured on a 600k-descriptor IVF-SQ8 index: 25 MB -> 1.4 MB anonymous memory per
        process, same search results). The index is read-only (nothing may be added) and
        keeps ``data`` alive. Falls back to a private copy where faiss cannot read in place
        (faiss < 1.10, or bytes that are not one contiguous uint8 array)."""
        buf = np.asarray(data)
        if (
            not hasattr(faiss, "ZeroCopyIOReader")
            or buf.dtype != np.uint8
            or buf.ndim != 1
            or not buf.flags.c_contiguous
            or buf.nbytes == 0
        ):
            return cls.deserialize(data, nprobe)
        reader = faiss.ZeroCopyIOReader(faiss.swig_ptr(buf), buf.nbytes)
        obj = cls(faiss.read_index(reader), nprobe)
        obj._buffer = buf  # the index's views point into it
        return obj

    @property
    def shared_buffer(self) -> np.ndarray | None:
        """The bytes the index reads in place (``from_buffer``), None for a private copy."""
        return self._buffer

    @property
    def ntotal(self) -> int:
        return int(self._index.ntotal)

    @property
    def kind(self) -> str:
        if self._ivf is None:
            return "flat"
        ivf = faiss.downcast_index(self._ivf)
        return "ivf-sq8" if isinstance(ivf, faiss.IndexIVFScalarQuantizer) else "ivf-flat"

    @property
    def nlist(self) -> int:
        return int(self._ivf.nlist) if self._ivf is not None else 1

    def memory_bytes(self) -> int:
        """Approximate resident size: codes + ids + coarse centroids."""
        if self._ivf is None:
            return int(self._index.ntotal * self._index.d * 4)
        code = int(self._ivf.code_size)
        return int(self._ivf.ntotal * (code + 8) + self._ivf.nlist * self._ivf.d * 4)

    # ----------------------------------------------------------------- search
    def search(
        self,
        queries: np.ndarray,
        k: int,
        allowed: np.ndarray | None = None,
        nprobe: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """k nearest descriptors of each query: (distances (N, k) float32, ids (N, k) int64),
        sorted by distance; missing neighbours have id -1 and distance inf.

        ``allowed`` (a uint8 bitmap over descriptor ids, little bit order, from
        ``bitmap_from_ranges``) restricts the search; out-of-scope descriptors are skipped
        before their distance is computed.
        """
        q = np.ascontiguousarray(queries, dtype=np.float32)
        if len(q) == 0:
            return np.zeros((0, k), np.float32), np.zeros((0, k), np.int64)
        npr = nprobe or self.nprobe
        # faiss's SearchParameters take keyword arguments (and keep the selector alive); its
        # stubs declare only __init__(self).
        params: faiss.SearchParameters | None = None
        if allowed is not None:
            sel = faiss.IDSelectorBitmap(len(allowed), faiss.swig_ptr(allowed))
            if self._ivf is not None:
                params = faiss.SearchParametersIVF(sel=sel, nprobe=npr)  # type: ignore[call-arg]
            else:
                params = faiss.SearchParameters(sel=sel)  # type: ignore[call-arg]
        elif self._ivf is not None:
            params = faiss.SearchParametersIVF(nprobe=npr)  # type: ignore[call-arg]
        coarse = self._coarse_assigner(len(q), npr)
        if coarse is not None:
            # The inverted lists to scan chosen here (``CoarseAssigner``: the same lists as the
            # flat quantizer's search, at about half its cost), then faiss scans them.
            Dq, Iq = coarse.assign(q, npr)
            D = np.empty((len(q), k), np.float32)
            I = np.empty((len(q), k), np.int64)
            self._ivf.search_preassigned_c(  # the raw call: the wrapper checks ivf.nprobe
                len(q),
                faiss.swig_ptr(q),
                k,
                faiss.swig_ptr(Iq),
                faiss.swig_ptr(Dq),
                faiss.swig_ptr(D),
                faiss.swig_ptr(I),
                False,
                params,
            )
        else:
            D, I = self._index.search(q, k, params=params)
        D = np.sqrt(np.maximum(D, 0.0), dtype=np.float32)
        D[I < 0] = np.inf
        return D, I

    def _coarse_assigner(self, n_queries: int, nprobe: int) -> CoarseAssigner | None:
        """The assigner for a search of ``n_queries`` (None: faiss's own quantizer search,
        for a flat index, an IVF whose quantizer is not flat L2 or not the index searched,
        few lists, or few queries, where a numpy call's overhead is the larger cost)."""
        if self._ivf is None or n_queries < COARSE_MIN_QUERIES:
            return None
        ivf = self._ivf
        if self._coarse_ok is None:
            flat = isinstance(faiss.downcast_index(ivf.quantizer), faiss.IndexFlatL2)
            same = isinstance(faiss.downcast_index(self._index), faiss.IndexIVF)
            self._coarse_ok = flat and same and ivf.nlist >= COARSE_MIN_LISTS
        if not self._coarse_ok:
            return None
        size = coarse_group_size(int(ivf.nlist), nprobe)
        got = self._coarse.get(size)
        if got is None:
            got = self._coarse[size] = CoarseAssigner(
                ivf.quantizer.reconstruct_n(0, ivf.nlist), size
            )
        return got if nprobe < got.n_groups else None


def coarse_group_size(n_lists: int, nprobe: int) -> int:
    """``CoarseAssigner``'s group size for ``nprobe`` lists of ``n_lists``: the power of two
    nearest sqrt(n_lists / nprobe), which balances its two selections (the group minima, about
    n_lists / size per query, and the nprobe best groups' members, nprobe x size). The lists
    chosen are the same for any size. Measured on redkitchen's 1,879 lists, real queries, one
    thread, against the size 32 used before (thread CPU, 48 interleaved calls each, nice 19,
    load 8): nprobe 16 (guided matching, size 8) 100 queries x0.67, 600 x0.62; nprobe 4
    (global matching, size 16) 300 queries x0.82, 600 x0.80, 1,000 x0.82; sizes 12 and 24 were
    slower than both, size 8 at nprobe 4 x0.90."""
    ideal = math.sqrt(max(1, n_lists) / max(1, nprobe))
    return int(min(64, max(4, 2 ** round(math.log2(max(ideal, 1.0))))))


# Below these the quantizer's own search is as fast (measured on redkitchen, 1,879 lists).
COARSE_MIN_QUERIES = 32
COARSE_MIN_LISTS = 256


class CoarseAssigner:
    """The ``nprobe`` nearest centroids of each query, exactly (ties aside), at about half
    the cost of faiss's flat quantizer search (issue 10: 1,879 centroids on redkitchen, that
    search was 40% of a relocalization's k-ANN search, ~8 ms for 600 queries of 32 dims, most
    of it selecting the nearest from each row of the distance matrix, not computing it).

    The centroids are split into G groups; a query's distances to all of them come from one
    matrix product, each group's minimum from G-wide elementwise minima (contiguous rows:
    the centroids are stored group-interleaved). The nprobe nearest centroids lie in the
    nprobe groups with the smallest minima (any centroid outside them is farther than those
    nprobe group minima, so at best the (nprobe+1)-th), and are selected among those groups'
    members only."""

    def __init__(self, centroids: np.ndarray, group_size: int = 16) -> None:
        c = np.asarray(centroids, np.float32)
        n, d = c.shape
        self.n_lists = n
        self.group_size = group_size
        self.n_groups = -(-n // group_size)
        m = self.n_groups * group_size
        # column j of the product is centroid perm[j] (-1: padding, infinitely far); group g
        # holds columns g, g + G, g + 2G, ...: position (r, g) of the (group_size, G) view
        self.perm = np.full(m, -1, np.int64)
        self.perm[:n] = np.arange(n)
        cols = np.zeros((m, d), np.float32)
        cols[:n] = c
        self.neg2_ct = np.ascontiguousarray(-2.0 * cols.T)  # (d, m)
        self.norms = np.full(m, np.inf, np.float32)
        self.norms[:n] = (c.astype(np.float64) ** 2).sum(1)

    def assign(self, x: np.ndarray, nprobe: int) -> tuple[np.ndarray, np.ndarray]:
        """(squared distances (N, nprobe) float32, list ids (N, nprobe) int64), nearest first."""
        n = len(x)
        G, S = self.n_groups, self.group_size
        dist = x @ self.neg2_ct
        dist += self.norms  # |c|^2 - 2 x.c: the squared distance less |x|^2
        by_group = dist.reshape(n, S, G)
        mins = by_group.min(axis=1)  # (n, G)
        groups = np.argpartition(mins, nprobe - 1, axis=1)[:, :nprobe]  # (n, nprobe)
        rows = np.arange(n)[:, None, None]
        members = groups[:, None, :] + G * np.arange(S)[None, :, None]  # (n, S, nprobe)
        cand = by_group[rows, np.arange(S)[None, :, None], groups[:, None, :]].reshape(n, -1)
        members = members.reshape(n, -1)
        pick = np.argpartition(cand, nprobe - 1, axis=1)[:, :nprobe]
        cd = np.take_along_axis(cand, pick, 1)
        order = np.argsort(cd, axis=1, kind="stable")
        cd = np.take_along_axis(cd, order, 1)
        ids = self.perm[np.take_along_axis(np.take_along_axis(members, pick, 1), order, 1)]
        xx = np.einsum("ij,ij->i", x, x, dtype=np.float32)
        return np.maximum(cd + xx[:, None], 0.0).astype(np.float32), ids


def bitmap_from_ranges(n: int, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """A faiss ``IDSelectorBitmap`` bitmap (uint8, little bit order) with ids in the half-open
    ranges ``[starts[i], ends[i])`` set (``0 <= starts[i] <= ends[i] <= n``).

    Written byte by byte, touching ranges merged first: a guided scope's images are runs of
    consecutive map images on a map from video, so ~300 image ranges (every-frame redkitchen
    map, 2.6 M descriptors) are a few dozen runs; the bitmap is 1/8 of a bool mask and needs
    no packing (0.55-0.62 -> 0.07-0.09 ms per guided batch there, the same bits)."""
    bits = np.zeros((n + 7) // 8, np.uint8)
    s = np.asarray(starts, np.int64)
    e = np.asarray(ends, np.int64)
    keep = e > s
    s, e = s[keep], e[keep]
    if len(s) == 0:
        return bits
    order = np.argsort(s, kind="stable")
    s, e = s[order], e[order]
    run = np.ones(len(s), bool)  # a range starting past every earlier range's end opens a run
    run[1:] = s[1:] > np.maximum.accumulate(e)[:-1]
    run_end = np.maximum.reduceat(e, np.nonzero(run)[0])
    for a, b in zip(s[run].tolist(), run_end.tolist()):
        a8, b8 = (a + 7) >> 3, b >> 3  # the whole bytes inside [a, b): [a8, b8)
        if a8 > b8:  # within one byte
            bits[b8] |= ((1 << (b - a)) - 1) << (a & 7)
            continue
        bits[a8:b8] = 0xFF
        if a & 7:
            bits[a >> 3] |= (0xFF << (a & 7)) & 0xFF
        if b & 7:
            bits[b8] |= (1 << (b & 7)) - 1
    return bits


def _ivf_or_none(index: faiss.Index):
    try:
        return faiss.extract_index_ivf(index)
    except RuntimeError:
        return None
