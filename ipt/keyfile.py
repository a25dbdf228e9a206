"""The shared authentication key file, read the same way by the sender, the receiver and any checker.

One rule for every reader (:func:`read_key_file`): a regular file of at most :data:`MAX_KEY_FILE_BYTES`
(no device, pipe or folder; see :func:`ipt.fileio.read_bytes_file`), that other users cannot read or
write (no permission bit for "other": a key anyone on the machine can read authenticates nothing), holding
at least :data:`MIN_KEY_BYTES` bytes once one trailing line break is dropped (keys are often written with
``echo``). Every problem is one :class:`KeyFileError` line naming the file.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from ipt.errors import IptError
from ipt.fileio import read_bytes_file

MIN_KEY_BYTES = 16
"""Shortest key accepted (the protocol's minimum, 128 bits)."""
MAX_KEY_FILE_BYTES = 4096
"""Largest key file read (keys are 16 bytes and up; 32 random bytes is the usual)."""


class KeyFileError(IptError):
    """A key file cannot be used: missing, not a regular file, readable by others, too short."""


def check_key_file_mode(path: Path | str, mode: int) -> None:
    """Raise :class:`KeyFileError` if ``mode`` gives "other" users any permission on the key file ``path``."""
    others = stat.S_IMODE(mode) & stat.S_IRWXO
    if others:
        raise KeyFileError(
            f"{path}: the key file is open to other users (mode {stat.S_IMODE(mode):04o}); "
            f"make it private with: chmod o-rwx {path}"
        )


def read_key_file(path: Path | str) -> bytes:
    """The key in ``path``: its bytes less one trailing line break (``\\n`` or ``\\r\\n``); see the module doc
    for the rule. Raises :class:`KeyFileError` naming the file."""
    p = Path(path)
    key = read_bytes_file(p, KeyFileError, "a key file", max_bytes=MAX_KEY_FILE_BYTES, missing="no such key file")
    for ending in (b"\r\n", b"\n"):
        if key.endswith(ending):
            key = key[: -len(ending)]
            break
    if len(key) < MIN_KEY_BYTES:
        raise KeyFileError(f"{p}: the key is {len(key)} bytes; at least {MIN_KEY_BYTES} are needed")
    try:
        mode = os.stat(p).st_mode
    except OSError as exc:  # removed between the read and the look
        raise KeyFileError(f"{p}: cannot read the key file ({exc.strerror or exc})") from None
    check_key_file_mode(p, mode)
    return key
