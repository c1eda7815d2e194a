"""The second simulation of a process runs SUMO in a child process that does not re-import ``__main__``."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

TWO_ENVS_WITHOUT_MAIN_GUARD = """\
import numpy as np

from idas_sumo.env import MergeParallelEnv
from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.sim.backend import SubprocessBackend

traffic = TrafficConfig(n_vehicles=4, min_vehicles_per_road=2, max_vehicles_per_road=2)
first = MergeParallelEnv(traffic=traffic, seed=1)
second = MergeParallelEnv(traffic=traffic, seed=1)
obs_a, _ = first.reset(seed=1)
obs_b, _ = second.reset(seed=1)
assert isinstance(second.sim.backend, SubprocessBackend)
for _ in range(5):
    actions = {a: int(np.flatnonzero(obs_a[a]["action_mask"])[0]) for a in first.agents}
    obs_a, *_ = first.step(actions)
    obs_b, *_ = second.step(actions)
    for agent in obs_a:
        assert np.array_equal(obs_a[agent]["observation"], obs_b[agent]["observation"])
first.close()
second.close()
print("TOP-LEVEL RAN")
"""


@pytest.mark.sumo
def test_script_without_main_guard_runs_two_envs(tmp_path: Path) -> None:
    # multiprocessing's "spawn" re-imports __main__ in the child: this script would run itself again
    # there and fail. The child must start without importing the user's script.
    script = tmp_path / "two_envs.py"
    script.write_text(TWO_ENVS_WITHOUT_MAIN_GUARD)
    result = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("TOP-LEVEL RAN") == 1, result.stdout
    assert "Traceback" not in result.stderr, result.stderr[-3000:]


CTRL_C_WHILE_TWO_ENVS_RUN = """\
import sys

from idas_sumo.env import MergeParallelEnv

first = MergeParallelEnv(seed=1)
second = MergeParallelEnv(seed=1)
first.reset()
second.reset()  # the backend is chosen here: SUMO in a child process
print("CHILD", second.sim.backend._proc.pid, flush=True)
try:
    while True:
        for env in (first, second):
            if not env.agents:
                env.reset()
            env.step(dict.fromkeys(env.agents, 2))
            print("STEP", flush=True)
except KeyboardInterrupt:
    print("interrupted", file=sys.stderr)
    sys.exit(130)  # no close(): the child must still go away with the parent
"""


@pytest.mark.sumo
@pytest.mark.skipif(sys.platform == "win32", reason="process groups and signals are POSIX here")
def test_ctrl_c_reaches_only_the_parent_and_the_child_goes_away(tmp_path: Path) -> None:
    # A terminal's Ctrl-C signals the whole foreground process group; the child must not print its
    # own KeyboardInterrupt traceback, and must not outlive the parent.
    script = tmp_path / "ctrl_c.py"
    script.write_text(CTRL_C_WHILE_TWO_ENVS_RUN)
    proc = subprocess.Popen(
        [sys.executable, str(script)],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own group, so killpg below plays the terminal
    )
    try:
        assert proc.stdout is not None
        child_pid = 0
        steps = 0
        deadline = time.monotonic() + 60.0
        while steps < 10 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            assert line, f"ended early: {proc.communicate()}"
            if line.startswith("CHILD"):
                child_pid = int(line.split()[1])
            steps += line.startswith("STEP")
        assert child_pid > 0 and steps == 10
        os.killpg(proc.pid, signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, stderr
    assert stderr.strip() == "interrupted", stderr
    assert _gone(child_pid, within_s=10.0)


def _gone(pid: int, within_s: float) -> bool:
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.sumo
def test_errors_in_the_child_are_raised_in_the_parent(
    merge_net: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    from idas_sumo.env.scenario import Scenario, VehicleSpec
    from idas_sumo.errors import InputError, SimulationError
    from idas_sumo.sim.backend import SubprocessBackend

    backend = SubprocessBackend(merge_net)
    try:
        backend.reset(Scenario("one", (VehicleSpec("ego", "main", 50.0, 10.0),)))
        backend.step()
        with pytest.raises(SimulationError, match=r"invalid speed command nan for vehicle 'ego'"):
            backend.set_speeds({"ego": float("nan")})
        with pytest.raises(AttributeError, match="no_such_method"):
            backend.raw_call("vehicle", "no_such_method")
        assert backend.vehicle_states().ids == ("ego",)  # still serving after the errors
    finally:
        backend.close()

    # The child's environment is the parent's: no display there either, the same InputError here.
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    gui = SubprocessBackend(merge_net, gui=True)
    try:
        with pytest.raises(InputError, match="--gui needs a display"):
            gui.reset(Scenario("one", (VehicleSpec("ego", "main", 50.0, 10.0),)))
    finally:
        gui.close()


@pytest.mark.sumo
@pytest.mark.skipif(sys.platform == "win32", reason="SIGSTOP is POSIX")
def test_close_kills_a_stuck_child(merge_net: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    import idas_sumo.sim.backend as backend_module
    from idas_sumo.errors import SimulationError

    monkeypatch.setattr(backend_module, "_CHILD_CLOSE_TIMEOUT_S", 0.5)
    backend = backend_module.SubprocessBackend(merge_net)
    pid = backend._proc.pid
    os.kill(pid, signal.SIGSTOP)  # stuck: it will never answer "close"
    started = time.monotonic()
    backend.close()
    assert time.monotonic() - started < 5.0
    assert backend._proc.returncode == -signal.SIGKILL
    backend.close()  # a second close does nothing
    with pytest.raises(SimulationError, match="closed"):
        backend.step()


class _NeedsTwoArgs(Exception):
    def __init__(self, a: str, b: str) -> None:  # pickle rebuilds exceptions from args: this one fails
        super().__init__(f"{a} {b}")


def test_an_error_that_cannot_be_pickled_travels_as_a_simulation_error() -> None:
    from idas_sumo.errors import SimulationError
    from idas_sumo.sim.backend import _portable_error

    plain = ValueError("bad value")
    assert _portable_error(plain) is plain
    odd = _portable_error(_NeedsTwoArgs("x", "y"))
    assert isinstance(odd, SimulationError)
    assert str(odd) == "_NeedsTwoArgs in the SUMO subprocess: x y"


# --- the handshake every child goes through (sim/rpc.py) ------------------------------------------------


def _both_sides(key_a: bytes, key_b: bytes) -> list[BaseException | None]:
    """Run the handshake over a socket pair, the accepting side with ``key_a``, the child with ``key_b``;
    what each side raised (None: it got its connection)."""
    import socket
    import threading

    from idas_sumo.sim.rpc import authenticated

    a, b = socket.socketpair()
    outcome: list[BaseException | None] = [None, None]

    def side(i: int, sock: socket.socket, key: bytes, first: bool) -> None:
        try:
            authenticated(sock, key, challenge_first=first, timeout_s=5.0).close()
        except BaseException as err:
            outcome[i] = err

    child = threading.Thread(target=side, args=(1, b, key_b, False))
    child.start()
    side(0, a, key_a, True)
    child.join(10.0)
    return outcome


def test_the_handshake_needs_the_same_key_on_both_sides() -> None:
    from multiprocessing import AuthenticationError

    assert _both_sides(b"k" * 32, b"k" * 32) == [None, None]
    refused = _both_sides(b"k" * 32, b"x" * 32)
    assert isinstance(refused[0], AuthenticationError) and isinstance(refused[1], AuthenticationError)


def test_a_caller_that_trickles_bytes_is_dropped_at_the_handshake_deadline() -> None:
    """The deadline bounds the whole handshake, not each read: one byte every 0.2 s cannot hold it open."""
    import socket
    import threading

    from idas_sumo.sim.rpc import authenticated

    ours, theirs = socket.socketpair()
    stop = threading.Event()

    def trickle() -> None:
        with contextlib.suppress(OSError):
            theirs.sendall(b"\0\0\0\x20")  # "32 bytes follow", then one every 0.2 s: 6.4 s in all
            while not stop.wait(0.2):
                theirs.sendall(b"\0")

    sender = threading.Thread(target=trickle)
    sender.start()
    started = time.monotonic()
    try:
        with pytest.raises(TimeoutError):
            authenticated(ours, b"k" * 32, challenge_first=True, timeout_s=1.0)
        assert time.monotonic() - started < 3.0
        assert ours.fileno() == -1  # closed on failure
    finally:
        stop.set()
        sender.join()
        theirs.close()
