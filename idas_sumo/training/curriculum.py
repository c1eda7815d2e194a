"""Which stages a training run goes through, in the paper's terms (Section IV-D).

Stage 1, the Robot World: one learning agent among SUMO's rule-following cars, J1 only.
Stage 2, the Intelligent World: 8 learning agents, J1 + J2 with α from the learner config.
'curriculum' is stage 1 then stage 2 from stage 1's weights (IDAS); 'robot' alone gives IDAS-V;
'direct' is stage 2 from scratch for the direct budget (IDAS-direct).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from idas_sumo.agents.learner import LearnerConfig
from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.training.config import TrainConfig

__all__ = ["StagePlan", "plan_stages"]


@dataclass(frozen=True)
class StagePlan:
    """One stage of a run."""

    name: str
    """'robot', 'intelligent' or 'direct'; names the stage's checkpoint file and metrics rows."""
    episodes: int
    traffic: TrafficConfig
    learner: LearnerConfig
    init_from_previous: bool
    """Start from the previous stage's network weights (fresh optimisers)."""

    @property
    def central(self) -> bool:
        return self.learner.use_central_critic


def plan_stages(config: TrainConfig) -> list[StagePlan]:
    robot = StagePlan(
        name="robot",
        episodes=config.robot_episodes,
        traffic=config.robot_traffic,
        learner=dataclasses.replace(config.learner, use_central_critic=False),
        init_from_previous=False,
    )
    stage2 = dataclasses.replace(config.learner, use_central_critic=True)
    intelligent = StagePlan(
        name="intelligent",
        episodes=config.intelligent_episodes,
        traffic=config.intelligent_traffic,
        learner=stage2,
        init_from_previous=True,
    )
    if config.stage == "robot":
        return [robot]
    if config.stage == "intelligent":
        return [dataclasses.replace(intelligent, init_from_previous=False)]
    if config.stage == "direct":
        return [
            StagePlan(
                name="direct",
                episodes=config.direct_episodes,
                traffic=config.intelligent_traffic,
                learner=stage2,
                init_from_previous=False,
            )
        ]
    return [robot, intelligent]
