"""The pipeline's gates on its poses: a pose far from where the recent motion puts the camera is held back
(``inconsistent``); before that motion is known, only a certain pose goes out (``unconfirmed``); a jump
faster than a drone flies is held back (``motion_jump``) until it repeats (:class:`PoseGates`, which the
pipeline asks about each frame's pose, in frame order)."""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from itertools import combinations

import numpy as np

from ipt.config.models import PoseConfig
from ipt.receiver.core.frameresult import FrameResult
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
#: A pose held back as inconsistent with a confirmed motion joins the gates' motion with a standard deviation of at
#: least its distance from the prediction over this.
HELD_SIGMAS = 3.0
#: The speed gate allows this much (m) beyond ``max_speed_mps`` times the time since the nearest pose out ...
JUMP_SLACK_M = 0.05
#: ... but this much while fewer than :data:`CONFIRMED_POSES` went out within :data:`GATE_WINDOW_US` (the start, after a
#: gap of dropped frames): a pose is held back until another agrees. Behind live a dense track after a gap went out
#: 53-73 mm from a right pose one camera frame before it (stop 47).
UNCONFIRMED_SLACK_M = 0.025
#: The motion counts as confirmed once this many poses went out within :data:`GATE_WINDOW_US` before the pose judged.
CONFIRMED_POSES = 8
#: ... but poses held back in a row that agree with each other (their offsets from the prediction within the
#: consistency gate's bound, this close in time) weigh in full: a right track the motion lost.
AGREE_US = 50_000
#: Before the motion is confirmed, a pose is weighed against those of the frames this close after it (two frames).
OUTVOTE_US = 20_000


class PoseGates:
    """The gates, and the motion they judge by: every pose they were asked about."""

    def __init__(self, cfg: PoseConfig) -> None:
        self.cfg = cfg
        self.motion = MotionTrack()
        """The motion of the poses that went out (or were held back), in frame order: the gates' reference."""
        self._accepted: deque[tuple[int, PoseEstimate]] = deque(maxlen=16)
        """The poses let through lately, with their capture times."""
        self._gated_in_a_row = 0
        self._held: tuple[int, np.ndarray] | None = None
        """The last pose held back as inconsistent since one went out: its capture time, its offset from the
        prediction (m)."""
        self._doubts: tuple[int, int, dict[int, tuple[PoseEstimate, str | None]]] = (-1, -1, {})
        """:meth:`doubt`'s answers at one capture time while the motion is unchanged: (the time, the motion's
        :attr:`~MotionTrack.changes`, answers by pose): a frame's poses are asked about two or three times."""

    def doubt(self, t_us: int, pose: PoseEstimate) -> str | None:
        """Why ``pose`` disagrees with the recent motion (the reason counted), or None if it does not."""
        at_us, changes, answers = self._doubts
        if at_us != t_us or changes != self.motion.changes:
            answers = {}
            self._doubts = (t_us, self.motion.changes, answers)
        elif (known := answers.get(id(pose))) is not None and known[0] is pose:
            return known[1]
        answer = self._doubt(t_us, pose)
        answers[id(pose)] = (pose, answer)
        return answer

    def _doubt(self, t_us: int, pose: PoseEstimate) -> str | None:
        cfg = self.cfg
        bound_m = self._consistency_bound_m(pose)
        if bound_m is not None:
            if cfg.track.rolling_shutter:
                bound_m = max(bound_m, ROLLING_GATE_SIGMAS * float(np.linalg.norm(pose.position_std_m)))
            predicted = self.motion.position_at(t_us)
            if predicted is None:
                # Nothing to check it against yet (the start, or after a gap): only a pose whose own
                # uncertainty is within the same bound goes out; the rest only feed the track.
                if float(np.linalg.norm(pose.position_std_m)) > bound_m:
                    return FrameReason.UNCONFIRMED
            elif float(np.linalg.norm(pose.position_m - predicted)) > bound_m:
                return FrameReason.INCONSISTENT
        if cfg.max_speed_mps is not None and self._accepted:
            last_us, last = min(self._accepted, key=lambda a: abs(a[0] - t_us))
            dt_us = abs(t_us - last_us)
            if 0 < dt_us <= GATE_WINDOW_US:
                slack_m = JUMP_SLACK_M if self._confirmed(t_us) else UNCONFIRMED_SLACK_M
                if _jumped((t_us, pose), (last_us, last), slack_m, cfg.max_speed_mps):
                    return FrameReason.MOTION_JUMP
        return None

    def judge(
        self,
        index: int,
        t_us: int,
        pose: PoseEstimate,
        tags: int,
        method: str,
        partner: int,
        later: Sequence[tuple[int, PoseEstimate]] = (),
    ) -> FrameResult:
        """The result of frame ``index`` (captured at ``t_us``) whose pose is ``pose``: the pose, or why the gates
        hold it back; the pose joins the motion either way. ``later``: the best poses so far of the frames after it
        (capture time, pose), which :meth:`outvoted` weighs before the motion is confirmed."""
        doubt = self.doubt(t_us, pose) or self.outvoted(t_us, pose, later)
        # Every solved pose goes into the track, gated or not: its fit is robust, and a gate that fed only
        # on what it let through could lock onto a wrong track and reject every good pose after it. But one held
        # back as inconsistent with a motion that poses going out confirm counts as uncertain as it is far from
        # the prediction (HELD_SIGMAS): a run of fits gone astray (an arena file wrong by centimetres at a seam)
        # no longer drags the motion until one of them agrees with it and goes out. At a flight's start (the
        # motion not confirmed yet), and for poses held back in a row that agree with each other (AGREE_US: a
        # right track the motion lost, after a few wrong poses went out), every pose weighs in full.
        self.motion.add(t_us, pose.position_m, pose.r_arena_cam, self._weight_std_m(t_us, pose, doubt))
        reset = False
        if doubt in (FrameReason.INCONSISTENT, FrameReason.UNCONFIRMED):
            return FrameResult(index, t_us, None, tags, doubt, method=method, partner=partner)
        if doubt == FrameReason.MOTION_JUMP:
            self._gated_in_a_row += 1
            if self._gated_in_a_row < GATE_RESET_AFTER:
                return FrameResult(index, t_us, None, tags, doubt, method=method, partner=partner)
            reset = True
            self._accepted.clear()
        self._gated_in_a_row = 0
        self._held = None
        self._accepted.append((t_us, pose))
        return FrameResult(index, t_us, pose, tags, FrameReason.POSE, reset, method, partner)

    def outvoted(self, t_us: int, pose: PoseEstimate, later: Sequence[tuple[int, PoseEstimate]]) -> str | None:
        """Before the motion is confirmed, :data:`FrameReason.MOTION_JUMP` if ``pose`` is further than the speed gate's
        unconfirmed allowance from every pose of the frames within :data:`OUTVOTE_US` after it, at least two that
        agree with each other: behind live the first frame of a run can be the one a track set a tag cell off, its
        right neighbours judged only after it (stop 47: 79 mm)."""
        speed_mps = self.cfg.max_speed_mps
        near = [(t, p) for t, p in later if 0 < t - t_us <= OUTVOTE_US]
        if speed_mps is None or len(near) < 2 or self._confirmed(t_us):
            return None
        far = all(_jumped((t_us, pose), n, UNCONFIRMED_SLACK_M, speed_mps) for n in near)
        if far and not any(_jumped(a, b, UNCONFIRMED_SLACK_M, speed_mps) for a, b in combinations(near, 2)):
            return FrameReason.MOTION_JUMP
        return None

    def _confirmed(self, t_us: int) -> bool:
        """Whether :data:`CONFIRMED_POSES` went out within :data:`GATE_WINDOW_US` before ``t_us``."""
        return sum(1 for t, _ in self._accepted if 0 <= t_us - t <= GATE_WINDOW_US) >= CONFIRMED_POSES

    def _consistency_bound_m(self, pose: PoseEstimate) -> float | None:
        """The consistency gate's bound (m) at ``pose``'s height, before a rolling shutter's widening; None: off."""
        if self.cfg.max_prediction_error_m is None:
            return None
        return self.cfg.max_prediction_error_m * gate_growth(float(pose.position_m[2]))

    def _weight_std_m(self, t_us: int, pose: PoseEstimate, doubt: str | None) -> float:
        """The position uncertainty (m) ``pose`` joins the motion with: its own, or at least its distance from the
        prediction over :data:`HELD_SIGMAS` if it is held back as inconsistent with a confirmed motion."""
        std_m = float(np.linalg.norm(pose.position_std_m))
        if doubt != FrameReason.INCONSISTENT:
            return std_m
        predicted = self.motion.position_at(t_us)
        if not self._confirmed(t_us) or predicted is None:
            return std_m
        offset = pose.position_m - predicted
        held, self._held = self._held, (t_us, offset)
        bound_m = self._consistency_bound_m(pose)
        if (
            held is not None
            and 0 < t_us - held[0] <= AGREE_US
            and bound_m is not None
            and float(np.linalg.norm(offset - held[1])) <= bound_m
        ):
            return std_m  # it agrees with the pose held back just before it: a right track the motion lost
        far_m = float(np.linalg.norm(offset)) / HELD_SIGMAS
        return far_m if not np.isfinite(std_m) else max(std_m, far_m)


def _jumped(a: tuple[int, PoseEstimate], b: tuple[int, PoseEstimate], slack_m: float, speed_mps: float) -> bool:
    """Whether poses ``a`` and ``b`` (capture time in µs, pose) lie further apart than ``slack_m`` plus ``speed_mps``
    over the time between them allows (the speed gate's test)."""
    allowed_m = slack_m + speed_mps * abs(a[0] - b[0]) * 1e-6
    return float(np.linalg.norm(a[1].position_m - b[1].position_m)) > allowed_m
