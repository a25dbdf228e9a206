"""How invisible the hidden tags are, and how much of them a camera gets: every modulation profile.

Pure: frames in, figures out. For each input frame (at projector size) and each profile, the two output
frames of opposite phase are made by the sender's own modulator, and:

- **fused error**: the eye fuses 60 Hz flicker by averaging light (Talbot–Plateau), so what is seen is
  the linear-light mean of the two phases (sRGB codes decoded to linear light, averaged). Its CIEDE2000
  difference from the input frame (:func:`ciede2000`, CIELAB under D65) is reported over the tag pixels
  (mask ±1) and over the other pixels: mean, 99th percentile, maximum. ``identical_fraction`` of the
  non-tag pixels is the share where both phases equal the input bit for bit.
- **saccade error**: during an eye movement the two phases land on the retina a few pixels apart, so
  the flicker no longer cancels pixel by pixel (the "phantom array" along tag edges). What is seen at a
  retinal point is then the linear mean of the ``+`` phase at x and the ``-`` phase at x + d
  (``saccade_px``, horizontal); it is compared, by CIEDE2000, with what the same eye movement makes of the
  unmodulated input (the mean of the input at x and at x + d), over the points where x or x + d is a tag
  pixel. No modulation can make this 0: it shows how visible the tags' edges are to a moving eye.
- **camera-side signal**: the mean over tag pixels of ``(L*(+) - L*(-)) · T_mask``, the lightness
  difference between the two phases a camera subtracts, in 8-bit L units (L* · 255/100). The paper's
  modulator aims at ``2ΔL``. ``flat_fraction`` is the share of tag pixels where the phases are equal
  (no signal at all, e.g. pure white or black content under the ``ipt`` profile with no clip allowance).

Percentiles come from a histogram with 0.001 bins up to 20 (bounded memory over long videos).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Final

import numpy as np
import numpy.typing as npt

from ipt.config.models import ArenaConfig
from ipt.sender.colour import CODE_TO_LINEAR, L8_PER_LSTAR, LUMINANCE_WEIGHTS, linear_to_lab, lstar
from ipt.sender.content import ContentSource
from ipt.sender.modulator import PROFILES, Modulator, make_modulator, resize_to
from ipt.tagmap import grid_tag_map

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

_CHUNK: Final = 1 << 18  # pixels per CIEDE2000 batch (bounded temporary memory)
SACCADE_PX: Final = 4
"""Default distance (projector pixels) between where the two phases land on the retina for the saccade
figure: "a few pixels", as an eye moving across the picture makes of two frames 1/60 s apart."""


def ciede2000(lab1: npt.ArrayLike, lab2: npt.ArrayLike) -> F64:
    """CIEDE2000 colour difference (kL = kC = kH = 1) of CIELAB colours, last axis (L*, a*, b*).

    Written from Sharma, Wu & Dalal (2005), "The CIEDE2000 color-difference formula: implementation
    notes, supplementary test data, and mathematical observations", eqs. (1)-(17); hue angles in degrees.
    """
    x1 = np.asarray(lab1, dtype=np.float64)
    x2 = np.asarray(lab2, dtype=np.float64)
    l1, a1, b1 = x1[..., 0], x1[..., 1], x1[..., 2]
    l2, a2, b2 = x2[..., 0], x2[..., 1], x2[..., 2]
    p7 = 25.0**7
    c_bar = (np.hypot(a1, b1) + np.hypot(a2, b2)) / 2
    g = 0.5 * (1.0 - np.sqrt(c_bar**7 / (c_bar**7 + p7)))
    a1p, a2p = (1.0 + g) * a1, (1.0 + g) * a2
    c1p, c2p = np.hypot(a1p, b1), np.hypot(a2p, b2)
    h1p = np.where((a1p == 0) & (b1 == 0), 0.0, np.degrees(np.arctan2(b1, a1p)) % 360.0)
    h2p = np.where((a2p == 0) & (b2 == 0), 0.0, np.degrees(np.arctan2(b2, a2p)) % 360.0)
    chroma_product = c1p * c2p
    dl = l2 - l1
    dc = c2p - c1p
    dh = h2p - h1p
    dh = np.where(dh > 180.0, dh - 360.0, np.where(dh < -180.0, dh + 360.0, dh))
    dh = np.where(chroma_product == 0, 0.0, dh)
    dhh = 2.0 * np.sqrt(chroma_product) * np.sin(np.radians(dh) / 2.0)
    l_bar = (l1 + l2) / 2
    cp_bar = (c1p + c2p) / 2
    h_sum = h1p + h2p
    h_bar = np.where(
        np.abs(h1p - h2p) <= 180.0, h_sum / 2, np.where(h_sum < 360.0, (h_sum + 360.0) / 2, (h_sum - 360.0) / 2)
    )
    h_bar = np.where(chroma_product == 0, h_sum, h_bar)
    t = (
        1.0
        - 0.17 * np.cos(np.radians(h_bar - 30.0))
        + 0.24 * np.cos(np.radians(2.0 * h_bar))
        + 0.32 * np.cos(np.radians(3.0 * h_bar + 6.0))
        - 0.20 * np.cos(np.radians(4.0 * h_bar - 63.0))
    )
    d_theta = 30.0 * np.exp(-(((h_bar - 275.0) / 25.0) ** 2))
    r_c = 2.0 * np.sqrt(cp_bar**7 / (cp_bar**7 + p7))
    s_l = 1.0 + 0.015 * (l_bar - 50.0) ** 2 / np.sqrt(20.0 + (l_bar - 50.0) ** 2)
    s_c = 1.0 + 0.045 * cp_bar
    s_h = 1.0 + 0.015 * cp_bar * t
    r_t = -np.sin(np.radians(2.0 * d_theta)) * r_c
    tl, tc, th = dl / s_l, dc / s_c, dhh / s_h
    out: F64 = np.sqrt(np.maximum(tl**2 + tc**2 + th**2 + r_t * tc * th, 0.0))
    return out


@dataclass
class Distribution:
    """Mean, percentiles and maximum of non-negative values: exact zeros are counted apart, the rest in
    0.001-wide bins up to 20 (a percentile is the upper edge of its bin, so never below the true value)."""

    BIN: ClassVar[float] = 0.001
    counts: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(20_001, dtype=np.int64))
    zeros: int = 0
    n: int = 0
    total: float = 0.0
    max: float = 0.0

    def add(self, values: F64, zeros: int = 0) -> None:
        """Take in ``values`` and ``zeros`` more values that are exactly 0."""
        nonzero = values[values != 0]
        self.zeros += zeros + (values.size - nonzero.size)
        self.n += zeros + values.size
        if nonzero.size:
            bins = np.minimum(len(self.counts) - 1, (nonzero / self.BIN).astype(np.int64))
            self.counts += np.bincount(bins, minlength=len(self.counts))
            self.total += float(nonzero.sum())
            self.max = max(self.max, float(nonzero.max()))

    def percentile(self, p: float) -> float:
        """The ``p``-th percentile (nearest rank; see the class doc); NaN when empty."""
        if self.n == 0:
            return math.nan
        rank = max(1, math.ceil(p / 100.0 * self.n))
        if rank <= self.zeros:
            return 0.0
        index = int(np.searchsorted(np.cumsum(self.counts), rank - self.zeros))
        return min(self.max, (index + 1) * self.BIN)

    @property
    def mean(self) -> float:
        return self.total / self.n if self.n else math.nan

    def to_dict(self) -> dict[str, float]:
        return {"mean": round(self.mean, 4), "p99": round(self.percentile(99), 4), "max": round(self.max, 4)}


def _lstar(codes: U8) -> F64:
    lin = CODE_TO_LINEAR[codes]
    return lstar(lin @ LUMINANCE_WEIGHTS)


def _mean_error(ref_a: U8, ref_b: U8, a: U8, b: U8) -> F64:
    """CIEDE2000 between the linear-light mean of ``ref_a`` and ``ref_b`` and that of ``a`` and ``b`` (N×3
    codes each)."""
    out = np.empty(len(a), dtype=np.float64)
    for s in range(0, len(a), _CHUNK):
        sl = slice(s, s + _CHUNK)
        ref = (CODE_TO_LINEAR[ref_a[sl]] + CODE_TO_LINEAR[ref_b[sl]]) / 2
        seen = (CODE_TO_LINEAR[a[sl]] + CODE_TO_LINEAR[b[sl]]) / 2
        out[sl] = ciede2000(linear_to_lab(ref), linear_to_lab(seen))
    return out


def _fused_error(inputs: U8, plus: U8, minus: U8) -> F64:
    """CIEDE2000 between the input colours and the linear-light mean of the two phases (N×3 each)."""
    return _mean_error(inputs, inputs, plus, minus)


@dataclass
class ProfileFigures:
    """Everything measured for one profile over the pairs seen so far."""

    profile: str
    delta_l: float
    clip_allowance_l8: float | None = None
    saccade_px: int = SACCADE_PX
    tag: Distribution = field(default_factory=Distribution)
    saccade: Distribution = field(default_factory=Distribution)
    """The saccade error over points where either phase lands on a tag pixel."""
    non_tag: Distribution = field(default_factory=Distribution)
    non_tag_pixels: int = 0
    non_tag_identical: int = 0
    tag_pixels: int = 0
    flat_pixels: int = 0
    signal_sum_l8: float = 0.0
    pairs: list[dict[str, Any]] = field(default_factory=list)

    def add_pair(self, index: int, frame_rgb: U8, plus: U8, minus: U8, mask: npt.NDArray[np.int8]) -> None:
        """Measure the output pair (``plus``, ``minus``) of input frame ``index`` (all at projector size)."""
        tag = mask != 0
        rgb, p, m = frame_rgb.reshape(-1, 3), plus.reshape(-1, 3), minus.reshape(-1, 3)
        tag_flat = tag.reshape(-1)
        changed = np.any((p != rgb) | (m != rgb), axis=1)
        pair_tag = Distribution()
        for dist, where in ((self.tag, tag_flat), (self.non_tag, ~tag_flat)):
            sel = where & changed
            errors = _fused_error(rgb[sel], p[sel], m[sel])
            unchanged = int(np.count_nonzero(where)) - errors.size  # both phases equal the input: exactly 0
            dist.add(errors, unchanged)
            if dist is self.tag:
                pair_tag.add(errors, unchanged)
        non_tag = ~tag_flat
        self.non_tag_pixels += int(np.count_nonzero(non_tag))
        self.non_tag_identical += int(np.count_nonzero(non_tag & ~changed))
        sign = mask.reshape(-1)[tag_flat].astype(np.float64)
        diff_l8 = (_lstar(p[tag_flat]) - _lstar(m[tag_flat])) * sign * L8_PER_LSTAR
        self.tag_pixels += diff_l8.size
        self.flat_pixels += int(np.count_nonzero(np.all(p[tag_flat] == m[tag_flat], axis=1)))
        self.signal_sum_l8 += float(diff_l8.sum())
        saccade = self._add_saccade(frame_rgb, plus, minus, mask)
        self.pairs.append(
            {
                "input_frame": index,
                "tag_mean": round(pair_tag.mean, 4),
                "tag_p99": round(pair_tag.percentile(99), 4),
                "saccade_p99": round(saccade.percentile(99), 4),
                "signal_l8": round(float(diff_l8.mean()) if diff_l8.size else math.nan, 4),
            }
        )

    def _add_saccade(self, frame_rgb: U8, plus: U8, minus: U8, mask: npt.NDArray[np.int8]) -> Distribution:
        """Take in the saccade error of one pair (see the module doc); returns this pair's own figures."""
        pair = Distribution()
        d = self.saccade_px
        if not 0 < d < mask.shape[1]:
            return pair
        ref_a, ref_b = frame_rgb[:, :-d].reshape(-1, 3), frame_rgb[:, d:].reshape(-1, 3)
        a, b = plus[:, :-d].reshape(-1, 3), minus[:, d:].reshape(-1, 3)
        where = ((mask[:, :-d] != 0) | (mask[:, d:] != 0)).reshape(-1)
        changed = np.any((a != ref_a) | (b != ref_b), axis=1)
        sel = where & changed
        errors = _mean_error(ref_a[sel], ref_b[sel], a[sel], b[sel])
        unchanged = int(np.count_nonzero(where)) - errors.size
        for dist in (self.saccade, pair):
            dist.add(errors, unchanged)
        return pair

    @property
    def signal_l8(self) -> float:
        """Mean camera-side signal over all tag pixels of all pairs, 8-bit L units."""
        return self.signal_sum_l8 / self.tag_pixels if self.tag_pixels else math.nan

    def to_dict(self) -> dict[str, Any]:
        return {
            "profile": self.profile,
            "delta_l": self.delta_l,
            "clip_allowance_l8": self.clip_allowance_l8,
            "pairs_measured": len(self.pairs),
            "fused_ciede2000_tag": self.tag.to_dict(),
            "fused_ciede2000_non_tag": self.non_tag.to_dict(),
            "saccade_px": self.saccade_px,
            "saccade_ciede2000_tag": self.saccade.to_dict(),
            "non_tag_identical_fraction": round(self.non_tag_identical / self.non_tag_pixels, 6)
            if self.non_tag_pixels
            else None,
            "signal_l8": round(self.signal_l8, 4),
            "flat_tag_fraction": round(self.flat_pixels / self.tag_pixels, 6) if self.tag_pixels else None,
            "pairs": self.pairs,
        }


def measure(
    frames: Iterable[tuple[int, U8]],
    mask: npt.NDArray[np.int8],
    modulators: Mapping[str, Modulator],
    saccade_px: int = SACCADE_PX,
) -> dict[str, ProfileFigures]:
    """Figures for each modulator over ``frames``: (input index, H×W×3 RGB at projector size) pairs."""
    figures = {
        name: ProfileFigures(mod.profile, mod.delta_l, getattr(mod, "clip_allowance_l8", None), saccade_px)
        for name, mod in modulators.items()
    }
    for index, frame in frames:
        for name, mod in modulators.items():
            plus, minus = mod.phases(frame)
            figures[name].add_pair(index, frame, plus, minus, mask)
    return figures


def report(figures: Mapping[str, ProfileFigures], reference: str = "paper") -> dict[str, Any]:
    """The JSON-able report: each profile's figures, and its signal as a fraction of ``reference``'s."""
    ref = figures.get(reference)
    out: dict[str, Any] = {}
    for name, fig in figures.items():
        d = fig.to_dict()
        if ref is not None and ref.signal_l8 > 0:
            d["signal_vs_" + reference] = round(fig.signal_l8 / ref.signal_l8, 4)
        out[name] = d
    return out


def frame_indices(count: int, length: int | None, step_when_unknown: int) -> list[int]:
    """``count`` input frame indices spread over ``length`` frames (every ``step_when_unknown`` if unknown)."""
    if count < 1:
        raise ValueError(f"need at least one pair, got {count}")
    if length is None:
        return [k * step_when_unknown for k in range(count)]
    count = min(count, length)
    return sorted({k * length // count for k in range(count)})


def measure_scene(
    arena: ArenaConfig,
    scene: ContentSource,
    indices: Iterable[int],
    rate_hz: float,
    profiles: Iterable[str] = PROFILES,
    delta_l: float | None = None,
    clip_allowances_l8: Iterable[float] = (),
    saccade_px: int = SACCADE_PX,
) -> dict[str, Any]:
    """The report (:func:`report`) of every profile in ``profiles`` on input frames ``indices`` of ``scene``.

    Frames are resized to the projector size (``cv2.INTER_AREA``) as the sender does; ``delta_l`` replaces
    the arena's ΔL. The ``ipt`` profile is measured with the arena's clip allowance, and also with each of
    ``clip_allowances_l8`` (as ``ipt@A``, A in 8-bit L units). ``saccade_px``: see the module doc.
    """
    mod = arena.modulation
    dl = mod.delta_l if delta_l is None else delta_l
    w, h = arena.projector.width_px, arena.projector.height_px
    mask = grid_tag_map(arena).render_mask()
    modulators: dict[str, Modulator] = {}
    for name in profiles:
        modulators[name] = make_modulator(name, mask, dl, clip_allowance_l8=mod.clip_allowance_l8)
        if name == "ipt":
            for allowance in clip_allowances_l8:
                if allowance != mod.clip_allowance_l8:
                    modulators[f"ipt@{allowance:g}"] = make_modulator(name, mask, dl, clip_allowance_l8=allowance)
    frames = ((i, resize_to(scene.frame(i, rate_hz), w, h)) for i in indices)
    figures = measure(frames, mask, modulators, saccade_px)
    return {
        "projector": f"{w}x{h}",
        "tag_pixels_fraction": round(float(np.count_nonzero(mask)) / mask.size, 4),
        "delta_l": dl,
        "profiles": report(figures, "paper" if "paper" in figures else next(iter(figures))),
    }
