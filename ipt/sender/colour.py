"""Exact colour maths in float64: sRGB codes, linear light, luminance, CIE XYZ and CIELAB (D65).

Pure functions on numpy arrays. The formulas are those of IEC 61966-2-1 (sRGB) and CIE 15 (CIELAB):

- an 8-bit code ``k`` is the non-linear value ``V = k / 255``; linear light is ``V / 12.92`` for
  ``V <= 0.04045`` and ``((V + 0.055) / 1.055) ** 2.4`` above;
- linear RGB to XYZ is the sRGB matrix :data:`RGB_TO_XYZ`; its middle row gives the luminance ``Y``;
- the reference white is the matrix applied to RGB = (1, 1, 1), so that code (255, 255, 255) is exactly
  L* = 100, a* = b* = 0;
- ``L* = 116 f(Y) - 16`` with ``f(t) = t^(1/3)`` above ``(6/29)^3`` and ``t / (3 (6/29)^2) + 4/29`` below.

"8-bit L units" (the unit of ΔL, as in OpenCV's 8-bit Lab) are ``L* · 255 / 100``.
"""

from __future__ import annotations

from typing import Final

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

RGB_TO_XYZ: Final = np.array(
    [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ]
)
"""Linear sRGB (D65) to CIE XYZ."""

WHITE_XYZ: Final = RGB_TO_XYZ.sum(axis=1)
"""The reference white (D65 as the sRGB matrix has it): XYZ of linear RGB (1, 1, 1)."""

LUMINANCE_WEIGHTS: Final = RGB_TO_XYZ[1] / WHITE_XYZ[1]
"""Relative luminance Y (white = 1) of linear R, G, B: the middle row of :data:`RGB_TO_XYZ`, normalised."""

L8_PER_LSTAR: Final = 255.0 / 100.0
"""8-bit L units per unit of L*."""

_EPS: Final = (6.0 / 29.0) ** 3
_KAPPA: Final = 3.0 * (6.0 / 29.0) ** 2


def srgb_to_linear(v: npt.ArrayLike) -> F64:
    """Linear light (0..1) of non-linear sRGB values ``v`` (0..1)."""
    x = np.asarray(v, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: npt.ArrayLike) -> F64:
    """Non-linear sRGB values (0..1) of linear light ``x`` (0..1)."""
    y = np.asarray(x, dtype=np.float64)
    return np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.maximum(y, 0.0031308) ** (1 / 2.4) - 0.055)


CODE_TO_LINEAR: Final = srgb_to_linear(np.arange(256) / 255.0)
"""Linear light of each 8-bit sRGB code."""
CODE_TO_LINEAR.flags.writeable = False


def code_to_linear(rgb: npt.NDArray[np.uint8]) -> F64:
    """Linear light of 8-bit sRGB codes (any shape)."""
    out: F64 = CODE_TO_LINEAR[rgb]
    return out


def nearest_code(x: npt.ArrayLike) -> npt.NDArray[np.intp]:
    """The 8-bit code whose linear light is nearest to ``x`` (ties to the lower code)."""
    mids = (CODE_TO_LINEAR[:-1] + CODE_TO_LINEAR[1:]) / 2
    out: npt.NDArray[np.intp] = np.searchsorted(mids, np.asarray(x, dtype=np.float64), side="left")
    return out


def lstar(y: npt.ArrayLike) -> F64:
    """CIE L* (0..100) of relative luminance ``y`` (white = 1)."""
    t = np.asarray(y, dtype=np.float64)
    f = np.where(t > _EPS, np.cbrt(np.maximum(t, _EPS)), t / _KAPPA + 4.0 / 29.0)
    return 116.0 * f - 16.0


def lstar_to_luminance(lstar: npt.ArrayLike) -> F64:
    """Relative luminance of CIE L* (the inverse of :func:`lstar`)."""
    f = (np.asarray(lstar, dtype=np.float64) + 16.0) / 116.0
    return np.where(f > 6.0 / 29.0, f**3, _KAPPA * (f - 4.0 / 29.0))


def linear_to_lab(rgb_linear: npt.ArrayLike) -> F64:
    """CIELAB (L*, a*, b*) of linear sRGB, on the last axis."""
    rgb = np.asarray(rgb_linear, dtype=np.float64)
    xyz = (rgb @ RGB_TO_XYZ.T) / WHITE_XYZ
    f = np.where(xyz > _EPS, np.cbrt(np.maximum(xyz, _EPS)), xyz / _KAPPA + 4.0 / 29.0)
    lab: F64 = np.empty(f.shape, dtype=np.float64)
    lab[..., 0] = 116.0 * f[..., 1] - 16.0
    lab[..., 1] = 500.0 * (f[..., 0] - f[..., 1])
    lab[..., 2] = 200.0 * (f[..., 1] - f[..., 2])
    return lab


def code_to_lab(rgb: npt.NDArray[np.uint8]) -> F64:
    """CIELAB of 8-bit sRGB codes (last axis R, G, B)."""
    return linear_to_lab(code_to_linear(rgb))


def luminance(rgb_linear: npt.ArrayLike) -> F64:
    """Relative luminance Y of linear sRGB (last axis R, G, B)."""
    out: F64 = np.asarray(rgb_linear, dtype=np.float64) @ LUMINANCE_WEIGHTS
    return out
