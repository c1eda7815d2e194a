"""The paper's four named reward parts, as pure functions (values from Section V-B)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from idas_sumo.errors import InputError

FloatArray = npt.NDArray[np.float64]
REWARD_PART_NAMES: tuple[str, ...] = ("finish", "collide", "impede", "flow")
IMPEDE_PENALTY = -5.0
FLOW_PENALTY_PER_HARD_BRAKE = -1.0
MERGE_ZONE_RADIUS_M = 50.0  # the merging zone: within 50 m of the merge point
FINISH_DISTANCE_PAST_MERGE_M = 50.0  # ours: a vehicle finishes at the merging zone's far edge
CollisionSign = Literal["paper", "lower_priority_pays"]
ImpedeBlame = Literal["car_ahead", "braker_if_unforced"]
BrakeCount = Literal["step", "manoeuvre"]
TimeoutPrice = Literal["free", "forfeit_finish"]
FinishSlope = Literal["paper", "cooperative_waits"]


def finish_reward(b_type: npt.ArrayLike, slope: FinishSlope = "paper") -> FloatArray:
    """r_finish = (15·b_type + 50) / 4, once on finishing: 5 at b_type = -2, 20 at b_type = 2.

    ``cooperative_waits`` (ours, a labelled hypothesis): (-15·b_type + 50) / 4, 20 at -2 and 5 at +2, so that a
    cooperative driver (b_type = 2, L277) gains less from hurrying, as the paper's text (L196) says a small
    final reward should make a driver *less* cooperative.
    """
    sign = -1.0 if slope == "cooperative_waits" else 1.0
    return np.asarray((sign * 15.0 * np.asarray(b_type, dtype=np.float64) + 50.0) / 4.0)


def collide_reward(b_prio: npt.ArrayLike, sign: CollisionSign = "paper", scale: float = 1.0) -> FloatArray:
    """r_collide = -5·b_prio - 5 as printed in the paper (the higher-priority car pays more), times ``scale``
    (1 in the paper; ``RewardConfig.collide_scale``).

    The paper's text says the lower-priority car should take more responsibility; ``lower_priority_pays``
    implements that reading: -5·(1 - b_prio) - 5.
    """
    prio = np.asarray(b_prio, dtype=np.float64)
    if sign == "lower_priority_pays":
        prio = 1.0 - prio
    return np.asarray(scale * (-5.0 * prio - 5.0))


def hard_brakes_in_merge_zone(hard_brake_dist_to_merge_m: npt.ArrayLike) -> int:
    """How many of these hard brakes (distances to the merge point, m) lie within the merging zone."""
    d = np.asarray(hard_brake_dist_to_merge_m, dtype=np.float64)
    return int(np.count_nonzero(np.abs(d) <= MERGE_ZONE_RADIUS_M))


def flow_penalty(hard_brake_dist_to_merge_m: npt.ArrayLike) -> float:
    """r_flow: -1 per hard brake within the merging zone; shared, enters only the joint reward."""
    return float(FLOW_PENALTY_PER_HARD_BRAKE * hard_brakes_in_merge_zone(hard_brake_dist_to_merge_m))


@dataclass(frozen=True)
class RewardConfig:
    """Which variant of the paper's rewards to use."""

    collision_sign: CollisionSign = "paper"
    """'paper' (-5·b_prio - 5, the default) or 'lower_priority_pays'."""
    impede_blame: ImpedeBlame = "car_ahead"
    """Who pays r_impede for a hard brake. 'car_ahead' (the default, our reading of "penalizes agents that
    cause other agents to hard brake", L286): the nearest car ahead, on either road, within sight.
    'braker_if_unforced' (ours, a labelled variant): an agent that hard-brakes while its mask still allowed
    a Δa action chose the brake, so it pays for it itself, whether or not a car is in sight; a brake the
    mask forced, and a SUMO-driven car's brake, are still charged to the car ahead. Under 'car_ahead' such
    a chosen brake is free for the braker in J1 (only the joint reward sees it), and the car ahead, which
    did nothing, is charged."""
    brake_count: BrakeCount = "step"
    """What r_impede and r_flow count as one hard brake. 'step' (the default, our reading of "every sudden
    brake"): every 0.2 s step a car brakes hard. 'manoeuvre' (ours, a labelled variant): only the step a hard
    brake begins (the car did not brake hard the step before), so a long brake costs what a short one does.
    The evaluation's hard-brake counts and perfect success count steps either way."""
    timeout: TimeoutPrice = "free"
    """What a car still driving when the time limit cuts the episode off gets. 'free' (the default; the
    paper names no time limit): nothing, and training bootstraps its value from the state it was cut off
    in. 'forfeit_finish' (ours, a labelled variant): it pays the r_finish it did not earn,
    -(15·b_type + 50)/4, booked in the ``finish`` part, and its episode ends there (nothing is
    bootstrapped). Under 'free' a car that stops short of the merge pays nothing at all, which is where
    every full-budget stage-2 run ended (docs/results.md)."""
    collide_scale: float = 1.0
    """r_collide times this (1: the paper's price). Ours, a labelled variant: with the paper's price a
    collision costs the joint reward about what four hard-brake steps do, and every stage-2 run traded brakes
    for collisions (docs/results.md, "Declared: a collision priced above the brakes it saves"). Scales both
    sign readings; the evaluation's collision counts do not depend on it."""

    finish_slope: FinishSlope = "paper"
    """How r_finish depends on b_type. 'paper' (the default): the printed (15·b_type + 50)/4, under which a
    larger b_type makes finishing, and so hurrying, worth more. 'cooperative_waits' (ours, a labelled
    hypothesis, never the headline): (-15·b_type + 50)/4, the slope the paper's explanation (L196) and Fig. 6
    need (``finish_reward``). Evaluation's normalized reward keeps the printed formula."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.collide_scale) and self.collide_scale > 0.0):
            raise InputError(f"collide_scale must be a positive number, got {self.collide_scale}")

    def finish(self, b_type: npt.ArrayLike) -> FloatArray:
        """r_finish of cars of driver types ``b_type`` under this config's slope."""
        return finish_reward(b_type, self.finish_slope)

    def collide(self, b_prio: float) -> float:
        """r_collide of a car from a road of priority ``b_prio``, under this config's sign and scale."""
        return float(collide_reward(b_prio, self.collision_sign, self.collide_scale))

    @property
    def timeout_ends_episode(self) -> bool:
        """Whether a timeout is an end with nothing to bootstrap (training), as a finish or collision is."""
        return self.timeout == "forfeit_finish"
