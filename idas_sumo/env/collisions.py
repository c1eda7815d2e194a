"""The engine's geometric collision check: cars of one copy whose bodies overlap on one road."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from idas_sumo.env.jit import kernel
from idas_sumo.env.snapshot import TrafficSnapshot

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def geometric_collisions(
    snap: TrafficSnapshot, origin: IntArray, joined_past_m: FloatArray | float = 0.0
) -> list[tuple[int, int]]:
    """Rows (i, j), i < j, in order, of cars of one copy whose bodies overlap on one road.

    A body spans [front, front + length] in distance to the merge point; overlapping means a bumper gap
    below zero, SUMO's own criterion with ``--collision.mingap-factor 0``. A car drives on the lanes of
    its incoming road (``origin``: MAIN or MERGE) until its lane joins the outgoing one,
    ``joined_past_m`` past the merge point (per car or one value: the junction's internal lane of its
    road; 0 for a net without one). So two overlapping cars collide when they came from the same road,
    or when both fronts are past the point where their lanes joined. Before that the two roads' cars are
    side by side, however close in projection; in the junction SUMO's own check
    (``--collision.check-junctions``) sees when their shapes touch. Counting every projected overlap
    inside the junction called near misses collisions: 3 of 100 paper-suite episodes (own-lane mask,
    IDM ego) where the cars came within 0.6 m in projection while their lanes were still apart, and the
    leader pulled away.

    Sorted by (copy, distance) only neighbours closer than the longest car can overlap, so this costs
    O(n log n) per step rather than an n x n matrix.
    """
    n = len(snap)
    if n < 2:
        return []
    d = snap.dist_to_merge_m
    copy = snap.copy if snap.copy is not None else np.zeros(n, dtype=np.int64)
    order = snap.by_distance.order  # by (copy, distance), shared with the step's relations and grids
    joined_past = np.asarray(joined_past_m, dtype=np.float64)
    if joined_past.shape != d.shape:  # one value for every car
        joined_past = np.broadcast_to(joined_past, d.shape)
    pairs = _overlapping_pairs(
        order,
        _contiguous(d, np.float64),
        _contiguous(copy, np.int64),
        _contiguous(snap.length_m, np.float64),
        _contiguous(origin, np.int64),
        np.ascontiguousarray(joined_past),
        snap.longest_m,
    )
    if not len(pairs):  # (nearly every step)
        return []
    return sorted(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist(), strict=True))


def _contiguous(a: npt.NDArray[np.generic], dtype: type) -> npt.NDArray[np.generic]:
    """``a`` as a contiguous array of ``dtype`` (itself when it is one: the engine's arrays are)."""
    if a.dtype == dtype and a.flags.c_contiguous:
        return a
    return np.ascontiguousarray(a, dtype=dtype)


@kernel
def _bodies_overlap(d, length, origin, i, j, joined_past_i, joined_past_j):
    """Whether cars i and j collide: on one road (the same origin, or both fronts past where their lanes
    joined) with their bodies overlapping."""
    one_road = origin[i] == origin[j] or (d[i] < -joined_past_i and d[j] < -joined_past_j)
    return one_road and d[i] < d[j] + length[j] and d[j] < d[i] + length[i]


@kernel
def _overlapping_pairs(order, d, copy, length, origin, joined_past, reach):
    """(pairs, 2) rows (lower, higher) of ``geometric_collisions``' colliding pairs, in scan order. Sorted
    by (copy, distance), each car only meets the next ones of its copy until one is farther than
    ``reach`` (the longest car) ahead of it."""
    n = order.shape[0]
    found = np.empty((0, 2), dtype=np.int64)
    for count_only in (True, False):
        m = 0
        for p in range(n):
            i = order[p]
            for q in range(p + 1, n):
                j = order[q]
                if copy[j] != copy[i] or d[j] - d[i] > reach:
                    break
                if _bodies_overlap(d, length, origin, i, j, joined_past[i], joined_past[j]):
                    if not count_only:
                        found[m, 0] = min(i, j)
                        found[m, 1] = max(i, j)
                    m += 1
        if count_only:
            found = np.empty((m, 2), dtype=np.int64)
    return found


@kernel
def any_overlap(order, d, copy, length, origin, joined_past_by_origin, reach):
    """Whether ``geometric_collisions`` finds any pair (the same scan, stopping at the first), with each car's
    ``joined_past_m`` looked up by its origin: the engine's check of every step, most of which find none,
    without the per-car arrays the pairs' search takes."""
    n = order.shape[0]
    for p in range(n):
        i = order[p]
        for q in range(p + 1, n):
            j = order[q]
            if copy[j] != copy[i] or d[j] - d[i] > reach:
                break
            past_i, past_j = joined_past_by_origin[origin[i]], joined_past_by_origin[origin[j]]
            if _bodies_overlap(d, length, origin, i, j, past_i, past_j):
                return True
    return False
