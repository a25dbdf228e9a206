"""Every command line, every file argument, every way it can be wrong: one clear line, exit code 2.

The matrix: for each of ``ipt`` (map export/check, sim, eval, demo), ``ipt-receiver`` (replay, run) and
``ipt-sender``, and for each file it takes, a path that does not exist, a folder, an empty file and a
file of the wrong kind (another of our formats, binary junk, text where a video or image belongs); then
outputs that cannot be written and flags with wrong values. tests/test_cli.py, test_sender.py,
test_daemon.py and test_eval.py hold the cases they already cover (a missing or empty arena for map
export, a missing camera for replay, an unknown flag, a bad listen address, ...); they are not repeated.

"One clear line" means: exit code 2, no traceback, exactly one ``PROG...: error: ...`` line on stderr,
it is the last line, it holds the words that name the file and the problem, and every other stderr
line is the program's own (no library log noise). All subprocesses run at the start, a few at a time,
so the matrix costs seconds, not minutes.
"""

from __future__ import annotations

import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from ipt.config.camera_info import CameraInfo, save_camera_info
from ipt.config.models import ArenaConfig
from ipt.tagmap import grid_tag_map

MODULES = {"ipt": "ipt.cli", "ipt-receiver": "ipt.receiver.cli", "ipt-sender": "ipt.sender.cli"}
TIMEOUT_S = 90.0

TINY_ARENA: dict[str, Any] = {
    "projector": {"width_px": 320, "height_px": 288, "rate_hz": 60},
    "screen": {"width_m": 1.0, "height_m": 0.9},
    "tag_map": {"rows": 2, "cols": 2, "tag_size_px": 64},
    "modulation": {"delta_l": 8, "input_rate_hz": 30},
}
CAMERA = CameraInfo(width_px=64, height_px=48, fx_px=60.0, fy_px=60.0, cx_px=31.5, cy_px=23.5, name="bad_input")


@dataclass(frozen=True)
class Case:
    id: str
    argv: tuple[str, ...]
    """Program name, then its arguments; ``{z}`` stands for the folder of prepared files."""
    fragments: tuple[str, ...]
    """Words the error line must hold: usually the file's name and the problem."""
    xfail: str | None = None
    """Why this case is known to fail (a bug in a module this test does not own), or None."""


def _c(id_: str, argv: str, *fragments: str, xfail: str | None = None) -> Case:
    return Case(id_, tuple(argv.split()), fragments, xfail)


# Bounded runs for the cases that would otherwise start working: --frames, --max-frames, --seconds.
SENDER = "ipt-sender --sink null --frames 2 --listen 127.0.0.1:0 --config {z}/arena.yaml"
RUN = "ipt-receiver run --max-frames 2 --send 127.0.0.1:9 --arena {z}/arena.yaml --camera {z}/camera.yaml"
REPLAY = "ipt-receiver replay --config {z}/arena.yaml --camera {z}/camera.yaml --fps 120"
SIM = "ipt sim --seconds 0.02 --config {z}/arena.yaml"
EVAL = "ipt eval --truth {z}/truth.tum --poses {z}/truth.tum"

# fmt: off
CASES = [
    # --- ipt map export: the arena file (missing and empty are in test_cli.py) and both outputs
    _c("map-export-config-folder", "ipt map export --config {z}/folder --image {z}/o.png --layout {z}/o.json",
       "folder", "is a directory"),
    _c("map-export-config-binary", "ipt map export --config {z}/binary.yaml --image {z}/o.png --layout {z}/o.json",
       "binary.yaml", "not a text file"),
    _c("map-export-config-camera", "ipt map export --config {z}/camera.yaml --image {z}/o.png --layout {z}/o.json",
       "camera.yaml", "image_width: unknown key"),
    _c("map-export-image-no-folder", "ipt map export --config {z}/arena.yaml --image {z}/none/m.png --layout "
       "{z}/o.json", "none/m.png", "cannot write", "No such file"),
    _c("map-export-image-is-folder", "ipt map export --config {z}/arena.yaml --image {z}/folder --layout {z}/o.json",
       "folder", "cannot write", "Is a directory"),
    _c("map-export-layout-is-folder", "ipt map export --config {z}/arena.yaml --image {z}/o.png --layout {z}/folder",
       "folder", "cannot write"),
    # --- ipt map export: an arena whose landing pad leaves the screen or has tags too small to decode
    _c("map-export-pad-off-screen", "ipt map export --config {z}/pad-off.yaml --image {z}/o.png --layout {z}/o.json",
       "pad-off.yaml", "landing pad 'edge'", "off the screen"),
    _c("map-export-pad-small-tags", "ipt map export --config {z}/pad-bits.yaml --image {z}/o.png --layout "
       "{z}/o.json", "pad-bits.yaml", "6 projector px per bit"),
    _c("map-export-grid-small-tags", "ipt map export --config {z}/grid-bits.yaml --image {z}/o.png --layout "
       "{z}/o.json", "grid-bits.yaml", "7 projector px per bit"),
    # --- ipt map check: a layout whose tags overlap, repeat an id, are too small or leave the screen
    _c("map-check-layout-overlap", "ipt map check --layout {z}/overlap.json", "overlap.json", "tags 0 and 1 overlap"),
    _c("map-check-layout-duplicate", "ipt map check --layout {z}/duplicate.json", "duplicate.json",
       "duplicate id 0"),
    _c("map-check-layout-small-bits", "ipt map check --layout {z}/small-bits.json", "small-bits.json",
       "tag 2 has 7.0 projector px per bit"),
    _c("map-check-layout-off-screen", "ipt map check --layout {z}/off-screen.json", "off-screen.json",
       "tag 3", "off the 320x288 projector image"),
    # --- ipt map check: the layout and the image
    _c("map-check-layout-missing", "ipt map check --layout {z}/missing.json", "missing.json", "no such file"),
    _c("map-check-layout-folder", "ipt map check --layout {z}/folder", "folder", "is a directory"),
    _c("map-check-layout-empty", "ipt map check --layout {z}/empty.json", "empty.json", "not valid JSON"),
    _c("map-check-layout-yaml", "ipt map check --layout {z}/arena.yaml", "arena.yaml", "not valid JSON"),
    _c("map-check-layout-binary", "ipt map check --layout {z}/binary.yaml", "binary.yaml", "not a text file"),
    _c("map-check-layout-deep", "ipt map check --layout {z}/deep.json", "deep.json", "nested too deeply"),
    _c("map-check-image-missing", "ipt map check --layout {z}/layout.json --image {z}/missing.png",
       "missing.png", "no such file"),
    _c("map-check-image-folder", "ipt map check --layout {z}/layout.json --image {z}/folder", "folder",
       "is a directory, expected an image"),
    _c("map-check-image-empty", "ipt map check --layout {z}/layout.json --image {z}/empty.png",
       "empty.png", "not an image"),
    _c("map-bad-action", "ipt map frobnicate", "frobnicate", "invalid choice"),
    # --- ipt sim: arena, sim settings, content, output folder, flags
    _c("sim-config-missing", "ipt sim --out {z}/s1 --config {z}/missing.yaml", "missing.yaml", "no such file"),
    _c("sim-config-folder", "ipt sim --out {z}/s2 --config {z}/folder", "folder", "is a directory"),
    _c("sim-config-empty", "ipt sim --out {z}/s3 --config {z}/empty.yaml", "empty.yaml", "empty"),
    _c("sim-config-camera", "ipt sim --out {z}/s4 --config {z}/camera.yaml", "camera.yaml", "unknown key"),
    _c("sim-settings-missing", f"{SIM} --out {{z}}/s5 --sim-config {{z}}/missing.yaml", "missing.yaml", "no such file"),
    _c("sim-settings-empty", f"{SIM} --out {{z}}/s6 --sim-config {{z}}/empty.yaml", "empty.yaml", "empty"),
    _c("sim-settings-arena", f"{SIM} --out {{z}}/s7 --sim-config {{z}}/arena.yaml", "arena.yaml", "unknown key"),
    _c("sim-settings-yaml-date", f"{SIM} --out {{z}}/s8 --sim-config {{z}}/date.yaml", "date.yaml",
       "month must be in 1..12"),
    _c("sim-content-missing", f"{SIM} --out {{z}}/s9 --content {{z}}/missing.mkv", "missing.mkv", "no such file"),
    _c("sim-content-folder", f"{SIM} --out {{z}}/s10 --content {{z}}/folder", "folder", "holds no images"),
    _c("sim-content-empty", f"{SIM} --out {{z}}/s11 --content {{z}}/empty.mkv", "empty.mkv", "not a video"),
    _c("sim-content-fake-png", f"{SIM} --out {{z}}/s12 --content {{z}}/fake.png", "fake.png", "not an image"),
    _c("sim-out-is-a-file", f"{SIM} --out {{z}}/file.txt", "file.txt", "cannot create"),
    _c("sim-seconds-text", f"{SIM} --out {{z}}/s13 --seconds soon", "--seconds", "invalid float"),
    _c("sim-seconds-nan", f"{SIM} --out {{z}}/s14 --seconds nan", "--seconds"),
    # --- ipt eval: both trajectories and the outputs
    _c("eval-truth-missing", "ipt eval --truth {z}/missing.tum --poses {z}/truth.tum", "missing.tum", "no such file"),
    _c("eval-truth-folder", "ipt eval --truth {z}/folder --poses {z}/truth.tum", "folder", "is a directory"),
    _c("eval-truth-empty", "ipt eval --truth {z}/empty.tum --poses {z}/truth.tum", "empty.tum", "no poses"),
    _c("eval-truth-yaml", "ipt eval --truth {z}/arena.yaml --poses {z}/truth.tum", "arena.yaml", "expected 8 fields"),
    _c("eval-poses-binary", "ipt eval --truth {z}/truth.tum --poses {z}/binary.yaml", "binary.yaml", "not a text file"),
    _c("eval-plot-no-folder", f"{EVAL} --plot {{z}}/none/p.png", "none/p.png", "cannot write"),
    _c("eval-json-is-folder", f"{EVAL} --json {{z}}/folder", "folder", "cannot write"),
    _c("eval-max-dt-text", f"{EVAL} --max-dt x", "--max-dt", "invalid float"),
    # --- ipt demo: the arena and the results folder (it runs a closed loop: the errors come first)
    _c("demo-config-missing", "ipt demo --seconds 0.05 --config {z}/missing.yaml", "missing.yaml", "no such file"),
    _c("demo-config-folder", "ipt demo --seconds 0.05 --config {z}/folder", "folder", "is a directory"),
    _c("demo-config-empty", "ipt demo --seconds 0.05 --config {z}/empty.yaml", "empty.yaml", "empty"),
    _c("demo-config-camera", "ipt demo --seconds 0.05 --config {z}/camera.yaml", "camera.yaml", "unknown key"),
    _c("demo-out-is-a-file", "ipt demo --seconds 0.05 --out {z}/file.txt", "file.txt", "cannot create"),
    _c("demo-seconds-nan", "ipt demo --seconds nan", "--seconds", "nan"),
    # --- ipt-receiver replay: arena, camera, recording, output, flags (missing camera/video: test_cli.py)
    _c("replay-config-folder", "ipt-receiver replay --config {z}/folder --camera {z}/camera.yaml --video {z}/frames "
       "--fps 120 --output {z}/r.tum", "folder", "is a directory"),
    _c("replay-config-camera", "ipt-receiver replay --config {z}/camera.yaml --camera {z}/camera.yaml --video "
       "{z}/frames --fps 120 --output {z}/r.tum", "camera.yaml", "unknown key"),
    _c("replay-camera-folder", f"{REPLAY} --camera {{z}}/folder --video {{z}}/frames --output {{z}}/r.tum",
       "folder", "is a directory"),
    _c("replay-camera-empty", f"{REPLAY} --camera {{z}}/empty.yaml --video {{z}}/frames --output {{z}}/r.tum",
       "empty.yaml", "empty"),
    _c("replay-camera-binary", f"{REPLAY} --camera {{z}}/binary.yaml --video {{z}}/frames --output {{z}}/r.tum",
       "binary.yaml", "not a text file"),
    _c("replay-camera-huge-int", f"{REPLAY} --camera {{z}}/huge.yaml --video {{z}}/frames --output {{z}}/r.tum",
       "huge.yaml", "4300 digits"),
    _c("replay-video-folder", f"{REPLAY} --video {{z}}/folder --output {{z}}/r.tum", "folder", "holds no images"),
    _c("replay-video-empty", f"{REPLAY} --video {{z}}/empty.mkv --output {{z}}/r.tum", "empty.mkv", "not a video"),
    _c("replay-video-fake-png", f"{REPLAY} --video {{z}}/fake.png --output {{z}}/r.tum", "fake.png"),
    _c("replay-output-no-folder", f"{REPLAY} --video {{z}}/frames --output {{z}}/none/r.tum",
       "none/r.tum", "cannot write"),
    _c("replay-output-is-folder", f"{REPLAY} --video {{z}}/frames --output {{z}}/folder", "folder", "cannot write"),
    _c("replay-profile-bogus", f"{REPLAY} --video {{z}}/frames --output {{z}}/r.tum --profile fast",
       "--profile", "invalid choice"),
    _c("replay-fps-text", f"{REPLAY} --video {{z}}/frames --output {{z}}/r.tum --fps fast", "--fps", "invalid float"),
    _c("replay-fps-nan", "ipt-receiver replay --config {z}/arena.yaml --camera {z}/camera.yaml --video {z}/frames "
       "--output {z}/r.tum --fps nan", "--fps"),
    # --- ipt-receiver run: its config and every file and flag it overrides
    _c("run-config-missing", "ipt-receiver run --config {z}/missing.yaml", "missing.yaml", "no such file"),
    _c("run-config-folder", "ipt-receiver run --config {z}/folder", "folder", "is a directory"),
    _c("run-config-empty", "ipt-receiver run --config {z}/empty.yaml", "empty.yaml", "empty"),
    _c("run-config-arena", "ipt-receiver run --config {z}/arena.yaml", "arena.yaml", "missing key", "unknown key"),
    _c("run-config-binary", "ipt-receiver run --config {z}/binary.yaml", "binary.yaml", "not a text file"),
    _c("run-config-nul-path", "ipt-receiver run --max-frames 2 --config {z}/nul-path.yaml", "nul-path.yaml", "NUL"),
    _c("run-config-bool-tag", "ipt-receiver run --config {z}/bool-tag.yaml", "bool-tag.yaml", "cannot be read"),
    _c("run-key-folder", "ipt-receiver run --max-frames 2 --config {z}/key-folder.yaml", "folder", "key file"),
    _c("run-key-missing", "ipt-receiver run --max-frames 2 --config {z}/key-missing.yaml", "missing.key", "key file"),
    _c("run-key-empty", "ipt-receiver run --max-frames 2 --config {z}/key-empty.yaml", "empty.key", "0 bytes"),
    _c("run-arena-missing", f"{RUN} --arena {{z}}/missing.yaml", "missing.yaml", "no such file"),
    _c("run-arena-folder", f"{RUN} --arena {{z}}/folder", "folder", "is a directory"),
    _c("run-arena-camera", f"{RUN} --arena {{z}}/camera.yaml", "camera.yaml", "unknown key"),
    _c("run-camera-missing", f"{RUN} --camera {{z}}/missing.yaml", "missing.yaml", "no such file"),
    _c("run-camera-empty", f"{RUN} --camera {{z}}/empty.yaml", "empty.yaml", "empty"),
    _c("run-camera-arena", f"{RUN} --camera {{z}}/arena.yaml", "arena.yaml", "camera_info"),
    _c("run-source-missing", f"{RUN} --source video:{{z}}/missing.mkv", "missing.mkv", "no such file"),
    _c("run-source-folder", f"{RUN} --source video:{{z}}/folder", "folder", "holds no images"),
    _c("run-source-empty", f"{RUN} --source video:{{z}}/empty.mkv", "empty.mkv", "not a video"),
    _c("run-source-text", f"{RUN} --source video:{{z}}/text.mkv", "text.mkv"),
    _c("run-source-bogus", f"{RUN} --source camera0", "source", "source must be sim, video:PATH"),
    _c("run-send-port-0", f"{RUN} --send 127.0.0.1:0", "send", "port 0"),
    _c("run-vehicle-too-big", f"{RUN} --vehicle-id 70000", "vehicle_id", "65535"),
    _c("run-fps-negative", f"{RUN} --fps -1", "--fps", "frame rate of 1 to 1000 Hz"),
    _c("run-max-frames-zero", "ipt-receiver run --max-frames 0", "--max-frames", "positive integer"),
    _c("run-bogus-flag", "ipt-receiver run --frobnicate", "--frobnicate"),
    _c("receiver-no-command", "ipt-receiver", "COMMAND"),
    # --- ipt-sender: arena, content, key, output, flags (short key, bad --listen: test_sender.py)
    _c("sender-config-missing", "ipt-sender --sink null --frames 2 --config {z}/missing.yaml", "missing.yaml",
       "no such file"),
    _c("sender-config-folder", "ipt-sender --sink null --frames 2 --config {z}/folder", "folder", "is a directory"),
    _c("sender-config-empty", "ipt-sender --sink null --frames 2 --config {z}/empty.yaml", "empty.yaml", "empty"),
    _c("sender-config-camera", "ipt-sender --sink null --frames 2 --config {z}/camera.yaml", "camera.yaml",
       "unknown key"),
    _c("sender-config-deep", "ipt-sender --sink null --frames 2 --config {z}/deep.yaml", "deep.yaml",
       "nested too deeply"),
    _c("sender-video-missing", f"{SENDER} --video {{z}}/missing.mkv", "missing.mkv", "no such file"),
    _c("sender-video-folder", f"{SENDER} --video {{z}}/folder", "folder", "holds no images"),
    _c("sender-video-empty", f"{SENDER} --video {{z}}/empty.mkv", "empty.mkv", "not a video"),
    _c("sender-video-yaml", f"{SENDER} --video {{z}}/arena.yaml", "arena.yaml", "not a video"),
    _c("sender-image-missing", f"{SENDER} --image {{z}}/missing.png", "missing.png", "no such file"),
    _c("sender-image-folder", f"{SENDER} --image {{z}}/folder", "folder", "is a directory, expected an image"),
    _c("sender-image-empty", f"{SENDER} --image {{z}}/empty.png", "empty.png", "not an image"),
    _c("sender-image-fake-png", f"{SENDER} --image {{z}}/fake.png", "fake.png", "not an image"),
    _c("sender-key-missing", f"{SENDER} --auth-key-file {{z}}/missing.key", "missing.key", "key file"),
    _c("sender-key-folder", f"{SENDER} --auth-key-file {{z}}/folder", "folder", "key file"),
    _c("sender-key-empty", f"{SENDER} --auth-key-file {{z}}/empty.key", "0 bytes"),
    _c("sender-output-folder", "ipt-sender --config {z}/arena.yaml --sink file --frames 2 --output {z}/folder",
       "folder", "cannot write"),
    _c("sender-output-no-folder", "ipt-sender --config {z}/arena.yaml --sink file --frames 2 --output "
       "{z}/none/v.mkv", "none/v.mkv", "cannot create"),
    _c("sender-listen-port-too-big", f"{SENDER} --listen 127.0.0.1:70000", "70000", "HOST:PORT"),
    _c("sender-listen-not-an-address", f"{SENDER} --listen 999.1.1.1:5", "999.1.1.1", "cannot listen"),
    _c("sender-frames-zero", "ipt-sender --sink null --frames 0", "--frames"),
    _c("sender-sink-bogus", "ipt-sender --sink screen", "--sink", "invalid choice"),
    _c("sender-bogus-flag", "ipt-sender --frobnicate", "--frobnicate"),
    _c("sender-vehicles-out-of-range", f"{SENDER} --vehicles 70000", "--vehicles"),
]
# fmt: on

QUICK = {
    "map-export-image-no-folder", "map-check-layout-deep", "map-check-layout-binary", "sim-settings-yaml-date",
    "eval-truth-folder", "eval-json-is-folder", "demo-config-camera", "replay-output-is-folder",
    "replay-camera-huge-int", "run-config-nul-path", "run-config-bool-tag", "run-key-folder", "run-source-empty",
    "sender-config-deep", "sender-image-fake-png", "sender-key-missing", "map-check-layout-overlap",
    "map-export-pad-off-screen",
}  # fmt: skip
"""One case per program and kind of mistake, for a quick run (``-m "not slow"``); the rest are marked slow."""


def _prepare(z: Path) -> None:
    """The files the cases point at."""
    (z / "folder").mkdir()
    (z / "file.txt").write_text("a file where a folder belongs\n", encoding="utf-8")
    for name in ("empty.yaml", "empty.json", "empty.tum", "empty.mkv", "empty.png", "empty.key"):
        (z / name).write_bytes(b"")
    (z / "binary.yaml").write_bytes(bytes(range(256)) * 4)
    (z / "fake.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(200)))
    (z / "text.mkv").write_text("not a video\n" * 50, encoding="utf-8")
    (z / "arena.yaml").write_text(yaml.safe_dump(TINY_ARENA), encoding="utf-8")
    save_camera_info(CAMERA, z / "camera.yaml")
    layout = grid_tag_map(ArenaConfig.model_validate(TINY_ARENA)).layout_dict()
    (z / "layout.json").write_text(json.dumps(layout), encoding="utf-8")
    _prepare_maps(z, layout)
    (z / "deep.json").write_text("[" * 100_000 + "]" * 100_000, encoding="utf-8")
    (z / "deep.yaml").write_text("projector: " + "[" * 5000 + "]" * 5000 + "\n", encoding="utf-8")
    (z / "date.yaml").write_text("seed: 2024-13-01\n", encoding="utf-8")
    camera = yaml.safe_load((z / "camera.yaml").read_text(encoding="utf-8"))
    camera_text = yaml.safe_dump(camera).replace("image_width: 64", "image_width: " + "6" * 5000)
    (z / "huge.yaml").write_text(camera_text, encoding="utf-8")
    (z / "truth.tum").write_text("".join(f"{t} 0 0 1 0 0 0 1\n" for t in range(5)), encoding="utf-8")
    frames = z / "frames"
    frames.mkdir()
    for i in range(2):
        cv2.imwrite(str(frames / f"f{i}.png"), np.full((48, 64, 3), 100, np.uint8))
    base = "arena: arena.yaml\ncamera: camera.yaml\nsend: ['127.0.0.1:9']\n"
    (z / "nul-path.yaml").write_text('arena: "arena\\0.yaml"\ncamera: camera.yaml\n', encoding="utf-8")
    (z / "bool-tag.yaml").write_text(base + "realtime: !!bool maybe\n", encoding="utf-8")
    (z / "key-folder.yaml").write_text(base + "auth_key_file: folder\n", encoding="utf-8")
    (z / "key-missing.yaml").write_text(base + "auth_key_file: missing.key\n", encoding="utf-8")
    (z / "key-empty.yaml").write_text(base + "auth_key_file: empty.key\n", encoding="utf-8")


def _prepare_maps(z: Path, layout: dict[str, Any]) -> None:
    """Arenas and layouts that draw no usable map."""

    def moved(tag: dict[str, Any], du: float, dv: float, scale: float = 1.0) -> dict[str, Any]:
        c = np.asarray(tag["corners_px"], np.float64)
        c = c.mean(axis=0) + (c - c.mean(axis=0)) * scale + (du, dv)
        return {**tag, "corners_px": c.tolist()}

    tags = layout["tags"]
    bad = {
        "overlap": [tags[0], moved(tags[1], -150.0, 0.0), *tags[2:]],
        "duplicate": [tags[0], {**tags[1], "id": 0}, *tags[2:]],
        "small-bits": [*tags[:2], moved(tags[2], 0.0, 0.0, 56 / 64), tags[3]],
        "off-screen": [*tags[:3], moved(tags[3], 60.0, 0.0)],
    }
    for name, t in bad.items():
        (z / f"{name}.json").write_text(json.dumps({**layout, "tags": t}), encoding="utf-8")
    pad = {"name": "edge", "centre_m": [0.45, 0.0], "size_m": 0.3}
    arenas = {
        "pad-off": {"pads": [pad]},
        "pad-bits": {"pads": [{**pad, "centre_m": [0.0, 0.0], "tag_size_px": 48}]},
        "grid-bits": {"tag_size_px": 56},
    }
    for name, changes in arenas.items():
        arena = {**TINY_ARENA, "tag_map": {**TINY_ARENA["tag_map"], **changes}}
        (z / f"{name}.yaml").write_text(yaml.safe_dump(arena), encoding="utf-8")


def _run(case: Case, z: Path) -> subprocess.CompletedProcess[str]:
    prog, *args = case.argv
    cmd = [sys.executable, "-m", MODULES[prog], *(a.replace("{z}", str(z)) for a in args)]
    return subprocess.run(
        cmd, cwd=z, capture_output=True, text=True, timeout=TIMEOUT_S, check=False, stdin=subprocess.DEVNULL
    )


Results = tuple[Path, dict[str, subprocess.CompletedProcess[str]]]


@pytest.fixture(scope="module")
def results(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Results:
    """Every selected case (``-m "not slow"`` leaves the quick ones) run once, three at a time."""
    selected = [
        item.callspec.params["case"]
        for item in request.session.items
        if isinstance(item, pytest.Function) and item.originalname == "test_bad_input_gives_one_clear_line_and_exit_2"
    ]
    z = tmp_path_factory.mktemp("bad-input")
    _prepare(z)
    with ThreadPoolExecutor(max_workers=3) as pool:
        done = dict(zip([c.id for c in selected], pool.map(lambda c: _run(c, z), selected), strict=True))
    return z, done


def _marks(case: Case) -> list[pytest.MarkDecorator]:
    if case.xfail:
        return [pytest.mark.xfail(strict=True, reason=case.xfail), pytest.mark.slow]
    return [] if case.id in QUICK else [pytest.mark.slow]


def test_case_ids_are_unique() -> None:
    ids = [c.id for c in CASES]
    assert len(ids) == len(set(ids))
    assert set(ids) >= QUICK


@pytest.mark.parametrize(
    "case",
    [pytest.param(c, id=c.id, marks=_marks(c)) for c in CASES],
)
def test_bad_input_gives_one_clear_line_and_exit_2(case: Case, results: Results) -> None:
    z, done = results
    proc = done[case.id]
    prog = case.argv[0]
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    lines = proc.stderr.splitlines()
    errors = [line for line in lines if ": error: " in line]
    assert len(errors) == 1, proc.stderr
    assert lines[-1] == errors[0], "the error is the last word"
    noise = [line for line in lines if not line.startswith(prog)]
    assert noise == [], "only the program's own lines"
    line = errors[0].replace(str(z) + "/", "")
    for fragment in case.fragments:
        assert fragment in line, (fragment, line)


def test_failed_outputs_leave_no_partial_files(results: Results) -> None:
    z, done = results
    assert sorted(p.name for p in z.rglob("*partial*")) == []
    assert list((z / "folder").iterdir()) == []
    assert not (z / "none").exists()
    assert not (z / "r.tum").exists(), "no replay succeeded"
    assert done, "at least one case ran"
