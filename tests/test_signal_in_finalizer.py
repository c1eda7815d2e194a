"""A stop signal that lands inside a finalizer still stops the command (``cli.exits.sigterm_as_interrupt``).

Python runs signal handlers between any two bytecodes of the main thread, also inside ``__del__``; the
KeyboardInterrupt raised there is only reported ("Exception ignored in ..."), so without a second delivery
the run went on as if nothing had come."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

SCRIPT = """
import gc, sys, time
from idas_sumo.cli.exits import Terminated, sigterm_as_interrupt

class SlowToDie:
    def __del__(self):
        print("in finalizer", flush=True)
        end = time.monotonic() + 1.5
        while time.monotonic() < end:  # the signal comes now, inside __del__
            pass

try:
    with sigterm_as_interrupt():
        obj = SlowToDie()
        del obj
        end = time.monotonic() + 10.0
        while time.monotonic() < end:
            time.sleep(0.01)
        print("survived", flush=True)
except KeyboardInterrupt as stop:  # Terminated for SIGTERM
    signum = stop.signum if isinstance(stop, Terminated) else 2
    print("stopped", signum, flush=True)
    sys.exit(128 + signum)
"""


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_inside_a_finalizer_still_stops_the_run(signum: int) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", SCRIPT], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "in finalizer"
        time.sleep(0.3)
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=8)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert "survived" not in out, err
    assert proc.returncode == 128 + signum, (out, err)
