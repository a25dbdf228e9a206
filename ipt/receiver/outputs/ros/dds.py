"""ROS 2 topics over DDS, with CycloneDDS's Python binding: no ROS installation needed on the drone.

ROS 2 nodes talk DDS; a topic ``/ipt/pose`` of type ``geometry_msgs/msg/PoseWithCovarianceStamped`` is
the DDS topic ``rt/ipt/pose`` of type ``geometry_msgs::msg::dds_::PoseWithCovarianceStamped_`` in plain
CDR (XCDR1), keyless. The structs below mirror the ROS 2 definitions field for field (their CDR layout is
checked against rosbags' independent type store in ``tests/test_rosmsg.py``), so any rclcpp or rclpy node
(or a ROS 2 bag recorder) on the same domain receives them like those of a ROS node.

QoS: ``sensor_data`` (best effort, keep last 5, volatile: rclpy's ``qos_profile_sensor_data``) for the
pose and odometry by default, or ``reliable`` (keep last 10). ``/tf`` is reliable with keep last 100,
what tf2's listeners ask for (a best-effort writer would match no reliable reader, silently). The
network setup is CycloneDDS's own: ``CYCLONEDDS_URI`` is honoured as in any CycloneDDS program.

A participant that cannot start (a bad ``CYCLONEDDS_URI``, an interface that is not there) is a
:class:`Ros2Error` at start-up; a write that fails later is counted and reported once, and the daemon
goes on.
"""

# No ``from __future__ import annotations`` here: the binding reads the structs' field annotations as
# types at run time, and resolves string annotations only against names of this module.

import contextlib
import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from cyclonedds.core import DDSException, Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic

from ipt.config.receiver import Ros2Config
from ipt.errors import IptError
from ipt.receiver.outputs.ros.ddsconfig import check_cyclonedds_uri
from ipt.receiver.outputs.ros.frames import Outgoing
from ipt.rosmsg import ODOMETRY, POSE, TF, Message, dds_topic_name


class Ros2Error(IptError):
    """The DDS participant or a topic cannot be created."""


# --- the ROS 2 types, as DDS structs ------------------------------------------------------------------
# (mypy sees cyclonedds as untyped, hence the ignores on the class lines: IdlStruct is Any to it, and its
# ``typename`` keyword unknown.)


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):  # type: ignore[call-arg,misc]
    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):  # type: ignore[call-arg,misc]
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):  # type: ignore[call-arg,misc]
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):  # type: ignore[call-arg,misc]
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):  # type: ignore[call-arg,misc]
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):  # type: ignore[call-arg,misc]
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):  # type: ignore[call-arg,misc]
    pose: Pose = field(default_factory=Pose)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class PoseWithCovarianceStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"):  # type: ignore[call-arg,misc]
    header: Header = field(default_factory=Header)
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):  # type: ignore[call-arg,misc]
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):  # type: ignore[call-arg,misc]
    twist: Twist = field(default_factory=Twist)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class Odometry(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):  # type: ignore[call-arg,misc]
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)
    twist: TwistWithCovariance = field(default_factory=TwistWithCovariance)


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):  # type: ignore[call-arg,misc]
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):  # type: ignore[call-arg,misc]
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):  # type: ignore[call-arg,misc]
    transforms: t.sequence[TransformStamped] = field(default_factory=list)


# --- nested dicts (ipt.rosmsg) → structs -------------------------------------------------------------


def _header(m: Message) -> Header:
    return Header(Time(int(m["stamp"]["sec"]), int(m["stamp"]["nanosec"])), str(m["frame_id"]))


def _xyz(cls: Any, m: Message) -> Any:
    return cls(float(m["x"]), float(m["y"]), float(m["z"]))


def _quat(m: Message) -> Quaternion:
    return Quaternion(float(m["x"]), float(m["y"]), float(m["z"]), float(m["w"]))


def _pose_cov(m: Message) -> PoseWithCovariance:
    pose = Pose(_xyz(Point, m["pose"]["position"]), _quat(m["pose"]["orientation"]))
    return PoseWithCovariance(pose, [float(c) for c in m["covariance"]])


def pose_struct(m: Message) -> PoseWithCovarianceStamped:
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` from its nested-dict form."""
    return PoseWithCovarianceStamped(_header(m["header"]), _pose_cov(m["pose"]))


def odometry_struct(m: Message) -> Odometry:
    """``nav_msgs/msg/Odometry`` from its nested-dict form."""
    tw = m["twist"]
    twist = TwistWithCovariance(
        Twist(_xyz(Vector3, tw["twist"]["linear"]), _xyz(Vector3, tw["twist"]["angular"])),
        [float(c) for c in tw["covariance"]],
    )
    return Odometry(_header(m["header"]), str(m["child_frame_id"]), _pose_cov(m["pose"]), twist)


def tf_struct(m: Message) -> TFMessage:
    """``tf2_msgs/msg/TFMessage`` from its nested-dict form."""
    return TFMessage(
        [
            TransformStamped(
                _header(x["header"]),
                str(x["child_frame_id"]),
                Transform(_xyz(Vector3, x["transform"]["translation"]), _quat(x["transform"]["rotation"])),
            )
            for x in m["transforms"]
        ]
    )


STRUCTS: dict[str, tuple[type[IdlStruct], Callable[[Message], IdlStruct]]] = {
    POSE: (PoseWithCovarianceStamped, pose_struct),
    ODOMETRY: (Odometry, odometry_struct),
    TF: (TFMessage, tf_struct),
}
"""The ROS type each published message has, its struct and the converter from :mod:`ipt.rosmsg` dicts."""


# --- QoS --------------------------------------------------------------------------------------------


def qos_profile(name: str) -> Qos:
    """The writer QoS of a profile name: ``sensor_data`` or ``reliable`` (as rclpy defines them), or ``tf``."""
    xcdr1 = Policy.DataRepresentation(use_cdrv0_representation=True)  # what ROS 2's DDS layers speak
    if name == "sensor_data":
        return Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5), Policy.Durability.Volatile, xcdr1)
    if name == "reliable":
        return Qos(Policy.Reliability.Reliable(0), Policy.History.KeepLast(10), Policy.Durability.Volatile, xcdr1)
    if name == "tf":
        return Qos(Policy.Reliability.Reliable(0), Policy.History.KeepLast(100), Policy.Durability.Volatile, xcdr1)
    raise Ros2Error(f"unknown QoS profile {name!r} (sensor_data or reliable)")


def domain_from(cfg: Ros2Config, environ: dict[str, str] | None = None) -> int:
    """``cfg.domain_id``, else ``ROS_DOMAIN_ID`` from the environment, else 0."""
    if cfg.domain_id is not None:
        return cfg.domain_id
    env = os.environ if environ is None else environ
    text = env.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    if not text.isdigit() or not 0 <= int(text) <= 232:
        raise Ros2Error(f"ROS_DOMAIN_ID={text!r} is not a DDS domain (0..232)")
    return int(text)


# --- the output ---------------------------------------------------------------------------------------

_NATIVE_LOG_PREFIX = re.compile(r"^\d+\.\d+ \[\d+\]\s+\S+:\s*")


@contextlib.contextmanager
def _native_stderr(lines: list[str]) -> Iterator[None]:
    """Collect what the C library writes on stderr meanwhile (its own reason for a failure, in a line of its
    format) into ``lines`` instead of the terminal, so that a start-up error stays one line of ours. Used
    only while the daemon starts, before its other threads run."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no stderr to redirect: nothing to collect
        yield
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode("utf-8", "replace")
            lines.extend(_NATIVE_LOG_PREFIX.sub("", line).strip() for line in text.splitlines() if line.strip())


class Ros2Output:
    """DDS writers for the pose, odometry and (if asked) transforms of one vehicle.

    Created at start-up (a participant that cannot start raises :class:`Ros2Error`); :meth:`publish` takes
    a frame's :class:`~ipt.receiver.outputs.ros.frames.Outgoing` messages on the event loop and writes the ones it
    has a writer for (writes do not block: best effort, or reliable with keep-last history)."""

    def __init__(
        self,
        cfg: Ros2Config,
        topics: Sequence[tuple[str, str]],
        *,
        report: Callable[[str], None] | None = None,
        environ: dict[str, str] | None = None,
    ) -> None:
        """``topics``: (ROS topic, ``pkg/msg/Type``) pairs to create writers for."""
        self.domain_id = domain_from(cfg, environ)
        check_cyclonedds_uri()  # the environment CycloneDDS itself reads: a folder there meant default settings
        self.topics = [topic for topic, _ in topics]
        self.report = report
        self.published = 0
        self.errors = 0
        self.last_error: str | None = None
        native: list[str] = []
        try:
            with _native_stderr(native):
                self.participant = DomainParticipant(self.domain_id)
        except DDSException as exc:
            why = "; ".join(native) or str(exc)
            hint = " (check CYCLONEDDS_URI)" if os.environ.get("CYCLONEDDS_URI") else ""
            raise Ros2Error(f"DDS domain {self.domain_id} cannot start: {why}{hint}") from None
        for line in native:  # warnings of a domain that did start: pass them on, one line each
            if self.report is not None:
                self.report(f"ros2: cyclonedds: {line}")
        self._writers: dict[str, tuple[DataWriter, Callable[[Message], IdlStruct]]] = {}
        try:
            for topic, type_name in topics:
                struct, convert = STRUCTS[type_name]
                qos = qos_profile("tf" if type_name == TF else cfg.qos)
                dds_topic = Topic(self.participant, dds_topic_name(topic), struct, qos=qos)
                self._writers[topic] = (DataWriter(self.participant, dds_topic, qos=qos), convert)
        except DDSException as exc:
            self.close()
            raise Ros2Error(f"DDS domain {self.domain_id}: cannot create the topics: {exc}") from None

    def publish(self, items: Sequence[Outgoing]) -> int:
        """Write every item on a topic of this output; how many were written (failures are counted)."""
        written = 0
        for item in items:
            entry = self._writers.get(item.topic)
            if entry is None:
                continue
            writer, convert = entry
            try:
                writer.write(convert(item.message))
            except (DDSException, ValueError, TypeError) as exc:
                self.errors += 1
                self.last_error = f"{item.topic}: {exc}"
                if self.errors == 1 and self.report is not None:
                    self.report(f"ros2: writing {item.topic} failed ({exc}); counting failures, the rest goes on")
                continue
            written += 1
        self.published += written
        return written

    def matched(self, topic: str) -> int:
        """How many readers the writer of ``topic`` is matched with now."""
        entry = self._writers.get(topic)
        return 0 if entry is None else len(entry[0].get_matched_subscriptions())

    def close(self) -> None:
        """Delete the participant and everything in it (its sockets and threads end)."""
        self._writers = {}
        participant = getattr(self, "participant", None)
        if participant is not None:
            self.participant = None
            # The binding keeps every entity in a class-wide table, so dropping our reference does not
            # free it; its __del__ is the documented-in-code way to dds_delete it and its children.
            participant.__del__()

    def summary(self) -> str:
        """One line for the end of the run."""
        return (
            f"ros2: domain {self.domain_id}: {self.published} messages on {', '.join(self.topics) or '-'}"
            f", write errors {self.errors}"
        )


__all__ = [
    "STRUCTS",
    "Odometry",
    "PoseWithCovarianceStamped",
    "Ros2Error",
    "Ros2Output",
    "TFMessage",
    "domain_from",
    "odometry_struct",
    "pose_struct",
    "qos_profile",
    "tf_struct",
]
