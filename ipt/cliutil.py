"""Shared plumbing of the command-line tools: one-line errors, exit codes, stop signals, progress.

Kept light (standard library only): the tools import it before anything slow, so that the stop
signals are handled from the first moment (:mod:`ipt.signals`).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import threading
from collections.abc import Callable, Sequence
from typing import NoReturn

from ipt import signals
from ipt.errors import IptError
from ipt.signals import Interrupted

EXIT_USAGE = 2


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (with a pointer to --help) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def positive_float(text: str) -> float:
    """An argparse ``type``: a finite number above zero (``nan``, ``inf`` and ``0`` are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: '{text}'") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got '{text}'")
    return value


def bounded_float(low: float, high: float, unit: str = "") -> Callable[[str], float]:
    """An argparse ``type``: a number above ``low`` and at most ``high`` (``nan`` and ``inf`` are refused)."""

    def parse(text: str) -> float:
        value = positive_float(text) if low == 0 else _float(text)
        if not (math.isfinite(value) and low < value <= high):
            raise argparse.ArgumentTypeError(f"must be above {low:g} and at most {high:g}{unit}, got '{text}'")
        return value

    return parse


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: '{text}'") from None


SEED_MAX = 2**32 - 1
"""The largest ``--seed`` the tools take."""


def seed_int(text: str) -> int:
    """An argparse ``type``: a random seed, a whole number from 0 to :data:`SEED_MAX`."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: '{text}'") from None
    if not 0 <= value <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"must be a whole number from 0 to {SEED_MAX}, got '{text}'")
    return value


def same_file(a: str, b: str) -> bool:
    """True if the paths ``a`` and ``b`` name one file: the same path once links are followed (also when it does
    not exist yet), or the same inode (a hard link). Two outputs of one command must not be one file."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):  # one of them does not exist yet (or holds a NUL): two different files
        return False


def one_line(text: str) -> str:
    """``text`` with line breaks and other control characters shown escaped, so it prints as one line."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def quiet_native_logs() -> None:
    """Keep OpenCV's own log lines (``[ WARN:0@0.03] ... imread_(...)``) off stderr.

    The tools check every result they get from OpenCV and say what went wrong in one line of their own;
    OpenCV would print a second, cryptic one first. It reads ``OPENCV_LOG_LEVEL`` when it is loaded, so
    this must run before the first ``import cv2``; a level set by the user (e.g. ``WARNING``, to debug a
    camera) is kept.
    """
    os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")


def _file_names_print_as_given() -> None:
    """Let stdout print any file name the user gave, also one that is not valid UTF-8.

    Python decodes such a name with surrogate escapes; written back with ``surrogateescape`` it shows
    the user's own bytes instead of ending the tool with a ``UnicodeEncodeError``. (stderr already
    escapes them with backslashes, and error lines go through :func:`one_line`.)
    """
    with contextlib.suppress(AttributeError, ValueError, OSError):
        sys.stdout.reconfigure(errors="surrogateescape")  # type: ignore[union-attr]


def _launcher(action: str) -> None:
    """The console scripts hold the stop signals while the tool loads (:mod:`ipt.launch`). ``release``: the
    handlers are in place, let them through (one that came while loading is delivered now and stops the tool in
    order). ``hold``: the tool is done, hold them again before Python's own handlers come back."""
    do = getattr(sys.modules.get("ipt.launch"), action, None)
    if do is not None:
        do()


def run_main(
    prog: str,
    body: Callable[[Sequence[str] | None], int],
    argv: Sequence[str] | None,
    *,
    on_interrupt: Callable[[Interrupted], int] | None = None,
) -> int:
    """Run ``body``; a user mistake (:class:`IptError`) becomes one line on stderr and exit code 2.

    The stop signals are handled from here on (:mod:`ipt.signals`): one arriving while ``body`` works
    unwinds it (temporary files are removed on the way), then ``on_interrupt`` decides what is said and
    the exit status; by default one line ``PROG: interrupted by SIGTERM; ...`` and 128 + the signal's
    number. The previous signal handlers are put back when ``body`` returns.
    """
    main_thread = threading.current_thread() is threading.main_thread()
    restore = signals.install() if main_thread else (lambda: None)
    try:
        quiet_native_logs()
        _file_names_print_as_given()
        try:
            if main_thread:
                _launcher("release")
            return body(argv)
        except IptError as exc:
            # One line, whatever a file name or key in the message contains.
            print(f"{prog}: error: {one_line(str(exc))}", file=sys.stderr)
            return EXIT_USAGE
        except Exception as exc:  # a library's own error around the Interrupted its callback raised
            if (stop := signals.interruption(exc)) is None:
                raise
            raise stop from exc
    except Interrupted as exc:
        if on_interrupt is not None:
            return on_interrupt(exc)
        print(f"{prog}: interrupted by {exc.name}; nothing was left half-written", file=sys.stderr)
        return exc.exit_status
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; nothing was left half-written", file=sys.stderr)
        return 130
    finally:
        if main_thread:
            signals.at_end()
            _launcher("hold")
        restore()
