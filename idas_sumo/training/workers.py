"""Rollout workers: where episodes are collected, and a training round's gradients computed. The loop only sees
``RolloutWorkers.train_round`` (a round: episodes, then one learner step) and ``RolloutWorkers.run`` (episodes:
validation).

``InProcessWorkers`` runs the episodes in the training process. ``PoolWorkers`` drives W workers of a
``sim.processes.WorkerPool``: processes on this machine (``ProcessPool``, started by
``sim.processes.WorkerProcesses``: fresh interpreters, since libsumo allows one SUMO per process and
a forked SUMO is not safe) or Ray actors (``--ray-address``, distributed/ray_pool.py). Each worker
is a ``RolloutServer`` with its own episode engine (env/engine.py: ``copies`` episodes side by side
in one SUMO run, one actor forward per step for all of them); every round they get the current weights
(the actor's; for a training round every network's) and a share of the episodes.
Each episode carries its own action-sampling seed, so the data do not depend on the worker count, on
which worker ran which episode, or on the backend. In a training round each worker also computes the learner's
gradient on the groups of episodes it collected (``GROUP_EPISODES``; a share is whole groups) and sends back only
that and the episodes' stats; the training process weighs the groups' gradients into one step. The groups do not
depend on the worker count and every group's gradient is computed on one torch thread, so neither do the weights.

Every worker gets the run's resolved ``MergeSite`` and its ``EnvConfig`` (no worker parses the net). A
round may name its own site (a training run with ``[geometry]`` draws one per round, training/geometry.py);
it goes with the tasks, and a worker builds a new engine only when the merge differs from the one it runs.
A round that names none runs on the workers' own merge (the run's ``--net``: validation).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import traceback
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import numpy as np
import torch

from idas_sumo.agents.learner import (
    ActorStep,
    AdvantageScale,
    Batch,
    CriticStep,
    GradientPart,
    Learner,
    LearnerConfig,
    PendingPart,
    prepare_optimisers,
)
from idas_sumo.agents.rollout import (
    EpisodeData,
    EpisodeStats,
    RolloutTask,
    batch_from_episodes,
    collect_episodes,
    preload_episodes,
)
from idas_sumo.env.engine import EnvConfig, MergeEngine
from idas_sumo.env.jit import load_cached_kernels
from idas_sumo.errors import IdasError, SimulationError
from idas_sumo.sim.backend import load_libsumo
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.processes import ProcessPool, WorkerPool, derived_seed, release_fork_server
from idas_sumo.training.heap import freeze_alive, keep_freed_blocks
from idas_sumo.training.worker_count import EPISODES_PER_WORKER, ROLLOUT_SERVER_MODULE

__all__ = [
    "EpisodeTask",
    "InProcessWorkers",
    "PoolWorkers",
    "RolloutServer",
    "RolloutWorkers",
    "make_workers",
    "warm_up",
]

log = logging.getLogger(__name__)

ActorWeights = dict[str, np.ndarray]
LearnerWeights = dict[str, ActorWeights]
"""Each network of a learner (``LEARNER_NETWORKS``, and its anchor if any) as numpy arrays."""

GROUP_EPISODES = EPISODES_PER_WORKER
"""A training round's episodes are cut, in task order, into groups of this many (the last may hold fewer),
and the learner's gradient is computed per group (``Learner.gradient_part``) where the group was collected,
then weighed by rows into one step (``Learner.apply_gradients``). The cut does not depend on the worker
count: a worker's share is whole groups, so the weights do not either."""
LEARNER_NETWORKS = ("actor", "value", "central", "value_target", "central_target")


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


def learner_weights(learner: Learner) -> LearnerWeights:
    """Every network a gradient part reads (``LEARNER_NETWORKS``, the anchor if any), as numpy arrays."""
    nets = {name: getattr(learner, name) for name in LEARNER_NETWORKS}
    if learner.anchor is not None:
        nets["anchor"] = learner.anchor
    return {
        name: {k: v.detach().cpu().numpy().copy() for k, v in net.state_dict().items()}
        for name, net in nets.items()
    }


def _load_learner_weights(learner: Learner, weights: LearnerWeights) -> None:
    if "anchor" in weights and learner.anchor is None:
        learner.anchor_to_start()
    for name, state in weights.items():
        getattr(learner, name).load_state_dict({k: torch.from_numpy(v) for k, v in state.items()})


def _run_tasks(engine: MergeEngine, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]:
    return collect_episodes(engine, learner, tasks)


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """Torch on one thread: small-batch inference runs slower with intra-op threads fighting SUMO, and a
    gradient part gets the same bits wherever it is computed (a rollout worker runs one thread; torch's
    reductions and products may round by the thread count)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _gradient_parts(learner: Learner, episodes: list[EpisodeData], central: bool) -> list[GradientPart]:
    """The gradient part of each ``GROUP_EPISODES`` of ``episodes`` (which start at a group's start), on one
    torch thread."""
    with _one_thread():
        return [learner.gradient_part(batch) for batch in _group_batches(episodes, central)]


def _group_batches(episodes: list[EpisodeData], central: bool) -> Iterator[Batch]:
    for i in range(0, len(episodes), GROUP_EPISODES):
        yield batch_from_episodes(episodes[i : i + GROUP_EPISODES], central=central)


def _pending_parts(learner: Learner, episodes: list[EpisodeData], central: bool) -> list[PendingPart]:
    """``_gradient_parts`` up to the actor's gradient (``Learner.pending_part``), on one torch thread."""
    with _one_thread():
        return [learner.pending_part(batch) for batch in _group_batches(episodes, central)]


def _finished_parts(
    learner: Learner, pending: list[PendingPart], scale: AdvantageScale
) -> list[GradientPart]:
    with _one_thread():
        return [learner.finish_part(p, scale) for p in pending]


_Advantages = tuple[np.ndarray | None, np.ndarray | None]
"""A group's A1 and A2 (None in stage 1), None for a group without rows: what the whole round's
``AdvantageScale`` is computed from."""


def _advantages(pending: PendingPart) -> _Advantages:
    adv_v, adv_q = pending.advantages
    return (None if adv_v is None else adv_v.numpy(), None if adv_q is None else adv_q.numpy())


def _round_scale(groups: list[_Advantages]) -> AdvantageScale:
    """The round's ``AdvantageScale`` from its groups' advantages in task order (so it does not depend on the
    worker count), on one torch thread: the same operations as ``Learner.update`` on the round's batch."""
    # Copies: a Ray reply's arrays are read-only, which torch.from_numpy warns about.
    value = [torch.tensor(v) for v, _ in groups if v is not None]
    central = [torch.tensor(q) for v, q in groups if v is not None and q is not None]
    if not value:  # no rows in the round: no step, the scale is not read
        return AdvantageScale((0.0, None), None)
    with _one_thread():
        return AdvantageScale.over(value, central or None)


def _shares(tasks: list[EpisodeTask], workers: int) -> dict[int, list[EpisodeTask]]:
    """A training round's tasks by worker: whole groups (``GROUP_EPISODES``), in task order, as even as they go."""
    groups = -(-len(tasks) // GROUP_EPISODES)
    shares = {}
    for w, share in enumerate(np.array_split(np.arange(groups), workers)):
        if len(share):
            first, end = int(share[0]) * GROUP_EPISODES, (int(share[-1]) + 1) * GROUP_EPISODES
            shares[w] = tasks[first:end]
    return shares


class RolloutWorkers(ABC):
    """Collects episodes with given actor weights; results come back in task order."""

    _meanwhile: Callable[[], None] | None = None
    _ahead: list[EpisodeTask] = []  # (replaced, never changed in place)

    def meanwhile(self, task: Callable[[], None] | None) -> None:
        """Run ``task`` once during the next round: while its workers collect, or before this process collects
        (nothing it reads may change before the round ends); None: nothing."""
        self._meanwhile = task

    def _run_meanwhile(self) -> None:
        task, self._meanwhile = self._meanwhile, None
        if task is not None:
            task()

    def load_ahead(self, tasks: list[EpisodeTask]) -> None:
        """The tasks of the round after the next ``train_round``, on the same net: a worker process loads its
        share into its SUMO once it has sent its part of the round, while it waits for the next weights
        (``RolloutServer.work_ahead``). What the round then collects does not change; only when it starts."""
        self._ahead = tasks

    @abstractmethod
    def run(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None = None
    ) -> list[EpisodeData]:
        """The episodes of ``tasks`` on ``net`` (None: the workers' own merge)."""

    def train_round(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None, central: bool
    ) -> tuple[list[EpisodeStats], dict[str, float]]:
        """A training round: the episodes of ``tasks`` with the learner's actor, then one update of
        ``learner`` on all their agent-steps (``central``: with the centralised critic's fields). Returns
        the episodes' stats, in task order, and the update's metrics.

        The gradient is computed by groups (``GROUP_EPISODES``) where they were collected, and only the
        parts come back. With ``normalize_advantages`` (A1 and A2 standardised over the whole batch) in two
        phases: the groups' critic gradients and advantages, then, with the round's ``AdvantageScale`` from all
        the groups' advantages, their actor gradients."""
        if not learner.config.normalize_advantages:
            stats, parts = self._collect_gradients(learner, tasks, net, central)
        else:
            stats, advantages = self._collect_advantages(learner, tasks, net, central)
            parts = self._finish_gradients(learner, _round_scale(advantages))
        # On one thread, as the parts were computed: the step's norms then round alike on every machine, and sooner.
        with _one_thread():
            return stats, learner.apply_gradients(parts)

    def train_round_here(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None, central: bool
    ) -> tuple[list[EpisodeStats], dict[str, float]]:
        """``train_round`` with the episodes brought here and one ``Learner.update`` on all their rows: what a
        script that inspects each update's batch runs instead (experiments/stage2_collapse/instrumented_train.py). The same maths as ``train_round``; the floats
        differ in their last bits (one batch on this process's threads, not groups on one thread)."""
        episodes = self.run(learner, tasks, net)
        return [e.stats for e in episodes], learner.update(batch_from_episodes(episodes, central=central))

    @abstractmethod
    def _collect_gradients(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None, central: bool
    ) -> tuple[list[EpisodeStats], list[GradientPart]]:
        """The episodes' stats and the gradient parts of their groups, in task order."""

    @abstractmethod
    def _collect_advantages(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None, central: bool
    ) -> tuple[list[EpisodeStats], list[_Advantages]]:
        """The episodes' stats and their groups' advantages, in task order; the groups' pending parts stay
        where they were computed until ``_finish_gradients``."""

    @abstractmethod
    def _finish_gradients(self, learner: Learner, scale: AdvantageScale) -> list[GradientPart]:
        """The gradient parts of the last ``_collect_advantages``'s groups with the round's ``scale``."""

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
        self._pending: list[PendingPart] = []

    @property
    def engine(self) -> MergeEngine:
        """The engine of the net the last round ran on."""
        return self.engines.engine

    def run(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None = None
    ) -> list[EpisodeData]:
        self._run_meanwhile()
        with _one_thread():
            return _run_tasks(self.engines.on(net), learner, tasks)

    def _collect_gradients(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None, central: bool
    ) -> tuple[list[EpisodeStats], list[GradientPart]]:
        episodes = self.run(learner, tasks, net)
        return [e.stats for e in episodes], _gradient_parts(learner, episodes, central)

    def _collect_advantages(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None, central: bool
    ) -> tuple[list[EpisodeStats], list[_Advantages]]:
        episodes = self.run(learner, tasks, net)
        self._pending = _pending_parts(learner, episodes, central)
        return [e.stats for e in episodes], [_advantages(p) for p in self._pending]

    def _finish_gradients(self, learner: Learner, scale: AdvantageScale) -> list[GradientPart]:
        pending, self._pending = self._pending, []
        return _finished_parts(learner, pending, scale)

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


_PackedStep = tuple[np.ndarray, np.ndarray, np.ndarray, float]
_PackedPart = tuple[int, "_PackedStep | None", "_PackedStep | None", ActorStep | None, dict[str, list[Any]]]


def _pack_step(step: CriticStep | None) -> _PackedStep | None:
    if step is None:
        return None
    return (step.prediction.numpy(), step.target.numpy(), step.advantage.numpy(), step.loss)


def _unpack_step(packed: _PackedStep | None) -> CriticStep | None:
    if packed is None:
        return None
    prediction, target, advantage, loss = packed
    return CriticStep(
        torch.from_numpy(prediction), torch.from_numpy(target), torch.from_numpy(advantage), loss
    )


def _pack_part(p: GradientPart) -> _PackedPart:
    """A gradient part for the pipe: numpy arrays (torch's own pickling of tensors goes through shared memory)."""
    grads = {k: [None if g is None else g.numpy() for g in v] for k, v in p.grads.items()}
    return (p.rows, _pack_step(p.value), _pack_step(p.central), p.actor, grads)


def _unpack_part(packed: _PackedPart) -> GradientPart:
    rows, value, central, actor, grads = packed
    tensors = {k: [None if g is None else torch.from_numpy(g) for g in v] for k, v in grads.items()}
    return GradientPart(rows, _unpack_step(value), _unpack_step(central), actor, tensors)


@dataclass(frozen=True)
class _GradientRequest:
    """A training round's share for a rollout worker: its episodes, then the gradient parts of their groups
    under ``config`` (the learner's, with the round's weights). ``pending``: only their advantages, the parts
    kept for a ``_ScaleRequest`` (``normalize_advantages``)."""

    net: MergeSite | None
    tasks: list[EpisodeTask]
    config: LearnerConfig
    central: bool
    pending: bool = False
    ahead: list[EpisodeTask] = dataclasses.field(default_factory=list)
    """The worker's share of the next round (``RolloutWorkers.load_ahead``), on the same net."""


@dataclass(frozen=True)
class _ScaleRequest:
    """The round's ``AdvantageScale``: the worker's kept parts' actor gradients, then the parts."""

    scale: AdvantageScale


class RolloutServer:
    """A rollout worker (``sim.processes.Server``): owns one SUMO; answers a share of a round's tasks
    (``(net, tasks)``: the round's net, None for the worker's own), with the round's actor weights,
    by its packed episodes."""

    def __init__(self, init: tuple[MergeSite, EnvConfig, int, int]) -> None:
        site, env_config, seed, copies = init
        torch.set_num_threads(1)
        keep_freed_blocks()
        self.engines = _NetEngine(site, env_config, seed, copies)
        self.learner = Learner(LearnerConfig(), seed=0)
        self._pending: list[PendingPart] = []
        self._ahead: tuple[MergeSite | None, list[EpisodeTask]] = (None, [])
        """The next round's share and its net, for ``work_ahead``."""

    @property
    def engine(self) -> MergeEngine:
        """The engine of the net the last round ran on."""
        return self.engines.engine

    def handle(
        self,
        request: tuple[MergeSite | None, list[EpisodeTask]] | _GradientRequest | _ScaleRequest,
        weights: ActorWeights | LearnerWeights | None,
    ) -> tuple[Any, ...]:
        try:
            if isinstance(request, _ScaleRequest):
                pending, self._pending = self._pending, []
                return ("ok", [_pack_part(p) for p in _finished_parts(self.learner, pending, request.scale)])
            if isinstance(request, _GradientRequest):
                return self._gradients(request, weights)  # type: ignore[arg-type]
            net, tasks = request
            assert weights is not None  # a round's actor weights
            self.learner.actor.load_state_dict({k: torch.from_numpy(v) for k, v in weights.items()})
            return ("ok", [_pack(e) for e in _run_tasks(self.engines.on(net), self.learner, tasks)])
        except IdasError as err:
            return ("error", type(err).__name__, str(err))
        except Exception:
            return ("error", "Exception", traceback.format_exc())

    def _gradients(self, request: _GradientRequest, weights: LearnerWeights) -> tuple[Any, ...]:
        """The share's episodes' stats and its groups' gradient parts, with the round's learner."""
        if self.learner.config != request.config:
            self.learner = Learner(request.config, seed=0)
        _load_learner_weights(self.learner, weights)
        self._ahead = (request.net, request.ahead)
        episodes = _run_tasks(self.engines.on(request.net), self.learner, request.tasks)
        if request.pending:
            self._pending = _pending_parts(self.learner, episodes, request.central)
            return ("ok", [e.stats for e in episodes], [_advantages(p) for p in self._pending])
        parts = _gradient_parts(self.learner, episodes, request.central)
        return ("ok", [e.stats for e in episodes], [_pack_part(p) for p in parts])

    def work_ahead(self) -> None:
        """Once a round's reply is sent (``sim.processes.serve``): the next round's share loaded into SUMO
        (``preload_episodes``), so that the next request starts collecting at once."""
        (net, tasks), self._ahead = self._ahead, (None, [])
        if tasks:
            # (A failed load is left to the next request's own reset, which meets the error and answers with it.)
            with contextlib.suppress(IdasError):
                preload_episodes(self.engines.on(net), tasks)

    def close(self) -> None:
        self.engines.close()


class PoolWorkers(RolloutWorkers):
    """The workers of ``pool``, one SUMO each; a round splits the tasks into W contiguous shares and
    puts the episodes back in task order."""

    def __init__(self, pool: WorkerPool) -> None:
        self._pool = pool
        self._holding: list[int] = []
        """The workers asked in the last gradient round (those a ``_ScaleRequest`` goes to)."""

    def run(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None = None
    ) -> list[EpisodeData]:
        shares = [list(s) for s in np.array_split(np.arange(len(tasks)), self._pool.size)]
        requests = {w: (net, [tasks[i] for i in idx]) for w, idx in enumerate(shares) if idx}
        self._pool.submit(requests, shared=actor_weights(learner))
        self._run_meanwhile()
        return [_unpack(p) for reply in self._replies(requests) for p in reply[1]]

    def _collect_gradients(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None, central: bool
    ) -> tuple[list[EpisodeStats], list[GradientPart]]:
        replies = self._gradient_replies(learner, tasks, _GradientRequest(net, [], learner.config, central))
        stats = [s for reply in replies for s in reply[1]]
        return stats, [_unpack_part(p) for reply in replies for p in reply[2]]

    def _collect_advantages(
        self, learner: Learner, tasks: list[EpisodeTask], net: MergeSite | None, central: bool
    ) -> tuple[list[EpisodeStats], list[_Advantages]]:
        request = _GradientRequest(net, [], learner.config, central, pending=True)
        replies = self._gradient_replies(learner, tasks, request)
        return [s for reply in replies for s in reply[1]], [a for reply in replies for a in reply[2]]

    def _finish_gradients(self, learner: Learner, scale: AdvantageScale) -> list[GradientPart]:
        requests = dict.fromkeys(self._holding, _ScaleRequest(scale))
        self._pool.submit(requests)
        return [_unpack_part(p) for reply in self._replies(requests) for p in reply[1]]

    def _gradient_replies(
        self, learner: Learner, tasks: list[EpisodeTask], request: _GradientRequest
    ) -> list[tuple[Any, ...]]:
        """Each worker's ``request`` for its share of ``tasks`` (whole groups, in task order), with the
        learner's weights; the replies in worker order."""
        ahead, self._ahead = _shares(self._ahead, self._pool.size), []
        requests = {
            w: dataclasses.replace(request, tasks=share, ahead=ahead.get(w, []))
            for w, share in _shares(tasks, self._pool.size).items()
        }
        self._pool.submit(requests, shared=learner_weights(learner))
        self._holding = list(requests)
        learner.build_optimisers()  # while the workers collect (only the first round's build costs anything)
        self._run_meanwhile()
        return self._replies(requests)

    def _replies(self, requests: dict[int, Any]) -> list[tuple[Any, ...]]:
        """The workers' "ok" replies to ``requests``, in worker order (so results follow the task order); a
        ``SimulationError`` naming the first failure once all are in."""
        replies: list[tuple[Any, ...]] = []
        errors: list[str] = []
        for w in requests:
            try:
                reply = self._pool.result(w)
            except SimulationError as err:
                errors.append(str(err))
                continue
            if reply[0] == "ok":
                replies.append(reply)
            else:
                errors.append(f"{reply[1]}: {reply[2]}")
        if errors:
            raise SimulationError(f"rollout worker failed: {errors[0]}")
        return replies

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
    if workers <= 1 or ray_address is not None:
        release_fork_server()  # the run needs no worker processes of its own
    if workers <= 1 and ray_address is None:
        return InProcessWorkers(site, env_config, seed, copies, gui=gui)
    factory = f"{ROLLOUT_SERVER_MODULE}:RolloutServer"
    inits = [(site, env_config, derived_seed(seed, 1 + w), copies) for w in range(workers)]
    pool: WorkerPool
    if ray_address is not None:
        from idas_sumo.distributed.ray_pool import RayPool  # only here: ray is an optional extra

        pool = RayPool(factory, inits, "rollout worker", ray_address)
    else:
        pool = ProcessPool(factory, inits, "rollout worker", meanwhile=prepare_optimisers)
    return PoolWorkers(pool)


def warm_up() -> None:
    """What every rollout worker's first round loads alike, loaded once in the process they are forked from
    (``ROLLOUT_PRELOAD``): libsumo's library and numba's cached kernels. Then its objects are frozen out of the
    forks' garbage collections (Python's advice for a process that forks: ``gc.freeze`` before the forks)."""
    load_libsumo()
    load_cached_kernels()
    freeze_alive()
