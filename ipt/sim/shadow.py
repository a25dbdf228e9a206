"""The drone's own shadow: how much of the projector's light reaches each floor point past the body.

The body is a disk (radius ``radius_m``) centred on the camera, in the body's own plane, so it tilts
with the drone. A floor point is lit when the line from it to the projector lens misses the disk. The
lens is not a point: a disk of diameter ``aperture_m`` gives the shadow a soft edge whose width, measured
in the body's plane, is the aperture times the fraction of the way from the floor to the lens at which
the line crosses that plane (the penumbra). Pure: points and poses in, fractions out.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ipt.sim.config import ShadowConfig

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


def lit_fraction(floor_x_m: F32, floor_y_m: F32, body_centre_m: F64, body_normal: F64, cfg: ShadowConfig) -> F32:
    """Fraction (0..1) of the projector's light that reaches each floor point (x, y, 0).

    ``body_centre_m`` is the disk's centre in the arena, ``body_normal`` a unit vector normal to it (the
    body's z axis). Points whose line to the lens does not cross the disk's plane between them get 1.
    """
    px, py, pz = (np.float32(v) for v in cfg.projector_position_m)
    cx, cy, cz = (np.float32(v) for v in body_centre_m)
    nx, ny, nz = (np.float32(v) for v in body_normal)
    # The line X + s (P - X) meets the plane n·(Q - C) = 0 at s = n·(C - X) / n·(P - X).
    dx, dy = px - floor_x_m, py - floor_y_m
    num = nx * (cx - floor_x_m) + ny * (cy - floor_y_m) + nz * cz
    den = nx * dx + ny * dy + nz * pz
    with np.errstate(divide="ignore", invalid="ignore"):
        s = num / den
    qx = floor_x_m + s * dx - cx
    qy = floor_y_m + s * dy - cy
    qz = s * pz - cz
    distance = np.sqrt(qx * qx + qy * qy + qz * qz)
    width = np.maximum(np.float32(cfg.aperture_m) * s, np.float32(1e-4))
    # Smoothstep across the penumbra: 0 well inside the disk, 1 well outside.
    x = np.clip((distance - np.float32(cfg.radius_m)) / width + np.float32(0.5), 0, 1)
    edge = x * x * (np.float32(3) - np.float32(2) * x)
    blocked = (np.float32(1) - edge) * np.float32(cfg.opacity)
    crosses = (s > 0) & (s < 1) & np.isfinite(s)
    return np.asarray(np.where(crosses, np.float32(1) - blocked, np.float32(1)), dtype=np.float32)


def shadow_centre_m(body_centre_m: F64, cfg: ShadowConfig) -> F64:
    """Where the centre of the disk's shadow falls on the floor (x, y): along the line from the lens."""
    p = np.asarray(cfg.projector_position_m, np.float64)
    c = np.asarray(body_centre_m, np.float64)
    s = p[2] / (p[2] - c[2])
    return np.asarray(p[:2] + s * (c[:2] - p[:2]), np.float64)
