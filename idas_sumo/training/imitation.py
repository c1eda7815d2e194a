"""Ours: pre-train the actor (and V) by imitating a rule-based baseline under the same masks.

Not part of the paper's method; the warm start of the shipped IDAS and IDAS-V. It exists because the
paper's curriculum from random weights, in our budget, converges to "drive at the limit and let the
masks brake", while the masked IDM baseline drives far more smoothly (docs/results.md, "What we tried").
A checkpoint written by ``scripts/pretrain_imitation.py`` can start any stage through ``init_from``.

Imitation: masked cross-entropy between the actor and the teacher's actions. V regresses on each
agent's discounted Monte-Carlo return, so a following RL stage starts with a critic that fits the
teacher's behaviour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from idas_sumo.agents.learner import Learner
from idas_sumo.agents.returns import gae_advantages
from idas_sumo.agents.rollout import EpisodeData, record_episodes
from idas_sumo.baselines.policies import RuleBasedPolicy
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.scenario import TrafficConfig, generate_scenario, start_room_m

__all__ = ["EpochStats", "collect_demonstrations", "imitate"]


def collect_demonstrations(
    engine: MergeEngine,
    teacher: str,
    traffic: list[TrafficConfig],
    episodes: int,
    rng: np.random.Generator,
) -> list[EpisodeData]:
    """``episodes`` episodes driven by ``teacher`` ('idm' or 'fsm_idm'), cycling through the ``traffic``
    configs, ``engine.copies`` side by side."""
    room = start_room_m(engine.site)
    scenarios = [
        generate_scenario(
            rng, traffic[k % len(traffic)], engine.speed_limits_mps, name=f"demo-{k}", start_room_m=room
        )
        for k in range(episodes)
    ]
    return record_episodes(engine, RuleBasedPolicy(teacher), scenarios)


@dataclass(frozen=True)
class EpochStats:
    epoch: int
    cross_entropy: float
    """Mean masked cross-entropy of the teacher's actions under the actor (nats)."""
    agreement: float
    """Fraction of rows where the actor's most probable allowed action is the teacher's."""
    value_loss: float


def imitate(
    learner: Learner,
    episodes: list[EpisodeData],
    epochs: int,
    generator: torch.Generator,
    batch_size: int = 512,
) -> list[EpochStats]:
    """Fit the actor to the recorded actions and V to the discounted returns; one row per epoch."""
    obs = torch.from_numpy(np.concatenate([e.obs for e in episodes]))
    mask = torch.from_numpy(np.concatenate([e.mask for e in episodes])).bool()
    action = torch.from_numpy(np.concatenate([e.action for e in episodes]))
    gamma = learner.config.gamma
    # GAE with λ = 1 on the rewards themselves is the discounted return along each agent's own rows.
    returns = torch.cat(
        [
            gae_advantages(torch.from_numpy(e.reward), torch.from_numpy(e.next_row), gamma, 1.0)
            for e in episodes
        ]
    )
    n = len(action)
    stats = []
    for epoch in range(epochs):
        order = torch.randperm(n, generator=generator)
        ce_sum = agree = v_sum = 0.0
        for start in range(0, n, batch_size):
            rows = order[start : start + batch_size]
            dist = learner.actor.distribution(obs[rows], mask[rows])
            ce = -dist.log_prob(action[rows]).mean()
            learner.opt_actor.zero_grad(set_to_none=True)
            ce.backward()
            learner.opt_actor.step()
            v_loss = 0.5 * (learner.value(obs[rows]) - returns[rows]).pow(2).mean()
            learner.opt_value.zero_grad(set_to_none=True)
            v_loss.backward()
            learner.opt_value.step()
            ce_sum += float(ce.detach()) * len(rows)
            v_sum += float(v_loss.detach()) * len(rows)
            agree += float((dist.probs.argmax(dim=1) == action[rows]).sum())
        stats.append(EpochStats(epoch, ce_sum / n, agree / n, v_sum / n))
    learner.value_target.load_state_dict(learner.value.state_dict())
    return stats
