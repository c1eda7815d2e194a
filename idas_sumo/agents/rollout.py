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
from typing import Protocol

import numpy as np
import numpy.typing as npt
import torch

from idas_sumo.agents.critic_input import OTHERS_ACTIONS_DIM, others_actions_onehot
from idas_sumo.agents.learner import Batch
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.engine import (
    AgentBatch,
    EpisodeOutcome,
    MergeEngine,
    Policy,
    StepResult,
    run_episodes,
)
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.rewards import REWARD_PART_NAMES
from idas_sumo.env.scenario import Scenario
from idas_sumo.env.state_layout import STATE_DIM, STATE_SLOTS

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

    def __len__(self) -> int:
        return int(self.action.shape[0])

    @property
    def obs(self) -> npt.NDArray[np.float32]:
        return self.obs_bank[self.obs_index]

    @property
    def next_obs(self) -> npt.NDArray[np.float32]:
        """(N, OBS_DIM): the next observation, zeros where there is none (``done`` = 1)."""
        bank = np.concatenate([self.obs_bank, np.zeros((1, OBS_DIM), dtype=np.float32)])
        return bank[np.where(self.next_obs_index >= 0, self.next_obs_index, len(self.obs_bank))]


def _global_next_rows(episodes: list[EpisodeData]) -> npt.NDArray[np.int64]:
    """Each episode's ``next_row`` shifted to the row numbering of the concatenated batch."""
    rows, offset = [], 0
    for e in episodes:
        rows.append(np.where(e.next_row >= 0, e.next_row + offset, -1))
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
        next_obs=torch.from_numpy(np.concatenate([e.next_obs for e in episodes])),
        done=cat("done"),
        next_row=torch.from_numpy(_global_next_rows(episodes)),
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
    return batch


# -- on the episode engine: K episodes side by side, one forward per step -----------------------------


class _EpisodeRecorder:
    """One episode's agent-steps as ``collect_episode`` records them, filled from the engine's hooks."""

    def __init__(self) -> None:
        self.obs_rows: list[npt.NDArray[np.float32]] = []
        self.n_obs = 0
        self.obs_index: list[int] = []
        self.next_obs_index: list[int] = []
        self.masks: list[npt.NDArray[np.int8]] = []
        self.actions: list[int] = []
        self.rewards: list[float] = []
        self.dones: list[float] = []
        self.states: list[npt.NDArray[np.float32]] = []
        self.others: list[npt.NDArray[np.float32]] = []
        self.slots: list[int] = []
        self.joints: list[float] = []
        self.next_row: list[int] = []
        self.pending: dict[str, int] = {}
        self.returns: dict[str, float] = {}
        self.parts = dict.fromkeys(REWARD_PART_NAMES, 0.0)
        self.collisions = 0
        self.steps = 0
        self.end_reasons: dict[str, str] = {}
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
    ) -> None:
        assert self.state is not None, "the state is taken before the step"
        state = self.state
        slot_actions = np.zeros(STATE_SLOTS, dtype=np.int64)
        acting = np.zeros(STATE_SLOTS, dtype=np.bool_)
        in_range = agent_slots >= 0
        slot_actions[agent_slots[in_range]] = applied[in_range]
        acting[agent_slots[in_range]] = True
        onehot = others_actions_onehot(slot_actions, acting)
        self.obs_rows.append(obs)
        first_obs = self.n_obs
        self.n_obs += len(ids)
        finish, collide, impede = (REWARD_PART_NAMES.index(p) for p in ("finish", "collide", "impede"))
        for i, a in enumerate(ids):
            row = len(self.actions)
            if a in self.pending:
                self.next_row[self.pending.pop(a)] = row
            self.obs_index.append(first_obs + i)
            self.next_obs_index.append(-1)
            self.masks.append(mask[i])
            self.actions.append(int(applied[i]))
            r = float(rewards[i])
            self.rewards.append(r)
            self.returns[a] = self.returns.get(a, 0.0) + r
            self.parts["finish"] += float(parts[i, finish])
            self.parts["collide"] += float(parts[i, collide])
            self.parts["impede"] += float(parts[i, impede])
            reason = reasons[i] or None
            self.dones.append(1.0 if reason in DONE_REASONS else 0.0)
            self.states.append(state)
            slot = int(agent_slots[i])
            self.others.append(onehot[slot] if slot >= 0 else np.zeros(OTHERS_ACTIONS_DIM, dtype=np.float32))
            self.slots.append(slot)
            self.joints.append(joint)
            self.next_row.append(-1)
            if reason is not None:
                self.end_reasons[a] = reason
            if reason not in DONE_REASONS:  # still driving, or cut off: needs a next observation
                self.pending[a] = row
        if len(ids):
            self.parts["flow"] += float(parts[0, REWARD_PART_NAMES.index("flow")])
        self.collisions += collisions
        self.steps += 1

    def finish(self, engine: MergeEngine, k: int, outcome: EpisodeOutcome) -> EpisodeData:
        # Agents still pending were cut off (timeout): their final observation bootstraps V.
        cut = [a for a in self.pending if engine.row(k, a) is not None]
        if cut:
            self.obs_rows.append(engine.observe_agents(k, cut))
            for i, a in enumerate(cut):
                self.next_obs_index[self.pending[a]] = self.n_obs + i
            self.n_obs += len(cut)
        timed_out = bool(any(r == "timeout" for r in self.end_reasons.values()) or cut)
        return _episode_data(self, engine.time_s, timed_out, outcome)


def _episode_data(
    rec: _EpisodeRecorder, time_s: float, timed_out: bool, outcome: EpisodeOutcome
) -> EpisodeData:
    n = len(rec.actions)
    nxt = np.asarray(rec.next_row, dtype=np.int64)
    has_next = nxt >= 0
    obs_idx = np.asarray(rec.obs_index, dtype=np.int64)
    next_obs_idx = np.asarray(rec.next_obs_index, dtype=np.int64)
    next_obs_idx[has_next] = obs_idx[nxt[has_next]]
    state_arr = np.asarray(rec.states, dtype=np.float32).reshape(n, STATE_DIM)
    others_arr = np.asarray(rec.others, dtype=np.float32).reshape(n, OTHERS_ACTIONS_DIM)
    slot_arr = np.asarray(rec.slots, dtype=np.int64)
    action_arr = np.asarray(rec.actions, dtype=np.int64)
    next_state = np.zeros_like(state_arr)
    next_others = np.zeros_like(others_arr)
    next_slot = np.zeros(n, dtype=np.int64)
    next_action = np.zeros(n, dtype=np.int64)
    next_state[has_next] = state_arr[nxt[has_next]]
    next_others[has_next] = others_arr[nxt[has_next]]
    next_slot[has_next] = slot_arr[nxt[has_next]]
    next_action[has_next] = action_arr[nxt[has_next]]
    agent_returns = list(rec.returns.values())
    stats = EpisodeStats(
        agents=len(rec.returns),
        steps=rec.steps,
        agent_steps=n,
        sim_time_s=float(time_s),
        return_mean=float(np.mean(agent_returns)) if agent_returns else 0.0,
        reward_parts=rec.parts,
        collisions=rec.collisions,
        timed_out=timed_out,
        # The one definition (env/engine.py): no collision and every controlled car finished.
        success=outcome.success,
        perfect=outcome.perfect,
        end_reasons=rec.end_reasons,
    )
    bank = (
        np.concatenate(rec.obs_rows).astype(np.float32, copy=False)
        if rec.obs_rows
        else np.zeros((0, OBS_DIM), np.float32)
    )
    return EpisodeData(
        obs_bank=bank,
        obs_index=obs_idx,
        next_obs_index=next_obs_idx,
        mask=np.asarray(rec.masks, dtype=np.int8).reshape(n, N_ACTIONS),
        action=action_arr,
        reward=np.asarray(rec.rewards, dtype=np.float32),
        done=np.asarray(rec.dones, dtype=np.float32),
        state=state_arr,
        others_actions=others_arr,
        slot=slot_arr,
        joint_reward=np.asarray(rec.joints, dtype=np.float32),
        next_state=next_state,
        next_others_actions=next_others,
        next_slot=next_slot,
        next_action=next_action,
        next_valid=has_next.astype(np.float32),
        next_row=nxt,
        stats=stats,
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


class _LearningPolicy:
    """Every learning agent of every copy in one forward; each episode samples with its own generator."""

    def __init__(self, actor: GroupedActor, tasks: Sequence[RolloutTask]) -> None:
        self.actor = actor
        self.tasks = tasks
        self.generators = [torch.Generator().manual_seed(t.action_seed) for t in tasks]

    def act(self, batch: AgentBatch, rows: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        assert batch.job is not None, "the episode loop names each agent's job"
        jobs = batch.job[rows]
        out = np.zeros(len(rows), dtype=np.int64)
        # Greedy and sampling episodes may share a step: one forward per kind.
        greedy = np.array([self.tasks[j].deterministic for j in jobs.tolist()], dtype=np.bool_)
        for det in (False, True):
            part = np.flatnonzero(greedy == det)
            if not len(part):
                continue
            groups = [
                (np.flatnonzero(jobs[part] == j), self.generators[j]) for j in np.unique(jobs[part]).tolist()
            ]
            sel = rows[part]
            out[part] = self.actor.act_grouped(batch.obs[sel], batch.masks[sel], groups, deterministic=det)
        return out


class _Collector:
    """The engine observer of a rollout: one ``_EpisodeRecorder`` per job."""

    def __init__(self, n_jobs: int) -> None:
        self.recorders = [_EpisodeRecorder() for _ in range(n_jobs)]
        self.episodes: dict[int, EpisodeData] = {}

    def decided(
        self, engine: MergeEngine, jobs: Sequence[int], batch: AgentBatch, actions: npt.NDArray[np.int64]
    ) -> None:
        for k in np.unique(batch.copy).tolist():
            self.recorders[jobs[k]].state = engine.state(k)

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
        obs = batch.obs
        for k in np.unique(batch.copy).tolist():
            rows = np.flatnonzero(batch.copy == k)
            ids = [batch.ids[r] for r in rows]
            state_slot = engine.slots[k].state_slot
            agent_slots = np.array([state_slot.get(a, -1) for a in ids], dtype=np.int64)
            self.recorders[jobs[k]].step(
                ids,
                obs[rows],
                batch.masks[rows],
                agent_slots,
                result.applied[rows],
                result.rewards[rows],
                result.reward_parts[rows],
                [result.end_reason[r] for r in rows],
                float(result.joint_reward[k]),
                len(result.collisions[k]),
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
    return record_episodes(engine, _LearningPolicy(actor, tasks), [t.scenario for t in tasks])


def record_episodes(engine: MergeEngine, policy: Policy, scenarios: Sequence[Scenario]) -> list[EpisodeData]:
    """Every scenario run to its end with every learning agent on ``policy`` (a learned actor, or a
    rule-based teacher for imitation), recorded as agent-steps; in scenario order."""
    collector = _Collector(len(scenarios))
    run_episodes(engine, scenarios, lambda job, agent: 0, [policy], collector)
    return [collector.episodes[j] for j in range(len(scenarios))]
