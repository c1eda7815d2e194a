"""One episode at a time on the engine (K = 1), in the per-agent dictionaries the two environments hand out.

``MergeParallelEnv`` and ``MergeEnv`` share this: it names agents instead of batch rows, lets time run
while no agent is on the road, and keeps each agent's last observation for the step it ends in.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import cast

import numpy as np
import numpy.typing as npt
from gymnasium.error import ResetNeeded

from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.config import EnvConfig
from idas_sumo.env.contracts import AgentBatch, StepResult
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.lazy import lazy
from idas_sumo.env.scenario import Scenario
from idas_sumo.env.snapshot import ROAD_NAMES, TrafficSnapshot
from idas_sumo.errors import SimulationError
from idas_sumo.sim.backend import Backend
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.netgen import MergeNet

IntArray = npt.NDArray[np.int64]
_PLAIN_INTS = frozenset(
    {int, np.int64, np.int32, np.int16, np.int8, np.uint8, np.uint16, np.uint32, np.uint64}
)
"""Action types taken as they are (a bool, a float or a 0-d array goes through ``_checked_action``)."""

EPISODE_OVER = "step() after the episode ended (terminated or truncated): call reset() to start the next one"


class ResetFirst(ResetNeeded, SimulationError):
    """A step with no episode running (before ``reset()``, or after the episode ended): gymnasium's own
    ``ResetNeeded``, as its ``OrderEnforcing`` raises it, and an idas-sumo ``SimulationError``."""


class StepOutcome:
    """Everything one step produced, per agent that acted in it (``acting``, batch order).

    The per-agent dictionaries are built when first read: a single-ego env reads one agent's entries
    (``reward_of``, ``parts_of``, ``end_reason_of``), and eight dictionaries per step cost more than SUMO's step.
    """

    def __init__(self, acting: tuple[str, ...], requested: IntArray, result: StepResult) -> None:
        self.acting = acting
        self.result = result
        self._requested = requested
        self._row: dict[str, int] | None = None
        self._first: tuple[str, int] = ("", -1)
        """The first agent ``row`` was asked for, and its row (-1: none yet)."""

    @property
    def requested(self) -> IntArray:
        """The actions asked for, in ``acting`` order (``result.applied`` has those applied)."""
        return self._requested

    # (Read when asked: a single-ego env never reads these.)
    @lazy
    def joint_reward(self) -> float:
        """Sum of the agents' rewards plus the shared flow penalty (the centralised critic's reward)."""
        return float(self.result.joint_reward[0])

    @lazy
    def hard_brakes(self) -> int:
        return int(self.result.hard_brakes[0])

    @lazy
    def hard_brakes_merge_zone(self) -> int:
        return int(self.result.hard_brakes_merge_zone[0])

    @lazy
    def collisions(self) -> list[tuple[str, str]]:
        return list(self.result.collisions[0])

    def row(self, agent: str) -> int:
        """``agent``'s row in the step (KeyError: it did not act)."""
        if self._row is None:
            first, row = self._first
            if row >= 0 and agent == first:  # (a single-ego env asks for its ego three times a step)
                return row
            if row < 0:  # the first agent asked for: looked up without a dictionary of all
                try:
                    self._first = (agent, self.acting.index(agent))
                except ValueError:
                    raise KeyError(agent) from None
                return self._first[1]
            self._row = {a: i for i, a in enumerate(self.acting)}
        return self._row[agent]

    def reward_of(self, agent: str) -> float:
        return float(self.result.rewards[self.row(agent)])

    def parts_of(self, agent: str) -> dict[str, float]:
        result = self.result
        return dict(zip(result.part_names, result.reward_parts[self.row(agent)].tolist(), strict=True))

    def end_reason_of(self, agent: str) -> str:
        """'' while ``agent`` goes on, else one of END_REASONS."""
        return self.result.end_reason[self.row(agent)]

    @lazy
    def rewards(self) -> dict[str, float]:
        return dict(zip(self.acting, self.result.rewards.tolist(), strict=True))

    @lazy
    def reward_parts(self) -> dict[str, dict[str, float]]:
        names = self.result.part_names
        return {
            a: dict(zip(names, row, strict=True))
            for a, row in zip(self.acting, self.result.reward_parts.tolist(), strict=True)
        }

    @lazy
    def end_reason(self) -> dict[str, str]:
        """'finished', 'collided', 'removed' or 'timeout' for agents whose episode ended this step."""
        return {a: r for a, r in zip(self.acting, self.result.end_reason, strict=True) if r}

    @lazy
    def terminated(self) -> dict[str, bool]:
        ends = self.end_reason
        return {a: a in ends and ends[a] != "timeout" for a in self.acting}

    @lazy
    def truncated(self) -> dict[str, bool]:
        ends = self.end_reason
        return {a: ends.get(a) == "timeout" for a in self.acting}

    @lazy
    def replaced_actions(self) -> dict[str, int]:
        """Agents whose requested action was masked, and the action applied instead."""
        requested, applied = (
            self._requested.tolist(),
            self.result.applied.tolist(),
        )  # (plain ints compare fast)
        return {
            a: got for a, wanted, got in zip(self.acting, requested, applied, strict=True) if wanted != got
        }


class SingleEpisode:
    """A K = 1 ``MergeEngine`` (in-process libsumo, or a SUMO child process when libsumo is taken)."""

    def __init__(
        self,
        net: MergeSite | MergeNet | str | Path,
        seed: int = 0,
        config: EnvConfig | None = None,
        gui: bool = False,
    ) -> None:
        self.engine = MergeEngine(net, copies=1, seed=seed, config=config, gui=gui)
        self.scenario: Scenario | None = None
        self._batch: AgentBatch | None = None
        self._prev_batch: AgentBatch | None = None
        """The last batch with agents before ``_batch`` (an agent that ended was in it)."""
        self._last_obs: dict[str, npt.NDArray[np.float32]] = {}
        """Last observations of agents that ended before ``_prev_batch``."""

    @property
    def backend(self) -> Backend:
        """The single SUMO simulation the episode runs on."""
        return self.engine.single_backend

    def reset(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self._last_obs = {}
        self._batch = self._prev_batch = None
        self.engine.reset([scenario])
        self._advance()

    @property
    def batch(self) -> AgentBatch:
        """Every active agent now (in scenario order), with observations and masks."""
        if self._batch is None:
            raise ResetFirst("step() before reset(): call reset() first")
        return self._batch

    def _observe(self) -> None:
        batch = self.engine.observe()
        old = self._batch
        if old is not None and len(old):
            dropped = self._prev_batch
            if dropped is not None and dropped.ids is not old.ids and not set(dropped.ids) <= set(old.ids):
                # Agents of ``dropped`` that ended before ``old``: keep their last observations.
                for a, o in zip(dropped.ids, dropped.obs, strict=True):
                    if a not in old.ids:
                        self._last_obs[a] = o
            self._prev_batch = old
        self._batch = batch

    def _advance(self) -> None:
        """Nobody to act yet but controlled cars still to come: let time run to the next entry."""
        self._observe()
        while not self.engine.over(0) and not len(self.batch):
            self.engine.step(np.zeros(0, dtype=np.int64))
            self._observe()

    @property
    def active_agents(self) -> list[str]:
        return list(self.batch.ids)

    @property
    def finished_agents(self) -> dict[str, str]:
        """Agents whose episode ended, with the reason."""
        return self.engine.finished_agents(0)

    @property
    def episode_over(self) -> bool:
        """Every controlled vehicle finished, collided or left, or time ran out."""
        return self.engine.over(0)

    @property
    def time_s(self) -> float:
        return self.engine.time_s

    @property
    def snapshot(self) -> TrafficSnapshot:
        return self.engine.snapshot

    def timed_out(self) -> bool:
        return self.engine.timed_out()

    def observe(
        self, agent_ids: list[str] | None = None
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int8]]:
        """(observations, action masks) of these active agents (default: all), in that order."""
        batch = self.batch
        if agent_ids is None:
            return batch.obs, batch.masks
        if len(agent_ids) == len(batch.ids) and tuple(agent_ids) == batch.ids:  # (every agent, in order)
            # Built for the caller alone (nobody else holds it, so no copy): the engine's eager observations
            # are handed over (the batch builds its own again if asked), else built now.
            obs = batch.__dict__.pop("obs", None)
            if obs is None:
                obs = batch.all_obs()
            return obs, batch.masks.copy()
        if len(agent_ids) == 1:
            rows = np.array([batch.ids.index(agent_ids[0])], dtype=np.int64)
        else:
            index = {a: i for i, a in enumerate(batch.ids)}
            rows = np.array([index[a] for a in agent_ids], dtype=np.int64)
        if not len(rows):
            return batch.obs[:0], batch.masks[:0]
        return batch.obs_of(rows), batch.masks[rows]

    def last_observation(self, agent_id: str) -> npt.NDArray[np.float32]:
        """The observation ``agent_id`` last had (now, or in the last step it acted)."""
        for batch in (self._batch, self._prev_batch):
            if batch is not None and agent_id in batch.ids:
                return batch.obs_row(batch.ids.index(agent_id))  # (as ``MergeEnv.step`` builds one)
        return self._last_obs[agent_id]

    def prev_accel(self, agent_id: str) -> float:
        return self.engine.prev_accel(0, agent_id)

    def state(self) -> npt.NDArray[np.float32]:
        return self.engine.state(0)

    def agent_info(self, agent_id: str) -> dict[str, object]:
        """Raw physical values of an agent now (or at its last step on the road)."""
        return agent_info(self.engine, 0, agent_id)

    def agent_infos(self, agent_ids: Sequence[str]) -> list[dict[str, object]]:
        """``agent_info`` of each of these agents (of the scenario), read in one pass."""
        return agent_infos(self.engine, 0, agent_ids)

    def step(self, actions: Mapping[str, object]) -> StepOutcome:
        """Apply one action per active agent, advance SUMO one step, score it and end whoever is done."""
        batch = self.batch
        if self.engine.over(0):  # as gymnasium's OrderEnforcing refuses a step before reset()
            raise ResetFirst(EPISODE_OVER)
        acting = batch.ids
        try:
            values = [actions[a] for a in acting]
        except KeyError:
            missing = [a for a in acting if a not in actions]
            raise ValueError(f"no action for active agents {missing}") from None
        requested = _fast_actions(values)
        if requested is None:  # something is not a plain int in range: find it and name its agent
            requested = np.array(
                [_checked_action(a, v, batch.time_s) for a, v in zip(acting, values, strict=True)],
                dtype=np.int64,
            ).reshape(len(acting))
        return self.step_requested(requested)

    def step_requested(self, requested: IntArray) -> StepOutcome:
        """``step`` with the actions as an int64 array in ``batch`` order (checked by the engine)."""
        batch = self.batch
        if self.engine.over(0):
            raise ResetFirst(EPISODE_OVER)
        result = self.engine.step(requested)
        outcome = StepOutcome(batch.ids, requested, result)
        self._advance()
        return outcome

    def close(self) -> None:
        self.engine.close()


def agent_info(engine: MergeEngine, k: int, agent_id: str) -> dict[str, object]:
    """Raw physical values of slot k's agent now (or at its last step on the road); ``road`` "gone" once
    it left the road."""
    snap = engine.snapshot
    i, accel = engine.row_and_accel(k, agent_id)
    if i >= 0:
        return {
            "speed_mps": float(snap.speed_mps[i]),
            "accel_mps2": accel,
            "dist_to_merge_m": float(snap.dist_to_merge_m[i]),
            "road": ROAD_NAMES[int(snap.road[i])],
        }
    return _gone()


def agent_infos(engine: MergeEngine, k: int, agent_ids: Sequence[str]) -> list[dict[str, object]]:
    """``agent_info`` of each of slot k's ``agent_ids`` (vehicles of its scenario, agents or not), with
    numpy over all of them instead of lookups per agent."""
    snap = engine.snapshot
    if not len(snap):
        return [agent_info(engine, k, a) for a in agent_ids]
    speed, accel, dist, road = engine.agent_values(k, agent_ids)
    infos: list[dict[str, object]] = []
    for s, a, d, r in zip(speed, accel, dist, road, strict=True):
        if r >= 0:
            infos.append({"speed_mps": s, "accel_mps2": a, "dist_to_merge_m": d, "road": ROAD_NAMES[r]})
        else:
            infos.append(_gone())
    return infos


def _gone() -> dict[str, object]:
    nan = float("nan")
    return {"speed_mps": nan, "accel_mps2": nan, "dist_to_merge_m": nan, "road": "gone"}


def _fast_actions(values: list[object]) -> IntArray | None:
    """The actions as int64 when every one is a plain int (or numpy integer) in [0, 7), else None."""
    if not values:
        return np.zeros(0, dtype=np.int64)
    # (The range checked on the list: numpy's comparisons and ``all`` cost more than the list's min and max.)
    if set(map(type, values)) <= _PLAIN_INTS:
        ints = cast(list[int], values)
        if min(ints) >= 0 and max(ints) < N_ACTIONS:
            return np.array(ints, dtype=np.int64)
    return None


def _checked_action(agent: str, action: object, time_s: float) -> int:
    """An action index in [0, 7), or a ValueError naming the agent and the time."""
    value = action
    if isinstance(action, np.generic | np.ndarray) and np.ndim(action) == 0:
        value = action.item()  # numpy scalars and 0-d arrays (what many agents return)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < N_ACTIONS:
        raise ValueError(
            f"invalid action {action!r} for agent {agent!r} at t = {time_s:.1f} s: expected an int in [0, {N_ACTIONS})"
        )
    return value
