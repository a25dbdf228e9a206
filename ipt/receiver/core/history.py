"""The frames the pipeline keeps for pairing, and the rules that pair them (:class:`FrameHistory`); the records
it keeps of each frame (:class:`Frame`; before its turn, :class:`Prepared`), each pair (:class:`Pair`) and each
candidate pose (:class:`Candidate`).

A *pair* is two frames of opposite projector phase: a time step close to an odd number of projector periods
(:meth:`FrameHistory.phase_error`). A frame's partners are the kept frames on one side of it within
:data:`MAX_PAIR_PERIODS` periods, the best phase first and of equal phases the closer one
(:meth:`FrameHistory.partners`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from ipt.receiver.core.demodulator import PairDifference
from ipt.receiver.core.frameresult import FrameResult
from ipt.receiver.core.imagealign import AlignTarget
from ipt.receiver.core.pose import PoseEstimate

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

#: Frames kept for pairing.
HISTORY = 6
#: A pairing whose time step is this far (in projector periods) from an odd number is not tried. Half a
#: period is still tried as a fallback: when an exposure straddles a flip, its lag-2 partner straddles the
#: same way and the signal cancels, while the neighbour on the other side of the flip keeps half of it.
MAX_PHASE_ERROR = 0.55
#: Partners tried for a frame from each side, best phase first.
MAX_PARTNERS = 2
#: Pairs further apart than this many projector periods are not tried (the content changes in between).
MAX_PAIR_PERIODS = 2.6
#: A candidate fitting this share of the map's visible edges is a good one: the pipeline takes it without trying more
#: partners, and sends it out without waiting for later ones (sparse tracker); below it, a frame that took the sparse
#: tracker's dense way is paired with its untried partners on both sides.
GOOD_QUALITY = 0.3


@dataclass(frozen=True)
class Prepared:
    """A camera frame's own work, done before its turn (:meth:`~ipt.receiver.core.pipeline.Pipeline.prepare`)."""

    problem: str | None
    """Why it is not a frame to work on (:func:`~ipt.receiver.core.framecheck.frame_problem`), or None."""
    lum: U8 | None
    """Its lightness (binned if the pipeline bins its camera's frames, undistorted where the dense way needs it);
    None with a problem."""
    signal: U8 | None
    """Its signal mask (ipt profile)."""
    features: F32 | None
    """Its alignment features (ipt profile)."""


@dataclass
class Frame:
    """A camera frame the pipeline works on, and what it has learnt of it so far."""

    index: int
    time_us: int
    lum: U8
    """Lightness (undistorted in the ipt profile)."""
    signal: U8 | None = None
    features: F32 | None = None
    lit_share: float = 1.0
    """The share of the camera's view that its signal mask lights (measured in the ipt profile; else taken as
    all), for the reason of a frame without a pose."""
    target: AlignTarget | None = None
    rt: tuple[F64, F64] | None = None
    """OpenCV's (rvec, tvec) of the pose found for this frame."""
    phase: int | None = None
    """+1 if this frame showed the +ΔL phase, -1 the other, None if not known."""
    result: FrameResult | None = None
    final: bool = False
    tried: set[int] = field(default_factory=set)
    candidates: list[Candidate] = field(default_factory=list)
    """The poses found for this frame with each partner (ipt profile), not yet gated."""
    best: Candidate | None = None
    """The candidate that fits the map best so far."""
    failure: FrameResult | None = None
    """Why the last attempt gave no pose."""
    raw: U8 | None = None
    """Its lightness as the camera saw it (not undistorted), kept by the sparse tracker, which prepares
    :attr:`lum`, :attr:`signal` and :attr:`features` from it only when a dense pair needs them (until then
    :attr:`signal` is None)."""
    waiting: bool = False
    """The sparse chain waits for a later frame to pose this one."""


@dataclass(frozen=True)
class Candidate:
    """A pose found for a frame with one partner, and how well the map fitted it."""

    pose: PoseEstimate
    rt: tuple[F64, F64]
    tags: int
    method: str
    partner: int
    quality: float
    """The share of the visible map's edges on their steps (0 for a pose from tag corners alone)."""


@dataclass
class Pair:
    """Two frames' alignment and difference."""

    warp: F64
    """Carries the earlier frame onto the later one (undistorted pixels)."""
    later: PairDifference
    earlier: PairDifference | None = None


class FrameHistory:
    """The last :data:`HISTORY` frames, oldest first, and which of them pair with a frame."""

    def __init__(self, projector_hz: float, pairing: str) -> None:
        """``pairing``: "opposite_phase" (the ipt profile: :meth:`partners`) or "previous" (the frame before)."""
        self.projector_hz = projector_hz
        self.pairing = pairing
        self.pair_span_us = MAX_PAIR_PERIODS * 1e6 / projector_hz
        """Frames further apart than this are never paired (:data:`MAX_PAIR_PERIODS`)."""
        self._frames: deque[Frame] = deque(maxlen=HISTORY)

    def __iter__(self) -> Iterator[Frame]:
        return iter(self._frames)

    def __reversed__(self) -> Iterator[Frame]:
        return reversed(self._frames)

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, k: int) -> Frame:
        return self._frames[k]

    def append(self, frame: Frame) -> None:
        """Keep ``frame`` (the newest), forgetting the oldest beyond :data:`HISTORY`."""
        self._frames.append(frame)

    def clear(self) -> None:
        self._frames.clear()

    def phase_error(self, dt_us: int) -> float:
        """How far (in projector periods) a time step is from an odd number of periods: 0 for opposite phases,
        1 for the same phase."""
        periods = abs(dt_us) * 1e-6 * self.projector_hz
        return float(abs(periods - (2 * np.floor(periods / 2) + 1)))

    def partners(self, frame: Frame, earlier: bool) -> list[Frame]:
        """Frames to pair ``frame`` with, on one side, the best phase first."""
        others = [f for f in self._frames if (f.index < frame.index if earlier else f.index > frame.index)]
        if self.pairing == "previous":
            return others[-1:] if earlier else []
        others = [f for f in others if abs(frame.time_us - f.time_us) <= self.pair_span_us]
        good = [f for f in others if self.phase_error(frame.time_us - f.time_us) < MAX_PHASE_ERROR]
        return sorted(good, key=lambda f: self.partner_rank(frame, f))[:MAX_PARTNERS]

    def partner_rank(self, frame: Frame, other: Frame) -> tuple[int, int]:
        """Sorts ``frame``'s partners best first: phase errors within a twentieth of a period are equal here
        (capture times are whole microseconds), and of those the closer partner comes first."""
        dt_us = frame.time_us - other.time_us
        return round(self.phase_error(dt_us) * 20), abs(dt_us)

    def same_phase(self, a: Frame, b: Frame) -> bool:
        """Whether ``a`` and ``b`` are a whole even number of projector periods apart (within a quarter): as far
        from an odd number as can be (the pairing's phase error, which is 0 for opposite phases)."""
        dt_us = b.time_us - a.time_us
        return abs(dt_us) * 1e-6 * self.projector_hz > 1 and self.phase_error(dt_us) > 0.75

    def predicted_phase(self, frame: Frame) -> int | None:
        """+1 if ``frame`` probably showed the +ΔL phase, from what earlier poses revealed."""
        if frame.phase is not None:
            return frame.phase
        for f in reversed(self._frames):
            if f.phase is not None and f is not frame:
                flips = round((frame.time_us - f.time_us) * 1e-6 * self.projector_hz)
                return f.phase * (-1 if flips % 2 else 1)
        return None
