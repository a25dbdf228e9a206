"""The documented bounds of a flight file (``--sim-config``) beyond what its model checks.

:class:`ipt.sim.config.SimConfig` accepts any positive focal length and any non-negative noise; a focal
length of 1e-300 px turned the projection into NaN (a traceback, and ``ipt demo`` hung), a read noise of
1e300 overflowed. ``ipt sim`` and ``ipt demo`` check a flight against the bounds here before anything is
rendered or written, and name the file, the key and the bound in one line. (The bounds live here, not in the
model, so that adding them does not change the simulator's sources, whose digest keys the suite's renders.)
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

from ipt.cliutil import SEED_MAX
from ipt.config.camera_info import MAX_DISTORTION, MAX_FOCAL_WIDTHS, MIN_FOCAL_WIDTHS
from ipt.errors import IptError
from ipt.sim.config import SimConfig

FOCAL_RANGE_WIDTHS = (MIN_FOCAL_WIDTHS, MAX_FOCAL_WIDTHS)
"""A focal length, in image widths (fx, fy): the bounds a camera.yaml is held to (ipt.config.camera_info)."""
DISTORTION_LIMIT = MAX_DISTORTION
"""Each plumb_bob coefficient k1 k2 p1 p2 k3 is within ± this (camera.yaml's bound too)."""


class FlightLimitsError(IptError):
    """A flight file has a value outside its documented bounds."""


def _bounds(sim: SimConfig) -> Iterator[tuple[str, float, float, float, str]]:
    """(key, value, lowest, highest, unit) for every bounded value of ``sim``."""
    cam, flight = sim.camera, sim.flight
    lo, hi = FOCAL_RANGE_WIDTHS
    widths = f"px ({lo:g} to {hi:g} image widths)"
    yield "camera.fx_px", cam.fx_px, lo * cam.width_px, hi * cam.width_px, widths
    yield "camera.fy_px", cam.fy_px, lo * cam.width_px, hi * cam.width_px, widths
    yield "camera.cx_px", cam.cx_px, 0.0, float(cam.width_px), "px (inside the image)"
    yield "camera.cy_px", cam.cy_px, 0.0, float(cam.height_px), "px (inside the image)"
    for name, k in zip(("k1", "k2", "p1", "p2", "k3"), cam.distortion, strict=True):
        yield f"camera.distortion ({name})", k, -DISTORTION_LIMIT, DISTORTION_LIMIT, ""
    yield "camera.gain", cam.gain, 1e-3, 10.0, "(1 = saturation)"
    yield "camera.ambient", cam.ambient, 0.0, 10.0, "(units of projector white)"
    yield "camera.blur_sigma_px", cam.blur_sigma_px, 0.0, 20.0, "px"
    yield "camera.read_noise", cam.read_noise, 0.0, 1.0, "(fraction of full scale)"
    yield "camera.full_well_e", cam.full_well_e, 10.0, 1e12, "electrons (1e12: no shot noise to speak of)"
    for i, v in enumerate(flight.size_m):
        yield f"flight.size_m[{i}]", v, 0.0, 100.0, "m"
    for i, v in enumerate(flight.centre_m):
        yield f"flight.centre_m[{i}]", v, -100.0, 100.0, "m"
    yield "flight.altitude_wobble_m", flight.altitude_wobble_m, 0.0, 1.0, "m"
    yield "flight.heading_deg", flight.heading_deg, -360.0, 360.0, "degrees"
    if flight.pilot is not None:
        yield "flight.pilot.drift_m", flight.pilot.drift_m, 0.0, 10.0, "m"
    if sim.shadow is not None:
        for i, v in enumerate(sim.shadow.projector_position_m[:2]):
            yield f"shadow.projector_position_m[{i}]", v, -100.0, 100.0, "m"
    for i, v in enumerate(sim.content.pan_px_per_frame):
        yield f"content.pan_px_per_frame[{i}]", v, -1000.0, 1000.0, "px"
    yield "projector_offset_ms", sim.projector_offset_ms, -1000.0, 1000.0, "ms"
    yield "seed", float(sim.seed), 0.0, float(SEED_MAX), ""


def flight_problem(sim: SimConfig) -> str | None:
    """The first value of ``sim`` outside its bounds, said in words (``key: value is outside lo to hi unit``)."""
    for key, value, lo, hi, unit in _bounds(sim):
        if not (math.isfinite(value) and lo <= value <= hi):
            return f"{key}: {value:g} is outside {lo:g} to {hi:g} {unit}".rstrip()
    return None


def check_flight(sim: SimConfig, source: str | Path | None) -> SimConfig:
    """``sim`` if it is within bounds; else :class:`FlightLimitsError` naming ``source`` (the flight file) and
    the key."""
    problem = flight_problem(sim)
    if problem is not None:
        where = "the default flight" if source is None else str(source)
        raise FlightLimitsError(f"{where}: {problem}")
    return sim


__all__ = ["FlightLimitsError", "check_flight", "flight_problem"]
