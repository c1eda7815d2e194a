"""make_vec's vector env: K worlds in one SUMO give MergeEnv's episodes whatever K is; masks, autoreset, info."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest

import idas_sumo  # noqa: F401  (registers idas_sumo/Merge-v0)
from idas_sumo.env import MergeEnv
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.vector_env import MergeVectorEnv
from idas_sumo.errors import SimulationError

pytestmark = [pytest.mark.sumo, pytest.mark.usefixtures("no_leaked_simulation")]

SEED = 11
EPISODES = 2
"""Episodes per world compared: the second comes after a wave change (the autoreset path)."""


def _pick(rng: np.random.Generator, mask: np.ndarray) -> int:
    return int(rng.choice(np.flatnonzero(mask)))


Episode = list[tuple[bytes, float]]
"""(observation bytes, reward) per non-idle step; the reset observation has reward 0."""


class KeepOrFirst:
    """``others=``: keep the acceleration where allowed, else the first allowed action (row by row)."""

    def act(self, batch: Any, rows: np.ndarray) -> np.ndarray:
        masks = batch.masks[rows].astype(bool)
        return np.where(masks[:, 2], 2, np.argmax(masks, axis=1)).astype(np.int64)


def _vector_episodes(k_worlds: int, seed: int, budget: Any, others: Any = None) -> list[list[Episode]]:
    """EPISODES episodes of each world, idle rows dropped; world k's actions come from its own generator."""
    env = gymnasium.make_vec(
        "idas_sumo/Merge-v0",
        num_envs=k_worlds,
        vectorization_mode="vector_entry_point",
        others=others,
        **budget.env_kwargs(),
    )
    assert isinstance(env, MergeVectorEnv)
    rngs = [np.random.default_rng(1000 + seed + k) for k in range(k_worlds)]
    done: list[list[Episode]] = [[] for _ in range(k_worlds)]
    current: list[Episode] = [[] for _ in range(k_worlds)]
    try:
        obs, info = env.reset(seed=seed)
        assert obs.shape == (k_worlds, OBS_DIM) and env.action_masks().shape == (k_worlds, N_ACTIONS)
        reward = np.zeros(k_worlds)
        ended = np.zeros(k_worlds, dtype=bool)
        while min(len(d) for d in done) < EPISODES:
            masks = env.action_masks()
            assert np.array_equal(masks, info["action_mask"].astype(bool))
            actions = np.zeros(k_worlds, dtype=np.int64)
            for k in range(k_worlds):
                if info["idle"][k]:
                    assert masks[k].tolist() == [True] + [False] * (N_ACTIONS - 1) and not obs[k].any()
                    continue
                current[k].append((obs[k].tobytes(), float(reward[k])))
                if ended[k]:  # the next step is the reset step (it may come after idle steps): no action
                    done[k].append(current[k])
                    current[k] = []
                    continue
                actions[k] = _pick(rngs[k], masks[k])
            obs, reward, terminated, truncated, info = env.step(actions)
            ended = terminated | truncated
            assert not (ended & info["idle"]).any()
            assert (reward[info["idle"]] == 0).all()
    finally:
        env.close()
    return [d[:EPISODES] for d in done]


def _single_episodes(seed: int, world: int, budget: Any, others: Any = None) -> list[Episode]:
    """The same world on MergeEnv: seed + world, the same action generator."""
    env = MergeEnv(others=others, **budget.env_kwargs())
    rng = np.random.default_rng(1000 + seed + world)
    episodes: list[Episode] = []
    try:
        obs, info = env.reset(seed=seed + world)
        for _ in range(EPISODES):
            episode: Episode = [(obs.tobytes(), 0.0)]
            while True:
                obs, reward, terminated, truncated, info = env.step(_pick(rng, info["action_mask"]))
                episode.append((obs.tobytes(), float(reward)))
                if terminated or truncated:
                    break
            episodes.append(episode)
            obs, info = env.reset()
    finally:
        env.close()
    return episodes


def test_results_do_not_depend_on_k(small_budget: Any) -> None:
    eight = _vector_episodes(8, SEED, small_budget)
    assert _vector_episodes(1, SEED + 5, small_budget)[0] == eight[5], "world 5 of 8 differs from it alone"
    assert _single_episodes(SEED, 3, small_budget) == eight[3], "world 3 differs from MergeEnv"
    assert len({tuple(e[0]) for e in eight}) == 8  # the worlds' episodes differ from each other


def test_worlds_with_other_agents_are_merge_env_episodes(small_budget: Any) -> None:
    # Every other car an agent (others=): only the egos' observations are built, from the shared batch.
    three = _vector_episodes(3, SEED, small_budget, KeepOrFirst())
    assert _single_episodes(SEED, 2, small_budget, KeepOrFirst()) == three[2]


class MaskLog:
    """Wraps ``MergeVectorEnv.step``: every action checked against the env's own masks at that moment."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.steps = 0
        self.masked: list[tuple[int, int, int]] = []
        self.restricted = 0
        step = MergeVectorEnv.step

        def checked(env: MergeVectorEnv, actions: Any) -> Any:
            masks = env.action_masks()
            acts = np.asarray(actions).reshape(-1)
            for k in np.flatnonzero(~masks[np.arange(len(acts)), acts]).tolist():
                self.masked.append((self.steps, k, int(acts[k])))
            # rows of an acting ego whose safety mask forbids something (not an idle row's placeholder)
            self.restricted += int(((masks.sum(axis=1) > 1) & ~masks.all(axis=1)).sum())
            self.steps += 1
            return step(env, actions)

        monkeypatch.setattr(MergeVectorEnv, "step", checked)


def _example(name: str) -> Any:
    path = Path(__file__).resolve().parents[1] / "examples" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"example_{name}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cleanrl_style_ppo_never_takes_a_masked_action(monkeypatch: pytest.MonkeyPatch) -> None:
    log = MaskLog(monkeypatch)
    args = ["--total-steps", "384", "--num-envs", "4", "--num-steps", "32", "--episode-s", "8"]
    stats = _example("cleanrl_ppo_masked").main(args)
    assert stats["steps"] == 384 and stats["decisions"] > 100 and stats["masked_taken"] == 0
    assert stats["episodes"] >= 4  # waves ended and began again (the autoreset path)
    assert log.steps >= 96 and log.restricted > 10  # the masks forbade something, often
    assert log.masked == [], f"masked actions taken (step, world, action): {log.masked[:5]}"


def test_sb3_maskable_ppo_on_make_vec_never_takes_a_masked_action(monkeypatch: pytest.MonkeyPatch) -> None:
    log = MaskLog(monkeypatch)
    stats = _example("sb3_maskable_ppo").main(["--timesteps", "256", "--num-envs", "4", "--episode-s", "10"])
    assert stats["timesteps"] == 256
    assert log.steps >= 64 and log.restricted > 10
    assert log.masked == [], f"masked actions taken (step, world, action): {log.masked[:5]}"


def test_make_vec_picks_the_engine_and_checks_its_input(small_budget: Any) -> None:
    from gymnasium.error import ResetNeeded

    env = gymnasium.make_vec(
        "idas_sumo/Merge-v0", num_envs=2, **small_budget.env_kwargs()
    )  # the default mode
    try:
        assert isinstance(env, MergeVectorEnv) and env.metadata["autoreset_mode"].value == "NextStep"
        assert env.observation_space.shape == (2, OBS_DIM) and env.action_space.shape == (2,)
        with pytest.raises(ResetNeeded):
            env.step(np.zeros(2, dtype=np.int64))
        _, info = env.reset(seed=0)
        assert {"action_mask", "idle", "ego", "speed_mps", "road"} <= info.keys()
        with pytest.raises(ValueError, match=r"expected \(2,\)"):
            env.step(np.zeros(3, dtype=np.int64))
        acting = int(np.argmin(info["idle"]))
        bad = np.zeros(2, dtype=np.int64)
        bad[acting] = N_ACTIONS
        with pytest.raises(ValueError, match=rf"invalid action 7 for agent '{info['ego'][acting]}'"):
            env.step(bad)
    finally:
        env.close()


def test_make_vec_beside_an_open_simulation_says_so(small_budget: Any) -> None:
    single = MergeEnv(**small_budget.env_kwargs())
    try:
        single.reset(seed=0)  # holds this process's libsumo simulation
        with pytest.raises(SimulationError, match="another simulation is open"):
            gymnasium.make_vec("idas_sumo/Merge-v0", num_envs=2, **small_budget.env_kwargs())
    finally:
        single.close()


def test_rgb_array_frames_have_a_fixed_shape_and_show_the_ego(small_budget: Any) -> None:
    from idas_sumo.env.drawing import vehicle_colour

    single = gymnasium.make("idas_sumo/Merge-v0", render_mode="rgb_array", **small_budget.env_kwargs())
    try:
        _, info = single.reset(seed=1)
        first = single.render()
        for _ in range(5):
            _, _, _, _, info = single.step(int(np.flatnonzero(info["action_mask"])[0]))
        later = single.render()
        assert isinstance(first, np.ndarray) and isinstance(later, np.ndarray)
        assert first.shape == later.shape == (320, 640, 3) and first.dtype == np.uint8
        assert not np.array_equal(first, later)  # the cars moved
        ego = single.unwrapped.sim.scenario.vehicles  # type: ignore[attr-defined]
        spec = next(v for v in ego if v.id == info["ego"])
        colour = vehicle_colour(spec.road, spec.b_type, True)
        assert (later == colour).all(axis=2).sum() > 20  # the ego's square, in its road's colour
    finally:
        single.close()
    env = gymnasium.make_vec(
        "idas_sumo/Merge-v0", num_envs=2, render_mode="rgb_array", **small_budget.env_kwargs()
    )
    try:
        env.reset(seed=0)
        frames = env.render()
        assert frames is not None and [f.shape for f in frames] == [(320, 640, 3)] * 2
    finally:
        env.close()


def test_render_modes_are_checked_before_sumo_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    """ "human" is sumo-gui (a display needed: a clear error instead of sumo-gui aborting the process);
    an unknown mode is refused; both environments list the same modes."""
    from idas_sumo.env.gym_env import MergeEnv
    from idas_sumo.env.vector_env import MergeVectorEnv
    from idas_sumo.errors import InputError

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert (
        MergeEnv.metadata["render_modes"] == MergeVectorEnv.metadata["render_modes"] == ["rgb_array", "human"]
    )
    for make in (lambda mode: MergeEnv(render_mode=mode), lambda mode: MergeVectorEnv(2, render_mode=mode)):
        with pytest.raises(InputError, match="needs a display"):
            make("human")
        with pytest.raises(ValueError, match="render_mode 'ansi'"):
            make("ansi")
