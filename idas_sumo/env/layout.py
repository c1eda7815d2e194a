"""The observation layout shared by the adapter, the networks and the checkpoints.

One agent's observation is a flat float32 vector::

    [speed, accel, dist_to_merge, b_prio, b_type,      # 5 scalars, normalised by SCALAR_SCALES
     obs_cl occupancy (400), obs_cl relative speed (400),
     obs_ol occupancy (400), obs_ol relative speed (400)]

The grids cover 100 m behind to 100 m ahead of the agent at 0.5 m per cell, projected on the
distance to the merge point (cell 0 is 100 m behind, cell 399 just under 100 m ahead).
Relative speeds are (other - ego) / RELATIVE_SPEED_SCALE_MPS.
"""

from __future__ import annotations

SCALAR_NAMES: tuple[str, ...] = ("speed", "accel", "dist_to_merge", "b_prio", "b_type")
N_SCALARS = len(SCALAR_NAMES)
SPEED_SCALE_MPS = 20.0
ACCEL_SCALE_MPS2 = 4.0
DIST_SCALE_M = 250.0
B_TYPE_SCALE = 2.0
SCALAR_SCALES: tuple[float, ...] = (SPEED_SCALE_MPS, ACCEL_SCALE_MPS2, DIST_SCALE_M, 1.0, B_TYPE_SCALE)
RELATIVE_SPEED_SCALE_MPS = 20.0

VISIBILITY_M = 100.0
CELL_M = 0.5
GRID_CELLS = int(2 * VISIBILITY_M / CELL_M)  # 400
N_LANES = 2  # obs_cl, obs_ol
N_CHANNELS = 2  # occupancy, relative speed
GRID_SIZE = N_LANES * N_CHANNELS * GRID_CELLS
OBS_DIM = N_SCALARS + GRID_SIZE  # 1605

# Recorded in checkpoints so a policy trained on another layout is refused on load.
OBS_LAYOUT_ID = f"scalars{N_SCALARS}-lanes{N_LANES}-ch{N_CHANNELS}-cells{GRID_CELLS}-v1"
