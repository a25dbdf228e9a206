"""The pipeline's gates on its poses: a pose far from where the recent motion puts the camera is held back
(``inconsistent``); before that motion is known, only a certain pose goes out (``unconfirmed``); a jump
faster than a drone flies is held back (``motion_jump``) until it repeats. A mix-in of
:class:`ipt.receiver.core.pipeline.Pipeline`, whose state it reads and keeps."""

from __future__ import annotations

from collections import deque

import numpy as np

from ipt.config.models import PipelineConfig
from ipt.receiver.core.frameresult import FrameResult, _Frame
from ipt.receiver.core.motion import MotionTrack
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.core.reasons import FrameReason
from ipt.receiver.core.scales import gate_growth

#: The motion gate compares with accepted poses this close in time.
GATE_WINDOW_US = 250_000
#: After this many gated poses in a row the track is re-initialised (the earlier pose was the wrong one).
GATE_RESET_AFTER = 4
#: With a rolling shutter's sweep fitted, the consistency gate's bound is at least this many times the
#: pose's own position uncertainty: the sweep's six unknowns make a right pose less certain (its σ about
#: 8 mm, not 1), and a fixed 15 mm turned away a third of the rolling flight's right poses.
ROLLING_GATE_SIGMAS = 3.0


class PoseGates:
    """The gates, as methods of :class:`~ipt.receiver.core.pipeline.Pipeline` (which sets the state below)."""

    cfg: PipelineConfig
    _track: MotionTrack
    """The camera's recent motion, from every solved pose."""
    _accepted: deque[tuple[int, PoseEstimate]]
    """The poses let through lately, with their capture times."""
    _gated_in_a_row: int

    def _doubtful(self, t_us: int, pose: PoseEstimate) -> str | None:
        """Why ``pose`` disagrees with the recent motion (the reason counted), or None if it does not."""
        cfg = self.cfg.pose
        if cfg.max_prediction_error_m is not None:
            bound_m = cfg.max_prediction_error_m * gate_growth(float(pose.position_m[2]))
            if cfg.track.rolling_shutter:
                bound_m = max(bound_m, ROLLING_GATE_SIGMAS * float(np.linalg.norm(pose.position_std_m)))
            predicted = self._track.pose_at(t_us)
            if predicted is None:
                # Nothing to check it against yet (the start, or after a gap): only a pose whose own
                # uncertainty is within the same bound goes out; the rest only feed the track.
                if float(np.linalg.norm(pose.position_std_m)) > bound_m:
                    return FrameReason.UNCONFIRMED
            elif float(np.linalg.norm(pose.position_m - predicted[0])) > bound_m:
                return FrameReason.INCONSISTENT
        if cfg.max_speed_mps is not None and self._accepted:
            last_us, last = min(self._accepted, key=lambda a: abs(a[0] - t_us))
            dt_us = abs(t_us - last_us)
            if 0 < dt_us <= GATE_WINDOW_US:
                allowed_m = 0.05 + cfg.max_speed_mps * dt_us * 1e-6
                if float(np.linalg.norm(pose.position_m - last.position_m)) > allowed_m:
                    return FrameReason.MOTION_JUMP
        return None

    def _gated(self, frame: _Frame, pose: PoseEstimate, tags: int, method: str, partner: int) -> FrameResult:
        t_us = frame.time_us
        doubt = self._doubtful(t_us, pose)
        # Every solved pose goes into the track, gated or not: its fit is robust, and a gate that fed only
        # on what it let through could lock onto a wrong track and reject every good pose after it.
        self._track.add(t_us, pose.position_m, pose.r_arena_cam, float(np.linalg.norm(pose.position_std_m)))
        reset = False
        if doubt in (FrameReason.INCONSISTENT, FrameReason.UNCONFIRMED):
            return FrameResult(frame.index, t_us, None, tags, doubt, method=method, partner=partner)
        if doubt == FrameReason.MOTION_JUMP:
            self._gated_in_a_row += 1
            if self._gated_in_a_row < GATE_RESET_AFTER:
                return FrameResult(frame.index, t_us, None, tags, doubt, method=method, partner=partner)
            reset = True
            self._accepted.clear()
        self._gated_in_a_row = 0
        self._accepted.append((t_us, pose))
        return FrameResult(frame.index, t_us, pose, tags, FrameReason.POSE, reset, method, partner)
