"""The command-line tools as a user runs them: real subprocesses, help texts, outputs, one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from ipt.config.camera_info import CameraInfo, save_camera_info
from ipt.config.models import shipped_config_path

IPT = [sys.executable, "-m", "ipt.cli"]
RECEIVER = [sys.executable, "-m", "ipt.receiver.cli"]
CAMERA = CameraInfo(width_px=64, height_px=48, fx_px=60.0, fy_px=60.0, cx_px=31.5, cy_px=23.5, name="cli_test")


def _run(cmd: list[str], cwd: Path, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout, check=False)


def _assert_one_line_error(
    proc: subprocess.CompletedProcess[str], prog: str, *fragments: str, stdout_empty: bool = True
) -> str:
    """Exit code 2, no traceback and exactly one line on stderr: 'PROG...: error: ...' with the fragments."""
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    line = lines[0]
    assert line.startswith(prog), line
    assert ": error: " in line
    if stdout_empty:
        assert proc.stdout == ""
    for f in fragments:
        assert f in line, (f, line)
    return line


@pytest.fixture
def camera_file(tmp_path: Path) -> Path:
    path = tmp_path / "camera.yaml"
    save_camera_info(CAMERA, path)
    return path


# --- help ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("cmd", "expected"),
    [
        ([*IPT, "--help"], ["usage: ipt", "map", "sim", "eval", "demo"]),
        ([*IPT, "map", "export", "--help"], ["--image", "--layout", "--config", "MAP.png"]),
        ([*IPT, "map", "check", "--help"], ["--layout", "--image"]),
        ([*RECEIVER, "--help"], ["usage: ipt-receiver", "replay"]),
        ([*RECEIVER, "replay", "--help"], ["--camera", "--video", "--output", "--fps", "--config"]),
    ],
)
def test_help(tmp_path: Path, cmd: list[str], expected: list[str]) -> None:
    proc = _run(cmd, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    for word in expected:
        assert word in proc.stdout, word


def test_version(tmp_path: Path) -> None:
    proc = _run([*IPT, "--version"], tmp_path)
    assert proc.returncode == 0
    assert proc.stdout.startswith("ipt ")


# --- map export and check -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Exported:
    image: Path
    layout: Path
    proc: subprocess.CompletedProcess[str]


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Exported:
    """``ipt map export`` of the shipped arena, run once for the module."""
    out = tmp_path_factory.mktemp("export")
    image, layout = out / "map.png", out / "layout.json"
    proc = _run([*IPT, "map", "export", "--image", str(image), "--layout", str(layout)], out)
    return Exported(image, layout, proc)


def test_map_export_then_check(exported: Exported, tmp_path: Path) -> None:
    assert exported.proc.returncode == 0, exported.proc.stderr
    assert "107 tags" in exported.proc.stdout
    png = cv2.imread(str(exported.image), cv2.IMREAD_UNCHANGED)
    assert png is not None
    assert png.shape == (2160, 1920)
    assert png.dtype == np.uint8
    data = json.loads(exported.layout.read_text(encoding="utf-8"))
    assert data["projector"] == {"width_px": 1920, "height_px": 2160}
    grid = set(range(81)) - {10, 11, 19, 20, 28, 29}  # the pad's small tags take these cells
    assert sorted(t["id"] for t in data["tags"]) == sorted(grid | set(range(81, 81 + 32)))
    assert sorted(p.name for p in exported.image.parent.iterdir()) == ["layout.json", "map.png"]

    check = _run([*IPT, "map", "check", "--layout", str(exported.layout), "--image", str(exported.image)], tmp_path)
    assert check.returncode == 0, check.stderr
    assert "107/107" in check.stdout
    assert "107 tags, ids unique" in check.stdout
    worst = float(check.stdout.split("largest corner difference")[1].split("px")[0])
    assert worst < 0.5


def test_map_export_with_custom_config(tmp_path: Path) -> None:
    cfg = tmp_path / "small.yaml"
    cfg.write_text(
        "projector: {width_px: 640, height_px: 480}\nscreen: {width_m: 1.0, height_m: 0.75}\n"
        "tag_map: {rows: 3, cols: 4, tag_size_px: 64}\n",
        encoding="utf-8",
    )
    image, layout = tmp_path / "m.png", tmp_path / "l.json"
    proc = _run([*IPT, "map", "export", "--config", str(cfg), "--image", str(image), "--layout", str(layout)], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "12 tags" in proc.stdout
    png = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    assert png is not None
    assert png.shape == (480, 640)
    check = _run([*IPT, "map", "check", "--layout", str(layout), "--image", str(image)], tmp_path)
    assert check.returncode == 0, check.stdout + check.stderr
    assert "12/12" in check.stdout


def test_map_check_reports_missing_tags_with_exit_1(exported: Exported, tmp_path: Path) -> None:
    layout = exported.layout
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((2160, 1920), 127, np.uint8))
    proc = _run([*IPT, "map", "check", "--layout", str(layout), "--image", str(blank)], tmp_path)
    assert proc.returncode == 1
    assert "0/107" in proc.stdout
    assert "Traceback" not in proc.stderr


def test_map_check_duplicate_id(exported: Exported, tmp_path: Path) -> None:
    layout = tmp_path / "dup-layout.json"
    data = json.loads(exported.layout.read_text(encoding="utf-8"))
    data["tags"][5]["id"] = data["tags"][4]["id"]
    layout.write_text(json.dumps(data), encoding="utf-8")
    proc = _run([*IPT, "map", "check", "--layout", str(layout)], tmp_path)
    _assert_one_line_error(proc, "ipt", "dup-layout.json", "duplicate id")


def test_map_check_image_not_an_image(exported: Exported, tmp_path: Path) -> None:
    fake = tmp_path / "fake.png"
    fake.write_text("not a png", encoding="utf-8")
    proc = _run([*IPT, "map", "check", "--layout", str(exported.layout), "--image", str(fake)], tmp_path)
    # The layout's own check is reported on stdout before the image fails.
    _assert_one_line_error(proc, "ipt", "fake.png", "not an image", stdout_empty=False)


# --- one-line errors ------------------------------------------------------------------------------------------


def _export_cmd(tmp_path: Path, *extra: str) -> list[str]:
    return [*IPT, "map", "export", "--image", str(tmp_path / "m.png"), "--layout", str(tmp_path / "l.json"), *extra]


def test_unknown_flag(tmp_path: Path) -> None:
    _assert_one_line_error(_run([*_export_cmd(tmp_path), "--bogus"], tmp_path), "ipt", "--bogus")
    cmd = [*RECEIVER, "replay", "--camera", "c.yaml", "--video", "v.mkv", "--output", "o.tum", "--bogus"]
    _assert_one_line_error(_run(cmd, tmp_path), "ipt-receiver", "--bogus")
    assert not (tmp_path / "m.png").exists()


def test_unknown_command(tmp_path: Path) -> None:
    _assert_one_line_error(_run([*IPT, "frobnicate"], tmp_path), "ipt", "frobnicate")
    _assert_one_line_error(_run([*IPT], tmp_path), "ipt")


def test_missing_required_option(tmp_path: Path) -> None:
    proc = _run([*IPT, "map", "export", "--image", str(tmp_path / "m.png")], tmp_path)
    _assert_one_line_error(proc, "ipt", "--layout")
    proc = _run([*RECEIVER, "replay", "--camera", "c.yaml", "--output", "o.tum"], tmp_path)
    _assert_one_line_error(proc, "ipt-receiver", "--video")
    assert not list(tmp_path.iterdir())


def test_config_missing_file(tmp_path: Path) -> None:
    proc = _run(_export_cmd(tmp_path, "--config", str(tmp_path / "nope.yaml")), tmp_path)
    _assert_one_line_error(proc, "ipt", "nope.yaml", "no such file")
    assert not (tmp_path / "m.png").exists()
    assert not (tmp_path / "l.json").exists()


def test_config_empty_file(tmp_path: Path) -> None:
    cfg = tmp_path / "empty.yaml"
    cfg.write_text("", encoding="utf-8")
    _assert_one_line_error(_run(_export_cmd(tmp_path, "--config", str(cfg)), tmp_path), "ipt", "empty.yaml", "empty")


def test_config_unknown_key(tmp_path: Path) -> None:
    cfg = tmp_path / "typo.yaml"
    cfg.write_text("tag_map:\n  rows: 9\n  colums: 9\n", encoding="utf-8")
    proc = _run(_export_cmd(tmp_path, "--config", str(cfg)), tmp_path)
    _assert_one_line_error(proc, "ipt", "typo.yaml", "tag_map.colums", "unknown key")
    assert not (tmp_path / "m.png").exists()


def test_receiver_config_errors(tmp_path: Path, camera_file: Path) -> None:
    cfg = tmp_path / "bad-arena.yaml"
    cfg.write_text("projector: [1, 2]\n", encoding="utf-8")
    proc = _run(
        [*RECEIVER, "replay", "--config", str(cfg), "--camera", str(camera_file), "--video", "v", "--output", "o"],
        tmp_path,
    )
    _assert_one_line_error(proc, "ipt-receiver", "bad-arena.yaml", "projector")


# --- replay ---------------------------------------------------------------------------------------------------


def _replay(tmp_path: Path, camera: Path, video: Path, output: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    cmd = [*RECEIVER, "replay", "--camera", str(camera), "--video", str(video), "--output", str(output), *extra]
    return _run(cmd, tmp_path)


def _no_output(output: Path) -> None:
    assert not output.exists()
    assert not [p for p in output.parent.iterdir() if p.name.startswith(f".{output.name}")], "no temporary file"


def test_replay_missing_camera_file(tmp_path: Path) -> None:
    out = tmp_path / "poses.tum"
    proc = _replay(tmp_path, tmp_path / "nocam.yaml", tmp_path, out, "--fps", "120")
    _assert_one_line_error(proc, "ipt-receiver", "nocam.yaml")
    _no_output(out)


def test_replay_camera_file_not_camera_info(tmp_path: Path) -> None:
    out = tmp_path / "poses.tum"
    proc = _replay(tmp_path, shipped_config_path("arena.yaml"), tmp_path, out, "--fps", "120")
    _assert_one_line_error(proc, "ipt-receiver", "arena.yaml", "camera_info")
    _no_output(out)


def test_replay_missing_video(tmp_path: Path, camera_file: Path) -> None:
    out = tmp_path / "poses.tum"
    proc = _replay(tmp_path, camera_file, tmp_path / "flight.mkv", out)
    _assert_one_line_error(proc, "ipt-receiver", "flight.mkv")
    _no_output(out)


def test_replay_text_file_named_mkv(tmp_path: Path, camera_file: Path) -> None:
    video = tmp_path / "x.mkv"
    video.write_text("this is not a video\n" * 20, encoding="utf-8")
    out = tmp_path / "poses.tum"
    proc = _replay(tmp_path, camera_file, video, out)
    _assert_one_line_error(proc, "ipt-receiver", "x.mkv")
    _no_output(out)


def _frames_folder(tmp_path: Path, sizes: list[tuple[int, int]]) -> Path:
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, (w, h) in enumerate(sizes):
        cv2.imwrite(str(folder / f"frame_{i:03d}.png"), np.full((h, w, 3), 100 + 10 * i, np.uint8))
    return folder


def test_replay_of_image_folder(tmp_path: Path, camera_file: Path) -> None:
    folder = _frames_folder(tmp_path, [(64, 48)] * 3)
    out = tmp_path / "poses.tum"
    proc = _replay(tmp_path, camera_file, folder, out, "--fps", "120")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "0 poses from 3 frames" in proc.stdout
    assert out.is_file()
    lines = out.read_text(encoding="utf-8").splitlines()
    assert len(lines) == 1, "header only: plain frames carry no tags"
    assert lines[0].startswith("#")


def test_replay_of_image_folder_needs_fps(tmp_path: Path, camera_file: Path) -> None:
    folder = _frames_folder(tmp_path, [(64, 48)] * 2)
    out = tmp_path / "poses.tum"
    _assert_one_line_error(_replay(tmp_path, camera_file, folder, out), "ipt-receiver", "--fps")
    _no_output(out)
    _assert_one_line_error(_replay(tmp_path, camera_file, folder, out, "--fps", "-5"), "ipt-receiver", "--fps")
    _no_output(out)


def test_replay_told_of_a_rolling_shutter_fits_its_sweep(tmp_path: Path, short_flight: Path) -> None:
    """``--rolling-shutter`` reaches the pipeline (``pose.track.rolling_shutter``, as a daemon's receiver.yaml sets
    it): the dense way's fits, the first pose's among them, gain the sweep's six unknowns, which on this
    global-shutter flight fit noise, so the poses differ from those of the replay not told of it."""
    camera, video = short_flight / "camera.yaml", short_flight / "frames.mkv"
    plain, told = tmp_path / "plain.tum", tmp_path / "told.tum"
    for out, extra in ((plain, ()), (told, ("--rolling-shutter",))):
        proc = _replay(tmp_path, camera, video, out, "--fps", "120", *extra)
        assert proc.returncode == 0, proc.stderr[-3000:]
    poses = [
        [line for line in f.read_text(encoding="utf-8").splitlines() if not line.startswith("#")] for f in (plain, told)
    ]
    assert len(poses[0]) >= 50
    assert len(poses[1]) >= 50
    assert poses[0][0] != poses[1][0], "the first pose (the dense way's) fitted the same without the sweep"


def test_replay_rolling_shutter_needs_the_ipt_profile_and_a_video(tmp_path: Path, camera_file: Path) -> None:
    folder = _frames_folder(tmp_path, [(64, 48)] * 2)
    out = tmp_path / "poses.tum"
    proc = _replay(tmp_path, camera_file, folder, out, "--fps", "120", "--profile", "paper", "--rolling-shutter")
    _assert_one_line_error(proc, "ipt-receiver", "--rolling-shutter", "ipt profile")
    _no_output(out)
    proc = _run([*RECEIVER, "replay", "--frames", str(folder), "--output", str(out), "--rolling-shutter"], tmp_path)
    _assert_one_line_error(proc, "ipt-receiver", "--frames", "drop the other flags")
    _no_output(out)


def test_replay_camera_size_mismatch(tmp_path: Path, camera_file: Path) -> None:
    folder = _frames_folder(tmp_path, [(80, 48)] * 2)
    out = tmp_path / "poses.tum"
    proc = _replay(tmp_path, camera_file, folder, out, "--fps", "120")
    _assert_one_line_error(proc, "ipt-receiver", "camera.yaml", "64x48", "80x48")
    _no_output(out)


def test_replay_skips_a_bad_frame_midway_and_counts_it(tmp_path: Path, camera_file: Path) -> None:
    # The second image has another size and the fourth is not an image: a recording is read to its end,
    # as the daemon reads it, each bad frame skipped, said (naming it) and counted; the others keep their times.
    folder = _frames_folder(tmp_path, [(64, 48), (32, 24), (64, 48), (64, 48)])
    (folder / "frame_003.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    out = tmp_path / "poses.tum"
    proc = _replay(tmp_path, camera_file, folder, out, "--fps", "120")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "0 poses from 2 frames" in proc.stdout
    lines = proc.stderr.splitlines()
    assert any("frame_001.png" in line and "32x24" in line and "skipped" in line for line in lines), lines
    assert any("frame_003.png" in line and "not an image" in line and "skipped" in line for line in lines), lines
    assert "2 unreadable frames skipped" in lines[-1]
    assert out.is_file()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".poses.tum")] == []
