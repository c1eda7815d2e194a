"""The paper's reward formulas and their one config (values from Section V-B); ``env/scoring.py`` applies them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
REWARD_PART_NAMES: tuple[str, ...] = ("finish", "collide", "impede", "flow")
"""The paper's four named parts, the first columns of ``StepResult.reward_parts`` in this order."""
IMPEDE_PENALTY = -5.0
FLOW_PENALTY_PER_HARD_BRAKE = -1.0
MERGE_ZONE_RADIUS_M = 50.0  # the merging zone: within 50 m of the merge point
FINISH_DISTANCE_PAST_MERGE_M = 50.0  # ours: a vehicle finishes at the merging zone's far edge
CollisionSign = Literal["paper", "lower_priority_pays"]


def finish_reward(b_type: npt.ArrayLike) -> FloatArray:
    """r_finish = (15·b_type + 50) / 4, once on finishing: 5 at b_type = -2, 20 at b_type = 2."""
    return np.asarray((15.0 * np.asarray(b_type, dtype=np.float64) + 50.0) / 4.0)


def collide_reward(b_prio: npt.ArrayLike, sign: CollisionSign = "paper") -> FloatArray:
    """r_collide = -5·b_prio - 5 as printed in the paper (the higher-priority car pays more).

    The paper's text says the lower-priority car should take more responsibility; ``lower_priority_pays``
    implements that reading: -5·(1 - b_prio) - 5.
    """
    prio = np.asarray(b_prio, dtype=np.float64)
    if sign == "lower_priority_pays":
        prio = 1.0 - prio
    return np.asarray(-5.0 * prio - 5.0)


@dataclass(frozen=True)
class RewardConfig:
    """The rewards' options: the collision sign, and extra named terms (``env/scoring.py``'s registry)."""

    RETIRED_KEYS: ClassVar[dict[str, Any]] = {
        "impede_blame": "car_ahead",
        "brake_count": "step",
        "collide_scale": 1.0,
        "timeout": "free",
        "finish_slope": "paper",
    }
    """Experiment switches measured and retired (experiments/README.md): files holding the default still load."""

    collision_sign: CollisionSign = "paper"
    """'paper' (-5·b_prio - 5, the default) or 'lower_priority_pays' (the paper's text, which says the lower-priority car should take more responsibility)."""
    extra_terms: tuple[str, ...] = ()
    """Reward terms registered by name (``scoring.register_reward_term``) scored after the paper's four: each
    adds a column to ``StepResult.reward_parts``. Empty for the paper."""

    def finish(self, b_type: npt.ArrayLike) -> FloatArray:
        """r_finish of cars of driver types ``b_type``."""
        return finish_reward(b_type)

    def collide(self, b_prio: float) -> float:
        """r_collide of a car from a road of priority ``b_prio``, under this config's sign."""
        return float(collide_reward(b_prio, self.collision_sign))

    @property
    def part_names(self) -> tuple[str, ...]:
        """The columns of ``StepResult.reward_parts``: the paper's four, then ``extra_terms``."""
        return REWARD_PART_NAMES + self.extra_terms
