"""Validation during training (ours, not the paper's): the greedy policy on held-out scenarios.

In our budget, stage 2's policy improves for a few hundred episodes and then declines
(docs/results.md), so a run with ``validate_every`` > 0 keeps the weights that scored best here as
``<stage>_best.pt``. Every learning car drives the greedy policy, as in evaluation; the scenarios come
from the stage's own traffic generator with their own seed, the same set at every validation (with
``[geometry]`` and ``validation_geometries``, spread over merges drawn from the training ranges).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from idas_sumo.agents.rollout import EpisodeStats
from idas_sumo.env.scenario import Road, TrafficConfig, generate_scenario
from idas_sumo.training.config import ValidationCriterion
from idas_sumo.training.workers import EpisodeTask

__all__ = [
    "VALIDATION_COLUMNS",
    "VALIDATION_NAME",
    "ValidationScore",
    "score_episodes",
    "split_evenly",
    "validation_key",
    "validation_tasks",
]

VALIDATION_NAME = "validation.csv"
"""A run directory's validation rows (one per validation, ``VALIDATION_COLUMNS``)."""

VALIDATION_COLUMNS: tuple[str, ...] = (
    "stage",
    "episode",
    "global_episode",
    "joint_return",
    "perfect_rate",
    "success_rate",
    "mean_end_time_s",
    "best",
    "wall_time_s",
)


@dataclass(frozen=True)
class ValidationScore:
    """The held-out scenarios' means; ``joint_return`` is what picks the best weights."""

    joint_return: float
    """Mean over scenarios of the undiscounted joint reward (every agent's parts plus flow)."""
    perfect_rate: float
    success_rate: float
    mean_end_time_s: float


def validation_tasks(
    traffic: TrafficConfig,
    speed_limits: dict[Road, float],
    scenarios: int,
    seed: int,
    start_room_m: dict[Road, float] | None = None,
    max_episode_s: float | None = None,
) -> list[EpisodeTask]:
    """The held-out scenarios as greedy episode tasks (the action seed is unused when greedy), on roads
    with ``start_room_m`` (``generate_scenario``), timed out at ``max_episode_s`` (None: the training
    episodes' timeout)."""
    rng = np.random.default_rng(seed)
    return [
        EpisodeTask(
            scenario=generate_scenario(
                rng, traffic, speed_limits, name=f"validation-{i}", start_room_m=start_room_m
            ),
            action_seed=0,
            deterministic=True,
            max_episode_s=max_episode_s,
        )
        for i in range(scenarios)
    ]


def split_evenly(total: int, parts: int) -> list[int]:
    """``total`` items over ``parts`` groups as evenly as possible, the first groups one larger."""
    return [total // parts + (1 if i < total % parts else 0) for i in range(parts)]


def validation_key(score: ValidationScore, criterion: ValidationCriterion) -> tuple[float, float]:
    """What ranks validations (larger is better). 'joint_return': the paper's objective, the return
    alone. 'success_then_return' (ours): the success rate first, the joint return among equals."""
    if criterion == "success_then_return":
        return (score.success_rate, score.joint_return)
    return (score.joint_return, 0.0)


def score_episodes(stats: Sequence[EpisodeStats]) -> ValidationScore:
    if not stats:
        raise ValueError("no validation episodes to score")
    return ValidationScore(
        joint_return=float(np.mean([sum(s.reward_parts.values()) for s in stats])),
        perfect_rate=float(np.mean([s.perfect for s in stats])),
        success_rate=float(np.mean([s.success for s in stats])),
        mean_end_time_s=float(np.mean([s.sim_time_s for s in stats])),
    )
