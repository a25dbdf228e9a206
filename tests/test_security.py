"""No one let in: sockets only where configured, forged and replayed packets refused and counted, and no
network input anywhere near a shell, a path or ``eval``.

The socket checks look at what the kernel says a real subprocess holds (``/proc/PID/fd`` and
``/proc/PID/net/{udp,tcp}``), so they see every socket a library might open, not only ours.
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import types
import typing
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
from waiting import wait_until

from ipt.config.models import shipped_config_path
from ipt.config.receiver import DEFAULT_SEND_TARGET, load_receiver_config, parse_host_port
from ipt.protocol import CRC_OFFSET, PosePacket, QualityFlags, encode_pose
from ipt.sender.server import DEFAULT_LISTEN

REPO = Path(__file__).resolve().parent.parent
PACKAGE = REPO / "ipt"
KEY = b"ipt-security-test-key-0123456789"
TINY_ARENA = """\
projector: {width_px: 320, height_px: 288, rate_hz: 60}
screen: {width_m: 1.0, height_m: 0.9}
tag_map: {rows: 2, cols: 2, tag_size_px: 64}
modulation: {delta_l: 8, input_rate_hz: 30}
"""
START_TIMEOUT_S = 60.0


# --- what the kernel says a process holds ------------------------------------------------------------------


@dataclass(frozen=True)
class InetSocket:
    proto: str  # udp, udp6, tcp, tcp6
    local: tuple[str, int]
    remote: tuple[str, int]
    state: int  # /proc/net state: 0x0A is TCP LISTEN, 0x07 an unconnected UDP socket, 0x01 a connected one


def _address(text: str, v6: bool) -> tuple[str, int]:
    host_hex, port_hex = text.split(":")
    raw = bytes.fromhex(host_hex)
    if v6:  # four 32-bit words, each in host (little-endian) order
        raw = b"".join(raw[i : i + 4][::-1] for i in range(0, 16, 4))
        return socket.inet_ntop(socket.AF_INET6, raw), int(port_hex, 16)
    return socket.inet_ntop(socket.AF_INET, raw[::-1]), int(port_hex, 16)


def inet_sockets(pid: int) -> list[InetSocket]:
    """Every IPv4/IPv6 UDP and TCP socket that process ``pid`` has open."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:  # closed meanwhile
            continue
        if m := re.fullmatch(r"socket:\[(\d+)\]", target):
            inodes.add(int(m.group(1)))
    found = []
    for proto in ("udp", "udp6", "tcp", "tcp6"):
        table = Path(f"/proc/{pid}/net/{proto}")
        if not table.exists():
            continue
        for line in table.read_text().splitlines()[1:]:
            f = line.split()
            if int(f[9]) in inodes:
                v6 = proto.endswith("6")
                found.append(InetSocket(proto, _address(f[1], v6), _address(f[2], v6), int(f[3], 16)))
    return found


def _wait_for_line(log: Path, pattern: str, proc: subprocess.Popen[bytes], timeout_s: float) -> re.Match[str]:
    def found() -> re.Match[str] | None:
        return re.search(pattern, log.read_text(encoding="utf-8", errors="replace"))

    with contextlib.suppress(AssertionError):  # said below, with the log
        wait_until(lambda: found() or proc.poll() is not None, timeout_s)
    if (m := found()) is None:
        raise AssertionError(f"{pattern!r} not seen (exit {proc.poll()}):\n{log.read_text(errors='replace')}")
    return m


@contextmanager
def _process(cmd: list[str], log: Path, cwd: Path) -> Iterator[subprocess.Popen[bytes]]:
    """Run ``cmd`` with stderr to ``log``; on the way out SIGTERM it (and SIGKILL if it lingers)."""
    with log.open("wb") as err:
        proc = subprocess.Popen(cmd, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _sender_cmd(arena: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "ipt.sender.cli", "--config", str(arena), "--sink", "null", "--frames", "3600", *args]


@pytest.fixture
def arena(tmp_path: Path) -> Path:
    path = tmp_path / "arena.yaml"
    path.write_text(TINY_ARENA, encoding="utf-8")
    return path


# --- listeners bind only to configured addresses -------------------------------------------------------------


def _has_ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as s:
            s.bind(("::1", 0))
    except OSError:
        return False
    return True


@pytest.mark.parametrize("host", ["127.0.0.1", "::1"])
def test_sender_listens_on_the_configured_address_only(tmp_path: Path, arena: Path, host: str) -> None:
    if host == "::1" and not _has_ipv6_loopback():
        pytest.skip("no IPv6 loopback here")
    listen = f"[{host}]:0" if ":" in host else f"{host}:0"
    log = tmp_path / "sender.log"
    with _process(_sender_cmd(arena, "--listen", listen), log, tmp_path) as proc:
        m = _wait_for_line(log, r"listening for pose packets on udp (\S+):(\d+)", proc, START_TIMEOUT_S)
        sockets = inet_sockets(proc.pid)
    assert (m.group(1), int(m.group(2))) == (host, int(m.group(2)))
    assert sockets == [
        InetSocket("udp6" if ":" in host else "udp", (host, int(m.group(2))), sockets[0].remote, 0x07)
    ], "exactly one socket: the pose listener, bound to the configured address, connected to no one"
    assert sockets[0].remote[1] == 0


def test_receiver_sockets_are_connected_to_its_targets_only(tmp_path: Path) -> None:
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as target_a,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as target_b,
    ):
        target_a.bind(("127.0.0.1", 0))
        target_b.bind(("127.0.0.1", 0))
        ports = [target_a.getsockname()[1], target_b.getsockname()[1]]
        cmd = [sys.executable, "-m", "ipt.receiver.cli", "run", "--source", "sim", "--realtime", "--max-frames",
               "2400", *(a for p in ports for a in ("--send", f"127.0.0.1:{p}"))]  # fmt: skip
        log = tmp_path / "receiver.log"
        with _process(cmd, log, tmp_path) as proc:
            _wait_for_line(log, r"ipt-receiver: running: ", proc, START_TIMEOUT_S)
            sockets = inet_sockets(proc.pid)
    # One connected UDP socket per target (the kernel then delivers it datagrams from that target only),
    # bound to the loopback address, and nothing else: no wildcard socket, no TCP listener.
    assert sorted(s.remote for s in sockets) == [("127.0.0.1", p) for p in sorted(ports)], sockets
    for s in sockets:
        assert s.proto == "udp"
        assert s.local[0] == "127.0.0.1"
        assert s.state == 0x01, "connected"


def test_examples_and_defaults_use_loopback() -> None:
    loopback = {"127.0.0.1", "::1", "localhost"}
    assert DEFAULT_LISTEN[0] == "127.0.0.1"
    assert parse_host_port(DEFAULT_SEND_TARGET)[0] in loopback
    shipped = load_receiver_config(shipped_config_path("receiver.yaml"))
    assert {host for host, _ in shipped.send_targets} <= loopback
    raw = yaml.safe_load(shipped_config_path("receiver.yaml").read_text(encoding="utf-8"))
    assert raw["send"] == ["127.0.0.1:9870"]
    help_text = subprocess.run(
        [sys.executable, "-m", "ipt.sender.cli", "--help"], capture_output=True, text=True, timeout=60, check=True
    ).stdout
    assert "default 127.0.0.1:9870" in help_text


# --- with a key: forged and replayed packets are refused, each counted ------------------------------------------


def _pose(vehicle: int, seq: int) -> PosePacket:
    return PosePacket(vehicle, seq, 1_000 * seq, (0.1, 0.2, 1.0), (0.0, 1.0, 0.0, 0.0), num_tags=4)


def _tampered(data: bytes) -> bytes:
    """``data`` with its x position changed and its CRC made right again: only the tag can tell."""
    buf = bytearray(data)
    struct.pack_into("<d", buf, 24, 0.5)
    struct.pack_into("<I", buf, CRC_OFFSET, zlib.crc32(bytes(buf[:CRC_OFFSET])))
    return bytes(buf)


def test_authenticated_sender_refuses_and_counts_forged_and_replayed_packets(tmp_path: Path, arena: Path) -> None:
    key_file = tmp_path / "key"
    key_file.write_bytes(KEY + b"\n")
    key_file.chmod(0o600)  # a key file others can read is refused
    datagrams = [
        (encode_pose(_pose(1, 10), KEY), "accepted"),
        (encode_pose(_pose(1, 10), KEY), "replayed"),  # the same datagram again
        (encode_pose(_pose(1, 9), KEY), "replayed"),  # an older one
        (encode_pose(_pose(1, 11)), "unauthenticated"),  # no tag
        (encode_pose(_pose(1, 12), b"not-the-shared-key-0123456789"), "bad_auth"),
        (_tampered(encode_pose(_pose(1, 13), KEY)), "bad_auth"),
        (encode_pose(_pose(1, 10 + 2**31), KEY), "replayed"),  # outside the window: as good as behind
        (encode_pose(_pose(1, 14), KEY), "accepted"),  # the refusals did not move the baseline
        (encode_pose(_pose(1, 14), KEY), "replayed"),
        (encode_pose(_pose(2, 0), KEY), "accepted"),
        (encode_pose(_pose(3, 1), KEY), "unknown_vehicle"),  # not in --vehicles
        (b"IPTL\x01\x01" + bytes(10), "malformed"),
    ]
    expected: dict[str, int] = {}
    for _, outcome in datagrams:
        expected[outcome] = expected.get(outcome, 0) + 1
    log = tmp_path / "sender.log"
    cmd = _sender_cmd(arena, "--listen", "127.0.0.1:0", "--auth-key-file", str(key_file), "--vehicles", "1", "2",
                      "--stats-every", "0.3")  # fmt: skip
    with _process(cmd, log, tmp_path) as proc:
        port = int(
            _wait_for_line(log, r"listening for pose packets on udp 127\.0\.0\.1:(\d+)", proc, START_TIMEOUT_S)[1]
        )
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            for data, _ in datagrams:
                sock.sendto(data, ("127.0.0.1", port))  # in order (loopback keeps it), 12 far below the buffer
        total = len(datagrams)
        _wait_for_line(log, rf"t=\S+ .*accepted={expected['accepted']} rejected={total - expected['accepted']}\b",
                       proc, 30)  # fmt: skip
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    text = log.read_text(encoding="utf-8")
    assert "authenticated packets only" in text
    final = text.strip().splitlines()[-1]
    assert "done:" in final, final
    counted = {k: int(v) for k, v in re.findall(r"\b(accepted|[a-z_]+)=(\d+)", final.split("packets ")[1])}
    counted.pop("rejected")
    assert {k: v for k, v in counted.items() if v} == expected, final
    assert "vehicles=2" in final, "only the two vehicles with valid packets are drawn"


# --- no network input reaches a shell, a path or eval -------------------------------------------------------------


def _python_files() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def _call_name(node: ast.Call) -> str:
    """``os.system`` for ``os.system(...)``, ``eval`` for ``eval(...)``, "" for anything fancier."""
    parts = []
    func: ast.expr = node.func
    while isinstance(func, ast.Attribute):
        parts.append(func.attr)
        func = func.value
    if isinstance(func, ast.Name):
        parts.append(func.id)
        return ".".join(reversed(parts))
    return ""


BANNED_CALLS = {
    "eval", "exec", "compile", "__import__", "input", "breakpoint", "os.system", "os.popen", "os.execv", "os.execve",
    "os.execvp", "os.execl", "os.execlp", "os.spawnv", "os.spawnl", "os.posix_spawn", "pty.spawn", "yaml.load",
    "yaml.unsafe_load", "yaml.full_load", "yaml.load_all", "pickle.loads", "pickle.load", "marshal.loads",
}  # fmt: skip
BANNED_IMPORTS = {"pickle", "marshal", "shelve", "subprocess", "pty", "code", "codeop"}
SUBPROCESS_ALLOWED: set[str] = {"receiver/detect/tagworker.py", "receiver/doctor.py"}
"""Modules (paths under ipt/) that may start processes. Add one only after checking that nothing it
runs is built from network input, and never with shell=True. ``receiver/detect/tagworker.py`` starts this
Python (``sys.executable -m ipt.receiver.detect.tagworker``) with an argument list of a descriptor number and
the detector's settings from the configuration, as JSON. ``receiver/doctor.py`` runs the fixed argument list
``timedatectl show --property=NTPSynchronized --value`` (no input of any kind in it)."""


def test_no_shell_eval_or_unsafe_deserialisation_in_the_package() -> None:
    problems = []
    for path in _python_files():
        rel = str(path.relative_to(PACKAGE))
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call):
                name = _call_name(node)
                if name in BANNED_CALLS:
                    problems.append(f"{rel}:{node.lineno}: {name}()")
                if any(k.arg == "shell" and not (isinstance(k.value, ast.Constant) and not k.value.value)
                       for k in node.keywords):  # fmt: skip
                    problems.append(f"{rel}:{node.lineno}: shell=...")
                if name == "importlib.import_module":  # a module name may only be chosen inside a fixed package
                    arg = node.args[0] if node.args else None
                    fixed = isinstance(arg, ast.Constant) or (
                        isinstance(arg, ast.JoinedStr)
                        and isinstance(arg.values[0], ast.Constant)
                        and str(arg.values[0].value).endswith(".")
                    )
                    if not fixed:
                        problems.append(f"{rel}:{node.lineno}: import_module of a free name")
            elif isinstance(node, ast.Import | ast.ImportFrom):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                for name in names:
                    top = name.split(".")[0]
                    if top in BANNED_IMPORTS and not (top == "subprocess" and rel in SUBPROCESS_ALLOWED):
                        problems.append(f"{rel}:{node.lineno}: import {name}")
    assert problems == []


def test_the_scan_finds_what_it_looks_for(tmp_path: Path) -> None:
    code = "import subprocess\nsubprocess.run(cmd, shell=True)\neval(x)\nos.system(y)\nyaml.load(z)\n"
    tree = ast.parse(code)
    calls = [_call_name(n) for n in ast.walk(tree) if isinstance(n, ast.Call)]
    assert {"eval", "os.system", "yaml.load"} <= set(calls) & BANNED_CALLS
    assert "subprocess" in BANNED_IMPORTS
    assert len(_python_files()) > 20


# The modules a datagram passes through, from the socket to the overlay.
NETWORK_PATH = ["protocol.py", "ratelimit.py", "sender/server.py", "sender/overlay.py", "receiver/outputs/udp.py"]
FILE_AND_PROCESS_NAMES = {
    "open", "Path", "PurePath", "os.remove", "os.unlink", "os.rename", "os.replace", "os.open", "os.makedirs",
    "os.mkdir", "os.rmdir", "os.chmod", "os.chown", "os.symlink", "os.link", "os.truncate", "shutil.rmtree",
    "shutil.copy", "shutil.move", "importlib.import_module", "getattr", "setattr",
}  # fmt: skip


@pytest.mark.parametrize("module", NETWORK_PATH)
def test_the_network_path_touches_no_files_and_names_nothing(module: str) -> None:
    tree = ast.parse((PACKAGE / module).read_text(encoding="utf-8"))
    found = [
        f"{module}:{n.lineno}: {_call_name(n)}"
        for n in ast.walk(tree)
        if isinstance(n, ast.Call)
        and _call_name(n) in FILE_AND_PROCESS_NAMES
        and not (_call_name(n) in {"getattr", "setattr"} and isinstance(n.args[1], ast.Constant))
    ]
    # getattr with a literal name is an optional-method check. protocol.py also reads PosePacket fields by
    # a fixed list of names (its own attributes, never from a packet's bytes). Nothing else on this path
    # may open a file or look up a name it was given.
    allowed = {"protocol.py": {"getattr"}}.get(module, set())
    assert [f for f in found if f.rsplit(": ", 1)[1] not in allowed] == []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            assert not {n.split(".")[0] for n in names} & {"pathlib", "shutil", "tempfile", "importlib"}, module


def test_a_datagram_can_only_carry_numbers() -> None:
    # What leaves decode_pose is all the network can say: integers, floats and flags (or nothing: a
    # version-1 packet has no stream id). No string, no bytes, no path: nothing that could name a file, a
    # module or a command.
    hints = typing.get_type_hints(PosePacket)
    allowed = {int, float, QualityFlags, type(None)}
    for f in dataclasses.fields(PosePacket):
        hint = hints[f.name]
        composite = typing.get_origin(hint) in (tuple, types.UnionType, typing.Union)
        leaves = set(typing.get_args(hint)) if composite else {hint}
        assert leaves <= allowed, (f.name, hint)
