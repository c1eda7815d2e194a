"""One step's traffic, as arrays over every vehicle in the simulation, plus lane relations.

Vehicles are projected onto one axis: the distance to the merge point (positive before it, negative
after). A vehicle on an incoming road shares its *current lane* with the cars on its own road and on
the outgoing road; its *other lane* is the other incoming road. A vehicle on the outgoing road has the
outgoing road as current lane and both incoming roads as other lane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from idas_sumo.env.jit import kernel
from idas_sumo.env.lazy import lazy

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

MAIN, MERGE, OUT = 0, 1, 2
ROAD_NAMES: tuple[str, ...] = ("main", "merge", "out")
NO_LEADER = -1


@dataclass(frozen=True)
class TrafficSnapshot:
    """Every vehicle in the simulation at one step (index i refers to ids[i])."""

    ids: tuple[str, ...]
    road: IntArray
    """MAIN, MERGE or OUT."""
    dist_to_merge_m: FloatArray
    """Front bumper's distance to the merge point along its path; negative once past it."""
    speed_mps: FloatArray
    accel_mps2: FloatArray
    length_m: FloatArray
    speed_limit_mps: FloatArray
    """The limit the rule mask enforces for this vehicle now (merge exemption included)."""
    copy: IntArray | None = None
    """Which copy of the merge each vehicle drives in (None: all in one)."""
    known_copy_bounds: IntArray | None = None
    """``copy_bounds`` where the maker already has them (copy k's rows bounds[k]:bounds[k + 1]; there may
    be entries for empty copies past the last vehicle's), to save working them out again."""
    known_longest_m: float | None = None
    """``longest_m`` where the maker already knows it (the engine: the same lengths while the same cars drive)."""
    known_by_distance: DistanceOrder | None = None
    """``by_distance`` where the maker sorted the rows already (the engine, in the same call that placed them).
    Like ``known_longest_m``, a copy (``dataclasses.replace``) that changes distances or lengths passes None."""

    def __len__(self) -> int:
        return len(self.ids)

    @lazy
    def _lookup(self) -> dict[str, int]:
        return {vid: i for i, vid in enumerate(self.ids)}

    def index(self, vehicle_ids: list[str] | tuple[str, ...]) -> IntArray:
        lookup = self._lookup
        return np.array([lookup[v] for v in vehicle_ids], dtype=np.int64)

    def __contains__(self, vehicle_id: str) -> bool:
        return vehicle_id in self._lookup

    @lazy
    def longest_m(self) -> float:
        """The longest vehicle's length (m; 0 without vehicles): how far a body reaches past its front."""
        if self.known_longest_m is not None:
            return self.known_longest_m
        return float(self.length_m.max()) if len(self.length_m) else 0.0

    @lazy
    def by_distance(self) -> DistanceOrder:
        """The rows sorted by (copy, distance to the merge point), for searching relations."""
        if self.known_by_distance is not None:
            return self.known_by_distance
        return DistanceOrder.of(self)

    @lazy
    def copy_bounds(self) -> IntArray | None:
        """Where each copy's vehicles start (K + 1 entries), if they come copy by copy; else None."""
        if self.copy is None:
            return None
        return self.known_copy_bounds if self.known_copy_bounds is not None else _copy_bounds(self.copy)


@dataclass(frozen=True)
class Neighbourhood:
    """Each ego's candidate neighbours as matrix columns: the vehicles of its own copy, in snapshot order.

    Every (ego, vehicle) relation is a (n_egos, m) matrix over these columns. With K copies side by side
    m is the largest copy's vehicle count, not every vehicle in the simulation: 16 copies of 8 cars give
    128 x 8 matrices instead of 128 x 128 (the cross-copy 15/16 could never relate). Column order is
    snapshot order, so ties (argmin picks the first) break exactly as over all vehicles.
    """

    cols: IntArray
    """(n_egos, m) vehicle indices; padding columns repeat the ego's own index (a valid, harmless gather)."""
    valid: BoolArray
    """(n_egos, m): a vehicle of the ego's copy other than the ego itself."""


def _copy_bounds(copy: IntArray) -> IntArray | None:
    """Start of each copy's vehicles in snapshot order (K + 1 entries), or None if copies interleave."""
    if len(copy) and np.any(copy[1:] < copy[:-1]):
        return None
    n_copies = int(copy.max()) + 1 if len(copy) else 0
    return np.searchsorted(copy, np.arange(n_copies + 1)).astype(np.int64)


def neighbourhood(snapshot: TrafficSnapshot, egos: IntArray) -> Neighbourhood:
    """The columns every relation matrix of these egos is built over (see ``Neighbourhood``)."""
    n_egos, n = len(egos), len(snapshot)
    own = egos[:, None]
    bounds = None if snapshot.copy is None else snapshot.copy_bounds
    if snapshot.copy is None or bounds is None:
        cols = np.broadcast_to(np.arange(n, dtype=np.int64)[None, :], (n_egos, n))
        valid = cols != own
        if snapshot.copy is not None:  # interleaved copies: every vehicle a column, other copies masked
            valid &= snapshot.copy[cols] == snapshot.copy[egos][:, None]
        return Neighbourhood(cols=cols, valid=valid)
    ego_copy = snapshot.copy[egos]
    first = bounds[ego_copy]
    size = bounds[ego_copy + 1] - first
    width = int(size.max()) if n_egos else 0
    j = np.arange(width, dtype=np.int64)[None, :]
    inside = j < size[:, None]
    cols = np.where(inside, first[:, None] + j, own)
    return Neighbourhood(cols=cols, valid=inside & (cols != own))


def lane_relations(snapshot: TrafficSnapshot, egos: IntArray) -> tuple[Neighbourhood, BoolArray, BoolArray]:
    """(neighbourhood, same_lane, other_lane): the bool matrices over the neighbourhood's columns; a
    vehicle is never its own neighbour, nor a neighbour of a vehicle in another copy."""
    nb = neighbourhood(snapshot, egos)
    road = snapshot.road
    ego_road = road[egos][:, None]
    other_road = road[nb.cols]
    incoming_ego = ego_road != OUT
    same = np.where(incoming_ego, (other_road == ego_road) | (other_road == OUT), other_road == OUT)
    other = np.where(incoming_ego, (other_road != ego_road) & (other_road != OUT), other_road != OUT)
    return nb, same & nb.valid, other & nb.valid


def leaders(snapshot: TrafficSnapshot, egos: IntArray) -> tuple[IntArray, FloatArray]:
    """Nearest car ahead in each ego's current lane: (index or NO_LEADER, bumper gap in m or inf)."""
    leader, gap, _ = leaders_and_speeds(snapshot, egos)
    return leader, gap


def leaders_and_speeds(snapshot: TrafficSnapshot, egos: IntArray) -> tuple[IntArray, FloatArray, FloatArray]:
    """``leaders`` and their ``leader_speeds`` (the ego's own speed where it has none), in one compiled call
    (what the safety mask needs every step)."""
    egos, by_dist, lo, hi = walk_start(snapshot, egos)
    return _leaders_kernel(
        snapshot.road,
        snapshot.dist_to_merge_m,
        snapshot.length_m,
        snapshot.speed_mps,
        by_dist.order,
        by_dist.sorted_dist,
        lo,
        hi,
        egos,
    )


def nearest_ahead(
    snapshot: TrafficSnapshot, egos: IntArray, any_lane: bool, level_counts: bool, max_ahead_m: float
) -> tuple[IntArray, FloatArray]:
    """Per ego, the nearest vehicle of its copy ahead of it in projection (front to front), in its
    current lane (``lane_relations``' same lane) or, with ``any_lane``, on either lane: (index or
    NO_LEADER, how far ahead in m, inf without one). Ahead means by more than 0 m, or by 0 m too with
    ``level_counts``, and by at most ``max_ahead_m``. Ties go to the first vehicle in snapshot order.

    The same relation as the (ego, neighbourhood) matrices of ``lane_relations``, as a compiled walk
    from the ego down its copy's vehicles sorted by distance (``DistanceOrder``), which stops at the
    first candidate: the matrices cost a few dozen numpy calls per step (at 8 cars a copy more than
    SUMO's own step of those cars) and grew as N x N in one world.
    """
    egos, by_dist, lo, hi = walk_start(snapshot, egos)
    return _nearest_ahead_kernel(
        snapshot.road,
        snapshot.dist_to_merge_m,
        by_dist.order,
        by_dist.sorted_dist,
        lo,
        hi,
        egos,
        any_lane,
        level_counts,
        float(max_ahead_m),
    )


@dataclass(frozen=True)
class DistanceOrder:
    """The snapshot's rows sorted by (copy, distance to the merge point): copy k's vehicles are
    ``order[starts[k]:starts[k + 1]]``, nearest the finish first. Relations search it instead of
    scanning every vehicle of a copy."""

    order: IntArray
    sorted_dist: FloatArray
    starts: IntArray

    @staticmethod
    def of(snapshot: TrafficSnapshot) -> DistanceOrder:
        dist = np.ascontiguousarray(snapshot.dist_to_merge_m, dtype=np.float64)
        if snapshot.copy is None or snapshot.known_copy_bounds is not None:
            # Rows come copy by copy: one compiled pass sorts each copy's span (stable, as lexsort is).
            if snapshot.copy is None:
                starts = np.array([0, len(dist)], dtype=np.int64)
            else:
                starts = np.asarray(snapshot.known_copy_bounds, dtype=np.int64)
            order, sorted_dist = _sort_spans(dist, starts)
            return DistanceOrder(order=order, sorted_dist=sorted_dist, starts=starts)
        # Copies interleave (a snapshot made by hand): sorted by (copy, distance) over all rows.
        copy = np.asarray(snapshot.copy, dtype=np.int64)
        order = np.lexsort((dist, copy)).astype(np.int64, copy=False)
        n_copies = int(copy.max()) + 1 if len(copy) else 0
        starts = np.searchsorted(copy[order], np.arange(n_copies + 1)).astype(np.int64)
        return DistanceOrder(order=order, sorted_dist=dist[order], starts=starts)

    def spans(self, snapshot: TrafficSnapshot, egos: IntArray) -> tuple[IntArray, IntArray]:
        """Per ego, where its copy's vehicles lie in ``order``: [lo, hi)."""
        if snapshot.copy is None:
            hi = np.empty(len(egos), dtype=np.int64)
            hi.fill(len(self.order))  # (np.full's value, without its Python wrapper)
            return np.zeros(len(egos), dtype=np.int64), hi
        ego_copy = np.asarray(snapshot.copy, dtype=np.int64)[egos]
        return self.starts[ego_copy], self.starts[ego_copy + 1]


@kernel
def _sorts_after(a, b):
    """Whether ``a`` comes after ``b`` in numpy's sort order (NaN last)."""
    return a > b or (a != a and b == b)


_INSERTION_SORT_MAX = 32
"""``_sort_spans`` sorts a copy's span of up to this many rows by insertion (no arrays made; a copy of 8 cars
sorted 5x faster), a longer one with mergesort (insertion's n² moves would cost more)."""


@kernel
def _sort_spans(dist, starts):
    """Each span ``starts[k]:starts[k + 1]`` of the rows sorted by distance (stable: ``np.lexsort((dist,
    copy))``'s order for rows grouped by copy), and the distances in that order."""
    n = dist.shape[0]
    order = np.arange(n)
    for k in range(starts.shape[0] - 1):
        lo, hi = starts[k], min(starts[k + 1], n)
        if hi - lo > _INSERTION_SORT_MAX:
            order[lo:hi] = lo + np.argsort(dist[lo:hi], kind="mergesort")
        else:  # a short span sorted in place (stable too: the same order), without argsort's arrays
            for i in range(lo + 1, hi):
                row = order[i]
                d = dist[row]
                j = i - 1
                while j >= lo and _sorts_after(dist[order[j]], d):
                    order[j + 1] = order[j]
                    j -= 1
                order[j + 1] = row
    sorted_dist = np.empty(n)
    for i in range(n):
        sorted_dist[i] = dist[order[i]]
    return order, sorted_dist


def walk_start(
    snapshot: TrafficSnapshot, egos: IntArray
) -> tuple[IntArray, DistanceOrder, IntArray, IntArray]:
    """What every compiled walk down a copy's vehicles starts from: the egos as a contiguous int64 array, the
    snapshot's distance order, and each ego's span of it, [lo, hi) (``DistanceOrder.spans``)."""
    egos = np.ascontiguousarray(egos, dtype=np.int64)
    by_dist = snapshot.by_distance
    lo, hi = by_dist.spans(snapshot, egos)
    return egos, by_dist, lo, hi


@kernel
def same_lane(ego_road: int, road: int) -> bool:
    """``lane_relations``' same lane, for one pair: an incoming road shares its lane with the outgoing
    road; the outgoing road only with itself. Every other vehicle of the copy is on the other lane."""
    if ego_road != OUT:
        return road in (ego_road, OUT)
    return road == OUT


@kernel
def _nearest_ahead_kernel(road, dist, order, sorted_dist, lo, hi, egos, any_lane, level_counts, max_ahead_m):
    n_egos = egos.shape[0]
    nearest = np.full(n_egos, NO_LEADER, dtype=np.int64)
    best = np.full(n_egos, np.inf)
    for r in range(n_egos):
        e = egos[r]
        # Down the copy's vehicles from the last one level with the ego: each is at least as far ahead as
        # the one before (rounded subtraction is monotone), so the walk stops past the nearest, after any
        # that tie with it (the first row wins a tie, as in a scan in snapshot order).
        p = lo[r] + np.searchsorted(sorted_dist[lo[r] : hi[r]], dist[e], side="right") - 1
        while p >= lo[r]:
            j = order[p]
            p -= 1
            if j == e or not (any_lane or same_lane(road[e], road[j])):
                continue
            ahead = dist[e] - dist[j]
            if ahead > max_ahead_m or ahead > best[r]:
                break
            if (ahead > 0.0 or (level_counts and ahead == 0.0)) and (ahead < best[r] or j < nearest[r]):
                best[r] = ahead
                nearest[r] = j
    return nearest, best


@kernel
def _leaders_kernel(road, dist, length, speed, order, sorted_dist, lo, hi, egos):
    leader, ahead_by = _nearest_ahead_kernel(
        road, dist, order, sorted_dist, lo, hi, egos, False, False, np.inf
    )
    gap = np.empty(egos.shape[0])
    leader_speed = np.empty(egos.shape[0])
    for r in range(egos.shape[0]):
        if leader[r] != NO_LEADER:
            gap[r] = ahead_by[r] - length[leader[r]]
            leader_speed[r] = speed[leader[r]]
        else:
            gap[r] = np.inf
            leader_speed[r] = speed[egos[r]]
    return leader, gap, leader_speed


def _nearest_ahead(
    snapshot: TrafficSnapshot, nb: Neighbourhood, distance: FloatArray
) -> tuple[IntArray, FloatArray]:
    """Per ego row of ``distance`` (front to front over the neighbourhood's columns, inf: not a
    candidate): (nearest vehicle index or NO_LEADER, gap)."""
    rows = np.arange(distance.shape[0])
    if distance.shape[1] == 0:
        return np.full(rows.shape, NO_LEADER, dtype=np.int64), np.full(rows.shape, np.inf)
    col = np.argmin(distance, axis=1)
    nearest = nb.cols[rows, col]
    has = np.isfinite(distance[rows, col])
    gap = np.where(has, distance[rows, col] - snapshot.length_m[nearest], np.inf)
    return np.where(has, nearest, NO_LEADER).astype(np.int64), gap.astype(np.float64)


def leader_speeds(snapshot: TrafficSnapshot, egos: IntArray, leader: IntArray) -> FloatArray:
    """Each leader's speed (m/s); the ego's own speed where it has none (so IDM sees no approach rate)."""
    has = leader != NO_LEADER
    speed = np.where(has, snapshot.speed_mps[np.where(has, leader, 0)], snapshot.speed_mps[egos])
    return speed.astype(np.float64)


def other_road_leaders(
    snapshot: TrafficSnapshot,
    egos: IntArray,
    max_ahead_m: float,
    zone_m: float = np.inf,
    level_counts_for_main: bool = False,
    never_leading: BoolArray | None = None,
) -> tuple[IntArray, FloatArray]:
    """Nearest car on the *other incoming road* ahead of each ego in projection: (index or NO_LEADER, gap).

    Only egos on an incoming road at or before the merge point have one. A candidate must be ahead of the
    ego by more than 0 and at most ``max_ahead_m`` (front bumper to front bumper), and both cars must be
    within ``zone_m`` of the merge point. With ``level_counts_for_main`` a main-road car exactly level
    with a merge-road ego counts as ahead (so two level cars never both see a free road). The gap is the
    projected distance minus the leader's length and may be <= 0: the cars already overlap in projection.
    """
    nb = neighbourhood(snapshot, egos)
    road = snapshot.road
    dist = snapshot.dist_to_merge_m
    ego_road = road[egos][:, None]
    ego_dist = dist[egos][:, None]
    cand_road = road[nb.cols]
    cand_dist = dist[nb.cols]
    incoming_ego = ((ego_road == MAIN) | (ego_road == MERGE)) & (ego_dist >= 0.0) & (ego_dist <= zone_m)
    # Cars already past the merge point are real leaders (leaders()), so only the other incoming road counts.
    other_incoming = ((cand_road == MAIN) | (cand_road == MERGE)) & (cand_road != ego_road)
    ahead_by = ego_dist - cand_dist  # > 0: closer to the merge point than the ego
    ahead = ahead_by > 0.0
    if level_counts_for_main:
        ahead |= (ahead_by == 0.0) & (cand_road == MAIN)
    candidates = incoming_ego & other_incoming & ahead & (ahead_by <= max_ahead_m) & (cand_dist <= zone_m)
    candidates &= nb.valid
    if never_leading is not None:
        candidates &= ~never_leading[nb.cols]
    return _nearest_ahead(snapshot, nb, np.where(candidates, ahead_by, np.inf))
