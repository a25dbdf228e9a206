"""The frames no pair can solve because their exposure spans a content change: a pose from the frame
before and the frame after together (:func:`bridge_difference`), offered as a candidate by
:class:`ContentBridge`, which the pipeline holds and tells of each new frame; it tracks through the pipeline's
own stages (:class:`BridgeTracker`).

Why. The sender shows each video frame for two projector frames, so the video changes at every other
projector flip. A 120 FPS camera whose exposure spans such a flip sees part of the old picture and part of
the new; paired with the frame a projector period before (old picture) or after (new), its difference is
full of content, and on textured video that pans (grass, leaves) nothing of the tags survives. On the
suite's moving-content flight these were 70 of the 75 frames lost in its first 600, every one of them the
same frame of the camera's four per video frame. The frame before and the frame after, each carried onto
it, mixed in the share that explains its content, leave its tags. Only frames that every pair failed
are bridged, so a frame that had a pose keeps it.

Which neighbours keep the tags. Say a share α of the frame's exposure fell before the flip (old content O,
phase −S) and 1 − α after it (new content N, phase +S): its tags are (1 − 2α)S. Its neighbours one frame
away lie wholly inside those two projector frames (O − S and N + S): any mix of them that explains the
content, α and 1 − α, cancels the tags exactly. Two frames away they straddle the flips before and after
it as it does, with the same α (O + (2α − 1)S, N + (2α − 1)S). With the earlier one at two frames, the
later one at one frame leaves 2α²·S and the later one at two frames |2 − 4α|·S. The frame one before and
the frame three after lie inside the old and the new projector frame of the same phase (O − S, N − S):
they leave (2 − 2α)·S, at least S whenever the frame is mostly new content (α = 0.325 on the suite's
flights, 1.3 ms of a 4 ms exposure: 0.21, 0.70 and 1.35; a pair of opposite phases has 2). So a frame is
bridged with its earliest partner and its next later partner, then the one after it, as they come, and
last with the frame before it and the frame three on, for which it waits one frame longer (at the default
lookahead of two frames; its result comes out 25 ms after it instead of 17).

Light, not lightness. The camera adds the light of the two pictures; a mix of their lightness (CIELAB L,
what the pipeline works in) leaves a residue wherever the picture changed, larger than ΔL at strong
edges. The mix is fitted on linear light (a 256-entry table) and the difference taken in lightness.

Warps. They come from the poses of the three frames, corrected by the fit: the pairs' own alignment, made
from the images, locks onto the moving content instead. The frame being bridged has none, and the recent
motion's prediction misses a vibrating camera by pixels (5-20 px on the fast flight), so its pose is put
between the nearest frames before and after it that have one, in proportion to time, and its track starts
there.

Measured on the suite's renderings (diagnostic replays, one flight per core; moving-content / fast): the
first bridge 93.9 % on moving-content (90.4 % without); the second later partner 95.3 / 78.3 %; the mix in
linear light 96.7 / 82.9 %; with the frames one before and three on 97.6 / 83.2 %; the frame's pose
between its neighbours' 99.0 / 84.1 % (at cbd8279: shadow-vibration 98.0 → 98.6 %, independent 88.6 →
92.4 %, take-off's 0.7-1.2 m band 94.3 → 99.1 %, `ipt demo` 94.1 → 97.8 %). The frames one before and
three on alone, without the other two bridges, cost a third of the difference stage on fast (4.2 against
12-24 ms a frame) but gave 81.5 %.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

from ipt.receiver.core.demodulator import DIFF_SIGMA_PX, PairDifference, valid_difference, warp_masks
from ipt.receiver.core.history import Candidate, Frame, FrameHistory
from ipt.receiver.core.imagealign import translation
from ipt.receiver.core.motion import MotionTrack
from ipt.receiver.core.pose import Pose, pose_of, rt_of
from ipt.receiver.core.track import TrackResult

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]

#: At most this many Gauss-Newton steps of the joint fit of the two shifts and the mix, per level.
REFINE_STEPS = 4
#: The levels of the fit, coarse to fine: images blurred by this sigma (pixels), sampled every this many
#: pixels (the coarse level widens the basin beyond the grain of textured video).
REFINE_LEVELS = ((3.0, 4), (1.0, 3))
#: The bridge is tried with at most this many of a frame's later partners, as they come (the next frame, then
#: the one after it), until one gives a pose.
MAX_BRIDGES = 2
#: A shift correction larger than this (pixels) means the fit locked onto something else: no bridge. The
#: poses' prediction of a vibrating camera is often a few pixels off (1° is 8 px at 640 px wide).
MAX_REFINE_PX = 12.0
#: A frame no pair solved is also bridged with the frame before it and the frame three after it (the same
#: phase, two projector periods apart; see the module's note), so it waits for that frame one frame longer.
WIDE_AFTER = 3

_L_STAR = np.arange(256, dtype=np.float64) * 100 / 255
#: 8-bit CIELAB L → linear light (relative luminance Y, 0..255): the camera adds light, not lightness.
_TO_LINEAR = np.asarray(255 * np.where(_L_STAR > 8, ((_L_STAR + 16) / 116) ** 3, _L_STAR / 903.3), np.float32)


def _linear(lightness: U8) -> F32:
    """:data:`_TO_LINEAR` of an 8-bit lightness image (OpenCV's table look-up: the same values as numpy's
    indexing, at a tenth of its time)."""
    return np.asarray(cv2.LUT(lightness, _TO_LINEAR), np.float32)


def _lightness_u8(linear: F32) -> F32:
    """8-bit CIELAB L (as a float) of linear light on :data:`_TO_LINEAR`'s scale; the inverse of that table.
    (OpenCV's power for the cube root, a tenth of np.cbrt's time, and in place: full-size temporaries cost
    as much again as the arithmetic.)"""
    y = np.maximum(linear, np.float32(0))
    y *= np.float32(1 / 255)
    out = np.asarray(cv2.pow(y, 1 / 3), np.float32)
    out *= np.float32(2.55 * 116)
    out -= np.float32(2.55 * 16)
    dark = y <= np.float32(216 / 24389)
    np.multiply(y, np.float32(2.55 * 903.3), out=out, where=dark)
    return out


def _shifted(warp: F64, d: F64) -> F64:
    """``warp`` followed by a shift of the image by ``-d`` (so the result at x samples the source at x + d)."""
    return np.asarray(translation(-float(d[0]), -float(d[1])) @ warp, np.float64)


@dataclass
class _Level:
    """One neighbour prepared for a level of the fit: its linear light blurred, and that image's gradients
    (central differences), each computed once per level and then read only at the samples each step needs."""

    blurred: F32
    gx: F32
    gy: F32

    @classmethod
    def of(cls, image: F32, blur_px: float) -> _Level:
        blurred = np.asarray(cv2.GaussianBlur(image, (0, 0), blur_px), np.float32)
        gx = np.asarray(cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=1, scale=0.5), np.float32)
        gy = np.asarray(cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=1, scale=0.5), np.float32)
        return cls(blurred, gx, gy)


def _sample_maps(warp: F64, grid: tuple[F32, F32]) -> tuple[F32, F32, F64]:
    """Where each sample of the target's ``grid`` (x and y, pixels) lies in the image ``warp`` carries onto
    the target, and the 2x2 Jacobian of that mapping at the grid's centre (target → source)."""
    inv = np.linalg.inv(warp)
    x, y = grid
    den = inv[2, 0] * x + inv[2, 1] * y + inv[2, 2]
    map_x = np.asarray((inv[0, 0] * x + inv[0, 1] * y + inv[0, 2]) / den, np.float32)
    map_y = np.asarray((inv[1, 0] * x + inv[1, 1] * y + inv[1, 2]) / den, np.float32)
    cx, cy = float(x.mean()), float(y.mean())
    d = float(inv[2, 0] * cx + inv[2, 1] * cy + inv[2, 2])
    u = (inv[0, 0] * cx + inv[0, 1] * cy + inv[0, 2]) / d
    v = (inv[1, 0] * cx + inv[1, 1] * cy + inv[1, 2]) / d
    jac = np.array(
        [
            [(inv[0, 0] - u * inv[2, 0]) / d, (inv[0, 1] - u * inv[2, 1]) / d],
            [(inv[1, 0] - v * inv[2, 0]) / d, (inv[1, 1] - v * inv[2, 1]) / d],
        ]
    )
    return map_x, map_y, jac


def _refine_step(
    now: F32,
    levels: tuple[_Level, _Level],
    warps: tuple[F64, F64],
    shifts: list[F64],
    signals: tuple[U8, U8, U8],
    g: F64,
    stride: int,
    grid: tuple[F32, F32],
) -> F64 | None:
    """One Gauss-Newton step of the mix (g₁, g₂, offset) and the two shifts, on ``now`` (the target,
    blurred and sampled on ``grid``, every ``stride`` pixels) against the two neighbours carried onto it.

    The neighbours are blurred once per level and read at the samples alone (warping and blurring the whole
    image at every step, as the fit first did, gives the same values within interpolation: the warps between
    neighbouring frames are nearly translations); their gradients are carried into the target's geometry by
    the warp's Jacobian at the image centre. With the fine level every third pixel instead of every second
    and OpenCV's table look-up and power, a bridge takes 46 ms instead of 121 ms (ten of shadow-vibration's
    bridges, best of five passes, one core of the development machine)."""
    cols, grads, both = [], [], signals[1][::stride, ::stride]
    for level, warp, d, signal in zip(levels, warps, shifts, (signals[0], signals[2]), strict=True):
        map_x, map_y, jac = _sample_maps(_shifted(warp, d), grid)
        read = [
            np.asarray(cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT), np.float32)
            for img in (level.blurred, level.gx, level.gy)
        ]
        cols.append(read[0])
        # d/dx_target = J^T d/dx_source
        grads.append((jac[0, 0] * read[1] + jac[1, 0] * read[2], jac[0, 1] * read[1] + jac[1, 1] * read[2]))
        moved_signal = cv2.remap(signal, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        both = np.minimum(both, moved_signal)
    sample = np.flatnonzero(both.ravel())
    if len(sample) < 200:
        return None
    # The Jacobian's columns, read at the samples (take: a fifth of boolean indexing's cost).
    j = np.empty((len(sample), 7), np.float64)
    j[:, 0], j[:, 1], j[:, 2] = cols[0].ravel().take(sample), cols[1].ravel().take(sample), 1.0
    for c, (gx, gy), gain in ((3, grads[0], g[0]), (5, grads[1], g[1])):
        j[:, c] = gx.ravel().take(sample)
        j[:, c + 1] = gy.ravel().take(sample)
        j[:, c : c + 2] *= gain
    b, a = j[:, 0], j[:, 1]
    residual = now.ravel().take(sample) - (g[0] * b + g[1] * a + g[2])
    normal = j.T @ j
    try:
        delta = np.linalg.solve(normal, j.T @ residual)
    except np.linalg.LinAlgError:
        return None
    out = np.asarray(delta, np.float64)
    out[:3] += g
    return out


def bridge_difference(
    before: U8,
    target: U8,
    after: U8,
    warps: tuple[F64, F64],
    signals: tuple[U8, U8, U8],
    coverage: U8 | None = None,
    sigma_px: float = DIFF_SIGMA_PX,
) -> PairDifference | None:
    """The tags of ``target`` when its exposure spans a content change: ``target`` minus the mix of the
    frame ``before`` it and the frame ``after`` it that best explains it, in ``target``'s geometry; None
    when no mix of the two explains it.

    ``warps`` carry each neighbour onto ``target`` (from the poses: an alignment from the images would
    lock onto the content, which moved); each is corrected by a shift, jointly with the mix (gains g₁, g₂
    and an offset, g₁ + g₂ ≈ 1: the share of old and new content), by Gauss-Newton on the content, which
    dominates. The tags, whose phase differs between the three frames, do not cancel. ``signals`` are the
    three frames' signal masks (before, target, after). The mix is fitted in linear light, as the camera
    adds the two pictures, and the difference taken in lightness (8-bit L, as a pair's): a mix of the
    lightness instead leaves a residue wherever the picture changed, more than ΔL at strong edges.
    """
    h, w = target.shape
    sensor = np.full((h, w), 255, np.uint8) if coverage is None else coverage
    now, images = _linear(target), (_linear(before), _linear(after))
    shifts = [np.zeros(2), np.zeros(2)]
    g = np.array([0.5, 0.5, 0.0])
    for blur_px, stride in REFINE_LEVELS:
        smooth_now = np.asarray(cv2.GaussianBlur(now, (0, 0), blur_px), np.float32)[::stride, ::stride]
        levels = (_Level.of(images[0], blur_px), _Level.of(images[1], blur_px))
        ys, xs = np.mgrid[0:h:stride, 0:w:stride]
        grid = (xs.astype(np.float32), ys.astype(np.float32))
        for _ in range(REFINE_STEPS):
            step = _refine_step(smooth_now, levels, warps, shifts, signals, g, stride, grid)
            if step is None:
                return None
            g = step[:3]
            shifts[0] = shifts[0] + step[3:5]
            shifts[1] = shifts[1] + step[5:7]
            if float(np.abs(step[3:]).max()) < 0.02:
                break
    if not (0.5 <= g[0] + g[1] <= 2.0 and min(g[0], g[1]) > -0.25):
        return None  # no share of old and new content explains this frame
    if max(float(np.abs(d).max()) for d in shifts) > MAX_REFINE_PX:
        return None
    flat, seen, lit = [], sensor.copy(), signals[1]
    for image, warp, d, signal in zip(images, warps, shifts, (signals[0], signals[2]), strict=True):
        m = _shifted(warp, d)
        flat.append(np.asarray(cv2.warpPerspective(image, m, (w, h), flags=cv2.INTER_LINEAR), np.float32))
        moved_signal, moved_sensor = warp_masks(signal, sensor, m)
        lit, seen = np.minimum(lit, moved_signal), np.minimum(seen, moved_sensor)
    diff = np.asarray(target.astype(np.float32) - _lightness_u8(g[0] * flat[0] + g[1] * flat[1] + g[2]), np.float32)
    return valid_difference(diff, seen, lit[::4, ::4] > 0, sigma_px)


class BridgeTracker(Protocol):
    """The pipeline's stages the bridge uses."""

    def lap(self, stage: str, t0: float) -> float:
        """Count the processor time since ``t0`` to ``stage``; the time now."""

    def predicted_warp(self, a: Frame, b: Frame, poses: tuple[Pose, Pose] | None = None) -> F64 | None:
        """The floor homography from ``a`` to ``b`` from their ``poses``, if trusted."""

    def track_guessed(
        self, diff: PairDifference, guess: tuple[tuple[F64, F64], bool], lit: U8 | None
    ) -> TrackResult | None:
        """The pose tracked on ``diff`` from ``guess`` (OpenCV's rvec, tvec; and whether it is close)."""

    def candidate(self, tracked: TrackResult, partner: int) -> Candidate:
        """A candidate of the track's pose, paired with frame ``partner``."""

    def add_candidate(self, target: Frame, candidate: Candidate) -> None:
        """``candidate`` joins ``target``'s candidates."""


class ContentBridge:
    """The bridge over the frames of ``history`` that no pair solved, through ``stages``; ``motion``: the
    recent motion (the last resort for a frame's pose), ``coverage``: where the undistorted image has pixels
    of the sensor (None: everywhere), ``lookahead``: the pipeline's (:meth:`wait`)."""

    def __init__(
        self,
        history: FrameHistory,
        motion: MotionTrack,
        stages: BridgeTracker,
        coverage: U8 | None,
        lookahead: int,
        rolling_shutter: bool = False,
    ) -> None:
        self.history, self.motion, self.stages = history, motion, stages
        self.coverage, self.lookahead = coverage, lookahead
        self.rolling_shutter = rolling_shutter
        """The camera reads its rows out over time (``pose.track.rolling_shutter``): no bridge is tried and no
        frame waits for one. The bridge's one mix of old and new content per frame holds where every row saw the
        video change at once; under a rolling shutter each row has its own share, and the projector's phase flips
        inside the frame too. Told of the shutter, the bridge posed 1 frame in 9 calls on the suite's rolling flight
        and 1 in 23 on the held-out rolling-mjpeg-1.3m; without it, rolling-mjpeg-1.3m 98.23 -> 99.27 %, MAE 4.67 /
        7.23 / 1.86 -> 4.50 / 6.77 / 1.88 mm, its worst pose 50.0 -> 39.4 mm, a sixth less processor time; rolling
        98.44 -> 98.54 %, MAE 4.14 / 2.19 / 1.05 -> 4.39 / 2.36 / 1.01 mm (docs/receiver-cores.md, stop 72)."""
        self._bridged: dict[int, int] = {}
        """How many times the bridge has been tried on each frame with a later partner."""
        self.prepare: Callable[[Frame], None] | None = None
        """The dense preparation of the three frames of a bridge that is tried, where frames may lack it (the sparse
        tracker's have only their lightness: the pipeline sets it then); None: every frame has it."""
        self.too_late: Callable[[Frame], bool] = lambda frame: False
        """Whether a frame is too old for a bridge to be worth it (a live camera's: the sparse stage's rule)."""

    def keep_only(self, live: set[int]) -> None:
        """Forget the frames not in ``live`` (indices of the frames still kept)."""
        self._bridged = {k: n for k, n in self._bridged.items() if k in live}

    def offer(self, new: Frame) -> None:
        """Try the bridge on each frame that ``new`` has just been paired with, that no pair gave a pose and
        that was paired with an earlier frame too: its earliest partner, it and ``new``; once with each of its
        first :data:`MAX_BRIDGES` later partners; and on the frame :data:`WIDE_AFTER` before ``new``, with the
        frame before it and ``new`` when those two show the same phase (see the module's note on which
        neighbours keep the tags). None under a rolling shutter (:attr:`rolling_shutter`)."""
        if self.rolling_shutter:
            return
        for target in self.history:
            if target.final or target.best is not None or self.too_late(target):
                continue
            if new.index - target.index == WIDE_AFTER:
                before = next((f for f in self.history if f.index == target.index - 1), None)
                if before is not None and self.history.same_phase(before, new):
                    self.bridge(before, target, new)
                continue
            befores = [f for f in self.history if f.index < target.index and f.index in target.tried]
            if self._bridged.get(target.index, 0) >= MAX_BRIDGES or new.index not in target.tried or not befores:
                continue
            self._bridged[target.index] = self._bridged.get(target.index, 0) + 1
            self.bridge(min(befores, key=lambda f: f.index), target, new)

    def wait(self, frame: Frame) -> int:
        """How many frames longer than the pipeline's lookahead ``frame`` waits: one for a frame no pair gave a
        pose, which may still be bridged with the frame :data:`WIDE_AFTER` after it, when the lookahead is the
        default two frames (a shorter one was chosen for its latency; a longer one waits long enough); none for a
        frame :attr:`too_late` for a bridge, and none under a rolling shutter."""
        wants = frame.best is None and bool(frame.tried) and not self.too_late(frame) and not self.rolling_shutter
        return int(self.lookahead == WIDE_AFTER - 1 and wants)

    def frame_pose(self, frame: Frame) -> Pose | None:
        """``frame``'s pose for the bridge's warps: found (or its best candidate yet); else between the nearest
        frames within :data:`WIDE_AFTER` before and after it that have one, in proportion to time (on a vibrating
        camera far closer than the recent motion's prediction, which is the last resort)."""
        own = _found(frame)
        if own is not None:
            return own
        known = [(f, p) for f in self.history if abs(f.index - frame.index) <= WIDE_AFTER and (p := _found(f))]
        before = [(f, p) for f, p in known if f.index < frame.index]
        after = [(f, p) for f, p in known if f.index > frame.index]
        if not before or not after:
            return self.motion.pose_at(frame.time_us)
        (f0, (p0, r0)), (f1, (p1, r1)) = before[-1], after[0]
        s = (frame.time_us - f0.time_us) / (f1.time_us - f0.time_us)
        turn, _ = cv2.Rodrigues(r0.T @ r1)
        partial, _ = cv2.Rodrigues(s * turn)
        return p0 + s * (p1 - p0), np.asarray(r0 @ partial, np.float64)

    def bridge(self, before: Frame, target: Frame, after: Frame) -> None:
        """A candidate pose of ``target`` from the bridge with ``before`` and ``after``, unless neither of those
        has a pose: the warps would all come from the recent motion, and on the suite's fast flight such
        bridges gave 1 pose in 128 tries (a third of the bridge's time there, in its dark scenes)."""
        if _found(before) is None and _found(after) is None:
            return
        t0 = time.thread_time()
        poses = (self.frame_pose(before), self.frame_pose(target), self.frame_pose(after))
        if poses[0] is None or poses[1] is None or poses[2] is None:
            return
        to_target = (
            self.stages.predicted_warp(before, target, (poses[0], poses[1])),
            self.stages.predicted_warp(after, target, (poses[2], poses[1])),
        )
        if to_target[0] is None or to_target[1] is None:
            return
        if self.prepare is not None:
            for f in (before, target, after):
                self.prepare(f)
            t0 = time.thread_time()  # (the preparation counts as its own stage)
        assert before.signal is not None
        assert target.signal is not None
        assert after.signal is not None
        diff = bridge_difference(
            before.lum,
            target.lum,
            after.lum,
            (to_target[0], to_target[1]),
            (before.signal, target.signal, after.signal),
            self.coverage,
        )
        t0 = self.stages.lap("difference", t0)
        if diff is None:
            return
        tracked = self.stages.track_guessed(diff, (rt_of(*poses[1]), True), target.signal)
        self.stages.lap("track", t0)
        if tracked is not None:
            self.stages.add_candidate(target, replace(self.stages.candidate(tracked, before.index), method="bridge"))


def _found(frame: Frame) -> Pose | None:
    """``frame``'s pose; for a frame whose best fit the gates held back, that fit's (still a close guess)."""
    rt = frame.rt if frame.rt is not None else frame.best.rt if frame.best is not None else None
    return None if rt is None else pose_of(*rt)
