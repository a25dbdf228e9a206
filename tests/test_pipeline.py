"""The per-frame pipeline: pairing, polarity, gates, profiles and bad frames, on real simulated frames."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from flightpipeline import flight_frames, flight_pipeline

from ipt.config.models import ConfigError, DemodulationConfig, PipelineConfig
from ipt.receiver.core.bridge import ContentBridge
from ipt.receiver.core.detection import DetectorError
from ipt.receiver.core.history import Frame, FrameHistory
from ipt.receiver.core.motion import MotionTrack
from ipt.receiver.core.pipeline import FrameResult, Pipeline
from ipt.receiver.core.pose import PoseEstimate, rt_of
from ipt.receiver.core.reasons import FrameReason
from ipt.receiver.core.secondlook import SecondLook
from ipt.tum import read_tum

FPS = 120.0
DENSE = PipelineConfig(tracker="dense")
"""For the tests of the dense way's own mechanics (its pairs, the second look, the bridge): with the sparse tracker
(the default) most frames never take it."""


def _t_us(k: int) -> int:
    return round(k / FPS * 1e6)


@pytest.fixture(scope="module")
def frames(short_flight: Path) -> list[np.ndarray]:
    return flight_frames(short_flight)


def _run(p: Pipeline, frames: list[np.ndarray]) -> list[FrameResult]:
    """Every frame's result, in frame order (the last few come out when the recording ends)."""
    out: list[FrameResult] = []
    for k, f in enumerate(frames):
        out += p.process(k, f, _t_us(k))
    return out + p.flush()


def test_opposite_phase_pairing_prefers_one_projector_period(short_flight: Path) -> None:
    p = flight_pipeline(short_flight, PipelineConfig())
    # (capture times are whole microseconds, hence the tolerance)
    assert p.history.phase_error(_t_us(2)) == pytest.approx(0.0, abs=1e-4)  # lag 2 at 120 FPS: one 60 Hz period
    assert p.history.phase_error(_t_us(1)) == pytest.approx(0.5, abs=1e-4)
    assert p.history.phase_error(_t_us(4)) == pytest.approx(1.0, abs=1e-4)  # two periods: the same phase
    assert p.history.phase_error(round(3 / 180 * 1e6)) == pytest.approx(0.0, abs=1e-4)  # lag 3 at 180 FPS


START_UP_FRAMES = 6
"""Frames before the ipt profile's motion fit exists (5 poses over 30 ms): its start-up gate holds doubtful
poses back there."""


def test_ipt_profile_beats_the_paper_profile_on_the_same_frames(short_flight: Path, frames: list) -> None:  # type: ignore[type-arg]
    truth = read_tum(short_flight / "groundtruth.tum")
    yields, errors = {}, {}
    settled = {}
    for name in ("ipt", "paper"):
        results = _run(flight_pipeline(short_flight, PipelineConfig.profile(name)), frames)
        posed = [r for r in results if r.pose is not None]
        yields[name] = len(posed) / len(frames)
        settled[name] = sum(r.index >= START_UP_FRAMES for r in posed)
        errors[name] = max(np.linalg.norm(r.pose.position_m - truth.positions_m[r.index]) for r in posed)
    # On half a second the paper's pipeline does well too (its lag-1 pairs still see a third of the signal
    # where exposures straddle a flip). ipt holds back a pose or two at the start, until its motion fit
    # exists to check them against; from then on it finds nearly as many poses (52 against 54: one frame
    # lost, one held back), and none as far off.
    assert yields["ipt"] >= 0.85
    assert settled["ipt"] >= settled["paper"] - 2
    assert errors["ipt"] < 0.03
    assert errors["ipt"] < errors["paper"]


@pytest.mark.parametrize("tracker", ["dense", "sparse"])
def test_the_track_needs_apriltag_only_to_start_and_to_check(
    short_flight: Path,
    frames: list,  # type: ignore[type-arg]
    tracker: str,
) -> None:
    tracked = flight_pipeline(short_flight, PipelineConfig(tracker=tracker))
    results = []
    for k, f in enumerate(frames):
        results += tracked.process(k, f, _t_us(k))
        if k == 29:
            at_half = tracked.detector_runs
    results += tracked.flush()
    assert sum(r.method in ("track", tracker) for r in results) >= 0.85 * len(frames)
    if tracker == "sparse":  # most frames never take the dense way
        assert sum(r.method == "sparse" for r in results) >= 0.7 * len(frames)
    # AprilTag acquires in the first frames; once the track runs, it only checks it now and then.
    assert tracked.detector_runs - at_half <= 30 // PipelineConfig().pose.track.verify_every + 2
    both = flight_pipeline(short_flight, PipelineConfig.profile("paper"))
    _run(both, frames)
    assert both.detector_runs == 2 * (len(frames) - 1)


def test_results_come_out_once_each_and_in_frame_order(short_flight: Path, frames: list) -> None:  # type: ignore[type-arg]
    p = flight_pipeline(short_flight, PipelineConfig())
    waiting = 0
    out: list[FrameResult] = []
    for k, f in enumerate(frames):
        batch = p.process(k, f, _t_us(k))
        out += batch
        waiting = max(waiting, k + 1 - len(out))
    assert waiting <= PipelineConfig().demodulation.lookahead_frames + 1  # a pose waits at most that long
    out += p.flush()
    assert [r.index for r in out] == list(range(len(frames)))
    assert p.flush() == []


def test_without_lookahead_each_frame_comes_out_at_once(short_flight: Path, frames: list) -> None:  # type: ignore[type-arg]
    cfg = PipelineConfig().model_copy(update={"demodulation": DemodulationConfig(lookahead_frames=0)})
    p = flight_pipeline(short_flight, cfg)
    for k, f in enumerate(frames[:20]):
        assert [r.index for r in p.process(k, f, _t_us(k))] == [k]


def test_grey_frames_give_the_same_poses_as_their_rgb(short_flight: Path, frames: list) -> None:  # type: ignore[type-arg]
    # A mono camera's frames are its luminance: the ipt profile takes them as they come.
    grey = [np.asarray(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), np.uint8) for f in frames[:30]]
    cfg = PipelineConfig()
    from_grey = [r for r in _run(flight_pipeline(short_flight, cfg), grey) if r.pose is not None]
    from_rgb = [r for r in _run(flight_pipeline(short_flight, cfg), frames[:30]) if r.pose is not None]
    assert len(from_grey) >= 0.8 * len(from_rgb) > 0
    truth = read_tum(short_flight / "groundtruth.tum")
    assert max(np.linalg.norm(r.pose.position_m - truth.positions_m[r.index]) for r in from_grey) < 0.02


def test_bad_frames_are_counted_not_raised(short_flight: Path, frames: list) -> None:  # type: ignore[type-arg]
    p = flight_pipeline(short_flight, PipelineConfig())
    h, w = frames[0].shape[:2]
    inputs = [
        frames[0],
        frames[1],
        np.zeros((h // 2, w, 3), np.uint8),  # wrong size
        frames[2].astype(np.float32),  # wrong type
        np.zeros((h, w, 3), np.uint8),  # black
        np.full((h, w, 3), 255, np.uint8),  # saturated
        np.zeros((h, w, 4), np.uint8),  # four channels
        frames[5],
    ]
    results = _run(p, inputs)  # type: ignore[arg-type]
    assert [r.index for r in results] == list(range(len(inputs)))
    assert [r.reason for r in results[2:7]] == ["wrong_size", "bad_frame", "dark", "saturated", "bad_frame"]
    assert all(r.pose is None for r in results[2:7])
    assert results[7].partner is None  # pairing starts afresh after a frame that is not this camera's
    assert p.reasons["bad_frame"] == 2
    assert p.reasons["wrong_size"] == p.reasons["dark"] == p.reasons["saturated"] == 1


def test_a_jump_in_time_restarts_pairing(short_flight: Path, frames: list) -> None:  # type: ignore[type-arg]
    p = flight_pipeline(short_flight, PipelineConfig())
    out: list[FrameResult] = []
    for k in range(4):
        out += p.process(k, frames[k], _t_us(k))
    out += p.process(4, frames[4], _t_us(4) + 500_000)
    out += p.process(5, frames[5], _t_us(3))  # time going backwards
    out += p.flush()
    assert [r.reason for r in out[4:]] == ["time_gap", "time_gap"]


def _gate(p: Pipeline, xs: list[float], stds: list[float] | None = None) -> list[FrameResult]:
    """The gates' verdicts on poses at x = xs[k] (0.8 m up), one per frame 8.3 ms apart, in order."""
    out = []
    for k, x in enumerate(xs):
        cov = np.eye(3) * (stds[k] ** 2 / 3 if stds is not None else 1e-6)
        pose = PoseEstimate(np.array([x, 0.0, 0.8]), np.eye(3), (1, 2), 0.5, position_cov_m2=cov)
        out.append(p.gates.judge(k, _t_us(k), pose, 2, "track", k - 2))
    return out


def test_motion_gate_rejects_a_jump_then_reinitialises(short_flight: Path) -> None:
    # Poses 8 ms apart: three at the origin, then the solver "jumps" 0.5 m (more than 3 m/s allows).
    cfg = PipelineConfig()
    cfg = cfg.model_copy(update={"pose": cfg.pose.model_copy(update={"max_prediction_error_m": None})})
    results = _gate(flight_pipeline(short_flight, cfg), [0.0, 0.001, 0.002, 0.5, 0.5, 0.5, 0.5, 0.5])
    reasons = [r.reason for r in results]
    assert reasons[:3] == ["pose"] * 3
    assert reasons[3:6] == ["motion_jump"] * 3
    assert reasons[6] == "pose"  # the fourth jump in a row re-initialises the track at the new place
    assert results[6].reset
    assert reasons[7] == "pose"
    assert not results[7].reset


def test_consistency_gate_rejects_a_pose_off_the_recent_motion(short_flight: Path) -> None:
    # Moving at 0.6 m/s (5 mm per 8.3 ms frame); frame 8 is 25 mm off the line (within the speed gate's
    # 5 cm + 3 m/s once the motion is confirmed, so only the consistency gate can catch it).
    xs = [0.005 * k for k in range(12)]
    xs[8] += 0.025
    reasons = [r.reason for r in _gate(flight_pipeline(short_flight, PipelineConfig()), xs)]
    assert reasons[8] == "inconsistent"
    assert reasons[:8] == ["pose"] * 8
    assert reasons[9:] == ["pose"] * 3  # the doubtful pose did not drag the prediction along


def test_with_a_rolling_shutter_the_consistency_gate_allows_for_the_pose_s_own_uncertainty(
    short_flight: Path,
) -> None:
    # The same 25 mm step off the line, from poses whose own uncertainty is 10 mm (a rolling shutter's sweep
    # fitted): 3 sigma is 30 mm, so it passes; 45 mm off it would not; a global shutter keeps the 15 mm.
    xs = [0.005 * k for k in range(12)]
    xs[8] += 0.025
    stds = [0.010] * 12
    cfg = PipelineConfig()
    rolling = cfg.with_rolling_shutter()
    assert [r.reason for r in _gate(flight_pipeline(short_flight, rolling), xs, stds)] == ["pose"] * 12
    assert _gate(flight_pipeline(short_flight, cfg), xs, stds)[8].reason == "inconsistent"
    xs[8] += 0.020
    assert _gate(flight_pipeline(short_flight, rolling), xs, stds)[8].reason == "inconsistent"


def test_consistency_gate_follows_a_track_that_really_moved(short_flight: Path) -> None:
    # The first poses were a wrong lock 40 mm off; every later one agrees on the true place. The gate
    # rejects them only until they outnumber the wrong ones in its window, then follows.
    xs = [0.04] * 8 + [0.0] * 30
    reasons = [r.reason for r in _gate(flight_pipeline(short_flight, PipelineConfig()), xs)]
    assert reasons[:8] == ["pose"] * 8
    assert "inconsistent" in reasons[8:]
    assert reasons[-10:] == ["pose"] * 10


@pytest.mark.parametrize(("tracker", "method"), [("dense", "track"), ("sparse", "sparse")])
def test_poses_carry_a_covariance_that_grows_with_fewer_tags(
    short_flight: Path,
    frames: list,  # type: ignore[type-arg]
    tracker: str,
    method: str,
) -> None:
    cfg = PipelineConfig().model_copy(update={"tracker": tracker})
    results = [r for r in _run(flight_pipeline(short_flight, cfg), frames) if r.pose is not None]
    truth = np.loadtxt(short_flight / "groundtruth.tum", comments="#")
    by_tags: dict[int, list[float]] = {}
    z: list[np.ndarray] = []
    for r in results:
        std = r.pose.position_std_m
        assert np.all(np.isfinite(std))
        assert np.all(std > 0)
        assert np.all(np.isfinite(r.pose.attitude_std_rad))
        if r.method == method:  # (each fit's own noise model: compared within one)
            by_tags.setdefault(len(r.pose.tag_ids), []).append(float(np.linalg.norm(std)))
            z.append((r.pose.position_m - truth[r.index, 1:4]) / std)
    counts = sorted(by_tags)
    assert len(counts) >= 2
    if tracker == "dense":
        assert np.median(by_tags[counts[0]]) > np.median(by_tags[counts[-1]])
    # (The sparse fits here all see 38-46 tags through their ~700 edge samples: the fewest-tag group is one pose,
    # and which side of the most-tag group's median it falls was chance. tests/test_sparse.py fits one pair on
    # every tag in view and on three alone: the covariance grows as it should.)
    # ... and it says how far off the poses are: errors in standard deviations, RMS per axis, near 1.
    assert np.all(np.sqrt(np.mean(np.square(z), axis=0)) < 4.0)
    assert np.all(np.sqrt(np.mean(np.square(z), axis=0)) > 0.25)


def test_profiles_are_named() -> None:
    paper = PipelineConfig.profile("paper")
    assert paper.demodulation.pairing == "previous"
    assert paper.demodulation.alignment == "sampled_lines"
    assert paper.pose.refine_lm is False
    assert PipelineConfig.profile("ipt") == PipelineConfig()
    with pytest.raises(ConfigError, match="unknown pipeline profile"):
        PipelineConfig.profile("fast")


def test_an_uncertain_first_pose_waits_for_the_track(short_flight: Path) -> None:
    # Nothing to check the first poses against: a two-tag view with 3 cm of uncertainty is held back
    # (it still feeds the motion fit), a well-determined one goes out.
    reasons = [r.reason for r in _gate(flight_pipeline(short_flight, PipelineConfig()), [0.0, 0.0], [0.03, 0.004])]
    assert reasons == ["unconfirmed", "pose"]


SPOILED = 40
"""The frame whose fits the test below spoils (the motion is well known by then)."""


@pytest.mark.parametrize("spoil", ["wrong", "lost"])
def test_a_frame_the_motion_doubts_is_tracked_again_from_where_the_motion_puts_it(
    short_flight: Path,
    frames: list,  # type: ignore[type-arg]
    spoil: str,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Frame 40's fits are made wrong (5 cm off, as a fit settled in the wrong basin) or lost on every pair;
    # the second look tracks it again from the motion of the frames around it, on its real pairs.
    truth = read_tum(short_flight / "groundtruth.tum")
    solve = Pipeline._solve

    def spoiled_solve(self: Pipeline, a: Frame, b: Frame, target: Frame) -> None:
        solve(self, a, b, target)
        if target.index == SPOILED:
            shift_m = np.array([0.05, 0.0, 0.0])
            off = [replace(c.pose, position_m=c.pose.position_m + shift_m) for c in target.candidates]
            target.candidates = [replace(c, pose=p) for c, p in zip(target.candidates, off, strict=True)]
            if spoil == "lost":
                target.candidates = []
                target.failure = FrameResult(target.index, target.time_us, None, 0, FrameReason.LOST)

    monkeypatch.setattr(Pipeline, "_solve", spoiled_solve)
    looked = _run(flight_pipeline(short_flight, DENSE), frames)[SPOILED]
    assert looked.pose is not None
    assert np.linalg.norm(looked.pose.position_m - truth.positions_m[SPOILED]) < 0.005
    monkeypatch.setattr(SecondLook, "look", lambda self, f: None)
    unlooked = _run(flight_pipeline(short_flight, DENSE), frames)[SPOILED]
    assert unlooked.pose is None
    assert unlooked.reason == ("inconsistent" if spoil == "wrong" else "lost")


def test_a_detector_failure_is_flagged_on_exactly_one_result(
    short_flight: Path,
    frames: list,  # type: ignore[type-arg]
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The first detection fails (its helper died): however many results come out after it, and whichever
    # frame it was for, one of them carries the failure, which is what the daemon reports (once).
    p = flight_pipeline(short_flight, PipelineConfig())
    detect, calls = p.detector.detect, {"n": 0}

    def failing_once(gray: np.ndarray, decimate: float | None = None) -> tuple:  # type: ignore[type-arg]
        calls["n"] += 1
        if calls["n"] == 1:
            raise DetectorError("helper process failed (test)")
        return detect(gray, decimate)

    monkeypatch.setattr(p.detector, "detect", failing_once)
    results = _run(p, frames[:30])
    assert calls["n"] > 1
    assert sum(r.detector_failed for r in results) == 1
    assert sum(r.pose is not None for r in results) >= 20  # and it went on


def _pairs_lost_for(frame: int, but_with: int | None = None) -> Callable[[Pipeline, Frame, Frame, Frame], None]:
    """``Pipeline._solve`` for which every pair of ``frame`` is lost (its partner tried, no candidate), but the
    one with frame ``but_with``."""
    solve = Pipeline._solve

    def solve_or_lose(self: Pipeline, a: Frame, b: Frame, target: Frame) -> None:
        other = b if target is a else a
        if target.index == frame and other.index != but_with:
            target.tried.add(other.index)
            target.failure = FrameResult(target.index, target.time_us, None, 0, FrameReason.LOST)
            return
        solve(self, a, b, target)

    return solve_or_lose


def test_a_frame_whose_only_good_pair_is_with_a_later_frame_that_has_its_pose_still_gets_that_pair(
    short_flight: Path,
    frames: list,  # type: ignore[type-arg]
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Frame 20's pairs fail except the one with frame 21, which finds its own pose with frame 19 first (a
    # projector period before: the better phase). Frame 21 is still paired with 20, for 20's sake. (No bridge,
    # which would otherwise try frame 20 with the frames around it.)
    only, truth = 20, read_tum(short_flight / "groundtruth.tum")
    monkeypatch.setattr(Pipeline, "_solve", _pairs_lost_for(only, but_with=only + 1))
    monkeypatch.setattr(ContentBridge, "bridge", lambda self, before, target, after: None)
    results = _run(flight_pipeline(short_flight, DENSE), frames)
    assert results[only + 1].pose is not None
    assert results[only + 1].partner == only - 1
    assert results[only].partner == only + 1
    assert results[only].pose is not None
    assert np.linalg.norm(results[only].pose.position_m - truth.positions_m[only]) < 0.005


def test_a_frame_no_pair_solved_waits_for_the_bridge_with_the_frame_three_on(
    short_flight: Path,
    frames: list,  # type: ignore[type-arg]
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Every pair of frame 20 fails (as across a content change on textured video): it comes out one frame later
    # than the others (when frame 23 arrives, not 22), after the bridges with its partners and the last one,
    # with frame 19 and frame 23 (the same phase, two projector periods apart), whose pose it takes.
    failing, truth = 20, read_tum(short_flight / "groundtruth.tum")
    bridge = ContentBridge.bridge
    bridged: list[tuple[int, int, int]] = []

    def last_bridge_only(self: ContentBridge, before: Frame, target: Frame, after: Frame) -> None:
        bridged.append((before.index, target.index, after.index))
        if after.index - target.index == 3:
            bridge(self, before, target, after)

    monkeypatch.setattr(Pipeline, "_solve", _pairs_lost_for(failing))
    monkeypatch.setattr(ContentBridge, "bridge", last_bridge_only)
    p = flight_pipeline(short_flight, DENSE)
    came_out_with: dict[int, int] = {}
    results: dict[int, FrameResult] = {}
    for k, f in enumerate(frames[:40]):
        for r in p.process(k, f, _t_us(k)):
            came_out_with[r.index], results[r.index] = k, r
    assert came_out_with[failing] == failing + 3
    assert came_out_with[failing + 1] == failing + 3  # in frame order, as it would have anyway
    assert came_out_with[failing - 1] == failing + 1
    assert [b for b in bridged if b[1] == failing][-1] == (failing - 1, failing, failing + 3)
    assert results[failing].pose is not None
    assert np.linalg.norm(results[failing].pose.position_m - truth.positions_m[failing]) < 0.005


class _NoStages:
    """Stages for a part of the pipeline that must not need them."""

    def __getattr__(self, name: str) -> None:
        raise AssertionError(f"the part called the pipeline's {name}")


def test_the_bridge_puts_a_frame_without_a_pose_between_its_neighbours() -> None:
    # The bridge alone, on a history of its own: no pipeline, no detector.
    history = FrameHistory(60.0, "opposite_phase")
    bridge = ContentBridge(history, MotionTrack(), _NoStages(), None, 2)  # type: ignore[arg-type]
    lum = np.zeros((4, 4), np.uint8)
    turn = cv2.Rodrigues(np.array([0.0, 0.0, 0.3]))[0]  # 0.3 rad about the optical axis over 3 frames
    poses = {
        9: (np.array([0.0, 0.0, 1.0]), np.diag([1.0, -1.0, -1.0])),
        12: (np.array([0.3, -0.6, 1.3]), np.diag([1.0, -1.0, -1.0]) @ turn),
    }
    for k in range(8, 14):
        f = Frame(k, _t_us(k), lum)
        if k in poses:
            f.rt = rt_of(*poses[k])
        history.append(f)
    middle = history[2]  # frame 10: a third of the way from frame 9 to frame 12 (whole microseconds)
    s = (_t_us(10) - _t_us(9)) / (_t_us(12) - _t_us(9))
    position_m, r_arena_cam = bridge.frame_pose(middle)  # type: ignore[misc]
    np.testing.assert_allclose(position_m, s * np.array([0.3, -0.6, 0.3]) + [0, 0, 1], atol=1e-9)
    third = cv2.Rodrigues(np.array([0.0, 0.0, 0.3 * s]))[0]
    np.testing.assert_allclose(r_arena_cam, np.diag([1.0, -1.0, -1.0]) @ third, atol=1e-9)
    own = bridge.frame_pose(history[1])  # frame 9 has its own pose
    assert own is not None
    np.testing.assert_allclose(own[0], poses[9][0], atol=1e-9)


def test_no_bridge_is_tried_or_waited_for_under_a_rolling_shutter(monkeypatch: pytest.MonkeyPatch) -> None:
    """Under a rolling shutter each row saw its own share of the old and the new video (and the projector's phase
    flips inside the frame): the bridge's one mix per frame does not hold, so a frame that every pair failed is
    neither bridged nor kept waiting for a bridge; with a global shutter it is both."""
    history = FrameHistory(60.0, "opposite_phase")
    lum = np.zeros((4, 4), np.uint8)
    for k in range(8, 11):
        history.append(Frame(k, _t_us(k), lum))
    target, new = history[1], history[2]
    target.tried = {8, 10}  # frame 9: paired with 8 and with 10, no pose from either
    for rolling_shutter, expected in ((False, [(8, 9, 10)]), (True, [])):
        bridge = ContentBridge(history, MotionTrack(), _NoStages(), None, 2, rolling_shutter)  # type: ignore[arg-type]
        calls: list[tuple[int, int, int]] = []
        monkeypatch.setattr(bridge, "bridge", lambda b, t, a, got=calls: got.append((b.index, t.index, a.index)))
        bridge.offer(new)
        assert calls == expected
        assert bridge.wait(target) == (0 if rolling_shutter else 1)


def test_a_pipeline_told_of_a_rolling_shutter_tells_its_bridge(short_flight: Path) -> None:
    for cfg, rolling_shutter in ((PipelineConfig(), False), (PipelineConfig().with_rolling_shutter(), True)):
        p = flight_pipeline(short_flight, cfg)
        p.close()
        assert p.bridge.rolling_shutter is rolling_shutter


def test_the_bridge_is_not_tried_when_neither_neighbour_has_a_pose(
    short_flight: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Its warps would all come from the recent motion (the fast flight's dark scenes: 1 pose in 128 tries).
    import ipt.receiver.core.bridge as bridge_module

    p = flight_pipeline(short_flight, DENSE)
    lum, down = np.zeros((360, 640), np.uint8), np.diag([1.0, -1.0, -1.0])
    for k in range(9, 14):  # frames 9 and 13 have poses, 10-12 none (each could be put between 9 and 13)
        p.history.append(Frame(k, _t_us(k), lum, lum))
    p.history[0].rt = rt_of(np.array([0.0, 0.0, 1.0]), down)
    p.history[4].rt = rt_of(np.array([0.004, 0.0, 1.0]), down)
    before, target, after = p.history[1], p.history[2], p.history[3]
    tried: list[int] = []
    monkeypatch.setattr(bridge_module, "bridge_difference", lambda *a, **k: tried.append(1))
    p.bridge.bridge(before, target, after)
    assert tried == []
    after.rt = rt_of(np.array([0.003, 0.0, 1.0]), down)
    p.bridge.bridge(before, target, after)
    assert tried == [1]


@pytest.mark.parametrize(("tracker", "taken", "next_taken"), [("dense", 13, 18), ("sparse", 5, 10)])
def test_finishing_before_a_later_frame_gives_what_processing_it_gives_only_sooner(
    short_flight: Path,
    frames: list,  # type: ignore[type-arg]
    tracker: str,
    taken: int,
    next_taken: int,
) -> None:
    # A live daemon that fell behind its camera after frame ``taken - 1`` dropped the next five and takes
    # ``next_taken`` next (50 ms later, past the 43 ms in which a frame may pair): the results waiting for later
    # partners are the same whether they come out before that frame is processed or with it. (Dense: 13-17
    # dropped, frames wait for the look-ahead; sparse: 5-9 dropped, frames 3 and 4 were posed the dense way while
    # the chain had no seed yet. Since its fits damp their swinging steps the chain refuses no frame of this flight;
    # until then frame 47, refused, was the sparse case.)
    runs = list(range(taken))

    def said(results: list[FrameResult]) -> list[tuple[object, ...]]:
        return [
            (r.index, r.reason, r.method, r.partner, None if r.pose is None else tuple(r.pose.position_m))
            for r in results
        ]

    cfg = PipelineConfig(tracker=tracker)
    early, late = flight_pipeline(short_flight, cfg), flight_pipeline(short_flight, cfg)
    got_early = [r for k in runs for r in early.process(k, frames[k], _t_us(k))]
    assert said([r for k in runs for r in late.process(k, frames[k], _t_us(k))]) == said(got_early)
    waiting = [k for k in runs if k not in {r.index for r in got_early}]
    assert waiting, "some results wait for later frames"
    # A frame 3 on could still pair with the last two taken (42 and 33 ms before it): they stay; a frame further
    # back that still waits is final.
    mid = taken + 3
    at_mid = early.finish_before(_t_us(mid))
    assert [r.index for r in at_mid] == [k for k in waiting if _t_us(mid) - _t_us(k) > early.pair_span_us]
    if tracker == "dense":
        assert {taken - 2, taken - 1} <= set(waiting) - {r.index for r in at_mid}
    finished = at_mid + early.finish_before(_t_us(next_taken))
    assert [r.index for r in finished] == waiting
    with_next = late.process(next_taken, frames[next_taken], _t_us(next_taken))

    assert said([r for r in with_next if r.index != next_taken]) == said(finished)
    assert any(r.pose is not None for r in finished)  # not only failures: a pose came out sooner


def test_frames_prepared_on_another_thread_give_the_same_poses(short_flight: Path, frames: list) -> None:  # type: ignore[type-arg]
    """What the replay does with a second core: each frame's own work (:meth:`Pipeline.prepare`) on another
    thread while the frame before it is processed. The poses are the same to the last bit, bad frames too."""
    from concurrent.futures import ThreadPoolExecutor

    feed = [*frames[:20], np.zeros_like(frames[0]), *frames[20:40]]  # a black frame midway: "dark"
    direct = _run(flight_pipeline(short_flight, PipelineConfig()), feed)
    p = flight_pipeline(short_flight, PipelineConfig())
    with ThreadPoolExecutor(max_workers=1) as ahead:
        prepared = [ahead.submit(p.prepare, f) for f in feed]
        ahead_results: list[FrameResult] = []
        for k, job in enumerate(prepared):
            ahead_results += p.process(k, job.result(), _t_us(k))
    ahead_results += p.flush()
    assert [(r.index, r.reason) for r in ahead_results] == [(r.index, r.reason) for r in direct]
    assert any(r.reason == "dark" for r in direct)
    assert sum(r.pose is not None for r in direct) >= 30
    for a, b in zip(ahead_results, direct, strict=True):
        assert (a.pose is None) == (b.pose is None)
        if a.pose is not None and b.pose is not None:
            assert np.array_equal(a.pose.position_m, b.pose.position_m)
            assert np.array_equal(a.pose.quat_wxyz, b.pose.quat_wxyz)


def test_a_frame_mostly_in_shadow_says_so(short_flight: Path, frames: list) -> None:  # type: ignore[type-arg]
    # Issue 30: below ~0.4 m the drone's own shadow covers most of the view; a frame without a pose says why,
    # from its image (the share of the view its signal mask lights), and the frames around keep their poses.
    h, w = frames[0].shape[:2]
    shadow = np.zeros((h, w), np.uint8)
    cv2.ellipse(shadow, (w // 2, h // 2), (int(0.62 * w), int(0.62 * h)), 0, 0, 360, 255, -1)
    dark = [f.copy() for f in frames[:40]]
    for k in range(20, 32):
        dark[k][shadow > 0] = 6  # the floor under the drone: only a little room light
    p = flight_pipeline(short_flight, PipelineConfig())
    results = _run(p, dark)
    shadowed = [r.index for r in results if r.reason == FrameReason.SHADOWED]
    assert shadowed, [r.reason for r in results[20:32]]
    assert set(shadowed) <= set(range(20, 32))
    assert all(r.pose is None for r in results if r.reason == FrameReason.SHADOWED)
    assert sum(r.pose is not None for r in results[8:20]) >= 10  # lit frames before it keep their poses
    assert p.reasons["shadowed"] == len(shadowed)
