"""The plumbing both daemons share (ipt/runtime.py): its duration histogram."""

from __future__ import annotations

import math

from ipt.runtime import Histogram


def test_histogram_percentiles_in_bins_capped_at_the_largest_seen() -> None:
    h = Histogram(bin_ms=0.1, limit_ms=10_000.0)
    assert h.quantile_ms(0.5) is None
    assert math.isnan(h.percentile(50))
    for ms in (1.0, 2.0, 3.0, 4.0, 100.0):
        h.add(ms)
    assert math.isclose(h.percentile(50), 3.05)  # the middle of the bin of 3.0 ms
    assert h.quantile_ms(0.5) == h.percentile(50)
    assert h.percentile(100) == 100.0  # its bin's middle (100.05) is above what was seen
    assert h.mean_ms == 22.0
    h.add(50_000.0)  # beyond the limit: the last bin, reported as the largest seen
    assert h.percentile(100) == 50_000.0
    h.clear()
    assert h.n == 0
    assert h.quantile_ms(0.99) is None
