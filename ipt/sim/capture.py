"""The simulated camera as a frame source of the receiver daemon (``ipt-receiver run --source sim``).

The receiver never imports the simulator: the command line (:mod:`ipt.receiver.cli`) makes this source
when the configuration asks for ``sim`` and hands it to :func:`ipt.receiver.daemon.run_daemon` as
``source=``, as the closed-loop demo (:mod:`ipt.sim.demo`) hands over its own. It is a
:class:`~ipt.receiver.capture.CaptureSource` like the recordings and cameras of
:mod:`ipt.receiver.capture`.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

import cv2
import numpy as np
from pydantic import ValidationError

from ipt.config.camera_info import CameraInfo
from ipt.config.models import ArenaConfig, ConfigError
from ipt.config.receiver import ReceiverConfig
from ipt.receiver.capture import CapturedFrame, CaptureError, Clock, Pacer, Sleep, capture_time_us
from ipt.sim.config import SimCameraConfig, SimConfig

if TYPE_CHECKING:  # the simulator plays the projector, so it uses sender code: import it only when used
    from ipt.sim.arena import SimulatedArena


def sim_camera_from(camera: CameraInfo, fps: float) -> SimCameraConfig:
    """The simulator's camera with the intrinsics of ``camera`` (so the receiver's model is exact)."""
    dist = list(camera.distortion)
    if len(dist) < 5:
        dist += [0.0] * (5 - len(dist))
    if any(dist[5:]):
        raise ConfigError(f"{camera.name}: the simulator models plumb_bob distortion (5 coefficients) only")
    try:
        return SimCameraConfig(
            width_px=camera.width_px,
            height_px=camera.height_px,
            fx_px=camera.fx_px,
            fy_px=camera.fy_px,
            cx_px=camera.cx_px,
            cy_px=camera.cy_px,
            distortion=(dist[0], dist[1], dist[2], dist[3], dist[4]),
            fps=fps,
        )
    except ValidationError as exc:
        raise ConfigError(f"the simulated camera cannot run this way: {exc.errors()[0]['msg']}") from None


class SimCapture:
    """Frames rendered live by the simulated arena; frame ``k`` is captured at ``k / fps``.

    Rendering is done on the capture thread (building the arena takes a moment, so ``open`` does it).
    With ``realtime`` frames are paced to the frame rate and treated as live; a renderer slower than
    the frame rate simply delivers frames later than their time (every frame is rendered, none skipped).
    """

    retry_open = False

    def __init__(
        self,
        arena: ArenaConfig,
        sim_cfg: SimConfig,
        fps: float | None = None,
        realtime: bool = False,
        *,
        clock: Clock = time.monotonic,
        sleep: Sleep = time.sleep,
        grey: bool = False,
    ) -> None:
        self.grey = grey
        """Hand over H×W luma frames (a colour camera's converted on the capture thread)."""
        rate = fps if fps is not None else sim_cfg.camera.fps
        if rate != sim_cfg.camera.fps:
            try:
                camera = SimCameraConfig.model_validate({**sim_cfg.camera.model_dump(), "fps": rate})
            except ValidationError as exc:
                raise ConfigError(f"the simulated camera cannot run at {rate} FPS: {exc.errors()[0]['msg']}") from None
            sim_cfg = sim_cfg.model_copy(update={"camera": camera})
        self.arena, self.sim_cfg, self.fps = arena, sim_cfg, rate
        self.name = "sim"
        self.live = realtime
        self._clock = clock
        self._pacer = Pacer(rate, clock, sleep) if realtime else None
        self._world: SimulatedArena | None = None
        self._next = 0

    def open(self) -> None:
        """Build the simulated arena (content, modulator, renderer)."""
        if self._world is not None:
            return
        from ipt.sim.arena import SimulatedArena, scene_for

        self._world = SimulatedArena(self.arena, self.sim_cfg, scene_for(self.sim_cfg, self.arena))
        self.notes = tuple(self._world.notes)  # the capture thread reports them once

    def read(self) -> CapturedFrame | None:
        """The next frame (the simulator never ends)."""
        world = self._world
        if world is None:
            raise CaptureError("sim: read before open")
        k = self._next
        self._next += 1
        image = world.render(k).image_rgb
        if self.grey and image.ndim == 3:
            image = np.asarray(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), dtype=np.uint8)
        if self._pacer is not None:
            self._pacer.wait(k)
        return CapturedFrame(k, capture_time_us(k, self.fps), image, self._clock())

    def close(self) -> None:
        """Nothing to release: the arena is kept for a reopen."""


def sim_source(cfg: ReceiverConfig, arena: ArenaConfig, camera: CameraInfo, stop: threading.Event) -> SimCapture:
    """The simulated camera of a receiver configuration whose ``source`` is ``sim``: the simulator's default
    flight seen through ``camera``'s intrinsics at ``cfg.fps`` (default: the simulator's rate). Its pacing
    sleeps end early when ``stop`` (the daemon's ``capture_stop``) is set."""
    grey = cfg.pipeline.luminance_only  # frames as luma, without a detour through RGB
    fps = cfg.fps if cfg.fps is not None else SimCameraConfig().fps
    sim = SimConfig(camera=sim_camera_from(camera, fps))
    return SimCapture(arena, sim, fps, cfg.realtime, sleep=stop.wait, grey=grey)


def receiver_sim_source(cfg: ReceiverConfig, stop: threading.Event) -> SimCapture:
    """:func:`sim_source` with the arena and camera files of ``cfg``: the factory ``ipt-receiver`` finds
    under the name ``sim`` in the ``ipt.capture_sources`` entry points (pyproject.toml), so that the
    receiver's code imports nothing of the simulator."""
    from ipt.config.camera_info import load_camera_info
    from ipt.config.models import load_arena_config

    return sim_source(cfg, load_arena_config(cfg.arena), load_camera_info(cfg.camera), stop)
