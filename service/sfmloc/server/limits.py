"""Per-client limits that keep a noisy or hostile client from costing the others: a frame-rate
token bucket per client, and a log limiter that turns a flood of rejections into a summary.

Both are bounded in memory whatever clients send: client ids are chosen by clients, so at most
``max_keys`` of them are tracked (the least recently seen are forgotten first).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable

from .logfmt import event


class RateLimiter:
    """Token bucket per key: ``rate`` events per second on average, bursts of ``burst``."""

    def __init__(
        self,
        rate: float,
        burst: float,
        max_keys: int = 4096,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.rate, self.burst, self.max_keys, self.clock = rate, burst, max_keys, clock
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # key -> (tokens, t)
        self._lock = threading.Lock()

    def allow(self, key: str) -> bool:
        now = self.clock()
        with self._lock:
            tokens, t = self._buckets.pop(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - t) * self.rate)
            ok = tokens >= 1.0
            self._buckets[key] = (tokens - 1.0 if ok else tokens, now)
            while len(self._buckets) > self.max_keys:
                self._buckets.popitem(last=False)
            self._prune(now, keep=1)  # the last is this key's
            return ok

    def prune(self) -> int:
        """Forget the buckets idle long enough to be full again (called on every ``allow``
        and by the server's reaper, so that the table empties when clients are gone)."""
        with self._lock:
            return self._prune(self.clock())

    def _prune(self, now: float, keep: int = 0) -> int:
        # A bucket idle long enough to be full again is the same as none: forgotten, so that
        # clients that came and went cost nothing (issue 16). Least recently seen first: stop
        # at the first one still refilling.
        n, refill_s = 0, self.burst / self.rate
        while len(self._buckets) > keep:
            k, (_, t_k) = next(iter(self._buckets.items()))
            if now - t_k < refill_s:
                break
            del self._buckets[k]
            n += 1
        return n

    def __len__(self) -> int:
        return len(self._buckets)


class LogLimiter:
    """At most ``per_key`` lines per key and ``total`` lines overall in each ``interval_s``;
    the lines held back are counted and reported by ``flush`` as one summary event per
    interval (``<name>_suppressed``, with the count and the keys and codes most seen).

    Measured before this: 6000 malformed frames logged 5649 lines (issue 12).
    """

    def __init__(
        self,
        logger: logging.Logger,
        name: str,
        interval_s: float = 10.0,
        per_key: int = 3,
        total: int = 50,
        max_keys: int = 4096,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.logger, self.name, self.interval_s = logger, name, interval_s
        self.per_key, self.total, self.max_keys, self.clock = per_key, total, max_keys, clock
        self._lock = threading.Lock()
        self._start = clock()
        self._lines = 0
        self._per_key: OrderedDict[str, int] = OrderedDict()
        self._held = 0
        self._held_keys: Counter[str] = Counter()
        self._held_codes: Counter[str] = Counter()

    def allow(self, key: str, code: str = "") -> bool:
        """Whether this line may be logged now (else it is counted for the summary)."""
        self.flush()
        with self._lock:
            n = self._per_key.pop(key, 0)
            self._per_key[key] = n + 1
            while len(self._per_key) > self.max_keys:
                self._per_key.popitem(last=False)
            if n < self.per_key and self._lines < self.total:
                self._lines += 1
                return True
            self._held += 1
            if key in self._held_keys or len(self._held_keys) < self.max_keys:
                self._held_keys[key] += 1
            self._held_codes[code] += 1
            return False

    def flush(self, force: bool = False) -> None:
        """Start a new interval once this one is over, logging what was held back in it."""
        now = self.clock()
        with self._lock:
            if not force and now - self._start < self.interval_s:
                return
            held, keys, codes = self._held, self._held_keys, self._held_codes
            span = now - self._start
            self._start, self._lines, self._held = now, 0, 0
            self._per_key.clear()
            self._held_keys, self._held_codes = Counter(), Counter()
        if held:
            event(
                self.logger,
                logging.WARNING,
                f"{self.name}_suppressed",
                count=held,
                interval_s=round(span, 1),
                clients=len(keys),
                top_clients=[k for k, _ in keys.most_common(5)],
                codes=dict(codes.most_common(5)),
            )
