"""ROS 2 messages without ROS: our definitions and our DDS structs against rosbags' independent CDR.

rosbags ships the ROS 2 Humble message definitions and its own CDR (de)serialiser; mcap-ros2-support
encodes from our ``.msg`` texts; CycloneDDS from our IDL structs. The same message must come out as the
same bytes from all three, and decode back to the same values.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from mcap_ros2._dynamic import serialize_dynamic
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from ipt.geometry import matrix_from_ypr, rot_z
from ipt.receiver.core.kinematics import Twist
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.outputs.mavlink.output import R_FRD_CAM_DOWNWARD, Mounting
from ipt.receiver.outputs.ros import dds as ros2
from ipt.receiver.outputs.ros.frames import (
    R_FLU_FRD,
    RosMessageMaker,
    RosNames,
    StampClock,
    body_pose,
    diagnostics_message,
    odometry_message,
    pose_message,
    tf_message,
)
from ipt.rosmsg import (
    COMPRESSED_IMAGE,
    DIAGNOSTICS,
    ODOMETRY,
    POSE,
    TF,
    dds_topic_name,
    dds_type_name,
    message_definition,
    time_msg,
    time_ns,
)

STORE = get_typestore(Stores.ROS2_HUMBLE)
STAMP_NS = 1_700_000_123_456_789_012


def _pose(position_m: tuple[float, float, float] = (0.31, -0.22, 0.81), heading_rad: float = 0.4) -> PoseEstimate:
    r_arena_flu = rot_z(heading_rad) @ matrix_from_ypr(0.0, 0.05, -0.03)
    r_arena_cam = r_arena_flu @ np.diag([1.0, -1.0, -1.0]) @ R_FRD_CAM_DOWNWARD
    return PoseEstimate(
        np.asarray(position_m),
        r_arena_cam,
        (3, 4, 12),
        0.41,
        np.array([[1e-6, 2e-7, 0.0], [2e-7, 4e-6, 1e-7], [0.0, 1e-7, 9e-6]]),
        np.diag([1e-6, 2e-6, 3e-6]),
    )


def _twist() -> Twist:
    return Twist(1000, np.array([0.5, -0.2, 0.05]), np.eye(3) * 1e-4, np.array([0.0, 0.01, 0.3]), np.eye(3) * 1e-5, 8)


def _encode_mcap(type_name: str, message: Any) -> bytes:
    encoder = serialize_dynamic(type_name, message_definition(type_name))[type_name]
    return bytes(encoder(message))


def _same(a: Any, b: Any, where: str = "") -> None:
    """Recursively compare a nested-dict message with a rosbags (or cyclonedds) message object."""
    if isinstance(a, dict):
        for key, value in a.items():
            _same(value, getattr(b, key), f"{where}.{key}")
    elif isinstance(a, (list, tuple, bytes)):
        b_list = list(b)
        assert len(a) == len(b_list), where
        for i, (x, y) in enumerate(zip(a, b_list, strict=True)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, float):
        assert float(b) == a or (math.isnan(a) and math.isnan(float(b))), where
    else:
        assert a == b, where


def _messages() -> dict[str, Any]:
    names = RosNames(namespace="drone1")
    mounting = Mounting(R_FRD_CAM_DOWNWARD, np.array([0.05, -0.02, 0.03]))
    pose = _pose()
    return {
        POSE: pose_message(pose, STAMP_NS, "arena"),
        ODOMETRY: odometry_message(pose, _twist(), mounting, STAMP_NS, names),
        TF: tf_message(pose, mounting, STAMP_NS, names),
        DIAGNOSTICS: diagnostics_message(
            STAMP_NS, names, "ipt vehicle 3", 42, 350_000, "pose", 3, pose, {"detect": 1e-3}
        ),
    }


@pytest.mark.parametrize("type_name", [POSE, ODOMETRY, TF, DIAGNOSTICS])
def test_mcap_encoding_from_our_definitions_is_rosbags_cdr(type_name: str) -> None:
    message = _messages()[type_name]
    ours = _encode_mcap(type_name, message)
    decoded = STORE.deserialize_cdr(ours, type_name)
    _same(message, decoded)
    assert bytes(STORE.serialize_cdr(decoded, type_name)) == ours  # and back, byte for byte


@pytest.mark.parametrize("type_name", [POSE, ODOMETRY, TF])
def test_dds_structs_serialise_exactly_as_ros2_cdr(type_name: str) -> None:
    message = _messages()[type_name]
    struct_type, convert = ros2.STRUCTS[type_name]
    struct = convert(message)
    assert struct_type.__idl_typename__.replace(".", "::") == dds_type_name(type_name)
    dds = bytes(struct.serialize())
    assert dds[:4] == b"\x00\x01\x00\x00", "plain CDR, little endian: what ROS 2's DDS layers speak"
    assert dds == _encode_mcap(type_name, message)
    decoded = STORE.deserialize_cdr(dds, type_name)
    _same(message, decoded)
    _same(message, struct_type.deserialize(dds))


def test_foxglove_compressed_image_definition_round_trips() -> None:
    text = message_definition(COMPRESSED_IMAGE)
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(text, COMPRESSED_IMAGE))
    message = {"timestamp": time_msg(STAMP_NS), "frame_id": "camera", "data": b"\xff\xd8\x00\x01", "format": "jpeg"}
    data = _encode_mcap(COMPRESSED_IMAGE, message)
    decoded = store.deserialize_cdr(data, COMPRESSED_IMAGE)
    assert bytes(decoded.data) == message["data"]
    assert decoded.format == "jpeg"
    assert time_ns(decoded.timestamp) == STAMP_NS


def test_definitions_list_every_dependency_once_after_a_separator() -> None:
    text = message_definition(ODOMETRY)
    assert text.startswith("std_msgs/Header header\nstring child_frame_id\n")
    deps = [line.split()[1] for line in text.splitlines() if line.startswith("MSG: ")]
    assert len(deps) == len(set(deps))
    assert set(deps) == {
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "geometry_msgs/PoseWithCovariance",
        "geometry_msgs/Pose",
        "geometry_msgs/Point",
        "geometry_msgs/Quaternion",
        "geometry_msgs/TwistWithCovariance",
        "geometry_msgs/Twist",
        "geometry_msgs/Vector3",
    }
    assert text.count("=" * 80) == len(deps)
    with pytest.raises(KeyError):
        message_definition("sensor_msgs/msg/Image")


def test_ros2_names() -> None:
    assert dds_topic_name("/ipt/pose") == "rt/ipt/pose"
    assert dds_topic_name("/tf") == "rt/tf"
    assert dds_type_name(POSE) == "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
    assert dds_type_name(TF) == "tf2_msgs::msg::dds_::TFMessage_"
    for ns in (0, 1, 999_999_999, 1_000_000_000, STAMP_NS):
        t = time_msg(ns)
        assert 0 <= t["nanosec"] < 1_000_000_000
        assert time_ns(t) == ns


# --- what the messages say ----------------------------------------------------------------------------------


def test_pose_message_is_the_camera_pose_with_its_own_covariance() -> None:
    pose = _pose()
    m = pose_message(pose, STAMP_NS, "arena")
    assert m["header"]["frame_id"] == "arena"
    assert time_ns(m["header"]["stamp"]) == STAMP_NS
    p, q = m["pose"]["pose"]["position"], m["pose"]["pose"]["orientation"]
    assert (p["x"], p["y"], p["z"]) == tuple(pose.position_m)
    np.testing.assert_allclose([q["w"], q["x"], q["y"], q["z"]], pose.quat_wxyz, atol=1e-15)
    cov = np.array(m["pose"]["covariance"]).reshape(6, 6)
    np.testing.assert_array_equal(cov[:3, :3], pose.position_cov_m2)
    np.testing.assert_array_equal(cov[3:, 3:], pose.attitude_cov_rad2)
    assert not cov[:3, 3:].any()
    unknown = PoseEstimate(pose.position_m, pose.r_arena_cam, (1,), 0.3)  # NaN covariances
    assert pose_message(unknown, 0, "arena")["pose"]["covariance"] == [0.0] * 36  # ROS: all zeros = unknown


def test_odometry_is_the_body_in_flu_with_its_twist_in_body_axes() -> None:
    pose = _pose(heading_rad=0.0)
    offset_frd = np.array([0.1, 0.0, 0.0])  # camera 10 cm ahead of the body origin
    mounting = Mounting(R_FRD_CAM_DOWNWARD, offset_frd)
    names = RosNames()
    twist = _twist()
    m = odometry_message(pose, twist, mounting, STAMP_NS, names)
    assert m["child_frame_id"] == "base_link"
    position, r_arena_flu, cov = body_pose(pose, mounting)
    r_arena_frd = r_arena_flu @ R_FLU_FRD
    np.testing.assert_allclose(position, pose.position_m - r_arena_frd @ offset_frd, atol=1e-15)
    np.testing.assert_allclose(pose.r_arena_cam, r_arena_flu @ R_FLU_FRD @ R_FRD_CAM_DOWNWARD, atol=1e-12)
    assert cov[0, 0] >= pose.position_cov_m2[0, 0]  # the lever arm adds attitude uncertainty
    lin = m["twist"]["twist"]["linear"]
    v_body = np.array([lin["x"], lin["y"], lin["z"]])
    expected_arena = twist.velocity_mps + np.cross(twist.angular_velocity_radps, -(r_arena_frd @ offset_frd))
    np.testing.assert_allclose(r_arena_flu @ v_body, expected_arena, atol=1e-12)
    assert m["twist"]["covariance"][0] > 0
    none = odometry_message(pose, None, mounting, STAMP_NS, names)
    assert none["twist"]["covariance"][0] == -1.0  # the ROS sign for "no estimate"


def test_tf_and_namespaces() -> None:
    pose = _pose()
    names = RosNames(namespace="drone7")
    m = tf_message(pose, Mounting(), STAMP_NS, names)
    children = [t["child_frame_id"] for t in m["transforms"]]
    assert children == ["drone7/camera", "drone7/base_link"]
    assert {t["header"]["frame_id"] for t in m["transforms"]} == {"arena"}
    assert (names.pose_topic, names.odom_topic, names.tf_topic) == ("/ipt/drone7/pose", "/ipt/drone7/odom", "/tf")
    cam = m["transforms"][0]["transform"]["translation"]
    assert (cam["x"], cam["y"], cam["z"]) == tuple(pose.position_m)


def test_maker_stamps_diagnoses_every_frame_and_fits_the_velocity() -> None:
    wall = [1_700_000_000_000_000_000]
    clock = StampClock(wall_ns=lambda: wall[0], monotonic_s=lambda: 50.0)
    maker = RosMessageMaker(RosNames(), Mounting(), clock)
    out = maker.frame(0, 1_000_000, 49.5, "first_frame", 0, None)
    assert [o.type_name for o in out] == [DIAGNOSTICS]
    assert out[0].stamp_ns == wall[0] - 500_000_000  # grabbed half a second before "now"
    assert clock.offset_ns == wall[0] - 500_000_000 - 1_000_000_000
    assert out[0].message["status"][0]["level"] == 1
    for k in range(1, 8):
        pose = _pose((0.3 + 0.01 * k, 0.0, 0.8))  # 1 cm per 10 ms: 1 m/s along arena x
        out = maker.frame(k, 1_000_000 + 10_000 * k, 0.0, "pose", 3, pose, stage_seconds={"detect": 0.002})
    assert [o.type_name for o in out] == [POSE, ODOMETRY, TF, DIAGNOSTICS]
    assert out[0].stamp_ns - clock.offset_ns == (1_000_000 + 70_000) * 1000  # capture time, on the ROS clock
    twist = out[1].message["twist"]
    r_arena_flu = body_pose(_pose(), Mounting())[1]
    lin = twist["twist"]["linear"]
    np.testing.assert_allclose(r_arena_flu @ [lin["x"], lin["y"], lin["z"]], [1.0, 0.0, 0.0], atol=1e-9)
    values = {kv["key"]: kv["value"] for kv in out[3].message["status"][0]["values"]}
    assert values["detect_ms"] == "2.000"
    assert values["tag_ids"] == "3 4 12"
