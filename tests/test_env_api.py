"""The two environments pass the official API checkers, are reproducible per seed, and expose the
documented observation, info and state."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import pytest

import idas_sumo  # noqa: F401  (registers idas_sumo/Merge-v0)
from idas_sumo.env import MergeEnv, MergeParallelEnv
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.engine import AgentBatch, EnvConfig
from idas_sumo.env.layout import GRID_CELLS, N_SCALARS, OBS_DIM
from idas_sumo.env.parallel import END_REASONS, GONE, ROAD_NAMES
from idas_sumo.env.scenario import Scenario, VehicleSpec
from idas_sumo.env.state_layout import STATE_DIM
from idas_sumo.errors import SimulationError

pytestmark = [pytest.mark.sumo, pytest.mark.usefixtures("no_leaked_simulation")]

INFO_KEYS = {"speed_mps", "accel_mps2", "dist_to_merge_m", "road"}


def test_gymnasium_check_env(small_budget: Any) -> None:
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make("idas_sumo/Merge-v0", **small_budget.env_kwargs()).unwrapped
    try:
        assert isinstance(env, MergeEnv)
        check_env(env, skip_render_check=True)
        obs, info = env.reset(seed=1)
        assert obs.shape == (OBS_DIM,) and obs.dtype == np.float32
        assert info.keys() >= INFO_KEYS and info["action_mask"].shape == (N_ACTIONS,)
        done = False
        while not done:
            action = int(np.flatnonzero(info["action_mask"])[0])
            obs, _reward, terminated, truncated, info = env.step(action)
            assert INFO_KEYS | {"reward_parts", "action_mask"} <= info.keys()
            done = terminated or truncated
    finally:
        env.close()


def test_pettingzoo_parallel_api(small_budget: Any) -> None:
    from pettingzoo.test import parallel_api_test

    env = MergeParallelEnv(seed=0, **small_budget.env_kwargs())
    try:
        parallel_api_test(env, num_cycles=small_budget.api_cycles)
    finally:
        env.close()


def test_pettingzoo_seed_test(small_budget: Any) -> None:
    from pettingzoo.test import parallel_seed_test

    made: list[MergeParallelEnv] = []

    def make() -> MergeParallelEnv:
        env = MergeParallelEnv(**small_budget.env_kwargs())
        made.append(env)
        return env

    try:
        parallel_seed_test(make, num_cycles=small_budget.api_cycles)
    finally:
        for env in made:
            env.close()


def _trajectory(seed: int, budget: Any) -> list[tuple[dict[str, np.ndarray], dict[str, float]]]:
    env = MergeParallelEnv(seed=seed, **budget.env_kwargs())
    rng = np.random.default_rng(seed)
    trace = []
    try:
        obs, _ = env.reset(seed=seed)
        trace.append(({a: o["observation"] for a, o in obs.items()}, {}))
        while env.agents:
            actions = {a: int(rng.choice(np.flatnonzero(obs[a]["action_mask"]))) for a in env.agents}
            obs, rewards, _, _, _ = env.step(actions)
            trace.append(({a: o["observation"] for a, o in obs.items()}, rewards))
    finally:
        env.close()
    return trace


def test_same_seed_same_trajectory(small_budget: Any) -> None:
    a, b = _trajectory(5, small_budget), _trajectory(5, small_budget)
    assert len(a) == len(b) > 5
    for (obs_a, rew_a), (obs_b, rew_b) in zip(a, b, strict=True):
        assert obs_a.keys() == obs_b.keys()
        for agent in obs_a:
            np.testing.assert_array_equal(obs_a[agent], obs_b[agent])
        assert rew_a == rew_b
    c = _trajectory(6, small_budget)
    assert len(c) != len(a) or any(
        x[0].keys() != y[0].keys() or any(not np.array_equal(x[0][k], y[0][k]) for k in x[0])
        for x, y in zip(a, c, strict=False)
    )


def _assert_numeric(value: Any) -> None:
    """Numbers all the way down: TorchRL's PettingZooWrapper makes a tensor of each (a str fails)."""
    if isinstance(value, dict):
        for v in value.values():
            _assert_numeric(v)
    else:
        assert np.asarray(value).dtype.kind in "biuf", value


def test_infos_and_state(small_budget: Any) -> None:
    env = MergeParallelEnv(seed=2, **small_budget.env_kwargs())
    try:
        obs, infos = env.reset(seed=2)
        assert env.agents and set(infos) == set(env.agents)
        for a in env.agents:
            assert infos[a].keys() >= INFO_KEYS
            assert ROAD_NAMES[infos[a]["road"]] in ("main", "merge")  # numbers only (TorchRL's tensors)
            assert 0.0 < infos[a]["dist_to_merge_m"] <= 250.0
            assert obs[a]["observation"].shape == (OBS_DIM,) and obs[a]["observation"].dtype == np.float32
            assert obs[a]["action_mask"].dtype == np.int8
        state = env.state()
        assert state.shape == (STATE_DIM,) and state.dtype == np.float32
        assert env.state_space.contains(state)
        _assert_numeric(infos)
        obs, _rewards, _, _, infos = env.step(dict.fromkeys(env.agents, 2))
        _assert_numeric(infos)
        for info in infos.values():
            assert info.keys() >= INFO_KEYS
            assert set(info["reward_parts"]) == {"finish", "collide", "impede", "flow"}
            assert "joint_reward" in info
        assert env.state().shape == (STATE_DIM,)
    finally:
        env.close()


def test_observation_grids_place_neighbours() -> None:
    # ego on main 150 m before the merge at 10 m/s; 'front' 10 m ahead on main at 14 m/s;
    # 'side' on the merge road 10 m further from the merge point than ego, at 8 m/s.
    scenario = Scenario(
        "grid",
        (
            VehicleSpec("ego", "main", 100.0, 10.0, b_type=1.0),
            VehicleSpec("front", "main", 110.0, 14.0, b_type=0.0),
            VehicleSpec("side", "merge", 90.0, 8.0, b_type=0.0),
        ),
        main_prio=1,
        merge_prio=0,
    )
    env = MergeParallelEnv(scenario=scenario)
    try:
        obs, infos = env.reset()
        assert infos["ego"]["dist_to_merge_m"] == pytest.approx(150.0)
        o = obs["ego"]["observation"]
        scalars = o[:N_SCALARS]
        np.testing.assert_allclose(scalars, [10.0 / 20.0, 0.0, 150.0 / 250.0, 1.0, 1.0 / 2.0], rtol=1e-6)
        grids = o[N_SCALARS:].reshape(2, 2, GRID_CELLS)
        cl_occ, cl_speed, ol_occ, ol_speed = grids[0, 0], grids[0, 1], grids[1, 0], grids[1, 1]
        # Cell 200 starts at ego's front bumper, 0.5 m per cell. 'front': rear 5 m ahead, front 10 m
        # ahead -> cells 210..220; relative speed (14 - 10)/20 = 0.2.
        assert np.flatnonzero(cl_occ).tolist() == list(range(210, 221))
        np.testing.assert_allclose(cl_speed[210:221], 0.2, rtol=1e-6)
        assert np.count_nonzero(cl_speed) == 11
        # 'side': front 10 m behind, rear 15 m behind -> cells 170..180; (8 - 10)/20 = -0.1.
        assert np.flatnonzero(ol_occ).tolist() == list(range(170, 181))
        np.testing.assert_allclose(ol_speed[170:181], -0.1, rtol=1e-6)
        assert np.count_nonzero(ol_speed) == 11
        # The ego itself is in neither grid.
        assert cl_occ[190:210].sum() == 0
        # From 'front''s point of view, ego is 10 m behind on its current lane.
        f = obs["front"]["observation"][N_SCALARS:].reshape(2, 2, GRID_CELLS)
        assert np.flatnonzero(f[0, 0]).tolist() == list(range(170, 181))
        np.testing.assert_allclose(f[0, 1][170:181], -0.2, rtol=1e-6)
    finally:
        env.close()


def test_close_twice_and_misuse() -> None:
    env = MergeParallelEnv(seed=0)
    with pytest.raises(SimulationError):
        env.step({})  # before reset
    env.reset(seed=0)
    actions = dict.fromkeys(env.agents, 2)
    env.step(actions)
    env.close()
    env.close()
    with pytest.raises(SimulationError):
        env.step(dict.fromkeys(env.agents, 2))
    with pytest.raises(SimulationError):
        env.reset(seed=0)

    genv = MergeEnv()
    with pytest.raises(SimulationError):
        genv.step(2)  # before reset
    genv.reset(seed=0)
    genv.close()
    genv.close()
    with pytest.raises(SimulationError):
        genv.step(2)


def test_agents_come_and_go() -> None:
    # 'late' enters 1 s into the episode; 'early' leaves when it finishes 50 m past the merge point.
    scenario = Scenario(
        "come-and-go",
        (
            VehicleSpec("early", "main", 230.0, 20.0),
            VehicleSpec("late", "merge", 10.0, 10.0, depart_s=1.0),
        ),
    )
    env = MergeParallelEnv(scenario=scenario, config=EnvConfig(max_episode_s=8.0))
    try:
        obs, infos = env.reset()
        assert env.agents == ["early"] and set(obs) == set(infos) == {"early"}
        seen: list[list[str]] = []
        ended: dict[str, str] = {}
        while env.agents:
            acting = list(env.agents)
            obs, _, terminated, truncated, infos = env.step(dict.fromkeys(acting, 2))
            seen.append(list(env.agents))
            for a in acting:  # every agent that acted gets its step's results
                assert a in obs and a in infos and a in terminated and a in truncated
                if "end_reason" in infos[a]:
                    ended[a] = END_REASONS[infos[a]["end_reason"]]
            for a in env.agents:  # every agent still in the game has an observation
                assert a in obs and obs[a]["action_mask"].any()
                assert infos[a]["road"] != GONE
        assert ["early", "late"] in seen  # both on the road at once
        assert ended["early"] == "finished"
        assert ended["late"] == "timeout"
        assert env.sim.time_s == pytest.approx(8.0)
    finally:
        env.close()


def test_reset_waits_for_the_first_agent() -> None:
    # Every controlled car enters late: reset runs the simulation until the first one is on the road,
    # so the episode does not look over before it started.
    scenario = Scenario("late", (VehicleSpec("late", "merge", 10.0, 10.0, depart_s=1.0),))
    env = MergeParallelEnv(scenario=scenario)
    try:
        obs, infos = env.reset()
        assert env.agents == ["late"] and set(obs) == set(infos) == {"late"}
        assert env.sim.time_s == pytest.approx(1.2)  # departs in the step that ends at 1.2 s
        assert not env.sim.episode_over
    finally:
        env.close()


def test_gym_env_with_policy_driven_others(small_budget: Any) -> None:
    # The others follow a given policy (always the first allowed action); they act only within masks.
    class FirstAllowed:
        def act(self, batch: AgentBatch, rows: np.ndarray) -> np.ndarray:
            assert batch.obs[rows].shape[1:] == (OBS_DIM,) and batch.masks[rows].shape[1:] == (N_ACTIONS,)
            assert env.ego not in {batch.ids[i] for i in rows}
            return np.argmax(batch.masks[rows], axis=1)

    env = MergeEnv(others=FirstAllowed(), **small_budget.env_kwargs())
    try:
        for seed in range(small_budget.episodes):
            _, info = env.reset(seed=seed)
            assert set(env.sim.active_agents) >= {env.ego}
            assert len(env.sim.scenario.controlled_ids) == len(env.sim.scenario.vehicles)  # type: ignore[union-attr]
            done = False
            while not done:
                _, _, terminated, truncated, info = env.step(2 if info["action_mask"][2] else 5)
                done = terminated or truncated
            assert info["end_reason"] in ("finished", "collided", "timeout", "removed")
    finally:
        env.close()


def test_action_masks_method_through_the_wrappers(small_budget: Any) -> None:
    # MaskablePPO reads the mask with get_wrapper_attr("action_masks"); it must equal info["action_mask"]
    # after reset and every step, including the placeholder handed back with the last observation.
    env = gymnasium.make("idas_sumo/Merge-v0", **small_budget.env_kwargs())
    try:
        assert env is not env.unwrapped  # gymnasium's wrappers are in between
        masks = env.get_wrapper_attr("action_masks")
        _, info = env.reset(seed=4)
        forbidding = 0
        done = False
        while not done:
            mask = masks()
            assert mask.dtype == bool and mask.shape == (N_ACTIONS,)
            np.testing.assert_array_equal(mask, info["action_mask"].astype(bool))
            forbidding += int(not mask.all())
            action = int(np.flatnonzero(mask)[-1])  # the highest allowed index: brakes when it may
            _, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        np.testing.assert_array_equal(masks(), info["action_mask"].astype(bool))
        assert forbidding > 0  # the episode met the safety mask, so equality above is not trivial
    finally:
        env.close()
