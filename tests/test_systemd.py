"""The systemd units in deploy/systemd: valid for systemd, hardened, and calling the real command lines.

``systemd-analyze verify`` insists that ExecStart's program exists, and /opt/ipt/venv does not exist on
a development machine or in CI, so each unit is verified as a copy in a temporary folder whose only
change is ExecStart's program: a small script there. The other checks read the shipped files as they
are. Without ``systemd-analyze`` (CI installs the Debian ``systemd`` package) the tests that need it are
skipped, saying so.
"""

from __future__ import annotations

import ast
import ctypes
import importlib
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
UNIT_DIR = ROOT / "deploy" / "systemd"
UNITS = ("ipt-receiver.service", "ipt-sender.service")
SHIPPED_CONFIG_DIR = ROOT / "ipt" / "config"
MAX_EXPOSURE = 5.0
"""``systemd-analyze security`` rates 0 (locked down) to 10 (no sandbox); below 5 is "OK" or "MEDIUM"."""

# Settings both units must have, with their exact value (the last assignment counts, as in systemd).
COMMON_SETTINGS = {
    "Unit": {},
    "Service": {
        "User": "ipt",
        "Group": "ipt",
        "Restart": "on-failure",
        "TimeoutStopSec": "5",
        "KillSignal": "SIGTERM",
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "ProtectKernelTunables": "yes",
        "ProtectKernelModules": "yes",
        "ProtectControlGroups": "yes",
        "RestrictNamespaces": "yes",
        "LockPersonality": "yes",
        "ReadOnlyPaths": "/etc/ipt",
        "CapabilityBoundingSet": "",
        "SystemCallArchitectures": "native",
        "SystemCallFilter": "@system-service",
        "DevicePolicy": "closed",
        "ProtectClock": "yes",
        "ProtectHostname": "yes",
        "RestrictRealtime": "yes",
        "RestrictSUIDSGID": "yes",
        "UMask": "0027",
    },
}
ADDRESS_FAMILIES = {"AF_INET", "AF_INET6", "AF_UNIX"}
"""UDP pose packets, the journal and (sender) the X server; neither daemon needs netlink."""


# --- reading unit files ------------------------------------------------------------------------------

Unit = dict[str, list[tuple[str, str]]]
"""Section name -> its assignments in file order (keys may repeat, as systemd allows)."""


def _logical_lines(text: str) -> list[str]:
    """The lines of a unit file with backslash continuations joined."""
    lines: list[str] = []
    pending = ""
    for raw in text.splitlines():
        if raw.endswith("\\"):
            pending += raw[:-1] + " "
            continue
        lines.append(pending + raw)
        pending = ""
    if pending:
        lines.append(pending)
    return lines


def parse_unit(text: str) -> Unit:
    """A unit file's sections and assignments (comments and blank lines dropped)."""
    sections: Unit = {}
    current: list[tuple[str, str]] | None = None
    for line in _logical_lines(text):
        stripped = line.strip()
        if not stripped or stripped[0] in "#;":
            continue
        if stripped.startswith("[") and stripped.endswith("]"):
            current = sections.setdefault(stripped[1:-1], [])
            continue
        key, sep, value = stripped.partition("=")
        assert sep, f"not a 'Key=value' line: {line!r}"
        assert current is not None, f"a setting before the first [Section]: {line!r}"
        current.append((key.strip(), value.strip()))
    return sections


def values(unit: Unit, section: str, key: str) -> list[str]:
    """Every value assigned to ``key`` in ``section``, in file order."""
    return [v for k, v in unit.get(section, []) if k == key]


def last(unit: Unit, section: str, key: str) -> str | None:
    """The value systemd uses for a single-valued setting: the last assignment, or None."""
    found = values(unit, section, key)
    return found[-1] if found else None


def words(unit: Unit, section: str, key: str) -> set[str]:
    """The space-separated items of a list setting, over all its assignments."""
    return {w for v in values(unit, section, key) for w in v.split()}


def environment(unit: Unit) -> dict[str, str]:
    """The service's Environment= variables."""
    env: dict[str, str] = {}
    for value in values(unit, "Service", "Environment"):
        for item in shlex.split(value):
            name, _, val = item.partition("=")
            env[name] = val
    return env


def exec_start(unit: Unit) -> list[str]:
    """ExecStart's command line as words; exactly one ExecStart is expected."""
    found = values(unit, "Service", "ExecStart")
    assert len(found) == 1, f"expected one ExecStart=, found {found}"
    return shlex.split(found[0])


def load(name: str) -> Unit:
    return parse_unit((UNIT_DIR / name).read_text(encoding="utf-8"))


# --- systemd-analyze ---------------------------------------------------------------------------------


def _systemd_analyze() -> str | None:
    found = shutil.which("systemd-analyze")
    if found is None and os.access("/usr/bin/systemd-analyze", os.X_OK):
        found = "/usr/bin/systemd-analyze"
    return found


SYSTEMD_ANALYZE = _systemd_analyze()


def need_systemd_analyze() -> str:
    """The path of systemd-analyze; skips the test (saying why) when it is not installed."""
    if SYSTEMD_ANALYZE is None:
        reason = (
            "systemd-analyze is not installed (not on PATH, not /usr/bin/systemd-analyze): cannot check the "
            "unit files; install the Debian 'systemd' package (CI does)"
        )
        print(reason)
        pytest.skip(reason)
    return SYSTEMD_ANALYZE


def _run(args: list[str], cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "SYSTEMD_COLORS": "0", "SYSTEMD_PAGER": "cat", "LC_ALL": "C.UTF-8"}
    return subprocess.run(args, capture_output=True, text=True, timeout=60, env=env, cwd=cwd, check=False)


def _systemd_version(analyze: str) -> int:
    first = _run([analyze, "--version"]).stdout.splitlines()[0]
    m = re.match(r"systemd (\d+)", first)
    assert m is not None, f"unexpected 'systemd-analyze --version' output: {first!r}"
    return int(m.group(1))


def _copy_with_runnable_exec_start(name: str, folder: Path) -> Path:
    """The unit copied to ``folder`` with ExecStart's program replaced by a script there; nothing else changes."""
    text = (UNIT_DIR / name).read_text(encoding="utf-8")
    program = exec_start(parse_unit(text))[0]
    stand_in = folder / Path(program).name
    stand_in.write_text("#!/bin/sh\nexit 0\n", encoding="utf-8")
    stand_in.chmod(0o755)
    pattern = re.compile(rf"^(ExecStart(?:Pre)?=-?){re.escape(program)}(?=\s|$)", re.MULTILINE)
    copied, count = pattern.subn(lambda m: m.group(1) + str(stand_in), text)
    assert count == 1 + len(values(parse_unit(text), "Service", "ExecStartPre")), f"{name}: ExecStart= line not found"
    target = folder / name
    target.write_text(copied, encoding="utf-8")
    return target


# What systemd prints for a setting it does not know or cannot parse ("Unknown key ...", "Unknown lvalue
# ...", "Failed to parse ..., ignoring"), for a bad section, or for a program it cannot run.
VERIFY_PROBLEMS = re.compile(r"unknown (key|lvalue|section)|failed|ignoring|invalid|not executable", re.IGNORECASE)


@pytest.mark.parametrize("name", UNITS)
def test_systemd_analyze_verify_accepts_the_unit(name: str, tmp_path: Path) -> None:
    analyze = need_systemd_analyze()
    unit = _copy_with_runnable_exec_start(name, tmp_path)
    result = _run([analyze, "verify", str(unit)], cwd=tmp_path)
    print(f"$ systemd-analyze verify {name} -> exit {result.returncode}\n{result.stdout}{result.stderr}")
    problems = [line for line in result.stderr.splitlines() if VERIFY_PROBLEMS.search(line)]
    assert result.returncode == 0, f"systemd-analyze verify {name} failed:\n{result.stderr}"
    assert not problems, f"systemd-analyze verify {name} complained:\n{result.stderr}"


@pytest.mark.parametrize("name", UNITS)
def test_security_exposure_is_low(name: str) -> None:
    analyze = need_systemd_analyze()
    help_text = _run([analyze, "--help"]).stdout
    if "--offline" not in help_text:
        reason = (
            f"systemd-analyze of systemd {_systemd_version(analyze)} has no 'security --offline' "
            "(needs a newer systemd, 252 is known to have it): cannot rate the unit's sandbox"
        )
        print(reason)
        pytest.skip(reason)
    result = _run([analyze, "security", "--offline=yes", str(UNIT_DIR / name)])
    m = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?) (\w+)", result.stdout)
    assert m is not None, f"no exposure level in the output (exit {result.returncode}):\n{result.stdout}{result.stderr}"
    score, rating = float(m.group(1)), m.group(2)
    print(f"{name}: exposure {score} {rating}")
    failing = "\n".join(line for line in result.stdout.splitlines() if line.startswith("✗"))
    assert score < MAX_EXPOSURE, f"{name}: exposure {score} {rating}; not sandboxed:\n{failing}"


# --- the settings themselves -------------------------------------------------------------------------


@pytest.mark.parametrize("name", UNITS)
def test_unit_has_the_restart_policy_user_and_hardening(name: str) -> None:
    unit = load(name)
    for section, expected in COMMON_SETTINGS.items():
        for key, value in expected.items():
            assert last(unit, section, key) == value, f"{name}: [{section}] {key}= should be {value!r}"
    restart_sec = {"ipt-receiver.service": "300ms", "ipt-sender.service": "1"}[name]
    assert last(unit, "Service", "RestartSec") == restart_sec, f"{name}: back quickly after a crash"
    assert last(unit, "Service", "DynamicUser") in (None, "no"), f"{name}: the account must be the fixed user ipt"
    assert "network-online.target" in words(unit, "Unit", "After"), name
    assert "network-online.target" in words(unit, "Unit", "Wants"), name
    assert words(unit, "Service", "RestrictAddressFamilies") == ADDRESS_FAMILIES, name
    assert values(unit, "Service", "CapabilityBoundingSet") == [""], f"{name}: no capabilities at all"
    assert exec_start(unit)[0].startswith("/opt/ipt/venv/bin/"), name
    assert values(unit, "Install", "WantedBy"), f"{name}: `systemctl enable` needs an [Install] target"


def test_receiver_can_use_the_camera_and_serial_ports() -> None:
    unit = load("ipt-receiver.service")
    assert {"video", "dialout"} <= words(unit, "Service", "SupplementaryGroups")
    allowed = set(values(unit, "Service", "DeviceAllow"))
    assert "char-video4linux rw" in allowed
    for serial in ("char-ttyAMA rw", "char-ttyACM rw", "char-ttyUSB rw"):
        assert serial in allowed, f"DeviceAllow={serial} missing"
    # numba's kernels need memory made executable, also when loaded from its cache (see
    # test_kernels_run_compiled_from_the_units_cache); the unit must say so rather than forget it.
    assert last(unit, "Service", "MemoryDenyWriteExecute") == "no"
    text = (UNIT_DIR / "ipt-receiver.service").read_text(encoding="utf-8")
    assert re.search(r"^# MemoryDenyWriteExecute= is off on purpose", text, re.MULTILINE)


def test_sender_reaches_the_display_and_gpu_and_hears_the_drones() -> None:
    text = (UNIT_DIR / "ipt-sender.service").read_text(encoding="utf-8")
    unit = parse_unit(text)
    assert environment(unit).get("DISPLAY") == ":0"
    assert "char-drm rw" in values(unit, "Service", "DeviceAllow")
    assert {"video", "render"} <= words(unit, "Service", "SupplementaryGroups")
    # Left out on purpose (GL drivers may generate code); the unit must say so rather than forget it.
    assert last(unit, "Service", "MemoryDenyWriteExecute") is None
    assert re.search(r"^# MemoryDenyWriteExecute= is left out on purpose", text, re.MULTILINE)
    # Pose packets come from the drones, so the sender must not listen on loopback only (its default).
    args = exec_start(unit)
    assert "--listen" in args, "without --listen the sender only hears 127.0.0.1"
    host = args[args.index("--listen") + 1].rpartition(":")[0].strip("[]")
    assert host not in ("127.0.0.1", "localhost", "::1"), f"--listen {host} is loopback only"


@pytest.mark.parametrize("name", UNITS)
def test_every_setting_is_explained_by_a_comment(name: str) -> None:
    lines = (UNIT_DIR / name).read_text(encoding="utf-8").splitlines()
    previous = ""
    for number, line in enumerate(lines, 1):
        stripped = line.strip()
        if stripped and stripped[0] not in "#;[" and "=" in stripped:
            assert previous.startswith("#"), f"{name}:{number}: {stripped!r} has no comment above it"
        if stripped:
            previous = stripped


# --- ExecStart against the real command line ----------------------------------------------------------


def _script_module(program: str) -> str:
    """The module behind a console script of pyproject.toml, e.g. ipt-receiver -> ipt.receiver.cli."""
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["scripts"]
    name = Path(program).name
    assert name in scripts, f"{program}: not a console script of this project ({sorted(scripts)})"
    module, _, function = scripts[name].partition(":")
    if module == "ipt.launch":  # the launcher holds the stop signals, then imports the tool's own cli module
        return _launched_module(function)
    return str(module)


def _launched_module(function: str) -> str:
    """The cli module an ``ipt.launch`` entry point imports its ``main`` from, read from the launcher's source
    (importing the launcher would hold this test process's stop signals)."""
    tree = ast.parse((ROOT / "ipt" / "launch.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == function:
            for inner in ast.walk(node):
                if isinstance(inner, ast.ImportFrom) and any(a.name == "main" for a in inner.names):
                    return str(inner.module)
    raise AssertionError(f"ipt.launch.{function} imports no main")


@pytest.mark.parametrize("name", UNITS)
def test_exec_start_uses_only_real_flags(name: str) -> None:
    args = exec_start(load(name))
    module = _script_module(args[0])
    rest = args[1:]
    subcommands = []
    for word in rest:
        if word.startswith("-"):
            break
        subcommands.append(word)
    result = _run([sys.executable, "-m", module, *subcommands, "--help"], cwd=ROOT)
    assert result.returncode == 0, result.stderr
    flags = [w.split("=", 1)[0] for w in rest if w.startswith("--")]
    assert flags, f"{name}: ExecStart passes no flags"
    for flag in flags:
        assert re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", result.stdout), (
            f"{name}: {flag} is not an option of `{' '.join([Path(args[0]).name, *subcommands])}`:\n{result.stdout}"
        )
    # And the whole command line parses (choices such as --sink window included).
    parser = importlib.import_module(module).build_parser()
    parser.parse_args(rest)


@pytest.mark.parametrize("name", UNITS)
def test_exec_start_config_is_a_shipped_example(name: str) -> None:
    args = exec_start(load(name))
    config = Path(args[args.index("--config") + 1])
    assert config.parent == Path("/etc/ipt"), f"{name}: the config belongs in /etc/ipt (ReadOnlyPaths=)"
    assert (SHIPPED_CONFIG_DIR / config.name).is_file(), f"{name}: no shipped ipt/config/{config.name} to copy"


# --- MemoryDenyWriteExecute=yes does not break the receiver ----------------------------------------------

PR_SET_MDWE = 65
PR_MDWE_REFUSE_EXEC_GAIN = 1
# Sets the kernel's memory-deny-write-execute (the same rule as systemd's MemoryDenyWriteExecute=, kept
# across exec), then becomes the given command; exit 77 if the kernel (< 6.3) does not have it.
_MDWE_EXEC = f"""
import ctypes, os, sys
if ctypes.CDLL(None, use_errno=True).prctl({PR_SET_MDWE}, {PR_MDWE_REFUSE_EXEC_GAIN}, 0, 0, 0) != 0:
    sys.exit(77)
os.execv(sys.argv[1], sys.argv[1:])
"""
_WX_PROBE = "import mmap; mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)"


def _under_mdwe(*command: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return _run([sys.executable, "-c", _MDWE_EXEC, *command], cwd=cwd)


def test_receiver_runs_without_wx_memory(tmp_path: Path) -> None:
    if not sys.platform.startswith("linux") or not hasattr(ctypes.CDLL(None), "prctl"):
        pytest.skip("needs Linux prctl(PR_SET_MDWE)")
    probe = _under_mdwe(sys.executable, "-c", _WX_PROBE)
    if probe.returncode == 77:
        reason = f"the kernel ({os.uname().release}) has no PR_SET_MDWE (Linux >= 6.3): cannot try W^X here"
        print(reason)
        pytest.skip(reason)
    assert "PermissionError" in probe.stderr, f"W^X not enforced: a W+X mapping was allowed\n{probe.stderr}"

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as listener:
        listener.bind(("127.0.0.1", 0))
        port = listener.getsockname()[1]
        result = _under_mdwe(
            sys.executable,
            "-m",
            "ipt.receiver.cli",
            "run",
            "--config",
            str(SHIPPED_CONFIG_DIR / "receiver.yaml"),
            "--send",
            f"127.0.0.1:{port}",
            "--max-frames",
            "8",
            cwd=tmp_path,
        )
        listener.setblocking(False)
        packets = 0
        while True:
            try:
                listener.recv(4096)
            except BlockingIOError:
                break
            packets += 1
    print(result.stderr)
    assert result.returncode == 0, result.stderr
    assert packets > 0, f"no pose packets arrived:\n{result.stderr}"


# --- the compiled kernels under the unit, from the cache it gives them ------------------------------------

_KERNELS_LINE = re.compile(r"kernels: compiled, cache (\S+), (\d+) loaded from the cache, (\d+) compiled")
_AHEAD_LINE = re.compile(r"kernels: built ahead of time, loaded from (\S+) \(numba not needed\)$", re.MULTILINE)


def _as_the_unit_runs(args: list[str], env: dict[str, str], wx: bool, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``python -m ipt.receiver.cli ARGS`` with the unit's environment, under W^X when the unit asks for it."""
    command = [sys.executable, "-m", "ipt.receiver.cli", *args]
    if wx:
        command = [sys.executable, "-c", _MDWE_EXEC, *command]
    return subprocess.run(command, capture_output=True, text=True, timeout=600, env=env, cwd=cwd, check=False)


def test_kernels_run_compiled_from_the_units_cache(tmp_path: Path, short_flight: Path) -> None:
    """As the unit starts the receiver (its ExecStartPre, its Environment, its CacheDirectory, its W^X
    setting; no home): `ipt-receiver warm` compiles the kernels into the cache (and builds them ahead of time
    there where a C compiler is), and a new process then runs them compiled, loaded from that cache (or the
    module built ahead), compiling none. Fails when the kernels fall back to numpy."""
    unit = load("ipt-receiver.service")
    pre = [shlex.split(v.lstrip("-@:+!")) for v in values(unit, "Service", "ExecStartPre")]
    assert any(Path(c[0]).name == "ipt-receiver" and c[1:] == ["warm"] for c in pre), (
        "the unit does not run `ipt-receiver warm` before the daemon: the kernels would compile in flight"
    )
    cache_dirs = words(unit, "Service", "CacheDirectory")
    assert cache_dirs, "no CacheDirectory=: under ProtectSystem=strict and no home, numba has nowhere to cache"
    unit_env = environment(unit)
    numba_dir = Path(unit_env.get("NUMBA_CACHE_DIR", "/nonexistent"))
    assert any(numba_dir.is_relative_to(Path("/var/cache") / d) for d in cache_dirs), (
        f"NUMBA_CACHE_DIR={numba_dir} is not in the unit's CacheDirectory= (/var/cache/{cache_dirs})"
    )
    here = tmp_path / "var-cache" / numba_dir.relative_to("/var/cache")  # what systemd makes, here
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_", "XDG_"))}
    env.update(unit_env, NUMBA_CACHE_DIR=str(here), HOME="/nonexistent")
    wx = last(unit, "Service", "MemoryDenyWriteExecute") == "yes"
    if wx and _as_the_unit_runs(["--version"], env, True, tmp_path).returncode == 77:
        pytest.skip(f"the unit asks for W^X and this kernel ({os.uname().release}) has no PR_SET_MDWE")

    warm = _as_the_unit_runs(["warm"], env, wx, tmp_path)
    print(warm.stdout, warm.stderr)
    assert warm.returncode == 0, f"ipt-receiver warm failed under the unit's settings:\n{warm.stdout}{warm.stderr}"
    replay = _as_the_unit_runs(
        ["replay", "--camera", str(short_flight / "camera.yaml"), "--video", str(short_flight / "frames.mkv"),
         "--fps", "120", "--output", str(tmp_path / "poses.tum")],
        env, wx, tmp_path,
    )  # fmt: skip
    print(replay.stdout, replay.stderr[-2000:])
    assert replay.returncode == 0, replay.stderr
    if "built ahead of time into" in warm.stdout:  # a C compiler was there (kernelbuild)
        ahead = _AHEAD_LINE.search(replay.stdout)
        assert ahead is not None, f"warm built the kernels ahead, the replay did not load them:\n{replay.stdout}"
        assert Path(ahead.group(1)).is_relative_to(here), f"built kernels loaded from {ahead.group(1)}, not {here}"
        return
    found = _KERNELS_LINE.search(replay.stdout)
    assert found is not None, f"the replay's kernels are not compiled and cached:\n{replay.stdout}"
    cache, loaded, compiled = Path(found.group(1)), int(found.group(2)), int(found.group(3))
    assert cache.is_relative_to(here), f"kernels cached in {cache}, not in the unit's cache folder {here}"
    assert loaded > 0, "no kernel was loaded from the cache"
    assert compiled == 0, f"{compiled} kernel versions compiled in flight after `ipt-receiver warm`"
