"""The simulated flight: an intended path, a pilot's wandering about it and the airframe's vibration.

Paths (pure functions of time giving position, velocity and acceleration):
- :class:`RectangleFlight`, the paper's rectangle at about 0.8 m, flown corner to corner: each edge is a
  minimum-jerk move from rest to rest (as a pilot flies a rectangle: accelerate, cruise, brake at the
  corner), so speed peaks at the configured value mid-edge;
- :class:`TakeoffPath`: up from the landing pad, a hover high up, and back down;
- :class:`HoverPath`: one point at one height.

:class:`Flight` puts the rest of a real flight on top: the pilot's corrections (a slow wandering of a few
centimetres, which adds accelerations and so tilt) and the attitude vibration of the airframe (roll and
pitch of 1-2° at 5-7 Hz, a little yaw). Attitude follows the acceleration as a quadrotor's does: the
thrust axis tilts along (a + g·z), yaw is the heading plus a slow wobble; the vibration rotates the body
on top of that. Pure: times in, poses out; the random parts are fixed by a seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from ipt.geometry import R_BODY_CAM_DOWNWARD, rot_x, rot_y, rot_z

F64 = npt.NDArray[np.float64]
GRAVITY_MPS2 = 9.81
# Minimum-jerk s(τ) = 10τ³ − 15τ⁴ + 6τ⁵ peaks in speed at τ = 1/2 with ds/dτ = 15/8.
_MIN_JERK_PEAK_RATE = 15.0 / 8.0
#: Period of the slow height wobble (s) and of the slow yaw wobble (s).
_HEIGHT_WOBBLE_S, _YAW_WOBBLE_S = 3.7, 5.3


@dataclass(frozen=True)
class FlightState:
    """The camera's pose at one instant (the ground truth)."""

    position_m: F64
    """Camera optical centre, arena ENU metres."""
    r_arena_cam: F64
    """Rotation camera (OpenCV optical) → arena."""
    velocity_mps: F64


Kinematics = tuple[F64, F64, F64]
"""Position (m), velocity (m/s) and acceleration (m/s²) in the arena, each of shape (3,)."""


class Path(Protocol):
    """An intended path: where the drone means to be at each time."""

    def kinematics(self, t_s: float) -> Kinematics: ...


def _min_jerk(tau: float, duration_s: float) -> tuple[float, float, float]:
    """s, ds/dt, d²s/dt² of the minimum-jerk move from 0 to 1 at τ = t / duration in [0, 1]."""
    s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
    ds = (30 * tau**2 - 60 * tau**3 + 30 * tau**4) / duration_s
    dds = (60 * tau - 180 * tau**2 + 120 * tau**3) / duration_s**2
    return s, ds, dds


def _height(altitude_m: float, wobble_m: float, t_s: float) -> tuple[float, float, float]:
    w = 2 * np.pi / _HEIGHT_WOBBLE_S
    return (
        altitude_m + wobble_m * np.sin(w * t_s),
        wobble_m * w * np.cos(w * t_s),
        -wobble_m * w**2 * np.sin(w * t_s),
    )


def attitude(acceleration_mps2: F64, yaw_rad: float) -> F64:
    """The body's rotation (FLU body → arena) when its thrust produces ``acceleration_mps2`` at heading
    ``yaw_rad``: the thrust axis along (a + g·z), the nose as close to the heading as that allows."""
    thrust = np.array([acceleration_mps2[0], acceleration_mps2[1], acceleration_mps2[2] + GRAVITY_MPS2])
    z_body = thrust / np.linalg.norm(thrust)
    x_heading = np.array([np.cos(yaw_rad), np.sin(yaw_rad), 0.0])
    y_body = np.cross(z_body, x_heading)
    y_body /= np.linalg.norm(y_body)
    x_body = np.cross(y_body, z_body)
    return np.column_stack([x_body, y_body, z_body])


@dataclass(frozen=True)
class RectangleFlight:
    """A rectangle centred on ``centre_m`` with sides ``size_m`` (x, y), flown counter-clockwise.

    On its own (:meth:`state`) it is the smooth textbook flight; :class:`Flight` adds a pilot and vibration.
    """

    size_m: tuple[float, float] = (1.0, 1.2)
    centre_m: tuple[float, float] = (0.0, 0.0)
    altitude_m: float = 0.8
    altitude_wobble_m: float = 0.03
    peak_speed_mps: float = 1.0
    heading_rad: float = 0.0
    yaw_wobble_rad: float = np.deg2rad(8.0)
    start_fraction: float = 0.1
    """Where along the first edge the flight starts (0..1), so t=0 is already in motion."""

    def _corners(self) -> F64:
        hx, hy = self.size_m[0] / 2, self.size_m[1] / 2
        cx, cy = self.centre_m
        return np.array([[cx - hx, cy - hy], [cx + hx, cy - hy], [cx + hx, cy + hy], [cx - hx, cy + hy]])

    def _edge_durations(self) -> F64:
        c = self._corners()
        lengths = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
        return np.asarray(_MIN_JERK_PEAK_RATE * lengths / self.peak_speed_mps)

    @property
    def loop_s(self) -> float:
        """Duration of one lap."""
        return float(self._edge_durations().sum())

    def kinematics(self, t_s: float) -> Kinematics:
        c = self._corners()
        durations = self._edge_durations()
        starts = np.concatenate([[0.0], np.cumsum(durations)])
        t = (t_s + self.start_fraction * durations[0]) % starts[-1]
        i = min(int(np.searchsorted(starts, t, side="right")) - 1, 3)
        s, ds, dds = _min_jerk((t - starts[i]) / durations[i], durations[i])
        a, b = c[i], c[(i + 1) % 4]
        z, vz, az = _height(self.altitude_m, self.altitude_wobble_m, t_s)
        p_xy, v_xy, a_xy = a + s * (b - a), ds * (b - a), dds * (b - a)
        return np.array([*p_xy, z]), np.array([*v_xy, vz]), np.array([*a_xy, az])

    def state(self, t_s: float) -> FlightState:
        """The camera's pose and velocity at time ``t_s`` (no pilot, no vibration)."""
        return Flight(self, self.heading_rad, self.yaw_wobble_rad).state(t_s)


@dataclass(frozen=True)
class TakeoffPath:
    """Climb from ``low_m`` to ``high_m`` over ``centre_m`` and back down, each a minimum-jerk move; the
    profile (hold low, climb, hold high, descend, hold low) repeats if the flight is longer."""

    centre_m: tuple[float, float] = (0.0, 0.0)
    low_m: float = 0.25
    high_m: float = 2.2
    hold_low_s: float = 0.5
    climb_s: float = 3.0
    hold_high_s: float = 1.0

    @property
    def period_s(self) -> float:
        return 2 * self.hold_low_s + 2 * self.climb_s + self.hold_high_s

    def kinematics(self, t_s: float) -> Kinematics:
        t = t_s % self.period_s
        span = self.high_m - self.low_m
        z, vz, az = self.low_m, 0.0, 0.0
        up_end = self.hold_low_s + self.climb_s
        down_start = up_end + self.hold_high_s
        if self.hold_low_s <= t < up_end:
            s, ds, dds = _min_jerk((t - self.hold_low_s) / self.climb_s, self.climb_s)
            z, vz, az = self.low_m + span * s, span * ds, span * dds
        elif up_end <= t < down_start:
            z = self.high_m
        elif down_start <= t < down_start + self.climb_s:
            s, ds, dds = _min_jerk((t - down_start) / self.climb_s, self.climb_s)
            z, vz, az = self.high_m - span * s, -span * ds, -span * dds
        return np.array([*self.centre_m, z]), np.array([0.0, 0.0, vz]), np.array([0.0, 0.0, az])


@dataclass(frozen=True)
class HoverPath:
    """One point at one height, with the slow height wobble."""

    centre_m: tuple[float, float] = (0.0, 0.0)
    altitude_m: float = 0.8
    altitude_wobble_m: float = 0.03

    def kinematics(self, t_s: float) -> Kinematics:
        z, vz, az = _height(self.altitude_m, self.altitude_wobble_m, t_s)
        return np.array([*self.centre_m, z]), np.array([0.0, 0.0, vz]), np.array([0.0, 0.0, az])


@dataclass(frozen=True)
class Oscillation:
    """A sum of sinusoids: x(t) = Σ aᵢ sin(2π fᵢ t + φᵢ), with its first two derivatives.

    :meth:`random` draws the frequencies in a band and the phases at random and scales the amplitudes so
    that Σ|aᵢ| is the given peak: |x| never exceeds it and comes close to it every few seconds, as the
    components beat.
    """

    amplitudes: tuple[float, ...] = ()
    frequencies_hz: tuple[float, ...] = ()
    phases_rad: tuple[float, ...] = ()

    @classmethod
    def random(cls, rng: np.random.Generator, peak: float, band_hz: tuple[float, float], parts: int = 3) -> Oscillation:
        weights = rng.uniform(0.5, 1.0, parts)
        return cls(
            tuple(float(a) for a in peak * weights / weights.sum()),
            tuple(float(f) for f in rng.uniform(band_hz[0], band_hz[1], parts)),
            tuple(float(p) for p in rng.uniform(0.0, 2 * np.pi, parts)),
        )

    def at(self, t_s: float) -> tuple[float, float, float]:
        """x, dx/dt, d²x/dt² at ``t_s``."""
        x = dx = ddx = 0.0
        for a, f, p in zip(self.amplitudes, self.frequencies_hz, self.phases_rad, strict=True):
            w = 2 * np.pi * f
            s, c = np.sin(w * t_s + p), np.cos(w * t_s + p)
            x, dx, ddx = x + a * s, dx + a * w * c, ddx - a * w * w * s
        return x, dx, ddx


@dataclass(frozen=True)
class Flight:
    """A path flown by a pilot on a vibrating airframe; the camera looks down from the body's origin."""

    path: Path
    heading_rad: float = 0.0
    yaw_wobble_rad: float = np.deg2rad(8.0)
    drift_xy: tuple[Oscillation, Oscillation] = field(default_factory=lambda: (Oscillation(), Oscillation()))
    """The pilot's wandering along arena x and y, metres."""
    vibration_rpy: tuple[Oscillation, Oscillation, Oscillation] = field(
        default_factory=lambda: (Oscillation(), Oscillation(), Oscillation())
    )
    """Roll, pitch and yaw oscillation of the body, radians."""

    def state(self, t_s: float) -> FlightState:
        """The camera's pose and velocity at time ``t_s``."""
        p, v, a = self.path.kinematics(t_s)
        dx, dy = self.drift_xy[0].at(t_s), self.drift_xy[1].at(t_s)
        p = p + np.array([dx[0], dy[0], 0.0])
        v = v + np.array([dx[1], dy[1], 0.0])
        a = a + np.array([dx[2], dy[2], 0.0])
        yaw = self.heading_rad + self.yaw_wobble_rad * np.sin(2 * np.pi * t_s / _YAW_WOBBLE_S)
        r_arena_body = attitude(a, yaw)
        roll, pitch, yaw_v = (osc.at(t_s)[0] for osc in self.vibration_rpy)
        if roll or pitch or yaw_v:
            r_arena_body = r_arena_body @ rot_z(yaw_v) @ rot_y(pitch) @ rot_x(roll)
        return FlightState(position_m=p, r_arena_cam=r_arena_body @ R_BODY_CAM_DOWNWARD, velocity_mps=v)
