"""Episodes on the episode engine (env/engine.py), recorded as agent-steps ready for ``Learner.update``.

Every step all active learning agents of every episode the engine runs side by side are observed
together, one forward picks their actions (each episode sampling with its own generator), the
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
from typing import Protocol, TypeVar

import numpy as np
import numpy.typing as npt
import torch

from idas_sumo.agents.critic_input import OTHERS_ACTIONS_DIM
from idas_sumo.agents.learner import Batch
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


class _EpisodeRecorder:
    """One episode's agent-steps, filled from the engine's hooks a step (all its agents) at a time and
    assembled into an ``EpisodeData`` at the end."""

    def __init__(self) -> None:
        self.obs_rows: list[npt.NDArray[np.float32]] = []
        self.ids: list[str] = []
        self.masks: list[npt.NDArray[np.int8]] = []
        self.actions: list[npt.NDArray[np.int64]] = []
        self.rewards: list[npt.NDArray[np.float64]] = []
        self.parts: list[npt.NDArray[np.float64]] = []
        self.reasons: list[str] = []
        self.states: list[npt.NDArray[np.float32]] = []
        self.others: list[npt.NDArray[np.float32]] = []
        self.slots: list[npt.NDArray[np.int64]] = []
        self.joints: list[float] = []
        self.agents_per_step: list[int] = []
        self.collisions = 0
        self.state: npt.NDArray[np.float32] | None = None

    def step(
        self,
        ids: list[str],
        obs: npt.NDArray[np.float32],
        mask: npt.NDArray[np.int8],
        agent_slots: npt.NDArray[np.int64],
        applied: npt.NDArray[np.int64],
        rewards: npt.NDArray[np.float64],
        parts: npt.NDArray[np.float64],
        reasons: list[str],
        joint: float,
        collisions: int,
        others: npt.NDArray[np.float32],
    ) -> None:
        """One step's rows of the episode (views of the step's arrays; ``others``: each row's
        ``_others_actions``)."""
        assert self.state is not None, "the state is taken before the step"
        self.others.append(others)
        self.obs_rows.append(obs)
        self.ids.extend(ids)
        self.masks.append(mask)
        self.actions.append(np.asarray(applied, dtype=np.int64))
        self.rewards.append(np.asarray(rewards, dtype=np.float64))
        self.parts.append(np.asarray(parts, dtype=np.float64))
        self.reasons.extend(reasons)
        self.states.append(self.state)
        self.slots.append(np.asarray(agent_slots, dtype=np.int64))
        self.joints.append(joint)
        self.agents_per_step.append(len(ids))
        self.collisions += collisions

    def finish(self, engine: MergeEngine, k: int, outcome: EpisodeOutcome) -> EpisodeData:
        rows = _AgentRows.of(self.ids, self.reasons, DONE_REASONS)
        bank = list(self.obs_rows)
        # Agents still pending were cut off (timeout): their final observation bootstraps V.
        cut = [(a, r) for a, r in rows.pending.items() if engine.row(k, a) is not None]
        next_obs_index = np.full(len(self.ids), -1, dtype=np.int64)
        if cut:
            bank.append(engine.observe_agents(k, [a for a, _ in cut]))
            next_obs_index[[r for _, r in cut]] = len(self.ids) + np.arange(len(cut))
        timed_out = bool(any(r == "timeout" for r in rows.end_reasons.values()) or cut)
        return _episode_data(self, rows, bank, next_obs_index, engine.time_s, timed_out, outcome)


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
    rec: _EpisodeRecorder,
    rows: _AgentRows,
    bank: list[npt.NDArray[np.float32]],
    next_obs_index: npt.NDArray[np.int64],
    time_s: float,
    timed_out: bool,
    outcome: EpisodeOutcome,
) -> EpisodeData:
    """The recorder's steps as one ``EpisodeData``: every row's columns, each linked to its agent's next row."""
    n = len(rec.ids)
    per_step = np.asarray(rec.agents_per_step, dtype=np.int64)
    nxt = rows.next_row
    has_next = nxt >= 0
    obs_idx = np.arange(n, dtype=np.int64)  # every row's observation is its own row of the bank
    next_obs_idx = next_obs_index.copy()
    next_obs_idx[has_next] = obs_idx[nxt[has_next]]
    state_arr = (
        np.repeat(np.asarray(rec.states, dtype=np.float32), per_step, axis=0)
        if n
        else np.zeros((0, STATE_DIM), np.float32)
    )
    others_arr = np.concatenate(rec.others) if n else np.zeros((0, OTHERS_ACTIONS_DIM), np.float32)
    slot_arr = np.concatenate(rec.slots) if n else np.zeros(0, np.int64)
    action_arr = np.concatenate(rec.actions) if n else np.zeros(0, np.int64)
    reward_arr = np.concatenate(rec.rewards) if n else np.zeros(0, np.float64)
    return EpisodeData(
        obs_bank=np.concatenate(bank).astype(np.float32, copy=False)
        if bank
        else np.zeros((0, OBS_DIM), np.float32),
        obs_index=obs_idx,
        next_obs_index=next_obs_idx,
        mask=(np.concatenate(rec.masks) if n else np.zeros((0, N_ACTIONS))).astype(np.int8, copy=False),
        action=action_arr,
        reward=reward_arr.astype(np.float32),
        done=rows.done,
        state=state_arr,
        others_actions=others_arr,
        slot=slot_arr,
        joint_reward=np.repeat(np.asarray(rec.joints, dtype=np.float32), per_step),
        next_state=_of_next_row(state_arr, nxt),
        next_others_actions=_of_next_row(others_arr, nxt),
        next_slot=_of_next_row(slot_arr, nxt),
        next_action=_of_next_row(action_arr, nxt),
        next_valid=has_next.astype(np.float32),
        next_row=nxt,
        stats=_episode_stats(rec, rows, reward_arr, time_s, timed_out, outcome),
        team_next_row=_first_row_of_next_step(per_step),
    )


def _first_row_of_next_step(per_step: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Each row's first row of the episode's next recorded step (-1 in the last step). A step in which no
    agent of the episode acted is not recorded: across such a gap the link skips the idle steps, whose joint
    reward is 0 (nobody acts, nobody brakes: ``scoring.py``)."""
    first = np.cumsum(per_step) - per_step
    following = np.append(first[1:], -1).astype(np.int64)
    return np.repeat(following, per_step)


_Column = TypeVar("_Column", bound=np.generic)


def _of_next_row(column: npt.NDArray[_Column], next_row: npt.NDArray[np.int64]) -> npt.NDArray[_Column]:
    """Each row's value of ``column`` at the same agent's next row; zeros where it has none."""
    out = np.zeros_like(column)
    has_next = next_row >= 0
    out[has_next] = column[next_row[has_next]]
    return out


def _episode_stats(
    rec: _EpisodeRecorder,
    rows: _AgentRows,
    reward_arr: npt.NDArray[np.float64],
    time_s: float,
    timed_out: bool,
    outcome: EpisodeOutcome,
) -> EpisodeStats:
    """What the episode amounted to: its counts, returns and summed reward parts."""
    n = len(rec.ids)
    per_step = np.asarray(rec.agents_per_step, dtype=np.int64)
    parts_arr = np.concatenate(rec.parts) if n else np.zeros((0, len(REWARD_PART_NAMES)), np.float64)
    # Each agent's return summed over its rows in step order (bincount adds them one after another).
    agent_returns = np.bincount(rows.agent_of_row, weights=reward_arr, minlength=len(rows.first_seen))
    column = REWARD_PART_NAMES.index
    first_of_step = np.cumsum(per_step)[per_step > 0] - per_step[per_step > 0]  # flow: once per step
    reward_parts = {
        "finish": _sequential_sum(parts_arr[:, column("finish")]),
        "collide": _sequential_sum(parts_arr[:, column("collide")]),
        "impede": _sequential_sum(parts_arr[:, column("impede")]),
        "flow": _sequential_sum(parts_arr[first_of_step, column("flow")]),
    }
    return EpisodeStats(
        agents=len(rows.first_seen),
        steps=len(rec.agents_per_step),
        agent_steps=n,
        sim_time_s=float(time_s),
        return_mean=float(np.mean(agent_returns.tolist())) if len(agent_returns) else 0.0,
        reward_parts={name: reward_parts[name] for name in REWARD_PART_NAMES},
        collisions=rec.collisions,
        timed_out=timed_out,
        # The one definition (env/engine.py): no collision and every controlled car finished.
        success=outcome.success,
        perfect=outcome.perfect,
        end_reasons=rows.end_reasons,
    )


class GroupedActor(Protocol):
    """``Learner.act_grouped``: one forward for agents of several episodes, each with its generator."""

    def act_grouped(
        self,
        obs: npt.NDArray[np.float32],
        mask: npt.NDArray[np.int8],
        groups: Sequence[tuple[npt.NDArray[np.int64], torch.Generator]],
        deterministic: bool = False,
    ) -> npt.NDArray[np.int64]: ...


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
    """Every learning agent of every copy in one forward; each episode samples with its own generator."""

    def __init__(self, actor: GroupedActor, tasks: Sequence[RolloutTask]) -> None:
        self.actor = actor
        self.tasks = tasks
        self.generators = [torch.Generator().manual_seed(t.action_seed) for t in tasks]
        self.greedy = np.array([t.deterministic for t in tasks], dtype=np.bool_)

    def act(self, batch: AgentBatch, rows: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        assert batch.job is not None, "the episode loop names each agent's job"
        jobs = batch.job[rows]
        out = np.zeros(len(rows), dtype=np.int64)
        # Greedy and sampling episodes may share a step: one forward per kind.
        greedy = self.greedy[jobs]
        for det in (False, True):
            part = np.flatnonzero(greedy == det)
            if not len(part):
                continue
            # Each job's rows (ascending) with its generator, jobs in ascending order.
            part_jobs = jobs[part]
            order = np.argsort(part_jobs, kind="stable")
            sorted_jobs = part_jobs[order]
            first = np.flatnonzero(np.diff(sorted_jobs, prepend=-1))  # where each job's rows begin
            ends = [*first[1:].tolist(), len(order)]
            groups = [
                (order[lo:hi], self.generators[j])
                for j, lo, hi in zip(sorted_jobs[first].tolist(), first.tolist(), ends, strict=True)
            ]
            sel = rows[part]
            if len(sel) == len(batch) and np.array_equal(sel, np.arange(len(batch))):
                obs, masks = batch.obs, batch.masks  # every row in order: no copy
            else:
                obs, masks = batch.obs[sel], batch.masks[sel]
            out[part] = self.actor.act_grouped(obs, masks, groups, deterministic=det)
        return out


class _Collector:
    """The engine observer of a rollout: one ``_EpisodeRecorder`` per job."""

    def __init__(self, n_jobs: int) -> None:
        self.recorders = [_EpisodeRecorder() for _ in range(n_jobs)]
        self.episodes: dict[int, EpisodeData] = {}
        self.agent_slots = np.zeros(0, dtype=np.int64)
        """The last decided batch's agents' state slots (``MergeEngine.state_slots``)."""

    def decided(
        self, engine: MergeEngine, jobs: Sequence[int], batch: AgentBatch, actions: npt.NDArray[np.int64]
    ) -> None:
        copies = np.unique(batch.copy)
        for k, state in zip(copies.tolist(), engine.states(copies), strict=True):
            self.recorders[jobs[k]].state = state
        self.agent_slots = engine.state_slots(batch.egos)  # read before the step replaces the snapshot

    def stepped(
        self,
        engine: MergeEngine,
        jobs: Sequence[int],
        batch: AgentBatch,
        actions: npt.NDArray[np.int64],
        result: StepResult,
    ) -> None:
        if not len(batch):
            return
        copy = batch.copy
        agent_slots = self.agent_slots
        others = _others_actions(copy, agent_slots, result.applied)
        # Each copy's rows as one slice of the step's arrays (the batch lists its agents copy by copy; else
        # sorted so, stably): views, where a row index per copy copied every column.
        in_order = bool(np.all(copy[1:] >= copy[:-1]))
        order = None if in_order else np.argsort(copy, kind="stable")

        def rows(a: npt.NDArray[_Column]) -> npt.NDArray[_Column]:
            return a if order is None else a[order]

        ids = batch.ids if order is None else [batch.ids[r] for r in order.tolist()]
        reasons = result.end_reason if order is None else [result.end_reason[r] for r in order.tolist()]
        columns = (
            rows(batch.obs),
            rows(batch.masks),
            rows(agent_slots),
            rows(np.asarray(result.applied, dtype=np.int64)),
            rows(np.asarray(result.rewards, dtype=np.float64)),
            rows(np.asarray(result.reward_parts, dtype=np.float64)),
            rows(others),
        )
        sorted_copy = rows(copy)
        present, first = np.unique(sorted_copy, return_index=True)
        ends = [*first[1:].tolist(), len(sorted_copy)]
        for k, lo, hi in zip(present.tolist(), first.tolist(), ends, strict=True):
            obs, mask, agent_slot, applied, reward, parts, other = (c[lo:hi] for c in columns)
            self.recorders[jobs[k]].step(
                list(ids[lo:hi]),
                obs,
                mask,
                agent_slot,
                applied,
                reward,
                parts,
                list(reasons[lo:hi]),
                float(result.joint_reward[k]),
                len(result.collisions[k]),
                other,
            )

    def ended(self, engine: MergeEngine, slot: int, job: int, outcome: EpisodeOutcome) -> None:
        self.episodes[job] = self.recorders[job].finish(engine, slot, outcome)
        self.recorders[job] = _EpisodeRecorder()  # free its lists


def collect_episodes(
    engine: MergeEngine, actor: GroupedActor, tasks: Sequence[RolloutTask]
) -> list[EpisodeData]:
    """Run every task's scenario to its end on ``engine`` (``engine.copies`` side by side), every learning
    agent on ``actor``; the recorded episodes in task order. Each episode samples with its own generator
    (``action_seed``), so its draws do not depend on which episodes ran beside it."""
    limits = {t.max_episode_s for t in tasks}
    if len(limits) > 1:
        raise ValueError(f"the tasks of one call share their timeout, got {sorted(map(str, limits))}")
    with engine.episode_limit(limits.pop() if limits else None):
        return record_episodes(engine, _LearningPolicy(actor, tasks), [t.scenario for t in tasks])


def record_episodes(engine: MergeEngine, policy: Policy, scenarios: Sequence[Scenario]) -> list[EpisodeData]:
    """Every scenario run to its end with every learning agent on ``policy`` (a learned actor, or a
    rule-based teacher for imitation), recorded as agent-steps; in scenario order."""
    collector = _Collector(len(scenarios))
    run_episodes(engine, scenarios, lambda job, agent: 0, [policy], collector)
    return [collector.episodes[j] for j in range(len(scenarios))]
