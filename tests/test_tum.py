"""TUM trajectory files: round trip, column order, and every malformed-line case."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ipt.errors import IptError
from ipt.tum import TUM_HEADER, Trajectory, TumError, format_tum_line, read_tum, write_tum


def _random_traj(n: int, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    times = 1_700_000_000.0 + np.cumsum(rng.uniform(0.001, 0.1, n))
    pos = rng.uniform(-3.0, 3.0, (n, 3))
    return Trajectory.from_arrays(times, pos, rng.normal(size=(n, 4)))


def test_round_trip_keeps_values(tmp_path: Path) -> None:
    traj = _random_traj(50)
    path = tmp_path / "traj.tum"
    write_tum(path, traj)
    back = read_tum(path)
    assert len(back) == 50
    np.testing.assert_allclose(back.times_s, traj.times_s, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.positions_m, traj.positions_m, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.quats_wxyz, traj.quats_wxyz, rtol=0, atol=2e-9)
    assert not list(tmp_path.glob("*.partial*")), "no temporary file left behind"


@settings(max_examples=50, deadline=None)
@given(
    t=st.floats(0.0, 2e9, allow_nan=False),
    pos=st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=3, max_size=3),
    quat=st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=4, max_size=4).filter(
        lambda q: float(np.linalg.norm(q)) > 0.1
    ),
)
def test_format_tum_line_precision(t: float, pos: list[float], quat: list[float]) -> None:
    fields = [float(f) for f in format_tum_line(t, pos, quat).split()]
    assert len(fields) == 8
    assert abs(fields[0] - t) <= 0.5e-6 + 2 * np.spacing(t)
    assert np.max(np.abs(np.array(fields[1:4]) - pos)) <= 0.5e-6 + 1e-12
    w, x, y, z = quat
    assert np.max(np.abs(np.array(fields[4:8]) - [x, y, z, w])) <= 0.5e-9 + 1e-15


def test_file_column_order_is_xyzw(tmp_path: Path) -> None:
    # A 90 deg rotation about z: (w, x, y, z) = (c, 0, 0, s); in the file qw must come last.
    c = np.sqrt(0.5)
    traj = Trajectory.from_arrays([1.5], [[1.0, 2.0, 3.0]], [[c, 0.0, 0.0, c]])
    path = tmp_path / "one.tum"
    write_tum(path, traj)
    lines = path.read_text().splitlines()
    assert lines[0] == TUM_HEADER
    assert lines[1].split() == [
        "1.500000",
        "1.000000",
        "2.000000",
        "3.000000",
        "0.000000000",
        "0.000000000",
        "0.707106781",
        "0.707106781",
    ]
    (tmp_path / "id.tum").write_text("0 0 0 0 0.2 0 0 0.9\n")
    q = read_tum(tmp_path / "id.tum").quats_wxyz[0]
    # qw = 0.9 is read as w (first in memory), and the quaternion is normalised.
    np.testing.assert_allclose(q, np.array([0.9, 0.2, 0.0, 0.0]) / np.hypot(0.9, 0.2), atol=1e-12)


def test_comments_and_blank_lines_are_ignored(tmp_path: Path) -> None:
    path = tmp_path / "c.tum"
    path.write_text("# header\n\n   \n0.0 1 2 3 0 0 0 1\n  # indented comment\n0.5 4 5 6 0 0 0 1\n\n")
    traj = read_tum(path)
    np.testing.assert_array_equal(traj.times_s, [0.0, 0.5])
    np.testing.assert_array_equal(traj.positions_m, [[1, 2, 3], [4, 5, 6]])


GOOD = "0.0 0 0 0 0 0 0 1\n"


@pytest.mark.parametrize(
    ("text", "line", "problem"),
    [
        (GOOD + "0.1 0 0 0 0 0 1\n", 2, "expected 8 fields"),
        (GOOD + "0.1 0 0 0 0 0 0 1 7\n", 2, "expected 8 fields"),
        ("# c\n" + GOOD + "0.1 0 zero 0 0 0 0 1\n", 3, "y is not a number"),
        (GOOD + "0.1 0 0 nan 0 0 0 1\n", 2, "z is not finite"),
        (GOOD + "0.1 0 0 0 0 0 inf 1\n", 2, "qz is not finite"),
        (GOOD + "0.1 0 0 0 0 0 0 0\n", 2, "zero quaternion"),
        (GOOD + "0.0 0 0 0 0 0 0 1\n", 2, "strictly increasing"),
        (GOOD + "\n-1.0 0 0 0 0 0 0 1\n", 3, "strictly increasing"),
    ],
)
def test_malformed_line_names_file_and_line(tmp_path: Path, text: str, line: int, problem: str) -> None:
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(TumError, match=re.escape(f"{path}:{line}: ")) as info:
        read_tum(path)
    assert problem in str(info.value)
    assert isinstance(info.value, IptError)


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n"])
def test_file_without_poses_is_an_error(tmp_path: Path, text: str) -> None:
    path = tmp_path / "empty.tum"
    path.write_text(text)
    with pytest.raises(TumError, match="no poses"):
        read_tum(path)


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.tum"
    with pytest.raises(TumError, match=re.escape(f"{path}: no such file")):
        read_tum(path)


def test_directory_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(TumError, match="directory"):
        read_tum(tmp_path)


def test_format_tum_line_rejects_non_finite_and_wrong_shapes() -> None:
    with pytest.raises(ValueError, match="non-finite"):
        format_tum_line(0.0, [0.0, float("nan"), 0.0], [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="expected 3 position"):
        format_tum_line(0.0, [0.0, 0.0], [1.0, 0.0, 0.0, 0.0])


def test_trajectory_checks_shapes() -> None:
    with pytest.raises(ValueError, match="expected times"):
        Trajectory(np.zeros(3), np.zeros((2, 3)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="zero quaternion"):
        Trajectory.from_arrays([0.0], [[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0, 0.0]])
