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
from idas_sumo.env.actions import HARD_BRAKE, N_DELTA_ACTIONS, closest_allowed_action
from idas_sumo.env.engine import AgentBatch
from idas_sumo.env.snapshot import TrafficSnapshot
from idas_sumo.physics.idm import IDMParams

IntArray = npt.NDArray[np.int64]


class RuleActions(Protocol):
    """A rule's arithmetic: actions for the vehicles ``egos`` (indices into ``snapshot``) under their masks.
    Not a policy contract: the engine's one is ``env.engine.Policy``, which ``RuleBasedPolicy`` implements."""

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


def hard_brake_only_when_forced(mask: npt.ArrayLike) -> npt.NDArray[np.int8]:
    """``mask`` (n, 7) with the hard brake taken out of every row that still allows a Δa action.

    Ours: ``closest_allowed_action`` picks the hard brake whenever the rule's target lies nearer -4 m/s²
    than the next Δa step, so a rule that wants -2.5 m/s² brakes hard (and the mask then holds the brake
    until IDM allows a release). With this mask the rule eases down at the jerk limit instead and brakes
    hard only where the safety mask leaves nothing else: the paper's "brake hard during emergency
    situations" (L269) read as a rule's choice, not as a mask on the learned policy.
    """
    out = np.array(mask, dtype=np.int8, copy=True, ndmin=2)
    out[np.any(out[:, :N_DELTA_ACTIONS] != 0, axis=1), HARD_BRAKE] = 0
    return out


def fsm_idm_smooth_actions(
    snapshot: TrafficSnapshot,
    egos: npt.ArrayLike,
    prev_accel: npt.ArrayLike,
    mask: npt.ArrayLike,
    params: FSMParams = DEFAULT_FSM,
) -> IntArray:
    """FSM+IDM that brakes hard only when the mask forces it (``hard_brake_only_when_forced``); ours."""
    return fsm_idm_actions(snapshot, egos, prev_accel, hard_brake_only_when_forced(mask), params)


BASELINES: dict[str, RuleActions] = {
    "idm": idm_actions,
    "fsm_idm": fsm_idm_actions,
    # Ours, beside the paper's two: docs/results.md, "Declared: a warm start that brakes hard only when forced".
    "fsm_idm_smooth": fsm_idm_smooth_actions,
}
"""Rule-based baselines by the name ``idas-sumo evaluate --baseline`` uses."""
EGO_ONLY_BASELINES: frozenset[str] = frozenset({"fsm_idm", "fsm_idm_smooth"})
"""Rules with no driver type: where a case gives the method several cars (the representative scenes), the paper
runs FSM+IDM on one car only and IDAS on the other; its smooth twin of ours runs the same way."""


class RuleBasedPolicy:
    """A baseline behind the engine's ``Policy`` contract: it reads the batch's snapshot, not observations."""

    def __init__(self, name: str, params: FSMParams = DEFAULT_FSM) -> None:
        self.name = name
        self._act = BASELINES[name]
        self.params = params

    def act(self, batch: AgentBatch, rows: IntArray) -> IntArray:
        return self._act(
            batch.snapshot, batch.egos[rows], batch.prev_accel[rows], batch.masks[rows], self.params
        )


__all__ = [
    "BASELINES",
    "EGO_ONLY_BASELINES",
    "RuleActions",
    "RuleBasedPolicy",
    "fsm_idm_actions",
    "fsm_idm_smooth_actions",
    "hard_brake_only_when_forced",
    "idm_actions",
]
