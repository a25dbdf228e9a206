"""Tests of the UDP pose packet (ipt.protocol) against the committed samples and docs/protocol.md.

The samples under tests/data/packets/ were written once by running this file as a script
(``./dev run python tests/test_protocol.py``); the tests check that encoding SAMPLE reproduces them
byte for byte, so a change to the wire format shows up as a failure here, not as a silent drift.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import math
import re
import struct
import sys
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ipt.errors import IptError
from ipt.protocol import (
    AUTH_PACKET_SIZE,
    AUTH_PACKET_SIZE_V2,
    CRC_OFFSET,
    CRC_OFFSET_V2,
    MAGIC,
    PACKET_SIZE,
    PACKET_SIZE_V2,
    SUPPORTED_VERSIONS,
    AuthKeyError,
    MessageType,
    PacketFilter,
    PosePacket,
    ProtocolError,
    QualityFlags,
    Rejection,
    decode_pose,
    encode_pose,
    seq_newer,
)
from ipt.streams import Source

DATA_DIR = Path(__file__).parent / "data" / "packets"
DOCS = Path(__file__).parent.parent / "docs" / "protocol.md"

SAMPLE_KEY = b"ipt-test-key-0123456789abcdef"
"""The shared key of pose_v1_auth.bin (29 ASCII bytes). A test key: never use it on a real system."""

SAMPLE = PosePacket(
    vehicle_id=7,
    seq=123_456,
    capture_time_us=1_700_000_000_123_456,
    position_m=(1.25, -0.5, 2.0),
    # camera 2 m above the tag plane looking straight down, image top turned 30° from arena +y towards -x
    quat_wxyz=(0.0, 0.9659258262890683, 0.25881904510252074, 0.0),
    position_std_m=(0.004, 0.004, 0.011),
    attitude_std_rad=(0.002, 0.002, 0.0015),
    num_tags=5,
    reprojection_rms_px=0.42,
    flags=QualityFlags.SMOOTHED,
)
"""The documented sample: pose_v1.bin is encode_pose(SAMPLE), pose_v1_auth.bin adds SAMPLE_KEY."""

SAMPLE_AUTH = dataclasses.replace(SAMPLE, flags=SAMPLE.flags | QualityFlags.AUTHENTICATED)
"""What decoding pose_v1_auth.bin with SAMPLE_KEY gives: the flag now means "verified"."""

SAMPLE_V2 = dataclasses.replace(SAMPLE, stream_id=1_699_999_940_000_000)
"""The documented version-2 sample: the same pose from a run (stream) that started 60 s before it was taken;
pose_v2.bin is encode_pose(SAMPLE_V2), pose_v2_auth.bin adds SAMPLE_KEY."""

FAST = settings(database=None, max_examples=300, deadline=None)
"""Hypothesis settings: no example database, so the tests leave no .hypothesis/ in the checkout."""


def sample_bytes(authenticated: bool = False, version: int = 1) -> bytes:
    name = f"pose_v{version}_auth.bin" if authenticated else f"pose_v{version}.bin"
    return (DATA_DIR / name).read_bytes()


def with_crc(data: bytes) -> bytes:
    """``data`` (a plain, 112-byte packet) with its CRC recomputed after an edit."""
    body = data[:CRC_OFFSET]
    return body + struct.pack("<I", zlib.crc32(body)) + data[PACKET_SIZE:]


def with_tag(data: bytes, key: bytes) -> bytes:
    """The first 112 bytes of ``data`` with a correct authentication tag for ``key``."""
    signed = data[:PACKET_SIZE]
    return signed + hmac.new(key, signed, hashlib.sha256).digest()[:16]


def patched(data: bytes, offset: int, fmt: str, *values: object) -> bytes:
    """``data`` with ``values`` packed little-endian at ``offset``, CRC recomputed."""
    buffer = bytearray(data)
    struct.pack_into("<" + fmt, buffer, offset, *values)
    return with_crc(bytes(buffer))


def rejection(data: bytes, key: bytes | None = None) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        decode_pose(data, key)
    return info.value


# ---------------------------------------------------------------------------------------------------
# Layout and the committed samples


def test_sizes_are_the_documented_ones() -> None:
    assert (CRC_OFFSET, PACKET_SIZE, AUTH_PACKET_SIZE) == (108, 112, 128)
    assert len(encode_pose(SAMPLE)) == PACKET_SIZE
    assert len(encode_pose(SAMPLE, SAMPLE_KEY)) == AUTH_PACKET_SIZE


def test_encoding_the_sample_reproduces_the_committed_bytes() -> None:
    assert encode_pose(SAMPLE) == sample_bytes()
    assert encode_pose(SAMPLE, SAMPLE_KEY) == sample_bytes(authenticated=True)


def test_decoding_the_committed_bytes_gives_the_sample() -> None:
    assert decode_pose(sample_bytes()) == SAMPLE
    assert decode_pose(sample_bytes(authenticated=True), SAMPLE_KEY) == SAMPLE_AUTH


def test_authenticated_sample_is_the_plain_one_with_flag_crc_and_tag() -> None:
    plain, auth = sample_bytes(), sample_bytes(authenticated=True)
    flags_plain, flags_auth = struct.unpack_from("<H", plain, 6)[0], struct.unpack_from("<H", auth, 6)[0]
    assert flags_auth == flags_plain | QualityFlags.AUTHENTICATED
    assert auth[:6] == plain[:6]
    assert auth[8:CRC_OFFSET] == plain[8:CRC_OFFSET]
    assert struct.unpack_from("<I", auth, CRC_OFFSET)[0] == zlib.crc32(auth[:CRC_OFFSET])
    assert auth[PACKET_SIZE:] == hmac.new(SAMPLE_KEY, auth[:PACKET_SIZE], hashlib.sha256).digest()[:16]


def test_fields_sit_at_the_documented_offsets() -> None:
    data = sample_bytes()
    assert data[0:4] == MAGIC == b"IPTL"
    assert struct.unpack_from("<BBHHHIQ", data, 4) == (
        1,
        1,
        QualityFlags.SMOOTHED,
        7,
        5,
        123_456,
        SAMPLE.capture_time_us,
    )
    assert struct.unpack_from("<3d", data, 24) == SAMPLE.position_m
    assert struct.unpack_from("<4d", data, 48) == SAMPLE.quat_wxyz
    assert struct.unpack_from("<3f", data, 80) == SAMPLE.position_std_m
    assert struct.unpack_from("<3f", data, 92) == SAMPLE.attitude_std_rad
    assert struct.unpack_from("<f", data, 104) == (SAMPLE.reprojection_rms_px,)
    assert struct.unpack_from("<I", data, 108) == (zlib.crc32(data[:108]),)


def _doc_hex(name: str) -> bytes:
    text = DOCS.read_text(encoding="utf-8")
    block = re.search(rf"<!-- hex {re.escape(name)} -->\s*```text\n(.*?)```", text, re.DOTALL)
    assert block is not None, f"docs/protocol.md has no hex dump of {name}"
    rows = [line.split(":", 1)[1] for line in block.group(1).splitlines() if line.strip()]
    return bytes.fromhex("".join(rows))


@pytest.mark.parametrize(
    ("name", "authenticated", "version"),
    [
        ("pose_v1.bin", False, 1),
        ("pose_v1_auth.bin", True, 1),
        ("pose_v2.bin", False, 2),
        ("pose_v2_auth.bin", True, 2),
    ],
)
def test_docs_worked_example_matches_the_sample(name: str, authenticated: bool, version: int) -> None:
    assert _doc_hex(name) == sample_bytes(authenticated, version)


# ---------------------------------------------------------------------------------------------------
# Version 2: the stream identity


def test_version_2_sizes_and_committed_bytes() -> None:
    assert (CRC_OFFSET_V2, PACKET_SIZE_V2, AUTH_PACKET_SIZE_V2) == (116, 120, 136)
    assert encode_pose(SAMPLE_V2) == sample_bytes(version=2)
    assert encode_pose(SAMPLE_V2, SAMPLE_KEY) == sample_bytes(authenticated=True, version=2)
    assert decode_pose(sample_bytes(version=2)) == SAMPLE_V2
    assert decode_pose(sample_bytes(authenticated=True, version=2), SAMPLE_KEY) == dataclasses.replace(
        SAMPLE_V2, flags=SAMPLE_V2.flags | QualityFlags.AUTHENTICATED
    )
    assert decode_pose(sample_bytes()).stream_id is None  # version 1 carries none


def test_version_2_is_version_1_with_the_stream_after_the_capture_time() -> None:
    v1, v2 = sample_bytes(), sample_bytes(version=2)
    assert (v2[:4], v2[4], v1[4]) == (v1[:4], 2, 1)
    assert v2[5:24] == v1[5:24]  # type, flags, vehicle, tags, sequence, capture time
    assert struct.unpack_from("<Q", v2, 24) == (SAMPLE_V2.stream_id,)
    assert v2[32:CRC_OFFSET_V2] == v1[24:CRC_OFFSET]  # the pose and its uncertainty, moved by 8 bytes
    assert struct.unpack_from("<I", v2, CRC_OFFSET_V2) == (zlib.crc32(v2[:CRC_OFFSET_V2]),)
    auth = sample_bytes(authenticated=True, version=2)
    assert auth[PACKET_SIZE_V2:] == hmac.new(SAMPLE_KEY, auth[:PACKET_SIZE_V2], hashlib.sha256).digest()[:16]


@pytest.mark.parametrize("authenticated", [False, True])
def test_a_version_1_only_decoder_rejects_version_2_saying_so(authenticated: bool) -> None:
    key = SAMPLE_KEY if authenticated else None
    with pytest.raises(ProtocolError) as info:
        decode_pose(sample_bytes(authenticated, version=2), key, versions=(1,))
    assert str(info.value) == "version 2 not supported (this decoder speaks version 1)"
    assert info.value.reason is Rejection.UNSUPPORTED
    # ... and the version-1 samples still decode with it, as with today's decoder.
    assert decode_pose(sample_bytes(), versions=(1,)) == SAMPLE


def test_version_2_byte_corruption_is_rejected() -> None:
    data = sample_bytes(authenticated=True, version=2)
    for offset in range(6, len(data)):
        for xor in (1, 0x80):
            corrupt = bytearray(data)
            corrupt[offset] ^= xor
            error = rejection(bytes(corrupt), SAMPLE_KEY)
            expected = Rejection.BAD_AUTH if offset >= PACKET_SIZE_V2 else Rejection.BAD_CRC
            assert error.reason is expected, (offset, xor)
    assert "bad length 128 bytes: a version-2 pose packet is 120 bytes" in str(rejection(data[:128]))


def test_the_stream_id_is_checked() -> None:
    with pytest.raises(ProtocolError, match="stream_id -1 is outside"):
        dataclasses.replace(SAMPLE, stream_id=-1)
    with pytest.raises(ProtocolError, match="stream_id must be an integer"):
        dataclasses.replace(SAMPLE, stream_id=1.5)


# ---------------------------------------------------------------------------------------------------
# Round trips

_finite64 = st.floats(allow_nan=False, allow_infinity=False)
_std = st.floats(min_value=0.0, max_value=1e30, allow_nan=False)


@st.composite
def _unit_quats(draw: st.DrawFn) -> tuple[float, float, float, float]:
    q = draw(st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda v: math.hypot(*v) > 1e-3))
    scale = draw(st.floats(1.0 - 5e-4, 1.0 + 5e-4)) / math.hypot(*q)
    return (q[0] * scale, q[1] * scale, q[2] * scale, q[3] * scale)


packets = st.builds(
    PosePacket,
    vehicle_id=st.integers(0, 0xFFFF),
    seq=st.integers(0, 0xFFFF_FFFF),
    capture_time_us=st.integers(0, 2**64 - 1),
    position_m=st.tuples(_finite64, _finite64, _finite64),
    quat_wxyz=_unit_quats(),
    position_std_m=st.tuples(_std, _std, _std),
    attitude_std_rad=st.tuples(_std, _std, _std),
    num_tags=st.integers(0, 0xFFFF),
    reprojection_rms_px=_std,
    flags=st.integers(0, 15).map(QualityFlags),
    stream_id=st.one_of(st.none(), st.integers(0, 2**64 - 1)),
)


@FAST
@given(packets)
def test_round_trip_without_key(packet: PosePacket) -> None:
    data = encode_pose(packet)
    assert len(data) == (PACKET_SIZE if packet.stream_id is None else PACKET_SIZE_V2)
    assert decode_pose(data) == dataclasses.replace(packet, flags=packet.flags & ~QualityFlags.AUTHENTICATED)


@FAST
@given(packets)
def test_round_trip_with_key(packet: PosePacket) -> None:
    data = encode_pose(packet, SAMPLE_KEY)
    assert len(data) == (AUTH_PACKET_SIZE if packet.stream_id is None else AUTH_PACKET_SIZE_V2)
    assert decode_pose(data, SAMPLE_KEY) == dataclasses.replace(
        packet, flags=packet.flags | QualityFlags.AUTHENTICATED
    )


def test_float32_fields_are_rounded_on_construction() -> None:
    assert SAMPLE.position_std_m[0] == float(np.float32(0.004))
    assert SAMPLE.position_std_m[0] != 0.004
    assert SAMPLE.reprojection_rms_px == float(np.float32(0.42))


def test_sequences_are_stored_as_tuples_of_float() -> None:
    # What an estimator hands over: numpy arrays and scalars, lists, ints (hence the ignore).
    loose: dict[str, object] = {
        "position_m": np.array([1.0, 2.0, 3.0]),
        "quat_wxyz": [1, 0, 0, 0],
        "vehicle_id": np.uint16(3),
    }
    packet = dataclasses.replace(SAMPLE, **loose)  # type: ignore[arg-type]
    assert packet.position_m == (1.0, 2.0, 3.0)
    assert type(packet.position_m) is tuple
    assert all(type(v) is float for v in packet.quat_wxyz)
    assert type(packet.vehicle_id) is int
    assert decode_pose(encode_pose(packet)) == packet


def test_quaternion_is_not_normalised() -> None:
    q = (1.0005, 0.0, 0.0, 0.0)
    assert decode_pose(encode_pose(dataclasses.replace(SAMPLE, quat_wxyz=q))).quat_wxyz == q


# ---------------------------------------------------------------------------------------------------
# Rejection of malformed input


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"vehicle_id": 0x1_0000}, "vehicle_id 65536 is outside 0..65535"),
        ({"vehicle_id": -1}, "vehicle_id -1 is outside"),
        ({"seq": 2**32}, "seq 4294967296 is outside"),
        ({"capture_time_us": 2**64}, "capture_time_us"),
        ({"num_tags": 70_000}, "num_tags 70000"),
        ({"seq": True}, "seq must be an integer"),
        ({"seq": 1.0}, "seq must be an integer"),
        ({"flags": 0x10}, "reserved bits"),
        ({"position_m": (0.0, math.nan, 0.0)}, "position_m[1] is nan"),
        ({"position_m": (0.0, 0.0)}, "position_m must have 3 values"),
        ({"position_m": "abc"}, "position_m must be a sequence"),
        ({"quat_wxyz": (1.0, 0.0, 0.0, math.inf)}, "quat_wxyz[3] is inf"),
        ({"quat_wxyz": (0.0, 0.0, 0.0, 0.0)}, "zero quaternion"),
        ({"quat_wxyz": (1.002, 0.0, 0.0, 0.0)}, "within 0.001 of 1"),
        ({"position_std_m": (0.0, -0.1, 0.0)}, "position_std_m[1] is -0.1; it must be >= 0"),
        ({"attitude_std_rad": (0.0, 0.0, 1e39)}, "too large for a float32"),
        ({"reprojection_rms_px": math.nan}, "reprojection_rms_px is nan"),
    ],
)
def test_invalid_packet_values_are_refused(changes: dict[str, object], message: str) -> None:
    with pytest.raises(ProtocolError, match=re.escape(message)) as info:
        dataclasses.replace(SAMPLE, **changes)  # type: ignore[arg-type]
    assert info.value.reason is Rejection.MALFORMED


@pytest.mark.parametrize("authenticated", [False, True])
def test_every_single_byte_corruption_is_rejected(authenticated: bool) -> None:
    data = sample_bytes(authenticated)
    key = SAMPLE_KEY if authenticated else None
    for offset in range(len(data)):
        for xor in range(1, 256):
            corrupt = bytearray(data)
            corrupt[offset] ^= xor
            with pytest.raises(ProtocolError) as info:
                decode_pose(bytes(corrupt), key)
            message = str(info.value)
            if offset < 4:
                assert message.startswith("bad magic"), (offset, xor)
            elif offset == 4 and data[4] ^ xor in SUPPORTED_VERSIONS:  # another known version: its length is wrong
                assert message.startswith(f"bad length {len(data)} bytes: a version-{data[4] ^ xor} pose packet")
            elif offset == 4:
                assert message.startswith(f"version {data[4] ^ xor} not supported")
            elif offset == 5:
                assert message.startswith(f"message type {data[5] ^ xor} not supported")
            elif offset >= PACKET_SIZE:
                assert info.value.reason is Rejection.BAD_AUTH
            else:  # past magic, version and type, the CRC is the first check to fail
                assert info.value.reason is Rejection.BAD_CRC, (offset, xor)


def test_tag_is_not_checked_without_a_key_and_the_packet_is_not_marked_verified() -> None:
    corrupt = bytearray(sample_bytes(authenticated=True))
    corrupt[-1] ^= 0x01
    assert decode_pose(bytes(corrupt)) == SAMPLE
    assert QualityFlags.AUTHENTICATED not in decode_pose(sample_bytes(authenticated=True)).flags


@pytest.mark.parametrize("authenticated", [False, True])
def test_every_truncation_and_extension_is_rejected(authenticated: bool) -> None:
    data = sample_bytes(authenticated)
    key = SAMPLE_KEY if authenticated else None
    for size in range(len(data)):
        with pytest.raises(ProtocolError):
            decode_pose(data[:size], key)
    for extra in range(1, 200):
        with pytest.raises(ProtocolError):
            decode_pose(data + bytes(extra), key)
        with pytest.raises(ProtocolError):
            decode_pose(data + b"\xa5" * extra, key)


def test_a_plain_packet_with_a_tag_appended_is_rejected_without_flag() -> None:
    error = rejection(sample_bytes() + bytes(16))
    assert "AUTHENTICATED flag is clear but the packet is 128 bytes" in str(error)


def test_an_authenticated_packet_cut_to_112_bytes_is_rejected() -> None:
    error = rejection(sample_bytes(authenticated=True)[:PACKET_SIZE])
    assert "AUTHENTICATED flag is set but the packet is 112 bytes" in str(error)


@pytest.mark.parametrize(
    ("make", "message", "reason"),
    [
        (lambda d: d[:3], "packet too short: 3 bytes", Rejection.MALFORMED),
        (lambda d: b"IPTX" + d[4:], "bad magic b'IPTX', expected b'IPTL'", Rejection.MALFORMED),
        (lambda d: patched(d, 4, "B", 7), "version 7 not supported", Rejection.UNSUPPORTED),
        (lambda d: patched(d, 4, "B", 0), "version 0 not supported", Rejection.UNSUPPORTED),
        (lambda d: patched(d, 5, "B", 9), "message type 9 not supported", Rejection.UNSUPPORTED),
        (lambda d: d[:50], "bad length 50 bytes", Rejection.MALFORMED),
        (lambda d: d[:-1] + bytes([d[-1] ^ 1]), "bad CRC", Rejection.BAD_CRC),
        (lambda d: patched(d, 6, "H", 0x8002), "flags 0x8002 set reserved bits", Rejection.MALFORMED),
        (lambda d: patched(d, 32, "d", math.nan), "position_m[1] is nan", Rejection.MALFORMED),
        (lambda d: patched(d, 48, "d", -math.inf), "quat_wxyz[0] is -inf", Rejection.MALFORMED),
        (lambda d: patched(d, 48, "4d", 0.0, 0.0, 0.0, 0.0), "zero quaternion", Rejection.MALFORMED),
        (lambda d: patched(d, 48, "4d", 0.5, 0.5, 0.5, 0.0), "norm 0.866025", Rejection.MALFORMED),
        (lambda d: patched(d, 84, "f", -1.0), "position_std_m[1] is -1.0", Rejection.MALFORMED),
        (lambda d: patched(d, 100, "f", math.inf), "attitude_std_rad[2] is inf", Rejection.MALFORMED),
        (lambda d: patched(d, 104, "f", math.nan), "reprojection_rms_px is nan", Rejection.MALFORMED),
    ],
)
def test_malformed_packets_name_the_problem(
    make: Callable[[bytes], bytes], message: str, reason: Rejection
) -> None:
    error = rejection(make(sample_bytes()))
    assert message in str(error)
    assert error.reason is reason
    assert isinstance(error, IptError)


def test_header_errors_are_reported_before_the_crc() -> None:
    # A version this build does not know says so even if the rest (CRC included) is not understood.
    data = bytearray(sample_bytes())
    data[4] = 3
    assert "version 3 not supported (this decoder speaks versions 1 and 2)" in str(rejection(bytes(data)))


@FAST
@given(st.binary(max_size=2 * AUTH_PACKET_SIZE), st.sampled_from([None, SAMPLE_KEY]))
def test_random_bytes_only_ever_raise_protocol_error(data: bytes, key: bytes | None) -> None:
    try:
        packet = decode_pose(data, key)
    except ProtocolError:
        return
    assert isinstance(packet, PosePacket)


@FAST
@given(
    st.integers(0, 15),
    st.binary(min_size=PACKET_SIZE - 8, max_size=PACKET_SIZE - 8),
    st.sampled_from([None, SAMPLE_KEY]),
)
def test_random_bodies_with_valid_header_and_crc_only_ever_raise_protocol_error(
    flags: int, body: bytes, key: bytes | None
) -> None:
    # Get past the magic, version, type, CRC and flag checks, so that the values are what is tested.
    data = with_crc(MAGIC + bytes([1, 1]) + struct.pack("<H", flags) + body)
    tagged = bool(flags & QualityFlags.AUTHENTICATED)
    if tagged:
        data = with_tag(data, SAMPLE_KEY)
    outcome: PosePacket | ProtocolError
    try:
        outcome = decode_pose(data, key)
    except ProtocolError as error:
        outcome = error
    if isinstance(outcome, ProtocolError):
        assert outcome.reason in {Rejection.MALFORMED, Rejection.UNAUTHENTICATED}
    else:
        assert encode_pose(outcome, SAMPLE_KEY if tagged else None) == data


@FAST
@given(st.binary(max_size=2 * AUTH_PACKET_SIZE), st.sampled_from([None, SAMPLE_KEY]))
def test_random_tails_after_a_valid_header_only_ever_raise_protocol_error(
    tail: bytes, key: bytes | None
) -> None:
    data = MAGIC + bytes([1, 1]) + tail
    with pytest.raises(ProtocolError) as info:
        decode_pose(data, key)
    if len(data) in (PACKET_SIZE, AUTH_PACKET_SIZE):
        assert info.value.reason is Rejection.BAD_CRC
    else:
        assert "bad length" in str(info.value)


# ---------------------------------------------------------------------------------------------------
# Authentication


def test_wrong_key_is_rejected() -> None:
    error = rejection(sample_bytes(authenticated=True), b"another-key-0123456789")
    assert error.reason is Rejection.BAD_AUTH
    assert "authentication tag does not match" in str(error)


def test_tampered_tag_is_rejected() -> None:
    data = bytearray(sample_bytes(authenticated=True))
    data[PACKET_SIZE] ^= 0x80
    assert rejection(bytes(data), SAMPLE_KEY).reason is Rejection.BAD_AUTH


def test_tampered_body_with_recomputed_crc_is_rejected() -> None:
    # The CRC only catches accidents: someone who edits the position and fixes the CRC needs the key too.
    data = patched(sample_bytes(authenticated=True), 24, "d", 9.0)
    assert decode_pose(data).position_m[0] == 9.0  # well-formed, as far as a keyless reader can tell
    assert rejection(data, SAMPLE_KEY).reason is Rejection.BAD_AUTH


def test_unauthenticated_packet_is_rejected_when_a_key_is_set() -> None:
    error = rejection(sample_bytes(), SAMPLE_KEY)
    assert error.reason is Rejection.UNAUTHENTICATED
    assert "not authenticated" in str(error)


def test_encode_sets_the_authenticated_flag_from_the_key_alone() -> None:
    assert encode_pose(SAMPLE_AUTH) == sample_bytes()
    assert encode_pose(SAMPLE, SAMPLE_KEY) == encode_pose(SAMPLE_AUTH, SAMPLE_KEY)


def test_short_keys_are_a_configuration_error_not_a_packet_error() -> None:
    with pytest.raises(AuthKeyError, match="15 bytes"):
        encode_pose(SAMPLE, b"k" * 15)
    with pytest.raises(AuthKeyError):
        decode_pose(sample_bytes(), b"")
    with pytest.raises(AuthKeyError):
        PacketFilter(key=b"short")
    assert not issubclass(AuthKeyError, ProtocolError)
    assert decode_pose(encode_pose(SAMPLE, b"k" * 16), b"k" * 16) == SAMPLE_AUTH


def test_message_type_and_flags_values_are_stable() -> None:
    assert int(MessageType.POSE) == 1
    assert [int(f) for f in QualityFlags] == [1, 2, 4, 8]


# ---------------------------------------------------------------------------------------------------
# PacketFilter


def pose(seq: int, vehicle_id: int = 7, key: bytes | None = None, stream: int | None = None) -> bytes:
    return encode_pose(dataclasses.replace(SAMPLE, seq=seq, vehicle_id=vehicle_id, stream_id=stream), key)


def nonzero(counts: dict[str, int]) -> dict[str, int]:
    return {k: v for k, v in counts.items() if v}


def test_seq_newer_uses_serial_arithmetic() -> None:
    assert seq_newer(1, 0)
    assert not seq_newer(0, 0)
    assert not seq_newer(0, 1)
    assert seq_newer(0, 2**32 - 1)
    assert seq_newer(5, 2**32 - 3)
    assert not seq_newer(2**32 - 3, 5)
    assert seq_newer(2**31 - 1, 0)
    assert not seq_newer(2**31, 0)
    assert seq_newer(10, 0, window=10)
    assert not seq_newer(11, 0, window=10)


def test_filter_rejects_replayed_and_older_packets() -> None:
    gate = PacketFilter()
    assert gate.accept(pose(10)) == dataclasses.replace(SAMPLE, seq=10)
    assert gate.accept(pose(10)) is None
    assert gate.accept(pose(9)) is None
    assert gate.accept(pose(12)) is not None
    assert gate.accept(pose(11)) is None
    assert gate.last_seq(7) == 12
    assert nonzero(gate.counts) == {"accepted": 2, "replayed": 3}


def test_filter_accepts_across_the_uint32_wraparound() -> None:
    gate = PacketFilter()
    for seq in (2**32 - 2, 2**32 - 1, 0, 1):
        assert gate.accept(pose(seq)) is not None, seq
    assert gate.accept(pose(2**32 - 1)) is None
    assert gate.last_seq(7) == 1
    assert nonzero(gate.counts) == {"accepted": 4, "replayed": 1}


def test_filter_window_limits_forward_jumps() -> None:
    gate = PacketFilter(window=100)
    assert gate.accept(pose(1000)) is not None
    assert gate.accept(pose(1101)) is None
    assert gate.accept(pose(1100)) is not None


def test_filter_keeps_sequence_state_per_vehicle() -> None:
    gate = PacketFilter()
    assert gate.accept(pose(500, vehicle_id=1)) is not None
    assert gate.accept(pose(3, vehicle_id=2)) is not None
    assert gate.accept(pose(4, vehicle_id=1)) is None
    assert gate.accept(pose(4, vehicle_id=2)) is not None
    assert (gate.last_seq(1), gate.last_seq(2), gate.last_seq(3)) == (500, 4, None)


def test_filter_counts_unknown_vehicles_and_keeps_no_state_for_them() -> None:
    gate = PacketFilter(vehicle_ids={1, 2})
    assert gate.accept(pose(1, vehicle_id=7)) is None
    assert gate.accept(pose(1, vehicle_id=2)) is not None
    assert gate.last_seq(7) is None
    assert nonzero(gate.counts) == {"accepted": 1, "unknown_vehicle": 1}


def test_filter_counts_each_rejection_reason_once_per_packet() -> None:
    gate = PacketFilter(key=SAMPLE_KEY, vehicle_ids=[7])
    bad_crc = bytearray(pose(1, key=SAMPLE_KEY))
    bad_crc[30] ^= 0xFF
    inputs = [
        pose(1, key=SAMPLE_KEY),  # accepted
        pose(1, key=SAMPLE_KEY),  # replayed
        pose(2),  # unauthenticated
        pose(3, key=b"not-the-right-key-at-all"),  # bad_auth
        bytes(bad_crc),  # bad_crc
        b"",  # malformed
        b"IPTL\x03\x01" + bytes(106),  # unsupported (version 3)
        pose(4, vehicle_id=8, key=SAMPLE_KEY),  # unknown_vehicle
        pose(5, key=SAMPLE_KEY),  # accepted
    ]
    results = [gate.accept(data) for data in inputs]
    assert [r is not None for r in results] == [True] + [False] * 7 + [True]
    assert gate.counts == {
        "accepted": 2,
        "malformed": 1,
        "unsupported": 1,
        "bad_crc": 1,
        "unauthenticated": 1,
        "bad_auth": 1,
        "unknown_vehicle": 1,
        "replayed": 1,
        "vehicle_limit": 0,
        "rate_limited": 0,
    }
    assert sum(gate.counts.values()) == len(inputs)


def test_rejected_packets_do_not_move_the_baseline() -> None:
    # A forged packet with a far-ahead number must not lock the real vehicle out.
    gate = PacketFilter(key=SAMPLE_KEY)
    assert gate.accept(pose(10, key=SAMPLE_KEY)) is not None
    assert gate.accept(pose(1_000_000, key=b"forger-key-0123456789")) is None
    assert gate.accept(pose(1_000_000)) is None
    assert gate.accept(pose(11, key=SAMPLE_KEY)) is not None
    assert gate.last_seq(7) == 11


def test_forget_lets_a_restarted_sender_back_in() -> None:
    gate = PacketFilter()
    assert gate.accept(pose(5000)) is not None
    assert gate.accept(pose(0)) is None
    gate.forget(7)
    assert gate.accept(pose(0)) is not None
    assert gate.last_seq(7) == 0


def test_resync_after_silence_uses_the_callers_clock() -> None:
    gate = PacketFilter(resync_after_s=2.0)
    assert gate.accept(pose(5000), now=100.0) is not None
    assert gate.accept(pose(0), now=101.5) is None  # not silent long enough: a replay
    assert gate.accept(pose(1), now=102.0) is None  # 2.0 s exactly is not "longer than"
    assert gate.accept(pose(2), now=102.5) is not None
    assert gate.resyncs == 1
    assert gate.accept(pose(1), now=102.6) is None
    assert nonzero(gate.counts) == {"accepted": 2, "replayed": 3}


def test_filter_argument_checks() -> None:
    with pytest.raises(ValueError, match="needs `now`"):
        PacketFilter(resync_after_s=1.0).accept(pose(1))
    with pytest.raises(ValueError, match="window"):
        PacketFilter(window=2**31)
    with pytest.raises(ValueError, match="window"):
        PacketFilter(window=0)
    with pytest.raises(ValueError, match="resync_after_s"):
        PacketFilter(resync_after_s=0.0)


def _write_samples() -> None:
    """Write the committed samples (run once, by hand: a changed sample is a changed wire format)."""
    DATA_DIR.mkdir(parents=True, exist_ok=True)
    for name, data in (
        ("pose_v1.bin", encode_pose(SAMPLE)),
        ("pose_v1_auth.bin", encode_pose(SAMPLE, SAMPLE_KEY)),
        ("pose_v2.bin", encode_pose(SAMPLE_V2)),
        ("pose_v2_auth.bin", encode_pose(SAMPLE_V2, SAMPLE_KEY)),
    ):
        (DATA_DIR / name).write_bytes(data)
        print(f"{DATA_DIR / name}: {len(data)} bytes", file=sys.stderr)
        for offset in range(0, len(data), 16):
            print(f"{offset:04x}: {data[offset : offset + 16].hex(' ')}")


if __name__ == "__main__":
    _write_samples()


# ---------------------------------------------------------------------------------------------------
# Streams: a restarted receiver is a newer stream, heard at once; an older stream's packets stay refused


OLD_RUN, NEW_RUN = 1_764_000_000_000_000, 1_764_000_005_000_000  # two runs' start times, µs


@pytest.mark.parametrize("key", [None, SAMPLE_KEY])
def test_a_newer_stream_is_accepted_at_its_first_packet(key: bytes | None) -> None:
    gate = PacketFilter(key=key, resync_after_s=10.0)
    for seq in range(100):
        assert gate.accept(pose(seq, key=key, stream=OLD_RUN), now=1.0 + seq / 120) is not None
    assert gate.accept(pose(0, key=key, stream=NEW_RUN), now=2.0) is not None  # 0.2 s after: no silence
    assert (gate.new_streams, gate.resyncs) == (1, 0)
    assert gate.accept(pose(1, key=key, stream=NEW_RUN), now=2.01) is not None
    assert nonzero(gate.counts) == {"accepted": 102}


def test_a_packet_of_an_older_run_is_refused_after_the_restart() -> None:
    gate = PacketFilter(key=SAMPLE_KEY, resync_after_s=10.0)
    recorded = [pose(seq, key=SAMPLE_KEY, stream=OLD_RUN) for seq in range(50)]
    for k, data in enumerate(recorded):
        assert gate.accept(data, now=k / 120) is not None
    assert gate.accept(pose(0, key=SAMPLE_KEY, stream=NEW_RUN), now=3.0) is not None
    # Replayed: any packet of the old run, even with a sequence number far ahead of the new run's.
    for data in (recorded[0], recorded[-1], pose(10_000, key=SAMPLE_KEY, stream=OLD_RUN)):
        assert gate.accept(data, now=3.1) is None
    # A forged stream identity does not pass the tag.
    forged = bytearray(pose(10_000, key=SAMPLE_KEY, stream=OLD_RUN))
    struct.pack_into("<Q", forged, 24, NEW_RUN + 1)
    assert gate.accept(bytes(with_crc_v2(bytes(forged))), now=3.2) is None
    assert nonzero(gate.counts) == {"accepted": 51, "replayed": 3, "bad_auth": 1}
    assert gate.last_seq(7) == 0


def with_crc_v2(data: bytes) -> bytes:
    """A version-2 packet with its CRC recomputed after an edit (the tag, if any, left as it was)."""
    body = data[:CRC_OFFSET_V2]
    return body + struct.pack("<I", zlib.crc32(body)) + data[PACKET_SIZE_V2:]


def test_version_1_packets_keep_todays_rules_and_rank_below_every_stream() -> None:
    gate = PacketFilter(resync_after_s=10.0)
    assert gate.accept(pose(500), now=0.0) is not None
    assert gate.accept(pose(501), now=0.1) is not None
    assert gate.accept(pose(0), now=0.2) is None  # a version-1 restart: refused until 10 s of silence
    assert gate.accept(pose(1), now=10.2) is not None
    assert gate.resyncs == 1
    assert gate.accept(pose(0, stream=0), now=10.3) is not None  # any stream is newer than none
    assert gate.accept(pose(2), now=10.4) is None  # and version 1 is then older
    assert nonzero(gate.counts) == {"accepted": 4, "replayed": 2}


def test_two_sources_alternating_are_one_conflict_a_restart_is_none() -> None:
    gate = PacketFilter(resync_after_s=10.0)
    t = 0.0
    for seq in range(20):  # a run, then its restart from another port: no conflict
        gate.accept(pose(seq, stream=OLD_RUN), now=t, source="h", peer="h:1000")
        t += 0.01
    for seq in range(20):
        assert gate.accept(pose(seq, stream=NEW_RUN), now=t, source="h", peer="h:1001") is not None
        t += 0.01
    assert gate.take_conflicts() == []
    # A third receiver with the same id, started earlier, keeps speaking: one conflict, however long.
    for seq in range(20, 60):
        assert gate.accept(pose(seq, stream=NEW_RUN), now=t, source="h", peer="h:1001") is not None
        assert gate.accept(pose(seq + 1000, stream=OLD_RUN + 1), now=t + 0.005, source="g", peer="g:2000") is None
        t += 0.01
    conflicts = gate.take_conflicts()
    assert len(conflicts) == 1
    (conflict,) = conflicts
    assert (conflict.vehicle_id, conflict.kept, conflict.other) == (
        7, Source("h:1001", NEW_RUN), Source("g:2000", OLD_RUN + 1)
    )
    text = str(conflict)
    assert text.startswith("vehicle 7 is claimed by two sources within 1 s: h:1001 (stream ")
    assert "g:2000 (stream 1764000000000001)" in text
    assert "drawing the newer stream (h:1001" in text
    assert gate.take_conflicts() == []


def test_two_version_1_sources_are_named_and_judged_by_sequence_number() -> None:
    gate = PacketFilter(resync_after_s=10.0)
    for k in range(10):
        gate.accept(pose(100 + k), now=k * 0.01, source="a", peer="a:1")
        gate.accept(pose(k), now=k * 0.01 + 0.005, source="b", peer="b:1")
    (conflict,) = gate.take_conflicts()
    assert {conflict.kept.peer, conflict.other.peer} == {"a:1", "b:1"}
    assert conflict.same_stream
    assert "sequence number" in str(conflict)
    assert gate.counts["accepted"] == 10  # a's, whose numbers are ahead: as before


def test_sources_heard_more_than_a_second_apart_are_no_conflict() -> None:
    gate = PacketFilter(resync_after_s=10.0)
    gate.accept(pose(1, stream=OLD_RUN), now=0.0, peer="a:1")
    gate.accept(pose(1, stream=NEW_RUN), now=1.5, peer="b:1")
    gate.accept(pose(2, stream=OLD_RUN), now=2.6, peer="a:1")  # b 1.5 s after a, and 1.1 s before it again
    assert gate.take_conflicts() == []
    gate.accept(pose(2, stream=NEW_RUN), now=3.0, peer="b:1")  # a 0.4 s before b: now within the second
    assert len(gate.take_conflicts()) == 1


def test_slow_sources_alternating_are_a_conflict() -> None:
    # Two receivers each sending a pose every 2 s (a loaded machine): b falls between two of a's packets,
    # within a second of the first.
    gate = PacketFilter(resync_after_s=10.0)
    gate.accept(pose(1, stream=OLD_RUN), now=0.0, peer="a:1")
    gate.accept(pose(1, stream=NEW_RUN), now=0.7, peer="b:1")
    gate.accept(pose(2, stream=OLD_RUN), now=2.0, peer="a:1")
    assert [c.other.peer for c in gate.take_conflicts()] == ["a:1"]
