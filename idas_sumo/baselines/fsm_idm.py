"""FSM+IDM, the paper's rule-based baseline, as pure vectorised functions over a ``TrafficSnapshot``.

The paper: "the agent will first examine if there is any vehicle on the other lane that has similar
distances to the merge point as itself. If there is such vehicle, the agent will select that car as
another front vehicle besides its actual front vehicle and then utilize IDM to follow both of them."

Reading adopted here (*ours*, the paper gives no numbers): the other-road vehicle counts as a *virtual
leader* only when it is strictly closer to the merge point than the ego, by at most
``SIMILAR_DISTANCE_WINDOW_M``; the nearest such vehicle wins. A vehicle exactly level with the ego or
behind it is deliberately ignored. That is the failure mode the paper reports for FSM+IDM in the
representative scenes ("if any vehicle drives slightly behind the ego car or by its side ... collision
happens"), so a baseline that also yielded to those cars would not be the paper's baseline.

Following both leaders means taking the smaller of the two IDM accelerations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from idas_sumo.env.snapshot import TrafficSnapshot, leader_speeds, leaders, other_road_leaders
from idas_sumo.physics.idm import DEFAULT_IDM, IDMParams, idm_acceleration

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

SIMILAR_DISTANCE_WINDOW_M = 20.0
"""How far ahead (m, projected onto distance-to-merge, front bumper to front bumper) an other-road car
may be and still count as being at a "similar distance to the merge point".

20 m is about IDM's desired gap at the paper's speeds (s* = s0 + v·T = 2 + 15·1 = 17 m on the 15 m/s
road, 22 m on the 20 m/s road), i.e. one car length plus the headway the ego would want behind that
car anyway. A car further ahead than that already leaves room to fall in behind at a comfortable gap,
so treating it as a leader would only add braking without a safety reason; a much smaller window
would let the ego notice a converging car only once braking can no longer avoid it."""


@dataclass(frozen=True)
class FSMParams:
    """Parameters of the rule-based baselines (IDM uses only ``idm``)."""

    similar_distance_window_m: float = SIMILAR_DISTANCE_WINDOW_M
    """See ``SIMILAR_DISTANCE_WINDOW_M``."""
    idm: IDMParams = field(default_factory=IDMParams)
    """IDM used for both the real and the virtual leader."""

    def __post_init__(self) -> None:
        if not np.isfinite(self.similar_distance_window_m) or self.similar_distance_window_m <= 0.0:
            window = self.similar_distance_window_m
            raise ValueError(f"similar_distance_window_m must be positive and finite (m), got {window}")


DEFAULT_FSM = FSMParams()


def _as_indices(snapshot: TrafficSnapshot, egos: npt.ArrayLike) -> IntArray:
    idx = np.atleast_1d(np.asarray(egos, dtype=np.int64))
    if idx.ndim != 1:
        raise ValueError(f"egos must be a 1-D array of vehicle indices, got shape {idx.shape}")
    if np.any((idx < 0) | (idx >= len(snapshot))):
        raise ValueError(f"ego indices must lie in [0, {len(snapshot)}), got {idx.tolist()}")
    return idx


def virtual_leaders(
    snapshot: TrafficSnapshot,
    egos: npt.ArrayLike,
    window_m: float = SIMILAR_DISTANCE_WINDOW_M,
) -> tuple[IntArray, FloatArray, FloatArray]:
    """FSM's extra leader for each ego: (index or NO_LEADER, gap in m or inf, leader speed in m/s).

    Only egos on an incoming road at or before the merge point have one; it is the nearest vehicle on
    the *other* incoming road that is ahead of the ego in projection by more than 0 and at most
    ``window_m``. The gap is that projected distance minus the leader's length and may be ≤ 0 (the
    cars already overlap in projection): IDM then demands a very hard brake, which is the point.
    Where there is no virtual leader the speed is the ego's own (so IDM sees no approach rate).
    """
    idx = _as_indices(snapshot, egos)
    if idx.shape[0] == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.float64), np.empty(0, dtype=np.float64)
    leader, gap = other_road_leaders(snapshot, idx, max_ahead_m=window_m)
    return leader, gap, leader_speeds(snapshot, idx, leader)


def real_leader_idm_acceleration(
    snapshot: TrafficSnapshot, egos: npt.ArrayLike, idm: IDMParams = DEFAULT_IDM
) -> FloatArray:
    """Plain IDM (m/s²): follow the nearest car ahead in the current lane, drive towards the limit."""
    idx = _as_indices(snapshot, egos)
    if idx.shape[0] == 0:
        return np.empty(0, dtype=np.float64)
    leader, gap = leaders(snapshot, idx)
    v = snapshot.speed_mps[idx]
    return idm_acceleration(
        v, snapshot.speed_limit_mps[idx], gap, v - leader_speeds(snapshot, idx, leader), idm
    )


def fsm_idm_acceleration(
    snapshot: TrafficSnapshot, egos: npt.ArrayLike, params: FSMParams = DEFAULT_FSM
) -> FloatArray:
    """FSM+IDM acceleration (m/s²): the more restrictive of IDM to the real and to the virtual leader.

    Desired speed is ``snapshot.speed_limit_mps`` (the effective limit, merge exemption included).
    """
    idx = _as_indices(snapshot, egos)
    if idx.shape[0] == 0:
        return np.empty(0, dtype=np.float64)
    real = real_leader_idm_acceleration(snapshot, idx, params.idm)
    _, gap, leader_speed = virtual_leaders(snapshot, idx, params.similar_distance_window_m)
    v = snapshot.speed_mps[idx]
    virtual = idm_acceleration(v, snapshot.speed_limit_mps[idx], gap, v - leader_speed, params.idm)
    return np.minimum(real, virtual).astype(np.float64)


__all__ = [
    "DEFAULT_FSM",
    "SIMILAR_DISTANCE_WINDOW_M",
    "FSMParams",
    "fsm_idm_acceleration",
    "real_leader_idm_acceleration",
    "virtual_leaders",
]
