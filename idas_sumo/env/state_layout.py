"""The global state ``MergeEngine.state(k)`` returns for the centralised critic Q.

The state is a fixed number of vehicle slots (STATE_SLOTS), each a row of STATE_FEATURES floats::

    [present, on_main, on_merge, on_out, dist_to_merge / 250 m, speed / 20 m/s, accel / 4 m/s²,
     b_prio, b_type / 2, controlled]

flattened row-major into a vector of STATE_DIM floats. Empty slots are all zeros (``present`` = 0).
The scales are the observation's (``env/layout.py``), so both critics see the same units. What the
critic gets besides the state (the other agents' actions, its own slot) is agent-side:
``agents/critic_input.py``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from idas_sumo.env.jit import kernel
from idas_sumo.env.layout import ACCEL_SCALE_MPS2, B_TYPE_SCALE, DIST_SCALE_M, SPEED_SCALE_MPS
from idas_sumo.env.snapshot import MAIN, MERGE, OUT, FloatArray, IntArray, TrafficSnapshot

# 8 learning agents in stage 2 plus room for SUMO's own cars in stage 1 (2 to 8 per road).
STATE_SLOTS = 16
STATE_FEATURE_NAMES: tuple[str, ...] = (
    "present",
    "on_main",
    "on_merge",
    "on_out",
    "dist_to_merge",
    "speed",
    "accel",
    "b_prio",
    "b_type",
    "controlled",
)
STATE_FEATURES = len(STATE_FEATURE_NAMES)  # 10
STATE_DIM = STATE_SLOTS * STATE_FEATURES  # 160


def critic_states(
    snap: TrafficSnapshot,
    bounds: IntArray,
    copies: IntArray,
    car: IntArray,
    first: IntArray,
    b_type: FloatArray,
    acting: npt.NDArray[np.bool_],
    prio_by_road: FloatArray,
) -> npt.NDArray[np.float32]:
    """The state of each of ``copies`` (rows of the result, STATE_DIM each): the copy's cars (rows
    ``bounds[k]:bounds[k + 1]`` of ``snap``), car ``car[i]`` of row i in the slot of its place in its
    scenario (``car[i] - first[k]``; cars past STATE_SLOTS are left out).

    ``b_type``, ``acting`` (an agent still acting: the ``controlled`` feature): per car;
    ``prio_by_road``: (K, 3), each copy's b_prio of MAIN, MERGE and OUT. One compiled call for every copy
    of a step: a rollout records them all at each step."""
    out = np.zeros((len(copies), STATE_SLOTS, STATE_FEATURES), dtype=np.float32)
    _critic_states_kernel(
        snap.road,
        snap.dist_to_merge_m,
        snap.speed_mps,
        snap.accel_mps2,
        bounds,
        np.ascontiguousarray(copies, dtype=np.int64),
        car,
        first,
        b_type,
        acting,
        prio_by_road,
        out,
    )
    return out.reshape(len(copies), STATE_DIM)


@kernel
def _critic_states_kernel(
    road: IntArray,
    dist: FloatArray,
    speed: FloatArray,
    accel: FloatArray,
    bounds: IntArray,
    copies: IntArray,
    car: IntArray,
    first: IntArray,
    b_type: FloatArray,
    acting: npt.NDArray[np.bool_],
    prio_by_road: FloatArray,
    out: npt.NDArray[np.float32],
) -> None:
    for j in range(len(copies)):
        k = copies[j]
        for i in range(bounds[k], bounds[k + 1]):
            c = car[i]
            slot = c - first[k]
            if slot >= STATE_SLOTS:
                continue
            r = road[i]
            row = out[j, slot]
            row[0] = 1.0
            row[1] = r == MAIN
            row[2] = r == MERGE
            row[3] = r == OUT
            row[4] = dist[i] / DIST_SCALE_M
            row[5] = speed[i] / SPEED_SCALE_MPS
            row[6] = accel[i] / ACCEL_SCALE_MPS2
            row[7] = prio_by_road[k, r]
            row[8] = b_type[c] / B_TYPE_SCALE
            row[9] = acting[c]
