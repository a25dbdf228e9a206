"""The stop signals (SIGINT, SIGTERM, SIGHUP): one story for every program, from its first line to its last.

Every command-line tool installs the handler of this module first thing in ``main``
(:func:`ipt.cliutil.run_main` does it, before the heavy imports). Before that, while the tool's modules
load, the console scripts hold the signals back (:mod:`ipt.launch`); ``run_main`` lets them through once
the handler is in place, so one that came meanwhile acts then. From then on:

- **A tool at work** (no event loop running): the first stop signal raises :class:`Interrupted` in the
  main thread, as Ctrl-C raises ``KeyboardInterrupt``. The ``with`` blocks and ``finally`` clauses on
  the way out run, so the temporary ``.partial`` files are removed (:mod:`ipt.fileio`) and nothing that
  looks complete is left; the tool then says in one line that it was interrupted and exits with
  128 + the signal's number (130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP).
- **A daemon** (the sender, the receiver) routes the signals to its own orderly stop as soon as its
  event loop runs (:func:`route_to_loop`): the loop wakes at once, the daemon stops in order and prints
  its final statistics line, exit status 0. A signal that arrives while the loop is set up or runs but
  before the route is set up is kept and delivered when it is (:func:`kept_while_a_loop_runs`); one
  that arrives before (while the daemon reads its configuration) raises :class:`Interrupted`, which the
  daemon's ``main`` turns into the same final line and status.
- A signal that lands inside an import is delivered again once the import is over: raised there, it
  could come out as an ImportError or be lost. So is one whose :class:`Interrupted` Python could only
  print and drop ("Exception ignored in ..."): raised in a function that C code calls back (a ctypes
  callback, such as llvmlite's object cache while numba compiles), a weakref callback or a ``__del__``.
- Only the first signal acts. Later ones, while the program is already stopping, are noted and
  otherwise ignored, so that a cleanup is never cut short half way.

SIGHUP is not a reload: it stops a program like SIGTERM (a closed terminal, ``kill -HUP``).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from types import FrameType
from typing import TYPE_CHECKING

from ipt.errors import IptError

if TYPE_CHECKING:  # not imported at run time: this module loads before anything slow
    import asyncio

STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""The signals that stop every IPT program."""


class SignalsError(IptError):
    """Signals cannot be set up as asked (not the main thread)."""


class Interrupted(BaseException):
    """A stop signal arrived while the program was working; raised from the signal handler in the main thread.

    A ``BaseException`` like ``KeyboardInterrupt``, so that ``except Exception`` clauses let it pass.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

    @property
    def name(self) -> str:
        """The signal's name, e.g. ``SIGTERM``."""
        return signal_name(self.signum)

    @property
    def exit_status(self) -> int:
        """The conventional status of a program ended by this signal: 128 + its number."""
        return 128 + self.signum


def signal_name(signum: int) -> str:
    """``SIGTERM`` for 15, and so on."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class _State:
    received: int | None = None
    """The first stop signal since :func:`install`, if any."""
    quiet = False
    """No more raising: the program is at its end (a daemon's loop has finished)."""
    keep = False
    """No raising: an event loop is being set up or runs (:func:`kept_while_a_loop_runs`)."""


_state = _State()


#: A stop signal that landed in an import or a callback is delivered again this much later (seconds), until it
#: lands where it can act.
IMPORT_RETRY_S = 0.005


def _importing(frame: FrameType | None) -> bool:
    """True if ``frame`` (where the signal landed) is inside an import: Python's import machinery is on the
    stack."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _handle(signum: int, frame: FrameType | None) -> None:
    if _state.received is not None:
        return  # already stopping: never cut a cleanup short
    if _importing(frame):
        # Raising inside an import can come out as an ImportError (a C extension's initialisation turns
        # any exception into one) or vanish (in the import locks' weakref callbacks): a traceback or a
        # signal lost. The signal comes again once the import is over.
        _retry(signum)
        return
    _state.received = signum
    if _state.quiet or _state.keep:
        return
    # asyncio not imported yet, or half way through its import (the signal came during it): no event
    # loop can be running then.
    running_loop = getattr(sys.modules.get("asyncio"), "get_running_loop", None)
    try:
        if running_loop is None:
            raise RuntimeError("no running event loop")
        running_loop()
    except RuntimeError:
        raise Interrupted(signum) from None
    # An event loop runs: raising now could land in one of its callbacks, which would only log it.
    # The loop's owner picks the signal up when it routes the signals (route_to_loop).


def _retry(signum: int) -> None:
    """Send ``signum`` to this process again in :data:`IMPORT_RETRY_S` (from a timer thread)."""
    retry = threading.Timer(IMPORT_RETRY_S, _deliver_again, (signum,))
    retry.daemon = True
    retry.start()


def _unraisable(info: sys.UnraisableHookArgs) -> None:
    """``sys.unraisablehook`` while the handler is installed: an :class:`Interrupted` that Python could not
    raise on (it was raised in a callback from C, a weakref callback, a ``__del__``) is not printed and
    dropped but delivered again, so that it interrupts the program's own code. Anything else goes to the
    hook that was there before."""
    exc = info.exc_value
    if isinstance(exc, Interrupted) and _state.received == exc.signum:
        _state.received = None  # not acted on: the signal comes again
        _retry(exc.signum)
        return
    _previous_unraisable(info)


_previous_unraisable: Callable[[sys.UnraisableHookArgs], object] = sys.unraisablehook


def _deliver_again(signum: int) -> None:
    """A signal that landed in an import or a callback, sent again, unless the program has reached its end or
    another signal has acted meanwhile."""
    if not _state.quiet and _state.received is None:
        os.kill(os.getpid(), signum)


def at_end() -> None:
    """The program is at its end (:func:`ipt.cliutil.run_main` returns): a stop signal from now on is only
    noted, never raised (one sent again after landing in an import reached the end of a quick tool, between
    ``run_main``'s last ``except`` and its return, as an :class:`Interrupted` traceback)."""
    _state.quiet = True


def install() -> Callable[[], None]:
    """Handle the stop signals as the module doc says; returns a function that puts the previous handlers back.

    Call it in the main thread, as early as possible (before slow imports): until it runs, SIGTERM and
    SIGHUP end the process with no word.
    """
    if threading.current_thread() is not threading.main_thread():
        raise SignalsError("the stop signals can only be set up in the main thread")
    global _previous_unraisable
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    previous_hook = sys.unraisablehook
    _state.received, _state.quiet = None, False
    if previous_hook is not _unraisable:
        _previous_unraisable = previous_hook
    sys.unraisablehook = _unraisable
    for sig in STOP_SIGNALS:
        signal.signal(sig, _handle)

    def restore() -> None:
        with blocked():
            for sig, handler in previous.items():
                signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
            sys.unraisablehook = previous_hook

    return restore


def received() -> int | None:
    """The first stop signal received since :func:`install` (also when routed to a loop), or ``None``."""
    return _state.received


def interruption(exc: BaseException) -> Interrupted | None:
    """The stop signal that ``exc`` stands for: ``exc`` itself if it is an :class:`Interrupted`; any other
    exception once a stop signal has arrived (a library that calls back into Python may turn what its callback
    raised into an error of its own: pydantic serialising a path gave a ``PydanticSerializationError`` whose
    message was ``Interrupted: 2``); ``None`` when no stop signal came."""
    if isinstance(exc, Interrupted):
        return exc
    return None if _state.received is None else Interrupted(_state.received)


@contextlib.contextmanager
def blocked() -> Iterator[None]:
    """Hold the stop signals back in this thread while handlers are swapped; they are delivered after."""
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    except (AttributeError, OSError, ValueError):  # no pthread_sigmask here
        yield
        return
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def kept_while_a_loop_runs() -> Iterator[None]:
    """Within: a stop signal is kept, never raised. For the whole life of a daemon's event loop, its
    set-up included: an interruption raised while uvloop starts the loop (before asyncio calls it running)
    left the loop half started and the program ended in a traceback. The daemon routes the signals to its
    loop (:func:`route_to_loop`), which delivers a kept one at once."""
    before = _state.keep
    _state.keep = True
    try:
        yield
    finally:
        _state.keep = before


def route_to_loop(loop: asyncio.AbstractEventLoop, stop: Callable[[int], None]) -> Callable[[], None]:
    """Make the stop signals call ``stop(signum)`` on ``loop`` (asyncio's own handlers, which wake it).

    A signal that came before (kept by this module's handler while the loop ran) calls ``stop`` at once.
    Returns a function that puts back the handlers that were there before and, from then on, only notes
    further signals (the program is at its end). Outside the main thread nothing is routed.
    """
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}

    def on_signal(signum: int) -> None:
        if _state.received is None:
            _state.received = signum
        stop(signum)

    routed: list[signal.Signals] = []
    with blocked():
        for sig in STOP_SIGNALS:
            try:
                loop.add_signal_handler(sig, on_signal, int(sig))
            except (NotImplementedError, RuntimeError, ValueError):  # e.g. Windows: no loop signal handlers
                continue
            routed.append(sig)
    if _state.received is not None:
        loop.call_soon(stop, _state.received)

    def undo() -> None:
        with blocked():
            for sig in routed:
                with contextlib.suppress(Exception):
                    loop.remove_signal_handler(sig)
                handler = previous[sig]
                signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
            if previous.get(signal.SIGTERM) is _handle:
                _state.quiet = True

    return undo
