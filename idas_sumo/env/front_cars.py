"""Which car the safety mask keeps its distance to: the paper's own-lane front car, or a merge-aware one."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import SafetyMask, safety_bound
from idas_sumo.env.layout import VISIBILITY_M
from idas_sumo.env.rewards import MERGE_ZONE_RADIUS_M
from idas_sumo.env.snapshot import (
    MERGE,
    TrafficSnapshot,
    leader_speeds,
    leaders_and_speeds,
    other_road_leaders,
)
from idas_sumo.physics.idm import DEFAULT_IDM

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


def front_cars(
    snap: TrafficSnapshot, egos: IntArray, safety_mask: SafetyMask, controlled: BoolArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """(gap m, its speed m/s, ease_in; see MaskInputs) of the car each ego's safety mask keeps its distance to.

    'own_lane' (the paper's mask, the default): the nearest car ahead in the ego's own lane (its road,
    then the outgoing road); ``ease_in`` is all False. Before the merge point a car on the other road is no
    front car: the order at the merge point is the policy's to settle (FSM+IDM adds that car itself, as a
    virtual leader; baselines/fsm_idm.py).

    'merge_aware' (ours, a shield): a car on the other incoming road that is closer to the merge point
    (projected, within sight of both) will be in front of the ego after the merge, so whichever of the two
    asks for the lower IDM acceleration counts. Level cars: the main-road car counts as ahead.
    ``controlled``: per row of ``snap``, whether the engine drives the car.
    """
    _, gap, leader_speed = leaders_and_speeds(snap, egos)
    if safety_mask == "own_lane":
        return gap, leader_speed, np.zeros(len(egos), dtype=np.bool_)
    # SUMO's own cars on the merge road give way to every main-road car at the junction (stage 1's
    # "merge always yields"); counting them as front cars of main-road cars deadlocked both.
    sumo_yielding = (snap.road == MERGE) & ~controlled
    merge_leader, merge_gap = other_road_leaders(
        snap,
        egos,
        max_ahead_m=np.inf,
        zone_m=VISIBILITY_M,
        level_counts_for_main=True,
        never_leading=sumo_yielding,
    )
    speed = snap.speed_mps[egos]
    merge_speed = leader_speeds(snap, egos, merge_leader)
    own_lane_bound = safety_bound(speed, gap, leader_speed)
    other_road = (merge_leader >= 0) & (safety_bound(speed, merge_gap, merge_speed) < own_lane_bound)
    ease_in = (
        other_road
        & (snap.dist_to_merge_m[egos] > MERGE_ZONE_RADIUS_M)
        & (own_lane_bound >= -DEFAULT_IDM.comfortable_decel_mps2)
    )
    return np.where(other_road, merge_gap, gap), np.where(other_road, merge_speed, leader_speed), ease_in
