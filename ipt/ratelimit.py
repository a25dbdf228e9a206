"""Rate limits: token buckets per source, and log lines that do not flood the journal.

Pure: the time comes in as an argument (any monotonic clock, in seconds); no clocks, sockets or
threads here. The sender's packet filter limits the datagrams each source address may make it decode
(:class:`SourceRateLimit`); the daemons pass repeated events (a MAVLink peer announcing itself again
and again, unreadable frames of a recording) through :class:`LogThrottle`, so that stderr gets a few
lines and a count rather than thousands of lines.
"""

from __future__ import annotations

import math
from collections.abc import Hashable

from ipt.errors import IptError


class RateLimitError(IptError):
    """A rate limit was given unusable settings."""


def _check(rate_per_s: float, burst: float) -> None:
    if not (math.isfinite(rate_per_s) and rate_per_s > 0):
        raise RateLimitError(f"a rate limit must be a positive number per second, got {rate_per_s!r}")
    if not (math.isfinite(burst) and burst >= 1):
        raise RateLimitError(f"a burst must be at least 1, got {burst!r}")


class TokenBucket:
    """``rate_per_s`` events a second on average, up to ``burst`` at once (a full bucket to start with)."""

    def __init__(self, rate_per_s: float, burst: float) -> None:
        _check(rate_per_s, burst)
        self.rate_per_s = rate_per_s
        self.burst = float(burst)
        self._tokens = float(burst)
        self._last: float | None = None

    def take(self, now: float) -> bool:
        """Whether one more event is allowed at ``now``; if so it is counted."""
        if self._last is not None and now > self._last:
            self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate_per_s)
        if self._last is None or now > self._last:
            self._last = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


class SourceRateLimit:
    """A token bucket for each source (an address), so that one source cannot take everyone's share.

    At most ``max_sources`` sources are tracked, in bounded memory: when that many are known, the ones
    idle long enough for their bucket to be full again are forgotten (they lose nothing by it), and if
    none is, new sources share one bucket of the same size, so that a flood from many addresses is
    limited as one source.
    """

    def __init__(self, rate_per_s: float, burst: float | None = None, max_sources: int = 1024) -> None:
        burst = max(1.0, rate_per_s) if burst is None else burst
        _check(rate_per_s, burst)
        if max_sources < 1:
            raise RateLimitError(f"max_sources must be at least 1, got {max_sources}")
        self.rate_per_s = rate_per_s
        self.burst = float(burst)
        self.max_sources = max_sources
        self._refill_s = self.burst / rate_per_s  # an idle bucket is full again after this long
        self._buckets: dict[Hashable, list[float]] = {}  # source -> [tokens, last time]
        self._shared = [self.burst, -math.inf]
        self._next_sweep = -math.inf  # no bucket can be idle long enough before this time
        self.shared_sources = 0
        """Datagrams from sources that found the table full and went through the shared bucket."""

    def _bucket(self, source: Hashable, now: float) -> list[float]:
        bucket = self._buckets.get(source)
        if bucket is not None:
            return bucket
        if len(self._buckets) >= self.max_sources and now >= self._next_sweep:
            idle = [s for s, b in self._buckets.items() if now - b[1] >= self._refill_s]
            for s in idle:
                del self._buckets[s]
            # Until the quietest source left has been idle long enough, sweeping again finds nothing.
            oldest = min((b[1] for b in self._buckets.values()), default=now)
            self._next_sweep = oldest + self._refill_s
        if len(self._buckets) >= self.max_sources:
            self.shared_sources += 1
            return self._shared
        bucket = self._buckets[source] = [self.burst, now]
        return bucket

    def allow(self, source: Hashable, now: float) -> bool:
        """Whether a datagram from ``source`` at ``now`` is within its limit (if so it is counted)."""
        bucket = self._bucket(source, now)
        tokens, last = bucket
        if now > last:
            tokens = min(self.burst, tokens + (now - last) * self.rate_per_s)
            bucket[1] = now
        if tokens >= 1.0:
            bucket[0] = tokens - 1.0
            return True
        bucket[0] = tokens
        return False

    def __len__(self) -> int:
        return len(self._buckets)


class LogThrottle:
    """Lets through at most ``burst`` lines per ``period_s`` for each kind of event, and counts the rest.

    :meth:`line` returns the text to print, or ``None`` to stay quiet; the first line let through after
    some were held back says how many (``… (and 37 more like it in the last 10 s)``).
    """

    def __init__(self, period_s: float = 10.0, burst: int = 3) -> None:
        if not (math.isfinite(period_s) and period_s > 0) or burst < 1:
            raise RateLimitError(f"need period_s > 0 and burst >= 1, got {period_s!r}, {burst!r}")
        self.period_s = period_s
        self.burst = burst
        self._buckets: dict[Hashable, TokenBucket] = {}
        self._held: dict[Hashable, int] = {}
        self._held_since: dict[Hashable, float] = {}
        self.suppressed = 0
        """Lines held back so far, all kinds together."""

    def line(self, kind: Hashable, text: str, now: float) -> str | None:
        """``text`` (with a count of the lines held back before it) if it may be printed now, else ``None``."""
        bucket = self._buckets.get(kind)
        if bucket is None:
            bucket = self._buckets[kind] = TokenBucket(self.burst / self.period_s, self.burst)
        if not bucket.take(now):
            self.suppressed += 1
            if self._held.get(kind, 0) == 0:
                self._held_since[kind] = now
            self._held[kind] = self._held.get(kind, 0) + 1
            return None
        held = self._held.pop(kind, 0)
        if held:
            since = now - self._held_since.pop(kind, now)
            return f"{text} (and {held} more like it in the last {max(since, 0.0):.0f} s)"
        return text

    def pending(self, kind: Hashable) -> int:
        """Lines of ``kind`` held back since the last one let through."""
        return self._held.get(kind, 0)
