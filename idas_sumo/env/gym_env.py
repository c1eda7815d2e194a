"""Gymnasium single-agent view: one ego; the others are SUMO's robot cars or run a given policy."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from gymnasium import Env, spaces

from idas_sumo.env.actions import N_ACTIONS, SafetyMask
from idas_sumo.env.config import EnvConfig, with_safety_mask
from idas_sumo.env.contracts import Policy, placeholder_mask
from idas_sumo.env.drawing import RENDER_MODES, TopViewFrames, checked_render_mode, slot_frame
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.parallel import DEFAULT_NET
from idas_sumo.env.scenario import (
    Scenario,
    TrafficConfig,
    VehicleSpec,
    check_against_net,
    generate_scenario,
    start_room_m,
)
from idas_sumo.env.single import EPISODE_OVER, ResetFirst, SingleEpisode, _checked_action
from idas_sumo.errors import SimulationError
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.netgen import MergeNet


def with_controlled(scenario: Scenario, controlled: set[str]) -> Scenario:
    """The same scenario with exactly ``controlled`` driven by the adapter, the rest by SUMO."""
    vehicles = tuple(
        VehicleSpec(v.id, v.road, v.start_pos_m, v.speed_mps, v.b_type, v.id in controlled, v.depart_s)
        for v in scenario.vehicles
    )
    return Scenario(scenario.name, vehicles, scenario.main_prio, scenario.merge_prio)


_EGO_ATTEMPTS = 100
"""Drawn scenarios tried until the ego gets to act (a late entry may come after the timeout)."""


class MergeEnv(Env[npt.NDArray[np.float32], int]):
    """One ego vehicle learns; the others are robot cars (``others=None``) or follow ``others``.

    ``info["action_mask"]`` carries the ego's mask each step (also the raw physical values and the
    named reward parts); ``action_masks()`` returns the same mask as a bool array, the method
    sb3-contrib's ``MaskablePPO`` looks for (it reaches it through gymnasium's wrappers and SB3's vector
    envs). The reward is the ego's own (finish + collide + impede).

    Several environments may live in one process: libsumo runs one simulation per process, so the
    second and later ones run their SUMO in a child Python process (``SubprocessBackend``, started with
    ``subprocess``, so no ``if __name__ == "__main__":`` guard is needed); ``close()`` ends it.
    """

    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES), "render_fps": 5}

    def __init__(
        self,
        net: MergeSite | MergeNet | str | Path = DEFAULT_NET,
        scenario: Scenario | None = None,
        ego: str | None = None,
        others: Policy | None = None,
        traffic: TrafficConfig | None = None,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        gui: bool = False,
        safety_mask: SafetyMask | None = None,
    ) -> None:
        self.render_mode = checked_render_mode(render_mode)
        self._frames: TopViewFrames | None = None
        gui = gui or render_mode == "human"
        self.sim = SingleEpisode(net, config=with_safety_mask(config, safety_mask), gui=gui)
        # Among robots the ego is the only agent, and its observation is handed out every step.
        self.sim.engine.eager_obs = others is None
        if scenario is not None:
            engine = self.sim.engine
            check_against_net(scenario, engine.speed_limits_mps, start_room_m(engine.site), scenario.name)
            if ego is not None and ego not in {v.id for v in scenario.vehicles}:
                raise ValueError(f"ego {ego!r} is not a vehicle of scenario {scenario.name!r}")
        self.fixed_scenario = scenario
        self.fixed_ego = ego
        self.others = others
        self.traffic = traffic or TrafficConfig()
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(OBS_DIM,), dtype=np.float32)
        self.action_space: spaces.Space[Any] = spaces.Discrete(N_ACTIONS)
        self.ego = ""
        self._mask = placeholder_mask()
        self._ended = False
        """The ego's episode ended (terminated or truncated was returned): step() needs a reset() first."""

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[npt.NDArray[np.float32], dict[str, Any]]:
        super().reset(seed=seed)
        given = (options or {}).get("scenario") or self.fixed_scenario
        for _ in range(_EGO_ATTEMPTS):
            scenario = given
            if scenario is None:
                scenario = generate_scenario(
                    self.np_random,
                    self.traffic,
                    self.sim.engine.speed_limits_mps,
                    start_room_m=start_room_m(self.sim.engine.site),
                )
            ego = self.fixed_ego or str(self.np_random.choice([v.id for v in scenario.vehicles]))
            controlled = {v.id for v in scenario.vehicles} if self.others is not None else {ego}
            self.ego = ego
            self.sim.reset(with_controlled(scenario, controlled))
            self._advance_until_ego()
            if self.ego in self.sim.active_agents:
                break
            # The ego never got to act: its entry came after the timeout, or it collided as it entered.
            if given is not None:
                raise ValueError(
                    f"ego {ego!r} of scenario {scenario.name!r} never drives: it enters after the "
                    f"{self.sim.engine.config.max_episode_s:g} s timeout or collides as it enters"
                )
        else:
            raise SimulationError(
                f"no drawn scenario let the ego drive in {_EGO_ATTEMPTS} attempts: each entered after the "
                f"{self.sim.engine.config.max_episode_s:g} s timeout (max_episode_s) or collided as it entered"
            )
        obs, masks = self.sim.observe([self.ego])
        self._mask = masks[0]
        self._ended = False
        return obs[0], self._info(self._mask)

    def _advance_until_ego(self) -> None:
        while self.ego not in self.sim.active_agents and not self.sim.episode_over:
            self.sim.step_requested(self._others_actions(-1))

    def _others_actions(self, ego_row: int) -> npt.NDArray[np.int64]:
        """Every agent's action in batch order: ``others``' for all but row ``ego_row`` (-1: no ego), which
        is left 0 for the caller to fill."""
        batch = self.sim.batch
        actions = np.zeros(len(batch), dtype=np.int64)
        if len(batch) == (ego_row >= 0):  # nobody but the ego (every step among robots)
            return actions
        rows = np.arange(len(batch), dtype=np.int64)
        if ego_row >= 0:
            rows = np.concatenate((rows[:ego_row], rows[ego_row + 1 :]))  # (np.delete's, without its checks)
        if len(rows):
            assert self.others is not None
            chosen = self.others.act(batch, rows)
            if isinstance(chosen, np.ndarray) and chosen.dtype == np.int64:
                actions[rows] = chosen
            else:
                actions[rows] = [int(a) for a in chosen.tolist()]
        return actions

    def action_masks(self) -> npt.NDArray[np.bool_]:
        """The ego's current action mask (True = allowed): ``info["action_mask"]`` of the last reset/step.

        After the episode ended (before the next reset) it is the placeholder mask handed back with the
        last observation.
        """
        return self._mask.astype(bool)

    def _info(self, mask: npt.NDArray[np.int8], **extra: Any) -> dict[str, Any]:
        return {"action_mask": mask, "ego": self.ego, **self.sim.agent_info(self.ego), **extra}

    def step(self, action: int) -> tuple[npt.NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        if self._ended:  # the ego has left: there is no next step until reset() (was a KeyError)
            raise ResetFirst(EPISODE_OVER)
        sim = self.sim
        batch = sim.batch
        ego = self.ego
        ego_row = batch.ids.index(ego)
        actions = self._others_actions(ego_row)
        if type(action) is not int or not 0 <= action < N_ACTIONS:  # (a plain int passes as it is)
            action = _checked_action(ego, action, batch.time_s)
        actions[ego_row] = action
        # The ego's entries of the step's result read by its row in the batch that acted (``StepOutcome``'s
        # lookups, without them).
        result = sim.step_requested(actions).result
        reward = float(result.rewards[ego_row])
        reason = result.end_reason[ego_row]
        info = self._info_now()
        info["reward_parts"] = dict(
            zip(result.part_names, result.reward_parts[ego_row].tolist(), strict=True)
        )
        if not reason:
            now = sim.batch
            row = now.ids.index(ego)
            self._mask = mask = now.masks[row].copy()
            info["action_mask"] = mask
            return now.obs_row(row), reward, False, False, info
        info["end_reason"] = reason
        terminated, truncated = reason != "timeout", reason == "timeout"
        self._ended = True
        self._mask = info["action_mask"] = placeholder_mask()
        return sim.last_observation(ego), reward, terminated, truncated, info

    def _info_now(self) -> dict[str, Any]:
        """``_info``'s entries but the mask (set by the caller), the ego's values as they are now."""
        return {"action_mask": None, "ego": self.ego, **self.sim.agent_info(self.ego)}

    def render(self) -> npt.NDArray[np.uint8] | None:
        """``render_mode="rgb_array"``: the merge from above now (the drawing of ``idas-sumo replay``), a
        (320, 640, 3) uint8 frame, the ego ringed; ``"human"`` draws nothing here: sumo-gui shows every
        step."""
        if self.render_mode != "rgb_array":
            return None
        if self.sim.scenario is None:
            raise ResetFirst("render() before reset(): call reset() first")
        if self._frames is None:
            self._frames = TopViewFrames(self.sim.engine.site)
        return slot_frame(self._frames, self.sim.engine, 0, self.ego)

    def close(self) -> None:
        self.sim.close()
