"""Process handles of the AprilTag helper (:mod:`ipt.receiver.detect.tagworker`): its memory, this process's
thread count (may it fork?), and a forked helper's handle with what of ``subprocess.Popen`` the backend uses."""

from __future__ import annotations

import contextlib
import os
import signal
import time


def rss_anon_kb(pid: int) -> int | None:
    """A process's own resident memory (``RssAnon`` in ``/proc/PID/status``), or None if it is gone."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("RssAnon:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


class Forked:
    """A helper forked by :func:`ipt.receiver.detect.tagworker.prestart`, with the part of ``subprocess.Popen``'s
    interface the backend uses."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped elsewhere: gone all the same
                self.returncode = -1
                return self.returncode
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """Its exit status, once it ended; ``TimeoutError`` after ``timeout`` seconds (where ``Popen.wait`` raises
        ``subprocess.TimeoutExpired``)."""
        if timeout is None and self.returncode is None:
            with contextlib.suppress(ChildProcessError):
                _, status = os.waitpid(self.pid, 0)
                self.returncode = os.waitstatus_to_exitcode(status)
        deadline = time.monotonic() + (timeout or 0.0)
        while (code := self.poll()) is None:
            if time.monotonic() >= deadline:
                raise TimeoutError(f"helper {self.pid} still runs after {timeout or 0.0:g} s")
            time.sleep(0.002)
        return code

    def kill(self) -> None:
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)


def os_threads() -> int:
    """Threads of this process (Python's and native ones, e.g. a BLAS library's), or 0 if unknown."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Threads:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0
