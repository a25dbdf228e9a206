"""Bad input of every kind: only the reader's own error comes out, and its message names file and problem.

These complement the property tests of tests/test_protocol.py (packets) and tests/test_config.py
(arena and camera_info YAML data): here are the inputs those do not reach — what PyYAML and json do
with raw text (tags, dates, 5000-digit numbers, nesting thousands deep, non-UTF-8 bytes), the receiver
config and the layout reader, NUL characters in file names, the packet filter's bookkeeping over whole
streams, and a smoke run of benchmarks/fuzz.py (the 10^5-case run is that script, see docs/reliability.md).
"""

from __future__ import annotations

import importlib.util
import json
import random
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ipt.config.camera_info import CameraInfoError, load_camera_info
from ipt.config.models import ArenaConfig, ConfigError, PipelineConfig, load_arena_config, load_yaml_model
from ipt.config.receiver import (
    ReceiverConfig,
    load_receiver_config,
    parse_host_port,
    parse_source,
    read_auth_key,
)
from ipt.errors import IptError
from ipt.fileio import WriteError, read_text_file, write_text_atomic
from ipt.protocol import PacketFilter, PosePacket, Rejection, encode_pose, seq_newer
from ipt.tagmap import TagMapError, export_map, grid_tag_map, load_layout

REPO = Path(__file__).resolve().parent.parent
FUZZ_SCRIPT = REPO / "benchmarks" / "fuzz.py"
KEY = b"ipt-test-key-0123456789abcdef"

PROPERTY = settings(
    database=None, max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
"""Modest example counts: the suite stays quick; benchmarks/fuzz.py is the long run."""

Loader = Callable[[Path], object]

SMALL_ARENA = ArenaConfig.model_validate(
    {"projector": {"width_px": 640, "height_px": 480}, "screen": {"width_m": 1.0, "height_m": 0.75},
     "tag_map": {"rows": 2, "cols": 3, "tag_size_px": 64}}
)  # fmt: skip

# Every YAML reader with the only error it may raise.
YAML_READERS: list[tuple[str, Loader, type[IptError]]] = [
    ("arena", load_arena_config, ConfigError),
    ("pipeline", lambda p: load_yaml_model(p, PipelineConfig), ConfigError),
    ("receiver", load_receiver_config, ConfigError),
    ("camera_info", load_camera_info, CameraInfoError),
]
ALL_READERS: list[tuple[str, Loader, type[IptError]]] = [*YAML_READERS, ("layout", load_layout, TagMapError)]


def _outcome(loader: Loader, error: type[IptError], path: Path) -> str | None:
    """The message of ``error`` if ``loader`` raised it (checked to start with the path), None if it loaded."""
    try:
        loader(path)
    except error as exc:
        message = str(exc)
        assert message.startswith(f"{path}: "), message
        assert len(message) > len(f"{path}: ") + 3, message
        return message
    return None


# --- what PyYAML and json raise besides their own errors (found by benchmarks/fuzz.py) -------------------

DEEP = 5000
YAML_TRAPS = [
    ("date", "x: 2001-13-45\n", "month must be in 1..12"),
    ("bool_tag", "x: !!bool maybe\n", "maybe"),
    ("empty_int_tag", "x: !!int\n", "a value cannot be read"),
    ("bad_timestamp_tag", "x: !!timestamp x\n", "a value cannot be read"),
    ("bad_float_tag", "x: !!float abc\n", "abc"),
    ("timezone", "x: 2001-12-14t21:59:43.10-25:00\n", "a value cannot be read"),
    ("huge_integer", "x: " + "9" * 5000 + "\n", "4300 digits"),
    ("deep_list", "x: " + "[" * DEEP + "]" * DEEP + "\n", "nested too deeply"),
    ("deep_map", "x: " + "{a: " * DEEP + "1" + "}" * DEEP + "\n", "nested too deeply"),
    ("deep_block", "".join("  " * i + "-\n" for i in range(600)), "nested too deeply"),
]


@pytest.mark.parametrize(("name", "loader", "error"), YAML_READERS, ids=[r[0] for r in YAML_READERS])
@pytest.mark.parametrize(("trap", "text", "fragment"), YAML_TRAPS, ids=[t[0] for t in YAML_TRAPS])
def test_yaml_traps_are_the_readers_own_error(
    tmp_path: Path, name: str, loader: Loader, error: type[IptError], trap: str, text: str, fragment: str
) -> None:
    path = tmp_path / f"{trap}.yaml"
    path.write_text(text, encoding="utf-8")
    message = _outcome(loader, error, path)
    assert message is not None
    assert fragment in message, message
    assert len(message) < 500, "the message quotes the problem, not the whole value"


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("[" * DEEP + "]" * DEEP, "nested too deeply"),
        ('{"tags": ' + '{"a": ' * DEEP + "1" + "}" * DEEP + "}", "nested too deeply"),
        ('{"projector": {"width_px": ' + "9" * 5000 + ', "height_px": 480}, "tags": []}', "too many digits"),
        ('{"projector": {"width_px": 100000, "height_px": 480}, "tags": [{"id": 0}]}', "1..16384"),
    ],
)
def test_json_traps_are_tag_map_errors(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "layout.json"
    path.write_text(text, encoding="utf-8")
    message = _outcome(load_layout, TagMapError, path)
    assert message is not None
    assert fragment in message, message


def test_a_flood_of_problems_is_summed_up(tmp_path: Path) -> None:
    path = tmp_path / "typos.yaml"
    path.write_text("".join(f"key{i}: {i}\n" for i in range(5000)), encoding="utf-8")
    message = _outcome(load_arena_config, ConfigError, path)
    assert message is not None
    assert "key0: unknown key" in message
    assert "key11: unknown key" in message
    assert "key12: unknown key" not in message
    assert message.endswith("... and 4988 more")


def test_a_huge_value_is_not_quoted_whole(tmp_path: Path) -> None:
    path = tmp_path / "huge.yaml"
    path.write_text("tag_map: {tag_size_px: " + "9" * 4000 + "}\n", encoding="utf-8")
    message = _outcome(load_arena_config, ConfigError, path)
    assert message is not None
    assert "tag_size_px must be a multiple of 8" in message
    assert len(message) < len(str(path)) + 250


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("image_width: '" + "a" * 5000 + "'\n", "image_width: expected a positive integer"),
        ("image_width: 64\nimage_height: 48\ndistortion_model: " + "b" * 5000 + "\n", "is not supported"),
        ("".join(f"extra{i}: {i}\n" for i in range(3000)), "and 2992 more"),
    ],
)
def test_camera_info_messages_quote_bad_values_briefly(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "camera.yaml"
    path.write_text(text, encoding="utf-8")
    message = _outcome(load_camera_info, CameraInfoError, path)
    assert message is not None
    assert fragment in message
    assert len(message) < len(str(path)) + 600, message


# --- file names with NUL characters (a YAML string can hold one) ----------------------------------------


@pytest.mark.parametrize("field", ["arena", "camera", "auth_key_file"])
def test_nul_in_a_receiver_path_is_a_config_error(tmp_path: Path, field: str) -> None:
    data = {"arena": "arena.yaml", "camera": "camera.yaml", field: "a\0b.yaml"}
    path = tmp_path / "receiver.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    message = _outcome(load_receiver_config, ConfigError, path)
    assert message is not None
    assert f"{field}:" in message
    assert "NUL" in message


def test_nul_in_a_video_source_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="NUL"):
        parse_source("video:a\0b.mkv")


@pytest.mark.parametrize(("name", "loader", "error"), ALL_READERS, ids=[r[0] for r in ALL_READERS])
def test_nul_in_a_file_name_is_the_readers_own_error(
    tmp_path: Path, name: str, loader: Loader, error: type[IptError]
) -> None:
    with pytest.raises(error, match="NUL"):
        loader(tmp_path / "a\0b")


def test_nul_in_a_key_or_text_file_name_is_the_callers_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="NUL"):
        read_auth_key(tmp_path / "a\0b")
    with pytest.raises(LookupError, match="NUL"):
        read_text_file(tmp_path / "a\0b", LookupError, "a file")


# --- writing the map where it cannot go --------------------------------------------------------------------


@pytest.mark.parametrize("where", ["image_in_missing_folder", "image_is_folder", "layout_is_folder"])
def test_export_to_an_impossible_path_is_a_tag_map_error(tmp_path: Path, where: str) -> None:
    folder = tmp_path / "folder"
    folder.mkdir()
    image, layout = tmp_path / "map.png", tmp_path / "layout.json"
    if where == "image_in_missing_folder":
        image = tmp_path / "missing" / "map.png"
    elif where == "image_is_folder":
        image = folder
    else:
        layout = folder
    bad = layout if where == "layout_is_folder" else image
    with pytest.raises(TagMapError, match="cannot write") as info:
        export_map(grid_tag_map(SMALL_ARENA), image, layout)
    assert str(info.value).startswith(f"{bad}: ")
    assert not [p for p in tmp_path.rglob(".*partial*")], "no temporary file is left"


@pytest.mark.parametrize("where", ["missing_folder", "folder_in_the_way", "nul"])
def test_an_output_that_cannot_be_written_is_one_error_for_the_user_and_an_oserror(tmp_path: Path, where: str) -> None:
    (tmp_path / "folder").mkdir()
    target = {"missing_folder": tmp_path / "no" / "out.txt", "folder_in_the_way": tmp_path / "folder",
              "nul": tmp_path / "a\0b"}[where]  # fmt: skip
    with pytest.raises(WriteError) as info:
        write_text_atomic(target, "text")
    assert isinstance(info.value, IptError)
    assert isinstance(info.value, OSError), "callers that catch OSError still do"
    assert str(info.value).startswith(f"{target}: cannot write (")
    assert list((tmp_path / "folder").iterdir()) == []
    assert [p.name for p in tmp_path.iterdir()] == ["folder"], "no temporary file is left"


# --- properties: arbitrary bytes and text into every reader ---------------------------------------------------


@PROPERTY
@given(data=st.binary(max_size=600))
def test_arbitrary_bytes_only_raise_the_readers_own_error(tmp_path: Path, data: bytes) -> None:
    for name, loader, error in ALL_READERS:
        path = tmp_path / f"{name}.input"
        path.write_bytes(data)
        _outcome(loader, error, path)


_YAML_BITS = [
    "projector:", "tag_map:", "arena:", "camera:", "send:", "source:", "image_width:", "camera_matrix:", "data:",
    "rows: 3", "cols: 3", " ", "  ", "\n", "\n  ", "- ", ": ", "{", "}", "[", "]", ",", "&a ", "*a", "*b", "!!int",
    "!!bool", "!!float", "!!timestamp", "!!binary", "!!set", "!!str", "!!python/object:os.system", "? ", "<<: ",
    "2001-13-45", "2001-02-03", "1:20", "0x1f", "0o7", "1_0", ".inf", ".nan", "-1e999", "~", "yes", "'a'", '"\\0"',
    '"\\uD800"', "|", ">", "#", "%YAML 1.1\n", "---\n", "...\n", "\t", "9" * 4400, "é", "\u2028", "\x85",
]  # fmt: skip


@PROPERTY
@given(bits=st.lists(st.sampled_from(_YAML_BITS), max_size=25))
def test_yaml_token_soup_only_raises_the_readers_own_error(tmp_path: Path, bits: list[str]) -> None:
    text = "".join(bits)
    for name, loader, error in YAML_READERS:
        path = tmp_path / f"{name}.yaml"
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
        _outcome(loader, error, path)


_SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(["sim", "video:x.mkv", "device:0", "device:1000", "127.0.0.1:9870", "[::1]:1", "h:0", "a\0b"]),
)
_RECEIVER_KEYS = st.sampled_from(
    [*ReceiverConfig.model_fields, "demodulation", "detector", "pose", "threads", "min_tags", "pairing", "x"]
)
_RECEIVER_DATA = st.dictionaries(
    _RECEIVER_KEYS,
    st.recursive(
        _SCALARS,
        lambda children: st.one_of(
            st.lists(children, max_size=4), st.dictionaries(_RECEIVER_KEYS, children, max_size=4)
        ),
        max_leaves=12,
    ),
    max_size=8,
)


@PROPERTY
@given(data=_RECEIVER_DATA, with_required=st.booleans())
def test_receiver_config_data_only_raises_config_errors(
    tmp_path: Path, data: dict[str, Any], with_required: bool
) -> None:
    if with_required:
        data = {"arena": "arena.yaml", "camera": "camera.yaml", **data}
    path = tmp_path / "receiver.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    if _outcome(load_receiver_config, ConfigError, path) is not None:
        return
    cfg = load_receiver_config(path)
    # A config that loads is one the daemon can use: its parsed views work and its paths are absolute.
    spec = cfg.source_spec
    assert parse_source(str(spec)) == spec
    assert all(1 <= port <= 65535 for _, port in cfg.send_targets)
    assert cfg.arena.is_absolute()
    assert cfg.camera.is_absolute()


_LAYOUT_KEYS = st.sampled_from(["projector", "tags", "width_px", "height_px", "id", "corners_px", "corners_m", "x"])
_JSON_DATA = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-(2**40), 2**40), st.floats(), st.text(max_size=6)),
    lambda children: st.one_of(st.lists(children, max_size=5), st.dictionaries(_LAYOUT_KEYS, children, max_size=5)),
    max_leaves=40,
)


@PROPERTY
@given(data=_JSON_DATA, mangle=st.integers(0, 3))
def test_layout_data_only_raises_tag_map_errors(tmp_path: Path, data: Any, mangle: int) -> None:
    layout = grid_tag_map(SMALL_ARENA).layout_dict()
    # Put the arbitrary value somewhere in an otherwise valid layout, or use it whole.
    if mangle == 0:
        doc = data
    elif mangle == 1:
        doc = {**layout, "projector": data}
    elif mangle == 2:
        doc = {**layout, "tags": [*layout["tags"][:2], data]}
    else:
        doc = {**layout, "tags": [{**layout["tags"][0], "corners_px": data}]}
    path = tmp_path / "layout.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    if _outcome(load_layout, TagMapError, path) is None:
        tm = load_layout(path)
        assert 0 < tm.width_px <= 16384
        assert len({t.tag_id for t in tm.tags}) == len(tm.tags)


# --- properties: the small parsers and the key file --------------------------------------------------------------


@PROPERTY
@given(text=st.one_of(st.text(max_size=30), st.from_regex(r"\[?[0-9a-z.:]{0,12}\]?:[0-9]{0,6}", fullmatch=True)))
def test_host_port_parses_or_says_why(text: str) -> None:
    try:
        host, port = parse_host_port(text)
    except ValueError as exc:
        message = str(exc)
    else:
        message = ""
    if message:
        assert repr(text) in message or "port" in message
        return
    assert 1 <= port <= 65535
    assert host
    shown = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    assert parse_host_port(shown) == (host, port)


@PROPERTY
@given(text=st.one_of(st.text(max_size=20), st.from_regex(r"(sim|video|device):?.{0,8}", fullmatch=True)))
def test_source_parses_or_says_why(text: str) -> None:
    try:
        spec = parse_source(text)
    except ValueError:
        return  # refused (with a ValueError and nothing else)
    assert parse_source(str(spec)) == spec


@PROPERTY
@given(content=st.binary(max_size=40))
def test_key_file_is_its_bytes_less_one_newline_or_a_config_error(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "key"
    path.write_bytes(content)
    path.chmod(0o600)  # a key file others can read is refused
    expected = content[:-2] if content.endswith(b"\r\n") else content[:-1] if content.endswith(b"\n") else content
    if len(expected) < 16:
        with pytest.raises(ConfigError, match=r"at least 16"):
            read_auth_key(path)
    else:
        assert read_auth_key(path) == expected


# --- properties: the packet filter over whole streams ---------------------------------------------------------

Datagram = tuple[int, int, str]  # vehicle id, sequence number, how it is sent


def _datagram(vehicle: int, seq: int, how: str) -> bytes:
    packet = PosePacket(vehicle, seq, seq, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    if how == "keyed":
        return encode_pose(packet, KEY)
    if how == "other_key":
        return encode_pose(packet, b"another-key-0123456789")
    if how == "plain":
        return encode_pose(packet)
    data = bytearray(encode_pose(packet, KEY))
    data[-1] ^= 1  # a tampered tag
    return bytes(data)


_STREAM = st.lists(
    st.tuples(
        st.integers(0, 3),
        st.one_of(st.integers(0, 12), st.integers(2**32 - 4, 2**32 - 1), st.integers(0, 2**32 - 1)),
        st.sampled_from(["keyed", "keyed", "keyed", "plain", "other_key", "tampered"]),
    ),
    max_size=60,
)


@PROPERTY
@given(stream=_STREAM, window=st.sampled_from([1, 16, 2**31 - 1]), allowed=st.sampled_from([None, [0, 1]]))
def test_packet_filter_lets_no_one_in_and_counts_every_datagram(
    stream: list[Datagram], window: int, allowed: list[int] | None
) -> None:
    gate = PacketFilter(key=KEY, vehicle_ids=allowed, window=window)
    last: dict[int, int] = {}
    for i, (vehicle, seq, how) in enumerate(stream, start=1):
        data = _datagram(vehicle, seq, how)
        packet = gate.accept(data)
        assert sum(gate.counts.values()) == i, "one count per datagram"
        if packet is None:
            continue
        # Only correctly keyed packets of allowed vehicles, each strictly newer than the last accepted.
        assert how == "keyed"
        assert allowed is None or vehicle in allowed
        if vehicle in last:  # so never the same datagram twice in a row
            assert seq_newer(seq, last[vehicle], window)
        last[vehicle] = seq
        assert gate.last_seq(vehicle) == seq
    forged = sum(1 for _, _, how in stream if how != "keyed")
    rejected_forged = sum(gate.counts[r.value] for r in (Rejection.UNAUTHENTICATED, Rejection.BAD_AUTH))
    assert rejected_forged == forged


# --- the fuzz script itself ----------------------------------------------------------------------------------


def _fuzz_module() -> ModuleType:
    spec = importlib.util.spec_from_file_location("ipt_fuzz_script", FUZZ_SCRIPT)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_fuzz_harness_reports_an_unexpected_exception_with_a_reproducer(tmp_path: Path) -> None:
    fuzz = _fuzz_module()

    def fragile(data: bytes, path: Path) -> object:
        if data.startswith(b"b"):
            raise KeyError("boom")  # a bug: not the allowed error
        if data.startswith(b"a"):
            raise ConfigError(f"{path}: a problem")
        if data.startswith(b"c"):
            raise ConfigError("no file name")  # the allowed error, but a bad message
        return data

    target = fuzz.Target("fragile", ConfigError, ".yaml", lambda r: bytes([r.choice(b"abcd")]), fragile)
    result = fuzz.run_target(target, 200, 0, tmp_path, tmp_path / "out", 5.0)
    assert result["cases"] == 200
    assert set(result["outcomes"]) == {"valid", "ConfigError", "unexpected KeyError"}
    kinds = {f["kind"].split(" at ")[0]: f for f in result["findings"]}
    assert set(kinds) == {"KeyError", "ConfigError"}
    repro = Path(kinds["KeyError"]["reproducer"])
    assert repro.read_bytes() == b"b"
    note = json.loads(repro.with_suffix(".json").read_text())
    assert "KeyError: 'boom'" in note["traceback"]
    assert "--replay" in note["replay"]
    assert kinds["ConfigError"]["problem"] == "message does not start with the file name"


def test_fuzz_mutations_are_reproducible_and_varied() -> None:
    fuzz = _fuzz_module()
    targets = fuzz.build_targets(random.Random(0))
    for target in targets.values():
        first = [target.make(random.Random(5)) for _ in range(3)]
        assert first == [target.make(random.Random(5)) for _ in range(3)]
        rng = random.Random(1)
        inputs = {target.make(rng) for _ in range(200)}
        assert len(inputs) > 150, target.name


def test_fuzz_script_short_run_finds_nothing(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(FUZZ_SCRIPT), "--cases", "150", "--seed", "11", "--out", str(tmp_path / "found")],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = [json.loads(line) for line in proc.stdout.splitlines()]
    results, summary = lines[:-1], lines[-1]["summary"]
    assert [r["target"] for r in results] == ["decode_pose", "arena", "receiver", "camera_info", "layout"]
    for r in results:
        assert r["cases"] == 150
        assert sum(r["outcomes"].values()) == 150
        assert r["findings"] == []
        # The mutator reaches both sides: some inputs are still valid, most are refused for many reasons.
        assert r["outcomes"].get("valid", 0) > 0, r
        assert r["outcomes"].get(r["allowed_error"], 0) > 75, r
        assert r["distinct_messages"] >= 8, r
    assert summary["findings"] == 0
    assert not (tmp_path / "found").exists()
