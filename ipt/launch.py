"""The console scripts' entry points (``ipt``, ``ipt-sender``, ``ipt-receiver``): stop signals held from the
first line.

A tool's ``main`` handles the stop signals (:mod:`ipt.signals`) only once its module is imported, and that
takes 20-50 ms; a Ctrl-C in that time came out as a ``KeyboardInterrupt`` traceback. So this module, the
first of IPT that a console script imports (``ipt/__init__`` only sets the version), holds SIGINT, SIGTERM and
SIGHUP back (blocked, not lost) while it loads, and :func:`ipt.cliutil.run_main` lets them through once its
handlers are in place: a signal from this moment on ends the tool with its own one line and 128 + the
signal's number. (Before this module runs the interpreter itself is starting, about 10-15 ms: a signal then
ends Python as it ends any program, without a line.)

Importing this module holds the signals in the calling thread until a tool's ``run_main`` runs, and again
once it is done (:func:`hold`): import it only as an entry point.
"""

# The interpreter's own C module, loaded before any Python code runs: nothing to import before the signals are
# held (``import signal`` would cost 0.5 ms of the window). It has no type stubs; the calls are signal's own.
import _signal  # type: ignore[import-not-found]

_STOP: set[int] = {_signal.SIGINT, _signal.SIGTERM, _signal.SIGHUP}
_OURS = frozenset(_STOP - _signal.pthread_sigmask(_signal.SIG_BLOCK, _STOP))
"""The stop signals this module holds (one blocked already, by whoever started us, stays so)."""
_holding = True


def release() -> None:
    """Let the held stop signals through (one that came meanwhile is delivered now), in the thread that imported
    this module. :func:`ipt.cliutil.run_main` calls it once its handlers are in place."""
    global _holding
    if _holding and _OURS:
        _signal.pthread_sigmask(_signal.SIG_UNBLOCK, _OURS)
    _holding = False


def hold() -> None:
    """Hold the stop signals again: the tool is done (:func:`ipt.cliutil.run_main` is about to put Python's own
    handlers back, and Python's SIGINT handler would end the finished tool in a ``KeyboardInterrupt``
    traceback). The process exits with the tool's status; a signal that came at the end is not delivered."""
    global _holding
    if not _holding and _OURS:
        _signal.pthread_sigmask(_signal.SIG_BLOCK, _OURS)
    _holding = True


def ipt() -> int:
    """``ipt``."""
    from ipt.cli import main

    return main()


def sender() -> int:
    """``ipt-sender``."""
    from ipt.sender.cli import main

    return main()


def receiver() -> int:
    """``ipt-receiver``."""
    from ipt.receiver.cli import main

    return main()
