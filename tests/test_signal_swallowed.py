"""A stop signal whose exception Python can only report still stops the command
(``cli.exits.sigterm_as_interrupt``).

Python runs a signal handler between any two bytecodes of the main thread: also inside a ctypes callback
(numba's compiler calls llvmlite's while it compiles the engine's kernels, the first second of a fresh
install's run) and inside ``__del__``. An exception raised there is only reported ("Exception ignored
...") and the run went on as if the signal had never come: ``stops.check`` raises it again."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

SCRIPT = """
import ctypes, sys, time
from idas_sumo import stops
from idas_sumo.cli.exits import Terminated, sigterm_as_interrupt

def busy():
    print("inside", flush=True)
    end = time.monotonic() + 1.5
    while time.monotonic() < end:  # the signal comes now
        pass
    return 0

class SlowToDie:
    def __del__(self):
        busy()

try:
    with sigterm_as_interrupt():
        {inside}
        end = time.monotonic() + 10.0
        while time.monotonic() < end:  # the episode loop: a step, then stops.check()
            time.sleep(0.01)
            stops.check()
        print("survived", flush=True)
except KeyboardInterrupt as stop:  # Terminated for SIGTERM
    signum = stop.signum if isinstance(stop, Terminated) else 2
    print("stopped", signum, flush=True)
    sys.exit(128 + signum)
"""
INSIDE = {
    # called from C through ctypes (as llvmlite's callbacks are): its exceptions are only reported
    "ctypes_callback": "ctypes.CFUNCTYPE(ctypes.c_int)(busy)()",
    "finalizer": "obj = SlowToDie(); del obj",
}


@pytest.mark.parametrize("where", sorted(INSIDE))
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_whose_exception_is_swallowed_still_stops_the_run(where: str, signum: int) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", SCRIPT.format(inside=INSIDE[where])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "inside"
        time.sleep(0.3)
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=8)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert "survived" not in out, err
    assert proc.returncode == 128 + signum, (out, err)
    assert "Exception ignored" not in err  # the stop was handled, not reported as lost


@pytest.mark.sumo
def test_the_episode_loop_raises_a_swallowed_stop_again(net_path: Path) -> None:
    """The real loop: a stop raised and swallowed (as by a ctypes callback) before an episode is raised
    again at its first step; once the command caught it (``forget``), nothing is raised."""
    from idas_sumo import stops
    from idas_sumo.baselines.policies import RuleBasedPolicy
    from idas_sumo.env.config import EnvConfig
    from idas_sumo.env.engine import MergeEngine
    from idas_sumo.env.episodes import run_episodes
    from idas_sumo.env.scenario import Scenario, VehicleSpec

    scenario = Scenario(
        name="one", vehicles=[VehicleSpec(id="car", road="main", start_pos_m=50.0, speed_mps=10.0)]
    )
    stop = KeyboardInterrupt()
    engine = MergeEngine(net_path, config=EnvConfig(max_episode_s=5.0))
    try:
        with contextlib.suppress(KeyboardInterrupt):  # as Python does inside a callback it only reports
            stops.raise_stop(stop)
        with pytest.raises(KeyboardInterrupt) as raised:
            run_episodes(engine, [scenario], lambda job, agent: 0, [RuleBasedPolicy("idm")])
        assert raised.value is stop
        (outcome,) = run_episodes(engine, [scenario], lambda job, agent: 0, [RuleBasedPolicy("idm")])
    finally:
        stops.forget()
        engine.close()
    assert outcome.end_reasons == {"car": "timeout"}  # the episode ran to its end (5 s)


def test_a_stop_that_c_code_turned_into_its_own_error_is_still_a_stop(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """numba unpickling a kernel's constants calls Python from C: a SIGTERM landing there came out as
    ``SystemError: ... returned a result with an exception set`` (the stop its cause), and evaluate
    ended with a traceback and exit 1 (CI, 2026-11-26). It is the stop: exit 143, the usual line."""
    from idas_sumo import stops
    from idas_sumo.cli.exits import Terminated, exit_code

    def command() -> int:
        try:
            stops.raise_stop(Terminated(signal.SIGTERM))
        except KeyboardInterrupt as stop:
            raise SystemError("<function _numba_unpickle> returned a result with an exception set") from stop
        return 0

    assert exit_code(command, None) == 143
    assert capsys.readouterr().err.strip() == "idas-sumo: terminated (SIGTERM); completed outputs were kept"
    stops.check()  # forgotten once reported: nothing is raised again

    def bug() -> int:
        raise SystemError("a bug of ours")

    with pytest.raises(SystemError, match="a bug of ours"):
        exit_code(bug, None)
