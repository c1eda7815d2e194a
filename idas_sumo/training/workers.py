"""Rollout workers: where episodes are collected. The loop only sees ``RolloutWorkers.run``.

``InProcessWorkers`` runs the episodes in the training process. ``PoolWorkers`` drives W workers of a
``sim.processes.WorkerPool``: processes on this machine (``ProcessPool``, started by
``sim.processes.WorkerProcesses``: fresh interpreters, since libsumo allows one SUMO per process and
a forked SUMO is not safe) or Ray actors (``--ray-address``, distributed/ray_pool.py). Each worker
is a ``RolloutServer`` with its own episode engine (env/engine.py: ``copies`` episodes side by side
in one SUMO run, one actor forward per step for all of them); every round they get the current actor
weights and a share of the episodes.
Each episode carries its own action-sampling seed, so the data do not depend on the worker count, on
which worker ran which episode, or on the backend.

Every worker gets the run's resolved ``MergeSite`` and its ``EnvConfig`` (no worker parses the net). A
round may name its own site (a training run with ``[geometry]`` draws one per round, training/geometry.py);
it goes with the tasks, and a worker builds a new engine only when the merge differs from the one it runs.
A round that names none runs on the workers' own merge (the run's ``--net``: validation).
"""

from __future__ import annotations

import dataclasses
import logging
import traceback
from abc import ABC, abstractmethod
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import numpy as np
import torch

from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.agents.rollout import EpisodeData, RolloutTask, collect_episodes
from idas_sumo.env.engine import EnvConfig, MergeEngine
from idas_sumo.errors import IdasError, SimulationError
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.processes import ProcessPool, WorkerPool, derived_seed

__all__ = [
    "EpisodeTask",
    "InProcessWorkers",
    "PoolWorkers",
    "RolloutServer",
    "RolloutWorkers",
    "make_workers",
]

log = logging.getLogger(__name__)

ActorWeights = dict[str, np.ndarray]


EpisodeTask = RolloutTask
"""One episode to collect: the scenario, the seed of its action sampling, greedy (validation) or not."""


def _same_merge(a: MergeSite, b: MergeSite) -> bool:
    return (a.path, a.junction_id) == (b.path, b.junction_id)


class _NetEngine:
    """A worker's engine, built again for another merge site (same copies, seed and episode rules)."""

    def __init__(
        self, site: MergeSite, env_config: EnvConfig, seed: int, copies: int, gui: bool = False
    ) -> None:
        self.home, self.env_config, self.seed, self.copies, self.gui = site, env_config, seed, copies, gui
        self.site = site
        self.engine = self._build(site)

    def _build(self, site: MergeSite) -> MergeEngine:
        # The site is the merge: ``env_config.junction`` only picks one from a net file.
        return MergeEngine(site, copies=self.copies, seed=self.seed, config=self.env_config, gui=self.gui)

    def on(self, site: MergeSite | None) -> MergeEngine:
        """The engine for ``site`` (None: the worker's own), rebuilt only when the merge changes."""
        site = site or self.home
        if not _same_merge(site, self.site):
            self.engine.close()
            self.site = site
            self.engine = self._build(site)
        return self.engine

    def close(self) -> None:
        self.engine.close()


def actor_weights(learner: Learner) -> ActorWeights:
    """The actor's weights as numpy arrays (cheap to pickle to another process)."""
    return {k: v.detach().cpu().numpy().copy() for k, v in learner.actor.state_dict().items()}


def _run_tasks(engine: MergeEngine, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]:
    return collect_episodes(engine, learner, tasks)


class RolloutWorkers(ABC):
    """Collects episodes with given actor weights; results come back in task order."""

    @abstractmethod
    def run(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None = None
    ) -> list[EpisodeData]:
        """The episodes of ``tasks`` on ``net`` (None: the workers' own merge)."""

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

    def __init__(
        self, site: MergeSite, env_config: EnvConfig, seed: int, copies: int, gui: bool = False
    ) -> None:
        copies = 1 if gui else copies
        self.engines = _NetEngine(site, env_config, seed, copies, gui)

    @property
    def engine(self) -> MergeEngine:
        """The engine of the net the last round ran on."""
        return self.engines.engine

    def run(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None = None
    ) -> list[EpisodeData]:
        # Small-batch inference runs slower with intra-op threads fighting SUMO; the learner update
        # afterwards gets the threads back.
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return _run_tasks(self.engines.on(net), learner, tasks)
        finally:
            torch.set_num_threads(threads)

    def close(self) -> None:
        self.engines.close()


@dataclass
class _PackedEpisode:
    """An episode for the pipe: observations sparse (~4 % non-zero), next-step copies dropped."""

    episode: EpisodeData
    obs_shape: tuple[int, int]
    obs_flat_index: np.ndarray
    obs_values: np.ndarray


def _pack(e: EpisodeData) -> _PackedEpisode:
    flat = e.obs_bank.reshape(-1)
    index = np.flatnonzero(flat).astype(np.int32 if flat.size < 2**31 else np.int64)
    empty = np.zeros(0, dtype=np.float32)
    light = dataclasses.replace(
        e,
        obs_bank=empty.reshape(0, e.obs_bank.shape[1]),
        next_state=empty,
        next_others_actions=empty,
        next_slot=empty.astype(np.int64),
        next_action=empty.astype(np.int64),
    )
    return _PackedEpisode(light, (int(e.obs_bank.shape[0]), int(e.obs_bank.shape[1])), index, flat[index])


def _unpack(p: _PackedEpisode) -> EpisodeData:
    e = p.episode
    obs = np.zeros(p.obs_shape[0] * p.obs_shape[1], dtype=np.float32)
    obs[p.obs_flat_index] = p.obs_values
    valid = e.next_row >= 0
    nxt = e.next_row[valid]
    next_state = np.zeros_like(e.state)
    next_others = np.zeros_like(e.others_actions)
    next_slot = np.zeros_like(e.slot)
    next_action = np.zeros_like(e.action)
    next_state[valid] = e.state[nxt]
    next_others[valid] = e.others_actions[nxt]
    next_slot[valid] = e.slot[nxt]
    next_action[valid] = e.action[nxt]
    return dataclasses.replace(
        e,
        obs_bank=obs.reshape(p.obs_shape),
        next_state=next_state,
        next_others_actions=next_others,
        next_slot=next_slot,
        next_action=next_action,
    )


class RolloutServer:
    """A rollout worker (``sim.processes.Server``): owns one SUMO; answers a share of a round's tasks
    (``(net, tasks)``: the round's net, None for the worker's own), with the round's actor weights,
    by its packed episodes."""

    def __init__(self, init: tuple[MergeSite, EnvConfig, int, int]) -> None:
        site, env_config, seed, copies = init
        torch.set_num_threads(1)
        self.engines = _NetEngine(site, env_config, seed, copies)
        self.learner = Learner(LearnerConfig(), seed=0)

    @property
    def engine(self) -> MergeEngine:
        """The engine of the net the last round ran on."""
        return self.engines.engine

    def handle(
        self, request: tuple[MergeSite | None, list[EpisodeTask]], weights: ActorWeights
    ) -> tuple[Any, ...]:
        try:
            net, tasks = request
            self.learner.actor.load_state_dict({k: torch.from_numpy(v) for k, v in weights.items()})
            return ("ok", [_pack(e) for e in _run_tasks(self.engines.on(net), self.learner, tasks)])
        except IdasError as err:
            return ("error", type(err).__name__, str(err))
        except Exception:
            return ("error", "Exception", traceback.format_exc())

    def close(self) -> None:
        self.engines.close()


class PoolWorkers(RolloutWorkers):
    """The workers of ``pool``, one SUMO each; a round splits the tasks into W contiguous shares and
    puts the episodes back in task order."""

    def __init__(self, pool: WorkerPool) -> None:
        self._pool = pool

    def run(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None = None
    ) -> list[EpisodeData]:
        shares = [list(s) for s in np.array_split(np.arange(len(tasks)), self._pool.size)]
        requests = {w: (net, [tasks[i] for i in idx]) for w, idx in enumerate(shares) if idx}
        self._pool.submit(requests, shared=actor_weights(learner))
        results: list[EpisodeData] = []
        errors: list[str] = []
        for w in requests:  # in order, so results follow the task order
            try:
                reply = self._pool.result(w)
            except SimulationError as err:
                errors.append(str(err))
                continue
            if reply[0] == "ok":
                results.extend(_unpack(p) for p in reply[1])
            else:
                errors.append(f"{reply[1]}: {reply[2]}")
        if errors:
            raise SimulationError(f"rollout worker failed: {errors[0]}")
        return results

    def close(self) -> None:
        self._pool.close()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._pool.__exit__(exc_type, exc, tb)  # closes the pool, or kills it mid-round after an error


def make_workers(
    site: MergeSite,
    env_config: EnvConfig,
    seed: int,
    workers: int,
    copies: int,
    gui: bool = False,
    ray_address: str | None = None,
) -> RolloutWorkers:
    """``workers`` processes (1: this one), each running ``copies`` episodes side by side; with
    ``ray_address`` (distributed/ray_pool.py), ``workers`` Ray actors instead, even for 1."""
    if workers <= 1 and ray_address is None:
        return InProcessWorkers(site, env_config, seed, copies, gui=gui)
    factory = "idas_sumo.training.workers:RolloutServer"
    inits = [(site, env_config, derived_seed(seed, 1 + w), copies) for w in range(workers)]
    pool: WorkerPool
    if ray_address is not None:
        from idas_sumo.distributed.ray_pool import RayPool  # only here: ray is an optional extra

        pool = RayPool(factory, inits, "rollout worker", ray_address)
    else:
        pool = ProcessPool(factory, inits, "rollout worker")
    return PoolWorkers(pool)
