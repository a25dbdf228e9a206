"""Writing files so that a reader never sees half of one: write beside the target, then rename."""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from ipt.errors import IptError


def _default_file_mode() -> int:
    """0o666 less the process umask: the mode ``open()`` would give a new file."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _default_file_mode()


class WriteError(IptError, OSError):
    """An output file cannot be created or put in place: no such folder, a folder in the way, no permission.

    Both an :class:`OSError` (``errno`` and ``strerror`` are the system's, ``filename`` is the target), so
    code that catches ``OSError`` still does, and an :class:`IptError`, so that the command-line tools
    report it as one line naming the file instead of a traceback.
    """

    def __str__(self) -> str:
        return f"{self.filename}: cannot write ({self.strerror})"


def _write_error(target: Path, exc: OSError) -> WriteError:
    return WriteError(exc.errno, exc.strerror or str(exc), str(target))


@contextlib.contextmanager
def atomic_path(target: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success it is renamed onto ``target``.

    If the body raises, the temporary file is removed and ``target`` is left as it was. If the temporary
    file cannot be made beside ``target`` or cannot be renamed onto it, :class:`WriteError` is raised.
    """
    t = Path(target)
    parent = t.parent if str(t.parent) else Path(".")
    try:
        fd, tmp = tempfile.mkstemp(dir=parent, prefix=f".{t.name}.", suffix=".partial" + t.suffix)
    except OSError as exc:
        raise _write_error(t, exc) from None
    except ValueError:  # a NUL character in the name
        raise WriteError(errno.EINVAL, "the name contains a NUL character", str(t)) from None
    os.close(fd)
    os.chmod(tmp, _FILE_MODE)  # mkstemp makes 0600 files; results should be as readable as any other
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        try:
            os.replace(tmp_path, t)
        except OSError as exc:
            raise _write_error(t, exc) from None
    finally:
        tmp_path.unlink(missing_ok=True)


def read_text_file(path: Path, error: type[Exception], expected: str) -> str:
    """The UTF-8 text of ``path``; any problem becomes ``error`` with one line naming the file.

    ``expected`` says what the file should be, for the message about a directory (e.g. "a YAML file").
    """
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except IsADirectoryError:
        raise error(f"{path}: is a directory, expected {expected}") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file (expected {expected})") from None
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror or exc})") from None
    except ValueError:  # a NUL character in the name (from a config file, say): no file can be called that
        raise error(f"{path}: not a usable file name (it contains a NUL character)") from None


def write_text_atomic(target: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")
