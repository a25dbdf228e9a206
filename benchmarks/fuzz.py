"""Fuzz every reader of untrusted input: only the module's own error comes out, and it names the problem.

Targets (each gets ``--cases`` inputs):

=============  =====================================================  ==================
target         what is called                                         allowed error
=============  =====================================================  ==================
decode_pose    ``ipt.protocol.decode_pose`` (with and without a key),  ``ProtocolError``
               and the same datagrams through one ``PacketFilter``
arena          ``ipt.config.models.load_yaml_model(path, ArenaConfig)``  ``ConfigError``
receiver       ``ipt.config.receiver.load_receiver_config``            ``ConfigError``
camera_info    ``ipt.config.camera_info.load_camera_info``             ``CameraInfoError``
layout         ``ipt.tagmap.load_layout``                              ``TagMapError``
=============  =====================================================  ==================

Inputs are made by a structure-aware mutator of our own (seeded, so a run is reproducible): it starts
from valid inputs (packets of random poses, the shipped YAML files, an exported layout) and

- for files: parses them and drops, renames, adds or swaps keys, puts wrong types, huge and tiny
  numbers, NaN and infinities, long and odd strings (NUL, right-to-left marks) in their place, nests
  values thousands deep, injects YAML tags and scalars PyYAML resolves to dates or numbers
  (``2001-13-45``, ``!!bool maybe``, an integer of 5000 digits), then writes them out again;
- for packets: sets a field to an extreme value and recomputes the CRC (and the authentication tag),
  so that the checks behind them are reached; changes the header, flags and length;
- for both: flips, inserts, deletes and duplicates bytes and lines (duplicate keys, non-UTF-8 bytes,
  a UTF-16 or BOM-prefixed encoding), splices two inputs, and sends plain random bytes.

An outcome is either a value (the input was valid) or an exception. The allowed error must carry a
message that names the problem: for a file it starts with ``<path>: `` followed by words, it is at most
``MAX_MESSAGE_CHARS`` long; a valid packet must re-encode to the same bytes. Anything else (another
exception type, a bad message, a case slower than ``--case-timeout``) is a finding: its input is saved
under ``--out`` with a JSON note (exception, traceback, how to replay it) once per distinct place.
``--replay FILE --target T`` runs one saved input again and shows the traceback.

Prints one JSON object per target as it finishes, then a summary line; exit status 1 if anything was
found. On one (shared) core a YAML target runs at 100-200 cases/s and the packet target at 30,000/s: a
run of 10^5 cases per target takes about 45 minutes. The default ``--case-timeout`` of 20 s leaves
room for the slowest legitimate case (a 20,000-deep flow sequence costs PyYAML about a second of CPU).

    ./dev run python benchmarks/fuzz.py --cases 100000
    ./dev run python benchmarks/fuzz.py --cases 2000 --targets decode_pose,layout --seed 3
    ./dev run python benchmarks/fuzz.py --replay results/fuzz-.../arena-ValueError-1.bin --target arena
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import math
import os
import random
import re
import signal
import struct
import sys
import tempfile
import time
import traceback
import zlib
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

import yaml

from ipt.config.camera_info import CameraInfo, CameraInfoError, load_camera_info
from ipt.config.models import ArenaConfig, ConfigError, load_yaml_model, shipped_config_path
from ipt.config.receiver import load_receiver_config
from ipt.protocol import (
    AUTH_PACKET_SIZE,
    CRC_OFFSET,
    PACKET_SIZE,
    PacketFilter,
    PosePacket,
    ProtocolError,
    QualityFlags,
    decode_pose,
    encode_pose,
)
from ipt.tagmap import TagMap, TagMapError, grid_tag_map, load_layout

KEY = b"ipt-fuzz-key-0123456789abcdef"
"""The shared key of the authenticated packets and of the keyed decodes."""

MAX_MESSAGE_CHARS = 4000
"""Longest acceptable error message: a message is one line a person reads."""

# --- interesting values -------------------------------------------------------------------------------

_HUGE_DIGITS = "9" * 5000  # past Python's int-from-string limit (4300 digits)
_INTERESTING: list[Any] = [
    None, True, False, 0, -1, 1, 7, 8, 16, 65535, 65536, 2**31 - 1, 2**31, 2**32, 2**63 - 1, 2**63, -(2**63),
    2**64, 10**30, -(10**30), 10**400, 0.0, -0.0, 0.5, -0.5, 1e-300, 5e-324, 1e308, -1e308, math.inf,
    -math.inf, math.nan, "", "0", "1", "x", "sim", "video:", "device:", "device:99999", "video:/dev/zero",
    "127.0.0.1:0", "[::1]:9870", "host:99999", "a" * 5000, "\0", "a\0b", "é", "\u202e", "\ud7ff", "\t\n",
    "tag36h11", "plumb_bob", "paper", [], {}, [0], [1.0, 2.0, 3.0], [[1], [2]], {"a": 1}, {"rows": 3},
    {"rows": 3, "cols": 3, "data": [1] * 9},
]  # fmt: skip
# Text put in place of a value after serialising: things the data model cannot express.
_YAML_TOKENS = [
    "__DEEP_LIST__", "__DEEP_MAP__", _HUGE_DIGITS, "-" + _HUGE_DIGITS, "2001-13-45", "2001-02-29",
    "2001-12-14t21:59:43.10-25:00", "!!bool maybe", "!!int", "!!int abc", "!!float abc", "!!timestamp x",
    "!!binary '@@@'", "!!set {a, b}", "!!omap [1]", "!!python/object:os.system {}",
    "!!python/name:os.system", "*nowhere", "&a [*a]", "{<<: 1}", "{? [1, 2] : 3}", "!<tag:x> 1",
    "0x1F", "0o17", "0b101", "1_000", "1:30:00", ".inf", "-.inf", ".nan", "~", "null", "yes", "off",
    "'\\x00'", '"\\0"', '"\\uDC80"', "|\n  a\n  b", ">-\n  folded", "[1, 2", "{a: 1", "\t1", "%YAML 1.1",
    "---", "...", "@x", "`x", "? ", "- - - 1",
]  # fmt: skip
_JSON_TOKENS = [
    "__DEEP_LIST__", "__DEEP_MAP__", _HUGE_DIGITS, "-" + _HUGE_DIGITS, "1e999", "-1e999", "NaN", "Infinity",
    "-Infinity", "1.5e-400", '"\\ud800"', '"\\u0000"', "[", "{", "]", "}", ",", ":", "true", "null",
    '"x"', "0.0000000000000000000001", "01", "-0", '{"a": 1, "a": 2}',
]  # fmt: skip
_BYTE_TOKENS = [b"\0", b"\xff", b"\xfe\xff", b"\xef\xbb\xbf", b"\xc3", b"\xed\xa0\x80", b"\r", b"\n", b"\t", b"\x1b["]


def _interesting(rng: random.Random) -> Any:
    """One of the interesting values, copied: the documents are edited in place."""
    return copy.deepcopy(rng.choice(_INTERESTING))


def _deep(kind: str, depth: int) -> str:
    if kind == "__DEEP_LIST__":
        return "[" * depth + "1" + "]" * depth
    return '{"a": ' * depth + "1" + "}" * depth


# --- generic byte mutations ---------------------------------------------------------------------------


def mutate_bytes(rng: random.Random, data: bytes, pool: list[bytes]) -> bytes:
    """1..4 random byte-level edits of ``data`` (``pool``: other inputs to splice with)."""
    buf = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(9)
        n = len(buf)
        if op == 0 and n:  # flip one bit
            buf[rng.randrange(n)] ^= 1 << rng.randrange(8)
        elif op == 1 and n:  # an interesting byte
            buf[rng.randrange(n)] = rng.choice([0x00, 0xFF, 0x7F, 0x80, 0x0A, 0x22, 0x27, 0x5B, 0x7B, 0x3A, 0x2D, 0x20])
        elif op == 2:  # insert random bytes (half the time printable ones, which keep a text file text)
            at = rng.randrange(n + 1)
            low, high = (32, 127) if rng.random() < 0.5 else (0, 256)
            buf[at:at] = bytes(rng.randrange(low, high) for _ in range(rng.randint(1, 8)))
        elif op == 3 and n:  # delete a span
            at = rng.randrange(n)
            del buf[at : at + rng.randint(1, 32)]
        elif op == 4 and n:  # duplicate a span (in a text file: a repeated key or line)
            at = rng.randrange(n)
            chunk = buf[at : at + rng.randint(1, 64)]
            to = rng.randrange(n + 1)
            buf[to:to] = chunk
        elif op == 5 and n:  # truncate
            del buf[rng.randrange(n) :]
        elif op == 6:  # an odd byte sequence (invalid UTF-8, BOM, control characters)
            at = rng.randrange(n + 1)
            buf[at:at] = rng.choice(_BYTE_TOKENS)
        elif op == 7 and pool:  # splice with another input
            other = rng.choice(pool)
            buf = buf[: rng.randrange(n + 1)] + other[rng.randrange(len(other) + 1) :]
        elif op == 8 and n:  # duplicate a whole line
            lines = bytes(buf).split(b"\n")
            i = rng.randrange(len(lines))
            lines.insert(rng.randrange(len(lines) + 1), lines[i])
            buf = bytearray(b"\n".join(lines))
    return bytes(buf)


def random_bytes(rng: random.Random) -> bytes:
    return bytes(rng.randrange(256) for _ in range(rng.choice([0, 1, 4, 16, 64, 256, 1024])))


# --- structure-aware mutation of parsed documents -----------------------------------------------------


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def _get(node: Any, path: tuple[Any, ...]) -> Any:
    for k in path:
        node = node[k]
    return node


def _typo(rng: random.Random, key: str) -> str:
    if not key:
        return "x"
    i = rng.randrange(len(key))
    return rng.choice([key[:i] + key[i + 1 :], key[:i] + "x" + key[i:], key.upper(), key + " ", "_" + key])


def mutate_tree(rng: random.Random, doc: Any, tokens: list[str]) -> tuple[Any, list[str]]:
    """1..3 structural edits of a copy of ``doc``. Returns it and the raw text tokens to splice in: a
    value ``"__TOKEN_<i>__"`` in the tree is to be replaced by ``tokens[i]`` after serialising."""
    doc = json.loads(json.dumps(doc))  # a deep copy of plain data
    raw: list[str] = []
    for _ in range(rng.randint(1, 3)):
        paths = _paths(doc)
        path = rng.choice(paths)
        parent = _get(doc, path[:-1]) if path else None
        key = path[-1] if path else None
        op = rng.randrange(8)
        if parent is None:  # the document itself
            doc = rng.choice([[doc], {"x": doc}, _interesting(rng), doc])
        elif op == 0:  # drop the key or element
            del parent[key]
        elif op == 1 and isinstance(parent, dict):  # misspell the key (keeps the value)
            parent[_typo(rng, str(key))] = parent.pop(key)
        elif op == 2:  # a wrong type or an extreme value
            parent[key] = _interesting(rng)
        elif op == 3:  # raw text: a tag, a date, a huge number, deep nesting
            raw.append(rng.choice(tokens))
            parent[key] = f"__TOKEN_{len(raw) - 1}__"
        elif op == 4 and isinstance(parent, dict):  # an unknown key
            parent[rng.choice(["x", "extra", str(key) + "2", "", " "])] = _interesting(rng)
        elif op == 5:  # swap with another subtree
            other = rng.choice(paths)
            if other and other[: len(path)] != path and path[: len(other)] != other:
                o_parent = _get(doc, other[:-1])
                parent[key], o_parent[other[-1]] = o_parent[other[-1]], parent[key]
        elif op == 6:  # wrap in a container; 50 references to one value become YAML aliases
            parent[key] = rng.choice([[parent[key]], {"data": parent[key]}, [parent[key]] * 50])
            break  # no more edits: one edit of a shared value would show in all its places
        elif op == 7 and isinstance(parent[key], list) and parent[key]:  # resize a list
            factor = rng.choice([0, 2, 1000] if len(parent[key]) <= 9 else [0, 2])
            parent[key] = parent[key] * factor or parent[key][:-1]
            break  # the copies are shared: no more edits (see op 6)
    return doc, raw


def splice_tokens(text: str, raw: list[str], rng: random.Random) -> str:
    for i, token in enumerate(raw):
        if token in ("__DEEP_LIST__", "__DEEP_MAP__"):
            token = _deep(token, rng.choice([3, 50, 500, 2000, 20000]))
        # The placeholder may be quoted by the serialiser; replace it with its quotes.
        text = re.sub(rf"""(['"]?)__TOKEN_{i}__\1""", lambda _m, t=token: t, text)
    return text


def _dump_yaml(rng: random.Random, doc: Any) -> str:
    return yaml.safe_dump(doc, default_flow_style=rng.choice([False, True, None]), allow_unicode=rng.random() < 0.5)


def _dump_json(rng: random.Random, doc: Any) -> str:
    return json.dumps(doc, indent=rng.choice([None, 1]))


def _encode_text(rng: random.Random, text: str) -> bytes:
    r = rng.random()
    if r < 0.93:
        return text.encode("utf-8", "surrogatepass")
    if r < 0.96:
        return b"\xef\xbb\xbf" + text.encode("utf-8", "surrogatepass")  # a byte-order mark
    if r < 0.98:
        return text.encode("utf-16", "surrogatepass")
    return text.encode("latin-1", "replace")


def document_input(
    rng: random.Random,
    seeds: list[Any],
    seed_bytes: list[bytes],
    dump: Callable[[random.Random, Any], str],
    tokens: list[str],
) -> bytes:
    """One input for a file reader, from the parsed ``seeds`` and their file bytes ``seed_bytes``."""
    r = rng.random()
    if r < 0.05:
        return random_bytes(rng)
    if r < 0.08:  # a soup of the format's own tokens
        return " ".join(rng.choice(tokens[4:]) for _ in range(rng.randint(1, 12))).encode("utf-8", "surrogatepass")
    if r < 0.30:  # bytes of a valid file, mutated
        return mutate_bytes(rng, rng.choice(seed_bytes), seed_bytes)
    doc, raw = mutate_tree(rng, rng.choice(seeds), tokens)
    try:
        text = dump(rng, doc)
    except (ValueError, RecursionError):  # e.g. json.dumps of an int of more than 4300 digits
        text = dump(rng, rng.choice(seeds))
    data = _encode_text(rng, splice_tokens(text, raw, rng))
    if r > 0.85:  # then bytes too
        data = mutate_bytes(rng, data, seed_bytes)
    return data


# --- packets --------------------------------------------------------------------------------------------

# (offset, struct format, count) of each field after the header, from docs/protocol.md.
_FIELDS = [
    (4, "B", 1), (5, "B", 1), (6, "H", 1), (8, "H", 1), (10, "H", 1), (12, "I", 1), (16, "Q", 1),
    (24, "d", 3), (48, "d", 4), (80, "f", 3), (92, "f", 3), (104, "f", 1),
]  # fmt: skip
_FLOATS = [math.nan, math.inf, -math.inf, -0.0, 0.0, 1e308, -1e308, 5e-324, 3.4e38, 1e39, -1.0, 1.0, 1.0000001]
_INTS = [0, 1, 2, 0x7F, 0x80, 0xFF, 0xFFFF, 0x8000, 0xFFFF_FFFF, 0x8000_0000, 2**64 - 1, 2**63]


def random_packet(rng: random.Random) -> PosePacket:
    q = [rng.gauss(0, 1) for _ in range(4)]
    norm = math.sqrt(sum(v * v for v in q)) or 1.0
    return PosePacket(
        vehicle_id=rng.randrange(65536),
        seq=rng.randrange(2**32),
        capture_time_us=rng.randrange(2**64),
        position_m=tuple(rng.uniform(-10, 10) for _ in range(3)),  # type: ignore[arg-type]
        quat_wxyz=tuple(v / norm for v in q),  # type: ignore[arg-type]
        position_std_m=tuple(abs(rng.gauss(0, 0.01)) for _ in range(3)),  # type: ignore[arg-type]
        attitude_std_rad=tuple(abs(rng.gauss(0, 0.01)) for _ in range(3)),  # type: ignore[arg-type]
        num_tags=rng.randrange(90),
        reprojection_rms_px=abs(rng.gauss(0, 1)),
        flags=QualityFlags(rng.randrange(16) & ~1),
    )


def _fix_crc(buf: bytearray) -> None:
    if len(buf) >= PACKET_SIZE:
        struct.pack_into("<I", buf, CRC_OFFSET, zlib.crc32(bytes(buf[:CRC_OFFSET])))


def _fix_tag(buf: bytearray) -> bytearray:
    import hmac

    if len(buf) >= PACKET_SIZE:
        tag = hmac.new(KEY, bytes(buf[:PACKET_SIZE]), "sha256").digest()[:16]
        return buf[:PACKET_SIZE] + bytearray(tag)
    return buf


def packet_input(rng: random.Random, seeds: list[bytes]) -> bytes:
    r = rng.random()
    if r < 0.05:
        return random_bytes(rng)
    if r < 0.35:
        return mutate_bytes(rng, rng.choice(seeds), seeds)
    buf = bytearray(rng.choice(seeds))
    for _ in range(rng.randint(1, 3)):
        offset, fmt, count = rng.choice(_FIELDS)
        i = rng.randrange(count)
        size = struct.calcsize("<" + fmt)
        if fmt in "df":
            value: float | int = rng.choice(_FLOATS)
            try:
                struct.pack_into("<" + fmt, buf, offset + i * size, value)
            except OverflowError:  # 1e39 as a float32
                struct.pack_into("<" + fmt, buf, offset + i * size, math.inf)
        else:
            value = rng.choice(_INTS) & ((1 << (8 * size)) - 1)
            struct.pack_into("<" + fmt, buf, offset + i * size, value)
    if rng.random() < 0.15:  # a length the decoder must refuse or a tag that must be there
        buf = rng.choice([buf[: rng.randrange(len(buf) + 1)], buf + bytearray(16), buf[:PACKET_SIZE], buf + buf])
    if rng.random() < 0.8:
        _fix_crc(buf)
    if len(buf) == AUTH_PACKET_SIZE and rng.random() < 0.7:
        buf = _fix_tag(buf)
    return bytes(buf)


# --- targets --------------------------------------------------------------------------------------------


class _CaseTimeout(BaseException):
    """Raised by the interval timer inside a case that runs too long (a BaseException: never swallowed)."""


@dataclass
class Target:
    name: str
    error: type[Exception]
    suffix: str  # file name suffix, or "" for in-memory input
    make: Callable[[random.Random], bytes]
    call: Callable[[bytes, Path], object]
    seeds: list[bytes] = field(default_factory=list)


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


class _PacketTarget:
    """decode_pose with and without the key, checked by re-encoding; every datagram also goes through one
    long-lived PacketFilter, whose counts must add up."""

    def __init__(self) -> None:
        self.filter = PacketFilter(key=None, resync_after_s=5.0)
        self.keyed = PacketFilter(key=KEY)
        self.calls = 0
        self.now = 0.0

    def __call__(self, data: bytes, _path: Path) -> object:
        self.calls += 1
        self.now += 0.01
        self.filter.accept(data, self.now)  # never raises: rejections are counted
        self.keyed.accept(data)
        for f in (self.filter, self.keyed):
            if sum(f.counts.values()) != self.calls:
                raise AssertionError(f"PacketFilter counts {dict(f.counts)} do not add up to {self.calls}")
        key = KEY if self.calls % 2 else None
        packet = decode_pose(data, key)
        again = encode_pose(packet, key)
        if key is not None or len(data) == PACKET_SIZE:
            if again != data:
                raise AssertionError("a decoded packet does not re-encode to the same bytes")
        elif decode_pose(again) != packet:
            raise AssertionError("a decoded packet does not survive a round trip")
        return packet


def _layout_seed(tm: TagMap) -> bytes:
    return (json.dumps(tm.layout_dict(), indent=1) + "\n").encode()


def build_targets(rng: random.Random) -> dict[str, Target]:
    packets = [random_packet(rng) for _ in range(8)]
    packet_seeds = [encode_pose(p) for p in packets] + [encode_pose(p, KEY) for p in packets]

    arena_seed = shipped_config_path("arena.yaml").read_bytes()
    small_arena = (
        b"projector: {width_px: 640, height_px: 480, rate_hz: 59.94}\nscreen: {width_m: 1.0, height_m: 0.75}\n"
        b"tag_map: {rows: 3, cols: 4, tag_size_px: 64, first_id: 10}\nmodulation: {delta_l: 6, input_rate_hz: 29.97}\n"
    )
    receiver_seed = shipped_config_path("receiver.yaml").read_bytes()
    receiver_full = (
        b"arena: /etc/ipt/arena.yaml\ncamera: cam.yaml\nsource: video:flight.mkv\nfps: 120\nrealtime: true\n"
        b"vehicle_id: 7\nsend: ['127.0.0.1:9870', '[::1]:9871']\nauth_key_file: key\nstats_interval_s: 1\n"
        b"queue_size: 4\npipeline:\n  demodulation: {pairing: previous, alignment: sampled_lines, max_shift_px: 5}\n"
        b"  detector: {quad_decimate: 1.0, threads: 2}\n  pose: {min_tags: 1, max_speed_mps: null}\n"
    )
    camera_seed = shipped_config_path("camera.yaml").read_bytes()
    camera_8 = yaml.safe_dump(
        CameraInfo(800, 600, 700.0, 701.0, 399.5, 299.5, (0.1, -0.2, 0.001, 0.002, 0.3, 0.01, 0.02, 0.03)).to_ros_dict()
    ).encode()
    small_tm = grid_tag_map(ArenaConfig.model_validate(yaml.safe_load(small_arena)))
    layout_seeds = [_layout_seed(small_tm), _layout_seed(grid_tag_map(ArenaConfig()))]

    def yaml_target(name: str, error: type[Exception], seeds: list[bytes], call: Callable[[Path], object]) -> Target:
        docs = [yaml.safe_load(s) for s in seeds]
        return Target(
            name,
            error,
            ".yaml",
            lambda r: document_input(r, docs, seeds, _dump_yaml, _YAML_TOKENS),
            lambda data, path: call(_write(path, data)),
            seeds,
        )

    def load_receiver(path: Path) -> object:
        cfg = load_receiver_config(path)
        # What the daemon asks of a loaded config must work too.
        _ = (cfg.source_spec, cfg.send_targets)
        return cfg

    layout_docs = [json.loads(s) for s in layout_seeds]
    return {
        "decode_pose": Target(
            "decode_pose", ProtocolError, "", lambda r: packet_input(r, packet_seeds), _PacketTarget(), packet_seeds
        ),
        "arena": yaml_target(
            "arena", ConfigError, [arena_seed, small_arena], lambda p: load_yaml_model(p, ArenaConfig)
        ),
        "receiver": yaml_target("receiver", ConfigError, [receiver_seed, receiver_full], load_receiver),
        "camera_info": yaml_target("camera_info", CameraInfoError, [camera_seed, camera_8], load_camera_info),
        "layout": Target(
            "layout",
            TagMapError,
            ".json",
            lambda r: document_input(r, layout_docs, layout_seeds, _dump_json, _JSON_TOKENS),
            lambda data, path: load_layout(_write(path, data)),
            layout_seeds,
        ),
    }


# --- running --------------------------------------------------------------------------------------------


def _template(message: str, path: Path) -> str:
    """The kind of a message: the file name, numbers, quoted text and key paths blanked out."""
    text = message.replace(str(path), "<file>")
    text = re.sub(r"'[^']*'|\"[^\"]*\"", "'…'", text)
    text = re.sub(r"-?\d[\d.e+-]*|\b(nan|inf)\b", "N", text)
    return text[:120]


def _message_problem(target: Target, message: str, path: Path) -> str | None:
    if len(message) > MAX_MESSAGE_CHARS:
        return f"message of {len(message)} characters"
    if target.suffix:
        prefix = f"{path}: "
        if not message.startswith(prefix):
            return "message does not start with the file name"
        if len(message[len(prefix) :].strip()) < 3:
            return "message names no problem"
    elif len(message.strip()) < 3:
        return "message names no problem"
    return None


def _where(exc: BaseException) -> str:
    frames = traceback.extract_tb(exc.__traceback__)
    inner = frames[-1] if frames else None
    return f"{Path(inner.filename).name}:{inner.lineno}" if inner else "?"


def _on_alarm(_sig: int, _frame: FrameType | None) -> None:
    raise _CaseTimeout


@dataclass
class _Tally:
    outcomes: Counter[str] = field(default_factory=Counter)
    reasons: Counter[str] = field(default_factory=Counter)
    templates: Counter[str] = field(default_factory=Counter)
    findings: dict[str, dict[str, Any]] = field(default_factory=dict)
    slowest_s: float = 0.0
    slow_cases: int = 0
    """Cases that took more than a second (not findings unless over the timeout)."""


def _one_case(
    target: Target, data: bytes, path: Path, case_timeout_s: float, tally: _Tally
) -> tuple[str, BaseException] | None:
    """Run one input; count its outcome; return (problem, exception) if it is a finding."""
    t0 = time.perf_counter()
    signal.setitimer(signal.ITIMER_REAL, case_timeout_s)
    try:
        target.call(data, path)
        tally.outcomes["valid"] += 1
        return None
    except _CaseTimeout as exc:
        tally.outcomes["timeout"] += 1
        return f"took more than {case_timeout_s:g} s", exc
    except target.error as exc:
        tally.outcomes[type(exc).__name__] += 1
        message = str(exc)
        tally.templates[_template(message, path)] += 1
        if isinstance(exc, ProtocolError):
            tally.reasons[exc.reason.value] += 1
        problem = _message_problem(target, message, path)
        return None if problem is None else (problem, exc)
    except Exception as exc:  # anything else that a reader lets out is a bug
        tally.outcomes[f"unexpected {type(exc).__name__}"] += 1
        return f"unexpected {type(exc).__name__}: {str(exc)[:200]}", exc
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        elapsed = time.perf_counter() - t0
        tally.slowest_s = max(tally.slowest_s, elapsed)
        tally.slow_cases += elapsed > 1.0


def _record(
    target: Target, data: bytes, problem: str, exc: BaseException, path: Path, out: Path, tally: _Tally
) -> None:
    """Count a finding by kind (exception type and place); save the first input of each kind."""
    kind = f"{type(exc).__name__} at {_where(exc)}"
    if not problem.startswith("unexpected"):
        kind += f" ({_template(problem, path)[:60]})"
    found = tally.findings.setdefault(kind, {"kind": kind, "count": 0})
    found["count"] += 1
    if "reproducer" in found:
        return
    digest = hashlib.sha256(data).hexdigest()[:12]
    repro = out / f"{target.name}-{type(exc).__name__}-{digest}.bin"
    out.mkdir(parents=True, exist_ok=True)
    repro.write_bytes(data)
    note = {
        "target": target.name,
        "problem": problem,
        "traceback": "".join(traceback.format_exception(exc)),
        "replay": f"python benchmarks/fuzz.py --target {target.name} --replay {repro}",
    }
    repro.with_suffix(".json").write_text(json.dumps(note, indent=1) + "\n", encoding="utf-8")
    found["reproducer"] = str(repro)
    found["problem"] = problem


def run_target(target: Target, cases: int, seed: int, work: Path, out: Path, case_timeout_s: float) -> dict[str, Any]:
    """Run ``cases`` inputs of ``target``; the result as a JSON-able dict."""
    rng = random.Random(f"{seed}:{target.name}")
    path = work / f"input{target.suffix}"
    tally = _Tally()
    t_start = time.perf_counter()
    previous_handler = signal.signal(signal.SIGALRM, _on_alarm)
    try:
        for _ in range(cases):
            data = target.make(rng)
            finding = _one_case(target, data, path, case_timeout_s, tally)
            if finding is not None:
                _record(target, data, *finding, path, out, tally)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous_handler)
    seconds = time.perf_counter() - t_start
    result: dict[str, Any] = {
        "target": target.name,
        "allowed_error": target.error.__name__,
        "cases": cases,
        "seconds": round(seconds, 1),
        "cases_per_s": round(cases / seconds, 1) if seconds > 0 else None,
        "outcomes": dict(tally.outcomes.most_common()),
    }
    if tally.reasons:
        result["rejection_reasons"] = dict(tally.reasons.most_common())
    result["distinct_messages"] = len(tally.templates)
    result["top_messages"] = [f"{n} × {t}" for t, n in tally.templates.most_common(8)]
    result["slowest_case_ms"] = round(tally.slowest_s * 1e3, 1)
    result["cases_over_1s"] = tally.slow_cases
    result["findings"] = sorted(tally.findings.values(), key=lambda f: -int(f["count"]))
    return result


def replay(target: Target, file: Path, work: Path) -> int:
    data = file.read_bytes()
    try:
        value = target.call(data, work / f"input{target.suffix}")
    except target.error as exc:
        print(f"{type(exc).__name__} (allowed): {exc}")
        return 0
    print(f"valid: {value!r:.300}")
    return 0


def _uptime() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--cases", type=int, default=100_000, help="inputs per target (default 100000)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--targets", default="all", help="comma-separated subset of: decode_pose, arena, receiver, "
                   "camera_info, layout (default all)")  # fmt: skip
    p.add_argument("--out", type=Path, help="where findings are saved (default results/fuzz-<time>)")
    p.add_argument("--case-timeout", type=float, default=20.0, metavar="S", help="a slower case is a finding")
    p.add_argument("--replay", type=Path, metavar="FILE", help="run one saved input (with --target)")
    p.add_argument("--target", help="the target of --replay")
    args = p.parse_args(argv)
    out: Path = args.out or Path("results") / time.strftime("fuzz-%Y%m%d-%H%M%S")
    with tempfile.TemporaryDirectory(prefix="ipt-fuzz-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None) as tmp:
        work = Path(tmp)
        targets = build_targets(random.Random(args.seed))
        if args.replay is not None:
            if args.target not in targets:
                p.error(f"--replay needs --target, one of {', '.join(targets)}")
            return replay(targets[args.target], args.replay, work)
        names = list(targets) if args.targets == "all" else args.targets.split(",")
        unknown = [n for n in names if n not in targets]
        if unknown:
            p.error(f"unknown target(s) {', '.join(unknown)}; choose from {', '.join(targets)}")
        summary: dict[str, Any] = {"benchmark": "fuzz", "seed": args.seed, "cases_per_target": args.cases}
        summary["loadavg_before"] = _uptime()
        total_findings = 0
        t0 = time.perf_counter()
        for name in names:
            result = run_target(targets[name], args.cases, args.seed, work, out, args.case_timeout)
            total_findings += sum(int(f["count"]) for f in result["findings"])
            print(json.dumps(result), flush=True)
        summary.update(
            targets=names,
            cases=args.cases * len(names),
            findings=total_findings,
            findings_saved_in=str(out) if total_findings else None,
            seconds=round(time.perf_counter() - t0, 1),
            loadavg_after=_uptime(),
        )
        print(json.dumps({"summary": summary}), flush=True)
    return 1 if total_findings else 0


if __name__ == "__main__":
    sys.exit(main())
