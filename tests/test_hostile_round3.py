"""Issue 33, items 6, 7, 8, 11, 12, 13 and 16: absurd sizes, boards, flights and poses, two outputs that are
one file, and a stop signal while a tool loads. Each case runs the real command in a subprocess and wants
one line naming the file or flag and the problem, exit 2 (or 128 + the signal), no traceback, and nothing
written or replaced."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from waiting import wait_until

TIMEOUT_S = 120.0
TINY_ARENA: dict[str, Any] = {
    "projector": {"width_px": 320, "height_px": 288, "rate_hz": 60},
    "screen": {"width_m": 1.0, "height_m": 0.9},
    "tag_map": {"rows": 2, "cols": 2, "tag_size_px": 64},
    "modulation": {"delta_l": 8, "input_rate_hz": 30},
}


def _ipt(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ipt.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
        stdin=subprocess.DEVNULL,
    )


def _one_line_error(proc: subprocess.CompletedProcess[str], *fragments: str) -> None:
    """Exit 2, no traceback and no warning: stderr is one line, holding every fragment."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert len(lines) == 1, proc.stderr[-2000:]
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


def _arena_file(folder: Path, name: str, **screen: float) -> Path:
    arena = {**TINY_ARENA, "screen": {**TINY_ARENA["screen"], **screen}}
    path = folder / name
    path.write_text(yaml.safe_dump(arena), encoding="utf-8")
    return path


# --- item 6: absurd screen sizes


@pytest.mark.parametrize("size", ["5e-324", "1e-300"])
@pytest.mark.parametrize("key", ["width_m", "height_m"])
def test_an_absurd_screen_size_is_one_line(tmp_path: Path, size: str, key: str) -> None:
    config = _arena_file(tmp_path, "arena.yaml", **{key: float(size)})
    proc = _ipt("sim", "--seconds", "0.02", "--config", str(config), "--out", "out", cwd=tmp_path)
    _one_line_error(proc, "arena.yaml", f"screen.{key}", "0.1")
    assert not (tmp_path / "out").exists()


# --- item 7: the calibration board


@pytest.fixture
def board_images(tmp_path: Path) -> Path:
    folder = tmp_path / "views"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.full((120, 160), 128, np.uint8))
    return folder


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        ("--cols 7 --rows 5 --square-m inf", "--square-m"),
        ("--cols 7 --rows 5 --square-m 1e308", "--square-m"),
        ("--cols 7 --rows 5 --square-m nan", "--square-m"),
        ("--cols 2 --rows 2 --square-m 0.02", "--cols"),
        ("--cols 100000 --rows 100000 --square-m 0.02", "--cols"),
        ("--pattern charuco --cols 5 --rows 5 --square-m 0.04 --marker-m 1e-300", "--marker-m"),
        ("--pattern charuco --cols 20 --rows 20 --square-m 0.04 --marker-m 0.03", "--dictionary"),
    ],
)
def test_an_absurd_board_is_one_line(board_images: Path, args: str, flag: str) -> None:
    out = board_images.parent / "camera.yaml"
    proc = _ipt("calibrate", "camera", "--images", str(board_images), *args.split(), "--output", str(out),
                cwd=board_images.parent)  # fmt: skip
    _one_line_error(proc, flag)
    assert not out.exists()


# --- item 8: flight length, seeds, flight files; a failed demo leaves nothing


@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        ("sim --seconds 1e308", ("--seconds", "3600")),
        ("demo --seconds 1e308", ("--seconds", "3600")),
        ("sim --seconds 0.02 --seed -1", ("--seed",)),
        ("demo --seconds 0.02 --seed -1", ("--seed",)),
        ("sim --seconds 0.02 --sim-config fx.yaml", ("fx.yaml", "camera.fx_px", "1e-300")),
        ("demo --seconds 0.02 --sim-config fx.yaml", ("fx.yaml", "camera.fx_px", "1e-300")),
        ("sim --seconds 0.02 --sim-config noise.yaml", ("noise.yaml", "camera.read_noise")),
        ("demo --seconds 0.02 --sim-config noise.yaml", ("noise.yaml", "camera.read_noise")),
        ("sim --seconds 0.02 --sim-config seed.yaml", ("seed.yaml", "seed")),
    ],
)
def test_an_absurd_flight_is_one_line_and_leaves_no_folder(tmp_path: Path, args: str, fragments: tuple[str]) -> None:
    (tmp_path / "fx.yaml").write_text("camera:\n  fx_px: 1e-300\n", encoding="utf-8")
    (tmp_path / "noise.yaml").write_text("camera:\n  read_noise: 1e300\n", encoding="utf-8")
    (tmp_path / "seed.yaml").write_text(f"seed: {2**70}\n", encoding="utf-8")
    config = _arena_file(tmp_path, "arena.yaml")
    proc = _ipt(*args.split(), "--config", str(config), "--out", "out", cwd=tmp_path)
    _one_line_error(proc, *fragments)
    assert not (tmp_path / "out").exists()


def test_invisibility_refuses_a_negative_seed(tmp_path: Path) -> None:
    proc = _ipt("invisibility", "--seed", "-1", "--pairs", "1", cwd=tmp_path)
    _one_line_error(proc, "--seed")


def test_a_demo_that_fails_in_flight_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A part that fails once the results folder is made: the folder and what was put in it go again."""
    from ipt.config.models import shipped_config_path
    from ipt.sim import demo
    from ipt.sim.lockstep import DemoError

    async def broken(self: object, out: Path, flown_arena: Path, camera_path: Path) -> None:
        assert flown_arena.is_file()
        assert camera_path.is_file()
        (out / "sender.log").write_text("started\n", encoding="utf-8")
        raise DemoError("the sender failed")

    monkeypatch.setattr(demo._ClosedLoop, "fly", broken)
    out = tmp_path / "results" / "demo"
    with pytest.raises(DemoError, match="the sender failed"):
        demo.run_demo(shipped_config_path("arena.yaml"), 0.05, out)
    assert not (tmp_path / "results").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine\n", encoding="utf-8")
    with pytest.raises(DemoError):
        demo.run_demo(shipped_config_path("arena.yaml"), 0.05, kept)
    assert sorted(p.name for p in kept.iterdir()) == ["notes.txt"]


# --- items 11 and 12: ipt eval


def _tum(path: Path, rows: list[str]) -> Path:
    path.write_text("".join(f"{0.01 * i:.2f} {row}\n" for i, row in enumerate(rows)), encoding="utf-8")
    return path


def _no_nan(text: str) -> Any:
    def refuse(name: str) -> None:
        raise ValueError(f"{name} is not JSON")

    return json.loads(text, parse_constant=refuse)


@pytest.mark.parametrize("quat", ["1e200 1e200 1e200 1e200", "0 0 1e308 1e308", "1e-300 0 0 1e-300"])
def test_eval_with_huge_or_tiny_quaternions_is_a_number_or_one_line(tmp_path: Path, quat: str) -> None:
    truth = _tum(tmp_path / "truth.tum", [f"{0.01 * i} 0 1 0 0 0 1" for i in range(20)])
    poses = _tum(tmp_path / "poses.tum", [f"{0.01 * i} 0 1 {quat}" for i in range(20)])
    proc = _ipt("eval", "--truth", str(truth), "--poses", str(poses), "--json", "e.json", cwd=tmp_path)
    if proc.returncode == 2:  # a quaternion too small to be a rotation
        _one_line_error(proc, "poses.tum")
        assert not (tmp_path / "e.json").exists()
        return
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stderr == ""  # no numpy warnings
    assert "nan" not in proc.stdout.lower(), proc.stdout
    assert "inf" not in proc.stdout.lower(), proc.stdout
    report = _no_nan((tmp_path / "e.json").read_text(encoding="utf-8"))
    assert report["n_estimates"] == 20


def test_eval_with_huge_positions_is_one_line(tmp_path: Path) -> None:
    truth = _tum(tmp_path / "truth.tum", [f"{0.01 * i} 0 1 0 0 0 1" for i in range(20)])
    poses = _tum(tmp_path / "poses.tum", ["1e308 -1e308 1 0 0 0 1" for _ in range(20)])
    proc = _ipt("eval", "--truth", str(truth), "--poses", str(poses), "--json", "e.json", cwd=tmp_path)
    _one_line_error(proc, "poses.tum", "1e+308 m")
    assert not (tmp_path / "e.json").exists()


def test_eval_whose_plot_fails_leaves_no_json(tmp_path: Path) -> None:
    truth = _tum(tmp_path / "truth.tum", [f"{0.01 * i} 0 1 0 0 0 1" for i in range(20)])
    proc = _ipt("eval", "--truth", str(truth), "--poses", str(truth), "--json", "e.json", "--plot",
                "missing/f.png", cwd=tmp_path)  # fmt: skip
    _one_line_error(proc, "missing/f.png", "cannot write")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["truth.tum"]


def test_eval_interrupted_while_it_plots_leaves_no_json(tmp_path: Path) -> None:
    """SIGINT once the JSON is written (old code) or staged (its temporary file): neither is left."""
    truth = _tum(tmp_path / "truth.tum", [f"{0.001 * i} 0 1 0 0 0 1" for i in range(3000)])
    proc = subprocess.Popen(
        [sys.executable, "-m", "ipt.cli", "eval", "--truth", str(truth), "--poses", str(truth), "--json", "e.json",
         "--plot", "f.png"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip

    def json_begun() -> bool:
        assert proc.poll() is None, "the run ended before writing e.json"
        return any(p.name.startswith((".e.json", "e.json")) for p in tmp_path.iterdir())

    wait_until(json_begun, TIMEOUT_S, "e.json written or staged")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=TIMEOUT_S)
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err, err[-2000:]
    assert err.strip().endswith("nothing was left half-written"), err[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["truth.tum"]


def test_eval_refuses_one_file_for_json_and_plot(tmp_path: Path) -> None:
    truth = _tum(tmp_path / "truth.tum", [f"{0.01 * i} 0 1 0 0 0 1" for i in range(20)])
    proc = _ipt("eval", "--truth", str(truth), "--poses", str(truth), "--json", "o", "--plot", "./o", cwd=tmp_path)
    _one_line_error(proc, "--json and --plot")
    assert not (tmp_path / "o").exists()


# --- item 13: ipt map export with one file for both outputs


@pytest.mark.parametrize("layout", ["X.png", "./X.png", "../here/X.png", "link.png", "hard.png"])
def test_map_export_refuses_one_file_for_image_and_layout(tmp_path: Path, layout: str) -> None:
    here = tmp_path / "here"
    here.mkdir()
    (here / "X.png").write_bytes(b"my map")
    (here / "link.png").symlink_to("X.png")
    (here / "hard.png").hardlink_to(here / "X.png")
    config = _arena_file(tmp_path, "arena.yaml")
    proc = _ipt("map", "export", "--config", str(config), "--image", "X.png", "--layout", layout, cwd=here)
    _one_line_error(proc, "--image and --layout", layout)
    assert (here / "X.png").read_bytes() == b"my map"
    assert sorted(p.name for p in here.iterdir()) == ["X.png", "hard.png", "link.png"]


# --- item 16: a stop signal while a tool loads


def _script(name: str) -> str:
    """The console script ``name`` as pip writes it from this checkout's pyproject.toml."""
    with (Path(__file__).resolve().parents[1] / "pyproject.toml").open("rb") as f:
        entry = tomllib.load(f)["project"]["scripts"][name]
    module, func = entry.split(":")
    return f"import sys\nfrom {module} import {func}\nsys.exit({func}())\n"


# Modules each tool imports while it loads (after the interpreter has started): the signal is sent when one is in.
TRIGGERS = ("argparse", "ipt.errors", "ipt.signals", "ipt.cliutil")


@pytest.mark.parametrize("tool", ["ipt", "ipt-sender", "ipt-receiver"])
def test_sigint_while_a_tool_loads_is_no_traceback(tool: str) -> None:
    """A real SIGINT, sent while the tool's modules are being imported (``-X importtime`` says which is done)
    and then after 0-20 ms more: never a traceback; 130 and one line (the daemons: their final line, 0)."""
    outcomes = []
    for trigger in TRIGGERS:
        for delay_s in (0.0, 0.003, 0.01, 0.02):
            proc = subprocess.Popen(
                [sys.executable, "-X", "importtime", "-c", _script(tool), "--version"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
            )  # fmt: skip
            assert proc.stderr is not None
            seen = []
            for line in proc.stderr:
                seen.append(line)
                if line.startswith("import time:") and line.rstrip().endswith(f" {trigger}"):
                    break
            time.sleep(delay_s)  # real: how long after that import the signal comes is what the test varies
            proc.send_signal(signal.SIGINT)
            out, rest = proc.communicate(timeout=TIMEOUT_S)
            err = "\n".join(x for x in ("".join(seen) + rest).splitlines() if not x.startswith("import time:"))
            assert "Traceback" not in err, (trigger, delay_s, err[-3000:])
            assert "KeyboardInterrupt" not in err, (trigger, delay_s, err[-3000:])
            if proc.returncode == 0 and out.strip():  # finished before the signal: the version
                outcomes.append("finished")
            elif proc.returncode == -signal.SIGINT:  # at its very end, after Python gave the signal back
                outcomes.append("ended by the signal")
            else:
                assert proc.returncode in ((130,) if tool == "ipt" else (130, 0)), (trigger, delay_s, err)
                assert "SIGINT" in err, (trigger, delay_s, err)
                outcomes.append("interrupted")
    assert "interrupted" in outcomes, outcomes
