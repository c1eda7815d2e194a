"""Which car the safety mask keeps its distance to: the paper's own-lane front car, or a merge-aware one."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import N_ACTIONS, SafetyMask, _action_masks_kernel, safety_bound
from idas_sumo.env.jit import kernel
from idas_sumo.env.layout import VISIBILITY_M
from idas_sumo.env.observation import _SCALES, _observations_kernel, copy_operands, speed_spread
from idas_sumo.env.rewards import MERGE_ZONE_RADIUS_M
from idas_sumo.env.snapshot import (
    MERGE,
    TrafficSnapshot,
    _leaders_kernel,
    leader_speeds,
    leaders_and_speeds,
    other_road_leaders,
    walk_start,
)
from idas_sumo.physics.idm import DEFAULT_IDM, IDMParams

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


def own_lane_action_masks(
    snap: TrafficSnapshot, egos: IntArray, prev_accel: FloatArray, params: IDMParams = DEFAULT_IDM
) -> npt.NDArray[np.int8]:
    """``action_masks`` with the 'own_lane' front cars (``front_cars``), in one compiled call: the engine's
    masks every step, without the numpy between the leader walk and the masks (the same kernels)."""
    egos, by_dist, lo, hi = walk_start(snap, egos)
    return np.asarray(
        _own_lane_masks_kernel(
            snap.road,
            snap.dist_to_merge_m,
            snap.length_m,
            snap.speed_mps,
            snap.speed_limit_mps,
            by_dist.order,
            by_dist.sorted_dist,
            lo,
            hi,
            egos,
            np.ascontiguousarray(prev_accel, dtype=np.float64),
            params.max_accel_mps2,
            params.comfortable_decel_mps2,
            params.min_gap_m,
            params.time_headway_s,
            params.delta,
        )
    )


@kernel
def _own_lane_masks_kernel(
    road,
    dist,
    length,
    speed,
    limit,
    order,
    sorted_dist,
    lo,
    hi,
    egos,
    prev,
    max_accel,
    comfortable_decel,
    min_gap,
    time_headway,
    delta,
):
    """``leaders_and_speeds`` then ``action_masks`` of its gaps (no ease-in), as the engine called them."""
    _, gap, leader_speed = _leaders_kernel(road, dist, length, speed, order, sorted_dist, lo, hi, egos)
    n = egos.shape[0]
    ego_speed = np.empty(n)
    ego_limit = np.empty(n)
    for i in range(n):
        ego_speed[i] = speed[egos[i]]
        ego_limit[i] = limit[egos[i]]
    return _action_masks_kernel(
        prev,
        ego_speed,
        ego_limit,
        gap,
        leader_speed,
        np.zeros(n, dtype=np.bool_),
        max_accel,
        comfortable_decel,
        min_gap,
        time_headway,
        delta,
    )


def observe_own_lane(
    snap: TrafficSnapshot,
    row_copy: IntArray,
    car_row: IntArray,
    car_accel: FloatArray,
    agent_car: IntArray,
    agent_copy: IntArray,
    prio_by_road: FloatArray,
    params: IDMParams = DEFAULT_IDM,
) -> tuple[IntArray, FloatArray, FloatArray, npt.NDArray[np.int8]]:
    """The engine's ``observe`` under the 'own_lane' mask in one compiled call: each agent's row (its car's
    ``car_row``), the acceleration it drives with (``car_accel``), its road's priority in its copy
    (``prio_by_road[copy, road]``) and ``own_lane_action_masks`` of those rows. ``row_copy``: each snapshot
    row's copy (zeros in a one-copy snapshot)."""
    return _observe_own_lane_kernel(
        *_own_lane_operands(snap, row_copy, car_row, car_accel, agent_car, agent_copy, prio_by_road, params)
    )


def _own_lane_operands(
    snap: TrafficSnapshot,
    row_copy: IntArray,
    car_row: IntArray,
    car_accel: FloatArray,
    agent_car: IntArray,
    agent_copy: IntArray,
    prio_by_road: FloatArray,
    params: IDMParams,
) -> tuple[Any, ...]:
    """``_observe_own_lane_kernel``'s arguments (the first of ``_observe_own_lane_obs_kernel``'s)."""
    by_dist = snap.by_distance
    return (
        car_row,
        car_accel,
        agent_car,
        agent_copy,
        prio_by_road,
        row_copy,
        by_dist.starts,
        snap.road,
        snap.dist_to_merge_m,
        snap.length_m,
        snap.speed_mps,
        snap.speed_limit_mps,
        by_dist.order,
        by_dist.sorted_dist,
        params.max_accel_mps2,
        params.comfortable_decel_mps2,
        params.min_gap_m,
        params.time_headway_s,
        params.delta,
    )


def observe_own_lane_obs(
    snap: TrafficSnapshot,
    row_copy: IntArray,
    car_row: IntArray,
    car_accel: FloatArray,
    agent_car: IntArray,
    agent_copy: IntArray,
    prio_by_road: FloatArray,
    b_type: FloatArray,
    obs: npt.NDArray[np.float32],
    params: IDMParams = DEFAULT_IDM,
) -> tuple[IntArray, FloatArray, FloatArray, npt.NDArray[np.int8], bool, float]:
    """``observe_own_lane`` and the agents' observations, written into ``obs`` ((n, OBS_DIM) float32 zeros)
    as ``build_observations_checked`` writes them, in one compiled call (a single world's every step);
    then whether every scalar came out finite, and the speeds' spread (``speed_spread``)."""
    # The kernel fills arrays handed in rather than returning four (each returned array costs about 0.5 µs
    # of boxing): the rows, the accelerations and priorities as two rows of one array, the masks.
    n = len(agent_car)
    egos, floats, masks = np.empty(n, dtype=np.int64), np.empty((2, n)), np.empty((n, N_ACTIONS), np.int8)
    obs_kernel: Any = _observe_own_lane_obs_kernel  # (mypy cannot count the arguments a star hands on)
    finite, spread = obs_kernel(
        *_own_lane_operands(snap, row_copy, car_row, car_accel, agent_car, agent_copy, prio_by_road, params),
        b_type,
        obs,
        _SCALES,
        *copy_operands(snap),
        egos,
        floats,
        masks,
    )
    return egos, floats[0], floats[1], masks, finite, spread


@kernel
def _observe_own_lane_obs_kernel(
    car_row,
    car_accel,
    agent_car,
    agent_copy,
    prio_by_road,
    row_copy,
    starts,
    road,
    dist,
    length,
    speed,
    limit,
    order,
    sorted_dist,
    max_accel,
    comfortable_decel,
    min_gap,
    time_headway,
    delta,
    b_type,
    obs,
    scales,
    obs_row_copy,
    longest,
    rows_by_copy,
    out_egos,
    out_floats,
    out_masks,
):
    """``_observe_own_lane_kernel`` then ``_observations_kernel`` of its rows (``observe_own_lane_obs``); the
    rows, accelerations, priorities and masks into the ``out_`` arrays."""
    egos, prev, b_prio, masks = _observe_own_lane_kernel(
        car_row,
        car_accel,
        agent_car,
        agent_copy,
        prio_by_road,
        row_copy,
        starts,
        road,
        dist,
        length,
        speed,
        limit,
        order,
        sorted_dist,
        max_accel,
        comfortable_decel,
        min_gap,
        time_headway,
        delta,
    )
    finite = _observations_kernel(
        obs,
        speed,
        dist,
        egos,
        prev,
        b_prio,
        b_type,
        scales,
        road,
        length,
        order,
        sorted_dist,
        starts,
        obs_row_copy,
        longest,
        rows_by_copy,
    )
    for i in range(egos.shape[0]):
        out_egos[i] = egos[i]
        out_floats[0, i] = prev[i]
        out_floats[1, i] = b_prio[i]
        for j in range(masks.shape[1]):
            out_masks[i, j] = masks[i, j]
    return finite, speed_spread(speed)


@kernel
def _observe_own_lane_kernel(
    car_row,
    car_accel,
    agent_car,
    agent_copy,
    prio_by_road,
    row_copy,
    starts,
    road,
    dist,
    length,
    speed,
    limit,
    order,
    sorted_dist,
    max_accel,
    comfortable_decel,
    min_gap,
    time_headway,
    delta,
):
    n = agent_car.shape[0]
    egos = np.empty(n, dtype=np.int64)
    prev = np.empty(n)
    b_prio = np.empty(n)
    lo = np.empty(n, dtype=np.int64)
    hi = np.empty(n, dtype=np.int64)
    for i in range(n):
        e = car_row[agent_car[i]]
        egos[i] = e
        prev[i] = car_accel[agent_car[i]]
        b_prio[i] = prio_by_road[agent_copy[i], road[e]]
        c = row_copy[e]  # (``DistanceOrder.spans``: the ego's copy's span of the distance order)
        lo[i] = starts[c]
        hi[i] = starts[c + 1]
    masks = _own_lane_masks_kernel(
        road,
        dist,
        length,
        speed,
        limit,
        order,
        sorted_dist,
        lo,
        hi,
        egos,
        prev,
        max_accel,
        comfortable_decel,
        min_gap,
        time_headway,
        delta,
    )
    return egos, prev, b_prio, masks
