"""Exit codes and signals: 0 ok, 1 runtime failure, 2 bad input (one line on stderr), 130 Ctrl-C, 143
SIGTERM (129 SIGHUP). Every subcommand runs inside ``exit_code``, which maps errors to these codes."""

from __future__ import annotations

import atexit
import contextlib
import errno
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator

from idas_sumo import stops
from idas_sumo.errors import IdasError, InputError

EXIT_OK = 0
EXIT_FAILURE = 1
"""A runtime failure (SUMO died, the disk is full, ...)."""
EXIT_BAD_INPUT = 2
"""Bad usage or bad input: one line on stderr that names the file or flag, no traceback."""
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))
"""Signals that stop a run like Ctrl-C does (cleanup, checkpoint), with exit 128 + the signal."""
INTERRUPTED = "idas-sumo: interrupted; completed outputs were kept"
TERMINATED = "idas-sumo: terminated ({}); completed outputs were kept"
PATH_ERRNOS = frozenset({errno.ENAMETOOLONG, errno.ELOOP})
"""OS errors that say a path the user typed cannot name a file (too long, a symlink loop): bad input."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP), raised where Ctrl-C would be so that the same cleanup runs (checkpoint,
    temp files)."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__(signum)
        self.signum = signum


def in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM, and SIGHUP (the terminal closed) unless it is ignored (``nohup``), raise
    ``Terminated`` (a KeyboardInterrupt) while the command runs, so a stopped run cleans up as after
    Ctrl-C, which raises KeyboardInterrupt as Python's own handler does; the previous handlers come back
    afterwards (main may run in a test). All of them raise through ``stops.raise_stop``, so a stop that
    Python swallows is raised again at the loops' next step (and its "Exception ignored" report is not
    printed)."""
    if not in_main_thread():
        yield  # signal handlers can only be set from the main thread
        return

    def terminate(signum: int, frame: object) -> None:
        stops.raise_stop(Terminated(signum))

    def interrupt(signum: int, frame: object) -> None:
        stops.raise_stop(KeyboardInterrupt())

    handlers: dict[int, Callable[[int, object], None]] = dict.fromkeys(STOP_SIGNALS, terminate)
    # Ctrl-C too, where it has Python's own handler: a Ctrl-C swallowed in C code left `evaluate` running.
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        handlers[signal.SIGINT] = interrupt
    previous = {
        signum: signal.signal(signum, handler)
        for signum, handler in handlers.items()
        if signal.getsignal(signum) is not signal.SIG_IGN
    }
    report = sys.unraisablehook
    sys.unraisablehook = lambda unraisable: (
        None if stops.pending(unraisable.exc_value) else report(unraisable)
    )
    try:
        yield
    finally:
        stops.forget()
        sys.unraisablehook = report
        for signum, handler in previous.items():
            if signal.getsignal(signum) is handlers[signum]:  # LateSignals may own it now: leave it so
                signal.signal(signum, handler)


def forget_caught_interrupt() -> None:
    """Clear CPython's mark of an unhandled Ctrl-C. A KeyboardInterrupt raised inside source run by
    ``exec`` (a dataclass or namedtuple being built during an import) sets that mark even when the
    command catches it, and under ``python -m`` the interpreter then ends itself by SIGINT (returncode
    -2) instead of with our exit code; evaluating any source clears the mark."""
    exec("None")  # a constant source: the reset is all it is for


def stopped(signum: int) -> int:
    """Say that a signal stopped the run; its exit code (130 for Ctrl-C, 143 for SIGTERM, ...)."""
    line = INTERRUPTED if signum == signal.SIGINT else TERMINATED.format(signal.Signals(signum).name)
    with contextlib.suppress(OSError):  # after SIGHUP the terminal may be gone
        print(line, file=sys.stderr)
    return 128 + signum


class LateSignals:
    """Ctrl-C or SIGTERM after the command is done: recorded, not raised.

    Raised there, it would interrupt an exit handler (closing SUMO, removing temp folders) with an
    "Exception ignored in atexit callback" traceback, and the process would still exit 0. Instead the
    cleanup runs to its end and the process exits 130 / 143 with the usual line: the last exit handler
    (registered before any other, so it runs after them all) ends the process with that code.
    """

    def __init__(self) -> None:
        self.caught: int | None = None
        self.reported = False
        atexit.register(self._exit_if_caught)

    def install(self) -> None:
        for signum in (signal.SIGINT, *STOP_SIGNALS):
            if signal.getsignal(signum) is not signal.SIG_IGN:
                signal.signal(signum, self._record)

    def _record(self, signum: int, frame: object) -> None:
        self.caught = self.caught or signum

    def exit_code(self, code: int) -> int:
        """``code``, unless a signal came while it was being reported: then the signal's code."""
        if self.caught is None or self.reported:
            return code
        self.reported = True
        return stopped(self.caught)

    def _exit_if_caught(self) -> None:
        if self.caught is None or self.reported:
            return
        code = self.exit_code(EXIT_OK)
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def exit_code(command: Callable[[], int], late: LateSignals | None) -> int:
    """Run ``command``; a signal or an error becomes its exit code and one line on stderr. ``late``
    takes over the signals once the command is done (``LateSignals``)."""
    try:
        try:
            return command()
        finally:
            if late is not None:
                late.install()
    except KeyboardInterrupt as stop:  # Terminated for SIGTERM / SIGHUP
        return _stopped_by(stop)
    except Exception as err:
        # A stop raised inside C code that calls back into Python (numba unpickling a kernel's
        # constants) comes out as that code's own error, the stop as its cause: still a stop.
        cause = stops.behind(err)
        return _stopped_by(cause) if cause is not None else _error_exit(err)


def _stopped_by(stop: KeyboardInterrupt) -> int:
    stops.forget()
    return stopped(stop.signum if isinstance(stop, Terminated) else signal.SIGINT)


def _error_exit(err: Exception) -> int:
    """The exit code of a failed command and its one line; an error that is not ours is raised again
    (a bug: its traceback is the report)."""
    if isinstance(err, IdasError):
        print(f"idas-sumo: error: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT if isinstance(err, InputError) else err.exit_code
    if isinstance(err, OSError):  # disk full, I/O error: outputs are atomic, so earlier files are intact
        where = f"{err.filename}: " if err.filename else ""
        if err.errno in PATH_ERRNOS:  # the name itself is unusable, wherever the OS noticed
            print(f"idas-sumo: error: {where}{err.strerror}", file=sys.stderr)
            return EXIT_BAD_INPUT
        print(
            f"idas-sumo: error: {where}{err.strerror or err} (files written before are intact)",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    raise err
