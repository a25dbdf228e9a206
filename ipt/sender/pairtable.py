"""The ``ipt`` profile's colour table: the pairs of all 2^24 colours, shared in a process and kept on disk.

A pair depends only on the colour (:mod:`ipt.sender.pairs` computes it), so pairs are kept in a table of
all 2^24 colours (128 MB per ΔL and allowance, :class:`PairTable`; :func:`pair_table` shares them in a
process). It is filled lazily, a colour the first time a frame has it, or completely before a projection
starts (:meth:`PairTable.complete_with_cache`): computed once on all cores and kept in a cache file
(:func:`cache_path`, a header and the raw entries, checked by checksum and a spot check), read back in a
fraction of a second by the next run.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from ipt.fileio import atomic_path
from ipt.sender.colour import CODE_TO_LINEAR, L8_PER_LSTAR, LUMINANCE_WEIGHTS
from ipt.sender.pairs import (
    _MIDS,
    _SHIFT_DOWN,
    ALGORITHM_VERSION,
    COLOURS,
    PairsError,
    _compute_codes_c,
    _fill_codes_c,
    _fill_range_c,
    allowance_budget_de00,
    amplitude_grid,
)

U8 = npt.NDArray[np.uint8]
U64 = npt.NDArray[np.uint64]


def unpack(entries: U64) -> tuple[U8, U8]:
    """The (+, -) codes (N×3 each) of packed table entries."""
    shifts = np.array([0, 8, 16], dtype=np.uint64)
    up = ((entries[:, None] >> shifts) & np.uint64(255)).astype(np.uint8)
    down = (((entries[:, None] >> _SHIFT_DOWN) >> shifts) & np.uint64(255)).astype(np.uint8)
    return up, down


def colour_index(codes: U8) -> npt.NDArray[np.int64]:
    """Table index of N×3 colours."""
    c = codes.astype(np.int64)
    out: npt.NDArray[np.int64] = c[:, 0] | (c[:, 1] << 8) | (c[:, 2] << 16)
    return out


class PairTable:
    """The pairs of every 8-bit colour for one ΔL and clip allowance (see the module doc); get one with
    :func:`pair_table`, which shares them in a process."""

    def __init__(self, delta_l: float, clip_allowance_l8: float) -> None:
        self.delta_l = float(delta_l)
        self.clip_allowance_l8 = float(clip_allowance_l8)
        self.budget_de00 = allowance_budget_de00(clip_allowance_l8) if clip_allowance_l8 > 0 else 0.0
        """The allowance as CIEDE2000 (0: none)."""
        self.agrid = amplitude_grid(delta_l)
        # Written through once (128 MB) rather than np.zeros' untouched pages: faulting pages in one at a
        # time, at random, as new colours come (a page per colour at first) costs far more per page.
        self.table: U64 = np.empty(COLOURS, dtype=np.uint64)
        self.table.fill(0)
        self.lin = np.ascontiguousarray(CODE_TO_LINEAR)
        self.mids = np.ascontiguousarray(_MIDS)
        self.w = np.ascontiguousarray(LUMINANCE_WEIGHTS)
        self.target = 2.0 * delta_l / L8_PER_LSTAR
        self.complete = False
        """Every entry is filled."""
        self.lock = threading.Lock()
        """Held while the table is being completed."""

    def args(self) -> tuple[Any, ...]:
        """The table and its constants, as the compiled functions take them."""
        return self.table, self.lin, self.mids, self.agrid, self.w, self.target, self.budget_de00

    def pairs(self, codes: U8) -> tuple[U8, U8]:
        """The (+, -) codes of N colours (N×3 uint8): what a white tag pixel (mask +1) of that colour shows."""
        codes = np.ascontiguousarray(codes, dtype=np.uint8).reshape(-1, 3)
        _fill_codes_c(codes, *self.args())
        return unpack(self.table[colour_index(codes)])

    def fill(
        self, threads: int = 0, progress: Callable[[float], None] | None = None, stop: threading.Event | None = None
    ) -> bool:
        """Fill every entry not yet filled, in ``threads`` threads (0: one per core); ``progress`` is
        called with the share done (0..1) as chunks finish. Returns whether the table is complete.

        ``stop`` set (a stop signal, from another thread) or an exception in the waiting thread (a stop
        signal raised there) ends the fill within a chunk's time (tens of milliseconds): the chunks not
        begun are dropped, the table stays incomplete (the chunks done are valid entries)."""
        threads = threads if threads > 0 else max(1, os.cpu_count() or 1)
        chunk = 1 << 16
        starts = range(0, COLOURS, chunk)
        args = self.args()
        with ThreadPoolExecutor(threads, thread_name_prefix="ipt-pairs") as pool:
            futures = [pool.submit(_fill_range_c, s, s + chunk, *args) for s in starts]
            try:
                for done, fut in enumerate(futures, 1):
                    while not _finished(fut, stop):
                        pass
                    if stop is not None and stop.is_set():
                        break
                    fut.result()
                    if progress is not None:
                        progress(done / len(futures))
            finally:
                for fut in futures:  # nothing left when complete; else the chunks not begun
                    fut.cancel()
        if stop is not None and stop.is_set():
            return False
        self.complete = True
        return True

    def spot_check(self, entries: U64, count: int = 4096, seed: int = 0) -> int:
        """How many of ``count`` random colours (and the 8 corners of the cube) have another entry in
        ``entries`` (a whole table) than computing them again gives: 0 for a table made by this code."""
        rng = np.random.default_rng(seed)
        corners = [0, 0xFF, 0xFF00, 0xFFFF, 0xFF0000, 0xFF00FF, 0xFFFF00, 0xFFFFFF]
        index = np.concatenate([rng.integers(0, COLOURS, count), np.array(corners, np.int64)])
        codes = np.ascontiguousarray(np.stack([index & 255, (index >> 8) & 255, index >> 16], axis=1).astype(np.uint8))
        fresh = np.empty(len(index), dtype=np.uint64)
        _compute_codes_c(codes, fresh, *self.args()[1:])
        return int(np.count_nonzero(fresh != entries[index]))

    def complete_with_cache(self, cache_dir: os.PathLike[str] | None, log: Callable[[str], None]) -> str:
        """Make the table complete: from the cache file in ``cache_dir`` if it holds this table, else by
        computing it (progress through ``log``) and then writing the cache (``None``: no cache). Returns a
        sentence saying which, and how long it took. The stop flag of :func:`stoppable` set meanwhile (in
        the thread that called this) ends the computing early (see :meth:`fill`): the table is then left
        incomplete and nothing is cached."""
        with self.lock:
            if self.complete:
                return "colour table: already complete"
            t0 = time.perf_counter()
            path = None if cache_dir is None else cache_path(Path(cache_dir), self.delta_l, self.clip_allowance_l8)
            problem = None
            if path is not None and path.exists():
                problem = read_cache(path, self)
                if problem is None:
                    return f"colour table: read {path} in {time.perf_counter() - t0:.2f} s"
                log(f"colour table: {path}: {problem}; computing it again")
            log(
                f"colour table: computing the pairs of all {COLOURS:,} colours for ΔL {self.delta_l:g}, clip "
                f"allowance {self.clip_allowance_l8:g} (once; a minute or less)"
            )
            next_report = [0.1]

            def progress(share: float) -> None:
                if share >= next_report[0] - 1e-9:
                    log(f"colour table: {share:.0%} ({time.perf_counter() - t0:.0f} s)")
                    next_report[0] += 0.1

            if not self.fill(progress=progress, stop=getattr(_LOCAL, "stop", None)):
                return f"colour table: stopped after {time.perf_counter() - t0:.1f} s, incomplete; nothing cached"
            took = time.perf_counter() - t0
            if path is None:
                return f"colour table: computed in {took:.1f} s (no cache folder: computed at every start)"
            try:
                write_cache(path, self)
                remove_stale(path.parent)
            except OSError as exc:
                return (
                    f"colour table: computed in {took:.1f} s; cannot keep it in {path} ({exc}): computed at every start"
                )
            return f"colour table: computed in {took:.1f} s, kept in {path}"


def _finished(fut: Future[Any], stop: threading.Event | None) -> bool:
    """Wait a little for ``fut``: True once it is done or ``stop`` is set."""
    if stop is None:
        fut.exception()  # waits; the result is taken by the caller
        return True
    return wait([fut], timeout=STOP_POLL_S).done != set() or stop.is_set()


STOP_POLL_S: Final = 0.02
"""How often a fill that may be stopped looks at its stop flag (seconds)."""

_LOCAL = threading.local()


@contextlib.contextmanager
def stoppable(stop: threading.Event) -> Iterator[None]:
    """Within the block, :meth:`PairTable.complete_with_cache` called in this thread ends early once ``stop``
    is set (the sender sets it on a stop signal, which the thread building the table cannot receive)."""
    before = getattr(_LOCAL, "stop", None)
    _LOCAL.stop = stop
    try:
        yield
    finally:
        _LOCAL.stop = before


_TABLES: dict[tuple[float, float], PairTable] = {}
_TABLES_LOCK = threading.Lock()


def pair_table(delta_l: float, clip_allowance_l8: float) -> PairTable:
    """The process's table for ΔL and clip allowance (made, empty, on first use)."""
    with _TABLES_LOCK:
        key = (float(delta_l), float(clip_allowance_l8))
        table = _TABLES.get(key)
        if table is None:
            table = _TABLES[key] = PairTable(delta_l, clip_allowance_l8)
        return table


# --- the cache file -----------------------------------------------------------------------------------

_MAGIC: Final = b"IPTPAIRS"
_HEADER_BYTES: Final = 4096
"""The header (magic, then JSON padded with spaces) takes the first 4096 bytes; the entries follow,
little-endian uint64, so that they are read straight into the table."""


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/ipt`` (``~/.cache/ipt`` when it is not set)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "ipt"


def cache_path(cache_dir: Path, delta_l: float, clip_allowance_l8: float) -> Path:
    """The cache file of one table."""
    return cache_dir / f"pairs-v{ALGORITHM_VERSION}-dl{delta_l:.6g}-a{clip_allowance_l8:.6g}.bin"


def _header(table: PairTable, sha256: str) -> dict[str, Any]:
    return {
        "format": "ipt pair table",
        "version": ALGORITHM_VERSION,
        "delta_l": table.delta_l,
        "clip_allowance_l8": table.clip_allowance_l8,
        "entries": COLOURS,
        "dtype": "<u8",
        "sha256": sha256,
    }


def write_cache(path: Path, table: PairTable) -> None:
    """Write the complete ``table`` to ``path`` (made beside it and renamed: never half a file)."""
    if not table.complete:
        raise PairsError("only a complete table is cached")
    path.parent.mkdir(parents=True, exist_ok=True)
    data = table.table.astype("<u8", copy=False)
    header = json.dumps(_header(table, hashlib.sha256(data.data).hexdigest())).encode()
    block = _MAGIC + header.ljust(_HEADER_BYTES - len(_MAGIC), b" ")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(block)
        f.write(data.data)


def read_cache(path: Path, table: PairTable) -> str | None:
    """Read ``path`` into ``table`` and mark it complete; or say why not (the table is then left as it was
    before, entries already filled lazily kept)."""
    try:
        with open(path, "rb") as f:
            block = f.read(_HEADER_BYTES)
            if len(block) < _HEADER_BYTES or not block.startswith(_MAGIC):
                return "not a pair table"
            try:
                header = json.loads(block[len(_MAGIC) :].decode())
            except (UnicodeDecodeError, ValueError):
                return "unreadable header"
            want = _header(table, "")
            for key in ("format", "version", "delta_l", "clip_allowance_l8", "entries", "dtype"):
                if not isinstance(header, dict) or header.get(key) != want[key]:
                    return f"made for another table ({key})"
            data = np.empty(COLOURS, dtype="<u8")
            if f.readinto(data.data.cast("B")) != data.nbytes or f.read(1):
                return "truncated or too long"
    except OSError as exc:
        return f"cannot read ({exc.strerror or exc})"
    if hashlib.sha256(data.data).hexdigest() != header.get("sha256"):
        return "checksum mismatch (damaged)"
    if table.spot_check(data) != 0:  # made by other code that kept the version number
        return "its entries differ from what this version computes"
    # The entries filled lazily so far are the same in `data`; a kernel running now keeps the old array.
    table.table = data.view(np.uint64)
    table.complete = True
    return None


def remove_stale(cache_dir: Path) -> None:
    """Delete cache files of other algorithm versions in ``cache_dir`` (they can never be read again)."""
    with contextlib.suppress(OSError):
        for p in cache_dir.glob("pairs-v*-dl*-a*.bin"):
            if not p.name.startswith(f"pairs-v{ALGORITHM_VERSION}-"):
                p.unlink(missing_ok=True)
