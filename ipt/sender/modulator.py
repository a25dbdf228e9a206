"""Modulation: hide the tag map in the video as a 60 Hz lightness flicker.

Pure: frames and the mask in, frames out. Output frame ``j`` carries the ``+`` phase on white tag pixels
(and the ``-`` phase on black ones) when ``j`` is even and the opposite when it is odd, so phases keep
alternating whatever the ratio of output to input rate is (:class:`FrameTiming`). The flicker fuses for
people; a camera that subtracts two frames of opposite phase sees ``±2ΔL`` on the tags.

Profiles (``modulation.profile`` in the arena file):

- ``ipt`` (the default, :class:`IptModulator`): colour-exact and Talbot-balanced. Float64 colour maths
  (:mod:`ipt.sender.colour`); pixels outside the mask are copied bit for bit; on a tag pixel of linear
  colour ``c`` (luminance ``Y``) the two phases are ``c + v`` and ``c - v`` in linear light, so their
  mean, which is what the eye sees at 60 Hz (Talbot-Plateau), is ``c`` up to 8-bit quantisation. The
  luminance half-difference ``a`` is solved so that ``L*(Y + a) - L*(Y - a) = 2ΔL`` (ΔL in 8-bit L
  units, 255/100 of L*), and ``v = (a / Y)·c`` keeps the chromaticity of both phases that of ``c``.
  Where a channel would leave 0..1 (``c_i ± v_i``), that channel is held at its bound
  ``m_i=min(c_i,1-c_i)`` and the others are raised to make up the luminance (water-filling); where even
  that is not enough the pair shrinks symmetrically, down to no flicker at all on pure white or pure
  black, which cannot be balanced. The codes: ``+`` is one of the two 8-bit codes around ``c_i + v_i``,
  ``-`` the code nearest to ``2 c_i - lin(+)``, so the linear mean misses ``c_i`` by less than half a
  code step; of those choices the one whose L* step is nearest to 2ΔL is taken. Pure white and black
  and pure primaries would carry no signal at all, so a *clip allowance* (``modulation.clip_allowance_l8``,
  2.2 by default, 0 for exact) lets the centre of the pair move where the full step does not fit: by as
  little as gives it, in the direction that costs the least CIEDE2000 (darker for white, a little green and
  less red for pure red), and never so far that the fused colour differs from the input by more than a
  lightness change of the allowance costs at white (CIEDE2000 0.49 for 2.2, what the paper's profile
  leaves on white). Those are the only pixels where the fused image is not the input
  (:mod:`ipt.sender.pairs` has the details).
- ``paper`` (:class:`PaperModulator`): Algorithm 1 as published, in 8-bit CIELAB (OpenCV's 8-bit Lab: L
  scaled to 0..255). The round trip changes every pixel a little, and clipped phases do not average to
  the original.

Speed (``ipt``): each pixel's pair depends only on its 8-bit colour (and the mask sign), so pairs are
kept in a table over all 2^24 colours (128 MB per ΔL and allowance, shared in a process), and one
compiled pass (numba) writes both output frames of an input frame (:mod:`ipt.sender.pairs`). The table
fills lazily (a colour the first time a frame has it) unless :meth:`IptModulator.complete_table` filled
it first, as the sender does before its clock starts (read from a cache file, or computed once). numba
compiles the pass when the first modulator is made (cached on disk where it can write).
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from fractions import Fraction
from typing import Any, Final, Protocol

import cv2
import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.sender.framekernel import _modulate_rows_c, _modulate_rows_filled_c
from ipt.sender.pairs import JIT_UNAVAILABLE, amplitude_grid
from ipt.sender.pairtable import pair_table

__all__ = ["JIT_UNAVAILABLE", "amplitude_grid"]  # re-exported: the simulator and the tests take them from here

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]

PROFILES: Final = ("ipt", "paper")
"""Modulation profiles; the first is the default."""

MAX_CLIP_ALLOWANCE_L8: Final = 8.0
"""Largest clip allowance of the ``ipt`` profile (8-bit L units); see :class:`IptModulator`."""

DELTA_L_ADVISED: Final = (1.0, 20.0)
"""ΔL (8-bit L units) outside this range works but is either mostly lost to 8-bit quantisation (below) or
likely to be seen and to clip on much of the content (above); :func:`delta_l_warning` says so."""


class ModulationError(IptError):
    """The modulation settings or an input frame are unusable."""


def phase_sign(output_index: int) -> int:
    """+1 for output frames that add ΔL on white tag pixels (even indices), -1 for the others."""
    return 1 if output_index % 2 == 0 else -1


def _rate(value_hz: float) -> Fraction:
    # 1001 keeps NTSC rates exact: 60000/1001 over 30000/1001 is 2. A rate the small denominator cannot
    # hold to a millionth (a very low one would become 0 and divide by zero) is kept exactly instead.
    exact = Fraction(value_hz)
    near = exact.limit_denominator(1001)
    return near if near > 0 and abs(near - exact) <= exact / 1_000_000 else exact


def frames_per_input(input_rate_hz: float, output_rate_hz: float) -> int:
    """N = f_o / f_i when it is a whole number (as Algorithm 1 has it); see :class:`FrameTiming` otherwise."""
    ratio = _rate(output_rate_hz) / _rate(input_rate_hz)
    if ratio.denominator != 1 or ratio < 1:
        raise ModulationError(
            f"output rate {output_rate_hz:g} Hz is not a whole multiple of the input rate {input_rate_hz:g} Hz"
        )
    return int(ratio)


class FrameTiming:
    """Which input frame output frame ``j`` shows: ``i = floor(j · f_i / f_o)``.

    With ``f_o = N·f_i`` every input frame is shown for N output frames (Algorithm 1). With any other
    ratio (24 → 60 Hz: 3, 2, 3, 2, ... output frames per input frame, 2.5 on average; 50 → 60 Hz: some
    input frames shown twice) input frames are repeated unevenly, or dropped when ``f_i > f_o``. The
    phase never follows the input frames: it is ``phase_sign(j)`` of the output frame alone, so the
    projected flicker alternates strictly every output frame and any two consecutive output frames are
    of opposite phase, which is what the receiver pairs.
    """

    def __init__(self, input_rate_hz: float, output_rate_hz: float) -> None:
        for name, value in (("input", input_rate_hz), ("output", output_rate_hz)):
            if not (math.isfinite(value) and value > 0):
                raise ModulationError(f"the {name} frame rate must be a positive number, not {value!r}")
        self.input_rate_hz = input_rate_hz
        self.output_rate_hz = output_rate_hz
        self.ratio = _rate(output_rate_hz) / _rate(input_rate_hz)
        """f_o / f_i as a fraction."""

    @property
    def whole(self) -> bool:
        """Every input frame is shown for the same whole number of output frames."""
        return self.ratio.denominator == 1

    def input_of(self, output_index: int) -> int:
        """The input frame shown as output frame ``output_index``."""
        return output_index * self.ratio.denominator // self.ratio.numerator

    def note(self) -> str | None:
        """A sentence for the user when the rates are not a whole multiple, else ``None``."""
        fi, fo = self.input_rate_hz, self.output_rate_hz
        if self.whole:
            return None
        if self.ratio < 1:
            return (
                f"input {fi:g} Hz is faster than the projector's {fo:g} Hz: input frames are dropped to "
                f"keep time (output frame j shows input frame floor(j·{fi:g}/{fo:g})); the phase still "
                "alternates every output frame"
            )
        lo = math.floor(self.ratio)
        return (
            f"output {fo:g} Hz is not a whole multiple of input {fi:g} Hz: input frames are shown for {lo} or "
            f"{lo + 1} output frames ({float(self.ratio):.3g} on average); the phase alternates every output "
            "frame regardless, so consecutive output frames are always of opposite phase"
        )


def delta_l_warning(delta_l: float) -> str | None:
    """A warning for a ΔL that works badly (see :data:`DELTA_L_ADVISED`), else ``None``."""
    lo, hi = DELTA_L_ADVISED
    if delta_l < lo:
        return (
            f"ΔL {delta_l:g} is below {lo:g} 8-bit L unit: 8-bit output keeps little of such a small step, "
            "so the tags will be faint or missing for the camera"
        )
    if delta_l > hi:
        return (
            f"ΔL {delta_l:g} is above {hi:g} 8-bit L units: the flicker is likely to be seen and clips on "
            "bright and dark content"
        )
    return None


def _check_delta_l(delta_l: float) -> None:
    if not (isinstance(delta_l, int | float) and math.isfinite(delta_l) and 0 < delta_l <= 127):
        raise ModulationError(f"ΔL must be in (0, 127] 8-bit L units, got {delta_l}")


def _check_frame(frame_rgb: npt.NDArray[Any]) -> None:
    if (
        not isinstance(frame_rgb, np.ndarray)
        or frame_rgb.ndim != 3
        or frame_rgb.shape[2] != 3
        or frame_rgb.dtype != np.uint8
    ):
        shape = getattr(frame_rgb, "shape", None)
        dtype = getattr(frame_rgb, "dtype", type(frame_rgb).__name__)
        raise ModulationError(f"expected an H×W×3 uint8 RGB frame, got {shape} {dtype}")


class Modulator(Protocol):
    """What the sender and the simulator need of a modulation profile."""

    profile: str
    delta_l: float
    width_px: int
    height_px: int

    def phases(self, frame_rgb: U8, out: tuple[U8, U8] | None = None) -> tuple[U8, U8]:
        """Both output frames of an input frame: (the ``+`` phase, the ``-`` phase)."""
        ...

    def phase_region(self, frame_rgb: U8, sign: int, region: tuple[int, int, int, int]) -> U8:
        """Region ``(x0, y0, x1, y1)`` of the output frame of phase ``sign``, from that region of the input."""
        ...

    def modulate(self, frame_rgb: U8, first_output_index: int, count: int) -> list[U8]:
        """The ``count`` output frames of one input frame, starting at output index ``first_output_index``."""
        ...


def resize_to(frame_rgb: U8, width_px: int, height_px: int) -> U8:
    """``frame_rgb`` at ``width_px`` × ``height_px`` (``cv2.INTER_AREA``), or itself if it already is."""
    if frame_rgb.shape[:2] == (height_px, width_px):
        return frame_rgb
    return np.asarray(cv2.resize(frame_rgb, (width_px, height_px), interpolation=cv2.INTER_AREA), dtype=np.uint8)


def _check_region(region: tuple[int, int, int, int], width_px: int, height_px: int) -> None:
    x0, y0, x1, y1 = region
    if not (0 <= x0 < x1 <= width_px and 0 <= y0 < y1 <= height_px):
        raise ModulationError(f"region {region} is not inside the {width_px}x{height_px} frame")


# --- the paper's profile -------------------------------------------------------------------------------


class PaperModulator:
    """Algorithm 1: resize, RGB→CIELAB, duplicate N times, L ± ΔL·T_mask with alternating sign, clip, back.

    ``mask`` is T_mask (+1 white tag pixel, -1 black, 0 untouched) at the output resolution.
    """

    profile = "paper"

    def __init__(self, mask: npt.NDArray[np.int8], delta_l: float) -> None:
        _check_delta_l(delta_l)
        self.height_px, self.width_px = mask.shape
        self.delta_l = delta_l
        # ΔL·T_mask in 8-bit L units, rounded once (Algorithm 1 works on 8-bit L).
        self._offset_l = np.rint(mask.astype(np.float32) * np.float32(delta_l)).astype(np.int16)

    def prepare(self, frame_rgb: U8) -> U8:
        """Resize an input frame to the output resolution and convert it to 8-bit CIELAB (steps 3-4)."""
        _check_frame(frame_rgb)
        frame_rgb = resize_to(frame_rgb, self.width_px, self.height_px)
        return np.asarray(cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2Lab), dtype=np.uint8)

    def phase_frame(self, lab: U8, sign: int, region: tuple[int, int, int, int] | None = None) -> U8:
        """One output frame: L + sign·ΔL·T_mask, clipped to 0..255, back to RGB (steps 7-10).

        With ``region = (x0, y0, x1, y1)``, ``lab`` is that region of the prepared frame and only it is
        modulated (the simulator asks for the part of the floor the camera sees).
        """
        offset = self._offset_l
        if region is not None:
            x0, y0, x1, y1 = region
            offset = offset[y0:y1, x0:x1]
        if lab.shape[:2] != offset.shape:
            raise ModulationError(f"frame region {lab.shape[:2]} does not match the mask region {offset.shape}")
        out = lab.copy()
        lightness_l8 = lab[:, :, 0].astype(np.int16)
        if sign > 0:
            lightness_l8 += offset
        else:
            lightness_l8 -= offset
        np.clip(lightness_l8, 0, 255, out=lightness_l8)
        out[:, :, 0] = lightness_l8.astype(np.uint8)
        return np.asarray(cv2.cvtColor(out, cv2.COLOR_Lab2RGB), dtype=np.uint8)

    def phases(self, frame_rgb: U8, out: tuple[U8, U8] | None = None) -> tuple[U8, U8]:
        """Both output frames of an input frame (``out`` is ignored: new arrays are returned)."""
        lab = self.prepare(frame_rgb)
        return self.phase_frame(lab, 1), self.phase_frame(lab, -1)

    def phase_region(self, frame_rgb: U8, sign: int, region: tuple[int, int, int, int]) -> U8:
        """Region of the output frame of phase ``sign``; ``frame_rgb`` is that region of the (resized) input."""
        _check_frame(frame_rgb)
        _check_region(region, self.width_px, self.height_px)
        lab = np.asarray(cv2.cvtColor(np.ascontiguousarray(frame_rgb), cv2.COLOR_RGB2Lab), dtype=np.uint8)
        return self.phase_frame(lab, sign, region)

    def modulate(self, frame_rgb: U8, first_output_index: int, count: int) -> list[U8]:
        """The ``count`` output frames of one input frame, starting at output index ``first_output_index``."""
        lab = self.prepare(frame_rgb)
        return [self.phase_frame(lab, phase_sign(first_output_index + i)) for i in range(count)]


# --- the ipt profile ----------------------------------------------------------------------------------
# The colour maths of one pixel, the table of all colours and the compiled frame pass are in
# ipt.sender.pairs; what the profile does with them is here.

class IptModulator:
    """The ``ipt`` profile (see the module doc): colour-exact, Talbot-balanced, fast.

    ``mask`` is T_mask (+1 white tag pixel, -1 black, 0 untouched) at the output resolution. ``threads``
    worker threads share each frame (by rows); 1 keeps all the work on the calling thread.

    ``clip_allowance_l8`` (8-bit L units, default 0): where the content leaves no room for a balanced pair
    of the full step (pure white and black, pure primaries, and colours next to them), the centre of the
    pair may move, so that the camera still gets a signal there, by as little as gives the full step and in
    the direction that costs least; the average the eye sees then differs from the input at those pixels
    by at most what a lightness change of ``clip_allowance_l8`` costs at white (CIEDE2000 0.45 for 2; see
    :mod:`ipt.sender.pairs`). 0 keeps the average exact everywhere.

    The pairs come from the process's table for ΔL and the allowance, filled as colours appear;
    :meth:`complete_table` fills all of them first (the sender does, before its clock starts).
    """

    profile = "ipt"

    def __init__(
        self, mask: npt.NDArray[np.int8], delta_l: float, threads: int = 1, clip_allowance_l8: float = 0.0
    ) -> None:
        _check_delta_l(delta_l)
        if not (math.isfinite(clip_allowance_l8) and 0.0 <= clip_allowance_l8 <= MAX_CLIP_ALLOWANCE_L8):
            raise ModulationError(
                f"the clip allowance must be in [0, {MAX_CLIP_ALLOWANCE_L8:g}] 8-bit L units, got {clip_allowance_l8}"
            )
        if mask.ndim != 2 or mask.dtype != np.int8:
            raise ModulationError(f"the mask must be an H×W int8 array, got {mask.shape} {mask.dtype}")
        if threads < 1:
            raise ModulationError(f"threads must be at least 1, got {threads}")
        self.height_px, self.width_px = mask.shape
        self.delta_l = float(delta_l)
        self.mask = np.ascontiguousarray(mask)
        self.threads = threads
        self.clip_allowance_l8 = float(clip_allowance_l8)
        if JIT_UNAVAILABLE is not None:
            raise ModulationError(f"the ipt modulation profile needs numba, but {JIT_UNAVAILABLE}")
        self._pairs = pair_table(self.delta_l, self.clip_allowance_l8)
        # Compile (or load from the disk cache) the kernel now rather than in the first frame.
        tiny = np.zeros((1, 1, 3), np.uint8)
        one = np.ones((1, 1), np.int8)
        _modulate_rows_c(tiny, one, *self._pairs.args(), tiny.copy(), tiny.copy(), True, True, 0, 1)
        _modulate_rows_filled_c(tiny, one, *self._pairs.args(), tiny.copy(), tiny.copy(), True, True, 0, 1)
        self._pool = ThreadPoolExecutor(threads - 1, thread_name_prefix="ipt-modulate") if threads > 1 else None

    def close(self) -> None:
        """Stop the worker threads (if any)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False)

    # -- per colour --

    def pair_codes(self, codes: U8) -> tuple[U8, U8]:
        """The (+, -) codes of N colours (N×3 uint8): what a white tag pixel (mask +1) of that colour shows."""
        return self._pairs.pairs(codes)

    @property
    def table_complete(self) -> bool:
        """Every colour's pair is in the table: no frame will compute one."""
        return self._pairs.complete

    def complete_table(self, cache_dir: os.PathLike[str] | None, log: Callable[[str], None]) -> str:
        """Fill the pairs of all colours before frames are due: read from the cache file in ``cache_dir`` or
        computed (progress through ``log``) and kept there (see :meth:`PairTable.complete_with_cache`).
        Returns a sentence saying which."""
        return self._pairs.complete_with_cache(cache_dir, log)

    # -- frames --

    def _run(
        self,
        rgb: U8,
        mask: npt.NDArray[np.int8],
        plus: U8 | None,
        minus: U8 | None,
        rows: tuple[int, int] | None = None,
    ) -> None:
        """Rows ``rows`` (default all) of the phases wanted, split over the worker threads."""
        dummy = plus if plus is not None else minus
        assert dummy is not None
        row0, row1 = (0, rgb.shape[0]) if rows is None else rows
        kernel = self._kernel()  # before the table's arrays: a table completed meanwhile is a new array
        args: tuple[Any, ...] = (
            rgb,
            mask,
            *self._pairs.args(),
            plus if plus is not None else dummy,
            minus if minus is not None else dummy,
            plus is not None,
            minus is not None,
        )
        if self._pool is None or row1 - row0 < 64:
            kernel(*args, row0, row1)
            return
        bounds = [row0 + (row1 - row0) * k // self.threads for k in range(self.threads + 1)]
        calls: list[tuple[Any, ...]] = [(*args, r0, r1) for r0, r1 in itertools.pairwise(bounds[1:])]
        futures = [self._pool.submit(kernel, *call) for call in calls]
        kernel(*args, bounds[0], bounds[1])
        for f in futures:
            f.result()

    def _kernel(self) -> Any:
        """The frame kernel: the one without colour maths once every colour's pair is in the table."""
        return _modulate_rows_filled_c if self._pairs.complete else _modulate_rows_c

    def _output(self, given: U8 | None) -> U8:
        shape = (self.height_px, self.width_px, 3)
        if given is None:
            return np.empty(shape, dtype=np.uint8)
        if given.shape != shape or given.dtype != np.uint8 or not given.flags.c_contiguous:
            raise ModulationError(f"output buffers must be contiguous {shape} uint8 arrays")
        return given

    def prepare(self, frame_rgb: U8) -> U8:
        """The input frame at the output resolution, contiguous (resized with ``cv2.INTER_AREA`` if need be)."""
        _check_frame(frame_rgb)
        return np.ascontiguousarray(resize_to(frame_rgb, self.width_px, self.height_px))

    def phases(self, frame_rgb: U8, out: tuple[U8, U8] | None = None) -> tuple[U8, U8]:
        """Both output frames of an input frame, in one pass: (the ``+`` phase, the ``-`` phase).

        ``out`` are two arrays to write them into (reused between input frames by the sender).
        """
        rgb = self.prepare(frame_rgb)
        plus = self._output(None if out is None else out[0])
        minus = self._output(None if out is None else out[1])
        self._run(rgb, self.mask, plus, minus)
        return plus, minus

    def phases_rows(self, frame_rgb: U8, out: tuple[U8, U8], row0: int, row1: int) -> None:
        """Rows ``row0..row1`` of both phases of ``frame_rgb`` (contiguous, at the output resolution) into
        ``out``: :meth:`phases` in parts, so that the sender can spread an input frame's work over two output
        frames."""
        _check_frame(frame_rgb)
        if frame_rgb.shape[:2] != (self.height_px, self.width_px) or not frame_rgb.flags.c_contiguous:
            raise ModulationError(f"expected a contiguous {self.width_px}x{self.height_px} frame")
        if not 0 <= row0 <= row1 <= self.height_px:
            raise ModulationError(f"rows {row0}..{row1} are not inside 0..{self.height_px}")
        plus, minus = self._output(out[0]), self._output(out[1])
        self._run(frame_rgb, self.mask, plus, minus, (row0, row1))

    def phase_frame(self, frame_rgb: U8, sign: int, out: U8 | None = None) -> U8:
        """The output frame of phase ``sign`` only."""
        rgb = self.prepare(frame_rgb)
        frame = self._output(out)
        self._run(rgb, self.mask, frame if sign > 0 else None, None if sign > 0 else frame)
        return frame

    def phase_region(self, frame_rgb: U8, sign: int, region: tuple[int, int, int, int]) -> U8:
        """Region ``(x0, y0, x1, y1)`` of the output frame of phase ``sign``; ``frame_rgb`` is that region of the
        input (at the output resolution). Equal to the same crop of :meth:`phase_frame`."""
        _check_frame(frame_rgb)
        _check_region(region, self.width_px, self.height_px)
        x0, y0, x1, y1 = region
        if frame_rgb.shape[:2] != (y1 - y0, x1 - x0):
            raise ModulationError(f"frame region {frame_rgb.shape[:2]} does not match the region {region}")
        rgb = np.ascontiguousarray(frame_rgb)
        mask = np.ascontiguousarray(self.mask[y0:y1, x0:x1])
        out = np.empty_like(rgb)
        kernel = self._kernel()
        kernel(rgb, mask, *self._pairs.args(), out, out, sign > 0, sign <= 0, 0, rgb.shape[0])
        return out

    def modulate(self, frame_rgb: U8, first_output_index: int, count: int) -> list[U8]:
        """The ``count`` output frames of one input frame, starting at output index ``first_output_index``."""
        plus, minus = self.phases(frame_rgb)
        return [plus if phase_sign(first_output_index + i) > 0 else minus for i in range(count)]


def make_modulator(
    profile: str, mask: npt.NDArray[np.int8], delta_l: float, threads: int = 1, clip_allowance_l8: float = 0.0
) -> IptModulator | PaperModulator:
    """The modulator of ``profile`` (one of :data:`PROFILES`); ``clip_allowance_l8`` is for ``ipt`` only."""
    if profile == "ipt":
        return IptModulator(mask, delta_l, threads, clip_allowance_l8)
    if profile == "paper":
        return PaperModulator(mask, delta_l)
    raise ModulationError(f"unknown modulation profile {profile!r}; choose one of {', '.join(PROFILES)}")
