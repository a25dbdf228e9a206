"""AprilTag's C code in a helper process, replaced before its memory leak matters.

AprilTag's C code as pupil-apriltags 1.0.4 and dt-apriltags 3.1.7 ship it (the newest releases; the same
code) leaks 150-600 bytes per ``apriltag_detector_detect`` call:
``quad_segment_maxima`` returns early without freeing two arrays when an outline has fewer than four
corner candidates (found with valgrind; see docs/reliability.md). At 120 frames/s that is 70-260 MB an
hour, and freeing the detector gives none of it back; only the end of the process does. So the receiver
runs the detector in a helper process (:class:`ProcessBackend`) and, once the helper's own memory
(``RssAnon``) grew by ``recycle_mb`` since it warmed up, starts a fresh one in the background and
switches to it when it is ready: no frame waits for a helper to start. A helper that crashes or hangs is
replaced in the same way, and the frame in hand fails with :class:`~ipt.receiver.detect.apriltag_c.DetectorError`.

The image crosses in shared memory (a ``memfd`` both processes map); the request and the detections
cross the helper's stdin and stdout as little-endian binary::

    helper -> parent, once ready:  b"IPTW", u32 n, n bytes of JSON (the settings the C detector holds)
    parent -> helper, per image:   u32 height, u32 width, f64 quad_decimate (0: as made)
                                   (the image, row-major, is in shared memory)
    helper -> parent, per image:   u32 count, count x (i32 id, i32 hamming, f64 margin, 8 x f64 corners)

A helper ends when its stdin closes: when the parent closes it, exits, or is killed. The parent decides
when it ends, and can finish the frame in hand: the helper has a session of its own, so a terminal's
Ctrl-C does not reach it, and it ignores SIGINT and SIGTERM, which systemd sends to every process of the
unit. Linux only (``memfd_create``); elsewhere detection runs inline.

A daemon's first helper is best forked (:func:`prestart`) at the very start, once numpy is loaded and before
any thread or other library: a fork of that lean process costs a few hundredths of a second of processor
time where a new interpreter (``python -m ipt.receiver.detect.tagworker``) costs a tenth, which a restarted
daemon's first pose waits for. The forked helper is given its settings as its first message (u32 n, n bytes of
JSON) when :class:`ProcessBackend` adopts it; helpers started later (replacements) are new interpreters.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import mmap
import os
import select
import signal
import struct
import subprocess
import sys
import threading
import time
import traceback
import weakref
from dataclasses import dataclass, field
from typing import Final, NoReturn

import numpy as np
import numpy.typing as npt

from ipt.receiver.detect.apriltag_c import (
    DetectorError,
    RawDetection,
    make_pupil_detector,
    pupil_detect,
    pupil_settings,
)
from ipt.receiver.detect.helperprocs import Forked, os_threads, rss_anon_kb

MAGIC: Final = b"IPTW"
_U32: Final = struct.Struct("<I")
_REQUEST: Final = struct.Struct("<IId")
_RECORD: Final = struct.Struct("<iid8d")

START_TIMEOUT_S: Final = 60.0
"""A helper that has not said it is ready in this time is given up (a Pi's first start from an SD card
imports numpy slowly; here it takes about 0.3 s)."""
REPLY_TIMEOUT_S: Final = 10.0
"""A helper that takes longer than this over one image is taken to hang, and is replaced."""
WARM_CALLS: Final = 100
"""Calls before a helper's memory is taken as its baseline (the first calls size its working buffers)."""
CHECK_EVERY: Final = 50
"""Calls between two readings of a helper's memory."""
RETIRE_WAIT_S: Final = 5.0
"""A replaced helper that has not ended this long after its stdin closed is killed."""


def process_isolation_available() -> bool:
    """Whether :class:`ProcessBackend` can run here (Linux, with ``memfd_create``)."""
    return sys.platform.startswith("linux") and hasattr(os, "memfd_create")


def _read_exact(fd: int, n: int, deadline: float | None) -> bytes:
    """``n`` bytes from ``fd``; EOFError if it closes first, TimeoutError past ``deadline`` (monotonic)."""
    chunks: list[bytes] = []
    while n > 0:
        if deadline is not None:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([fd], [], [], remaining)[0]:
                raise TimeoutError
        chunk = os.read(fd, n)
        if not chunk:
            raise EOFError
        chunks.append(chunk)
        n -= len(chunk)
    return b"".join(chunks)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


# -- the helper process ------------------------------------------------------------------------------


def encode_detections(dets: list[RawDetection]) -> bytes:
    """A reply: the count, then one record per detection."""
    parts = [_U32.pack(len(dets))]
    parts.extend(
        _RECORD.pack(tag_id, hamming, margin, *corners.reshape(8)) for tag_id, hamming, margin, corners in dets
    )
    return b"".join(parts)


def decode_detections(count: int, body: bytes) -> list[RawDetection]:
    """The detections of a reply's body (``count`` records)."""
    out: list[RawDetection] = []
    for i in range(count):
        rec = _RECORD.unpack_from(body, i * _RECORD.size)
        out.append((rec[0], rec[1], rec[2], np.array(rec[3:], dtype=np.float64).reshape(4, 2)))
    return out


def serve(shm_fd: int, settings: dict[str, float], requests: int, replies: int) -> None:
    """The helper's loop: detect each image the parent announces, until ``requests`` closes."""
    det = make_pupil_detector(settings)
    hello = json.dumps(pupil_settings(det)).encode()
    _write_all(replies, MAGIC + _U32.pack(len(hello)) + hello)
    mapped: mmap.mmap | None = None
    pixels: npt.NDArray[np.uint8] = np.zeros(0, dtype=np.uint8)
    while True:
        try:
            height, width, decimate = _REQUEST.unpack(_read_exact(requests, _REQUEST.size, None))
        except EOFError:
            return
        n = height * width
        if n > pixels.size:  # the parent grew the shared memory for a larger image
            size = os.fstat(shm_fd).st_size
            if mapped is not None:
                del pixels
                mapped.close()
            mapped = mmap.mmap(shm_fd, size)
            pixels = np.frombuffer(mapped, dtype=np.uint8)
        dets = pupil_detect(det, pixels[:n].reshape(height, width), decimate or settings["quad_decimate"])
        _write_all(replies, encode_detections(dets))


def main(argv: list[str] | None = None) -> int:
    """Entry point of the helper (``python -m ipt.receiver.detect.tagworker``); started by :class:`ProcessBackend`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    parser = argparse.ArgumentParser(prog="ipt.receiver.detect.tagworker", description=__doc__.split("\n")[0])
    parser.add_argument("--shm-fd", type=int, required=True, help="the shared image memory (a memfd)")
    parser.add_argument("--settings", required=True, help="the C detector's settings, as JSON")
    args = parser.parse_args(argv)
    # The replies get a descriptor of their own, and anything a library prints goes to stderr instead of
    # into the reply stream.
    replies = os.dup(1)
    os.dup2(2, 1)
    with contextlib.suppress(BrokenPipeError):  # the parent went away mid-reply
        serve(args.shm_fd, json.loads(args.settings), requests=0, replies=replies)
    # No destructors: the detector's memory goes with the process (and the binding's own __del__
    # frees in the wrong order; see free_pupil_detector).
    os._exit(0)


# -- a helper forked from a lean parent ----------------------------------------------------------------


def _forked_main(shm_fd: int, requests: int, replies: int, parent_ends: tuple[int, int]) -> NoReturn:
    """The forked helper: what :func:`main` does in a new interpreter, the settings read from ``requests``."""
    code = 1
    try:
        for fd in parent_ends:
            os.close(fd)
        os.setsid()  # a session of its own, as main()'s helper: the terminal's Ctrl-C is the parent's
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGHUP, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_SETMASK, set())  # the parent may hold its stop signals (ipt.launch)
        os.dup2(2, 1)  # what a library prints goes to stderr
        with contextlib.suppress(OSError), open("/proc/self/comm", "w", encoding="ascii") as comm:
            comm.write("ipt-tagworker")  # its name in top and ps -o comm (its command line is the daemon's)
        gc.enable()  # the parent may hold it off while it starts (ipt.receiver.cli.GcHeldForStartUp)
        (n,) = _U32.unpack(_read_exact(requests, _U32.size, None))
        settings = json.loads(_read_exact(requests, n, None))
        with contextlib.suppress(BrokenPipeError):
            serve(shm_fd, settings, requests, replies)
        code = 0
    except EOFError:  # the parent went away, or had no use for this helper
        code = 0
    except BaseException:
        traceback.print_exc()
    finally:
        os._exit(code)  # never back into the parent's code; no destructors (see main)


@dataclass
class _Prestarted:
    helper: _Helper
    shm_fd: int


_prestarted: _Prestarted | None = None
"""The helper :func:`prestart` forked, until a :class:`ProcessBackend` adopts it (:func:`drop_prestarted`)."""


def prestart() -> bool:
    """Fork the detector's first helper process now, to be adopted by the next :class:`ProcessBackend` of this
    process. Only while this process runs one thread (a fork copies no other thread, and whatever lock one
    held stays held in the child): call it first thing, before the threads and heavy libraries of a daemon.
    Whether a helper was forked (not where the helper process is unavailable, or already done)."""
    global _prestarted
    if _prestarted is not None or not process_isolation_available() or os_threads() != 1:
        return False
    if threading.active_count() != 1:
        return False
    sys.stdout.flush()  # nothing buffered is written twice
    sys.stderr.flush()
    gc.freeze()  # what exists now lives on in both: no collection of either process scans (and copies) it
    shm_fd = os.memfd_create("ipt-tag-image", os.MFD_CLOEXEC)
    requests_r, requests_w = os.pipe()
    replies_r, replies_w = os.pipe()
    try:
        pid = os.fork()
    except OSError:
        for fd in (shm_fd, requests_r, requests_w, replies_r, replies_w):
            os.close(fd)
        return False
    if pid == 0:
        _forked_main(shm_fd, requests_r, replies_w, (requests_w, replies_r))
    os.close(requests_r)
    os.close(replies_w)
    _prestarted = _Prestarted(_Helper(Forked(pid), requests_w, replies_r), shm_fd)
    return True


def _take_prestarted() -> _Prestarted | None:
    global _prestarted
    taken, _prestarted = _prestarted, None
    return taken


def drop_prestarted() -> None:
    """End the helper :func:`prestart` forked if no backend adopted it (the configuration runs AprilTag inline)."""
    taken = _take_prestarted()
    if taken is None:
        return
    helpers = _Helpers([taken.helper], taken.shm_fd)
    helpers.end()


# -- the parent's side -------------------------------------------------------------------------------


@dataclass
class _Helper:
    proc: subprocess.Popen[bytes] | Forked
    requests: int
    """Our end of the helper's stdin."""
    replies: int
    """Our end of the helper's stdout."""
    settings: dict[str, float] | None = None
    """What the helper said it holds, once ready."""
    calls: int = 0
    baseline_kb: int | None = None
    retired_at: float | None = None

    def close_requests(self) -> None:
        """Close our end of the helper's stdin (once: the number may be reused by then)."""
        if self.requests >= 0:
            fd, self.requests = self.requests, -1
            with contextlib.suppress(OSError):
                os.close(fd)

    def close_replies(self) -> None:
        if self.replies >= 0:
            fd, self.replies = self.replies, -1
            with contextlib.suppress(OSError):
                os.close(fd)


@dataclass
class _Helpers:
    """Every helper process not yet reaped, for the finalizer (which must not hold the backend)."""

    live: list[_Helper] = field(default_factory=list)
    shm_fd: int | None = None

    def end(self) -> None:
        for h in self.live:
            h.close_requests()  # the helper exits on end of input
        deadline = time.monotonic() + 0.5
        for h in self.live:
            try:
                h.proc.wait(max(0.0, deadline - time.monotonic()))
            except (subprocess.TimeoutExpired, TimeoutError):  # a new interpreter's, a forked one's
                h.proc.kill()
                h.proc.wait()
            h.close_replies()
        self.live.clear()
        if self.shm_fd is not None:
            os.close(self.shm_fd)
            self.shm_fd = None


class ProcessBackend:
    """The C detector in a helper process; one caller at a time (:class:`TagDetector` holds a lock)."""

    def __init__(
        self,
        settings: dict[str, float],
        *,
        recycle_mb: float = 4.0,
        start_timeout_s: float = START_TIMEOUT_S,
        reply_timeout_s: float = REPLY_TIMEOUT_S,
        warm_calls: int = WARM_CALLS,
        check_every: int = CHECK_EVERY,
        wait: bool = True,
    ) -> None:
        """``wait=False`` returns while the helper still starts (imports take a few tenths of a second):
        the caller does its own set-up meanwhile and calls :meth:`wait_ready`, or the first call waits."""
        if not process_isolation_available():
            raise DetectorError("the detector's helper process needs Linux (memfd_create); use isolation: inline")
        self._settings = dict(settings)
        self.recycle_kb = recycle_mb * 1024
        self.start_timeout_s, self.reply_timeout_s = start_timeout_s, reply_timeout_s
        self.warm_calls, self.check_every = warm_calls, check_every
        self.recycles = 0
        """Helpers replaced (by a ready spare) because their memory grew."""
        self.restarts = 0
        """Helpers replaced because they crashed, hung or failed to start."""
        self._helpers = _Helpers()
        self._finalizer = weakref.finalize(self, self._helpers.end)
        self._mapped: mmap.mmap | None = None
        self._pixels: npt.NDArray[np.uint8] = np.zeros(0, dtype=np.uint8)
        self._current: _Helper | None = None
        self._spare: _Helper | None = None
        prestarted = _take_prestarted()
        if prestarted is not None:
            self._current = self._adopt(prestarted)
        if self._current is None:
            self._helpers.shm_fd = os.memfd_create("ipt-tag-image", os.MFD_CLOEXEC)
            self._current = self._start()
        if wait:
            self._wait_ready(self._current)

    def wait_ready(self) -> None:
        """Wait for the current helper's greeting; :class:`DetectorError` if it did not start."""
        if self._current is not None and self._current.settings is None:
            self._wait_ready(self._current)

    # -- helpers' lives ------------------------------------------------------------------------------

    def _adopt(self, prestarted: _Prestarted) -> _Helper | None:
        """The helper :func:`prestart` forked, given its settings (None if it is gone: a new one is started)."""
        helper = prestarted.helper
        self._helpers.live.append(helper)
        settings = json.dumps(self._settings).encode()
        try:
            _write_all(helper.requests, _U32.pack(len(settings)) + settings)
        except OSError:
            self._end(helper, kill=True)
            os.close(prestarted.shm_fd)
            return None
        self._helpers.shm_fd = prestarted.shm_fd
        return helper

    def _start(self) -> _Helper:
        fd = self._helpers.shm_fd
        assert fd is not None
        cmd = [sys.executable, "-m", "ipt.receiver.detect.tagworker", "--shm-fd", str(fd)]
        cmd += ["--settings", json.dumps(self._settings)]
        try:
            proc = subprocess.Popen(
                cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, pass_fds=(fd,), start_new_session=True
            )
        except OSError as exc:
            raise DetectorError(f"cannot start the tag detector's helper process: {exc}") from exc
        assert proc.stdin is not None
        assert proc.stdout is not None
        # Raw descriptors: the reads below wait with select() and need no Python-level buffering.
        helper = _Helper(proc, os.dup(proc.stdin.fileno()), os.dup(proc.stdout.fileno()))
        proc.stdin.close()
        proc.stdout.close()
        self._helpers.live.append(helper)
        return helper

    def _read_hello(self, helper: _Helper, deadline: float) -> None:
        head = _read_exact(helper.replies, len(MAGIC) + _U32.size, deadline)
        if head[: len(MAGIC)] != MAGIC:
            raise EOFError
        (n,) = _U32.unpack(head[len(MAGIC) :])
        helper.settings = json.loads(_read_exact(helper.replies, n, deadline))

    def _wait_ready(self, helper: _Helper) -> None:
        try:
            self._read_hello(helper, time.monotonic() + self.start_timeout_s)
        except (EOFError, TimeoutError, OSError, ValueError) as exc:
            self._end(helper, kill=True)
            code = helper.proc.returncode
            if isinstance(exc, TimeoutError):
                why = f"no answer in {self.start_timeout_s:g} s"
            else:
                why = f"exit code {code}"
            raise DetectorError(f"the tag detector's helper process did not start ({why}; see its stderr)") from exc

    def _spare_ready(self) -> bool:
        """Whether the spare said it is ready (without waiting); drops a spare that died."""
        spare = self._spare
        if spare is None:
            return False
        if spare.settings is not None:
            return True
        if not select.select([spare.replies], [], [], 0)[0]:
            return False
        try:
            self._read_hello(spare, time.monotonic() + self.start_timeout_s)
        except (EOFError, TimeoutError, OSError, ValueError):
            self._end(spare, kill=True)
            self._spare = None
            self.restarts += 1
            return False
        return True

    def _end(self, helper: _Helper, *, kill: bool) -> None:
        """Close a helper's input (it exits) or kill it; it is reaped later, or now if killed."""
        if kill:
            helper.proc.kill()
            helper.proc.wait()
            helper.close_requests()
            helper.close_replies()
            if helper in self._helpers.live:
                self._helpers.live.remove(helper)
            return
        helper.close_requests()
        helper.retired_at = time.monotonic()

    def _reap(self) -> None:
        """Collect replaced helpers that have exited; kill those that outstay :data:`RETIRE_WAIT_S`."""
        now = time.monotonic()
        for helper in list(self._helpers.live):
            if helper.retired_at is None:
                continue
            if helper.proc.poll() is None:
                if now - helper.retired_at < RETIRE_WAIT_S:
                    continue
                helper.proc.kill()
                helper.proc.wait()
            helper.close_replies()
            self._helpers.live.remove(helper)

    def _helper(self) -> _Helper:
        """The helper to use now: the current one, a ready spare, or a new one (waited for)."""
        if self._spare is not None and self._spare_ready():
            old, self._current, self._spare = self._current, self._spare, None
            if old is not None:
                self._end(old, kill=False)
                self.recycles += 1
        if self._current is None:
            helper = self._spare or self._start()
            self._spare = None
            if helper.settings is None:
                self._wait_ready(helper)
            self._current = helper
        elif self._current.settings is None:
            self._wait_ready(self._current)
        return self._current

    def _after_call(self, helper: _Helper) -> None:
        helper.calls += 1
        if helper.calls < self.warm_calls or helper.calls % self.check_every:
            return
        self._reap()
        rss = rss_anon_kb(helper.proc.pid)
        if rss is None:
            return
        if helper.baseline_kb is None:
            helper.baseline_kb = rss
        elif rss - helper.baseline_kb > self.recycle_kb and self._spare is None:
            self._spare = self._start()  # takes over once it is ready (see _helper)

    # -- the interface -------------------------------------------------------------------------------

    @property
    def helper_pids(self) -> list[int]:
        """Process ids of the helpers alive now (the current one first)."""
        pids = [h.proc.pid for h in self._helpers.live if h is self._current]
        return pids + [h.proc.pid for h in self._helpers.live if h is not self._current]

    def _ensure_capacity(self, n: int) -> None:
        if n <= self._pixels.size:
            return
        fd = self._helpers.shm_fd
        assert fd is not None
        size = max(n, 640 * 480)
        os.ftruncate(fd, size)
        if self._mapped is not None:
            self._pixels = np.zeros(0, dtype=np.uint8)
            self._mapped.close()
        self._mapped = mmap.mmap(fd, size)
        self._pixels = np.frombuffer(self._mapped, dtype=np.uint8)

    def detect_raw(self, gray: npt.NDArray[np.uint8], decimate: float | None = None) -> list[RawDetection]:
        if not self._finalizer.alive:
            raise DetectorError("the detector was closed")
        height, width = gray.shape
        n = height * width
        self._ensure_capacity(n)
        self._pixels[:n] = gray.reshape(-1)
        helper = self._helper()
        try:
            _write_all(helper.requests, _REQUEST.pack(height, width, decimate or 0.0))
            deadline = time.monotonic() + self.reply_timeout_s
            (count,) = _U32.unpack(_read_exact(helper.replies, _U32.size, deadline))
            dets = decode_detections(count, _read_exact(helper.replies, count * _RECORD.size, deadline))
        except (OSError, EOFError, TimeoutError) as exc:
            self._end(helper, kill=True)
            self._current = None
            self.restarts += 1
            code = helper.proc.returncode
            what = "hung" if isinstance(exc, TimeoutError) else f"ended (exit code {code})"
            raise DetectorError(f"the tag detector's helper process {what}; a new one takes the next frame") from exc
        self._after_call(helper)
        return dets

    def settings(self) -> dict[str, float]:
        settings = self._helper().settings
        assert settings is not None
        return dict(settings)

    def close(self) -> None:
        """End every helper (each within 0.5 s, or killed) and free the shared memory."""
        self._current = self._spare = None
        self._pixels = np.zeros(0, dtype=np.uint8)
        if self._mapped is not None:
            self._mapped.close()
            self._mapped = None
        self._finalizer()


if __name__ == "__main__":
    sys.exit(main())
