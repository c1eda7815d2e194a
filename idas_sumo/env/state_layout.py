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

from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from idas_sumo.env.layout import ACCEL_SCALE_MPS2, B_TYPE_SCALE, DIST_SCALE_M, SPEED_SCALE_MPS
from idas_sumo.env.scenario import VehicleSpec
from idas_sumo.env.snapshot import MAIN, MERGE, OUT, TrafficSnapshot

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


def critic_state(
    snap: TrafficSnapshot,
    rows: slice,
    place: Mapping[str, int],
    spec: Mapping[str, VehicleSpec],
    prio_by_road: npt.NDArray[np.float64],
    acting: npt.NDArray[np.bool_],
) -> npt.NDArray[np.float32]:
    """One episode's state: its cars (``rows`` of ``snap``) that have a ``place``, each in its slot.

    ``prio_by_road``: b_prio of MAIN, MERGE and OUT; ``acting``: per row of ``rows``, whether the car is an
    agent still acting (the ``controlled`` feature)."""
    state = np.zeros((STATE_SLOTS, STATE_FEATURES), dtype=np.float32)
    for i in range(rows.start, rows.stop):
        vid = snap.ids[i]
        slot = place.get(vid)
        if slot is None:
            continue
        road = int(snap.road[i])
        state[slot] = (
            1.0,
            road == MAIN,
            road == MERGE,
            road == OUT,
            snap.dist_to_merge_m[i] / DIST_SCALE_M,
            snap.speed_mps[i] / SPEED_SCALE_MPS,
            snap.accel_mps2[i] / ACCEL_SCALE_MPS2,
            prio_by_road[road],
            spec[vid].b_type / B_TYPE_SCALE,
            float(acting[i - rows.start]),
        )
    return state.reshape(STATE_DIM)
