"""CIE L*, CIELAB and CIEDE2000 of one colour at a time, compiled (numba) for the colour pairs' kernels.

The scalar twins of :func:`ipt.sender.colour.lstar`, :func:`ipt.sender.colour.linear_to_lab` and
:func:`ipt.invisibility.ciede2000`, called per colour by :mod:`ipt.sender.pairs` (which takes the compiled
versions, ``*_c``). Pure: floats in, floats out.
"""

from __future__ import annotations

import math
from typing import Any, Final

from ipt.sender.colour import RGB_TO_XYZ, WHITE_XYZ
from ipt.sender.jit import jit

_XYZ_N: Final = RGB_TO_XYZ / WHITE_XYZ[:, None]
"""Linear sRGB to XYZ relative to the white point (X/Xn, Y/Yn, Z/Zn)."""
_EPS: Final = (6.0 / 29.0) ** 3
_KAPPA: Final = 3.0 * (6.0 / 29.0) ** 2



def _lstar(y: float) -> float:
    """CIE L* of relative luminance ``y`` (as :func:`ipt.sender.colour.lstar`)."""
    if y > 0.008856451679035631:  # (6/29)^3
        return 116.0 * float(y ** (1.0 / 3.0)) - 16.0
    return 116.0 * (y / 0.12841854934601665 + 4.0 / 29.0) - 16.0  # 3 (6/29)^2


def _lab_f(t: float) -> float:
    if t > _EPS:
        return float(t ** (1.0 / 3.0))
    return t / _KAPPA + 4.0 / 29.0


def _lab(c0: float, c1: float, c2: float) -> tuple[float, float, float]:
    """CIELAB of linear sRGB (as :func:`ipt.sender.colour.linear_to_lab`)."""
    fx = _lab_f_c(_XYZ_N[0, 0] * c0 + _XYZ_N[0, 1] * c1 + _XYZ_N[0, 2] * c2)
    fy = _lab_f_c(_XYZ_N[1, 0] * c0 + _XYZ_N[1, 1] * c1 + _XYZ_N[1, 2] * c2)
    fz = _lab_f_c(_XYZ_N[2, 0] * c0 + _XYZ_N[2, 1] * c1 + _XYZ_N[2, 2] * c2)
    return 116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)


def de00(l1: float, a1: float, b1: float, l2: float, a2: float, b2: float) -> float:
    """CIEDE2000 of two CIELAB colours (kL = kC = kH = 1): the scalar form of
    :func:`ipt.invisibility.ciede2000` (Sharma, Wu & Dalal 2005, eqs. 1-17)."""
    p7 = 6103515625.0  # 25^7
    c_bar = (math.hypot(a1, b1) + math.hypot(a2, b2)) / 2.0
    c7 = c_bar**7
    g = 0.5 * (1.0 - math.sqrt(c7 / (c7 + p7)))
    a1p, a2p = (1.0 + g) * a1, (1.0 + g) * a2
    c1p, c2p = math.hypot(a1p, b1), math.hypot(a2p, b2)
    h1p = 0.0 if (a1p == 0.0 and b1 == 0.0) else math.degrees(math.atan2(b1, a1p)) % 360.0
    h2p = 0.0 if (a2p == 0.0 and b2 == 0.0) else math.degrees(math.atan2(b2, a2p)) % 360.0
    chroma_product = c1p * c2p
    dl = l2 - l1
    dc = c2p - c1p
    if chroma_product == 0.0:
        dh = 0.0
    else:
        dh = h2p - h1p
        if dh > 180.0:
            dh -= 360.0
        elif dh < -180.0:
            dh += 360.0
    dhh = 2.0 * math.sqrt(chroma_product) * math.sin(math.radians(dh) / 2.0)
    l_bar = (l1 + l2) / 2.0
    cp_bar = (c1p + c2p) / 2.0
    h_sum = h1p + h2p
    if chroma_product == 0.0:
        h_bar = h_sum
    elif abs(h1p - h2p) <= 180.0:
        h_bar = h_sum / 2.0
    elif h_sum < 360.0:
        h_bar = (h_sum + 360.0) / 2.0
    else:
        h_bar = (h_sum - 360.0) / 2.0
    t = (
        1.0
        - 0.17 * math.cos(math.radians(h_bar - 30.0))
        + 0.24 * math.cos(math.radians(2.0 * h_bar))
        + 0.32 * math.cos(math.radians(3.0 * h_bar + 6.0))
        - 0.20 * math.cos(math.radians(4.0 * h_bar - 63.0))
    )
    d_theta = 30.0 * math.exp(-(((h_bar - 275.0) / 25.0) ** 2))
    cp7 = cp_bar**7
    r_c = 2.0 * math.sqrt(cp7 / (cp7 + p7))
    lm = (l_bar - 50.0) ** 2
    s_l = 1.0 + 0.015 * lm / math.sqrt(20.0 + lm)
    s_c = 1.0 + 0.045 * cp_bar
    s_h = 1.0 + 0.015 * cp_bar * t
    r_t = -math.sin(math.radians(2.0 * d_theta)) * r_c
    tl, tc, th = dl / s_l, dc / s_c, dhh / s_h
    return math.sqrt(max(tl * tl + tc * tc + th * th + r_t * tc * th, 0.0))


# The compiled versions. Each function calls the compiled version of the ones above it, looked up as a
# global when it is compiled (at its first call).
_lstar_c: Any = jit(_lstar)
_lab_f_c: Any = jit(_lab_f)
_lab_c: Any = jit(_lab)
_de00_c: Any = jit(de00)
lstar_c: Final[Any] = _lstar_c
"""CIE L* of relative luminance (compiled)."""
lab_c: Final[Any] = _lab_c
"""CIELAB of linear sRGB (compiled)."""
de00_c: Final[Any] = _de00_c
"""CIEDE2000 of two CIELAB colours (compiled)."""
