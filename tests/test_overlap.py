"""The critics' step in the background (``Learner(critics_in_background=True)``, what training runs with
``IDAS_SUMO_OVERLAP_UPDATE=1``) gives
the serial update's weights bit for bit, and the training loop's results do not depend on it."""

from __future__ import annotations

import csv
import dataclasses
import threading
from pathlib import Path
from typing import Any

import pytest
import torch
from test_agents_networks import random_batch

from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import TrainConfig
from idas_sumo.training.loop import OVERLAP_UPDATE_ENV

ROWS = 600  # enough rows that the update's kernels split over both threads
NETS = ("actor", "value", "central")


def assert_same_tensors(a: Any, b: Any, where: str = "") -> None:
    """``a`` and ``b`` (nested dicts/lists of tensors and plain values) are equal, tensors bit for bit."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and torch.equal(a, b), f"{where} differs"
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{where}: keys differ"
        for k in a:
            assert_same_tensors(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, list | tuple):
        assert isinstance(b, list | tuple) and len(a) == len(b), f"{where}: lengths differ"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same_tensors(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


@pytest.mark.parametrize("central", [False, True])
def test_background_critics_give_the_serial_weights_bit_for_bit(central: bool) -> None:
    config = LearnerConfig(use_central_critic=central)
    serial, background = Learner(config, seed=3), Learner(config, seed=3, critics_in_background=True)
    for step in range(4):
        batch = random_batch(seed=step, n=ROWS)
        assert serial.update(batch) == background.update(batch)
    assert_same_tensors(serial.state_dict(), background.state_dict())


def test_begin_update_returns_before_the_critics_step_and_state_dict_waits(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The actor has stepped when ``begin_update`` returns; V and Q step later, and ``state_dict`` (what a
    checkpoint holds) has them after their step."""
    release = threading.Event()
    real_step = Learner._step_value_critic

    def gated_step(self: Learner, *args: Any) -> Any:
        assert release.wait(timeout=20), "the critic step was waited for before the update returned"
        return real_step(self, *args)

    monkeypatch.setattr(Learner, "_step_value_critic", gated_step)
    learner = Learner(LearnerConfig(use_central_critic=True), seed=0, critics_in_background=True)
    before = {net: {n: t.clone() for n, t in learner.state_dict()[net].items()} for net in NETS}
    pending = learner.begin_update(random_batch(n=64))
    # The critics have not moved (their step waits for `release`), the actor has.
    assert all(torch.equal(t, before["value"][n]) for n, t in learner.value.state_dict().items())
    assert all(torch.equal(t, before["central"][n]) for n, t in learner.central.state_dict().items())
    assert not all(torch.equal(t, before["actor"][n]) for n, t in learner.actor.state_dict().items())
    release.set()
    state = learner.state_dict()
    for net in ("value", "central"):
        assert not all(torch.equal(t, before[net][n]) for n, t in state[net].items()), net
    assert pending.stats()["v_loss"] > 0.0


def test_an_error_in_the_background_step_is_raised_by_the_next_call(monkeypatch: pytest.MonkeyPatch) -> None:
    def failing_step(self: Learner, *args: Any) -> Any:
        raise RuntimeError("critic step failed")

    monkeypatch.setattr(Learner, "_step_value_critic", failing_step)
    learner = Learner(LearnerConfig(), seed=0, critics_in_background=True)
    pending = learner.begin_update(random_batch())
    with pytest.raises(RuntimeError, match="critic step failed"):
        pending.stats()
    with pytest.raises(RuntimeError, match="critic step failed"):
        learner.finish_critics()
    learner.finish_critics()  # raised; nothing is pending any more


def tiny_config(**changes: Any) -> TrainConfig:
    """Both stages (V alone, then V and Q), rounds of 2 episodes, a checkpoint and a validation inside
    each stage: every place the loop reads the critics."""
    base = TrainConfig(
        robot_episodes=6,
        intelligent_episodes=6,
        robot_traffic=TrafficConfig(
            n_vehicles=0, min_vehicles_per_road=2, max_vehicles_per_road=3, max_controlled=2
        ),
        intelligent_traffic=TrafficConfig(n_vehicles=0, min_vehicles_per_road=2, max_vehicles_per_road=3),
        episodes_per_update=2,
        checkpoint_every=4,
        validate_every=4,
        validation_scenarios=1,
        max_episode_s=12.0,
    )
    return dataclasses.replace(base, **changes)


def rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return [{k: v for k, v in r.items() if k != "wall_time_s"} for r in csv.DictReader(f)]


@pytest.mark.sumo
@pytest.mark.parametrize("workers", [1, 2])
def test_overlapped_training_equals_serial_training(
    net_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, workers: int
) -> None:
    from idas_sumo.training.loop import run_training

    config = tiny_config(workers=workers)
    run_training(net_path, config, tmp_path / "serial", progress=False)
    monkeypatch.setenv(OVERLAP_UPDATE_ENV, "1")
    run_training(net_path, config, tmp_path / "overlapped", progress=False)

    for name in ("robot.pt", "robot_best.pt", "intelligent.pt", "intelligent_best.pt", "checkpoint.pt"):
        a, b = load_checkpoint(tmp_path / "overlapped" / name), load_checkpoint(tmp_path / "serial" / name)
        assert_same_tensors(a.learner, b.learner, name)
    for csv_name in ("metrics.csv", "validation.csv"):
        overlapped, serial = rows(tmp_path / "overlapped" / csv_name), rows(tmp_path / "serial" / csv_name)
        assert overlapped == serial
    metrics = rows(tmp_path / "overlapped" / "metrics.csv")
    assert len(metrics) == 12 and float(metrics[-1]["q_loss"]) > 0.0


@pytest.mark.sumo
def test_ctrl_c_during_a_collection_writes_the_held_rows_then_resume_continues_exactly(
    net_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C while round 3 collects: round 2's rows still wait for its critics' losses; the checkpoint
    counts round 2, so its rows must be written before it is saved (a resumed run rewrites only the rows
    after the checkpoint)."""
    from idas_sumo.training.loop import run_training
    from idas_sumo.training.workers import InProcessWorkers

    monkeypatch.setenv(OVERLAP_UPDATE_ENV, "1")
    config = tiny_config(stage="robot", robot_episodes=4, episodes_per_update=1, checkpoint_every=1000)
    config = dataclasses.replace(config, validate_every=0)
    straight = tmp_path / "straight"
    run_training(net_path, config, straight, progress=False)

    real_run = InProcessWorkers.run
    calls = {"n": 0}

    def run_then_interrupt(self: InProcessWorkers, *args: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real_run(self, *args)

    monkeypatch.setattr(InProcessWorkers, "run", run_then_interrupt)
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_training(net_path, config, run, progress=False)
    monkeypatch.undo()
    monkeypatch.setenv(OVERLAP_UPDATE_ENV, "1")
    assert load_checkpoint(run / "checkpoint.pt").episode == 2
    assert len(rows(run / "metrics.csv")) == 2
    run_training(net_path, config, run, resume=True, progress=False)
    assert rows(run / "metrics.csv") == rows(straight / "metrics.csv")
    assert_same_tensors(
        load_checkpoint(run / "robot.pt").learner, load_checkpoint(straight / "robot.pt").learner
    )


def test_a_signal_while_waiting_for_the_critics_leaves_them_pending_and_whole(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Ctrl-C (or SIGTERM) while the main thread waits for the background step: the step goes on, and the
    handler's second wait gets it whole (a Thread.join interrupted so let the second one return at once,
    before the step had finished)."""
    import signal

    release = threading.Event()
    real_step = Learner._step_value_critic

    def gated_step(self: Learner, *args: Any) -> Any:
        assert release.wait(timeout=20)
        return real_step(self, *args)

    monkeypatch.setattr(Learner, "_step_value_critic", gated_step)
    learner = Learner(LearnerConfig(), seed=0, critics_in_background=True)
    pending = learner.begin_update(random_batch(n=64))
    main = threading.main_thread().ident
    assert main is not None
    threading.Timer(0.3, signal.pthread_kill, (main, signal.SIGINT)).start()
    with pytest.raises(KeyboardInterrupt):
        learner.finish_critics()
    threading.Timer(0.3, release.set).start()
    assert pending.stats()["v_loss"] > 0.0
    learner.finish_critics()
