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


def lane_relations(road: IntArray, egos: IntArray) -> tuple[BoolArray, BoolArray]:
    """(same_lane, other_lane): bool (n_egos, n_vehicles) matrices; a vehicle is never its own neighbour."""
    ego_road = road[egos][:, None]
    other_road = road[None, :]
    incoming_ego = ego_road != OUT
    same = np.where(incoming_ego, (other_road == ego_road) | (other_road == OUT), other_road == OUT)
    other = np.where(incoming_ego, (other_road != ego_road) & (other_road != OUT), other_road != OUT)
    self_mask = np.arange(road.shape[0])[None, :] == egos[:, None]
    return same & ~self_mask, other & ~self_mask


def leaders(snapshot: TrafficSnapshot, egos: IntArray) -> tuple[IntArray, FloatArray]:
    """Nearest car ahead in each ego's current lane: (index or NO_LEADER, bumper gap in m or inf)."""
    same, _ = lane_relations(snapshot.road, egos)
    ahead_by = snapshot.dist_to_merge_m[egos][:, None] - snapshot.dist_to_merge_m[None, :]  # > 0: ahead
    candidates = same & (ahead_by > 0.0)
    distance = np.where(candidates, ahead_by, np.inf)
    leader = np.argmin(distance, axis=1)
    has_leader = np.isfinite(distance[np.arange(len(egos)), leader])
    gap = np.where(has_leader, distance[np.arange(len(egos)), leader] - snapshot.length_m[leader], np.inf)
    return np.where(has_leader, leader, NO_LEADER).astype(np.int64), gap.astype(np.float64)
