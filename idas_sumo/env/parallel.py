"""PettingZoo ``ParallelEnv`` over the merge: every controlled vehicle is an agent; agents come and go."""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.utils.env_logger import EnvLogger

from idas_sumo.env.actions import N_ACTIONS, SafetyMask
from idas_sumo.env.config import EnvConfig, with_safety_mask
from idas_sumo.env.contracts import placeholder_mask
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.outcome import END_REASONS
from idas_sumo.env.scenario import (
    ROADS,
    Scenario,
    TrafficConfig,
    check_against_net,
    generate_scenario,
    start_room_m,
)
from idas_sumo.env.single import ResetFirst, SingleEpisode, StepOutcome
from idas_sumo.env.snapshot import ROAD_NAMES
from idas_sumo.env.state_layout import STATE_DIM
from idas_sumo.resources import DEFAULT_NET
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.netgen import MergeNet

GONE = -1
"""``infos[agent]["road"]`` of a car no longer on the road (else an index into ``ROAD_NAMES``)."""

__all__ = ["END_REASONS", "GONE", "ROAD_NAMES", "MergeParallelEnv", "observation_space"]


def observation_space() -> spaces.Dict:
    return spaces.Dict(
        {
            "observation": spaces.Box(-np.inf, np.inf, shape=(OBS_DIM,), dtype=np.float32),
            "action_mask": spaces.Box(0, 1, shape=(N_ACTIONS,), dtype=np.int8),
        }
    )


class MergeParallelEnv(ParallelEnv[str, dict[str, np.ndarray], int]):
    """The merge as a PettingZoo parallel environment.

    Each reset draws a random scenario from the env's seed (or uses ``scenario``, or
    ``options={"scenario": ...}``). Observations are ``{"observation", "action_mask"}``; ``infos`` carry
    the raw physical values (``speed_mps``, ``accel_mps2``, ``dist_to_merge_m``, ``road``) and the named
    ``reward_parts``; ``state()`` is the centralised critic's input. Infos hold numbers only (wrappers
    such as TorchRL's make a tensor of each value): ``road`` is an index into ``ROAD_NAMES`` (-1: the car
    left the road), ``end_reason`` one into ``END_REASONS``. The shared flow penalty is not in
    ``rewards`` (the paper counts it only in the joint reward): read it from ``reward_parts["flow"]``
    or ``infos[agent]["joint_reward"]``.

    Several environments may live in one process: libsumo runs one simulation per process, so the
    second and later ones run their SUMO in a child Python process (``SubprocessBackend``, started with
    ``subprocess``, so no ``if __name__ == "__main__":`` guard is needed); ``close()`` ends it.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "name": "idas_sumo_merge_v0",
        "render_modes": [],
        "is_parallelizable": True,
    }  # gui=True: sumo-gui

    def __init__(
        self,
        net: MergeSite | MergeNet | str | Path = DEFAULT_NET,
        scenario: Scenario | None = None,
        traffic: TrafficConfig | None = None,
        config: EnvConfig | None = None,
        seed: int | None = None,
        render_mode: str | None = None,
        gui: bool = False,
        safety_mask: SafetyMask | None = None,
    ) -> None:
        self.render_mode = render_mode
        config = with_safety_mask(config, safety_mask)
        self.sim = SingleEpisode(net, seed=seed or 0, config=config, gui=gui)
        self.sim.engine.eager_obs = True  # (every agent's observation is handed out every step)
        self.fixed_scenario = scenario
        self.traffic = traffic or TrafficConfig()
        if scenario is not None:
            engine = self.sim.engine
            check_against_net(scenario, engine.speed_limits_mps, start_room_m(engine.site), scenario.name)
            self.possible_agents = list(scenario.controlled_ids)
        else:
            self.possible_agents = [f"{r}{i}" for r in ROADS for i in range(self.traffic.max_on_one_road)]
        self.agents: list[str] = []
        self._rng = np.random.default_rng(seed)
        self._obs_space = observation_space()
        self._act_space = spaces.Discrete(N_ACTIONS)
        self.state_space = spaces.Box(-np.inf, np.inf, shape=(STATE_DIM,), dtype=np.float32)
        self.last_outcome: StepOutcome | None = None

    def observation_space(self, agent: str) -> spaces.Space[Any]:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Space[Any]:
        return self._act_space

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, dict[str, Any]]]:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        scenario = (options or {}).get("scenario") or self.fixed_scenario
        if scenario is None:
            engine = self.sim.engine
            scenario = generate_scenario(
                self._rng, self.traffic, engine.speed_limits_mps, start_room_m=start_room_m(engine.site)
            )
        self.sim.reset(scenario)
        self.agents = self.sim.active_agents
        observations = self._observations()
        infos = self._infos(self.agents)
        return observations, infos

    def _observations(self) -> dict[str, dict[str, np.ndarray]]:
        obs, masks = self.sim.observe(self.agents)
        return {
            a: {"observation": o, "action_mask": m} for a, o, m in zip(self.agents, obs, masks, strict=True)
        }

    def _infos(self, agents: list[str], outcome: StepOutcome | None = None) -> dict[str, dict[str, Any]]:
        """Each agent's info: its raw physical values (``agent_info``), and with ``outcome`` the step's
        reward parts, joint reward, end reason and replaced action."""
        infos: dict[str, dict[str, Any]] = {}
        if not agents:  # (no agent entered: most steps)
            return infos
        for agent, info in zip(agents, self._physical(agents), strict=True):
            if outcome is not None:
                info["reward_parts"] = outcome.reward_parts[agent]
                info["joint_reward"] = outcome.joint_reward
                if agent in outcome.end_reason:
                    info["end_reason"] = END_REASONS.index(outcome.end_reason[agent])
                if agent in outcome.replaced_actions:
                    info["replaced_action"] = outcome.replaced_actions[agent]
            infos[agent] = info
        return infos

    def _physical(self, agents: list[str]) -> list[dict[str, Any]]:
        """``agent_infos`` of these agents with the road as its index (``GONE`` once off the road), read
        straight from the engine's values (not through the road's name and back)."""
        engine = self.sim.engine
        if not len(engine.snapshot):
            infos = self.sim.agent_infos(agents)
            for info in infos:
                road = info["road"]
                info["road"] = ROAD_NAMES.index(road) if road in ROAD_NAMES else GONE
            return infos
        nan = float("nan")
        return [
            {"speed_mps": s, "accel_mps2": a, "dist_to_merge_m": d, "road": r}
            if r >= 0
            else {"speed_mps": nan, "accel_mps2": nan, "dist_to_merge_m": nan, "road": GONE}
            for s, a, d, r in zip(*engine.agent_values(0, agents), strict=True)
        ]

    def step(
        self, actions: dict[str, int]
    ) -> tuple[
        dict[str, dict[str, np.ndarray]],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        if not self.agents:
            if self.sim.scenario is None:
                raise ResetFirst("step() before reset(): call reset() first")
            # After the episode: PettingZoo's convention (its OrderEnforcingWrapper), a warning and nothing
            # done; SUMO is not stepped past the episode's end.
            EnvLogger.warn_step_after_terminated_truncated()
            return {}, {}, {}, {}, {}
        acting = list(self.agents)
        outcome = self.sim.step({a: actions[a] for a in acting if a in actions})  # checked there, per agent
        self.last_outcome = outcome
        infos = self._step_infos(acting, outcome)
        self.agents = self.sim.active_agents
        observations = self._observations()
        for a in acting:
            if a not in observations:  # ended this step: hand back its last observation
                observations[a] = {
                    "observation": self.sim.last_observation(a),
                    "action_mask": placeholder_mask(),
                }
        acted = set(acting)
        new_agents = [a for a in self.agents if a not in acted]
        infos.update(self._infos(new_agents))
        if self.sim.timed_out():
            self.agents = []
        # ``outcome``'s rewards, terminated and truncated, read from the step's rows in one pass (its
        # per-agent dictionaries cost more than the step's SUMO call); agents that entered get 0.0 and False.
        # (Every agent that acted has an observation: the dictionaries' order is the observations'.)
        result = outcome.result
        rewards: dict[str, float] = dict.fromkeys(observations, 0.0)
        rewards.update(zip(outcome.acting, result.rewards.tolist(), strict=True))
        terminated: dict[str, bool] = dict.fromkeys(observations, False)
        truncated: dict[str, bool] = dict.fromkeys(observations, False)
        if any(result.end_reason):
            for a, end in zip(outcome.acting, result.end_reason, strict=True):
                if end:
                    terminated[a] = end != "timeout"
                    truncated[a] = end == "timeout"
        return observations, rewards, terminated, truncated, infos

    def _step_infos(self, acting: list[str], outcome: StepOutcome) -> dict[str, dict[str, Any]]:
        """``_infos(acting, outcome)`` read from the step's rows in one pass (same entries, same order):
        each agent's dictionary made at once, not filled in entry by entry."""
        engine = self.sim.engine
        if not len(engine.snapshot):
            return self._infos(acting, outcome)
        result = outcome.result
        names = result.part_names
        joint = float(result.joint_reward[0])
        nan = float("nan")
        infos: dict[str, dict[str, Any]] = {}
        for agent, s, a, d, r, parts in zip(
            acting, *engine.agent_values(0, acting), result.reward_parts.tolist(), strict=True
        ):
            if r < 0:
                s = a = d = nan
                r = GONE
            infos[agent] = {
                "speed_mps": s,
                "accel_mps2": a,
                "dist_to_merge_m": d,
                "road": r,
                "reward_parts": dict(zip(names, parts, strict=True)),
                "joint_reward": joint,
            }
        # The rare entries after the others (most steps nobody ends and no action is replaced).
        if any(result.end_reason):
            for agent, end in zip(acting, result.end_reason, strict=True):
                if end:
                    infos[agent]["end_reason"] = END_REASONS.index(end)
        requested, applied = outcome.requested.tolist(), result.applied.tolist()
        if requested != applied:
            for agent, wanted, got in zip(acting, requested, applied, strict=True):
                if wanted != got:
                    infos[agent]["replaced_action"] = got
        return infos

    def state(self) -> np.ndarray:
        return self.sim.state()

    def render(self) -> None:
        """Nothing to draw here: create the env with ``gui=True`` to watch the run in sumo-gui."""

    def close(self) -> None:
        self.sim.close()
