"""ROS 2 messages without ROS: the definitions IPT publishes and records, time stamps, and reading poses back.

What lives here is shared by the receiver (which writes the messages, :mod:`ipt.receiver.outputs.ros.frames`) and
``ipt eval`` (which reads ``/ipt/pose`` out of a recording):

- the message definitions, in the concatenated ``.msg`` form MCAP's ``ros2msg`` schema encoding and
  ``ros2 bag`` use (the type's own fields, then each type it uses after a line of 80 ``=``). They are the
  upstream definitions (ros2/common_interfaces, ros2/geometry2, foxglove/schemas) with comments removed;
  ``tests/test_rosmsg.py`` checks their CDR layout against rosbags' independent type store;
- the DDS names ROS 2 gives them: topic ``/ipt/pose`` is DDS topic ``rt/ipt/pose`` and
  ``geometry_msgs/msg/Pose`` is DDS type ``geometry_msgs::msg::dds_::Pose_``;
- ``builtin_interfaces/Time`` from nanoseconds and back;
- :func:`read_mcap_trajectory`: the poses of one topic of a recording as a :class:`~ipt.tum.Trajectory`.

Messages are plain nested dicts here, keyed by field name (what mcap-ros2-support encodes); the DDS output
turns them into its typed structs.
"""

from __future__ import annotations

import contextlib
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np

from ipt.errors import IptError
from ipt.tum import Trajectory

Message = dict[str, Any]
"""A ROS message as nested dicts (sub-messages), lists (arrays) and numbers or strings."""

SEPARATOR = "=" * 80
MCAP_MAGIC = b"\x89MCAP0\r\n"
"""The first 8 bytes of every MCAP file."""

# The leaf definitions, without comments. Field names and types are the upstream ones exactly: the CDR
# layout follows from them and a ROS node decodes by them.
_DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/PoseWithCovariance": "Pose pose\nfloat64[36] covariance",
    "geometry_msgs/PoseWithCovarianceStamped": "std_msgs/Header header\nPoseWithCovariance pose",
    "geometry_msgs/Twist": "Vector3 linear\nVector3 angular",
    "geometry_msgs/TwistWithCovariance": "Twist twist\nfloat64[36] covariance",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform",
    "nav_msgs/Odometry": "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
    "geometry_msgs/TwistWithCovariance twist",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "diagnostic_msgs/KeyValue": "string key\nstring value",
    "diagnostic_msgs/DiagnosticStatus": "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\n"
    "string name\nstring message\nstring hardware_id\nKeyValue[] values",
    "diagnostic_msgs/DiagnosticArray": "std_msgs/Header header\nDiagnosticStatus[] status",
    "foxglove_msgs/CompressedImage": "builtin_interfaces/Time timestamp\nstring frame_id\nuint8[] data\nstring format",
}

_PRIMITIVES = frozenset(
    [
        "bool",
        "byte",
        "char",
        "float32",
        "float64",
        "int8",
        "uint8",
        "int16",
        "uint16",
        "int32",
        "uint32",
        "int64",
        "uint64",
        "string",
        "wstring",
    ]
)

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
COMPRESSED_IMAGE = "foxglove_msgs/msg/CompressedImage"


class RosMsgError(IptError):
    """A recording cannot be read as IPT poses (not MCAP, no such topic, a message that is not a pose)."""


def _short(name: str) -> str:
    """``pkg/msg/Type`` → ``pkg/Type`` (the form used inside definitions)."""
    return name.replace("/msg/", "/")


def _dependencies(short: str) -> list[str]:
    """The message types ``short``'s fields use, resolved to ``pkg/Type``."""
    pkg = short.split("/")[0]
    found = []
    for line in _DEFINITIONS[short].splitlines():
        ftype = re.sub(r"\[\d*\]$", "", line.split()[0])
        if ftype in _PRIMITIVES or "=" in line:
            continue
        found.append(ftype if "/" in ftype else f"{pkg}/{ftype}")
    return found


def message_definition(name: str) -> str:
    """The full definition of ``name`` (``pkg/msg/Type``): its fields, then every type it uses, each once,
    after a separator line and ``MSG: pkg/Type`` (the text ROS 2 keeps in a bag and MCAP in a schema)."""
    short = _short(name)
    if short not in _DEFINITIONS:
        raise KeyError(f"no definition for {name}")
    order: list[str] = []
    todo = _dependencies(short)
    while todo:
        dep = todo.pop(0)
        if dep not in order:
            order.append(dep)
            todo.extend(_dependencies(dep))
    parts = [_DEFINITIONS[short]]
    parts.extend(f"{SEPARATOR}\nMSG: {dep}\n{_DEFINITIONS[dep]}" for dep in order)
    return "\n".join(parts) + "\n"


def dds_type_name(name: str) -> str:
    """The DDS type ROS 2 uses for ``pkg/msg/Type``: ``pkg::msg::dds_::Type_``."""
    pkg, kind, type_name = name.split("/")
    return f"{pkg}::{kind}::dds_::{type_name}_"


def dds_topic_name(topic: str) -> str:
    """The DDS topic of a ROS 2 topic: ``/ipt/pose`` → ``rt/ipt/pose``."""
    return "rt/" + topic.lstrip("/")


def time_msg(stamp_ns: int) -> Message:
    """``builtin_interfaces/Time`` for a time in nanoseconds (``nanosec`` always in [0, 1e9))."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def time_ns(msg: Any) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time`` (a dict or an object with ``sec`` and ``nanosec``)."""
    if isinstance(msg, dict):
        return int(msg["sec"]) * 1_000_000_000 + int(msg["nanosec"])
    return int(msg.sec) * 1_000_000_000 + int(msg.nanosec)


METADATA_NAME = "ipt"
"""The MCAP metadata record the receiver writes: ``capture_time_offset_ns`` (header stamp minus the frame's
capture time on the source's own clock), ``vehicle``, ``frame_id`` and the IPT version."""


def is_mcap(path: str | Path) -> bool:
    """Whether ``path`` starts like an MCAP file (False if it cannot be read: the caller reports that)."""
    try:
        with open(path, "rb") as f:
            return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except (OSError, ValueError):
        return False


def _read_poses(reader: Any, topic: str, offset_ns: int, path: Path, out: list[tuple[int, Any]]) -> None:
    """Append (capture-clock ns, pose) of every message on ``topic`` to ``out``, in file order (so that what
    was read stays when a cut-short file ends in the middle)."""
    for schema, channel, _, msg in reader.iter_decoded_messages(topics=[topic], log_time_order=False):
        if schema is None or schema.name != POSE:
            kind = schema.name if schema is not None else "no schema"
            raise RosMsgError(f"{path}: {channel.topic} holds {kind}, not {POSE}")
        out.append((time_ns(msg.header.stamp) - offset_ns, msg.pose.pose))


def _offset_ns(reader: Any) -> int:
    for meta in reader.iter_metadata():
        if meta.name == METADATA_NAME and "capture_time_offset_ns" in meta.metadata:
            return int(meta.metadata["capture_time_offset_ns"])
    return 0


def read_mcap_trajectory(
    path: str | Path, topic: str = "/ipt/pose", *, capture_time: bool = True
) -> Trajectory:
    """The poses on ``topic`` (``geometry_msgs/msg/PoseWithCovarianceStamped``) of an MCAP recording.

    Times are the header stamps; with ``capture_time`` (and the receiver's ``ipt`` metadata in the file)
    they are turned back into the frames' capture times on the source's own clock, the time base of
    ``ipt-receiver replay`` and of a simulated flight's ground truth. Poses out of time order (or a repeated
    stamp) end the trajectory's strictly increasing times, so the later one is dropped.

    A recording cut short (a ``.partial`` file of a run that was killed, or whose disk filled) has no
    summary at its end: it is then read from the start as a stream, up to the last complete chunk.
    """
    from mcap.exceptions import EndOfFile, McapError
    from mcap.reader import NonSeekingReader, make_reader
    from mcap_ros2.decoder import DecoderFactory

    p = Path(path)
    decoders = [DecoderFactory()]
    poses: list[tuple[int, Any]] = []
    try:
        with p.open("rb") as f:
            try:
                reader = make_reader(f, decoder_factories=decoders)
                offset = _offset_ns(reader) if capture_time else 0
                _read_poses(reader, topic, offset, p, poses)
            except (McapError, EOFError, ValueError, KeyError):  # no summary, or cut short: read it as a stream
                offset = 0
                cut = (EndOfFile, McapError, EOFError, struct.error)  # what the end of a cut-short file raises
                if capture_time:
                    f.seek(0)
                    with contextlib.suppress(*cut):
                        offset = _offset_ns(NonSeekingReader(f, decoder_factories=decoders))
                f.seek(0)
                poses.clear()
                with contextlib.suppress(*cut):
                    _read_poses(NonSeekingReader(f, decoder_factories=decoders), topic, offset, p, poses)
    except FileNotFoundError:
        raise RosMsgError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise RosMsgError(f"{p}: is a directory, expected an MCAP file") from None
    except OSError as exc:
        raise RosMsgError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except (McapError, ValueError, KeyError, AttributeError, EOFError) as exc:
        raise RosMsgError(f"{p}: not a readable MCAP recording ({type(exc).__name__}: {exc})") from None
    times: list[float] = []
    positions: list[tuple[float, float, float]] = []
    quats: list[tuple[float, float, float, float]] = []
    last_ns: int | None = None
    for stamp_ns, pose in sorted(poses, key=lambda sp: sp[0]):
        if last_ns is not None and stamp_ns <= last_ns:
            continue
        last_ns = stamp_ns
        times.append(stamp_ns * 1e-9)
        positions.append((pose.position.x, pose.position.y, pose.position.z))
        o = pose.orientation
        quats.append((o.w, o.x, o.y, o.z))
    if not times:
        raise RosMsgError(f"{p}: no messages on {topic}")
    pos, q = np.asarray(positions, np.float64), np.asarray(quats, np.float64)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(q))):
        raise RosMsgError(f"{p}: {topic} holds a pose that is not finite")
    try:
        return Trajectory.from_arrays(times, pos, q)
    except ValueError as exc:
        raise RosMsgError(f"{p}: {topic}: {exc}") from None


__all__ = [
    "COMPRESSED_IMAGE",
    "DIAGNOSTICS",
    "MCAP_MAGIC",
    "METADATA_NAME",
    "ODOMETRY",
    "POSE",
    "TF",
    "Message",
    "RosMsgError",
    "dds_topic_name",
    "dds_type_name",
    "is_mcap",
    "message_definition",
    "read_mcap_trajectory",
    "time_msg",
    "time_ns",
]
