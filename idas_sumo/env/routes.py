"""Where a car is relative to the merge point: tables looked up by the road a car came from and its edge."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import effective_speed_limit
from idas_sumo.env.snapshot import MAIN, MERGE, OUT
from idas_sumo.sim.batch import BatchStates
from idas_sumo.sim.merge_detect import MergeSite

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class Routes:
    """A merge site's route tables, and ``place``: each car's road, distance to the merge point and limit."""

    def __init__(self, site: MergeSite) -> None:
        self.out_limit_mps = site.out[0].speed_limit_mps
        self._edge_code, self._start_by, self._incoming_by, self._limit_by = _route_tables(site)
        # Per edge code: the main approach's lane on an edge both approaches share (a lane drop's
        # acceleration edge), else -1. A merging car on that lane has changed onto the main road.
        self._merged_lane = np.full(self._start_by.shape[1], -1, dtype=np.int64)
        for edge_id, lane_index in site.shared_lanes.items():
            self._merged_lane[self._edge_code[edge_id]] = lane_index
        self.via_length_m = np.array([site.main.via_length_m, site.merge.via_length_m])
        """By origin (MAIN, MERGE): where its junction lane joins the outgoing road, past the merge point."""
        self._code_by_edge_index: IntArray | None = None
        """The edge codes by ``BatchStates.edge_index``, where the backend numbers its edges."""

    def number_edges(self, edge_ids: Sequence[str]) -> None:
        """The backend numbers its edges so (``BatchStates.edge_index``, -1: none of the net's): the codes by
        that number, the last entry for -1, spare a dictionary lookup per car and step."""
        unknown = self._start_by.shape[1] - 1
        self._code_by_edge_index = np.array(
            [*(self._edge_code.get(e, unknown) for e in edge_ids), unknown], dtype=np.int64
        )

    def place(
        self, states: BatchStates, origin: IntArray
    ) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
        """(origin, road, distance to the merge point m, speed limit m/s) of each car of ``states``, given
        the road it started on (``origin``; a merging car that changed onto the main road's lane comes back
        as MAIN)."""
        n = len(states.ids)
        if self._code_by_edge_index is not None:
            code = self._code_by_edge_index[states.edge_index]
        else:
            unknown = self._start_by.shape[1] - 1
            code = np.fromiter(map(self._edge_code.get, states.edge, itertools.repeat(unknown)), np.int64, n)
        if states.lane_index is not None and n:
            # On a lane drop a merging car that changed onto the main road's lane drives on as a main-road
            # car: the cars behind it in that lane see it in their own lane (the paper's mask keeps its
            # distance to it), and it sees theirs.
            merged = (origin == MERGE) & (states.lane_index == self._merged_lane[code])
            origin = np.where(merged, MAIN, origin)
        incoming = self._incoming_by[origin, code]
        road = np.where(incoming, origin, OUT)
        # -(pos - start), not start - pos: bit for bit the T-junction's former formulas (L - pos on an
        # incoming road, -(via + pos) on the outgoing one, -pos on a junction lane, -0.0 included).
        dist = -(states.lane_pos_m - self._start_by[origin, code])
        lane_limit = self._limit_by[origin, code]
        own_limit = effective_speed_limit(lane_limit, dist, self.out_limit_mps)
        return origin, road.astype(np.int64), dist, np.where(incoming, own_limit, lane_limit)


def _route_tables(site: MergeSite) -> tuple[dict[str, int], FloatArray, npt.NDArray[np.bool_], FloatArray]:
    """What ``_read_snapshot`` looks a car up in, by its origin (MAIN or MERGE) and the edge it is on.

    (edge id -> code, start (2, E + 1), incoming (2, E + 1), limit (2, E + 1)): for every edge of either
    approach's route (junction-internal ones included), the distance of its start to the merge point
    along that origin's route (``MergeSite.distance_table``; a car at lane position ``pos`` is ``start -
    pos`` before it), whether it lies before the merge point (the car is still on its own road, MAIN or
    MERGE; after it the road is OUT), and its lane's speed limit (a junction lane
    takes the limit of the lane it leads onto: SUMO sets its speed from its curvature, not a sign). On a
    lane drop both approaches share the last edges and differ only by origin. The last column is for an
    edge on no route (a car SUMO sent elsewhere): past the merge point at its start, the outgoing limit.
    """
    routes = (site.route("main"), site.route("merge"))
    code: dict[str, int] = {}
    for route in routes:
        for lane in route:
            code.setdefault(lane.edge_id, len(code))
    unknown = len(code)
    start = np.zeros((2, unknown + 1))
    incoming = np.zeros((2, unknown + 1), dtype=np.bool_)
    limit = np.full((2, unknown + 1), site.out[0].speed_limit_mps)
    for origin, route in zip((MAIN, MERGE), routes, strict=True):
        onward = site.out[0].speed_limit_mps
        for lane in reversed(route):  # backwards: a junction lane takes the next ordinary lane's limit
            if not lane.internal:
                onward = lane.speed_limit_mps
            c = code[lane.edge_id]
            start[origin, c] = lane.start_to_merge_m
            incoming[origin, c] = lane.start_to_merge_m > 0.0
            limit[origin, c] = onward
    return code, start, incoming, limit
