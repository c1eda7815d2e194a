"""The paper's observation, built for all agents at once (layout in ``layout.py``)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from idas_sumo.env.jit import kernel, per_row
from idas_sumo.env.layout import (
    CELL_M,
    GRID_CELLS,
    GRID_SIZE,
    N_CHANNELS,
    N_LANES,
    N_SCALARS,
    OBS_DIM,
    RELATIVE_SPEED_SCALE_MPS,
    SCALAR_NAMES,
    SCALAR_SCALES,
    VISIBILITY_M,
)
from idas_sumo.env.snapshot import TrafficSnapshot, same_lane, walk_start

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


def build_grids(snapshot: TrafficSnapshot, egos: IntArray) -> npt.NDArray[np.float32]:
    """(n_egos, 2 lanes, 2 channels, 400 cells): occupancy and relative speed along each lane.

    A vehicle occupies every cell its body (rear to front bumper) touches. Cells are centred on the ego's
    front bumper: cell 200 starts there, lower cells lie behind, higher ahead.
    """
    grids = np.zeros((len(egos), GRID_SIZE), dtype=np.float32)
    _draw_grids(grids.reshape(-1), GRID_SIZE, 0, snapshot, egos)
    return grids.reshape(len(egos), N_LANES, N_CHANNELS, GRID_CELLS)


def _draw_grids(
    flat: npt.NDArray[np.float32], row_size: int, offset: int, snapshot: TrafficSnapshot, egos: IntArray
) -> None:
    """Draw the grids (``build_grids``' layout) of ego i into ``flat[i * row_size + offset:]``, zeroed.

    One compiled loop over the egos. Each looks up the vehicles of its copy within sight in the
    snapshot's distance order (``DistanceOrder``) and draws them in (ego, vehicle) order, snapshot
    order within an ego: overlapping bodies' speeds are written in that order, the last one winning.
    """
    if len(egos) == 0:
        return
    egos, by_dist, lo, hi = walk_start(snapshot, egos)
    # Copy by copy (or one world), a copy's span in the distance order is also its span of rows.
    rows_by_copy = snapshot.copy is None or snapshot.copy_bounds is not None
    _draw_grids_kernel(
        flat,
        row_size,
        offset,
        snapshot.road,
        snapshot.dist_to_merge_m,
        snapshot.length_m,
        snapshot.speed_mps,
        by_dist.order,
        by_dist.sorted_dist,
        lo,
        hi,
        egos,
        snapshot.longest_m,
        rows_by_copy,
    )


_WALK_ROWS_PER_NEAR_CAR = 4
"""A copy's rows are walked in order (each a comparison) rather than its cars within sight sorted (a few
comparisons and moves each) while it has at most this many rows per car within sight: at 32 cars a copy
the sort took half of the kernel's time."""


@kernel
def _draw_grids_kernel(
    flat, row_size, offset, road, dist, length, speed, order, sorted_dist, lo, hi, egos, longest, rows_by_copy
):
    seen = np.empty(order.shape[0], dtype=np.int64)
    for r in range(egos.shape[0]):
        e = egos[r]
        # Every body that can touch the grid lies within sight plus the longest body (1 m to spare for
        # rounding): the exact tests below decide, on the same numbers as before the window.
        near_from = dist[e] - VISIBILITY_M - longest - 1.0
        near_to = dist[e] + VISIBILITY_M + 1.0
        near = sorted_dist[lo[r] : hi[r]]
        a = lo[r] + np.searchsorted(near, near_from, side="left")
        b = lo[r] + np.searchsorted(near, near_to, side="right")
        m = b - a
        if rows_by_copy and hi[r] - lo[r] <= _WALK_ROWS_PER_NEAR_CAR * m:
            # [lo, hi) are the copy's rows: those within the window, in order, are order[a:b] sorted.
            m = 0
            for j in range(lo[r], hi[r]):
                if near_from <= dist[j] <= near_to:
                    seen[m] = j
                    m += 1
        else:
            seen[:m] = order[a:b]
            seen[:m].sort()
        for i in range(m):
            j = seen[i]
            if j == e:
                continue
            # Cells are counted from VISIBILITY_M behind the ego's front bumper; a body touches
            # [first, last], rear bumper to front bumper, and is drawn where that meets the grid.
            ahead_front = dist[e] - dist[j]
            first = np.floor((ahead_front - length[j] + VISIBILITY_M) / CELL_M)
            last = np.floor((ahead_front + VISIBILITY_M) / CELL_M)
            if not (last >= 0.0 and first < GRID_CELLS):  # (written so that a NaN is never drawn)
                continue
            lane_base = 0 if same_lane(road[e], road[j]) else N_CHANNELS * GRID_CELLS  # obs_ol after obs_cl
            start = r * row_size + offset + lane_base
            rel_speed = (speed[j] - speed[e]) / RELATIVE_SPEED_SCALE_MPS
            cells_from = start + int(max(first, 0.0))
            cells_to = start + int(min(last, GRID_CELLS - 1.0)) + 1
            flat[cells_from:cells_to] = 1.0
            flat[cells_from + GRID_CELLS : cells_to + GRID_CELLS] = rel_speed


def build_observations(
    snapshot: TrafficSnapshot,
    egos: IntArray,
    prev_accel_mps2: FloatArray,
    b_prio: FloatArray,
    b_type: FloatArray,
) -> npt.NDArray[np.float32]:
    """(n_egos, OBS_DIM) float32 observations; ``prev_accel`` is the acceleration the agent drives with."""
    return build_observations_checked(snapshot, egos, prev_accel_mps2, b_prio, b_type)[0]


def build_observations_checked(
    snapshot: TrafficSnapshot,
    egos: IntArray,
    prev_accel_mps2: FloatArray,
    b_prio: FloatArray,
    b_type: FloatArray,
) -> tuple[npt.NDArray[np.float32], bool]:
    """``build_observations``, and whether every scalar entry came out finite (a caller's check of the
    observations then only has to look at the grids)."""
    n = len(egos)
    obs = np.zeros((n, OBS_DIM), dtype=np.float32)
    if n == 0:
        return obs, True
    egos = np.ascontiguousarray(egos, dtype=np.int64)
    by_dist = snapshot.by_distance
    # The scalars, then the grids straight into the rows (``_draw_grids``), in one compiled call that also
    # finds each ego's span of the distance order (``walk_start``'s).
    finite = _observations_kernel(
        obs,
        snapshot.speed_mps,
        snapshot.dist_to_merge_m,
        egos,
        per_row(prev_accel_mps2, n),
        per_row(b_prio, n),
        per_row(b_type, n),
        _SCALES,
        snapshot.road,
        snapshot.length_m,
        by_dist.order,
        by_dist.sorted_dist,
        by_dist.starts,
        *copy_operands(snapshot),
    )
    return obs, bool(finite)


_NO_COPY = np.zeros(0, dtype=np.int64)
"""``_observations_kernel``'s row copies of a one-copy snapshot (every ego's span is every row)."""


def copy_operands(snapshot: TrafficSnapshot) -> tuple[npt.NDArray[np.int64], float, bool]:
    """``_observations_kernel``'s last three arguments: each row's copy (``_NO_COPY`` in a one-copy snapshot), the
    longest car, and whether the rows come copy by copy."""
    row_copy = _NO_COPY if snapshot.copy is None else np.ascontiguousarray(snapshot.copy, dtype=np.int64)
    return row_copy, snapshot.longest_m, snapshot.copy is None or snapshot.copy_bounds is not None


@kernel
def _observations_kernel(
    obs,
    speed,
    dist,
    egos,
    prev_accel,
    b_prio,
    b_type,
    scales,
    road,
    length,
    order,
    sorted_dist,
    starts,
    row_copy,
    longest,
    rows_by_copy,
):
    """``_write_scalars`` then ``_draw_grids_kernel`` into the rows after the scalars (one call of both), each
    ego's span of ``order`` its copy's (``DistanceOrder.spans``; every row without ``row_copy``)."""
    n = egos.shape[0]
    lo = np.zeros(n, dtype=np.int64)
    hi = np.full(n, order.shape[0], dtype=np.int64)
    if row_copy.shape[0] > 0:
        for i in range(n):
            c = row_copy[egos[i]]
            lo[i] = starts[c]
            hi[i] = starts[c + 1]
    finite = _write_scalars(obs, speed, dist, egos, prev_accel, b_prio, b_type, scales)
    _draw_grids_kernel(
        obs.reshape(-1),
        OBS_DIM,
        N_SCALARS,
        road,
        dist,
        length,
        speed,
        order,
        sorted_dist,
        lo,
        hi,
        egos,
        longest,
        rows_by_copy,
    )
    return finite


@kernel
def speed_spread(speed):
    """``speed.max() - speed.min()`` (NaN if any speed is NaN; 0.0 without speeds) in one compiled pass
    instead of two numpy reductions."""
    if speed.shape[0] == 0:
        return 0.0
    lo = hi = speed[0]
    for i in range(speed.shape[0]):
        v = speed[i]
        if v != v:
            return np.nan
        if v < lo:
            lo = v
        if v > hi:
            hi = v
    return hi - lo


_SCALES = np.asarray(SCALAR_SCALES, dtype=np.float64)
_SCALES.flags.writeable = False
if SCALAR_NAMES != ("speed", "accel", "dist_to_merge", "b_prio", "b_type"):  # ``_write_scalars``' columns
    raise ImportError(f"the observation's scalars changed to {SCALAR_NAMES}: update _write_scalars")


@kernel
def _write_scalars(obs, speed, dist, egos, prev_accel, b_prio, b_type, scales):
    """The scalar columns (``SCALAR_NAMES``' order), each divided by its scale in float64 and rounded to
    float32 as numpy's column assignment does; returns whether all of them are finite."""
    finite = True
    for i in range(egos.shape[0]):
        e = egos[i]
        obs[i, 0] = speed[e] / scales[0]
        obs[i, 1] = prev_accel[i] / scales[1]
        obs[i, 2] = dist[e] / scales[2]
        obs[i, 3] = b_prio[i] / scales[3]
        obs[i, 4] = b_type[i] / scales[4]
        for j in range(scales.shape[0]):
            finite = finite and np.isfinite(obs[i, j])
    return finite
