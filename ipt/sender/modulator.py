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
  (and pure primaries) would carry no signal at all, so a *clip allowance*
  (``modulation.clip_allowance_l8``, 2 by default, 0 for exact) lets the centre of the pair move towards
  mid-grey where the full step does not fit, by as little lightness as gives it and at most the
  allowance. Those are the only pixels where the fused image is not the input (about 0.5 CIEDE2000 on
  pure white or black at 2, as the paper's profile has it there too).
- ``paper`` (:class:`PaperModulator`): Algorithm 1 as published, in 8-bit CIELAB (OpenCV's 8-bit Lab: L
  scaled to 0..255). The round trip changes every pixel a little, and clipped phases do not average to
  the original.

Speed (``ipt``): each pixel's pair depends only on its 8-bit colour (and the mask sign), so pairs are
kept in a table over all 2^24 colours (128 MB per ΔL and allowance, shared in a process), filled lazily
(a colour is worked out, in about a microsecond, the first time it is seen, in the same pass), and one
compiled pass (numba) writes both output frames of an input frame. numba compiles it when the first
modulator is made (cached on disk where the package folder is writable).
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from fractions import Fraction
from typing import Any, Final, Protocol

import cv2
import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.sender.colour import CODE_TO_LINEAR, L8_PER_LSTAR, LUMINANCE_WEIGHTS, lightness

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


# --- the ipt profile: the colour maths of one pixel ------------------------------------------------------

AMPLITUDE_STEPS: Final = 1 << 16
"""Intervals of the luminance grid on which the amplitude a(Y) is solved (then interpolated linearly)."""


def amplitude_grid(delta_l: float, steps: int = AMPLITUDE_STEPS) -> F64:
    """``a(Y)`` at ``Y = k / steps``: the half-difference of luminance whose L* differ by 2ΔL around Y.

    Solves ``L*(Y + a) - L*(Y - a) = 2·ΔL·100/255`` for ``0 <= a <= Y`` by bisection to float64
    precision (``a = Y`` where even that is not enough: the darkest greys). ``a`` is not limited by
    ``Y + a <= 1``: that bound is the per-channel one applied later.
    """
    _check_delta_l(delta_l)
    target = 2.0 * delta_l / L8_PER_LSTAR
    y = np.linspace(0.0, 1.0, steps + 1)
    lo, hi = np.zeros_like(y), y.copy()
    for _ in range(64):
        a = (lo + hi) / 2
        above = lightness(y + a) - lightness(y - a) > target
        hi = np.where(above, a, hi)
        lo = np.where(above, lo, a)
    out: F64 = (lo + hi) / 2
    return out


_VALID: Final = np.uint64(1 << 63)
_LOW24: Final = np.uint64(0xFFFFFF)
_SHIFT_DOWN: Final = np.uint64(24)
_MIDS: Final = (CODE_TO_LINEAR[:-1] + CODE_TO_LINEAR[1:]) / 2
"""Linear light half way between consecutive codes: the nearest code to x is the number of mids below x."""


def _nearest(x: float, mids: F64) -> int:
    """The 8-bit code nearest to linear ``x`` (``np.searchsorted(mids, x)``)."""
    lo, hi = 0, mids.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if mids[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


def _floor_code(x: float, lin: F64) -> int:
    """The largest 8-bit code whose linear light is at most ``x`` (0 if none)."""
    lo, hi = 0, lin.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if lin[mid] <= x:
            lo = mid + 1
        else:
            hi = mid
    return max(lo - 1, 0)


def _lstar(y: float) -> float:
    """CIE L* of relative luminance ``y`` (as :func:`ipt.sender.colour.lightness`)."""
    if y > 0.008856451679035631:  # (6/29)^3
        return 116.0 * float(y ** (1.0 / 3.0)) - 16.0
    return 116.0 * (y / 0.12841854934601665 + 4.0 / 29.0) - 16.0  # 3 (6/29)^2


def _balanced(k: int, c: float, p: int, lin: F64, mids: F64) -> int:
    """The ``-`` code that balances ``+`` code ``p`` around code ``k`` (linear ``c``): nearest to 2c - lin(p);
    -1 if the mean of the two would miss ``c`` by more than 8-bit quantisation (half a code step at ``k``)."""
    q = min(int(_nearest_c(2.0 * c - lin[p], mids)), k)
    tol = max(lin[min(k + 1, 255)] - c, c - lin[max(k - 1, 0)]) / 2.0
    if abs(lin[p] + lin[q] - 2.0 * c) > 2.0 * tol:
        return -1
    return q


def _luminance_of_lstar(lstar: float) -> float:
    """Relative luminance of CIE L* (the inverse of :func:`_lstar`)."""
    f = (lstar + 16.0) / 116.0
    if f > 6.0 / 29.0:
        return f * f * f
    return 0.12841854934601665 * (f - 4.0 / 29.0)


def _amplitude(y: float, agrid: F64) -> float:
    """a(Y), linearly interpolated in :func:`amplitude_grid`."""
    n = agrid.shape[0] - 1
    x = y * n
    k = min(max(int(x), 0), n - 1)
    return float(agrid[k] + (agrid[k + 1] - agrid[k]) * (x - k))


def _fill(c0: float, c1: float, c2: float, a: float, w: F64) -> tuple[float, float, float]:
    """The half-difference v (linear RGB) whose luminance is ``a``, within the room of each channel.

    Water-filling: v_i = min(t·c_i, m_i) with m_i = min(c_i, 1 - c_i), t such that w·v = a. Channels that
    reach their bound are held there and the others raised; t = a / Y (chromaticity held) when none does.
    With no t enough, v = m.
    """
    w0, w1, w2 = w[0], w[1], w[2]
    m0, m1, m2 = min(c0, 1.0 - c0), min(c1, 1.0 - c1), min(c2, 1.0 - c2)
    s0 = s1 = s2 = False
    t = 0.0
    for _ in range(4):
        need, slope = a, 0.0
        if s0:
            need -= w0 * m0
        elif c0 > 0.0:
            slope += w0 * c0
        if s1:
            need -= w1 * m1
        elif c1 > 0.0:
            slope += w1 * c1
        if s2:
            need -= w2 * m2
        elif c2 > 0.0:
            slope += w2 * c2
        t = need / slope if slope > 0.0 else 0.0
        changed = False
        if not s0 and c0 > 0.0 and t * c0 > m0:
            s0 = changed = True
        if not s1 and c1 > 0.0 and t * c1 > m1:
            s1 = changed = True
        if not s2 and c2 > 0.0 and t * c2 > m2:
            s2 = changed = True
        if not changed:
            break
    v0 = m0 if s0 else max(0.0, min(t * c0, m0))
    v1 = m1 if s1 else max(0.0, min(t * c1, m1))
    v2 = m2 if s2 else max(0.0, min(t * c2, m2))
    return v0, v1, v2


def _recentre(c0: float, c1: float, c2: float, y: float, y_f: float, bright: bool) -> tuple[float, float, float]:
    """The linear colour ``c`` (luminance ``y``) moved to luminance ``y_f``: scaled if ``bright`` (keeps the
    chromaticity), else shifted by the same amount in every channel (grey added)."""
    if bright:
        scale = y_f / y
        return c0 * scale, c1 * scale, c2 * scale
    return c0 + (y_f - y), c1 + (y_f - y), c2 + (y_f - y)


def _ipt_pair(
    r: int, g: int, b: int, lin: F64, mids: F64, agrid: F64, w: F64, target: float, allowance: float
) -> np.uint64:
    """The pair of one colour: ``valid | up | down << 24`` with up/down packed as ``r << 16 | g << 8 | b``.

    ``target`` is 2ΔL and ``allowance`` the clip allowance, both in L* units.
    """
    c0, c1, c2 = lin[r], lin[g], lin[b]
    w0, w1, w2 = w[0], w[1], w[2]
    y = w0 * c0 + w1 * c1 + w2 * c2
    a = _amplitude_c(y, agrid)
    v0, v1, v2 = _fill_c(c0, c1, c2, a, w)
    k0, k1, k2 = r, g, b  # the codes the pair is balanced around
    reach = w0 * v0 + w1 * v1 + w2 * v2
    if allowance > 0.0 and _lstar_c(y + reach) - _lstar_c(y - reach) < target * (1.0 - 1e-4):
        # Too close to white or black for the full step: move the centre of the pair towards the middle
        # by as little lightness as gives the full step, at most `allowance` (scaling down keeps the
        # chromaticity of bright colours; dark ones get grey added).
        lstar = _lstar_c(y)
        bright = lstar >= 50.0
        if bright:
            y_far = _luminance_of_lstar_c(max(lstar - allowance, 0.0))
        else:
            y_far = _luminance_of_lstar_c(min(lstar + allowance, 100.0))
        lo, hi = 0.0, 1.0
        for it in range(26):
            f = hi if it == 0 else (lo + hi) / 2.0
            y_f = y + f * (y_far - y)
            d0, d1, d2 = _recentre_c(c0, c1, c2, y, y_f, bright)
            u0, u1, u2 = _fill_c(d0, d1, d2, _amplitude_c(y_f, agrid), w)
            reach = w0 * u0 + w1 * u1 + w2 * u2
            enough = _lstar_c(y_f + reach) - _lstar_c(y_f - reach) >= target * (1.0 - 1e-4)
            if it == 0 and not enough:  # even the whole allowance falls short: use it all
                lo = hi
                break
            if enough:
                hi = f
            else:
                lo = f
        f = hi
        y_f = y + f * (y_far - y)
        c0, c1, c2 = _recentre_c(c0, c1, c2, y, y_f, bright)
        v0, v1, v2 = _fill_c(c0, c1, c2, _amplitude_c(y_f, agrid), w)
        k0, k1, k2 = _nearest_c(c0, mids), _nearest_c(c1, mids), _nearest_c(c2, mids)
    # Codes: for each channel the + code is one of the two around c_i + v_i and the - code balances it
    # (nearest to 2 c_i - lin(+); a + code that cannot be balanced within half a code step is skipped, the
    # lower one always can); of those (up to 8) combinations, the one whose L* difference is nearest to 2ΔL
    # wins, so that the quantisation of a few dominant colours does not bias the signal.
    lo0 = min(max(_floor_code_c(c0 + v0, lin), k0), 255) if v0 > 0.0 else k0
    lo1 = min(max(_floor_code_c(c1 + v1, lin), k1), 255) if v1 > 0.0 else k1
    lo2 = min(max(_floor_code_c(c2 + v2, lin), k2), 255) if v2 > 0.0 else k2
    n0 = 2 if (v0 > 0.0 and lo0 < 255) else 1
    n1 = 2 if (v1 > 0.0 and lo1 < 255) else 1
    n2 = 2 if (v2 > 0.0 and lo2 < 255) else 1
    best = 1e300
    p0, q0, p1, q1, p2, q2 = k0, k0, k1, k1, k2, k2
    for i0 in range(n0):
        e0 = lo0 + i0
        f0 = _balanced_c(k0, c0, e0, lin, mids)
        if f0 < 0:
            continue
        for i1 in range(n1):
            e1 = lo1 + i1
            f1 = _balanced_c(k1, c1, e1, lin, mids)
            if f1 < 0:
                continue
            for i2 in range(n2):
                e2 = lo2 + i2
                f2 = _balanced_c(k2, c2, e2, lin, mids)
                if f2 < 0:
                    continue
                y_up = w0 * lin[e0] + w1 * lin[e1] + w2 * lin[e2]
                y_down = w0 * lin[f0] + w1 * lin[f1] + w2 * lin[f2]
                miss = abs(_lstar_c(y_up) - _lstar_c(y_down) - target)
                if miss < best:
                    best = miss
                    p0, q0, p1, q1, p2, q2 = e0, f0, e1, f1, e2, f2
    up = (np.uint64(p0) << np.uint64(16)) | (np.uint64(p1) << np.uint64(8)) | np.uint64(p2)
    down = (np.uint64(q0) << np.uint64(16)) | (np.uint64(q1) << np.uint64(8)) | np.uint64(q2)
    return _VALID | up | (down << _SHIFT_DOWN)


def _ipt_rows(
    rgb: U8,
    mask: npt.NDArray[np.int8],
    table: npt.NDArray[np.uint64],
    lin: F64,
    mids: F64,
    agrid: F64,
    w: F64,
    target: float,
    allowance: float,
    out_plus: U8,
    out_minus: U8,
    want_plus: bool,
    want_minus: bool,
    row0: int,
    row1: int,
) -> None:
    """Rows ``row0..row1`` of both phases (those wanted); fills the table entries it needs."""
    width = rgb.shape[1]
    for yy in range(row0, row1):
        for xx in range(width):
            m = mask[yy, xx]
            r, g, b = rgb[yy, xx, 0], rgb[yy, xx, 1], rgb[yy, xx, 2]
            if m == 0:
                if want_plus:
                    out_plus[yy, xx, 0], out_plus[yy, xx, 1], out_plus[yy, xx, 2] = r, g, b
                if want_minus:
                    out_minus[yy, xx, 0], out_minus[yy, xx, 1], out_minus[yy, xx, 2] = r, g, b
                continue
            i = (np.int64(r) << 16) | (np.int64(g) << 8) | np.int64(b)
            e = table[i]
            if e == 0:
                e = _ipt_pair_c(r, g, b, lin, mids, agrid, w, target, allowance)
                table[i] = e
            up = e & _LOW24
            down = (e >> _SHIFT_DOWN) & _LOW24
            if m < 0:
                up, down = down, up
            if want_plus:
                out_plus[yy, xx, 0] = (up >> np.uint64(16)) & np.uint64(255)
                out_plus[yy, xx, 1] = (up >> np.uint64(8)) & np.uint64(255)
                out_plus[yy, xx, 2] = up & np.uint64(255)
            if want_minus:
                out_minus[yy, xx, 0] = (down >> np.uint64(16)) & np.uint64(255)
                out_minus[yy, xx, 1] = (down >> np.uint64(8)) & np.uint64(255)
                out_minus[yy, xx, 2] = down & np.uint64(255)


def _ipt_colours(
    codes: U8,
    table: npt.NDArray[np.uint64],
    lin: F64,
    mids: F64,
    agrid: F64,
    w: F64,
    target: float,
    allowance: float,
) -> None:
    """Fill the table entries of the colours ``codes`` (N×3)."""
    for j in range(codes.shape[0]):
        r, g, b = codes[j, 0], codes[j, 1], codes[j, 2]
        i = (np.int64(r) << 16) | (np.int64(g) << 8) | np.int64(b)
        if table[i] == 0:
            table[i] = _ipt_pair_c(r, g, b, lin, mids, agrid, w, target, allowance)


JIT_UNAVAILABLE: str | None = None
"""Why numba cannot compile here (e.g. memory that is both writable and executable is forbidden, as
under systemd's MemoryDenyWriteExecute), or None if it can. The ``ipt`` profile needs it."""


def _jit(fn: Callable[..., Any]) -> Any:
    """``fn`` compiled by numba (nogil, so worker threads run in parallel); cached on disk if possible.

    Where numba cannot run, a stand-in that raises :class:`ModulationError` when called, so that the
    module (and the ``paper`` profile) still imports.
    """
    global JIT_UNAVAILABLE
    try:
        import numba
    except (ImportError, OSError) as exc:  # OSError: llvmlite refused executable memory
        JIT_UNAVAILABLE = f"numba cannot compile here ({type(exc).__name__}: {exc})"

        def unavailable(*_args: Any) -> Any:
            raise ModulationError(f"the ipt modulation profile needs numba, but {JIT_UNAVAILABLE}")

        return unavailable
    try:
        return numba.njit(nogil=True, cache=True)(fn)
    except RuntimeError:  # no writable cache location: compile in every process
        return numba.njit(nogil=True)(fn)


# The compiled versions. Each function calls the compiled version of the ones above it, looked up as a
# global when it is compiled (at its first call).
_nearest_c: Any = _jit(_nearest)
_floor_code_c: Any = _jit(_floor_code)
_lstar_c: Any = _jit(_lstar)
_luminance_of_lstar_c: Any = _jit(_luminance_of_lstar)
_amplitude_c: Any = _jit(_amplitude)
_fill_c: Any = _jit(_fill)
_balanced_c: Any = _jit(_balanced)
_recentre_c: Any = _jit(_recentre)
_ipt_pair_c: Any = _jit(_ipt_pair)
_ipt_rows_c: Any = _jit(_ipt_rows)
_ipt_colours_c: Any = _jit(_ipt_colours)


class _PairTable:
    """The lazily filled pairs of every 8-bit colour for one ΔL and clip allowance; shared by all
    modulators in a process."""

    def __init__(self, delta_l: float, clip_allowance_l8: float) -> None:
        self.delta_l = delta_l
        self.allowance = clip_allowance_l8 / L8_PER_LSTAR
        self.agrid = amplitude_grid(delta_l)
        # Written through once (128 MB) rather than np.zeros' untouched pages: faulting pages in one at a
        # time, at random, as new colours come (a page per colour at first) costs far more per page.
        self.table = np.empty(1 << 24, dtype=np.uint64)
        self.table.fill(0)
        self.lin = np.ascontiguousarray(CODE_TO_LINEAR)
        self.mids = np.ascontiguousarray(_MIDS)
        self.w = np.ascontiguousarray(LUMINANCE_WEIGHTS)
        self.target = 2.0 * delta_l / L8_PER_LSTAR

    def args(self) -> tuple[Any, ...]:
        return self.table, self.lin, self.mids, self.agrid, self.w, self.target, self.allowance


_TABLES: dict[tuple[float, float], _PairTable] = {}
_TABLES_LOCK = threading.Lock()


def _pair_table(delta_l: float, clip_allowance_l8: float) -> _PairTable:
    with _TABLES_LOCK:
        key = (delta_l, clip_allowance_l8)
        table = _TABLES.get(key)
        if table is None:
            table = _TABLES[key] = _PairTable(delta_l, clip_allowance_l8)
        return table


def _unpack(entries: npt.NDArray[np.uint64]) -> tuple[U8, U8]:
    shifts = np.array([16, 8, 0], dtype=np.uint64)
    up = ((entries[:, None] >> shifts) & np.uint64(255)).astype(np.uint8)
    down = (((entries[:, None] >> _SHIFT_DOWN) >> shifts) & np.uint64(255)).astype(np.uint8)
    return up, down


class IptModulator:
    """The ``ipt`` profile (see the module doc): colour-exact, Talbot-balanced, fast.

    ``mask`` is T_mask (+1 white tag pixel, -1 black, 0 untouched) at the output resolution. ``threads``
    worker threads share each frame (by rows); 1 keeps all the work on the calling thread.

    ``clip_allowance_l8`` (8-bit L units, default 0): where the content is too close to white or black for
    a balanced pair of the full step (pure white, pure black, and next to them), the centre of the pair may
    move towards mid-grey by up to this much lightness, so that the camera still gets a signal there. The
    average the eye sees then differs from the input by that much at those pixels (about 0.22 CIEDE2000
    per unit near white and black). 0 keeps the average exact everywhere.
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
        self._pairs = _pair_table(self.delta_l, self.clip_allowance_l8)
        # Compile (or load from the disk cache) the kernel now rather than in the first frame.
        tiny = np.zeros((1, 1, 3), np.uint8)
        _ipt_rows_c(tiny, np.ones((1, 1), np.int8), *self._pairs.args(), tiny.copy(), tiny.copy(), True, True, 0, 1)
        self._pool = ThreadPoolExecutor(threads - 1, thread_name_prefix="ipt-modulate") if threads > 1 else None

    def close(self) -> None:
        """Stop the worker threads (if any)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False)

    # -- per colour --

    def pair_codes(self, codes: U8) -> tuple[U8, U8]:
        """The (+, -) codes of N colours (N×3 uint8): what a white tag pixel (mask +1) of that colour shows."""
        codes = np.ascontiguousarray(codes, dtype=np.uint8).reshape(-1, 3)
        _ipt_colours_c(codes, *self._pairs.args())
        idx = (codes[:, 0].astype(np.int64) << 16) | (codes[:, 1].astype(np.int64) << 8) | codes[:, 2]
        return _unpack(self._pairs.table[idx])

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
            _ipt_rows_c(*args, row0, row1)
            return
        bounds = [row0 + (row1 - row0) * k // self.threads for k in range(self.threads + 1)]
        calls: list[tuple[Any, ...]] = [(*args, r0, r1) for r0, r1 in itertools.pairwise(bounds[1:])]
        futures = [self._pool.submit(_ipt_rows_c, *call) for call in calls]
        _ipt_rows_c(*args, bounds[0], bounds[1])
        for f in futures:
            f.result()

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
        _ipt_rows_c(rgb, mask, *self._pairs.args(), out, out, sign > 0, sign <= 0, 0, rgb.shape[0])
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
