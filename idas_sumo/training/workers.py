"""Rollout workers: where episodes are collected. The loop only sees ``RolloutWorkers.run``.

``InProcessWorkers`` runs the episodes in the training process. ``ProcessWorkers`` starts W
processes (spawn: libsumo allows one SUMO per process, and a forked SUMO is not safe), each with its
own ``MergeSimulation``; every round they get the current actor weights and a share of the episodes.
Each episode carries its own action-sampling seed, so the data do not depend on the worker count or
on which worker ran which episode. A Ray or other cluster backend would be one more implementation of
``RolloutWorkers``.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import signal
import traceback
from abc import ABC, abstractmethod
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import torch

from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.agents.rollout import EpisodeData, collect_episode
from idas_sumo.env.core import EnvConfig, MergeSimulation
from idas_sumo.env.scenario import Scenario
from idas_sumo.errors import IdasError, SimulationError

__all__ = ["EpisodeTask", "InProcessWorkers", "ProcessWorkers", "RolloutWorkers", "make_workers"]

log = logging.getLogger(__name__)

ActorWeights = dict[str, np.ndarray]


@dataclass(frozen=True)
class EpisodeTask:
    """One episode to collect: the scenario and the seed of its action sampling."""

    scenario: Scenario
    action_seed: int


def actor_weights(learner: Learner) -> ActorWeights:
    """The actor's weights as numpy arrays (cheap to pickle to another process)."""
    return {k: v.detach().cpu().numpy().copy() for k, v in learner.actor.state_dict().items()}


def _run_tasks(sim: MergeSimulation, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]:
    out = []
    for task in tasks:
        generator = torch.Generator().manual_seed(task.action_seed)
        out.append(collect_episode(sim, learner, task.scenario, generator))
    return out


class RolloutWorkers(ABC):
    """Collects episodes with given actor weights; results come back in task order."""

    @abstractmethod
    def run(self, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]: ...

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self) -> RolloutWorkers:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class InProcessWorkers(RolloutWorkers):
    """Collect in this process, with the learner's own actor."""

    def __init__(self, net_path: Path, env_config: EnvConfig, seed: int, gui: bool = False) -> None:
        self.sim = MergeSimulation(net_path, seed=seed, config=env_config, gui=gui)

    def run(self, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]:
        return _run_tasks(self.sim, learner, tasks)

    def close(self) -> None:
        self.sim.close()


def _worker_main(conn: Connection, net_path: str, env_config: EnvConfig, seed: int) -> None:
    """A worker process: owns one SUMO; answers ('run', weights, tasks) until ('close',)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    torch.set_num_threads(1)
    sim: MergeSimulation | None = None
    try:
        sim = MergeSimulation(net_path, seed=seed, config=env_config)
        learner = Learner(LearnerConfig(), seed=0)
        while True:
            msg = conn.recv()
            if msg[0] == "close":
                break
            _, weights, tasks = msg
            try:
                learner.actor.load_state_dict({k: torch.from_numpy(v) for k, v in weights.items()})
                conn.send(("ok", _run_tasks(sim, learner, tasks)))
            except IdasError as err:
                conn.send(("error", type(err).__name__, str(err)))
            except Exception:
                conn.send(("error", "Exception", traceback.format_exc()))
    except (EOFError, BrokenPipeError):
        pass
    finally:
        if sim is not None:
            sim.close()


class ProcessWorkers(RolloutWorkers):
    """W spawned processes, one SUMO each; a round splits the tasks into W contiguous shares."""

    def __init__(self, net_path: Path, env_config: EnvConfig, seed: int, workers: int) -> None:
        ctx = mp.get_context("spawn")
        self._conns: list[Connection] = []
        self._procs: list[Any] = []
        for w in range(workers):
            parent, child = ctx.Pipe()
            proc = ctx.Process(
                target=_worker_main,
                args=(child, str(net_path), env_config, seed + 1 + w),
                name=f"idas-rollout-{w}",
                daemon=True,
            )
            proc.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(proc)

    def run(self, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]:
        weights = actor_weights(learner)
        shares = [list(s) for s in np.array_split(np.arange(len(tasks)), len(self._conns))]
        busy = []
        for conn, idx in zip(self._conns, shares, strict=True):
            if idx:
                conn.send(("run", weights, [tasks[i] for i in idx]))
                busy.append(conn)
        results: list[EpisodeData] = []
        errors: list[str] = []
        for conn in busy:  # in order, so results follow the task order
            try:
                reply = conn.recv()
            except EOFError:
                errors.append("a rollout worker died")
                continue
            if reply[0] == "ok":
                results.extend(reply[1])
            else:
                errors.append(f"{reply[1]}: {reply[2]}")
        if errors:
            raise SimulationError(f"rollout worker failed: {errors[0]}")
        return results

    def close(self) -> None:
        for conn in self._conns:
            with contextlib.suppress(BrokenPipeError, OSError):
                conn.send(("close",))
        for proc in self._procs:
            proc.join(timeout=10)
            if proc.is_alive():
                log.warning("rollout worker %s did not stop; terminating it", proc.name)
                proc.terminate()
                proc.join(timeout=5)
        for conn in self._conns:
            conn.close()
        self._conns = []
        self._procs = []


def make_workers(
    net_path: Path, env_config: EnvConfig, seed: int, workers: int, gui: bool = False
) -> RolloutWorkers:
    if workers <= 1:
        return InProcessWorkers(net_path, env_config, seed, gui=gui)
    return ProcessWorkers(net_path, env_config, seed, workers)
