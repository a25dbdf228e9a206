"""Atomic writes: all or nothing, with ordinary permissions."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from ipt.fileio import atomic_path, write_text_atomic


def test_write_text_atomic_creates_file_with_umask_permissions(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"
    write_text_atomic(target, "hello\n")
    assert target.read_text() == "hello\n"
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~mask
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_failed_body_leaves_previous_file_and_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"
    target.write_text("old")
    def interrupted_write() -> None:
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        interrupted_write()
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_temporary_path_keeps_the_suffix(tmp_path: Path) -> None:
    with atomic_path(tmp_path / "fig.png") as tmp:
        assert tmp.suffix == ".png"
        assert tmp.parent == tmp_path
        tmp.write_bytes(b"x")
    assert (tmp_path / "fig.png").read_bytes() == b"x"


@pytest.mark.parametrize("step", ["close", "chmod"])
def test_a_stop_signal_right_after_the_temporary_file_is_made_leaves_nothing(
    tmp_path: Path, step: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A stop signal's handler raises wherever the program is: here in the first steps after the temporary
    # file exists, before the body runs (a hidden .partial file was once left by a SIGTERM there).
    import ipt.fileio as fileio

    def stopped(*args: object) -> None:
        raise KeyboardInterrupt

    real = getattr(os, step)

    class FileioOs:
        """The os module as fileio sees it, ``step`` stopped: patching os itself would stop every other
        caller too (a detector's finalizer closing its pipe when the garbage collector runs meanwhile)."""

        def __getattr__(self, name: str) -> object:
            return getattr(os, name)

    patched = FileioOs()
    setattr(patched, step, lambda *args: (real(*args), stopped())[1])
    monkeypatch.setattr(fileio, "os", patched)
    with pytest.raises(KeyboardInterrupt), atomic_path(tmp_path / "poses.tum"):
        pytest.fail("the body does not run")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []
