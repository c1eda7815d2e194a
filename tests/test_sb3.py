"""sb3-contrib's MaskablePPO trains on the Gymnasium env as registered: no ActionMasker, no changes."""

from __future__ import annotations

import typing
from typing import Any

import gymnasium
import numpy as np
import pytest
import torch

import idas_sumo  # noqa: F401  (registers idas_sumo/Merge-v0)
from idas_sumo.env import MergeEnv
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.engine import EnvConfig
from idas_sumo.sim.backend import slot_taken

pytestmark = pytest.mark.sumo

TRAIN_STEPS = 256


class ActionLog(gymnasium.Wrapper[Any, Any, Any, Any]):
    """Records, per step, the action taken and the env's mask at that moment (from ``action_masks()``)."""

    def __init__(self, env: gymnasium.Env[Any, Any]) -> None:
        super().__init__(env)
        self.steps: list[tuple[int, np.ndarray]] = []
        self.info_mask: np.ndarray | None = None
        self.mask_mismatches = 0

    def _check(self, info: dict[str, Any]) -> None:
        self.info_mask = info["action_mask"]
        if not np.array_equal(self.env.get_wrapper_attr("action_masks")(), self.info_mask.astype(bool)):
            self.mask_mismatches += 1

    def reset(self, **kwargs: Any) -> Any:
        obs, info = self.env.reset(**kwargs)
        self._check(info)
        return obs, info

    def step(self, action: Any) -> Any:
        mask = self.env.get_wrapper_attr("action_masks")()
        self.steps.append((int(action), mask))
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._check(info)
        return obs, reward, terminated, truncated, info


def _probs(dist: Any) -> torch.Tensor:
    """Action probabilities of the one observation a MaskableCategoricalDistribution was built for."""
    return typing.cast(torch.distributions.Categorical, dist.distribution).probs[0]


def test_maskable_ppo_trains_on_the_registered_env(small_budget: Any) -> None:
    from sb3_contrib import MaskablePPO
    from sb3_contrib.common.maskable.utils import get_action_masks, is_masking_supported
    from stable_baselines3.common.logger import Logger

    made = gymnasium.make("idas_sumo/Merge-v0", config=EnvConfig(max_episode_s=small_budget.max_episode_s))
    assert isinstance(made.unwrapped, MergeEnv)
    assert is_masking_supported(made)
    env = ActionLog(made)
    try:
        model = MaskablePPO(
            "MlpPolicy",
            env,
            n_steps=64,
            batch_size=32,
            n_epochs=1,
            policy_kwargs={"net_arch": [16]},
            seed=0,
            device="cpu",
        )
        # SB3 otherwise makes an empty SB3-<date> folder in the temp dir for every run.
        model.set_logger(Logger(folder=None, output_formats=[]))
        model.learn(total_timesteps=TRAIN_STEPS)
        assert model.num_timesteps == TRAIN_STEPS
        assert len(env.steps) == TRAIN_STEPS
        masks = np.array([m for _, m in env.steps])
        assert masks.shape == (TRAIN_STEPS, N_ACTIONS) and masks.dtype == bool
        # The run met the safety mask (otherwise "every action was allowed" would prove nothing).
        assert (~masks).any(axis=1).sum() > 10
        refused = [(t, a) for t, (a, m) in enumerate(env.steps) if not m[a]]
        assert refused == [], f"MaskablePPO took masked actions (step, action): {refused[:5]}"
        assert env.mask_mismatches == 0  # action_masks() always equals info["action_mask"]

        # The trained policy gives a masked action probability 0 (and > 0 without the mask).
        obs, info = env.reset(seed=3)
        for _ in range(500):  # to a state where the mask forbids something
            mask = get_action_masks(env)
            np.testing.assert_array_equal(mask, info["action_mask"].astype(bool))
            if not mask.all():
                break
            action, _ = model.predict(obs, action_masks=mask)
            obs, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                obs, info = env.reset()
        assert not mask.all()
        obs_t, _ = model.policy.obs_to_tensor(obs)
        with torch.no_grad():
            masked = _probs(model.policy.get_distribution(obs_t, action_masks=mask))
            free = _probs(model.policy.get_distribution(obs_t))
        assert torch.all(masked[torch.from_numpy(~mask)] == 0.0)
        assert torch.all(free > 0.0)
        assert float(masked.sum()) == pytest.approx(1.0, abs=1e-6)
    finally:
        env.close()
    assert not slot_taken()
