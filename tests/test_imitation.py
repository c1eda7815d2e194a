"""Imitation pre-training (the shipped warm start): discounted returns by hand, fitting a learnable teacher, IDM demos."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import SmallBudget

from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.agents.returns import gae_advantages
from idas_sumo.agents.rollout import EpisodeData
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.training.imitation import collect_demonstrations, imitate


def test_gae_with_lambda_one_is_each_agents_discounted_return() -> None:
    # What imitate() fits V to. Two agents interleaved: A on rows 0, 2, 4 and B on rows 1, 3. γ = 0.5.
    # A: G4 = 4, G2 = 2 + 0.5·4 = 4, G0 = 1 + 0.5·4 = 3.  B: G3 = 8, G1 = -1 + 0.5·8 = 3.
    rewards = torch.tensor([1.0, -1.0, 2.0, 8.0, 4.0])
    next_row = torch.tensor([2, 3, 4, -1, -1])
    torch.testing.assert_close(
        gae_advantages(rewards, next_row, 0.5, 1.0), torch.tensor([3.0, 3.0, 4.0, 8.0, 4.0])
    )


def _synthetic_episode(n: int, rng: np.random.Generator) -> EpisodeData:
    """Rows whose teacher action is a function of the first observation feature; every action allowed
    except the hard brake (masked), so the fit also shows a masked action never gains probability."""
    obs = np.zeros((n, OBS_DIM), dtype=np.float32)
    obs[:, 0] = rng.uniform(-1.0, 1.0, size=n)
    action = np.where(obs[:, 0] > 0.0, 4, 0).astype(np.int64)  # +0.2 when positive, else -0.2
    mask = np.ones((n, N_ACTIONS), dtype=np.int8)
    mask[:, 5] = 0
    zeros_f = np.zeros(n, dtype=np.float32)
    zeros_i = np.zeros(n, dtype=np.int64)
    return EpisodeData(
        obs_bank=obs,
        obs_index=np.arange(n),
        next_obs_index=np.full(n, -1),
        mask=mask,
        action=action,
        reward=np.ones(n, dtype=np.float32),
        done=np.ones(n, dtype=np.float32),
        state=np.zeros((n, 1), dtype=np.float32),
        others_actions=np.zeros((n, 1), dtype=np.float32),
        slot=zeros_i,
        joint_reward=zeros_f,
        next_state=np.zeros((n, 1), dtype=np.float32),
        next_others_actions=np.zeros((n, 1), dtype=np.float32),
        next_slot=zeros_i,
        next_action=zeros_i,
        next_valid=zeros_f,
        next_row=np.full(n, -1),
        stats=None,  # type: ignore[arg-type]
    )


def test_imitate_fits_a_learnable_teacher_and_v_fits_the_returns() -> None:
    rng = np.random.default_rng(0)
    learner = Learner(dataclasses.replace(LearnerConfig(), lr_actor=3e-3, lr_value=3e-3), seed=0)
    episode = _synthetic_episode(1024, rng)
    stats = imitate(learner, [episode], epochs=30, generator=torch.Generator().manual_seed(0), batch_size=256)
    assert stats[-1].cross_entropy < 0.5 * stats[0].cross_entropy
    assert stats[-1].agreement > 0.9
    # Every row is a one-step episode with reward 1: V should predict about 1 everywhere.
    with torch.no_grad():
        values = learner.value(torch.from_numpy(episode.obs_bank))
    assert float((values - 1.0).abs().mean()) < 0.2
    with torch.no_grad():
        probs = learner.actor.distribution(
            torch.from_numpy(episode.obs_bank), torch.from_numpy(episode.mask)
        ).probs
    assert float(probs[:, 5].max()) == 0.0


@pytest.mark.sumo
def test_idm_demonstrations_teach_the_actor_idm_actions(net_path: Path, small_budget: SmallBudget) -> None:
    from idas_sumo.env.engine import EnvConfig, MergeEngine
    from idas_sumo.env.scenario import TrafficConfig

    engine = MergeEngine(net_path, copies=2, config=EnvConfig(max_episode_s=small_budget.max_episode_s))
    try:
        traffic = TrafficConfig(
            n_vehicles=0, min_vehicles_per_road=2, max_vehicles_per_road=small_budget.max_vehicles_per_road
        )
        demos = collect_demonstrations(
            engine, "idm", [traffic], small_budget.episodes, np.random.default_rng(0)
        )
    finally:
        engine.close()
    assert len(demos) == small_budget.episodes
    for e in demos:
        assert bool(e.mask[np.arange(len(e)), e.action].all())  # the teacher only took allowed actions
    learner = Learner(LearnerConfig(), seed=0)
    stats = imitate(learner, demos, epochs=3, generator=torch.Generator().manual_seed(0))
    assert stats[-1].cross_entropy < stats[0].cross_entropy
