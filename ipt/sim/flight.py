"""The simulated flight: the paper's rectangle at about 0.8 m, flown corner to corner.

Each edge is a minimum-jerk move from rest to rest (as a pilot flies a rectangle: accelerate, cruise,
brake at the corner), so speed peaks at the configured value mid-edge. Attitude follows the
acceleration as a quadrotor's does: the thrust axis tilts along (a + g·z), yaw is the commanded heading
plus a slow wobble. Pure: times in, poses out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ipt.geometry import R_BODY_CAM_DOWNWARD

F64 = npt.NDArray[np.float64]
GRAVITY_MPS2 = 9.81
# Minimum-jerk s(τ) = 10τ³ − 15τ⁴ + 6τ⁵ peaks in speed at τ = 1/2 with ds/dτ = 15/8.
_MIN_JERK_PEAK_RATE = 15.0 / 8.0


@dataclass(frozen=True)
class FlightState:
    """The camera's pose at one instant (the ground truth)."""

    position_m: F64
    """Camera optical centre, arena ENU metres."""
    r_arena_cam: F64
    """Rotation camera (OpenCV optical) → arena."""
    velocity_mps: F64


@dataclass(frozen=True)
class RectangleFlight:
    """A rectangle centred on ``centre_m`` with sides ``size_m`` (x, y), flown counter-clockwise."""

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

    def _horizontal(self, t_s: float) -> tuple[F64, F64, F64]:
        """Position, velocity and acceleration in the floor plane."""
        c = self._corners()
        durations = self._edge_durations()
        starts = np.concatenate([[0.0], np.cumsum(durations)])
        t = (t_s + self.start_fraction * durations[0]) % starts[-1]
        i = min(int(np.searchsorted(starts, t, side="right")) - 1, 3)
        big_t = durations[i]
        tau = (t - starts[i]) / big_t
        s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
        ds = (30 * tau**2 - 60 * tau**3 + 30 * tau**4) / big_t
        dds = (60 * tau - 180 * tau**2 + 120 * tau**3) / big_t**2
        a, b = c[i], c[(i + 1) % 4]
        return a + s * (b - a), ds * (b - a), dds * (b - a)

    def state(self, t_s: float) -> FlightState:
        """The camera's pose and velocity at time ``t_s``."""
        p_xy, v_xy, a_xy = self._horizontal(t_s)
        w_z = 2 * np.pi / 3.7  # altitude wobble period 3.7 s
        z = self.altitude_m + self.altitude_wobble_m * np.sin(w_z * t_s)
        vz = self.altitude_wobble_m * w_z * np.cos(w_z * t_s)
        az = -self.altitude_wobble_m * w_z**2 * np.sin(w_z * t_s)
        yaw = self.heading_rad + self.yaw_wobble_rad * np.sin(2 * np.pi * t_s / 5.3)
        thrust = np.array([a_xy[0], a_xy[1], az + GRAVITY_MPS2])
        z_body = thrust / np.linalg.norm(thrust)
        x_heading = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        y_body = np.cross(z_body, x_heading)
        y_body /= np.linalg.norm(y_body)
        x_body = np.cross(y_body, z_body)
        r_arena_body = np.column_stack([x_body, y_body, z_body])
        return FlightState(
            position_m=np.array([p_xy[0], p_xy[1], z]),
            r_arena_cam=r_arena_body @ R_BODY_CAM_DOWNWARD,
            velocity_mps=np.array([v_xy[0], v_xy[1], vz]),
        )
