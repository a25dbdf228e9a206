"""TUM trajectory files: one pose per line, the format of the TUM RGB-D benchmark tools.

A line is eight whitespace-separated numbers::

    t x y z qx qy qz qw

- ``t``: time stamp in seconds;
- ``x y z``: position in metres (in IPT: the camera's optical centre in the arena frame, ENU);
- ``qx qy qz qw``: orientation as a Hamilton unit quaternion with the scalar part **last** (in IPT:
  ``R_arena_cam``, which rotates OpenCV camera vectors into the arena frame).

Blank lines and lines whose first non-blank character is ``#`` are ignored. In memory the quaternions
are kept scalar-first (``quat_wxyz``), like everywhere else in :mod:`ipt.geometry`; only the file has the
scalar last.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.fileio import read_text_file, write_text_atomic

F64 = npt.NDArray[np.float64]

MAX_TUM_BYTES = 512 * 2**20
"""Largest TUM file read: about 5 million poses, 12 hours of a 120 FPS camera (it is read whole)."""

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"
"""The comment line :func:`write_tum` puts first: the TUM column order."""

_TIME_DECIMALS = 6  # 1 µs
_POSITION_DECIMALS = 6  # 1 µm, well below the 0.1 mm needed
_QUAT_DECIMALS = 9  # 1e-9
_MIN_QUAT_NORM = 1e-9


class TumError(IptError):
    """A TUM trajectory file is missing or malformed."""


@dataclass(frozen=True)
class Trajectory:
    """A sequence of timed poses.

    Attributes:
        times_s: (N,) time stamps in seconds, strictly increasing.
        positions_m: (N, 3) positions in metres (x, y, z).
        quats_wxyz: (N, 4) unit quaternions, scalar first (w, x, y, z). Note the TUM *file* stores
            them scalar last (qx qy qz qw); :func:`read_tum` and :func:`write_tum` reorder.
    """

    times_s: F64
    positions_m: F64
    quats_wxyz: F64

    def __post_init__(self) -> None:
        n = self.times_s.shape[0] if self.times_s.ndim == 1 else -1
        if n < 0 or self.positions_m.shape != (n, 3) or self.quats_wxyz.shape != (n, 4):
            raise ValueError(
                "Trajectory: expected times (N,), positions (N, 3), quaternions (N, 4); got "
                f"{self.times_s.shape}, {self.positions_m.shape}, {self.quats_wxyz.shape}"
            )

    def __len__(self) -> int:
        return int(self.times_s.shape[0])

    @classmethod
    def from_arrays(
        cls,
        times_s: npt.ArrayLike,
        positions_m: npt.ArrayLike,
        quats_wxyz: npt.ArrayLike,
    ) -> Trajectory:
        """Build a trajectory from anything array-like; converts to float64 and normalises quaternions."""
        q = np.asarray(quats_wxyz, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != 4:
            raise ValueError(f"Trajectory: expected quaternions of shape (N, 4), got {q.shape}")
        norms = np.linalg.norm(q, axis=1, keepdims=True)
        if np.any(norms < _MIN_QUAT_NORM):
            raise ValueError("Trajectory: zero quaternion")
        return cls(
            np.asarray(times_s, dtype=np.float64),
            np.asarray(positions_m, dtype=np.float64),
            q / norms,
        )


_MAX_QUOTED_CHARS = 40
"""Longest piece of a line quoted in an error (a 5 KB field made a 5 KB error line)."""


def _quote(field: str, *, bare: bool = False) -> str:
    """``field`` for an error line: cut to :data:`_MAX_QUOTED_CHARS` characters (with the full length said)."""
    head = field[:_MAX_QUOTED_CHARS]
    shown = head if bare else repr(head)
    return shown if len(field) <= _MAX_QUOTED_CHARS else f"{shown}… ({len(field)} characters)"


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM file; quaternions are normalised and reordered to (w, x, y, z).

    Raises :class:`TumError` ("file:line: problem") for a line without exactly 8 fields, a value that is
    not a finite number, a zero quaternion, or a time stamp not after the previous one; and for a
    missing or unreadable file or one without any pose.
    """
    p = Path(path)
    text = read_text_file(p, TumError, "a TUM file", max_bytes=MAX_TUM_BYTES)

    rows: list[list[float]] = []
    prev_t = -math.inf
    prev_field, prev_line = "", 0
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{p}:{lineno}"
        fields = line.split()
        if len(fields) != 8:
            raise TumError(f"{where}: expected 8 fields 't x y z qx qy qz qw', got {len(fields)}")
        values: list[float] = []
        for name, field in zip(("t", "x", "y", "z", "qx", "qy", "qz", "qw"), fields, strict=True):
            try:
                v = float(field)
            except ValueError:
                raise TumError(f"{where}: {name} is not a number: {_quote(field)}") from None
            if not math.isfinite(v):
                raise TumError(f"{where}: {name} is not finite: {_quote(field)}")
            values.append(v)
        t = values[0]
        if t <= prev_t:
            raise TumError(
                f"{where}: time {_quote(fields[0], bare=True)} is not after {_quote(prev_field, bare=True)} on line "
                f"{prev_line} "
                "(times must be strictly increasing)"
            )
        qx, qy, qz, qw = values[4:]
        norm = math.hypot(qx, qy, qz, qw)  # no overflow to inf for huge components (1e200 gave NaN poses)
        if norm < _MIN_QUAT_NORM:
            raise TumError(f"{where}: zero quaternion (qx qy qz qw all 0)")
        rows.append([t, *values[1:4], qw / norm, qx / norm, qy / norm, qz / norm])
        prev_t, prev_field, prev_line = t, fields[0], lineno
    if not rows:
        raise TumError(f"{p}: no poses (the file is empty or holds only comments)")
    a = np.array(rows, dtype=np.float64)
    return Trajectory(a[:, 0].copy(), a[:, 1:4].copy(), a[:, 4:8].copy())


def format_tum_line(t: float, position_m: Sequence[float] | F64, quat_wxyz: Sequence[float] | F64) -> str:
    """One TUM line (with trailing newline) for time ``t``, a position and a (w, x, y, z) quaternion.

    Precision: 1 µs in time, 1 µm in position, 1e-9 in the quaternion components. Raises ``ValueError``
    for non-finite values or wrong lengths (a bug in the caller, not a user error).
    """
    pos = np.asarray(position_m, dtype=np.float64).reshape(-1)
    q = np.asarray(quat_wxyz, dtype=np.float64).reshape(-1)
    if pos.shape != (3,) or q.shape != (4,):
        raise ValueError(f"format_tum_line: expected 3 position and 4 quaternion values, got {pos}, {q}")
    if not (math.isfinite(t) and np.all(np.isfinite(pos)) and np.all(np.isfinite(q))):
        raise ValueError(f"format_tum_line: non-finite pose at t={t}: {pos}, {q}")
    w, x, y, z = q
    tp, pp, qp = _TIME_DECIMALS, _POSITION_DECIMALS, _QUAT_DECIMALS
    return f"{t:.{tp}f} {pos[0]:.{pp}f} {pos[1]:.{pp}f} {pos[2]:.{pp}f} {x:.{qp}f} {y:.{qp}f} {z:.{qp}f} {w:.{qp}f}\n"


def format_tum(traj: Trajectory) -> str:
    """The whole file text: the header comment, then one line per pose."""
    lines = [TUM_HEADER + "\n"]
    lines.extend(
        format_tum_line(float(t), p, q) for t, p, q in zip(traj.times_s, traj.positions_m, traj.quats_wxyz, strict=True)
    )
    return "".join(lines)


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write ``traj`` as a TUM file atomically (a reader never sees half a file)."""
    write_text_atomic(path, format_tum(traj))
