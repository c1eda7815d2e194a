"""Where a car is relative to the merge point: tables looked up by the road a car came from and its edge."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import MERGE_EXEMPTION_M
from idas_sumo.env.collisions import any_overlap
from idas_sumo.env.jit import kernel
from idas_sumo.env.snapshot import MAIN, MERGE, OUT, _sort_spans
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
        self._last_edges: tuple[str, ...] | None = None
        self._last_code = np.zeros(0, dtype=np.int64)
        """The edge codes of the last read's edges (``place`` without numbered edges)."""
        self._code_by_edge_index: IntArray | None = None
        """The edge codes by ``BatchStates.edge_index``, where the backend numbers its edges."""
        self._last_edge_index: IntArray | None = None
        self._index_code = np.zeros(0, dtype=np.int64)
        """The edge codes of ``_last_edge_index``."""

    def number_edges(self, edge_ids: Sequence[str]) -> None:
        """The backend numbers its edges so (``BatchStates.edge_index``, -1: none of the net's): the codes by
        that number, the last entry for -1, spare a dictionary lookup per car and step."""
        unknown = self._start_by.shape[1] - 1
        self._last_edge_index = None
        self._code_by_edge_index = np.array(
            [*(self._edge_code.get(e, unknown) for e in edge_ids), unknown], dtype=np.int64
        )

    def place(
        self, states: BatchStates, origin: IntArray
    ) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
        """(origin, road, distance to the merge point m, speed limit m/s) of each car of ``states``, given
        the road it started on (``origin``; a merging car that changed onto the main road's lane comes back
        as MAIN)."""
        # One compiled pass, bit for bit the numpy formulas it replaced (tests/test_engine_kernels.py).
        return _place_kernel(*self._place_args(states, origin))

    def place_in_order(
        self, states: BatchStates, origin: IntArray, length_m: FloatArray, longest_m: float
    ) -> tuple[IntArray, IntArray, FloatArray, FloatArray, IntArray, FloatArray, bool]:
        """``place``, then the rows sorted by (copy, distance) (``DistanceOrder``'s order and sorted distances;
        the copies' spans are ``states.bounds``) and whether any two bodies overlap (``any_overlap``; each
        car ``length_m`` long, the longest ``longest_m``), in one compiled call: the engine's every read."""
        n = len(states.ids)
        # The six arrays come as rows of two the kernel fills: a compiled call's every returned array
        # costs about 0.5 µs of boxing, a row view a third of that.
        ints, floats = np.empty((3, n), dtype=np.int64), np.empty((3, n))
        args = (
            *self._place_args(states, origin),
            states.bounds,
            length_m,
            states.copy,
            self.via_length_m,
            longest_m,
            ints,
            floats,
        )
        overlap = _place_in_order_kernel(*args)
        return ints[0], ints[1], floats[0], floats[1], ints[2], floats[2], overlap

    def _place_args(self, states: BatchStates, origin: IntArray) -> tuple[object, ...]:
        """``_place_kernel``'s arguments for these cars."""
        n = len(states.ids)
        if self._code_by_edge_index is not None:
            if states.edge_index is not self._last_edge_index:  # (the backend hands out the same array
                self._last_edge_index = states.edge_index  # while every car stays on its edge)
                self._index_code = self._code_by_edge_index[states.edge_index]
            code = self._index_code
        elif states.edge == self._last_edges:  # the same edges as the last read (most steps of one world)
            code = self._last_code
        else:
            unknown = self._start_by.shape[1] - 1
            code = np.fromiter(map(self._edge_code.get, states.edge, itertools.repeat(unknown)), np.int64, n)
            self._last_edges, self._last_code = states.edge, code
        lane_index = states.lane_index if states.lane_index is not None and n else _NO_LANES
        return (
            code,
            np.ascontiguousarray(states.lane_pos_m, dtype=np.float64),
            np.ascontiguousarray(origin, dtype=np.int64),
            np.ascontiguousarray(lane_index, dtype=np.int64),
            self._merged_lane,
            self._incoming_by,
            self._start_by,
            self._limit_by,
            float(self.out_limit_mps),
            MERGE_EXEMPTION_M,
        )


_NO_LANES = np.zeros(0, dtype=np.int64)


@kernel
def _place_in_order_kernel(
    code,
    lane_pos,
    origin,
    lane_index,
    merged_lane,
    incoming_by,
    start_by,
    limit_by,
    out_limit,
    exempt_m,
    starts,
    length,
    row_copy,
    joined_past_by_origin,
    longest,
    ints,
    floats,
):
    """``Routes.place_in_order``: ``_place_kernel``, ``_sort_spans`` and ``any_overlap`` in one call; origin,
    road and order into the rows of ``ints``, distance, limit and sorted distance into those of ``floats``."""
    out_origin, road, dist, limit = _place_kernel(
        code, lane_pos, origin, lane_index, merged_lane, incoming_by, start_by, limit_by, out_limit, exempt_m
    )
    order, sorted_dist = _sort_spans(dist, starts)
    overlap = any_overlap(order, dist, row_copy, length, out_origin, joined_past_by_origin, longest)
    for i in range(dist.shape[0]):
        ints[0, i] = out_origin[i]
        ints[1, i] = road[i]
        ints[2, i] = order[i]
        floats[0, i] = dist[i]
        floats[1, i] = limit[i]
        floats[2, i] = sorted_dist[i]
    return overlap


@kernel
def _place_kernel(
    code, lane_pos, origin, lane_index, merged_lane, incoming_by, start_by, limit_by, out_limit, exempt_m
):
    """``Routes.place`` per car: a merging car on the main road's lane of a lane drop (``lane_index`` has a
    row per car; empty elsewhere) counts as MAIN; road = its origin before the merge point, else OUT;
    distance ``-(pos - start)`` (not ``start - pos``: -0.0 as before); the limit is the lane's, raised to
    the outgoing road's within ``exempt_m`` before the merge point on an incoming road
    (``effective_speed_limit``)."""
    n = code.shape[0]
    out_origin = np.empty(n, dtype=np.int64)
    road = np.empty(n, dtype=np.int64)
    dist = np.empty(n)
    limit = np.empty(n)
    lanes = lane_index.shape[0] > 0
    for i in range(n):
        c = code[i]
        o = origin[i]
        if lanes and o == MERGE and lane_index[i] == merged_lane[c]:
            o = MAIN
        out_origin[i] = o
        incoming = incoming_by[o, c]
        road[i] = o if incoming else OUT
        d = -(lane_pos[i] - start_by[o, c])
        dist[i] = d
        lane_limit = limit_by[o, c]
        if incoming and d >= 0.0 and d <= exempt_m:
            limit[i] = max(lane_limit, out_limit)
        else:
            limit[i] = lane_limit
    return out_origin, road, dist, limit


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
