"""Shared plumbing of the command-line tools: one-line errors, exit codes, progress."""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable, Sequence
from typing import NoReturn

from ipt.errors import IptError

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


def run_main(prog: str, body: Callable[[Sequence[str] | None], int], argv: Sequence[str] | None) -> int:
    """Run ``body``; a user mistake (:class:`IptError`) becomes one line on stderr and exit code 2."""
    quiet_native_logs()
    try:
        return body(argv)
    except IptError as exc:
        # One line, whatever a file name or key in the message contains.
        print(f"{prog}: error: {one_line(str(exc))}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; nothing was left half-written", file=sys.stderr)
        return 130
