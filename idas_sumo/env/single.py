"""One episode at a time on the engine (K = 1), in the per-agent dictionaries the two environments hand out.

``MergeParallelEnv`` and ``MergeEnv`` share this: it names agents instead of batch rows, lets time run
while no agent is on the road, and keeps each agent's last observation for the step it ends in.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from gymnasium.error import ResetNeeded

from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.config import EnvConfig
from idas_sumo.env.contracts import AgentBatch
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.scenario import Scenario
from idas_sumo.env.snapshot import ROAD_NAMES, TrafficSnapshot
from idas_sumo.errors import SimulationError
from idas_sumo.sim.backend import Backend
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.netgen import MergeNet

EPISODE_OVER = "step() after the episode ended (terminated or truncated): call reset() to start the next one"


class ResetFirst(ResetNeeded, SimulationError):
    """A step with no episode running (before ``reset()``, or after the episode ended): gymnasium's own
    ``ResetNeeded``, as its ``OrderEnforcing`` raises it, and an idas-sumo ``SimulationError``."""


@dataclass
class StepOutcome:
    """Everything one step produced, per agent that acted in it."""

    rewards: dict[str, float]
    reward_parts: dict[str, dict[str, float]]
    joint_reward: float
    """Sum of the agents' rewards plus the shared flow penalty (the centralised critic's reward)."""
    terminated: dict[str, bool]
    truncated: dict[str, bool]
    end_reason: dict[str, str]
    """'finished', 'collided', 'removed' or 'timeout' for agents whose episode ended this step."""
    hard_brakes: int
    hard_brakes_merge_zone: int
    collisions: list[tuple[str, str]]
    replaced_actions: dict[str, int]
    """Agents whose requested action was masked, and the action applied instead."""


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
        self._last_obs: dict[str, npt.NDArray[np.float32]] = {}

    @property
    def backend(self) -> Backend:
        """The single SUMO simulation the episode runs on."""
        return self.engine.single_backend

    def reset(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self._last_obs = {}
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
        for a, o in zip(batch.ids, batch.obs, strict=True):
            self._last_obs[a] = o
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
        index = {a: i for i, a in enumerate(batch.ids)}
        rows = np.array([index[a] for a in agent_ids], dtype=np.int64)
        if not len(rows):
            return batch.obs[:0], batch.masks[:0]
        return batch.obs[rows], batch.masks[rows]

    def last_observation(self, agent_id: str) -> npt.NDArray[np.float32]:
        return self._last_obs[agent_id]

    def prev_accel(self, agent_id: str) -> float:
        return self.engine.prev_accel(0, agent_id)

    def state(self) -> npt.NDArray[np.float32]:
        return self.engine.state(0)

    def agent_info(self, agent_id: str) -> dict[str, object]:
        """Raw physical values of an agent now (or at its last step on the road)."""
        return agent_info(self.engine, 0, agent_id)

    def step(self, actions: Mapping[str, object]) -> StepOutcome:
        """Apply one action per active agent, advance SUMO one step, score it and end whoever is done."""
        batch = self.batch
        if self.engine.over(0):  # as gymnasium's OrderEnforcing refuses a step before reset()
            raise ResetFirst(EPISODE_OVER)
        acting = list(batch.ids)
        missing = [a for a in acting if a not in actions]
        if missing:
            raise ValueError(f"no action for active agents {missing}")
        requested = np.array(
            [_checked_action(a, actions[a], batch.time_s) for a in acting], dtype=np.int64
        ).reshape(len(acting))
        result = self.engine.step(requested)
        parts = {
            a: dict(zip(result.part_names, map(float, result.reward_parts[i]), strict=True))
            for i, a in enumerate(acting)
        }
        end_reason = {a: r for a, r in zip(acting, result.end_reason, strict=True) if r}
        outcome = StepOutcome(
            rewards={a: float(r) for a, r in zip(acting, result.rewards, strict=True)},
            reward_parts=parts,
            joint_reward=float(result.joint_reward[0]),
            terminated={a: a in end_reason and end_reason[a] != "timeout" for a in acting},
            truncated={a: end_reason.get(a) == "timeout" for a in acting},
            end_reason=end_reason,
            hard_brakes=int(result.hard_brakes[0]),
            hard_brakes_merge_zone=int(result.hard_brakes_merge_zone[0]),
            collisions=list(result.collisions[0]),
            replaced_actions={
                a: int(applied)
                for a, wanted, applied in zip(acting, requested, result.applied, strict=True)
                if wanted != applied
            },
        )
        self._advance()
        return outcome

    def close(self) -> None:
        self.engine.close()


def agent_info(engine: MergeEngine, k: int, agent_id: str) -> dict[str, object]:
    """Raw physical values of slot k's agent now (or at its last step on the road); ``road`` "gone" once
    it left the road."""
    snap = engine.snapshot
    i = engine.row(k, agent_id)
    if i is not None:
        accel = engine.prev_accel(k, agent_id) if engine.admitted(k, agent_id) else snap.accel_mps2[i]
        return {
            "speed_mps": float(snap.speed_mps[i]),
            "accel_mps2": float(accel),
            "dist_to_merge_m": float(snap.dist_to_merge_m[i]),
            "road": ROAD_NAMES[int(snap.road[i])],
        }
    return {
        "speed_mps": float("nan"),
        "accel_mps2": float("nan"),
        "dist_to_merge_m": float("nan"),
        "road": "gone",
    }


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
