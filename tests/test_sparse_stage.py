"""The sparse tracker's stage in the pipeline (ipt/receiver/core/sparsestage.py) in isolation: which dense pairs a
frame that took the dense way gets before it is judged."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ipt.config.models import PoseConfig
from ipt.receiver.core.frameresult import FrameResult
from ipt.receiver.core.gates import PoseGates
from ipt.receiver.core.history import Candidate, Frame, FrameHistory
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.core.reasons import FrameReason
from ipt.receiver.core.sparsestage import SparseStage

PERIOD_US = 8333  # 120 FPS


class _Chain:
    """Stands in for the live chain: only what the stage asks of it here."""

    def __init__(self) -> None:
        self.seeded: list[int] = []

    def seed(self, k: int, rt: object, sign: int) -> None:
        self.seeded.append(k)

    def reset(self, frames: bool = True) -> None:
        pass


def _candidate(method: str, partner: int, quality: float) -> Candidate:
    pose = PoseEstimate(np.array([0.0, 0.0, 1.0]), np.eye(3), (1, 2), 0.5)
    return Candidate(pose, (np.zeros(3), np.array([0.0, 0.0, 1.0])), 2, method, partner, quality)


def _stage(
    quality: float, prepare: Callable[[Frame], None] = lambda frame: None
) -> tuple[SparseStage, list[tuple[int, int, int]], Frame]:
    """Frames 0..4 at 120 FPS against a 60 Hz projector; frame 2 took the dense way and has one candidate, with
    its earlier partner 0, of ``quality``; frames 3 and 4 were posed by the chain. The pairs solved, as (a, b,
    target); ``prepare``: the stage's dense preparation of a frame."""
    history = FrameHistory(60.0, "opposite_phase")
    frames = [Frame(k, k * PERIOD_US, np.zeros((2, 2), np.uint8)) for k in range(5)]
    for f in frames:
        history.append(f)
    f = frames[2]
    f.tried.add(0)
    f.candidates = [_candidate("track", 0, quality)]
    f.best = f.candidates[0]
    for k in (3, 4):
        frames[k].candidates = [_candidate("sparse", k - 2, 0.9)]
        frames[k].best = frames[k].candidates[0]
    solved: list[tuple[int, int, int]] = []

    def solve(a: Frame, b: Frame, target: Frame) -> None:
        target.tried.add((b if target is a else a).index)
        solved.append((a.index, b.index, target.index))

    gates = PoseGates(PoseConfig())
    stage = SparseStage(
        _Chain(),  # type: ignore[arg-type]
        history,
        gates,
        solve,
        prepare,
        lambda frame, c: None,
        lambda stage, t0: t0,
        lambda: None,
    )
    return stage, solved, f


def test_a_frame_whose_dense_fit_is_weak_is_paired_with_its_later_partners_before_it_is_judged() -> None:
    """Its later partners (4: a period on, 3: half a period) posed themselves sparsely and never paired with it;
    its one dense candidate (quality 0.2, a pair whose content changed) is not to be the only one (realcam:
    such frames were 12-20 mm off where the dense tracker's partner on the other side gave 1 mm)."""
    stage, solved, f = _stage(0.2)
    stage.before_finish(f)
    assert (2, 4, 2) in solved
    assert (2, 3, 2) in solved
    assert all(target == 2 for _, _, target in solved)


def test_a_frame_whose_dense_fit_is_good_is_judged_as_it_is() -> None:
    stage, solved, f = _stage(0.6)
    stage.before_finish(f)
    assert solved == []


def test_a_sparse_pose_the_gates_doubt_is_dropped_and_does_not_join_their_motion() -> None:
    """Frame 2's only candidate is the chain's, 10 cm from where the recent motion (the camera still at 1 m) puts
    it, and its dense pairs find nothing: it goes out without a pose, and the gates' motion never sees the chain's
    (kept, it was fed to the motion as a gated dense fit is, and led the dense way's next guesses astray:
    two-projectors uncalibrated lost 28 frames and sent one pose 110 mm off)."""
    stage, solved, f = _stage(0.6)
    for k in range(-6, 0):
        stage.gates.motion.add(k * PERIOD_US, np.array([0.0, 0.0, 1.0]), np.eye(3), 0.001)
    wrong = _candidate("sparse", 0, 0.95)
    wrong.pose.position_m[0] = 0.1
    f.candidates, f.best, f.tried = [wrong], wrong, set()
    assert stage.gates.doubt(f.time_us, wrong.pose) is not None
    stage.before_finish(f)
    assert solved  # (it took the dense way, which found nothing here)
    assert f.candidates == []
    assert f.best is None
    assert f.rt is None


def test_frames_that_went_out_with_a_dense_pose_still_seed_the_chain() -> None:
    """A frame that took the dense way goes out as soon as its dense pose is good (it waits for no later partner),
    so it is often final when the chain next wants a seed (after a restart): its pose still seeds the chain if it
    went out; one the gates held back does not. (two-projectors, uncalibrated: with only the frames still
    waiting as seeds the chain stayed unseeded through a seam, the dense way's fits there went astray, 96.0 %
    and a pose 112 mm off; with these seeds 99.3 %.)"""
    stage, _, f = _stage(0.9)
    out, held = stage.history[0], stage.history[1]
    for g, pose in ((out, True), (held, False)):
        g.final, g.phase = True, 1
        g.candidates = [_candidate("track", g.index + 2, 0.8)]
        g.best = g.candidates[0]
        g.result = FrameResult(
            g.index, g.time_us, g.best.pose if pose else None, 2, FrameReason.POSE if pose else FrameReason.INCONSISTENT
        )
    f.phase = -1
    stage.after_dense(f)
    seeded = stage.chain.seeded  # type: ignore[attr-defined]
    assert out.index in seeded
    assert f.index in seeded
    assert held.index not in seeded


def test_the_bridge_being_possible_prepares_no_frame() -> None:
    """Issue 29: a frame whose dense pairs failed may want the bridge, which prepares the three frames of a bridge it
    tries (tests/test_sparse_fail_cost.py); the stage itself prepares none. (Before: every kept frame was prepared
    densely as soon as one frame might want the bridge.)"""
    prepared: list[int] = []
    stage, _, f = _stage(0.2, prepare=lambda frame: prepared.append(frame.index))
    f.candidates, f.best = [], None  # its dense pairs failed: the bridge may want it
    assert stage.bridge_ready()
    assert prepared == []


def test_live_a_frame_the_chain_waited_for_in_vain_takes_the_dense_way_only_while_young() -> None:
    """Issue 29, target 3 (stop 59): live, a frame the chain gave up on is three frames old at least, and its dense
    pairs took 10-60 ms more while every frame behind it waited. Past ``LIVE_LATE_US`` (20 ms, from its capture to
    the newest frame's capture plus that frame's wait before the pipeline took it) it is given up, ``late``;
    younger, and a recording's frame (no wait: ``now_us`` None), it is paired as before."""
    for waited_us, expect_late in ((None, False), (0, False), (3_000, False), (4_000, True), (90_000, True)):
        stage, solved, f = _stage(0.2)
        newest = stage.history[-1].time_us  # frame 4: frame 2 is two frames (16.7 ms) older
        stage.now_us = None if waited_us is None else newest + waited_us
        f.waiting = True
        stage.before_finish(f)
        assert (solved == []) is expect_late
        assert (f.failure is not None and f.failure.reason == FrameReason.LATE) is expect_late
        assert stage.late == int(expect_late)
