"""The paper's observation, built for all agents at once with numpy (layout in ``layout.py``)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from idas_sumo.env.layout import (
    CELL_M,
    GRID_CELLS,
    N_SCALARS,
    OBS_DIM,
    RELATIVE_SPEED_SCALE_MPS,
    SCALAR_SCALES,
    VISIBILITY_M,
)
from idas_sumo.env.snapshot import TrafficSnapshot, lane_relations

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


def build_grids(
    snapshot: TrafficSnapshot, egos: IntArray, out: npt.NDArray[np.float32] | None = None
) -> npt.NDArray[np.float32]:
    """(n_egos, 2 lanes, 2 channels, 400 cells): occupancy and relative speed along each lane.

    A vehicle occupies every cell its body (rear to front bumper) touches. Cells are centred on the ego's
    front bumper: cell 200 starts there, lower cells lie behind, higher ahead. ``out``: a zeroed array of
    that shape to draw into (e.g. a view into the observation rows), instead of a new one.
    """
    n_egos = len(egos)
    grids = np.zeros((n_egos, 2, 2, GRID_CELLS), dtype=np.float32) if out is None else out
    if n_egos == 0:
        return grids
    nb, same, other = lane_relations(snapshot, egos)
    dist = snapshot.dist_to_merge_m
    ahead_front = dist[egos][:, None] - dist[nb.cols]  # (egos, neighbourhood)
    ahead_rear = ahead_front - snapshot.length_m[nb.cols]
    first = np.floor((ahead_rear + VISIBILITY_M) / CELL_M).astype(np.int64)
    last = np.floor((ahead_front + VISIBILITY_M) / CELL_M).astype(np.int64)
    visible = (last >= 0) & (first < GRID_CELLS)
    first = np.clip(first, 0, GRID_CELLS - 1)
    last = np.clip(last, 0, GRID_CELLS - 1)
    speed = snapshot.speed_mps
    rel_speed = (speed[nb.cols] - speed[egos][:, None]) / RELATIVE_SPEED_SCALE_MPS
    max_cells = int(np.ceil(float(snapshot.length_m.max()) / CELL_M)) + 1 if len(snapshot) else 1
    offsets = np.arange(max_cells)
    for lane, related in enumerate((same, other)):
        e, v = np.nonzero(related & visible)
        if len(e) == 0:
            continue
        cells = first[e, v][:, None] + offsets[None, :]  # every cell a body may touch
        valid = cells <= last[e, v][:, None]
        rows = np.broadcast_to(e[:, None], cells.shape)[valid]
        speeds = np.broadcast_to(rel_speed[e, v][:, None], cells.shape)[valid]
        grids[rows, lane, 0, cells[valid]] = 1.0
        grids[rows, lane, 1, cells[valid]] = speeds
    return grids


def build_observations(
    snapshot: TrafficSnapshot,
    egos: IntArray,
    prev_accel_mps2: FloatArray,
    b_prio: FloatArray,
    b_type: FloatArray,
) -> npt.NDArray[np.float32]:
    """(n_egos, OBS_DIM) float32 observations; ``prev_accel`` is the acceleration the agent drives with."""
    n_egos = len(egos)
    obs = np.zeros((n_egos, OBS_DIM), dtype=np.float32)
    scalars = np.stack(
        [snapshot.speed_mps[egos], prev_accel_mps2, snapshot.dist_to_merge_m[egos], b_prio, b_type], axis=-1
    )
    obs[:, :N_SCALARS] = scalars / np.asarray(SCALAR_SCALES)
    # The grids are drawn straight into the observation rows (a view), not built and then copied.
    build_grids(snapshot, egos, out=obs[:, N_SCALARS:].reshape(n_egos, 2, 2, GRID_CELLS))
    return obs
