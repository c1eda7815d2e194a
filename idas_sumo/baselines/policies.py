"""The rule-based baselines (IDM, FSM+IDM) as policies that act like the learned one.

The paper equips every method with the same masks and the same 7 actions, so a baseline does not set
its acceleration directly: it computes the acceleration its model wants and picks the allowed action
whose resulting acceleration is closest. With Δa of at most 0.2 m/s² per step the baseline reaches
its target over a few steps, as the learned policy would, and it can never leave the masked set.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import numpy.typing as npt

from idas_sumo.baselines.fsm_idm import (
    DEFAULT_FSM,
    FSMParams,
    fsm_idm_acceleration,
    real_leader_idm_acceleration,
)
from idas_sumo.baselines.idm import IDMParams
from idas_sumo.env.actions import N_ACTIONS, candidate_accelerations
from idas_sumo.env.snapshot import TrafficSnapshot

IntArray = npt.NDArray[np.int64]

# Candidate accelerations lie on a 1e-6-rounded grid, so distances closer than this are the same.
_TIE_TOLERANCE_MPS2 = 1e-9


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


class BaselinePolicy(Protocol):
    """A baseline: actions for the vehicles ``egos`` (indices into ``snapshot``) under their masks."""

    def __call__(
        self,
        snapshot: TrafficSnapshot,
        egos: npt.ArrayLike,
        prev_accel: npt.ArrayLike,
        mask: npt.ArrayLike,
        params: FSMParams = ...,
    ) -> IntArray: ...


def idm_actions(
    snapshot: TrafficSnapshot,
    egos: npt.ArrayLike,
    prev_accel: npt.ArrayLike,
    mask: npt.ArrayLike,
    params: FSMParams | IDMParams = DEFAULT_FSM,
) -> IntArray:
    """IDM: follow the real leader (``leaders()``), drive at the speed limit with none."""
    idm = params.idm if isinstance(params, FSMParams) else params
    target = real_leader_idm_acceleration(snapshot, egos, idm)
    return closest_allowed_action(target, prev_accel, mask)


def fsm_idm_actions(
    snapshot: TrafficSnapshot,
    egos: npt.ArrayLike,
    prev_accel: npt.ArrayLike,
    mask: npt.ArrayLike,
    params: FSMParams = DEFAULT_FSM,
) -> IntArray:
    """FSM+IDM: IDM to the real leader and to an other-road car at a similar distance; the stricter wins."""
    target = fsm_idm_acceleration(snapshot, egos, params)
    return closest_allowed_action(target, prev_accel, mask)


BASELINES: dict[str, BaselinePolicy] = {
    "idm": idm_actions,
    "fsm_idm": fsm_idm_actions,
}
"""Rule-based baselines by the name ``idas-sumo evaluate --baseline`` uses."""

__all__ = ["BASELINES", "BaselinePolicy", "closest_allowed_action", "fsm_idm_actions", "idm_actions"]
