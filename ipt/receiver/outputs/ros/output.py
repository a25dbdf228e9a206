"""The daemon's ROS side: every frame's messages made once, on a thread of their own, to DDS and the recording.

The event loop hands each frame's result to :meth:`RosOutputs.on_result`, which only queues it (never
blocks: when the thread is behind, the oldest way out is to drop the new frame, and that is counted). The
thread makes the messages (:class:`~ipt.receiver.outputs.ros.frames.RosMessageMaker`: pose, odometry, transforms,
diagnostics, the velocity fit), writes them to DDS (:class:`~ipt.receiver.outputs.ros.dds.Ros2Output`) and queues them
for the recorder (:class:`~ipt.receiver.outputs.ros.record.McapRecorder`, which encodes and writes on its own thread).
Building and serialising ROS messages in Python costs about a millisecond a frame; off the event loop it
does not hold up the next frame's way to the pipeline and to the UDP targets.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ipt.config.models import ConfigError
from ipt.config.receiver import ReceiverConfig
from ipt.receiver.outputs.ros.frames import RosMessageMaker, RosNames, StampClock
from ipt.rosmsg import ODOMETRY, POSE, TF

if TYPE_CHECKING:
    from ipt.receiver.capture import CapturedFrame
    from ipt.receiver.core.pipeline import FrameResult
    from ipt.receiver.outputs.ros.dds import Ros2Output
    from ipt.receiver.outputs.ros.record import McapRecorder

QUEUE_SIZE = 64
"""Frames waiting for the ROS thread (half a second at 120 FPS); more are dropped and counted."""
CLOSE_TIMEOUT_S = 1.0
"""How long closing waits for the thread to finish the frames queued."""

Report = Callable[[str], None]


class RosOutputs:
    """The ROS 2 outputs of one run (DDS and/or recording). :meth:`create`, :meth:`start`, :meth:`on_result`
    ..., then :meth:`close` (or :meth:`abort` for a run that never started)."""

    def __init__(
        self, maker: RosMessageMaker, ros2: Ros2Output | None, recorder: McapRecorder | None, report: Report
    ) -> None:
        self.maker, self.ros2, self.recorder, self.report = maker, ros2, recorder, report
        self.dropped = 0
        """Frames not turned into messages because the thread was behind."""
        self.failures = 0
        self._offset_noted = False
        self._queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(maxsize=QUEUE_SIZE)
        self._thread = threading.Thread(target=self._run, name="ipt-ros", daemon=True)

    @classmethod
    def create(cls, cfg: ReceiverConfig, projector_hz: float, report: Report) -> RosOutputs | None:
        """The outputs ``cfg.ros2`` and ``cfg.record`` ask for (None for neither); raises
        :class:`~ipt.errors.IptError` if one cannot be set up (nothing is left open then)."""
        if not cfg.ros2.enabled and cfg.record.path is None:
            return None
        from ipt.receiver.outputs.mavlink.frames import mounting_from

        r = cfg.ros2
        names = RosNames(r.frame_id, r.base_frame_id, r.camera_frame_id, r.namespace)
        mounting = mounting_from(cfg.mavlink.r_frd_cam, cfg.mavlink.camera_position_frd_m)
        maker = RosMessageMaker(names, mounting, StampClock(), hardware_id=f"ipt vehicle {cfg.vehicle_id}")
        recorder: McapRecorder | None = None
        if cfg.record.path is not None:
            from ipt import __version__
            from ipt.receiver.outputs.ros.record import McapRecorder

            recorder = McapRecorder(
                cfg.record.path,
                metadata={"vehicle_id": str(cfg.vehicle_id), "frame_id": names.frame_id, "ipt_version": __version__},
                image_hz=cfg.record.image_hz,
                projector_hz=projector_hz,
                camera_frame_id=names.child(names.camera_frame_id),
                image_topic=names.topic("difference"),
                report=report,
            )
        ros2: Ros2Output | None = None
        if r.enabled:
            try:
                from ipt.receiver.outputs.ros.dds import Ros2Output
            except ImportError as exc:
                if recorder is not None:
                    recorder.abort()
                raise ConfigError(
                    f"ros2 output needs the cyclonedds package ({exc}); install it with: pip install 'ipt[ros2]'"
                ) from None
            topics = [(names.pose_topic, POSE), (names.odom_topic, ODOMETRY)] + ([(names.tf_topic, TF)] if r.tf else [])
            try:
                ros2 = Ros2Output(r, topics, report=report)
            except BaseException:
                if recorder is not None:
                    recorder.abort()
                raise
        return cls(maker, ros2, recorder, report)

    def start(self) -> None:
        """Start the ROS thread and the recorder's writer."""
        if self.recorder is not None:
            self.recorder.start()
        self._thread.start()

    def on_result(self, frame: CapturedFrame, result: FrameResult | None, stages: dict[str, float]) -> None:
        """Queue one frame's result (``None``: processing failed) for the ROS thread; never blocks."""
        if result is None:
            item: tuple[Any, ...] = (frame.index, frame.capture_time_us, frame.grabbed_s, "error", 0, None, False, {})
        else:
            item = (frame.index, frame.capture_time_us, frame.grabbed_s, result.reason, result.num_detections,
                    result.pose, result.reset, stages)  # fmt: skip
        try:
            self._queue.put_nowait((*item, frame.image))
        except queue.Full:
            self.dropped += 1

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                self._frame(item)
            except Exception as exc:  # a bug on one frame: report the first, count, go on
                self.failures += 1
                if self.failures == 1:
                    self.report(f"ros: a frame's messages failed ({type(exc).__name__}: {exc}); counting, going on")

    def _frame(self, item: tuple[Any, ...]) -> None:
        *fields, image = item
        items = self.maker.frame(*fields)
        if self.ros2 is not None:
            self.ros2.publish(items)
        if self.recorder is not None:
            if not self._offset_noted and self.maker.clock.offset_ns is not None:
                self._offset_noted = True
                self.recorder.set_metadata({"capture_time_offset_ns": str(self.maker.clock.offset_ns)})
            self.recorder.put(items)
            self.recorder.offer_frame(fields[1], items[-1].stamp_ns, image)

    def _stop_thread(self) -> None:
        if self._thread.is_alive():
            with contextlib.suppress(queue.Full):
                self._queue.put(None, timeout=CLOSE_TIMEOUT_S)
            self._thread.join(CLOSE_TIMEOUT_S)

    def close(self) -> None:
        """Finish the queued frames, the recording, and leave the DDS domain (blocking: not on the event loop)."""
        self._stop_thread()
        if self.recorder is not None:
            self.recorder.close()
        if self.ros2 is not None:
            self.ros2.close()

    def abort(self) -> None:
        """Leave without a recording (the run never started): the partial file is removed."""
        self._stop_thread()
        if self.recorder is not None:
            self.recorder.abort()
        if self.ros2 is not None:
            self.ros2.close()

    def summaries(self) -> list[str]:
        """The outputs' lines for the end of the run."""
        lines = []
        if self.dropped or self.failures:
            lines.append(f"ros: {self.dropped} frames dropped (the ROS thread was behind), {self.failures} failed")
        if self.ros2 is not None:
            lines.append(self.ros2.summary())
        if self.recorder is not None:
            lines.append(self.recorder.summary())
        return lines


__all__ = ["RosOutputs"]
