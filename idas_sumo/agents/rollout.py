"""Episodes on the episode engine (env/engine.py), recorded as agent-steps ready for ``Learner.update``.

Every step all active learning agents of every episode the engine runs side by side are observed
together, one forward picks their actions (each episode drawing from its own stream, agents/sampling.py), the
simulation steps, and each agent-step becomes one row of the learner's ``Batch``.
The rows of an agent are linked to its next step (``next_state``, ``next_action``, ...) so the
centralised critic can bootstrap SARSA-style; an agent that finishes or collides gets ``done`` = 1,
one cut off by the timeout gets ``done`` = 0 and the observation it ended in as ``next_obs``.

Observations are stored once in an ``obs_bank`` and referenced by index (``obs_index``,
``next_obs_index``), which halves the memory and what worker processes send back.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

import numpy as np
import numpy.typing as npt
import torch

from idas_sumo.agents.critic_input import OTHERS_ACTIONS_DIM
from idas_sumo.agents.learner import Batch
from idas_sumo.agents.sampling import ActionStreams
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.engine import AgentBatch, EpisodeOutcome, MergeEngine, Policy, StepResult
from idas_sumo.env.episodes import run_episodes
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.rewards import REWARD_PART_NAMES
from idas_sumo.env.scenario import Scenario
from idas_sumo.env.state_layout import STATE_DIM

__all__ = [
    "EpisodeData",
    "EpisodeStats",
    "RolloutTask",
    "batch_from_episodes",
    "collect_episodes",
    "preload_episodes",
    "record_episodes",
]

DONE_REASONS = frozenset({"finished", "collided", "removed"})
"""End reasons after which nothing is bootstrapped (a timeout is not one of them)."""


@dataclass
class EpisodeStats:
    """What one episode amounted to (success and perfect: docs/design-notes.md, "Definitions")."""

    agents: int
    """Learning agents that acted."""
    steps: int
    """Decision steps (0.2 s each) in which at least one agent acted."""
    agent_steps: int
    """Rows recorded: one per agent per step it acted."""
    sim_time_s: float
    """Simulated seconds when the episode ended."""
    return_mean: float
    """Mean over agents of each agent's undiscounted return (finish + collide + impede)."""
    reward_parts: dict[str, float]
    """Each named reward part summed over agents and steps; ``flow`` counted once per step."""
    collisions: int
    """Collision pairs SUMO reported, learning agents or not."""
    timed_out: bool
    """Some agent was still driving at the time limit."""
    success: bool
    """No collision at all and no timeout."""
    perfect: bool
    """Success and no deduction: no impede and no flow penalty."""
    end_reasons: dict[str, str] = field(default_factory=dict)


@dataclass
class EpisodeData:
    """The agent-steps of one episode as numpy arrays, row i = one agent at one step."""

    obs_bank: npt.NDArray[np.float32]  # (K, OBS_DIM) every observation taken, once
    obs_index: npt.NDArray[np.int64]  # (N,) row of obs_bank the action was chosen on
    next_obs_index: npt.NDArray[np.int64]  # (N,) row of the next observation; -1: none (done)
    mask: npt.NDArray[np.int8]  # (N, N_ACTIONS)
    action: npt.NDArray[np.int64]  # (N,) the action applied
    reward: npt.NDArray[np.float32]  # (N,)
    done: npt.NDArray[np.float32]  # (N,)
    state: npt.NDArray[np.float32]  # (N, STATE_DIM)
    others_actions: npt.NDArray[np.float32]  # (N, OTHERS_ACTIONS_DIM)
    slot: npt.NDArray[np.int64]  # (N,)
    joint_reward: npt.NDArray[np.float32]  # (N,)
    next_state: npt.NDArray[np.float32]  # (N, STATE_DIM), zeros where next_valid is 0
    next_others_actions: npt.NDArray[np.float32]  # (N, OTHERS_ACTIONS_DIM)
    next_slot: npt.NDArray[np.int64]  # (N,)
    next_action: npt.NDArray[np.int64]  # (N,)
    next_valid: npt.NDArray[np.float32]  # (N,)
    next_row: npt.NDArray[np.int64]  # (N,) row of the same agent's next step, -1 when none
    stats: EpisodeStats
    team_next_row: npt.NDArray[np.int64] | None = None
    """(N,) the first row of the episode's next step, -1 at its last step: where the joint return goes on
    after an agent has left (``LearnerConfig.q_horizon``). None: no agent leaves before the episode ends."""

    def __len__(self) -> int:
        return int(self.action.shape[0])

    @property
    def obs(self) -> npt.NDArray[np.float32]:
        """(N, OBS_DIM); a view of the bank when row i's observation is bank row i (as recorded)."""
        n = len(self.obs_index)
        if n <= len(self.obs_bank) and np.array_equal(self.obs_index, np.arange(n)):
            return self.obs_bank[:n]
        return self.obs_bank[self.obs_index]

    @property
    def next_obs(self) -> npt.NDArray[np.float32]:
        """(N, OBS_DIM): the next observation, zeros where there is none (``done`` = 1)."""
        return self._next_obs_of(np.arange(len(self)))

    @property
    def bootstrap_obs(self) -> npt.NDArray[np.float32]:
        """``next_obs`` of the rows without a next row that did not end (cut off by the timeout)."""
        return self._next_obs_of(np.flatnonzero((self.next_row < 0) & (self.done == 0)))

    def _next_obs_of(self, rows: npt.NDArray[np.int64]) -> npt.NDArray[np.float32]:
        index = self.next_obs_index[rows]
        out = np.zeros((len(rows), OBS_DIM), dtype=np.float32)
        has = index >= 0
        out[has] = self.obs_bank[index[has]]
        return out


def _global_next_rows(episodes: list[EpisodeData], column: str = "next_row") -> npt.NDArray[np.int64]:
    """Each episode's ``next_row`` (or another row-link ``column``) shifted to the row numbering of the
    concatenated batch."""
    rows, offset = [], 0
    for e in episodes:
        link = getattr(e, column)
        rows.append(np.where(link >= 0, link + offset, -1))
        offset += len(e)
    return np.concatenate(rows).astype(np.int64) if rows else np.zeros(0, dtype=np.int64)


def batch_from_episodes(episodes: list[EpisodeData], central: bool = True) -> Batch:
    """Concatenate episodes into one ``Batch``; ``central=False`` leaves the critic-Q fields None."""

    def cat(name: str) -> torch.Tensor:
        return torch.from_numpy(np.concatenate([getattr(e, name) for e in episodes]))

    batch = Batch(
        obs=torch.from_numpy(np.concatenate([e.obs for e in episodes])),
        mask=cat("mask").bool(),
        action=cat("action"),
        reward=cat("reward"),
        next_obs=None,  # o' is row next_row's o, or in bootstrap_obs
        done=cat("done"),
        next_row=torch.from_numpy(_global_next_rows(episodes)),
        bootstrap_obs=torch.from_numpy(np.concatenate([e.bootstrap_obs for e in episodes])),
    )
    if central:
        batch.state = cat("state")
        batch.others_actions = cat("others_actions")
        batch.slot = cat("slot").clamp(min=0)
        batch.joint_reward = cat("joint_reward")
        batch.next_state = cat("next_state")
        batch.next_others_actions = cat("next_others_actions")
        batch.next_slot = cat("next_slot")
        batch.next_action = cat("next_action")
        batch.next_valid = cat("next_valid")
        if all(e.team_next_row is not None for e in episodes):
            batch.team_next_row = torch.from_numpy(_global_next_rows(episodes, "team_next_row"))
    return batch


# -- on the episode engine: K episodes side by side, one forward per step -----------------------------


class _StepLog:
    """Every step's rows of a wave of episodes, as the step's own arrays: one append per column a step
    (the rows of all copies at once). An episode's rows are cut out of them when its wave is over."""

    def __init__(self) -> None:
        self.columns: dict[str, list[npt.NDArray[Any]]] = {name: [] for name in ("obs", *_empty_columns())}
        self.ids: list[str] = []
        self.reasons: list[str] = []
        self.collisions: list[list[int]] = []
        """Per step, how many collision pairs each copy had."""

    def add(self, **columns: npt.NDArray[Any]) -> None:
        for name, array in columns.items():
            self.columns[name].append(array)

    def rows_of(self, job: int) -> npt.NDArray[np.int64]:
        """The log's rows of ``job``, in step order (agents in each step's order)."""
        if not self.columns["job"]:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(np.concatenate(self.columns["job"]) == job)


@dataclass(frozen=True)
class _Ending:
    """What an episode's end leaves that its rows do not say: read from the engine when it ends."""

    rows: npt.NDArray[np.int64]
    """Its rows of the step log."""
    links: _AgentRows
    cut_rows: list[int]
    """The last rows of the agents cut off by the timeout (pending, and still on the road)."""
    bootstrap: list[npt.NDArray[np.float32]]
    """Their last observations (none, or one array of them, in ``cut_rows``' order)."""
    time_s: float
    timed_out: bool
    outcome: EpisodeOutcome
    slot: int


def _runs_of(values: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """``np.unique(values, return_inverse=True)`` of sorted ``values`` (a batch's copies), without its sort."""
    new = np.empty(len(values), dtype=np.bool_)
    new[:1] = True
    np.not_equal(values[1:], values[:-1], out=new[1:])
    return values[new], np.cumsum(new) - 1


def _others_actions(
    copy: npt.NDArray[np.int64], agent_slots: npt.NDArray[np.int64], applied: npt.NDArray[np.int64]
) -> npt.NDArray[np.float32]:
    """Each agent's row of ``others_actions_onehot`` for one step of every copy (``copy``: each row's; every
    agent with a slot acted): its copy's joint action one-hot with the agent's own entry cleared (its block then
    holds nothing, as COMA wants); an agent without a slot sees no one (zeros). The same 0/1 floats, built
    without a slots × slots table: one row per copy, then each agent's copy of it."""
    in_range = np.flatnonzero(agent_slots >= 0)
    hot = agent_slots[in_range] * N_ACTIONS + np.asarray(applied, dtype=np.int64)[in_range]
    joint = np.zeros((int(copy.max()) + 1 if len(copy) else 0, OTHERS_ACTIONS_DIM), dtype=np.float32)
    joint[copy[in_range], hot] = 1.0  # a slot is one agent's in its copy: no two rows set the same entry
    out = joint[copy]
    out[agent_slots < 0] = 0.0
    out[in_range, hot] = 0.0
    return out


@dataclass(frozen=True)
class _AgentRows:
    """How an episode's rows (in step order, agents in each step's order) link up by agent."""

    next_row: npt.NDArray[np.int64]
    """Row of the same agent's next step; -1 after its last."""
    done: npt.NDArray[np.float32]
    """1 where the agent finished, collided or was removed at that step (nothing to bootstrap)."""
    first_seen: list[str]
    """The agents in the order they first acted."""
    agent_of_row: npt.NDArray[np.int64]
    """Each row's agent, as an index into ``first_seen``."""
    pending: dict[str, int]
    """Agents whose last row is not an end (a timeout or none): that row, which needs a next observation."""
    end_reasons: dict[str, str]

    @classmethod
    def of(cls, ids: list[str], reasons: list[str], done_reasons: frozenset[str]) -> _AgentRows:
        n = len(ids)
        first_seen = list(dict.fromkeys(ids))
        index = {a: i for i, a in enumerate(first_seen)}
        agent = np.fromiter((index[a] for a in ids), dtype=np.int64, count=n)
        order = np.argsort(agent, kind="stable")  # each agent's rows, in step order
        next_row = np.full(n, -1, dtype=np.int64)
        same = agent[order[1:]] == agent[order[:-1]]
        next_row[order[:-1][same]] = order[1:][same]
        done = np.fromiter((r in done_reasons for r in reasons), dtype=np.float32, count=n)
        end_reasons = {a: r for a, r in zip(ids, reasons, strict=True) if r}
        last = {a: i for i, a in enumerate(ids)}  # each agent's last row
        by_last = sorted(last.items(), key=lambda item: item[1])  # cut-off observations go in this order
        pending = {a: r for a, r in by_last if reasons[r] not in done_reasons}
        return cls(next_row, done, first_seen, agent, pending, end_reasons)


def _sequential_sum(values: npt.NDArray[np.float64]) -> float:
    """The sum added up one value after another (as a running total would), not pairwise; a sum of
    penalties that were all zero is 0, not -0 (metrics.csv wrote "-0" for a run without hard brakes)."""
    return float(np.cumsum(values)[-1]) + 0.0 if len(values) else 0.0


def _episode_data(
    log: dict[str, npt.NDArray[Any]],
    step: npt.NDArray[np.int64],
    bank: npt.NDArray[np.float32],
    collisions: npt.NDArray[np.int64],
    end: _Ending,
) -> EpisodeData:
    """The episode's rows of the wave's concatenated step log (``log``, but the observations: ``bank``, its
    rows' and then the bootstrap ones; ``step``: each row's step; ``collisions``: steps × copies) as one
    ``EpisodeData``: every row's columns, each linked to its agent's next row."""
    rows, links = end.rows, end.links
    n = len(rows)
    steps, per_step = np.unique(step, return_counts=True)  # (the steps it had rows in)
    nxt = links.next_row
    has_next = nxt >= 0
    obs_idx = np.arange(n, dtype=np.int64)  # every row's observation is its own row of the bank
    next_obs_idx = np.full(n, -1, dtype=np.int64)
    next_obs_idx[end.cut_rows] = n + np.arange(len(end.cut_rows))
    next_obs_idx[has_next] = obs_idx[nxt[has_next]]
    state_arr, others_arr = log["state"][rows], log["others"][rows]
    slot_arr, action_arr, reward_arr = log["slot"][rows], log["action"][rows], log["reward"][rows]
    return EpisodeData(
        obs_bank=bank,
        obs_index=obs_idx,
        next_obs_index=next_obs_idx,
        mask=log["mask"][rows],
        action=action_arr,
        reward=reward_arr.astype(np.float32),
        done=links.done,
        state=state_arr,
        others_actions=others_arr,
        slot=slot_arr,
        joint_reward=log["joint"][rows],
        next_state=_of_next_row(state_arr, nxt),
        next_others_actions=_of_next_row(others_arr, nxt),
        next_slot=_of_next_row(slot_arr, nxt),
        next_action=_of_next_row(action_arr, nxt),
        next_valid=has_next.astype(np.float32),
        next_row=nxt,
        stats=_episode_stats(
            links, per_step, log["parts"][rows], reward_arr, int(collisions[steps, end.slot].sum()), end
        ),
        team_next_row=_first_row_of_next_step(per_step.astype(np.int64)),
    )


def _first_row_of_next_step(per_step: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Each row's first row of the episode's next recorded step (-1 in the last step). A step in which no
    agent of the episode acted is not recorded: across such a gap the link skips the idle steps, whose joint
    reward is 0 (nobody acts, nobody brakes: ``scoring.py``)."""
    first = np.cumsum(per_step) - per_step
    following = np.append(first[1:], -1)[: len(per_step)].astype(np.int64)
    return np.repeat(following, per_step)


_Column = TypeVar("_Column", bound=np.generic)


def _of_next_row(column: npt.NDArray[_Column], next_row: npt.NDArray[np.int64]) -> npt.NDArray[_Column]:
    """Each row's value of ``column`` at the same agent's next row; zeros where it has none."""
    out = np.zeros_like(column)
    has_next = next_row >= 0
    out[has_next] = column[next_row[has_next]]
    return out


def _episode_stats(
    links: _AgentRows,
    per_step: npt.NDArray[np.int64],
    parts_arr: npt.NDArray[np.float64],
    reward_arr: npt.NDArray[np.float64],
    collisions: int,
    end: _Ending,
) -> EpisodeStats:
    """What the episode amounted to: its counts, returns and summed reward parts."""
    # Each agent's return summed over its rows in step order (bincount adds them one after another).
    agent_returns = np.bincount(links.agent_of_row, weights=reward_arr, minlength=len(links.first_seen))
    column = REWARD_PART_NAMES.index
    first_of_step = np.cumsum(per_step) - per_step  # flow: once per step
    reward_parts = {
        "finish": _sequential_sum(parts_arr[:, column("finish")]),
        "collide": _sequential_sum(parts_arr[:, column("collide")]),
        "impede": _sequential_sum(parts_arr[:, column("impede")]),
        "flow": _sequential_sum(parts_arr[first_of_step, column("flow")]),
    }
    return EpisodeStats(
        agents=len(links.first_seen),
        steps=len(per_step),
        agent_steps=len(reward_arr),
        sim_time_s=float(end.time_s),
        return_mean=float(np.mean(agent_returns.tolist())) if len(agent_returns) else 0.0,
        reward_parts={name: reward_parts[name] for name in REWARD_PART_NAMES},
        collisions=collisions,
        timed_out=end.timed_out,
        # The one definition (env/engine.py): no collision and every controlled car finished.
        success=end.outcome.success,
        perfect=end.outcome.perfect,
        end_reasons=links.end_reasons,
    )


class RolloutActor(Protocol):
    """What a rollout's learning agents act on (``Learner.rollout_logits``): the actor's unmasked logits."""

    def rollout_logits(self, obs: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]: ...


@dataclass(frozen=True)
class RolloutTask:
    """One episode to collect: the scenario, the seed of its action sampling, greedy or not."""

    scenario: Scenario
    action_seed: int
    deterministic: bool = False
    max_episode_s: float | None = None
    """Another timeout for this episode than the engine's own (validation at evaluation's length); the tasks
    of one call share it."""


class _LearningPolicy:
    """Every learning agent of every copy in one forward; each episode draws from its own stream."""

    def __init__(self, actor: RolloutActor, tasks: Sequence[RolloutTask]) -> None:
        self.actor = actor
        self.streams = ActionStreams([t.action_seed for t in tasks], [t.deterministic for t in tasks])

    def act(self, batch: AgentBatch, rows: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        assert batch.job is not None, "the episode loop names each agent's job"
        if len(rows) == len(batch) and np.array_equal(rows, np.arange(len(batch))):
            obs, masks = batch.obs, batch.masks  # every row in order: no copy
        else:
            obs, masks = batch.obs[rows], batch.masks[rows]
        return self.streams.draw(self.actor.rollout_logits(obs), masks, batch.job[rows])


class _Collector:
    """The engine observer of a rollout: every step's rows into one ``_StepLog``; when a wave's episodes are
    all over, each one's rows become its ``EpisodeData``."""

    def __init__(self) -> None:
        self.log = _StepLog()
        self.endings: dict[int, _Ending] = {}
        """Episodes over whose ``EpisodeData`` is not built yet."""
        self.wave: frozenset[int] = frozenset()
        """The jobs of the wave the log holds."""
        self._episodes: dict[int, EpisodeData] = {}
        self.agent_slots = np.zeros(0, dtype=np.int64)
        """The last decided batch's agents' state slots (``MergeEngine.state_slots``)."""
        self.row_states = np.zeros((0, STATE_DIM), dtype=np.float32)
        """Its agents' copies' states before the step."""

    @property
    def episodes(self) -> dict[int, EpisodeData]:
        """The episodes over, by job."""
        if self.endings:
            self._build()
        return self._episodes

    def decided(
        self, engine: MergeEngine, jobs: Sequence[int], batch: AgentBatch, actions: npt.NDArray[np.int64]
    ) -> None:
        if len(batch):
            copies, inverse = _runs_of(batch.copy)
            self.row_states = engine.states(copies)[inverse]
        self.agent_slots = engine.state_slots(batch.egos)  # read before the step replaces the snapshot

    def stepped(
        self,
        engine: MergeEngine,
        jobs: Sequence[int],
        batch: AgentBatch,
        actions: npt.NDArray[np.int64],
        result: StepResult,
    ) -> None:
        self.wave = frozenset(jobs)
        if not len(batch):
            return
        log = self.log
        assert batch.job is not None, "the episode loop names each agent's job"
        log.ids.extend(batch.ids)
        log.reasons.extend(result.end_reason)
        log.collisions.append([len(pairs) for pairs in result.collisions])
        applied = np.asarray(result.applied, dtype=np.int64)
        log.add(
            job=batch.job,
            step=np.full(len(batch), len(log.collisions) - 1, dtype=np.int64),
            obs=batch.obs,
            mask=batch.masks,
            slot=self.agent_slots,
            action=applied,
            reward=np.asarray(result.rewards, dtype=np.float64),
            parts=np.asarray(result.reward_parts, dtype=np.float64),
            others=_others_actions(batch.copy, self.agent_slots, applied),
            state=self.row_states,
            joint=np.asarray(result.joint_reward, dtype=np.float32)[batch.copy],
        )

    def ended(self, engine: MergeEngine, slot: int, job: int, outcome: EpisodeOutcome) -> None:
        rows = self.log.rows_of(job)
        ids, reasons = [self.log.ids[r] for r in rows.tolist()], [self.log.reasons[r] for r in rows.tolist()]
        links = _AgentRows.of(ids, reasons, DONE_REASONS)
        # Agents still pending were cut off (timeout): their final observation bootstraps V.
        cut = [(a, r) for a, r in links.pending.items() if engine.row(slot, a) is not None]
        bootstrap = [engine.observe_agents(slot, [a for a, _ in cut])] if cut else []
        timed_out = bool(any(r == "timeout" for r in links.end_reasons.values()) or cut)
        end = _Ending(rows, links, [r for _, r in cut], bootstrap, engine.time_s, timed_out, outcome, slot)
        self.endings[job] = end
        over = set(self.endings) | set(self._episodes)
        if self.wave <= over:  # the wave is over: its episodes now, and its log freed
            self._build()

    def _build(self) -> None:
        log, self.log = self.log, _StepLog()
        # Every column in one array, but the observations (the bulk): each episode's are copied once, into its bank.
        columns = {
            name: np.concatenate(parts) for name, parts in log.columns.items() if parts and name != "obs"
        }
        if not columns:  # no agent acted in the wave
            columns = _empty_columns()
        steps_obs = log.columns["obs"]
        starts = np.cumsum([0, *map(len, steps_obs)])
        slots = max(e.slot for e in self.endings.values()) + 1  # (a wave without a logged step has no width)
        collisions = np.array(log.collisions, dtype=np.int64).reshape(
            len(log.collisions), -1 if log.collisions else slots
        )
        for job, end in self.endings.items():
            step = columns["step"][end.rows]
            bank = _bank(steps_obs, starts, step, end.rows, end.bootstrap)
            self._episodes[job] = _episode_data(columns, step, bank, collisions, end)
        self.endings = {}


def _bank(
    steps_obs: list[npt.NDArray[np.float32]],
    starts: npt.NDArray[np.int64],
    step: npt.NDArray[np.int64],
    rows: npt.NDArray[np.int64],
    bootstrap: list[npt.NDArray[np.float32]],
) -> npt.NDArray[np.float32]:
    """The observations of the log's ``rows`` (``step``: each one's step, whose rows are ``starts[s]`` on), then
    ``bootstrap``'s, in one new array: a run of consecutive rows of one step copied at a time."""
    n = len(rows)
    bank = np.empty((n + sum(map(len, bootstrap)), OBS_DIM), dtype=np.float32)
    firsts = [0, *(np.flatnonzero((np.diff(step) != 0) | (np.diff(rows) != 1)) + 1).tolist()]
    for lo, hi in zip(firsts, [*firsts[1:], n], strict=True) if n else ():
        s = int(step[lo])
        at = int(rows[lo]) - int(starts[s])
        bank[lo:hi] = steps_obs[s][at : at + hi - lo]
    if bootstrap:
        bank[n:] = np.concatenate(bootstrap)
    return bank


def _empty_columns() -> dict[str, npt.NDArray[Any]]:
    return {
        "job": np.zeros(0, np.int64),
        "step": np.zeros(0, np.int64),
        "mask": np.zeros((0, N_ACTIONS), np.int8),
        "slot": np.zeros(0, np.int64),
        "action": np.zeros(0, np.int64),
        "reward": np.zeros(0, np.float64),
        "parts": np.zeros((0, len(REWARD_PART_NAMES)), np.float64),
        "others": np.zeros((0, OTHERS_ACTIONS_DIM), np.float32),
        "state": np.zeros((0, STATE_DIM), np.float32),
        "joint": np.zeros(0, np.float32),
    }


def collect_episodes(
    engine: MergeEngine, actor: RolloutActor, tasks: Sequence[RolloutTask]
) -> list[EpisodeData]:
    """Run every task's scenario to its end on ``engine`` (``engine.copies`` side by side), every learning
    agent on ``actor``; the recorded episodes in task order. Each episode draws from its own stream
    (``action_seed``), so its draws do not depend on which episodes ran beside it."""
    with engine.episode_limit(_shared_limit(tasks)):
        return record_episodes(engine, _LearningPolicy(actor, tasks), [t.scenario for t in tasks])


def preload_episodes(engine: MergeEngine, tasks: Sequence[RolloutTask]) -> None:
    """The first ``engine.copies`` of ``tasks`` started as ``collect_episodes`` starts them (``MergeEngine.preload``):
    a ``collect_episodes`` of the same tasks then begins where this left them."""
    with engine.episode_limit(_shared_limit(tasks)):
        engine.preload([t.scenario for t in tasks[: engine.copies]])


def _shared_limit(tasks: Sequence[RolloutTask]) -> float | None:
    """The timeout the tasks share (None: the engine's own, or no tasks)."""
    limits = {t.max_episode_s for t in tasks}
    if len(limits) > 1:
        raise ValueError(f"the tasks of one call share their timeout, got {sorted(map(str, limits))}")
    return limits.pop() if limits else None


def record_episodes(engine: MergeEngine, policy: Policy, scenarios: Sequence[Scenario]) -> list[EpisodeData]:
    """Every scenario run to its end with every learning agent on ``policy`` (a learned actor, or a
    rule-based teacher for imitation), recorded as agent-steps; in scenario order."""
    collector = _Collector()
    run_episodes(engine, scenarios, lambda job, agent: 0, [policy], collector)
    return [collector.episodes[j] for j in range(len(scenarios))]
