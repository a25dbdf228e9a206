"""AprilTag's part in the ipt way (:class:`Acquisition`, held by :class:`~ipt.receiver.core.pipeline.Pipeline`):
acquiring a pose on a pair's difference when there is no track to follow (from two whole tags or more, or the map's
track started from one), checking the track now and then, and searching the whole map for a view without a whole tag
(:mod:`~ipt.receiver.core.mapsearch`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.config.models import PipelineConfig
from ipt.receiver.core.demodulator import PairDifference, binarise_difference
from ipt.receiver.core.detection import Detector, DetectorError, TagDetection
from ipt.receiver.core.frameresult import FrameResult
from ipt.receiver.core.history import Candidate, Frame, FrameHistory
from ipt.receiver.core.mapsearch import MapSearch
from ipt.receiver.core.pose import rt_of, solve_pose
from ipt.receiver.core.reasons import SHADOWED_SHARE, FrameReason
from ipt.receiver.core.scales import ScaleChooser
from ipt.receiver.core.track import TrackResult
from ipt.tagmap import TagMap

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]

#: While no pose and no whole tag is found, the map is searched on one pair every this many frames ...
SEARCH_EVERY = 3
#: ... for this many searches in a row that find nothing; after each further one the wait doubles, up to
#: :data:`SEARCH_EVERY_MAX`, until a search finds the pose or a new stretch without one begins
#: (:meth:`Acquisition._search_turn`). Of the 55 searches on the suite's and the held-out flights at stop 72, the three
#: that found a pose were the first, the third and the first of their stretch; held-out low-fast-big-shadow's stretch
#: 661-744 ran 27 and found nothing (0.86 s of processor time). (Doubling from the first miss on moved
#: takeoff-open-floor's third search from frame 173, where it found the pose, to 176, where it did not, and the pose
#: came 600 frames later: 63.85 -> 56.25 % of the flight. A search's luck is the frame it falls on.)
SEARCH_TRIES = 3
#: The longest wait between two map searches (frames: 0.2 s at 120 FPS).
SEARCH_EVERY_MAX = 24
#: A frame without a track whose view is mostly unlit is tried (its pairs, AprilTag) only every this many frames
#: (:meth:`Acquisition.rests`): 15 tries a second at 120 FPS. (Every :data:`SEARCH_EVERY`-th before stop 45: no try on
#: such a view has ever found a pose, and the frames between cost a third of a tried one; the take-offs' poses are
#: the same to the digit with 3, 8, 12 or 16, held-out low-fast-big-shadow's too.)
REST_EVERY = 8
#: Without a track, a frame whose signal mask lights less than this share of its view rests (:meth:`Acquisition.rests`)
#: and its map is not searched. Of the 1 212 acquisitions (AprilTag, then the map search) on the suite's and the
#: held-out flights (stop 54, `/work/tools/searchstat.py`), the 37 that found a pose had 40-78 % of their view lit;
#: none of the 574 below 35 % did (takeoff's climb through 0.27-0.33 m lit 26-35 %: 19 searches of 30 ms, and AprilTag
#: on every frame). A track goes on down to :data:`~ipt.receiver.core.reasons.SHADOWED_SHARE`.
ACQUIRE_LIT_SHARE = 0.35
#: A placement of the whole-map search is taken only if the track from it fits at least this share of the visible map's
#: edges. The map repeats tag after tag, and a placement a tag or more off can still fit part of it: the searches that
#: gave a pose 32-109 mm off fitted 0.34-0.49 of the edges, every right one 0.66-0.97 (stop 46: the suite's and the
#: held-out flights' replays, and shadow-vibration and fast modelled live at 1.5x and 3.5x this machine's time, where
#: such poses went out).
MIN_SEARCH_FIT = 0.6
#: A pair further than this (projector periods) from an odd number of periods apart is a fallback one (half a period:
#: one camera frame at 120 FPS, of the same phase half of the time). From a live camera the whole-map search skips it
#: (:attr:`Acquisition.live`).
FALLBACK_PHASE_ERROR = 0.25


class TrackStages(Protocol):
    """The pipeline's stages acquisition uses."""

    history: FrameHistory
    scales: ScaleChooser
    tracking: bool

    def track_from(
        self, diff: PairDifference, init: tuple[F64, F64], lit: U8 | None = None, coarse_px: float = 0.0
    ) -> TrackResult | None:
        """The pose from the map's edges on ``diff`` from ``init``."""

    def coarse(self, diff: PairDifference, init: tuple[F64, F64]) -> tuple[F64, F64]:
        """``init`` moved by the image shift that best lays the map on the difference."""

    def candidate(self, tracked: TrackResult, partner: int) -> Candidate:
        """A candidate of the track's pose, paired with frame ``partner``."""

    def lap(self, stage: str, t0: float) -> float:
        """Count processor time since ``t0`` to ``stage``; the time now."""


class Acquisition:
    """AprilTag (``detector``) and the map search for the pipeline's ``stages``."""

    def __init__(
        self,
        stages: TrackStages,
        tag_map: TagMap,
        pinhole: CameraInfo,
        cfg: PipelineConfig,
        detector: Detector,
        mask: npt.NDArray[np.int8] | None = None,
    ) -> None:
        """``mask``: the map's :meth:`~ipt.tagmap.TagMap.render_mask` if the caller made it already (kept for the map
        search until its first use)."""
        self.stages, self.tag_map, self.pinhole, self.cfg, self.detector = stages, tag_map, pinhole, cfg, detector
        self._mask = mask
        self.runs = 0
        """AprilTag runs so far."""
        self.since_verify = 0
        """Tracked frames since AprilTag last checked the track."""
        self.detector_failed = False
        """The detector failed since the last result went out (the next result says so)."""
        self.map_search: MapSearch | None = None
        """The search of the whole map for a view without a whole tag (built at its first use)."""
        self.searched_at = -SEARCH_EVERY
        self.search_misses = 0
        """Map searches in a row that found nothing (:meth:`_search_turn`)."""
        self.search_asked_at = -SEARCH_EVERY_MAX
        """The last frame whose map search's turn was asked for (a gap longer than :data:`SEARCH_EVERY_MAX` since:
        a new stretch without a pose)."""
        self.shadowed_at = -REST_EVERY
        """The last frame AprilTag was tried on while most of its view was unlit (:meth:`rests`)."""
        self.live = False
        """The frames come from a live camera (the daemon sets it): the map search is not run on a fallback pair.
        After frames were dropped the worker takes the newest few; the middle one's only partner is then its
        neighbour, half a projector period away, where AprilTag and a 31-48 ms search found nothing (traced live), and
        the next frame's pair, a whole period apart, comes 8 ms later. A replay keeps it (its first search is on
        frames 0 and 1, and finds the pose there: moving-content, rolling, two-projectors lost frames without it)."""

    def acquire(self, target: Frame, other: Frame, diff: PairDifference) -> Candidate | None:
        """AprilTag on the pair's difference, then (tracking) the map's edges from its pose; None: no pose."""
        first = self.stages.history.predicted_phase(target) or 1
        for scale, sign in ((s, sign) for s in self.stages.scales.to_try(target.index) for sign in (first, -first)):
            self.runs += 1
            dets = self.detector.detect(binarise_difference(diff, sign, scale.ksize), scale.decimate)
            if len(dets) < self.cfg.pose.min_tags:
                found = self.one_tag(dets, target, other, diff) if len(dets) == 1 else None
                if found is not None:
                    return found
                continue
            target.phase, other.phase = sign, -sign
            pose = solve_pose(dets, self.tag_map, self.pinhole, self.cfg.pose)
            if pose is None:
                target.failure = FrameResult(target.index, target.time_us, None, len(dets), FrameReason.POSE_REJECTED)
                return None
            start = rt_of(pose.position_m, pose.r_arena_cam)
            if self.stages.tracking:
                refined = self.stages.track_from(diff, self.stages.coarse(diff, start), target.signal)
                if refined is not None:
                    self.since_verify = 0
                    return self.stages.candidate(refined, other.index)
            return Candidate(pose, start, len(dets), "apriltag", other.index, 0.0)
        return self.search_map(target, other, diff) if self.stages.tracking else None

    def one_tag(
        self, dets: Sequence[TagDetection], target: Frame, other: Frame, diff: PairDifference
    ) -> Candidate | None:
        """One whole tag (too few for a pose: ``pose.min_tags``): each of its two poses (IPPE's: one small tag leaves
        the tilt ambiguous) as the start of the map's track, taken only if the track fits :data:`MIN_SEARCH_FIT` of the
        map's visible edges, as a placement of the map search is (the pose then rests on the edges of every tag in view,
        not on the one tag's corners). Takeoff's climb from its pad: AprilTag found one pad tag from frame 65 on (the
        camera 0.25 m up) and never two, and the pose came at frame 137 (0.39 m); with the tag as the track's start,
        poses from frame 65 on, unbroken from frame 118 (0.31 m): 75.0 -> 79.9 % of the flight, no pose over 23 mm."""
        if not self.stages.tracking:
            return None
        corners_m = self.tag_map.corners_m(dets[0].tag_id)
        if corners_m is None:
            return None
        k, dist = self.pinhole.camera_matrix, self.pinhole.dist_coeffs
        obj, img = np.asarray(corners_m, np.float64), np.asarray(dets[0].corners_px, np.float64)
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, k, dist, flags=cv2.SOLVEPNP_IPPE)
        for rvec, tvec in zip(rvecs[:n], tvecs[:n], strict=True):
            start = (np.asarray(rvec, np.float64).reshape(3), np.asarray(tvec, np.float64).reshape(3))
            found = self._placed(target, other, diff, self.stages.coarse(diff, start))
            if found is not None:
                self.since_verify = 0
                return found
        return None

    def rests(self, target: Frame, later: bool = False) -> bool:
        """Whether AprilTag skips ``target``, a frame without a track to follow (its pair is then not made either):
        most of its view is unlit (below :data:`ACQUIRE_LIT_SHARE`: the drone's shadow on the ground and early in
        the climb) and it is less than :data:`REST_EVERY` frames after the last such frame tried, or it is that frame
        and its partner is a ``later`` one (it is tried with its earlier partners only: its later pairs were two more
        alignments, differences and AprilTag runs on each of the next two frames, takeoff's tried frames came in
        threes of 7-11 ms; stop 63). The scales' cycle moves on over it as over a frame tried, so the frames after
        meet the scales they would have. Of 2 106 AprilTag attempts on views lit below 40 % (takeoff-open-floor
        1 263, takeoff 835, the held-out low-fast-big-shadow 8; stop 43) none found a pose, at a pair's alignment and
        difference and two AprilTag runs each: a shadowed frame of takeoff-open-floor cost 15 ms, a posed one 7 ms."""
        if target.lit_share >= ACQUIRE_LIT_SHARE:
            return False
        self._search_turn(target)  # the map search's turn goes by too, as if searched (:meth:`search_map`)
        if later or (target.index != self.shadowed_at and target.index - self.shadowed_at < REST_EVERY):
            self.stages.scales.to_try(target.index)  # its turn of the scales goes by, as if tried
            return True
        self.shadowed_at = target.index
        return False

    def searcher(self) -> MapSearch:
        """The search of the whole map, built at its first use (from the caller's mask, which it then lets go)."""
        if self.map_search is None:
            self.map_search, self._mask = MapSearch.of(self.tag_map, mask=self._mask), None
        return self.map_search

    def search_map(self, target: Frame, other: Frame, diff: PairDifference) -> Candidate | None:
        """No whole tag: the level poses that lay the whole map on the difference (:mod:`~ipt.receiver.core.
        mapsearch`; one pair every :data:`SEARCH_EVERY` frames), the first the track confirms. Not on a frame
        whose view is mostly unlit (below :data:`ACQUIRE_LIT_SHARE`: the drone's shadow at take-off): the map cannot
        be laid on it, and a search costs 25-60 ms here (on the suite's take-offs 109 of 126 and 63 of 82 searches
        were on views lit below 30 %, none found a pose; the four that did, on any flight, had 37-49 % lit; stop 54:
        the seven that did, 40-78 %). A placement whose track fits less than :data:`MIN_SEARCH_FIT` of the map's
        visible edges is not taken (the next is tried). From a live camera, not on a fallback pair (:attr:`live`)."""
        if self.live and self.stages.history.phase_error(target.time_us - other.time_us) > FALLBACK_PHASE_ERROR:
            return None  # the next pair, a whole number of periods apart, is searched instead
        if not self._search_turn(target) or target.lit_share < ACQUIRE_LIT_SHARE:
            return None  # (a dim frame's turn goes by, as if searched: the frames after meet the turns they would have)
        lit = diff.valid if target.signal is None else np.minimum(diff.valid, target.signal)
        for h in self.searcher().search(diff.diff, lit, self.pinhole.camera_matrix):
            # (a search around the start, not _coarse's: that one lays a level guess's view wrong by a tag)
            found = self._placed(target, other, diff, (h.rvec, h.tvec), h.search_px)
            if found is not None:
                self.search_misses = 0
                return found
        self.search_misses += 1
        return None

    def _placed(
        self, target: Frame, other: Frame, diff: PairDifference, start: tuple[F64, F64], coarse_px: float = 0.0
    ) -> Candidate | None:
        """The map's track from a placement of it (a search's, or one tag's), taken only if it fits
        :data:`MIN_SEARCH_FIT` of the map's visible edges (the pair's phases then set from it)."""
        try:
            tracked = self.stages.track_from(diff, start, target.signal, coarse_px)
        except np.linalg.LinAlgError:  # a wrong placement's samples may all run one way
            return None
        if tracked is None or tracked.inlier_fraction < MIN_SEARCH_FIT:
            return None
        target.phase, other.phase = tracked.sign, -tracked.sign
        return self.stages.candidate(tracked, other.index)

    def _search_turn(self, target: Frame) -> bool:
        """Whether the map search's turn falls on ``target`` (:data:`SEARCH_EVERY` frames after the last, twice as
        many after each miss in a row (:attr:`search_misses`) beyond :data:`SEARCH_TRIES`, at most
        :data:`SEARCH_EVERY_MAX`; a view lit below :data:`~ipt.receiver.core.reasons.SHADOWED_SHARE` does not use it
        up), taking it if so. Asked for after more than :data:`SEARCH_EVERY_MAX` frames without asking (the frames
        between had a track), the misses are forgotten."""
        if target.index - self.search_asked_at > SEARCH_EVERY_MAX:
            self.search_misses = 0
        self.search_asked_at = target.index
        gap = min(SEARCH_EVERY << max(self.search_misses - SEARCH_TRIES + 1, 0), SEARCH_EVERY_MAX)
        if target.index - self.searched_at < gap or target.lit_share < SHADOWED_SHARE:
            return False
        self.searched_at = target.index
        return True

    def verified(self, tracked: TrackResult, diff: PairDifference, t0: float) -> bool:
        """AprilTag's view of the frame agrees with the track (or sees too little to say)."""
        self.since_verify = 0
        r_cam, _ = cv2.Rodrigues(tracked.rvec)
        position = -r_cam.T @ tracked.tvec
        scale = self.stages.scales.at(float(position[2]))
        self.runs += 1
        try:
            dets = self.detector.detect(binarise_difference(diff, tracked.sign, scale.ksize), scale.decimate)
        except DetectorError:
            self.detector_failed = True  # reported with the next result that comes out; the track goes on
            return True
        finally:
            self.stages.lap("detect", t0)
        if len(dets) < self.cfg.pose.min_tags:
            return True
        pose = solve_pose(dets, self.tag_map, self.pinhole, self.cfg.pose)
        if pose is None:
            return True
        return float(np.linalg.norm(position - pose.position_m)) < 0.05
