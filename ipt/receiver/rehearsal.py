"""A live daemon's rehearsal: a few frames of the arena's own hidden map, made up from the map and the camera, through
a throwaway pipeline before the camera starts, so that the first real frames do not pay for code run the first time.

A pipeline's first frames cost more than the same frames later: first calls into OpenCV, numpy's first buffers of
each size, the AprilTag helper's first images, the first pair's alignment and track. Live, that cost lands on the
frames that wait behind the first acquisition, when the start already holds the worker longest: shadow-vibration's
first pose took 25-31 ms of a warm pipeline's wall time and 52 ms as the daemon's first (``docs/receiver-cores.md``,
stop 60). The rehearsal's frames show the map from :data:`REHEARSAL_HEIGHT_M` straight above its middle, without lens
distortion (the throwaway pipeline is told the camera has none), each with the ± phase the camera sees at twice the
projector's rate; the throwaway pipeline shares the detector (the helper process warms too) and is dropped, so the
daemon's own pipeline starts as new. A recording needs none (its frames wait for the worker).

No clock, socket or thread of its own: the tag map, the camera, the settings and the detector in; frames, a pose count
and the processor time out (the daemon calls :func:`warm_up` on its worker thread).
"""

from __future__ import annotations

import dataclasses
import gc
import time
from typing import TextIO

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.config.models import PipelineConfig
from ipt.receiver.core.detection import Detector
from ipt.receiver.core.pipeline import Pipeline
from ipt.runtime import write_line
from ipt.tagmap import TagMap, pixel_to_arena

F64 = npt.NDArray[np.float64]

#: The rehearsal camera's height above the middle of the map (the paper's flights).
REHEARSAL_HEIGHT_M = 0.8
#: How many frames the rehearsal shows: an acquisition (AprilTag), a track, a sparse fit.
REHEARSAL_FRAMES = 4
#: The rehearsal's lightness step either side of its content (8-bit levels), the content's mean and spread.
REHEARSAL_STEP = 12.0
REHEARSAL_GREY = 150.0
REHEARSAL_CONTENT = 8.0
#: The camera's frame rate the rehearsal assumes (IPT's: twice the projector's 60 Hz).
REHEARSAL_FPS = 120.0


def _in_view(image_from_floor: F64, corners_m: F64, size: tuple[int, int]) -> bool:
    """Whether a corner of a tag (floor metres) falls in an image of ``size`` (width, height)."""
    p = cv2.perspectiveTransform(corners_m.reshape(-1, 1, 2), image_from_floor).reshape(-1, 2)
    return bool(np.any((p[:, 0] >= 0) & (p[:, 0] < size[0]) & (p[:, 1] >= 0) & (p[:, 1] < size[1])))


def rehearsal_frames(
    tag_map: TagMap, camera: CameraInfo, projector_hz: float, count: int = REHEARSAL_FRAMES
) -> tuple[list[npt.NDArray[np.uint8]], npt.NDArray[np.float64]]:
    """``count`` RGB frames of the camera's size showing the map from :data:`REHEARSAL_HEIGHT_M` above its middle,
    looking straight down (image x along the floor's x), at :data:`REHEARSAL_FPS`; and the camera's position (m)."""
    corners = np.array([c for t in tag_map.tags for c in t.corners_m], np.float64)
    centre = np.array([*corners[:, :2].mean(axis=0), REHEARSAL_HEIGHT_M])
    r_cam_arena = np.diag([1.0, -1.0, -1.0])  # looking down: the camera's z is the floor's -z
    t = -r_cam_arena @ centre
    image_from_floor = camera.camera_matrix @ np.column_stack([r_cam_arena[:, 0], r_cam_arena[:, 1], t])
    warp = image_from_floor @ pixel_to_arena(tag_map)
    size = (camera.width_px, camera.height_px)
    in_view = tuple(t for t in tag_map.tags if _in_view(image_from_floor, np.asarray(t.corners_m)[:, :2], size))
    mask = TagMap(tag_map.width_px, tag_map.height_px, in_view).render_mask().view(np.uint8)  # (the whole map: slow)
    step = cv2.warpPerspective(mask, warp, size, flags=cv2.INTER_NEAREST).view(np.int8).astype(np.float32)
    step = cv2.GaussianBlur(step, (3, 3), 0) * REHEARSAL_STEP  # (a lens's blur: edges a pixel wide)
    # The projected content: smooth blotches (fixed seed), for the pairs' alignment to lock on.
    noise = np.random.default_rng(0).normal(0.0, 1.0, (size[1] // 40 + 2, size[0] // 40 + 2)).astype(np.float32)
    content = cv2.resize(noise, size, interpolation=cv2.INTER_CUBIC) * REHEARSAL_CONTENT + REHEARSAL_GREY
    frames = []
    for k in range(count):
        phase = 1.0 if int(k / REHEARSAL_FPS * projector_hz) % 2 == 0 else -1.0  # [+, +, -, -] at 120 and 60 Hz
        grey = np.clip(content + phase * step, 0, 255).astype(np.uint8)
        frames.append(np.repeat(grey[:, :, None], 3, axis=2))
    return frames, centre


def rehearse(
    tag_map: TagMap, camera: CameraInfo, cfg: PipelineConfig, projector_hz: float, detector: Detector
) -> tuple[int, float]:
    """Run :func:`rehearsal_frames` through a throwaway live pipeline that shares ``detector`` (left open); return
    how many of them got a pose and the processor seconds it took. The garbage it leaves is collected here, not in
    the middle of the flight."""
    t0 = time.thread_time()
    pinhole = dataclasses.replace(camera, distortion=(0.0,) * len(camera.distortion))  # as the frames are made
    frames, _ = rehearsal_frames(tag_map, pinhole, projector_hz)
    throwaway = Pipeline(tag_map, pinhole, cfg, projector_hz, detector)
    throwaway.acquisition.live = True
    posed = 0
    for k, frame in enumerate(frames):
        results = throwaway.process(k, frame, round(k * 1e6 / REHEARSAL_FPS), 0)
        posed += sum(r.pose is not None for r in results)
    posed += sum(r.pose is not None for r in throwaway.flush())
    del throwaway, frames
    gc.collect()
    return posed, time.thread_time() - t0


def warm_up(pipeline: Pipeline, out: TextIO) -> None:
    """The daemon's call (on its pipeline's worker thread, before a live camera starts): :func:`rehearse` with
    ``pipeline``'s map, camera, settings and detector. A failure is said on ``out`` and the run goes on: the rehearsal
    only saves the first frames time, and the real frames meet whatever failed again, and say so then."""
    try:
        rehearse(pipeline.tag_map, pipeline.sensor, pipeline.cfg, pipeline.projector_hz, pipeline.detector)
    except Exception as exc:  # any: see above
        write_line(out, f"ipt-receiver: rehearsal failed (the first frames will be slower): {exc}")
