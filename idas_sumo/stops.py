"""A stop signal (Ctrl-C, SIGTERM) that Python swallowed, raised again at the next safe point.

Python runs a signal handler between any two bytecodes of the main thread: also inside a ctypes
callback (numba's compiler calls llvmlite's while it compiles the engine's kernels), a finalizer or a
``__getattr__`` that C code calls and clears the error of. The handler's exception is then only reported,
or not even that, and the run would go on as if the signal had never come. So the CLI's handlers raise
through ``raise_stop``, which remembers the exception until the command has caught it (``forget``), and
the loops call ``check`` between steps: a stop that was raised but is not being handled now was lost.
"""

from __future__ import annotations

import sys
import threading
from typing import NoReturn

_raised: KeyboardInterrupt | None = None


def raise_stop(stop: KeyboardInterrupt) -> NoReturn:
    """Raise ``stop`` (from a signal handler), remembered until ``forget``."""
    global _raised
    _raised = stop
    raise stop


def forget() -> None:
    """The command caught its stop (or is over): nothing is lost."""
    global _raised
    _raised = None


def pending(exc: BaseException | None) -> bool:
    """Whether ``exc`` is the stop raised and not yet caught (its "Exception ignored" report is noise:
    ``check`` raises it again)."""
    return exc is not None and exc is _raised


def behind(err: BaseException) -> KeyboardInterrupt | None:
    """The stop that ``err`` was raised from (its cause or context, at any depth), if one was: C code
    that calls back into Python turns an exception there into its own error, chained to it."""
    seen: set[int] = set()
    link: BaseException | None = err
    while link is not None and id(link) not in seen:
        if isinstance(link, KeyboardInterrupt):
            return link
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    return None


def check() -> None:
    """Raise again a stop that was raised and lost: one still remembered while no exception is being
    handled (a stop on its way up runs ``except``/``finally`` blocks with it as the current exception),
    in the main thread (the only one a signal handler runs in)."""
    global _raised
    if (
        _raised is not None
        and sys.exc_info()[1] is None
        and threading.current_thread() is threading.main_thread()
    ):
        stop, _raised = _raised, None
        raise stop
