"""One step's traffic, as arrays over every vehicle in the simulation, plus lane relations.

Vehicles are projected onto one axis: the distance to the merge point (positive before it, negative
after). A vehicle on an incoming road shares its *current lane* with the cars on its own road and on
the outgoing road; its *other lane* is the other incoming road. A vehicle on the outgoing road has the
outgoing road as current lane and both incoming roads as other lane.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

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

    def __len__(self) -> int:
        return len(self.ids)

    @functools.cached_property
    def _lookup(self) -> dict[str, int]:
        return {vid: i for i, vid in enumerate(self.ids)}

    def index(self, vehicle_ids: list[str] | tuple[str, ...]) -> IntArray:
        lookup = self._lookup
        return np.array([lookup[v] for v in vehicle_ids], dtype=np.int64)

    def __contains__(self, vehicle_id: str) -> bool:
        return vehicle_id in self._lookup


def same_copy(copy: IntArray | None, egos: IntArray) -> BoolArray | None:
    """(n_egos, n_vehicles): True where the vehicle drives in the ego's copy (None: one copy, all True)."""
    if copy is None:
        return None
    return np.asarray(copy[egos][:, None] == copy[None, :])


def lane_relations(
    road: IntArray, egos: IntArray, copy: IntArray | None = None
) -> tuple[BoolArray, BoolArray]:
    """(same_lane, other_lane): bool (n_egos, n_vehicles) matrices; a vehicle is never its own neighbour,
    nor a neighbour of a vehicle in another copy (``copy``: each vehicle's copy, None: one copy)."""
    ego_road = road[egos][:, None]
    other_road = road[None, :]
    incoming_ego = ego_road != OUT
    same = np.where(incoming_ego, (other_road == ego_road) | (other_road == OUT), other_road == OUT)
    other = np.where(incoming_ego, (other_road != ego_road) & (other_road != OUT), other_road != OUT)
    self_mask = np.arange(road.shape[0])[None, :] == egos[:, None]
    related = ~self_mask
    in_copy = same_copy(copy, egos)
    if in_copy is not None:
        related &= in_copy
    return same & related, other & related


def leaders(snapshot: TrafficSnapshot, egos: IntArray) -> tuple[IntArray, FloatArray]:
    """Nearest car ahead in each ego's current lane: (index or NO_LEADER, bumper gap in m or inf)."""
    same, _ = lane_relations(snapshot.road, egos, snapshot.copy)
    ahead_by = snapshot.dist_to_merge_m[egos][:, None] - snapshot.dist_to_merge_m[None, :]  # > 0: ahead
    return _nearest_ahead(snapshot, np.where(same & (ahead_by > 0.0), ahead_by, np.inf))


def _nearest_ahead(snapshot: TrafficSnapshot, distance: FloatArray) -> tuple[IntArray, FloatArray]:
    """Per ego row of ``distance`` (front to front, inf: not a candidate): (nearest index or NO_LEADER, gap)."""
    rows = np.arange(distance.shape[0])
    if distance.shape[1] == 0:
        return np.full(rows.shape, NO_LEADER, dtype=np.int64), np.full(rows.shape, np.inf)
    nearest = np.argmin(distance, axis=1)
    has = np.isfinite(distance[rows, nearest])
    gap = np.where(has, distance[rows, nearest] - snapshot.length_m[nearest], np.inf)
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
    road = snapshot.road
    dist = snapshot.dist_to_merge_m
    ego_road = road[egos][:, None]
    ego_dist = dist[egos][:, None]
    incoming_ego = ((ego_road == MAIN) | (ego_road == MERGE)) & (ego_dist >= 0.0) & (ego_dist <= zone_m)
    # Cars already past the merge point are real leaders (leaders()), so only the other incoming road counts.
    other_incoming = ((road[None, :] == MAIN) | (road[None, :] == MERGE)) & (road[None, :] != ego_road)
    ahead_by = ego_dist - dist[None, :]  # > 0: closer to the merge point than the ego
    ahead = ahead_by > 0.0
    if level_counts_for_main:
        ahead |= (ahead_by == 0.0) & (road[None, :] == MAIN)
    candidates = incoming_ego & other_incoming & ahead & (ahead_by <= max_ahead_m) & (dist[None, :] <= zone_m)
    if never_leading is not None:
        candidates &= ~never_leading[None, :]
    in_copy = same_copy(snapshot.copy, egos)
    if in_copy is not None:
        candidates &= in_copy
    return _nearest_ahead(snapshot, np.where(candidates, ahead_by, np.inf))
