"""The engine's compiled step loops (numba) and the end-reason codes they return."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import N_ACTIONS, _candidate
from idas_sumo.env.cars import ACTIVE
from idas_sumo.env.contracts import AgentBatch
from idas_sumo.env.jit import kernel
from idas_sumo.env.outcome import END_REASONS, HARD_BRAKE_DETECT_MPS2

IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class HardBrakes:
    """A step's hard brakes, placed where each braking car was when it decided (the step's start)."""

    rows: IntArray
    """Rows of the step's first snapshot: the agents' (batch order), then SUMO's cars'."""
    per_copy: IntArray
    zone_per_copy: IntArray
    """Of those, within the merging zone (each costs the flow penalty)."""
    ids: list[list[str]]
    """Per copy: the braking vehicles, in the order counted."""


_REASON_BY_CODE: tuple[str, ...] = ("", *END_REASONS)
_REASON_CODE = {reason: code for code, reason in enumerate(_REASON_BY_CODE)}
_COLLIDED, _REMOVED, _FINISHED = _REASON_CODE["collided"], _REASON_CODE["removed"], _REASON_CODE["finished"]


def _checked_actions(batch: AgentBatch, actions: npt.ArrayLike) -> IntArray:
    """Actions as int64 (n,), or a ValueError naming the first bad one's agent and the time."""
    raw = np.asarray(actions)
    n = len(batch)
    if raw.shape != (n,):
        raise ValueError(f"{raw.shape} actions for {n} agents")
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if raw.dtype.kind not in "iu":
        bad = 0
        for i, v in enumerate(raw.tolist()):
            if isinstance(v, bool) or not isinstance(v, int):
                bad = i
                break
        else:
            raw = raw.astype(np.int64)
        if raw.dtype.kind not in "iu":
            raise ValueError(
                f"invalid action {raw[bad]!r} for agent {batch.ids[bad]!r} at t = {batch.time_s:.1f} s: "
                f"expected an int in [0, {N_ACTIONS})"
            )
    out = raw.astype(np.int64)
    i = _first_outside(out, N_ACTIONS)
    if i >= 0:
        raise ValueError(
            f"invalid action {int(out[i])} for agent {batch.ids[i]!r} at t = {batch.time_s:.1f} s: "
            f"expected an int in [0, {N_ACTIONS})"
        )
    return out


@kernel
def _first_outside(actions, n_actions):
    """The first index whose action is not in [0, n_actions), or -1."""
    for i in range(actions.shape[0]):
        if not 0 <= actions[i] < n_actions:
            return i
    return -1


@kernel
def _allowed_step(masks, actions, prev, speed, egos, step_s, out):
    """When every agent's action is allowed by its mask row (nearly every step): True, with
    ``next_acceleration`` and ``_next_speeds`` of it in the rows of ``out`` (2, n), in one pass (filled, not
    returned: a compiled call's every returned array costs about 0.5 µs of boxing); else False."""
    n = actions.shape[0]
    for i in range(n):
        if masks[i, actions[i]] == 0:
            return False
    for i in range(n):
        a = _candidate(prev[i], actions[i])
        out[0, i] = a
        v = speed[egos[i]] + a * step_s
        out[1, i] = v if v > 0.0 or v != v else 0.0
    return True


@kernel
def _next_speeds(speed, egos, accel, step_s):
    """The speed (m/s) each agent is told to reach in this step: v + a·dt, at least 0, as
    ``np.maximum(v + a * dt, 0.0)`` gives it (a NaN stays NaN, -0.0 becomes 0.0)."""
    out = np.empty(egos.shape[0])
    for i in range(egos.shape[0]):
        v = speed[egos[i]] + accel[i] * step_s
        out[i] = v if v > 0.0 or v != v else 0.0
    return out


@kernel
def _hard_brakes(
    egos,
    agent_brake,
    accel,
    car_of_row,
    acting,
    car_copy,
    car_state,
    rows_before,
    copy_before,
    dist_before,
    zone_m,
    rows,
    copy,
    in_zone,
    per_copy,
):
    """The step's hard brakes as rows of the step's first snapshot: the agents' (``agent_brake``, batch
    order), then those of the cars now braking at ``HARD_BRAKE_DETECT_MPS2`` or harder (rows of the new
    snapshot, in order) that are no agents, drive in an acting copy and were on the road before.

    Fills (rows, their copies, within ``zone_m`` of the merge point; each as long as ``egos`` and ``accel``
    together) and ``per_copy`` (zeros, (2, K): brakes per copy, of those within ``zone_m`` per copy), and
    returns how many rows it found (filled, not returned: a compiled call's every returned array costs
    about 0.5 µs of boxing); ``acting`` has one entry per copy."""
    m = 0
    for i in range(egos.shape[0]):
        if agent_brake[i]:
            rows[m] = egos[i]
            m += 1
    for r in range(accel.shape[0]):
        if accel[r] <= HARD_BRAKE_DETECT_MPS2:
            c = car_of_row[r]
            if acting[car_copy[c]] and car_state[c] != ACTIVE and rows_before[c] >= 0:
                rows[m] = rows_before[c]
                m += 1
    for i in range(m):
        copy[i] = copy_before[rows[i]]
        in_zone[i] = np.abs(dist_before[rows[i]]) <= zone_m
        per_copy[0, copy[i]] += 1
        if in_zone[i]:
            per_copy[1, copy[i]] += 1
    return m


@kernel
def _maybe_hard_brakes(applied, hard_brake, accel):
    """Whether ``_hard_brakes`` can find any: an agent chose ``hard_brake``, or some car now brakes at
    ``HARD_BRAKE_DETECT_MPS2`` or harder (most steps neither: the step then skips the full search)."""
    for i in range(applied.shape[0]):
        if applied[i] == hard_brake:
            return True
    for r in range(accel.shape[0]):  # noqa: SIM110
        if accel[r] <= HARD_BRAKE_DETECT_MPS2:
            return True
    return False


@kernel
def _book_counts(agent_car, car_scored, rewards, impede, agent_copy, car_copy, car_state, rows, per_copy):
    """``MergeEngine._book``'s counts in one pass: into ``rows[0]`` the agents acting for the first time
    (batch rows; their cars marked scored), into ``rows[1]`` those with a nonzero reward (batch rows), into
    ``per_copy`` (zeros, (2, K)) per copy the agents with an impede penalty and the cars still acting;
    returns how many rows each of the first two has (filled, not returned: a compiled call's every
    returned array costs about 0.5 µs of boxing)."""
    n = agent_car.shape[0]
    n_first = n_scored = 0
    for i in range(n):
        if not car_scored[agent_car[i]]:
            rows[0, n_first] = i
            n_first += 1
            car_scored[agent_car[i]] = True
        if rewards[i] != 0.0:
            rows[1, n_scored] = i
            n_scored += 1
        if impede[i] < 0.0:
            per_copy[0, agent_copy[i]] += 1
    for c in range(car_state.shape[0]):
        if car_state[c] == ACTIVE:
            per_copy[1, car_copy[c]] += 1
    return n_first, n_scored


@kernel
def _end_codes(collided, row, dist, finish_below_m, otherwise):
    """Each agent's end reason (``_REASON_CODE``), the first that holds: collided, removed (no ``row`` in
    the new snapshot), finished (its distance to the merge point at or below ``finish_below_m``), else
    ``otherwise`` (timeout, or going on)."""
    code = np.empty(collided.shape[0], dtype=np.int64)
    for i in range(collided.shape[0]):
        if collided[i]:
            code[i] = _COLLIDED
        elif row[i] < 0:
            code[i] = _REMOVED
        elif dist[row[i]] <= finish_below_m:
            code[i] = _FINISHED
        else:
            code[i] = otherwise
    return code


@kernel
def _step_ends(collided, car_row, agent_car, dist, finish_below_m, otherwise, applied, hard_brake, accel):
    """The step's checks after SUMO's step, in one call: each agent's end code (``_end_codes`` of its car's
    row), how many ended, and whether there may be hard brakes (``_maybe_hard_brakes``)."""
    row = np.empty(agent_car.shape[0], dtype=np.int64)
    for i in range(agent_car.shape[0]):
        row[i] = car_row[agent_car[i]]
    code = _end_codes(collided, row, dist, finish_below_m, otherwise)
    ended = 0
    for i in range(code.shape[0]):
        if code[i] != 0:
            ended += 1
    return code, ended, _maybe_hard_brakes(applied, hard_brake, accel)


@kernel
def _agent_values(car, car_row, admitted, car_accel, speed, accel, dist, road, out, out_road):
    """``MergeEngine.agent_values``' gathers in one pass: per car its speed, acceleration (an admitted car's
    own) and distance into the rows of ``out`` (3, n), its road into ``out_road`` (-1 off the road, where
    the others are row 0's, which the caller ignores)."""
    for i in range(car.shape[0]):
        c = car[i]
        r = car_row[c]
        on = r >= 0
        if not on:
            r = 0
        out[0, i] = speed[r]
        out[1, i] = car_accel[c] if admitted[c] else accel[r]
        out[2, i] = dist[r]
        out_road[i] = road[r] if on else -1
