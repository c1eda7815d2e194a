"""The paper's seven actions and its three masks (kinematic, rule, safety), as pure array functions.

An agent's acceleration persists between steps; the five Δa actions change it by a jerk-bounded
step, hard brake sets it to -4 m/s², and release brake sets it to 0 m/s² (allowed only directly
after a hard brake). A mask entry of 1 means the action may be taken. The final mask is the
intersection of the three allowed sets (the paper's union of the masked-out sets). Hard brake is
never masked, so every agent always has at least one action. ``closest_allowed_action`` turns a wanted
acceleration (a masked request, a rule-based baseline's target) into the allowed action nearest to it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
import numpy.typing as npt

from idas_sumo.env.jit import kernel, per_row
from idas_sumo.physics.idm import DEFAULT_IDM, IDMParams, idm_acceleration_one
from idas_sumo.sim.backend import STEP_LENGTH_S  # one decision per SUMO step (5 Hz)

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

DELTA_ACCEL_MPS2: tuple[float, ...] = (-0.2, -0.1, 0.0, 0.1, 0.2)
HARD_BRAKE_MPS2 = -4.0
RELEASE_BRAKE_MPS2 = 0.0
N_DELTA_ACTIONS = len(DELTA_ACCEL_MPS2)
HARD_BRAKE = N_DELTA_ACTIONS  # action index 5
RELEASE_BRAKE = N_DELTA_ACTIONS + 1  # action index 6
N_ACTIONS = N_DELTA_ACTIONS + 2

SafetyMask = Literal["own_lane", "merge_aware"]
"""Which car the safety mask keeps a safe distance to (``MergeEngine.front_cars``): the own-lane front
car (the paper, L219) or also the other road's car nearer the merge point (ours, a shield)."""
SAFETY_MASKS: tuple[str, ...] = get_args(SafetyMask)
DEFAULT_SAFETY_MASK: SafetyMask = "own_lane"

MIN_ACCEL_MPS2 = -2.0  # kinematic range outside hard braking
MAX_ACCEL_MPS2 = 2.0
MERGE_EXEMPTION_M = 100.0  # the merge car may exceed its road's limit this close to the merge point
_TOLERANCE = 1e-6
_JERK_STEP_MPS2 = DELTA_ACCEL_MPS2[-1]  # the largest |Δa| per step
_DELTAS = np.asarray(DELTA_ACCEL_MPS2)
# Candidate accelerations lie on a 1e-6-rounded grid, so distances closer than this are the same.
_TIE_TOLERANCE_MPS2 = 1e-9


def next_acceleration(prev_accel: npt.ArrayLike, actions: npt.ArrayLike) -> FloatArray:
    """Acceleration (m/s²) each agent drives with after taking ``actions`` (int array)."""
    prev, act = np.asarray(prev_accel, dtype=np.float64), np.asarray(actions, dtype=np.int64)
    if prev.shape != act.shape:  # (the engine's call, once per step, has equal shapes: no broadcast)
        prev, act = np.broadcast_arrays(prev, act)
    if act.ndim == 1 and prev.flags.c_contiguous and act.flags.c_contiguous:  # (the engine's call again)
        accel, bad = _next_accelerations(prev, act)
    else:
        accel, bad = _next_accelerations(
            np.ascontiguousarray(prev.ravel()), np.ascontiguousarray(act.ravel())
        )
    if bad >= 0:
        raise ValueError(f"actions must lie in [0, {N_ACTIONS}), got {act.tolist()}")
    return np.asarray(accel.reshape(act.shape), dtype=np.float64)


def candidate_accelerations(prev_accel: npt.ArrayLike) -> FloatArray:
    """(n_agents, 7) acceleration each action would produce."""
    return np.asarray(
        _candidates(np.ascontiguousarray(np.atleast_1d(np.asarray(prev_accel, dtype=np.float64))))
    )


@kernel
def _candidate(prev: float, action: int) -> float:
    """The acceleration (m/s²) ``action`` produces after ``prev``."""
    if action == HARD_BRAKE:
        return HARD_BRAKE_MPS2
    if action == RELEASE_BRAKE:
        return RELEASE_BRAKE_MPS2
    # np.round(·, 6) as numpy computes it (·10⁶, rint, /10⁶): keeps the 0.1 grid exact.
    return float(np.rint((prev + _DELTAS[action]) * 1e6) / 1e6)


@kernel
def _candidates(prev):
    cand = np.empty((prev.shape[0], N_ACTIONS))
    for i in range(prev.shape[0]):
        for j in range(N_ACTIONS):
            cand[i, j] = _candidate(prev[i], j)
    return cand


@kernel
def _next_accelerations(prev, actions):
    """(``_candidate`` per agent, the first agent whose action is out of range or -1): checked here, in
    the one pass, rather than by a few numpy calls before it."""
    accel = np.empty(prev.shape[0])
    bad = -1
    for i in range(prev.shape[0]):
        if 0 <= actions[i] < N_ACTIONS:
            accel[i] = _candidate(prev[i], actions[i])
        else:
            accel[i] = np.nan
            if bad < 0:
                bad = i
    return accel, bad


def closest_allowed_action(
    target_accel: npt.ArrayLike, prev_accel: npt.ArrayLike, mask: npt.ArrayLike
) -> IntArray:
    """(n,) int64: the allowed action whose acceleration is closest to ``target_accel`` (m/s²).

    ``mask`` is (n, 7), nonzero = allowed. Ties go to the lower acceleration (the safer choice), then
    to the lower action index so the result is deterministic. A row with no allowed action is an
    error: hard brake is never masked, so such a mask is a bug upstream.
    """
    target = np.atleast_1d(np.asarray(target_accel, dtype=np.float64))
    prev = np.atleast_1d(np.asarray(prev_accel, dtype=np.float64))
    allowed = np.asarray(mask) != 0
    if allowed.ndim == 1 and target.shape[0] == 1:
        allowed = allowed[None, :]
    n = target.shape[0]
    if target.ndim != 1 or prev.shape != (n,) or allowed.shape != (n, N_ACTIONS):
        raise ValueError(
            f"expected target_accel (n,), prev_accel (n,), mask (n, {N_ACTIONS}); got "
            f"{target.shape}, {prev.shape}, {allowed.shape}"
        )
    if not np.all(np.isfinite(target)):
        raise ValueError(f"target_accel must be finite, got {target.tolist()}")
    if n == 0:
        return np.empty(0, dtype=np.int64)
    if not np.all(allowed.any(axis=1)):
        bad = np.flatnonzero(~allowed.any(axis=1)).tolist()
        raise ValueError(f"mask rows {bad} allow no action (hard brake is never masked)")
    cand = candidate_accelerations(prev)
    distance = np.where(allowed, np.abs(cand - target[:, None]), np.inf)
    best = distance.min(axis=1, keepdims=True)
    tied = allowed & (distance <= best + _TIE_TOLERANCE_MPS2)
    # Among the tied actions take the lowest acceleration; argmin returns the first (lowest index)
    # of equal values, which settles actions that produce the same acceleration.
    return np.argmin(np.where(tied, cand, np.inf), axis=1).astype(np.int64)


def kinematic_mask(prev_accel: npt.ArrayLike, cand: FloatArray | None = None) -> BoolArray:
    """Δa actions keep a in [-2, 2] m/s²; release brake only directly after a hard brake."""
    prev = _as_rows(prev_accel)
    cand = candidate_accelerations(prev) if cand is None else cand
    return _masks(_KINEMATIC, prev, cand)


def effective_speed_limit(
    road_limit_mps: npt.ArrayLike,
    dist_to_merge_m: npt.ArrayLike,
    exemption_limit_mps: npt.ArrayLike,
) -> FloatArray:
    """The limit the rule mask enforces: a car on the slower incoming road may go up to
    ``exemption_limit_mps`` (the outgoing road's limit) within 100 m before the merge point."""
    road = np.asarray(road_limit_mps, dtype=np.float64)
    dist = np.asarray(dist_to_merge_m, dtype=np.float64)
    exempt = (dist >= 0.0) & (dist <= MERGE_EXEMPTION_M)
    return np.asarray(np.where(exempt, np.maximum(road, exemption_limit_mps), road), dtype=np.float64)


def rule_mask(
    prev_accel: npt.ArrayLike,
    speed_mps: npt.ArrayLike,
    speed_limit_mps: npt.ArrayLike,
    cand: FloatArray | None = None,
) -> BoolArray:
    """Actions after which the agent can stay within the (effective) speed limit without a hard brake.

    Ours: a positive acceleration can only be taken back by 0.2 m/s² per step (the jerk limit), and the
    speed keeps rising meanwhile, so the check is on the peak speed reached while easing off at the jerk
    limit, not just on the next speed. Checking only v + a·dt let an agent reach the limit at +2 m/s²
    with every Δa action then breaking the rule: the hard brake was its only action, and learned policies
    drove saw-tooth profiles of hard brakes at the limit (5-7 per two-car representative scenario).
    """
    prev = _as_rows(prev_accel)
    cand = candidate_accelerations(prev) if cand is None else cand
    return _masks(_RULE, prev, cand, speed=_as_rows(speed_mps), limit=_as_rows(speed_limit_mps))


def _peak_speed_gain(a: float) -> float:
    """Speed gained (m/s) from driving one step at ``a`` and then easing off to 0 at the jerk limit.

    a > 0: steps at a, a - 0.2, ..., down to the last positive value: dt·((m+1)·a - 0.2·m(m+1)/2) with
    m = floor(a / 0.2). a <= 0: the one step's a·dt.
    """
    if a <= 0.0:
        return a * STEP_LENGTH_S
    step = _JERK_STEP_MPS2
    m = np.floor(a / step + _TOLERANCE)
    return ((m + 1.0) * a - step * m * (m + 1.0) / 2.0) * STEP_LENGTH_S


_peak_speed_gain_one = kernel(_peak_speed_gain)


@kernel
def _peak_speed_gains(accel):
    gain = np.empty(accel.shape[0])
    for i in range(accel.shape[0]):
        gain[i] = _peak_speed_gain_one(accel[i])
    return gain


def peak_speed_gain(accel_mps2: npt.ArrayLike) -> FloatArray:
    """``_peak_speed_gain`` of each acceleration (m/s²), in m/s."""
    accel = np.asarray(accel_mps2, dtype=np.float64)
    return np.asarray(
        _peak_speed_gains(np.ascontiguousarray(accel.ravel())).reshape(accel.shape), dtype=np.float64
    )


def safety_bound(
    speed_mps: npt.ArrayLike,
    gap_m: npt.ArrayLike,
    leader_speed_mps: npt.ArrayLike,
    params: IDMParams = DEFAULT_IDM,
) -> FloatArray:
    """The largest acceleration (m/s²) the safety mask allows: IDM's interaction part.

    IDM's free-road term is left out on purpose: with v0 = the speed limit it is ~1 at the limit, which
    would forbid every non-braking action whenever any car is in sight. The rule mask enforces the limit.
    """
    v = np.atleast_1d(np.asarray(speed_mps, dtype=np.float64))
    gap = np.atleast_1d(np.asarray(gap_m, dtype=np.float64))
    leader = np.asarray(leader_speed_mps, dtype=np.float64)
    if not (v.shape == gap.shape == leader.shape and v.ndim == 1):  # (the engine's calls: equal shapes)
        v, gap, leader = np.broadcast_arrays(v, gap, leader)
    bound = _safety_bounds(
        np.ascontiguousarray(v.ravel()),
        np.ascontiguousarray(gap.ravel()),
        np.ascontiguousarray(leader.ravel()),
        params.max_accel_mps2,
        params.comfortable_decel_mps2,
        params.min_gap_m,
        params.time_headway_s,
        params.delta,
    )
    return np.asarray(bound.reshape(v.shape), dtype=np.float64)


_idm_acceleration_one = kernel(idm_acceleration_one)


@kernel
def _safety_bounds(speed, gap, leader_speed, max_accel, comfortable_decel, min_gap, time_headway, delta):
    """``safety_bound`` per agent: IDM with no desired speed (inf), inf where there is no leader."""
    bound = np.empty(speed.shape[0])
    for i in range(speed.shape[0]):
        if np.isinf(gap[i]):
            bound[i] = np.inf
        else:
            bound[i] = _idm_acceleration_one(
                speed[i],
                np.inf,
                gap[i],
                speed[i] - leader_speed[i],
                max_accel,
                comfortable_decel,
                min_gap,
                time_headway,
                delta,
            )
    return bound


def safety_mask(
    prev_accel: npt.ArrayLike,
    speed_mps: npt.ArrayLike,
    gap_m: npt.ArrayLike,
    leader_speed_mps: npt.ArrayLike,
    params: IDMParams = DEFAULT_IDM,
    cand: FloatArray | None = None,
    ease_in: BoolArray | None = None,
) -> BoolArray:
    """Actions whose acceleration does not exceed IDM's to the car in front (gap = inf: no leader).

    Ours: while IDM asks for no more than the comfortable deceleration (bound >= -b), the strongest
    Δa step stays allowed even if it does not reach the bound yet, so the agent closes in on the bound at
    the jerk limit (the strongest step within the kinematic range: at a = -2 that is keeping -2). Without
    this, any bound between a - 0.2 and -2 m/s² left only the hard brake, and dense traffic turned into
    hard-brake waves (every agent timed out in the intelligent world). When IDM asks for more than -b, only
    actions under the bound (and the hard brake) remain, except where ``ease_in`` is set: there the
    strongest Δa step stays allowed whatever the bound (see ``MaskInputs.ease_in``).
    """
    prev = _as_rows(prev_accel)
    cand = candidate_accelerations(prev) if cand is None else cand
    bound = safety_bound(speed_mps, gap_m, leader_speed_mps, params)
    return _masks(_SAFETY, prev, cand, bound=bound, ease_in=ease_in, params=params)


@dataclass(frozen=True)
class MaskInputs:
    """Per-agent physical quantities the masks need (1-D arrays of equal length)."""

    prev_accel_mps2: FloatArray
    speed_mps: FloatArray
    speed_limit_mps: FloatArray
    gap_m: FloatArray
    """Bumper gap to the front car (inf: none); see ``MergeEngine.front_cars`` for which car that is."""
    leader_speed_mps: FloatArray
    ease_in: BoolArray | None = None
    """Ours: the front car is on the other road and the ego is still outside the merging zone. Opening a
    gap to it only has to be done by the merge point, and from there comfortable braking does it, so
    the strongest Δa step stays allowed instead of forcing a hard brake the moment it comes into sight."""


def action_masks(inputs: MaskInputs, params: IDMParams = DEFAULT_IDM) -> npt.NDArray[np.int8]:
    """(n_agents, 7) int8 mask: kinematic ∩ rule ∩ safety."""
    prev = _as_rows(inputs.prev_accel_mps2)
    n = prev.shape[0]
    return np.asarray(
        _action_masks_kernel(
            prev,
            per_row(inputs.speed_mps, n),
            per_row(inputs.speed_limit_mps, n),
            per_row(inputs.gap_m, n),
            per_row(inputs.leader_speed_mps, n),
            per_row(inputs.ease_in, n, np.bool_),
            params.max_accel_mps2,
            params.comfortable_decel_mps2,
            params.min_gap_m,
            params.time_headway_s,
            params.delta,
        ),
        dtype=np.int8,
    )


@kernel
def _action_masks_kernel(
    prev, speed, limit, gap, leader_speed, ease_in, max_accel, comfortable_decel, min_gap, time_headway, delta
):
    """``action_masks`` in one call: the candidates, the safety bound and the three masks' intersection
    (what ``candidate_accelerations``, ``safety_bound`` and ``_masks`` compute, without their numpy around)."""
    bound = _safety_bounds(
        speed, gap, leader_speed, max_accel, comfortable_decel, min_gap, time_headway, delta
    )
    allowed = _masks_kernel(
        _KINEMATIC | _RULE | _SAFETY,
        prev,
        _candidates(prev),
        speed,
        limit,
        bound,
        ease_in,
        -comfortable_decel - _TOLERANCE,
    )
    return allowed.astype(np.int8)


_KINEMATIC, _RULE, _SAFETY = 1, 2, 4
"""Which of the three masks ``_masks`` intersects (bit flags)."""


def _as_rows(values: npt.ArrayLike) -> FloatArray:
    return np.ascontiguousarray(np.atleast_1d(np.asarray(values, dtype=np.float64)))


def _masks(
    which: int,
    prev: FloatArray,
    cand: FloatArray,
    speed: FloatArray | None = None,
    limit: FloatArray | None = None,
    bound: FloatArray | None = None,
    ease_in: BoolArray | None = None,
    params: IDMParams = DEFAULT_IDM,
) -> BoolArray:
    """The intersection of the masks ``which`` names (the inputs of the others are unused)."""
    n = cand.shape[0]
    if not (cand.shape == (n, N_ACTIONS) and cand.dtype == np.float64):
        cand = np.broadcast_to(np.asarray(cand, dtype=np.float64), (n, N_ACTIONS))
    return np.asarray(
        _masks_kernel(
            which,
            per_row(prev, n),
            np.ascontiguousarray(cand),
            per_row(speed, n),
            per_row(limit, n),
            per_row(bound, n),
            per_row(ease_in, n, np.bool_),
            -params.comfortable_decel_mps2 - _TOLERANCE,
        ),
        dtype=np.bool_,
    )


@kernel
def _masks_kernel(which, prev, cand, speed, limit, bound, ease_in, comfortable_floor):
    """One pass over every agent's seven actions; the masks as the docstrings of ``kinematic_mask``,
    ``rule_mask`` and ``safety_mask`` say. Hard brake is never masked."""
    n = cand.shape[0]
    allowed = np.ones((n, N_ACTIONS), dtype=np.bool_)
    for i in range(n):
        # np.isclose(prev, HARD_BRAKE_MPS2) with its default tolerances: directly after a hard brake.
        after_hard_brake = abs(prev[i] - HARD_BRAKE_MPS2) <= 1e-8 + 1e-5 * abs(HARD_BRAKE_MPS2)
        # Safety: the strongest Δa step within the kinematic range (the first one; none during a hard
        # brake) stays allowed while IDM asks for no more than the comfortable deceleration.
        strongest = -1
        for j in range(N_DELTA_ACTIONS):
            if cand[i, j] >= MIN_ACCEL_MPS2 - _TOLERANCE:
                strongest = j
                break
        comfortable = bound[i] >= comfortable_floor or ease_in[i]
        for j in range(N_ACTIONS):
            if j == HARD_BRAKE:
                continue
            a = cand[i, j]
            ok = True
            if which & _KINEMATIC:
                if j == RELEASE_BRAKE:
                    ok = after_hard_brake
                else:
                    ok = MIN_ACCEL_MPS2 - _TOLERANCE <= a <= MAX_ACCEL_MPS2 + _TOLERANCE
            if which & _RULE:
                ok = ok and speed[i] + _peak_speed_gain_one(a) <= limit[i] + _TOLERANCE
            if which & _SAFETY:
                ok = ok and (a <= bound[i] + _TOLERANCE or (j == strongest and comfortable))
            allowed[i, j] = ok
    return allowed
