"""Raw descriptors during a build, held on disk so that peak memory follows the final map.

(``RawStore`` also holds the Harris-point stage's per-corner descriptors, float16.)

The raw 104-d float32 DAISY vectors (416 B each) are 6.5x the stored PCA-32 float16 ones and
are needed only for PCA (a bounded sample) and the projection (one pass). ``RawStore``
appends them image by image to a flat float32 file in the build's temporary folder and reads
them back in chunks of ``chunk_rows`` with ordinary reads into one reused buffer: a memory map
would count every page it touched in the process's resident set, so one pass over a mapped
file would bring the whole file back into RSS. ``folder=None`` keeps them in memory instead
(the old path: every raw vector resident; for comparisons and tiny maps).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from io import BufferedRandom
from pathlib import Path

import numpy as np


class RawStore:
    def __init__(
        self,
        dim: int,
        folder: str | Path | None = None,
        chunk_rows: int = 65536,
        dtype: type = np.float32,
    ) -> None:
        self.dim = dim
        self.dtype = np.dtype(dtype)
        self.chunk_rows = max(1, int(chunk_rows))
        self._n = 0
        self._mem: list[np.ndarray] | None = None
        self._file: BufferedRandom | None = None
        self.path: Path | None = None
        if folder is None:
            self._mem = []
        else:
            Path(folder).mkdir(parents=True, exist_ok=True)
            fd, name = tempfile.mkstemp(prefix="raw-descriptors-", suffix=".f32", dir=str(folder))
            self.path = Path(name)
            self._file = os.fdopen(fd, "w+b")

    def __len__(self) -> int:
        return self._n

    @property
    def on_disk(self) -> bool:
        return self._mem is None

    def _disk(self) -> BufferedRandom:
        """The open file of an on-disk store."""
        if self._file is None:
            raise ValueError(f"raw descriptor store {self.path} is closed")
        return self._file

    def append(self, raw: np.ndarray) -> None:
        raw = np.ascontiguousarray(raw, dtype=self.dtype).reshape(-1, self.dim)
        if self._mem is not None:
            self._mem.append(raw)
        else:
            self._disk().write(raw.tobytes())  # an OSError (full disk) names the file
        self._n += len(raw)

    def chunks(self) -> Iterator[tuple[int, np.ndarray]]:
        """``(first row, rows)`` in order; on disk the rows are a view of a reused buffer,
        valid until the next chunk."""
        if self._mem is not None:
            self._consolidate()
            if self._n:
                yield 0, self._mem[0]
            return
        file = self._disk()
        file.flush()
        buf = np.empty((min(self.chunk_rows, max(self._n, 1)), self.dim), self.dtype)
        file.seek(0)
        start = 0
        while start < self._n:
            m = min(len(buf), self._n - start)
            view = buf[:m]
            got = file.readinto(view.data.cast("B"))
            if got != view.nbytes:
                msg = f"short read of raw descriptors ({got} of {view.nbytes} bytes)"
                raise OSError(msg, str(self.path))
            yield start, view
            start += m

    def read(self, start: int, stop: int) -> np.ndarray:
        """Rows ``start:stop`` as a new array (one positioned read on disk)."""
        start, stop = max(0, int(start)), min(self._n, int(stop))
        out = np.empty((max(0, stop - start), self.dim), self.dtype)
        if len(out) == 0:
            return out
        if self._mem is not None:
            self._consolidate()
            out[:] = self._mem[0][start:stop]
            return out
        file = self._disk()
        file.flush()
        got = os.preadv(file.fileno(), [out.data.cast("B")], start * self._row_bytes)
        if got != out.nbytes:
            msg = f"short read of stored rows ({got} of {out.nbytes} bytes)"
            raise OSError(msg, str(self.path))
        return out

    @property
    def _row_bytes(self) -> int:
        return self.dim * self.dtype.itemsize

    def take(self, rows: np.ndarray) -> np.ndarray:
        """The given rows (any order, no repeats), as a new array in that order."""
        rows = np.asarray(rows, dtype=np.int64)
        if self._mem is not None:
            self._consolidate()
            return self._mem[0][rows] if self._n else np.zeros((0, self.dim), self.dtype)
        out = np.empty((len(rows), self.dim), self.dtype)
        order = np.argsort(rows, kind="stable")
        srt = rows[order]
        for start, chunk in self.chunks():
            lo, hi = np.searchsorted(srt, [start, start + len(chunk)])
            if hi > lo:
                out[order[lo:hi]] = chunk[srt[lo:hi] - start]
        return out

    def _consolidate(self) -> None:
        if self._mem is not None and len(self._mem) > 1:
            self._mem = [np.concatenate(self._mem)]

    def close(self) -> None:
        """Remove the file (idempotent)."""
        if self._file is not None:
            self._file.close()
            self._file = None
        if self.path is not None:
            self.path.unlink(missing_ok=True)
        self._mem = [] if self._mem is not None else None

    def __enter__(self) -> RawStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
