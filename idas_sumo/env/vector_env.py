"""Gymnasium vector view: K single-ego worlds side by side in one SUMO, on the episode engine (copies = K).

``gymnasium.make_vec("idas_sumo/Merge-v0", num_envs=K)`` builds this. World k is ``MergeEnv`` (the
single-ego env) seeded with ``seed + k``: the same draws of scenario and ego, the same observations, rewards
and info, whatever K is. The K worlds run as slots of one ``MergeEngine``, so a step costs one SUMO step
for all of them.

Waves. SUMO advances every slot together and starts them together (one load), so a world cannot start its
next episode alone: the engine starts K episodes at once (a *wave*), and the next wave begins when every
world's episode has ended. Between its episode's end and the step its next ego enters the road, a world is
*idle*: ``info["idle"][k]`` is True, its action is ignored, its reward is 0, its observation zeros and its
mask allows only action 0 (the placeholder mask ``MergeEnv`` hands out after an episode). A world is idle
too while a new wave waits for its ego to enter (the single env's ``reset()`` lets that time run unseen).

Autoreset is Gymnasium 1.x's next-step mode, counting only a world's non-idle steps: the step that ends
an episode returns its last observation with ``terminated``/``truncated``; the world's next non-idle step
is the reset step (reward 0, not terminated, the new episode's first observation, the reset info) and
ignores its action. Dropping the idle rows of world k gives exactly ``MergeEnv``'s episodes
(tests/test_vector_env.py); a learner that cannot drop rows sees idle rows as reward-0 steps whose one
allowed action carries no policy gradient.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from idas_sumo.env.actions import N_ACTIONS, SafetyMask
from idas_sumo.env.config import EnvConfig, with_safety_mask
from idas_sumo.env.contracts import AgentBatch, Policy, StepResult, placeholder_mask
from idas_sumo.env.drawing import RENDER_MODES, TopViewFrames, checked_render_mode, slot_frame
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.gym_env import _EGO_ATTEMPTS, with_controlled
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.scenario import Scenario, TrafficConfig, check_against_net, generate_scenario, start_room_m
from idas_sumo.env.single import ResetFirst, _checked_action, agent_info
from idas_sumo.env.snapshot import ROAD_NAMES
from idas_sumo.errors import SimulationError
from idas_sumo.resources import DEFAULT_NET
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.netgen import MergeNet

_PRE, _ACTING, _DONE = 0, 1, 2
"""A world's phase: its episode runs but its ego is not on the road yet; its ego acts; it waits for the
next wave (its ego ended, or never got to act)."""

Obs = npt.NDArray[np.float32]
_ROAD_NAMES = np.array(ROAD_NAMES, dtype=object)
_PLACEHOLDER = placeholder_mask()
_NO_ROWS = np.zeros(0, dtype=np.int64)
_PLACEHOLDER.flags.writeable = False


class MergeVectorEnv(VectorEnv[Obs, npt.NDArray[np.int64], npt.NDArray[Any]]):
    """K ``MergeEnv`` worlds in one SUMO (module docstring: waves, idle worlds, autoreset).

    ``action_masks()`` is the (K, 7) bool mask of the last reset/step (``info["action_mask"]``), the
    method sb3-contrib's ``MaskablePPO`` calls through SB3's vector envs. ``others`` must act on each row
    alone (deterministic, or sampling from per-row state) for K not to change the episodes.
    """

    metadata: dict[str, Any] = {
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": list(RENDER_MODES),
        "render_fps": 5,
    }

    def __init__(
        self,
        num_envs: int = 1,
        net: MergeSite | MergeNet | str | Path = DEFAULT_NET,
        scenario: Scenario | None = None,
        ego: str | None = None,
        others: Policy | None = None,
        traffic: TrafficConfig | None = None,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        safety_mask: SafetyMask | None = None,
    ) -> None:
        render_mode = checked_render_mode(render_mode)
        self.engine = MergeEngine(
            net, copies=num_envs, config=with_safety_mask(config, safety_mask), gui=render_mode == "human"
        )
        if self.engine.copies != num_envs:
            self.engine.close()
            raise SimulationError(
                f"{num_envs} worlds need one SUMO run of {num_envs} copies, which this process cannot hold: "
                "another simulation is open in it (close that environment first) or the net cannot be copied"
            )
        if scenario is not None:
            check_against_net(
                scenario, self.engine.speed_limits_mps, start_room_m(self.engine.site), scenario.name
            )
            if ego is not None and ego not in {v.id for v in scenario.vehicles}:
                raise ValueError(f"ego {ego!r} is not a vehicle of scenario {scenario.name!r}")
        self.num_envs = num_envs
        self.render_mode = render_mode
        self._frames: TopViewFrames | None = None
        self.fixed_scenario, self.fixed_ego, self.others = scenario, ego, others
        self.traffic = traffic or TrafficConfig()
        self.single_observation_space = spaces.Box(-np.inf, np.inf, shape=(OBS_DIM,), dtype=np.float32)
        self.single_action_space = spaces.Discrete(N_ACTIONS)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._rngs: list[np.random.Generator | None] = [None] * num_envs
        self.egos = [""] * num_envs
        """Each world's ego in its current (or last) episode."""
        self._phase = np.full(num_envs, _DONE, dtype=np.int8)
        self._attempts = np.zeros(num_envs, dtype=np.int64)
        self._masks = np.tile(placeholder_mask(), (num_envs, 1))
        self._last_obs = np.zeros((num_envs, OBS_DIM), dtype=np.float32)
        self._batch: AgentBatch | None = None
        self._ego_row = np.full(num_envs, -1, dtype=np.int64)
        self._ego_car = np.zeros(num_envs, dtype=np.int64)
        self._worlds = list(range(num_envs))
        """Each world's ego as the engine's car (``MergeEngine.car_rows``), fixed for a wave."""
        self._unreleased: list[int] = []
        """The worlds whose slot is still in SUMO (``_release_over``), in order."""

    # -- episodes ----------------------------------------------------------------------------------
    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Obs, dict[str, Any]]:
        """Seed world k with ``seed + k`` (or ``seed[k]``) and start a wave; as ``MergeEnv.reset``."""
        if options:
            raise ValueError(f"options are not supported by the vector env, got {sorted(options)}")
        if isinstance(seed, Sequence):
            if len(seed) != self.num_envs:
                raise ValueError(f"{len(seed)} seeds for {self.num_envs} worlds")
            seeds = list(seed)
        else:
            super().reset(seed=seed)
            seeds = [None if seed is None else seed + k for k in range(self.num_envs)]
        for k, s in enumerate(seeds):
            if s is not None or self._rngs[k] is None:
                self._rngs[k] = seeding.np_random(s)[0]
        self._attempts[:] = 0
        self._new_wave()  # an episode still running is dropped, as MergeEnv.reset drops it
        started = self._observe()
        if not started:
            started = self._advance()
        obs, _, _, _, infos = self._outputs([], _NO_ROWS, started, None)
        return obs, infos

    def _draw(self, k: int) -> tuple[Scenario, str]:
        """World k's next scenario and ego, drawn as ``MergeEnv.reset`` draws them."""
        rng = self._rngs[k]
        assert rng is not None
        scenario = self.fixed_scenario
        if scenario is None:
            scenario = generate_scenario(
                rng, self.traffic, self.engine.speed_limits_mps, start_room_m=start_room_m(self.engine.site)
            )
        ego = self.fixed_ego or str(rng.choice([v.id for v in scenario.vehicles]))
        controlled = {v.id for v in scenario.vehicles} if self.others is not None else {ego}
        return with_controlled(scenario, controlled), ego

    def _new_wave(self) -> None:
        drawn = [self._draw(k) for k in range(self.num_envs)]
        self.egos = [ego for _, ego in drawn]
        self.engine.reset([s for s, _ in drawn])
        self._ego_car = np.array([self.engine.car_index(k, ego) for k, ego in enumerate(self.egos)], np.int64)
        self._phase[:] = _PRE
        self._unreleased = list(range(len(self.engine.slots)))

    def _observe(self) -> list[int]:
        """Read the engine's agents; returns the worlds whose ego entered now (their reset step)."""
        batch = self._batch = self.engine.observe()
        ego_row = self._ego_row
        ego_row[:] = -1
        if self.others is None:  # only the egos are agents
            ego_row[batch.copy] = np.arange(len(batch))
        elif len(batch):
            index = np.empty(len(batch.snapshot), dtype=np.int64)  # snapshot row -> batch row
            index.fill(-1)
            index[batch.egos] = np.arange(len(batch))
            rows = self.engine.car_rows(self._ego_car)  # each ego's snapshot row (-1: not on the road)
            on = (rows >= 0) & (self._phase != _DONE)
            ego_row[on] = index[rows[on]]
        started = []
        for k in (self._phase == _PRE).nonzero()[0].tolist():
            if self._ego_row[k] >= 0:
                self._phase[k] = _ACTING
                self._attempts[k] = 0
                started.append(k)
            elif self.engine.over(k):
                self._ego_failed(k)
        return started

    def _ego_failed(self, k: int) -> None:
        """World k's ego never got to act (it entered after the timeout, or collided as it entered)."""
        self._phase[k] = _DONE
        self._attempts[k] += 1
        timeout = self.engine.config.max_episode_s
        if self.fixed_scenario is not None:
            raise ValueError(
                f"ego {self.egos[k]!r} of scenario {self.fixed_scenario.name!r} never drives: it enters after "
                f"the {timeout:g} s timeout or collides as it enters"
            )
        if self._attempts[k] >= _EGO_ATTEMPTS:
            raise SimulationError(
                f"no drawn scenario let world {k}'s ego drive in {_EGO_ATTEMPTS} attempts: each entered after "
                f"the {timeout:g} s timeout (max_episode_s) or collided as it entered"
            )

    def _release_over(self) -> None:
        """Over slots leave SUMO, so that they cost nothing until the next wave."""
        if not self._unreleased:  # (every step once the wave's worlds left)
            return
        slots = self.engine.slots
        for k in [k for k in self._unreleased if slots[k].over]:
            self.engine.release_slot(k)
            self._unreleased.remove(k)

    def _advance(self) -> list[int]:
        """No world acts: let time run (the others drive) until an ego enters; a new wave once every
        world is done. Returns the worlds whose ego entered."""
        started: list[int] = []
        while not started:
            if (self._phase == _DONE).all() and all(s.over for s in self.engine.slots):
                self._new_wave()
            else:
                self._engine_step(np.zeros(self.num_envs, dtype=np.int64))
            started = self._observe()
        return started

    def _engine_step(self, ego_actions: npt.NDArray[np.int64]) -> StepResult:
        """One engine step: the acting egos take ``ego_actions``, every other agent follows ``others``."""
        batch = self._batch
        assert batch is not None
        self._release_over()
        actions = np.zeros(len(batch), dtype=np.int64)
        acting = self._phase == _ACTING
        ego_rows = self._ego_row[acting]
        is_ego = np.zeros(len(batch), dtype=np.bool_)
        is_ego[ego_rows] = True
        actions[ego_rows] = ego_actions[acting]
        rows = (~is_ego).nonzero()[0]
        if len(rows):
            assert self.others is not None
            actions[rows] = self.others.act(batch, rows)
        return self.engine.step(actions)

    # -- stepping ----------------------------------------------------------------------------------
    def step(
        self, actions: npt.ArrayLike
    ) -> tuple[Obs, npt.NDArray[np.float64], npt.NDArray[np.bool_], npt.NDArray[np.bool_], dict[str, Any]]:
        if self._batch is None:
            raise ResetFirst("step() before reset(): call reset() first")
        acts = np.asarray(actions)
        if acts.shape != (self.num_envs,):
            raise ValueError(
                f"actions of shape {acts.shape} for {self.num_envs} worlds: expected ({self.num_envs},)"
            )
        acting = (self._phase == _ACTING).nonzero()[0].tolist()
        if not acting:
            return self._outputs([], _NO_ROWS, self._advance(), None)
        batch = self._batch
        ego_actions = np.zeros(self.num_envs, dtype=np.int64)
        if acts.dtype.kind in "iu" and acts.min() >= 0 and acts.max() < N_ACTIONS:
            if acting == self._worlds:
                ego_actions[:] = acts
            else:
                ego_actions[acting] = acts[acting]
        else:  # an error names the world's ego (MergeEnv's message)
            for k in acting:
                ego_actions[k] = _checked_action(self.egos[k], acts[k].item(), batch.time_s)
        rows = self._ego_row[acting]
        result = self._engine_step(ego_actions)
        ended = [k for k, r in zip(acting, rows.tolist(), strict=True) if result.end_reason[r]]
        self._phase[ended] = _DONE
        started = self._observe()
        return self._outputs(acting, rows, started, result)

    def _outputs(
        self,
        worlds: list[int],
        ego_rows: npt.NDArray[np.int64],
        started: list[int],
        result: StepResult | None,
    ) -> tuple[Obs, npt.NDArray[np.float64], npt.NDArray[np.bool_], npt.NDArray[np.bool_], dict[str, Any]]:
        """The step's five outputs. ``worlds``: those whose ego acted, ``ego_rows``: their egos' rows in
        ``result``; ``started``: the worlds whose ego entered (their reset step)."""
        n = self.num_envs
        batch = self._batch
        assert batch is not None
        phase = self._phase.tolist()
        live = [k for k in worlds if phase[k] == _ACTING] + started
        everyone_lives = live == self._worlds  # every world's ego acts (most steps): no scatter anywhere
        masks = self._masks
        if everyone_lives:
            rows = self._ego_row
            obs = self._ego_observations(batch, rows)
            self._last_obs[:] = obs
            masks[:] = batch.masks[rows]
        else:
            obs = np.zeros((n, OBS_DIM), dtype=np.float32)
            masks[:] = _PLACEHOLDER
            if live:
                rows = self._ego_row[live]
                new = self._ego_observations(batch, rows)
                obs[live] = new
                self._last_obs[live] = new  # (an ended world is never live: it kept its last one)
                masks[live] = batch.masks[rows]
        reasons = [""] * n
        ended: list[int] = []
        if result is None or not worlds:
            rewards = np.zeros(n, dtype=np.float64)
            parts = np.zeros((n, len(result.part_names) if result is not None else 0))
        else:
            if worlds == self._worlds:
                rewards, parts = result.rewards[ego_rows], result.reward_parts[ego_rows]
            else:
                rewards = np.zeros(n, dtype=np.float64)
                parts = np.zeros((n, len(result.part_names)))
                rewards[worlds] = result.rewards[ego_rows]
                parts[worlds] = result.reward_parts[ego_rows]
            end_reason = result.end_reason
            for k, r in zip(worlds, ego_rows.tolist(), strict=True):
                if end_reason[r]:
                    reasons[k] = end_reason[r]
                    ended.append(k)
        terminated = np.zeros(n, dtype=np.bool_)
        truncated = np.zeros(n, dtype=np.bool_)
        if everyone_lives:  # (and so nobody ended)
            idle = np.zeros(n, dtype=np.bool_)
        else:
            if ended:
                obs[ended] = self._last_obs[ended]  # as MergeEnv: the observation the ego last acted on
                for k in ended:
                    (truncated if reasons[k] == "timeout" else terminated)[k] = True
            idle = np.ones(n, dtype=np.bool_)
            idle[live] = False
            idle[ended] = False
        infos = self._infos(idle, live, ended, worlds, parts, reasons, result)
        return obs, rewards, terminated, truncated, infos

    def _infos(
        self,
        idle: npt.NDArray[np.bool_],
        live: list[int],
        ended: list[int],
        stepped: list[int],
        parts: npt.NDArray[np.float64],
        reasons: list[str],
        result: StepResult | None,
    ) -> dict[str, Any]:
        """MergeEnv's info of each world, batched as Gymnasium's vector envs do (``_key``: who has ``key``).
        ``live``: the worlds whose ego acts now, ``ended``: those whose episode ended in this step (the
        others are idle)."""
        n = self.num_envs
        everyone = np.ones(n, dtype=np.bool_)
        infos: dict[str, Any] = {
            "action_mask": self._masks.copy(),
            "_action_mask": everyone,
            "idle": idle,
            "_idle": everyone,
        }
        acting = ~idle
        infos.update(self._ego_values(live, ended, acting))
        if result is not None and stepped:
            has = np.zeros(n, dtype=np.bool_)
            has[stepped] = True
            named: dict[str, Any] = {}
            columns = np.ascontiguousarray(parts.T)  # (one copy: each part's column a row of it)
            for j, name in enumerate(result.part_names):
                named[name], named[f"_{name}"] = columns[j], has
            infos["reward_parts"], infos["_reward_parts"] = named, has
            if ended:
                end_reason = np.empty(n, dtype=object)
                has_end = np.zeros(n, dtype=np.bool_)
                for k in ended:
                    end_reason[k] = reasons[k]
                    has_end[k] = True
                infos["end_reason"], infos["_end_reason"] = end_reason, has_end
        return infos

    def _ego_values(self, live: list[int], ended: list[int], acting: npt.NDArray[np.bool_]) -> dict[str, Any]:
        """The info's ego, speed, acceleration, distance and road of the acting worlds (``agent_info``'s
        values), each with its ``_key`` (``acting``)."""
        n = self.num_envs
        batch = self._batch
        assert batch is not None
        snap = batch.snapshot
        if live == self._worlds:  # every world's ego on the road and acting (most steps)
            rows = self._ego_row
            egos = batch.egos[rows]
            values: dict[str, npt.NDArray[Any]] = {
                "ego": np.array(self.egos, dtype=object),
                "speed_mps": snap.speed_mps[egos],
                "accel_mps2": batch.prev_accel[rows],
                "dist_to_merge_m": snap.dist_to_merge_m[egos],
                "road": _ROAD_NAMES[snap.road[egos]],
            }
        else:
            values = {
                "ego": np.empty(n, dtype=object),  # (None where unset)
                "speed_mps": np.zeros(n),
                "accel_mps2": np.zeros(n),
                "dist_to_merge_m": np.zeros(n),
                "road": np.empty(n, dtype=object),
            }
            if live:  # on the road and acting: read from the batch
                rows = self._ego_row[live]
                egos = batch.egos[rows]
                values["speed_mps"][live] = snap.speed_mps[egos]
                values["accel_mps2"][live] = batch.prev_accel[rows]
                values["dist_to_merge_m"][live] = snap.dist_to_merge_m[egos]
                values["road"][live] = _ROAD_NAMES[snap.road[egos]]
            ego = values["ego"]
            for k in (*live, *ended):
                ego[k] = self.egos[k]
            for k in ended:  # its episode ended in this step (agent_info: also when it left the road)
                for key, v in agent_info(self.engine, k, self.egos[k]).items():
                    values[key][k] = v
        out: dict[str, Any] = {}
        for key, v in values.items():
            out[key], out[f"_{key}"] = v, acting
        return out

    def _ego_observations(self, batch: AgentBatch, rows: npt.NDArray[np.int64]) -> Obs:
        """The egos' observations: only theirs are built when other agents share the batch."""
        return batch.obs_of(rows)

    def action_masks(self) -> npt.NDArray[np.bool_]:
        """(K, 7): each world's action mask of the last reset/step (True = allowed)."""
        return self._masks.astype(bool)

    def render(self) -> tuple[npt.NDArray[np.uint8], ...] | None:
        """``render_mode="rgb_array"``: one frame per world (``MergeEnv.render``'s), an idle world's slot as
        it is (empty once its episode ended); ``"human"`` draws nothing here: sumo-gui shows every step of
        the K worlds (each on its own copy of the net)."""
        if self.render_mode != "rgb_array":
            return None
        if self._batch is None:
            raise ResetFirst("render() before reset(): call reset() first")
        if self._frames is None:
            self._frames = TopViewFrames(self.engine.site)
        return tuple(slot_frame(self._frames, self.engine, k, self.egos[k]) for k in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:
        self.engine.close()
