"""Issue 33 items 4, 9, 14, 15 and 17: absurd settings and hostile files are one line at start-up.

Each case failed at 5def445: a MAVLink lever arm of 1e308 or NaN loaded (and later ended the daemon or
silenced ODOMETRY), a stats interval of 1e-6 or 1e-300 s loaded, a camera.yaml with a focal length of
1e9 px loaded, the sender's key errors did not name the key file and a key file anyone could read was
accepted, ``calibrate arena`` printed raw pydantic text or numpy warnings and a traceback, a TUM error
quoted 5 KB, NaN was reported as "less than or equal to 1000", and a folder in ``CYCLONEDDS_URI``
started DDS with its default settings. Every subprocess here talks to 127.0.0.1 only.
"""

from __future__ import annotations

import glob
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from ipt.config.base import ConfigError, load_yaml_model, shipped_config_path
from ipt.config.camera_info import CameraInfo, CameraInfoError, load_camera_info, save_camera_info
from ipt.config.receiver import load_receiver_config, read_auth_key
from ipt.tum import TumError, read_tum

ROOT = Path(__file__).resolve().parent.parent
ARENA = {
    "projector": {"width_px": 320, "height_px": 288, "rate_hz": 60},
    "screen": {"width_m": 1.0, "height_m": 0.9},
    "tag_map": {"rows": 2, "cols": 2, "tag_size_px": 64},
    "modulation": {"delta_l": 8, "input_rate_hz": 30},
}
CAMERA = CameraInfo(width_px=64, height_px=48, fx_px=60.0, fy_px=60.0, cx_px=31.5, cy_px=23.5, name="refused")
KEY = b"0123456789abcdef0123456789abcdef"


def _files(z: Path) -> None:
    (z / "arena.yaml").write_text(yaml.safe_dump(ARENA), encoding="utf-8")
    save_camera_info(CAMERA, z / "camera.yaml")
    (z / "frames").mkdir()
    for i in range(2):
        cv2.imwrite(str(z / "frames" / f"f{i}.png"), np.full((48, 64, 3), 100, np.uint8))


def _run(z: Path, *argv: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", *argv], cwd=z, capture_output=True, text=True, timeout=120, check=False,
        stdin=subprocess.DEVNULL, env=env,
    )  # fmt: skip


def _one_line(proc: subprocess.CompletedProcess[str], *words: str) -> str:
    """The one error line (exit 2, no traceback, the last line), holding every one of ``words``."""
    assert "Traceback" not in proc.stderr, proc.stderr
    assert "Warning" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    lines = proc.stderr.splitlines()
    assert [line for line in lines if ": error: " in line] == [lines[-1]], proc.stderr
    for word in words:
        assert word in lines[-1], (word, lines[-1])
    assert "\\n" not in lines[-1], lines[-1]
    assert "https://" not in lines[-1], lines[-1]
    return lines[-1]


def _receiver_yaml(z: Path, extra: dict[str, Any]) -> Path:
    data = {"arena": "arena.yaml", "camera": "camera.yaml", "send": ["127.0.0.1:9"], **extra}
    path = z / "receiver.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


# --- item 4: MAVLink settings ------------------------------------------------------------------------------

MAVLINK_CASES = {
    "huge-lever-arm": ({"camera_position_frd_m": [1e308, 0.0, 0.0]}, "mavlink.camera_position_frd_m.0"),
    "nan-lever-arm": ({"camera_position_frd_m": [float("nan"), 0.0, 0.0]}, "mavlink.camera_position_frd_m.0"),
    "inf-lever-arm": ({"camera_position_frd_m": [0.0, float("-inf"), 0.0]}, "mavlink.camera_position_frd_m.1"),
    "lever-arm-50m": ({"camera_position_frd_m": [0.0, 0.0, 50.0]}, "mavlink.camera_position_frd_m.2"),
    "nan-rotation": ({"r_frd_cam": [[float("nan"), 0, 0], [0, 1, 0], [0, 0, 1]]}, "mavlink.r_frd_cam.0.0"),
    "huge-rotation": ({"r_frd_cam": [[1e308, 0, 0], [0, 1, 0], [0, 0, 1]]}, "mavlink.r_frd_cam"),
    "tiny-quality-std": ({"zero_quality_std_m": 1e-300}, "mavlink.zero_quality_std_m"),
    "inf-reset-jump": ({"reset_jump_m": float("inf")}, "mavlink.reset_jump_m"),
}


@pytest.mark.parametrize("case", list(MAVLINK_CASES), ids=list(MAVLINK_CASES))
def test_absurd_mavlink_settings_are_refused_when_the_config_loads(tmp_path: Path, case: str) -> None:
    mavlink, key = MAVLINK_CASES[case]
    path = _receiver_yaml(tmp_path, {"mavlink": {"link": "udpout:127.0.0.1:9", **mavlink}})
    with pytest.raises(ConfigError) as info:
        load_receiver_config(path)
    text = str(info.value)
    assert text.startswith(f"{path}: "), text
    assert key in text, text
    assert "\n" not in text


def test_a_sane_lever_arm_still_loads(tmp_path: Path) -> None:
    path = _receiver_yaml(tmp_path, {"mavlink": {"camera_position_frd_m": [0.12, -0.03, 0.05]}})
    assert load_receiver_config(path).mavlink.camera_position_frd_m == (0.12, -0.03, 0.05)


def test_the_daemon_refuses_a_huge_lever_arm_before_it_starts(tmp_path: Path) -> None:
    _files(tmp_path)
    _receiver_yaml(tmp_path, {"mavlink": {"link": "udpout:127.0.0.1:9", "camera_position_frd_m": [1e308, 0, 0]}})
    proc = _run(tmp_path, "ipt.receiver.cli", "run", "--max-frames", "2", "--config", "receiver.yaml")
    _one_line(proc, "receiver.yaml", "mavlink.camera_position_frd_m.0")


# --- item 9: statistics intervals ---------------------------------------------------------------------------


@pytest.mark.parametrize("interval", [1e-6, 0.0, 1e-300])
def test_a_tiny_stats_interval_is_refused(tmp_path: Path, interval: float) -> None:
    path = _receiver_yaml(tmp_path, {"stats_interval_s": interval})
    with pytest.raises(ConfigError, match="stats_interval_s"):
        load_receiver_config(path)


@pytest.mark.parametrize("every", ["1e-300", "0.01", "nan", "1e308"])
def test_the_sender_refuses_an_absurd_stats_interval(tmp_path: Path, every: str) -> None:
    _files(tmp_path)
    proc = _run(tmp_path, "ipt.sender.cli", "--config", "arena.yaml", "--sink", "null", "--frames", "2",
                "--listen", "127.0.0.1:0", "--stats-every", every)  # fmt: skip
    _one_line(proc, "--stats-every", "0.1 to 86400")


# --- item 14: camera intrinsics -----------------------------------------------------------------------------

ABSURD_CAMERAS = {
    "focal-1e-9": ({"fx_px": 1e-9}, "fx=1e-09"),
    "focal-1e9": ({"fy_px": 1e9}, "fy=1e+09"),
    "focal-0.01-widths": ({"fx_px": 0.6}, "fx=0.6"),
    "distortion-1e3": ({"distortion": (0.1, 1e3, 0.0, 0.0, 0.0)}, "value 2 is 1000"),
    "principal-point-left": ({"cx_px": -50.0}, "cx=-50"),
    "principal-point-below": ({"cy_px": 1e4}, "cy=10000"),
}


@pytest.mark.parametrize("case", list(ABSURD_CAMERAS), ids=list(ABSURD_CAMERAS))
def test_absurd_intrinsics_are_one_line_naming_the_file(tmp_path: Path, case: str) -> None:
    changes, words = ABSURD_CAMERAS[case]
    path = tmp_path / "camera.yaml"
    save_camera_info(CameraInfo(**{**CAMERA.__dict__, **changes}), path)
    with pytest.raises(CameraInfoError) as info:
        load_camera_info(path)
    text = str(info.value)
    assert text.startswith(f"{path}: "), text
    assert words in text, text
    assert "\n" not in text


def test_replay_refuses_an_absurd_camera(tmp_path: Path) -> None:
    _files(tmp_path)
    save_camera_info(CameraInfo(**{**CAMERA.__dict__, "fx_px": 1e9}), tmp_path / "camera.yaml")
    proc = _run(tmp_path, "ipt.receiver.cli", "replay", "--config", "arena.yaml", "--camera", "camera.yaml",
                "--fps", "120", "--video", "frames", "--output", "r.tum")  # fmt: skip
    _one_line(proc, "camera.yaml", "focal length")
    assert not (tmp_path / "r.tum").exists()


def test_every_suite_camera_and_the_shipped_one_pass_the_bounds(tmp_path: Path) -> None:
    from ipt.sim.config import SimConfig
    from ipt.sim.render import camera_info_of

    flights = sorted(glob.glob(str(ROOT / "benchmarks" / "flights" / "*.yaml")))
    flights += sorted(glob.glob(str(ROOT / "benchmarks" / "heldout" / "*.yaml")))
    assert len(flights) >= 15
    for flight in flights:
        info = camera_info_of(load_yaml_model(flight, SimConfig).camera)
        save_camera_info(info, tmp_path / "camera.yaml")
        assert load_camera_info(tmp_path / "camera.yaml") == info, flight
    assert load_camera_info(shipped_config_path("camera.yaml")).width_px > 0


# --- item 15: the messages ----------------------------------------------------------------------------------


def _key(z: Path, data: bytes, mode: int) -> Path:
    path = z / "ipt.key"
    path.write_bytes(data)
    path.chmod(mode)
    return path


SENDER_KEY = ("ipt.sender.cli", "--config", "arena.yaml", "--sink", "null", "--frames", "2", "--listen",
              "127.0.0.1:0", "--auth-key-file", "ipt.key")  # fmt: skip


def test_the_senders_short_key_error_names_the_key_file(tmp_path: Path) -> None:
    _files(tmp_path)
    _key(tmp_path, b"short\n", 0o600)
    _one_line(_run(tmp_path, *SENDER_KEY), "ipt.key", "5 bytes", "at least 16")


@pytest.mark.parametrize("mode", [0o644, 0o604, 0o602, 0o601, 0o666], ids=lambda m: f"{m:04o}")
def test_a_key_file_open_to_others_is_refused_by_sender_and_receiver(tmp_path: Path, mode: int) -> None:
    _files(tmp_path)
    key = _key(tmp_path, KEY + b"\n", mode)
    _one_line(_run(tmp_path, *SENDER_KEY), "ipt.key", "open to other users", f"{mode:04o}", "chmod o-rwx")
    with pytest.raises(ConfigError, match=r"ipt\.key: the key file is open to other users"):
        read_auth_key(key)


@pytest.mark.parametrize("mode", [0o600, 0o640, 0o400], ids=lambda m: f"{m:04o}")
def test_a_private_key_file_is_accepted(tmp_path: Path, mode: int) -> None:
    assert read_auth_key(_key(tmp_path, KEY + b"\n", mode)) == KEY


@pytest.mark.parametrize("distance", ["1e308", "1e300", "nan", "-1"])
def test_calibrate_arena_distance_is_one_clean_line(tmp_path: Path, distance: str) -> None:
    _files(tmp_path)
    before = (tmp_path / "arena.yaml").read_bytes()
    proc = _run(tmp_path, "ipt.cli", "calibrate", "arena", "--config", "arena.yaml", "--tags", "0", "1",
                "--distance-m", distance)  # fmt: skip
    _one_line(proc, "--distance-m", "at most 1000 m")
    assert (tmp_path / "arena.yaml").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arena.yaml", "camera.yaml", "frames"]


def test_a_distance_that_makes_a_huge_arena_is_one_clean_line(tmp_path: Path) -> None:
    _files(tmp_path)
    proc = _run(tmp_path, "ipt.cli", "calibrate", "arena", "--config", "arena.yaml", "--tags", "0", "1",
                "--distance-m", "900")  # fmt: skip
    _one_line(proc, "screen.width_m", "not a usable arena")


def test_calibrate_arena_points_with_huge_values_is_one_line_without_warnings(tmp_path: Path) -> None:
    _files(tmp_path)
    rows = ["u_px,v_px,x_m,y_m", "0,0,0,0", "300,0,1e308,0", "300,280,1e308,1e308", "0,280,0,1e308"]
    (tmp_path / "p.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    proc = _run(tmp_path, "ipt.cli", "calibrate", "arena", "--config", "arena.yaml", "--points", "p.csv", "--dry-run")
    _one_line(proc, "p.csv", "row 3", "x_m")
    assert proc.stderr.count("\n") == 1, proc.stderr


@pytest.mark.parametrize(
    "field", ["1" * 5000, "x" * 5000, "0." + "0" * 5000], ids=["overflow", "not-a-number", "long-time"]
)
def test_a_5kb_tum_field_gives_a_short_error(tmp_path: Path, field: str) -> None:
    path = tmp_path / "poses.tum"
    second = f"{field} 0 0 1 0 0 0 1" if field.startswith("0.") else f"1 {field} 0 1 0 0 0 1"
    path.write_text(f"0 0 0 1 0 0 0 1\n{second}\n", encoding="utf-8")
    with pytest.raises(TumError) as info:
        read_tum(path)
    text = str(info.value)
    assert len(text) < len(str(path)) + 200, text
    assert "characters)" in text, text


def test_nan_is_reported_as_nan(tmp_path: Path) -> None:
    path = _receiver_yaml(tmp_path, {"fps": float("nan")})
    with pytest.raises(ConfigError) as info:
        load_receiver_config(path)
    assert str(info.value) == f"{path}: fps: nan is not a number"


# --- item 17: CYCLONEDDS_URI --------------------------------------------------------------------------------


def _uri_cases(z: Path) -> dict[str, tuple[str, str | None]]:
    xml = z / "dds.xml"
    xml.write_text("<CycloneDDS/>\n", encoding="utf-8")
    return {
        "folder": (str(z), "is a folder"),
        "file-url-folder": (f"file://{z}", "is a folder"),
        "missing": (str(z / "none.xml"), "no such file"),
        "device": (os.devnull, "not a regular file"),
        "second-of-list": (f"file://{xml},{z}", "is a folder"),
        "file": (f"file://{xml}", None),
        "plain-path": (str(xml), None),
        "inline-xml": ("<CycloneDDS><Domain/></CycloneDDS>", None),
        "empty": ("", None),
    }


def test_cyclonedds_uri_is_checked(tmp_path: Path) -> None:
    from ipt.receiver.outputs.ros.ddsconfig import DdsConfigError, check_cyclonedds_uri

    for name, (value, problem) in _uri_cases(tmp_path).items():
        if problem is None:
            check_cyclonedds_uri({"CYCLONEDDS_URI": value})
            continue
        with pytest.raises(DdsConfigError) as info:
            check_cyclonedds_uri({"CYCLONEDDS_URI": value})
        assert str(info.value).startswith("CYCLONEDDS_URI: "), (name, info.value)
        assert problem in str(info.value), (name, info.value)


def test_the_daemon_refuses_a_folder_in_cyclonedds_uri(tmp_path: Path) -> None:
    pytest.importorskip("cyclonedds")
    _files(tmp_path)
    _receiver_yaml(tmp_path, {"ros2": {"enabled": True}})
    env = {**os.environ, "CYCLONEDDS_URI": str(tmp_path / "frames")}
    proc = _run(tmp_path, "ipt.receiver.cli", "run", "--max-frames", "2", "--config", "receiver.yaml", env=env)
    _one_line(proc, "CYCLONEDDS_URI", "frames", "is a folder")
