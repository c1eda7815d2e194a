"""The Intelligent Driver Model (Treiber et al. 2000), as a pure, vectorised function.

    dv/dt = a_max * (1 - (v / v0)**delta - (s_star / s)**2)
    s_star = s0 + max(0, v*T + v*dv / (2*sqrt(a_max*b)))

v is the speed, v0 the desired speed (the road's limit), s the bumper-to-bumper gap to the leader,
dv = v - v_leader the approach rate. Without a leader (gap = +inf) the interaction term vanishes and
the car drives towards v0. The paper's safety mask uses the same formula with s0 = 2 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class IDMParams:
    """IDM parameters. Defaults: the paper's s0 and acceleration range, common values otherwise."""

    max_accel_mps2: float = 2.0
    """a: the largest acceleration (the kinematic mask's upper bound)."""
    comfortable_decel_mps2: float = 2.0
    """b: comfortable deceleration, positive (the kinematic mask's lower bound, magnitude)."""
    min_gap_m: float = 2.0
    """s0: the gap kept at standstill (the paper: 2 m)."""
    time_headway_s: float = 1.0
    """T: the desired time gap to the leader."""
    delta: float = 4.0
    """Acceleration exponent."""


DEFAULT_IDM = IDMParams()
_GAP_FLOOR_M = 0.01
"""Gaps are clipped here: a touching leader gives a very large braking demand, not a division by zero."""
_DESIRED_SPEED_FLOOR_MPS = 1e-6


def idm_acceleration(
    speed: npt.ArrayLike,
    desired_speed: npt.ArrayLike,
    gap: npt.ArrayLike,
    approach_rate: npt.ArrayLike,
    params: IDMParams = DEFAULT_IDM,
) -> FloatArray:
    """IDM acceleration in m/s² for each vehicle; arrays broadcast.

    speed, desired_speed in m/s; gap in m (np.inf when there is no leader; clipped at 1 cm so a
    touching leader gives a very large braking demand instead of a division by zero);
    approach_rate = own speed - leader speed in m/s (ignored where gap is inf).
    """
    v = np.asarray(speed, dtype=np.float64)
    v0 = np.asarray(desired_speed, dtype=np.float64)
    s = np.maximum(np.asarray(gap, dtype=np.float64), _GAP_FLOOR_M)
    dv = np.asarray(approach_rate, dtype=np.float64)
    free_road = (np.maximum(v, 0.0) / np.maximum(v0, _DESIRED_SPEED_FLOOR_MPS)) ** params.delta
    dynamic_gap = v * params.time_headway_s + v * dv / (
        2.0 * np.sqrt(params.max_accel_mps2 * params.comfortable_decel_mps2)
    )
    s_star = params.min_gap_m + np.maximum(dynamic_gap, 0.0)
    interaction = np.where(np.isinf(s), 0.0, (s_star / s) ** 2)
    return np.asarray(params.max_accel_mps2 * (1.0 - free_road - interaction), dtype=np.float64)


def idm_acceleration_one(
    speed: float,
    desired_speed: float,
    gap: float,
    approach_rate: float,
    max_accel: float,
    comfortable_decel: float,
    min_gap: float,
    time_headway: float,
    delta: float,
) -> float:
    """``idm_acceleration`` of one vehicle, the parameters spelled out: plain arithmetic that the env's
    compiled loops call (env/actions.py). The same operations in the same order give the same numbers,
    except for ``** delta``, where numpy may take its SIMD power (AVX-512), which can differ from libm's in
    the last bit. Without a free-road term (desired_speed = inf: 0 ** delta, as in the safety bound) they
    agree bit for bit but for the sign of a NaN. Each ``np.maximum(x, floor)`` is written out as numpy
    computes it: x where x > floor or x is NaN, else floor (so -0.0 against 0.0 gives 0.0)."""
    s = gap if gap > _GAP_FLOOR_M or gap != gap else _GAP_FLOOR_M
    v = speed if speed > 0.0 or speed != speed else 0.0
    v0 = (
        desired_speed
        if desired_speed > _DESIRED_SPEED_FLOOR_MPS or desired_speed != desired_speed
        else _DESIRED_SPEED_FLOOR_MPS
    )
    free_road = (v / v0) ** delta
    dynamic_gap = speed * time_headway + speed * approach_rate / (
        2.0 * math.sqrt(max_accel * comfortable_decel)
    )
    s_star = min_gap + (dynamic_gap if dynamic_gap > 0.0 or dynamic_gap != dynamic_gap else 0.0)
    interaction = 0.0 if math.isinf(s) else (s_star / s) ** 2
    return max_accel * (1.0 - free_road - interaction)
