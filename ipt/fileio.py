"""Files in and out for every tool: bounded reads of small files, and writes that a reader never sees half of.

Reading (:func:`read_bytes_file`, :func:`read_text_file`): a configuration, a layout, a key or an image
is read whole, so the read is bounded (a ``--config /dev/zero`` would otherwise grow to gigabytes) and
only regular files are read. The file is opened with ``O_NONBLOCK`` and checked with ``fstat`` before
a byte is read, so a named pipe with no writer is refused at once instead of blocking for ever.

Writing (:func:`atomic_path`): write beside the target, then rename. A symbolic link is followed to its
target (the link stays); a character device (``/dev/null``) is written through, as ``> /dev/null`` does
in a shell; a named pipe, a socket or a block device is refused with one line before anything is
written (a pipe with no reader would block): no output ever replaces any of them (nor a folder: the
rename onto one fails). Inside :func:`output_group`, the
renames wait until the whole group succeeded, so the outputs of one run appear together or not at all.
A disk that cannot take a file (full, over quota, read-only, file too large) is reported as one
:class:`WriteError` naming the target, wherever the error surfaced (:func:`disk_write_error`); the
temporary file is removed on any error and on the stop signals (:mod:`ipt.signals` turns those into an
exception that unwinds through here).
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path

from ipt.errors import IptError

MAX_CONFIG_BYTES = 1 << 20
"""Largest configuration, camera_info, layout or key file read (1 MiB; the shipped ones are a few kB)."""

DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG})
"""The ``errno`` values that mean the file system cannot take the file, whatever was being written."""

_PARTIAL = ".partial"
_RANDOM_CHARS = 8  # the random part of a temporary name
#: A new temporary file, never an existing one or a link (as :func:`tempfile.mkstemp` makes it).
_CREATE_FLAGS = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
_MAX_TEMP_SUFFIX_BYTES = 16  # a longer "suffix" is not a file type: left out of the temporary name


def _default_file_mode() -> int:
    """0o666 less the process umask: the mode ``open()`` would give a new file."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _default_file_mode()


class WriteError(IptError, OSError):
    """An output file cannot be created or put in place: no such folder, a folder in the way, no permission,
    a full or read-only disk.

    Both an :class:`OSError` (``errno`` and ``strerror`` are the system's, ``filename`` is the target), so
    code that catches ``OSError`` still does, and an :class:`IptError`, so that the command-line tools
    report it as one line naming the file instead of a traceback.
    """

    def __str__(self) -> str:
        return f"{self.filename}: cannot write ({self.strerror})"


class ReadError(IptError):
    """A file cannot be read (the default error of :func:`read_bytes_file`)."""


def _write_error(target: Path | str, exc: OSError) -> WriteError:
    return WriteError(exc.errno, exc.strerror or os.strerror(exc.errno or 0) or str(exc), str(target))


def disk_write_error(target: Path | str, exc: BaseException) -> WriteError | None:
    """The :class:`WriteError` naming ``target`` if ``exc`` says the disk cannot take it, else ``None``.

    Looks at ``exc`` and the exceptions it was raised from (a library may wrap the ``OSError``): any
    ``errno`` in :data:`DISK_ERRNOS` (no space, quota, read-only file system, file too large) counts.
    """
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        code = getattr(current, "errno", None)
        if isinstance(code, int) and code in DISK_ERRNOS:
            return WriteError(code, os.strerror(code), str(target))
        current = current.__cause__ or current.__context__
    return None


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return 255


def _temp_affixes(target: Path, folder: Path) -> tuple[str, str]:
    """Prefix and suffix of the temporary file beside ``target``: ``.NAME.<random>.partial.EXT``, with NAME
    cut so that the whole name fits the file system's limit (NAME_MAX bytes) whenever ``target``'s does."""
    suffix = target.suffix if len(os.fsencode(target.suffix)) <= _MAX_TEMP_SUFFIX_BYTES else ""
    tail = _PARTIAL + suffix
    room = _name_max(folder) - len(os.fsencode("." + "." + tail)) - _RANDOM_CHARS
    name = os.fsencode(target.name)[: max(1, room)]
    return "." + os.fsdecode(name) + ".", tail


class _Group:
    """The temporary files of one :func:`output_group`, in the order they were finished."""

    def __init__(self) -> None:
        self.done: list[tuple[Path, Path]] = []


_GROUP: contextvars.ContextVar[_Group | None] = contextvars.ContextVar("ipt_output_group", default=None)


@contextlib.contextmanager
def output_group() -> Iterator[None]:
    """Every :func:`atomic_path` finished inside the block is put in place only when the block ends without
    an error, all at once; if it raises (or a file cannot be put in place), every one is removed.

    So the outputs of a run appear together or not at all: a full disk while writing the last file
    leaves none of them, rather than a folder of files that look complete. A group inside a group joins
    the outer one. The group belongs to the thread (context) that opened it.
    """
    if _GROUP.get() is not None:
        yield
        return
    group = _Group()
    token = _GROUP.set(group)
    try:
        yield
    except BaseException:
        _GROUP.reset(token)
        for tmp, _ in group.done:
            tmp.unlink(missing_ok=True)
        raise
    _GROUP.reset(token)
    placed: list[Path] = []
    try:
        for tmp, target in group.done:
            _replace(tmp, target)
            placed.append(target)
    except BaseException:
        # Half a set looks like a whole one: take back what was already put in place.
        for target in placed:
            target.unlink(missing_ok=True)
        for tmp, _ in group.done:
            tmp.unlink(missing_ok=True)
        raise


def _refused(target: Path, mode: int) -> WriteError:
    if stat.S_ISLNK(mode):
        return WriteError(errno.ELOOP, "a loop of symbolic links", str(target))
    kind = _file_kind(mode)
    return WriteError(errno.EINVAL, f"{kind}, not a regular file: an output never replaces one", str(target))


def output_target(target: Path) -> tuple[Path, bool]:
    """Where an output named ``target`` goes, and whether it is written straight through (a character device).

    A symbolic link is followed to its final target. A regular file or no file: written beside, then
    renamed (a folder too: the rename fails). A named pipe, a socket or a block device: :class:`WriteError`
    naming ``target``.
    """
    try:
        real = Path(os.path.realpath(target)) if os.path.islink(target) else target
        mode = os.lstat(real).st_mode
    except FileNotFoundError:
        return real, False
    except ValueError:  # a NUL character in the name
        raise WriteError(errno.EINVAL, "the name contains a NUL character", str(target)) from None
    except OSError as exc:  # a path through a file, a loop of links, no permission to look
        if exc.errno == errno.ENOTDIR:
            return target, False  # reported as before, when the temporary file cannot be made
        raise _write_error(target, exc) from None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return real, False  # a folder: the rename onto it fails and says so, as it always did
    if stat.S_ISCHR(mode):
        return real, True
    raise _refused(target, mode)


def _write_through(device: Path) -> Iterator[Path]:
    """The body of :func:`atomic_path` for a character device: it writes to the device itself."""
    try:
        yield device
    except OSError as exc:
        disk = disk_write_error(device, exc)
        if disk is None:
            raise
        raise disk from None


def _replace(tmp: Path, target: Path) -> None:
    """Rename ``tmp`` onto ``target``, unless something other than a regular file took its place meanwhile."""
    try:
        mode = os.lstat(target).st_mode
    except OSError:
        mode = stat.S_IFREG
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):  # a folder: os.replace refuses it below
        raise _refused(target, mode)
    try:
        os.replace(tmp, target)
    except OSError as exc:
        raise _write_error(target, exc) from None


@contextlib.contextmanager
def atomic_path(target: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success it is renamed onto ``target``.

    If the body raises, the temporary file is removed and ``target`` is left as it was; an ``OSError``
    saying the disk is full or read-only (:func:`disk_write_error`) becomes a :class:`WriteError` naming
    ``target``. If the temporary file cannot be made beside ``target`` or cannot be renamed onto it,
    :class:`WriteError` is raised. Inside :func:`output_group` the rename waits for the group.

    ``target`` may be a symbolic link (its target is written, the link kept) or a character device (the
    yielded path is the device itself: written through, nothing renamed); a named pipe, a socket or a block
    device is refused with :class:`WriteError` before the body runs.
    """
    named = Path(target)
    t, through = output_target(named)
    if through:
        yield from _write_through(t)
        return
    parent = t.parent if str(t.parent) else Path(".")
    group = _GROUP.get()
    kept = False
    tmp_path: Path | None = None
    try:
        # The temporary file's name is known (and cleaned up by ``finally``) before the file exists: a stop
        # signal's exception can come between any two statements, and one that came between making the file
        # and entering a ``try`` left a hidden .partial file behind.
        try:
            prefix, suffix = _temp_affixes(t, parent)
            for _ in range(100):
                tmp_path = parent / f"{prefix}{secrets.token_hex(_RANDOM_CHARS // 2)}{suffix}"
                try:
                    fd = os.open(tmp_path, _CREATE_FLAGS, _FILE_MODE)
                    break
                except FileExistsError:
                    tmp_path = None
            else:
                raise FileExistsError(errno.EEXIST, "no free temporary name", str(parent))
        except OSError as exc:
            tmp_path = None  # nothing was made (and a read-only disk refuses even to unlink what is not there)
            raise _write_error(named, exc) from None
        except ValueError:  # a NUL character in the name
            tmp_path = None
            raise WriteError(errno.EINVAL, "the name contains a NUL character", str(named)) from None
        os.close(fd)
        os.chmod(tmp_path, _FILE_MODE)  # as readable as any other result, whatever the umask did
        try:
            yield tmp_path
        except OSError as exc:
            disk = disk_write_error(named, exc)
            if disk is None:
                raise
            raise disk from None
        if group is not None:
            group.done.append((tmp_path, t))
            kept = True
        else:
            _replace(tmp_path, t)
    finally:
        if tmp_path is not None and not kept:
            tmp_path.unlink(missing_ok=True)


def _file_kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISFIFO, "a named pipe"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def _size_text(n: int) -> str:
    return f"{n / 2**20:g} MiB" if n >= 2**20 else f"{n / 2**10:g} KiB" if n >= 2**10 else f"{n} bytes"


def read_bytes_file(
    path: Path | str,
    error: type[Exception] = ReadError,
    expected: str = "a file",
    *,
    max_bytes: int = MAX_CONFIG_BYTES,
    missing: str = "no such file",
) -> bytes:
    """The bytes of ``path``, at most ``max_bytes`` of them; any problem is ``error`` with one line naming it.

    Only a regular file is read: a folder, a named pipe, a device (``/dev/zero``) or a socket is
    refused before anything is read, and opening does not block (``O_NONBLOCK``, then ``fstat``). A file
    larger than ``max_bytes`` is refused, also one that grows past it while being read. ``expected`` says
    what the file should be (e.g. "a YAML file"); ``missing`` is the message for a path that does not exist.
    """
    return bytes(FileBuffer().read(path, error, expected, max_bytes=max_bytes, missing=missing))


class FileBuffer:
    """Reads file after file (:meth:`read`, the checks of :func:`read_bytes_file`) into one buffer that is
    kept and grown, never shrunk: for a stream of images, where a fresh bytes object for each would cost
    its page faults (a 691 kB BMP frame: 0.4–1.2 ms here, against 0.07 ms into a kept buffer)."""

    def __init__(self) -> None:
        self._buffer = bytearray(0)

    def read(
        self,
        path: Path | str,
        error: type[Exception] = ReadError,
        expected: str = "a file",
        *,
        max_bytes: int = MAX_CONFIG_BYTES,
        missing: str = "no such file",
    ) -> memoryview:
        """The bytes of ``path`` as :func:`read_bytes_file` reads them, as a view of this buffer that the next
        read overwrites."""
        p = Path(path)
        fd, size = _open_regular(p, error, expected, max_bytes, missing)
        try:
            if len(self._buffer) < size + 1:  # one byte more than the file: its end is seen in the same read
                self._buffer = bytearray(min(size + 1, max_bytes + 1))
            total = 0
            while True:
                if total == len(self._buffer):  # the file grew while it was read: a larger buffer, same bytes
                    grown = bytearray(min(2 * total + 1, max_bytes + 1))
                    grown[:total] = self._buffer
                    self._buffer = grown
                view = memoryview(self._buffer)
                n = os.readv(fd, [view[total:]])
                if n == 0:
                    return view[:total]
                total += n
                if total > max_bytes:
                    raise error(_too_big(p, max_bytes, expected))
        except OSError as exc:
            raise error(f"{p}: cannot read ({exc.strerror or exc})") from None
        finally:
            os.close(fd)


def _too_big(p: Path, max_bytes: int, expected: str) -> str:
    return f"{p}: larger than {_size_text(max_bytes)}, too large for {expected}"


def _open_regular(p: Path, error: type[Exception], expected: str, max_bytes: int, missing: str) -> tuple[int, int]:
    """``p`` opened for reading without blocking, once ``fstat`` shows a regular file of at most ``max_bytes``
    (else ``error``, nothing read): the descriptor and the size ``fstat`` gave."""
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(p, flags)
    except FileNotFoundError:
        raise error(f"{p}: {missing}") from None
    except IsADirectoryError:
        raise error(f"{p}: is a directory, expected {expected}") from None
    except OSError as exc:
        raise error(f"{p}: cannot read ({exc.strerror or exc})") from None
    except ValueError:  # a NUL character in the name (from a config file, say): no file can be called that
        raise error(f"{p}: not a usable file name (it contains a NUL character)") from None
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise error(f"{p}: is a directory, expected {expected}")
        if not stat.S_ISREG(info.st_mode):
            raise error(f"{p}: {_file_kind(info.st_mode)}, not a regular file; expected {expected}")
        if info.st_size > max_bytes:
            raise error(_too_big(p, max_bytes, expected))
    except OSError as exc:
        os.close(fd)
        raise error(f"{p}: cannot read ({exc.strerror or exc})") from None
    except BaseException:
        os.close(fd)
        raise
    return fd, info.st_size


def read_text_file(path: Path, error: type[Exception], expected: str, *, max_bytes: int = MAX_CONFIG_BYTES) -> str:
    """The UTF-8 text of ``path`` (a regular file of at most ``max_bytes``); any problem becomes ``error``
    with one line naming the file (see :func:`read_bytes_file`).

    ``expected`` says what the file should be, for the messages (e.g. "a YAML file").
    """
    data = read_bytes_file(path, error, expected, max_bytes=max_bytes)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file (expected {expected})") from None


def write_text_atomic(target: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_bytes_atomic(target: str | Path, data: bytes) -> None:
    """Write ``data`` to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
