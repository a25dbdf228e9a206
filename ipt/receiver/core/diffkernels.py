"""The pair difference's inner loops (:func:`ipt.receiver.core.demodulator.pair_difference`), as plain Python
that :mod:`ipt.receiver.core.kernels` compiles (numba), and the same with numpy where numba cannot compile:
the brightness match's samples (:func:`sample_pair`) and the difference, its valid pixels and its changed
ones (:func:`difference_pass`) in one pass over the image each instead of numpy's eight.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]


def sample_pair(moved: U8, later: U8, moved_signal: U8, later_signal: U8, step: int) -> tuple[F32, F32]:
    """The two frames of a pair (``moved``: the earlier one carried onto the later one) on every ``step``-th
    row and column where both have signal: (earlier values, later values), as float32."""
    h, w = later.shape
    rows, cols = (h + step - 1) // step, (w + step - 1) // step
    xs = np.empty(rows * cols, np.float32)
    ys = np.empty(rows * cols, np.float32)
    count = 0
    for y in range(0, h, step):
        for x in range(0, w, step):
            if later_signal[y, x] > 0 and moved_signal[y, x] > 0:
                xs[count] = moved[y, x]
                ys[count] = later[y, x]
                count += 1
    return xs[:count], ys[:count]


def sample_pair_numpy(moved: U8, later: U8, moved_signal: U8, later_signal: U8, step: int) -> tuple[F32, F32]:
    """:func:`sample_pair` with numpy (where numba cannot compile)."""
    both = (later_signal[::step, ::step] > 0) & (moved_signal[::step, ::step] > 0)
    return moved[::step, ::step][both].astype(np.float32), later[::step, ::step][both].astype(np.float32)


def difference_pass(
    moved: U8,
    later: U8,
    moved_seen: U8,
    coverage: U8,
    gain: float,
    offset: float,
    limit: float,
    diff: F32,
    seen: U8,
    changed: U8,
) -> None:
    """The pair's raw difference, ``later − (gain · moved + offset)`` (``moved``: the earlier frame carried
    onto the later one), into ``diff``; into ``seen`` the lesser of ``coverage`` and ``moved_seen`` (where the
    later and the carried earlier frame see the floor); 1 into ``changed`` where the difference exceeds
    ``limit`` (else 0). One pass instead of numpy's eight over the whole image."""
    h, w = later.shape
    g, o = np.float32(gain), np.float32(offset)
    for y in range(h):
        for x in range(w):
            d = np.float32(later[y, x]) - (g * np.float32(moved[y, x]) + o)
            diff[y, x] = d
            seen[y, x] = min(coverage[y, x], moved_seen[y, x])
            changed[y, x] = 1 if abs(d) > limit else 0


def difference_pass_numpy(
    moved: U8,
    later: U8,
    moved_seen: U8,
    coverage: U8,
    gain: float,
    offset: float,
    limit: float,
    diff: F32,
    seen: U8,
    changed: U8,
) -> None:
    """:func:`difference_pass` with numpy (where numba cannot compile)."""
    np.subtract(later.astype(np.float32), np.float32(gain) * moved.astype(np.float32) + np.float32(offset), out=diff)
    np.minimum(coverage, moved_seen, out=seen)
    np.greater(np.abs(diff), limit, out=changed.view(np.bool_))
