"""Shared fixtures: the default net, a freshly generated net, and one place that shrinks test budgets."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from idas_sumo.resources import DEFAULT_NET

REPO_ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class SmallBudget:
    """Sizes that keep SUMO-backed tests fast (change them here, not in the tests)."""

    episodes: int = 3
    n_vehicles: int = 4
    """Cars per generated scenario (staggered entries, the generator's default otherwise)."""
    max_vehicles_per_road: int = 3
    max_episode_s: float = 20.0
    api_cycles: int = 30
    """num_cycles for the PettingZoo API test."""

    def env_kwargs(self) -> dict[str, Any]:
        """The environments' ``traffic`` and ``config`` at this budget."""
        from idas_sumo.env.engine import EnvConfig
        from idas_sumo.env.scenario import TrafficConfig

        return {
            "traffic": TrafficConfig(
                n_vehicles=self.n_vehicles, max_vehicles_per_road=self.max_vehicles_per_road
            ),
            "config": EnvConfig(max_episode_s=self.max_episode_s),
        }


def pytest_configure(config: pytest.Config) -> None:
    """A suite started in the background (``cmd &`` in a script) inherits SIGINT ignored (under nohup, SIGHUP too),
    and so would every process the signal tests start: they would see no KeyboardInterrupt or hangup. A handler set
    here is reset to the default in each child at exec, so those tests behave as from a terminal."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if signal.getsignal(signal.SIGHUP) == signal.SIG_IGN:  # nohup: the SIGHUP tests need a hangup to land
        signal.signal(signal.SIGHUP, signal.SIG_DFL)


@pytest.fixture(scope="session")
def small_budget() -> SmallBudget:
    return SmallBudget()


@pytest.fixture
def no_leaked_simulation() -> Iterator[None]:
    """Fails a test that leaves this process's SUMO simulation open (``pytest.mark.usefixtures``)."""
    from idas_sumo.sim.backend import slot_taken

    yield
    assert not slot_taken(), "a test left a SUMO simulation open"


@pytest.fixture(scope="session")
def net_path() -> Path:
    """The shipped default network."""
    return DEFAULT_NET


@pytest.fixture(scope="session")
def fresh_net(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The default network regenerated with netconvert into a temporary directory (once per session)."""
    from idas_sumo.sim.netgen import generate_net

    return generate_net(tmp_path_factory.mktemp("net") / "tjunction.net.xml")


@pytest.fixture(scope="session")
def merge_net(net_path: Path):  # type: ignore[no-untyped-def]
    """The committed default network, read and validated."""
    from idas_sumo.sim.netgen import read_merge_net

    return read_merge_net(net_path)


def checkpoint_payload(learner: Any, /, **changes: Any) -> Any:
    """A complete ``TrainingCheckpoint`` around ``learner``, with ``changes`` to its fields (for
    checkpoint tests)."""
    import dataclasses

    import numpy as np
    import torch

    from idas_sumo.training.checkpoint import TrainingCheckpoint
    from idas_sumo.training.config import TrainConfig

    checkpoint = TrainingCheckpoint(
        learner=learner.state_dict(),
        config=TrainConfig(),
        stage="robot",
        stage_index=0,
        episode=7,
        global_episode=7,
        numpy_rng=np.random.default_rng(3).bit_generator.state,
        torch_rng=torch.Generator().manual_seed(3).get_state(),
    )
    return dataclasses.replace(checkpoint, **changes)


# A training run of a few seconds (a TOML for --config).
TINY_TRAIN_TOML = """\
episodes_per_update = 1
checkpoint_every = 1000
max_episode_s = 12.0
[robot_traffic]
n_vehicles = 4
min_vehicles_per_road = 2
max_vehicles_per_road = 2
max_controlled = 1
[intelligent_traffic]
n_vehicles = 4
min_vehicles_per_road = 2
max_vehicles_per_road = 2
"""


def interrupt_when(
    proc: Any, ready: Any, settle_s: float = 0.0, timeout_s: float = 30.0, signum: int | None = None
) -> str:
    """Wait until ``ready()`` (or ``timeout_s``), let ``settle_s`` pass, send Ctrl-C (or ``signum``);
    return stderr.

    Fails if the process ended before it could be interrupted; never leaves it running.
    """
    import signal
    import time

    try:
        deadline = time.monotonic() + timeout_s
        while proc.poll() is None and not ready() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(settle_s)
        assert proc.poll() is None, f"finished before it could be interrupted: {proc.communicate()}"
        proc.send_signal(signal.SIGINT if signum is None else signum)
        _, stderr = proc.communicate(timeout=timeout_s)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return str(stderr)


def evaluate_args(out: Path, net: Path, *extra: str) -> list[str]:
    """``idas-sumo evaluate`` of IDM on ``net`` into ``out``, no progress bar, then ``extra``."""
    return ["evaluate", "--baseline", "idm", "--net", str(net), "--out", str(out), "--no-progress", *extra]


def main_in_process(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """``idas_sumo.cli.main`` in this process: (exit code, stdout, stderr)."""
    from idas_sumo.cli import main

    try:
        code = main(list(args))
    except SystemExit as exit_:  # argparse exits on bad usage
        code = int(exit_.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def run_cli(
    *args: str, cwd: Path | None = None, env: dict[str, str] | None = None, timeout: float = 60.0
) -> subprocess.CompletedProcess[str]:
    """`python -m idas_sumo.cli ARGS` in a child process (repo root by default), output captured."""
    return subprocess.run(
        [sys.executable, "-m", "idas_sumo.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd or REPO_ROOT,
        timeout=timeout,
        env=env if env is not None else {**os.environ, "PYTHONUNBUFFERED": "1"},
    )
