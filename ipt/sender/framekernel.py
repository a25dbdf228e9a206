"""The frame kernels of the ``ipt`` profile: both phases of an input frame from the pair table, in one pass.

**The frame kernel** (:func:`_modulate_rows`, compiled as ``_modulate_rows_c``) writes both output frames of
an input frame in one pass: pixels outside the tags copied, tag pixels looked up (and filled if new). It
reads each pixel as one unaligned 32-bit load, writes it as one 32-bit store (the fourth byte is overwritten
by the next pixel; the last pixel of a range is written byte by byte, so ranges written by different threads
never overlap) and prefetches the table entry of the pixel 64 ahead: on photographic content the entries of
a frame span megabytes, and waiting for each in turn doubled the time of the pass. Once the table is
complete, :func:`_modulate_rows_filled` does the same without the branch that fills new colours: every tag
pixel is one load from the table and a select of its sign, which takes about half the time (the call to the
colour maths inside the loop kept the compiled loop from being tight).

The pairs themselves, one colour's and the table's entries, are :mod:`ipt.sender.pairs`; the table
:class:`~ipt.sender.pairtable.PairTable`, whose :meth:`~ipt.sender.pairtable.PairTable.args` the kernels take
after the frame and the mask.
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np
import numpy.typing as npt

from ipt.sender.jit import intrinsics, jit
from ipt.sender.pairs import _LOW24, _SHIFT_DOWN, _ipt_pair_c

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]
U64 = npt.NDArray[np.uint64]

PREFETCH_PX: Final = 64
"""How many pixels ahead the frame kernel asks for a table entry (measured: 32-64 halve the time of a
photographic frame against none; 8-16 gain less)."""


def _modulate_rows(
    rgb: U8,
    mask: npt.NDArray[np.int8],
    table: U64,
    lin: F64,
    mids: F64,
    agrid: F64,
    w: F64,
    target: float,
    budget: float,
    out_plus: U8,
    out_minus: U8,
    want_plus: bool,
    want_minus: bool,
    row0: int,
    row1: int,
) -> None:
    """Rows ``row0..row1`` of both phases (those wanted); fills the table entries it needs (see the module
    doc). All arrays C-contiguous; ``rgb`` and the outputs H×W×3, ``mask`` H×W."""
    width = mask.shape[1]
    first, last = row0 * width, row1 * width - 1  # pixel indices
    if last < first:
        return
    src = rgb.reshape(-1)
    plus = out_plus.reshape(-1)
    minus = out_minus.reshape(-1)
    flat_mask = mask.reshape(-1)
    m8, sh8, sh16 = np.uint32(255), np.uint32(8), np.uint32(16)
    low24 = np.uint32(0xFFFFFF)
    px: Any
    for i in range(first, last + 1):
        j = 3 * i
        ahead = i + PREFETCH_PX
        if ahead < last and flat_mask[ahead] != 0:
            _prefetch(table, np.int64(_load_u32(src, 3 * ahead) & low24))
        if i < last:
            px = _load_u32(src, j) & low24
        else:
            px = np.uint32(src[j]) | (np.uint32(src[j + 1]) << sh8) | (np.uint32(src[j + 2]) << sh16)
        m = flat_mask[i]
        if m == 0:
            up = down = px
        else:
            e = table[np.int64(px)]
            if e == 0:
                red, green, blue = np.int64(px & m8), np.int64((px >> sh8) & m8), np.int64(px >> sh16)
                e = _ipt_pair_c(red, green, blue, lin, mids, agrid, w, target, budget)
                table[np.int64(px)] = e
            brighter = np.uint32(e & _LOW24)
            darker = np.uint32((e >> _SHIFT_DOWN) & _LOW24)
            up, down = (brighter, darker) if m > 0 else (darker, brighter)
        if i < last:
            if want_plus:
                _store_u32(plus, j, up)
            if want_minus:
                _store_u32(minus, j, down)
        else:
            if want_plus:
                plus[j], plus[j + 1], plus[j + 2] = up & m8, (up >> sh8) & m8, (up >> sh16) & m8
            if want_minus:
                minus[j], minus[j + 1], minus[j + 2] = down & m8, (down >> sh8) & m8, (down >> sh16) & m8


def _modulate_rows_filled(
    rgb: U8,
    mask: npt.NDArray[np.int8],
    table: U64,
    lin: F64,
    mids: F64,
    agrid: F64,
    w: F64,
    target: float,
    budget: float,
    out_plus: U8,
    out_minus: U8,
    want_plus: bool,
    want_minus: bool,
    row0: int,
    row1: int,
) -> None:
    """:func:`_modulate_rows` for a complete table (every entry filled): the same frames, no colour maths.
    The arguments are :func:`_modulate_rows`' (those for the colour maths unused), so the two swap."""
    width = mask.shape[1]
    first, last = row0 * width, row1 * width - 1  # pixel indices
    if last < first:
        return
    src = rgb.reshape(-1)
    plus = out_plus.reshape(-1)
    minus = out_minus.reshape(-1)
    flat_mask = mask.reshape(-1)
    low24 = np.uint32(0xFFFFFF)
    for i in range(first, last):  # the last pixel, below, byte by byte
        j = 3 * i
        ahead = i + PREFETCH_PX
        if ahead < last:
            _prefetch(table, np.int64(_load_u32(src, 3 * ahead) & low24))
        px = _load_u32(src, j) & low24
        m = flat_mask[i]
        e = table[np.int64(px)]
        brighter = np.uint32(e & _LOW24)
        darker = np.uint32((e >> _SHIFT_DOWN) & _LOW24)
        up = px if m == 0 else (brighter if m > 0 else darker)
        down = px if m == 0 else (darker if m > 0 else brighter)
        if want_plus:
            _store_u32(plus, j, up)
        if want_minus:
            _store_u32(minus, j, down)
    j = 3 * last
    m = flat_mask[last]
    e = table[np.int64(src[j]) | (np.int64(src[j + 1]) << 8) | (np.int64(src[j + 2]) << 16)]
    for c in range(3):
        shift = np.uint64(8 * c)
        code = src[j + c]
        brighter_c = np.uint8((e >> shift) & np.uint64(255))
        darker_c = np.uint8((e >> (_SHIFT_DOWN + shift)) & np.uint64(255))
        if want_plus:
            plus[j + c] = code if m == 0 else (brighter_c if m > 0 else darker_c)
        if want_minus:
            minus[j + c] = code if m == 0 else (darker_c if m > 0 else brighter_c)


_load_u32, _store_u32, _prefetch = intrinsics()

# The compiled versions (numba looks the compiled functions they call up as globals of this module).
_modulate_rows_c: Any = jit(_modulate_rows)
_modulate_rows_filled_c: Any = jit(_modulate_rows_filled)
