"""Find the merges in any SUMO network, and describe each along the routes through it.

A merge is a place where two roads' lanes become one. Two kinds are found, both at a junction (node):

- ``junction``: lanes of two incoming roads connect into the same outgoing lane, and both roads lead
  nowhere else (the generated T-junction, a side road joining a main road). A crossing, whose roads
  lead to several outgoing roads, is not a merge.
- ``lane_drop``: an on-ramp's acceleration lane. The ramp's lane goes on as the highway's rightmost
  lane, which ends at a later junction: netconvert gives the ending lane no connection (or connects it
  into the same lane as its neighbour), so its cars change into the neighbouring lane. It counts only
  when the two lanes, followed upstream, come from different roads (a lane that a road simply loses
  is no merge of two roads).

The merge point is the end of the two merging lanes (the junction). Each ``MergeSite`` gives the two
approaches (``main``: the road with right of way, by SUMO priority, then speed limit, then the
straighter one; ``merge``: the other, and on a lane drop always the ending lane), each as the lanes a
car drives, upstream first, followed back from the merge point through single predecessors for at
least ``upstream_m`` (or until a lane has no single predecessor), with junction-internal lanes in
between; the lanes after the merge point (``out``, followed through single successors for
``downstream_m``); and for every lane the distance of its start to the merge point along the route
(negative past it), so that a car's distance to the merge point is ``start_to_merge_m - lane
position`` on whichever edge it is. Nothing here assumes edge names or lengths.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from idas_sumo.errors import InputError
from idas_sumo.sim.netgen import MergeNet, RoadInfo, load_sumo_net, turn_deg

DEFAULT_UPSTREAM_M = 500.0
"""Follow each approach back at least this far from the merge point (the scenarios' start range, 200 m,
plus the 100 m sensor range behind the merge point, with room to spare)."""
DEFAULT_DOWNSTREAM_M = 300.0
"""Follow the outgoing lanes at least this far past the merge point (finish line and sensor range)."""
FOLLOW_SPLIT_M = 100.0
"""A road that splits into several straight roads closer than this past the merge point goes on along
its straightest one (then the highest priority): the finish line (50 m past the merge point) and the
sensor range ahead need that much road. A split farther on ends the outgoing road, as it always did."""
MAX_TRACE_M = 10_000.0
"""How far back a lane drop's two lanes are followed to find the two roads they come from."""
MAX_LISTED = 12
"""Junctions named in the message for a net without a merge (a city has thousands)."""
MAX_DESCRIBED = 4
"""Merges described in full in the message that asks for ``--junction``."""

MergeKind = Literal["junction", "lane_drop"]
Side = Literal["main", "merge"]
VEHICLE_CLASS = "passenger"
"""The SUMO vehicle class whose lanes count (the package's cars are passenger cars)."""
_TURNAROUND = "t"
_STRAIGHT = "s"


@dataclass(frozen=True)
class RouteLane:
    """One lane of a route through the merge, with where it starts relative to the merge point."""

    edge_id: str
    lane_index: int
    length_m: float
    start_to_merge_m: float
    """Along the route from this lane's start to the merge point; negative for lanes past it."""
    speed_limit_mps: float
    priority: int
    """The edge's SUMO priority."""
    lane_count: int
    internal: bool
    """A junction-internal lane (between two edges; its edge id starts with ``:``)."""

    @property
    def lane_id(self) -> str:
        return f"{self.edge_id}_{self.lane_index}"


@dataclass(frozen=True)
class Approach:
    """The lanes a car drives to the merge point on one road, upstream first."""

    lanes: tuple[RouteLane, ...]
    """Ends with the lane that ends at the merge point; junction-internal lanes included."""
    through: tuple[RouteLane, ...]
    """The junction-internal lanes from the merge point onto the outgoing lane (start_to_merge_m <= 0)."""
    road_index: int
    """Index in ``lanes`` of this approach's own road: the last lane not shared with the other approach
    (on a lane drop both approaches end on the same edge)."""
    ending: bool = False
    """Its lane ends at the merge point without a connection: its cars change into the main lane."""

    @property
    def edges(self) -> tuple[RouteLane, ...]:
        """The lanes on ordinary edges (no junction-internal ones), upstream first."""
        return tuple(lane for lane in self.lanes if not lane.internal)

    @property
    def edge_ids(self) -> tuple[str, ...]:
        return tuple(lane.edge_id for lane in self.edges)

    @property
    def road(self) -> RouteLane:
        return self.lanes[self.road_index]

    @property
    def length_m(self) -> float:
        """From the start of the first lane to the merge point."""
        return self.lanes[0].start_to_merge_m

    @property
    def via_length_m(self) -> float:
        """Length of the junction-internal lanes from the merge point onto the outgoing lane."""
        return sum(lane.length_m for lane in self.through)

    @property
    def edges_length_m(self) -> float:
        """The summed length of its ordinary edges: the room a car can start on (junction-internal lanes
        between them take none)."""
        return sum(lane.length_m for lane in self.edges)

    def edge_point(self, along_edges_m: float) -> tuple[RouteLane, float]:
        """The ordinary lane and position ``along_edges_m`` from the approach's start counted along its
        edges only (each junction-internal lane passed adds its length to the distance driven, none to
        this count), so every point lands on an edge and points drawn some metres apart end up at least
        that far apart. A point on the first edge is its position there; an InputError beyond the last
        edge's end or before the start."""
        rest = along_edges_m
        if rest >= 0.0:
            for lane in self.edges:
                if rest < lane.length_m:
                    return lane, rest
                rest -= lane.length_m
        raise InputError(
            f"{along_edges_m:g} m from the start of the approach {'+'.join(self.edge_ids)} lies outside its "
            f"edges (0 to {self.edges_length_m:g} m along them)"
        )

    def lane_at(self, dist_to_merge_m: float) -> tuple[RouteLane, float]:
        """The ordinary lane a point ``dist_to_merge_m`` before the merge point lies on, and the
        position on it; an InputError when the point lies outside the approach."""
        for lane in self.edges:
            pos = lane.start_to_merge_m - dist_to_merge_m
            if 0.0 <= pos < lane.length_m:
                return lane, pos
        where = (
            "between two of its edges (a junction-internal lane): pick a point on an edge"
            if 0.0 < dist_to_merge_m <= self.length_m
            else f"outside it (above 0 and up to {self.length_m:g} m before the merge point)"
        )
        raise InputError(
            f"{dist_to_merge_m:g} m before the merge point on the approach {'+'.join(self.edge_ids)} lies {where}"
        )


@dataclass(frozen=True)
class MergeSite:
    """A merge found in a net: where, the two approaches, and the road after it."""

    path: Path
    junction_id: str
    kind: MergeKind
    main: Approach
    merge: Approach
    out: tuple[RouteLane, ...]
    """The lanes after the merge junction, from the outgoing lane on; ``start_to_merge_m`` from the
    outgoing lane's start (0 for it): ``route`` shifts them by each approach's junction lanes."""

    def approach(self, side: Side) -> Approach:
        return self.main if side == "main" else self.merge

    def route(self, side: Side) -> tuple[RouteLane, ...]:
        """Every lane of the route from ``side``'s first lane to the end of ``out``, with the distance
        of each lane's start to the merge point along this route (negative past it)."""
        approach = self.approach(side)
        shift = approach.via_length_m
        past = tuple(
            RouteLane(
                r.edge_id,
                r.lane_index,
                r.length_m,
                r.start_to_merge_m - shift,
                r.speed_limit_mps,
                r.priority,
                r.lane_count,
                r.internal,
            )
            for r in self.out
        )
        return (*approach.lanes, *approach.through, *past)

    @property
    def shared_lanes(self) -> dict[str, int]:
        """Edge id -> the main approach's lane on it, for the ordinary edges both approaches drive
        before the merge point (a lane drop's acceleration edges; none at a junction merge). A merging
        car on that lane has changed onto the main road's lane."""
        merge_edges = set(self.merge.edge_ids)
        return {lane.edge_id: lane.lane_index for lane in self.main.edges if lane.edge_id in merge_edges}

    @property
    def fastest_limit_mps(self) -> float:
        """The highest speed limit on either route, the road after the merge included (the cars' top
        speed must reach it)."""
        return max(lane.speed_limit_mps for side in ("main", "merge") for lane in self.route(side))

    def route_edge_ids(self, side: Side) -> tuple[str, ...]:
        """The ordinary edges of ``side``'s route, as a SUMO route file lists them."""
        return tuple(r.edge_id for r in self.route(side) if not r.internal)

    def distance_table(self, side: Side) -> dict[str, float]:
        """Edge id (junction-internal ones too) -> distance of its start to the merge point along
        ``side``'s route: a car on that edge at lane position ``pos`` is ``table[edge] - pos`` before
        the merge point (negative: past it)."""
        return {r.edge_id: r.start_to_merge_m for r in self.route(side)}

    def as_merge_net(self) -> MergeNet:
        """The site as the engine's ``MergeNet`` today (two one-lane roads of one edge each into one
        outgoing road); an InputError naming what differs for any other site."""
        if self.kind != "junction" or len(self.main.edges) != 1 or len(self.merge.edges) != 1:
            raise InputError(
                f"{self.path}: the merge at {self.junction_id!r} is not two single roads into one "
                f"(main {'+'.join(self.main.edge_ids)}, merge {'+'.join(self.merge.edge_ids)}, {self.kind})"
            )

        def info(lane: RouteLane, via_length_m: float) -> RoadInfo:
            return RoadInfo(lane.edge_id, lane.length_m, lane.speed_limit_mps, lane.priority, via_length_m)

        return MergeNet(
            self.path,
            info(self.main.edges[0], self.main.via_length_m),
            info(self.merge.edges[0], self.merge.via_length_m),
            info(self.out[0], 0.0),
            self.junction_id,
        )


# -- reading lanes ----------------------------------------------------------------------------------


def _is_internal(lane: Any) -> bool:
    return str(lane.getEdge().getFunction()) == "internal"


def _via_lanes(net: Any, connection: Any) -> list[Any]:
    """The junction-internal lanes a connection drives through (several where netconvert splits a
    junction lane at an internal junction)."""
    lanes = []
    via = connection.getViaLaneID()
    while via:
        lane = net.getLane(via)
        lanes.append(lane)
        onward = lane.getOutgoing()
        via = onward[0].getViaLaneID() if onward else ""
    return lanes


def _normal_outgoing(lane: Any) -> list[Any]:
    return [c for c in lane.getOutgoing() if c.getDirection() != _TURNAROUND]


def _normal_incoming(lane: Any) -> list[Any]:
    return [
        c
        for c in lane.getIncomingConnections()
        if not _is_internal(c.getFromLane()) and c.getDirection() != _TURNAROUND
    ]


def _trace_upstream(net: Any, lane: Any, limit_m: float) -> list[Any]:
    """``lane`` and the lanes before it (ordinary and junction-internal, upstream first), followed
    through single predecessors until they reach ``limit_m``."""
    chain = [lane]
    total = float(lane.getLength())
    seen = {lane.getID()}
    while total < limit_m:
        incoming = _normal_incoming(chain[0])
        if len(incoming) != 1:
            break
        previous = incoming[0].getFromLane()
        if previous.getID() in seen:  # a loop road
            break
        seen.add(previous.getID())
        vias = _via_lanes(net, incoming[0])
        chain[:0] = [previous, *vias]
        total += float(previous.getLength()) + sum(float(v.getLength()) for v in vias)
    return chain


def _trace_downstream(net: Any, lane: Any, limit_m: float, avoid: frozenset[str] = frozenset()) -> list[Any]:
    """``lane`` and the lanes after it, followed through single (or single straight) successors
    until they reach ``limit_m``; within ``FOLLOW_SPLIT_M`` through a split too, along the straightest
    branch. Never onto an edge of ``avoid`` (the approaches': a ring road leads back into them, and an
    edge twice on a route has no single distance to the merge point)."""
    chain = [lane]
    total = float(lane.getLength())
    seen = {lane.getID()}
    while total < limit_m:
        onward = _normal_outgoing(chain[-1])
        if len(onward) > 1:
            onward = [c for c in onward if c.getDirection() == _STRAIGHT]
        if len(onward) > 1 and total < FOLLOW_SPLIT_M:
            onward = _straightest(chain[-1], [c for c in onward if str(c.getTo().getID()) not in avoid])
        if (
            len(onward) != 1
            or onward[0].getToLane().getID() in seen
            or str(onward[0].getTo().getID()) in avoid
        ):
            break
        vias = _via_lanes(net, onward[0])
        following = onward[0].getToLane()
        seen.add(following.getID())
        chain += [*vias, following]
        total += float(following.getLength()) + sum(float(v.getLength()) for v in vias)
    return chain


def _straightest(lane: Any, onward: list[Any]) -> list[Any]:
    """The connection among ``onward`` that turns least from ``lane`` (then the highest priority, then
    the lowest lane id), alone; none of none."""
    if not onward:
        return []
    return [
        min(
            onward,
            key=lambda c: (
                turn_deg(lane, c.getToLane()),
                -int(c.getTo().getPriority()),
                str(c.getToLane().getID()),
            ),
        )
    ]


def _route_lanes(lanes: list[Any], end_at_m: float, downstream: bool = False) -> tuple[RouteLane, ...]:
    """``lanes`` as RouteLanes. Upstream: the last lane ends ``end_at_m`` before the merge point.
    Downstream: the first lane starts ``end_at_m`` before it (0 or negative)."""
    out: list[RouteLane] = []
    if downstream:
        start = end_at_m
        for lane in lanes:
            out.append(_route_lane(lane, start))
            start -= float(lane.getLength())
        return tuple(out)
    end = end_at_m
    for lane in reversed(lanes):
        start = end + float(lane.getLength())
        out.append(_route_lane(lane, start))
        end = start
    return tuple(reversed(out))


def _route_lane(lane: Any, start_to_merge_m: float) -> RouteLane:
    edge = lane.getEdge()
    return RouteLane(
        edge_id=str(edge.getID()),
        lane_index=int(lane.getIndex()),
        length_m=float(lane.getLength()),
        start_to_merge_m=start_to_merge_m,
        speed_limit_mps=float(lane.getSpeed()),
        priority=int(edge.getPriority()),
        lane_count=int(edge.getLaneNumber()),
        internal=_is_internal(lane),
    )


# -- finding merges ---------------------------------------------------------------------------------


def _drivable(lane: Any) -> bool:
    """A lane cars may use (an OSM import's sidewalks and bike lanes end everywhere: no merges)."""
    return bool(lane.allows(VEHICLE_CLASS))


def _signalled(node: Any) -> bool:
    kind = str(node.getType())
    return kind.startswith("traffic_light") or kind.startswith("rail_")


def _leads_only_to(edge: Any, target: Any) -> bool:
    """Every connection of ``edge`` (turnarounds aside) goes onto ``target``: the road ends in the merge."""
    targets = {c.getTo().getID() for lane in edge.getLanes() for c in _normal_outgoing(lane)}
    return targets == {target.getID()}


def _candidates(node: Any) -> list[tuple[Any, Any, Any, bool]]:
    """(lane a, lane b, the outgoing lane, a ends without a connection) for each pair of lanes that
    become one at ``node``."""
    found = []
    outgoing = sorted(
        (
            lane
            for edge in node.getOutgoing()
            if edge.getFunction() != "internal"
            for lane in edge.getLanes()
            if _drivable(lane)
        ),
        key=lambda lane: (lane.getEdge().getID(), lane.getIndex()),
    )
    for into in outgoing:
        sources = sorted(
            (
                c.getFromLane()
                for c in _normal_incoming(into)
                if c.getFrom().getToNode() is node and _drivable(c.getFromLane())
            ),
            key=lambda lane: lane.getID(),
        )
        if len(sources) == 2:
            found.append((sources[0], sources[1], into, False))
    for edge in sorted(node.getIncoming(), key=lambda e: e.getID()):
        if edge.getFunction() == "internal":
            continue
        drivable = [lane for lane in edge.getLanes() if _drivable(lane)]
        going_on = [lane for lane in drivable if _normal_outgoing(lane)]
        for lane in drivable:
            if _normal_outgoing(lane) or not going_on:
                continue  # a lane that goes on, or the end of the network
            # The ending lane's cars change into the nearest lane that goes on (the right one first).
            neighbour = min(
                going_on, key=lambda other: (abs(other.getIndex() - lane.getIndex()), other.getIndex())
            )
            onward = _normal_outgoing(neighbour)
            straight = [c for c in onward if c.getDirection() == _STRAIGHT] if len(onward) > 1 else onward
            if len(straight) == 1:
                found.append((lane, neighbour, straight[0].getToLane(), True))
    return found


def _diverges(a: list[Any], b: list[Any]) -> int | None:
    """How many ordinary lanes back from the merge point the two chains first lie on different edges
    (0: at once, two roads), or None if they never do."""
    ordinary_a = [lane for lane in reversed(a) if not _is_internal(lane)]
    ordinary_b = [lane for lane in reversed(b) if not _is_internal(lane)]
    for k, (x, y) in enumerate(zip(ordinary_a, ordinary_b, strict=False)):
        if x.getEdge().getID() != y.getEdge().getID():
            return k
    return None


def _road_index(chain: list[Any], back: int) -> int:
    """Index in ``chain`` of the ordinary lane ``back`` ordinary lanes before the last one."""
    ordinary = [i for i, lane in enumerate(chain) if not _is_internal(lane)]
    return ordinary[len(ordinary) - 1 - back]


def _rank(chain: list[Any], index: int, into: Any) -> tuple[int, float, float]:
    """Right of way of an approach's own road, highest for the main road: SUMO priority, speed limit,
    then how straight it runs on (into the next lane on its chain, or the outgoing lane)."""
    lane = chain[index]
    onward = next((x for x in chain[index + 1 :] if not _is_internal(x)), into)
    return (int(lane.getEdge().getPriority()), float(lane.getSpeed()), -turn_deg(lane, onward))


def _site(
    net: Any,
    path: Path,
    node: Any,
    candidate: tuple[Any, Any, Any, bool],
    upstream_m: float,
    downstream_m: float,
) -> MergeSite | None:
    a, b, into, a_ends = candidate
    out_edge = into.getEdge()
    if not (_leads_only_to(a.getEdge(), out_edge) and _leads_only_to(b.getEdge(), out_edge)):
        return None  # the roads also lead elsewhere: a crossing or a fork, not a merge
    kind: MergeKind = "junction" if a.getEdge() is not b.getEdge() else "lane_drop"
    chain_a, chain_b = _trace_upstream(net, a, upstream_m), _trace_upstream(net, b, upstream_m)
    back = _diverges(chain_a, chain_b)
    if back is None and kind == "lane_drop":
        chain_a, chain_b = _trace_upstream(net, a, MAX_TRACE_M), _trace_upstream(net, b, MAX_TRACE_M)
        back = _diverges(chain_a, chain_b)
    if back is None:
        return None  # a lane the road loses: both lanes come from the same road
    index_a, index_b = _road_index(chain_a, back), _road_index(chain_b, back)
    b_conn = next(c for c in _normal_outgoing(b) if c.getToLane() is into)
    through_b = _route_lanes(_via_lanes(net, b_conn), 0.0, downstream=True)
    if a_ends:
        through_a = through_b  # its cars change into b's lane before the merge point
    else:
        a_conn = next(c for c in _normal_outgoing(a) if c.getToLane() is into)
        through_a = _route_lanes(_via_lanes(net, a_conn), 0.0, downstream=True)
    approach_a = Approach(_route_lanes(chain_a, 0.0), through_a, index_a, ending=a_ends)
    approach_b = Approach(_route_lanes(chain_b, 0.0), through_b, index_b)
    if a_ends or _rank(chain_b, index_b, into) >= _rank(chain_a, index_a, into):
        main, merge = approach_b, approach_a
    else:
        main, merge = approach_a, approach_b
    approach_edges = frozenset(str(x.getEdge().getID()) for x in (*chain_a, *chain_b))
    out = _route_lanes(_trace_downstream(net, into, downstream_m, approach_edges), 0.0, downstream=True)
    return MergeSite(path, str(node.getID()), kind, main, merge, out)


def detect_merges(
    path: str | Path,
    upstream_m: float = DEFAULT_UPSTREAM_M,
    downstream_m: float = DEFAULT_DOWNSTREAM_M,
    *,
    none_is_error: bool = False,
) -> tuple[MergeSite, ...]:
    """Every merge in the net at ``path``, one per junction, sorted by junction id. Signalled
    junctions are left out: a signal, not the cars, decides who goes there. ``none_is_error``: a net
    without a merge is an InputError saying what the net has (the net is read once: a city takes
    seconds)."""
    p = Path(path)
    net = load_sumo_net(p)
    sites = []
    for node in sorted(net.getNodes(), key=lambda n: n.getID()):
        if _signalled(node):
            continue
        for candidate in _candidates(node):
            site = _site(net, p, node, candidate, upstream_m, downstream_m)
            if site is not None:
                sites.append(site)
                break  # one merge per junction: the first outgoing lane's
    if none_is_error and not sites:
        raise InputError(
            f"{p}: no merge (two roads' lanes becoming one at an unsignalled junction, or an on-ramp's "
            f"acceleration lane) in the network: {_net_summary(net)}"
        )
    return tuple(sites)


# -- describing and choosing ------------------------------------------------------------------------


def _limits(lanes: tuple[RouteLane, ...]) -> str:
    speeds = sorted({lane.speed_limit_mps for lane in lanes if not lane.internal})
    return f"{speeds[0]:g} m/s" if len(speeds) == 1 else f"{speeds[0]:g}-{speeds[-1]:g} m/s"


def describe_approach(approach: Approach) -> str:
    edges = "+".join(f"{lane.edge_id}[{lane.lane_index}]" for lane in approach.edges)
    return (
        f"{edges} {approach.length_m:.1f} m, {_limits(approach.lanes)}, priority {approach.road.priority}"
        + (", lane ends" if approach.ending else "")
    )


def describe_site(site: MergeSite) -> str:
    """One line: junction, kind, both approaches (edges[controlled lane], length to the merge point,
    limits, priority) and the outgoing road."""
    out_edges = "+".join(lane.edge_id for lane in site.out if not lane.internal)
    out_length = sum(lane.length_m for lane in site.out if not lane.internal)
    kind = "lane drop" if site.kind == "lane_drop" else "junction"
    return (
        f"{site.junction_id} ({kind}): main {describe_approach(site.main)}; "
        f"merge {describe_approach(site.merge)}; out {out_edges} {out_length:.1f} m, {_limits(site.out)}"
    )


def describe_net(path: str | Path) -> str:
    """What a net without a merge has: its roads and the junctions where several roads meet."""
    return _net_summary(load_sumo_net(path))


def _net_summary(net: Any) -> str:
    edges = [e for e in net.getEdges() if e.getFunction() != "internal"]
    meeting = []
    for node in sorted(net.getNodes(), key=lambda n: n.getID()):
        n_in = sum(1 for e in node.getIncoming() if e.getFunction() != "internal")
        n_out = sum(1 for e in node.getOutgoing() if e.getFunction() != "internal")
        if n_in >= 2:
            # A signalled one is said to be left out: a net that is a merge but for its signal
            # (a traffic_light T-junction) must not read as a net without any junction to use.
            kind = f"a signal ({node.getType()}), left out" if _signalled(node) else str(node.getType())
            # A road that ends here without a connection onward (no car can drive on) is why a
            # junction that looks like a merge is none: name it.
            stuck = sorted(
                str(e.getID())
                for e in node.getIncoming()
                if e.getFunction() != "internal" and not any(_normal_outgoing(lane) for lane in e.getLanes())
            )
            dead = f"; {', '.join(stuck)} lead(s) nowhere from it: route not drivable" if stuck else ""
            meeting.append(f"{node.getID()} ({kind}, {n_in} in, {n_out} out{dead})")
    listed = ", ".join(meeting[:MAX_LISTED]) + (
        f" and {len(meeting) - MAX_LISTED} more" if len(meeting) > MAX_LISTED else ""
    )
    return f"{len(edges)} roads, {len(net.getNodes())} junctions; " + (
        f"junctions where several roads meet: {listed}" if meeting else "no junction where two roads meet"
    )


def choose_merge(
    path: str | Path,
    junction: str | None = None,
    upstream_m: float = DEFAULT_UPSTREAM_M,
    downstream_m: float = DEFAULT_DOWNSTREAM_M,
    flag: str = "--junction",
) -> MergeSite:
    """The merge at ``junction``, or the net's only merge; an InputError listing what was found when
    there is none, several and no ``junction``, or no merge at ``junction``."""
    sites = detect_merges(path, upstream_m, downstream_m, none_is_error=True)
    # A city has dozens of on-ramps: name them all, describe the first few (nets inspect lists all).
    more = (
        f"; and {len(sites) - MAX_DESCRIBED} more (idas-sumo nets inspect {path})"
        if len(sites) > MAX_DESCRIBED
        else ""
    )
    found = "; ".join(describe_site(s) for s in sites[:MAX_DESCRIBED]) + more
    if junction is None:
        if len(sites) == 1:
            return sites[0]
        ids = ", ".join(s.junction_id for s in sites)
        raise InputError(f"{path}: {len(sites)} merges ({ids}); choose one with {flag} ID: {found}")
    for site in sites:
        if site.junction_id == junction:
            return site
    raise InputError(f"{flag} {junction}: no merge at that junction in {path}; its merges: {found}")


def as_site(net: MergeSite | MergeNet | str | Path, junction: str | None = None) -> MergeSite:
    """The merge site the engine and the backends run on: a ``MergeSite`` as is, a ``MergeNet`` (the
    T-junction's adapter, ``read_merge_net``) as the site detected at its junction, a path as
    ``choose_merge(path, junction)``."""
    if isinstance(net, MergeSite):
        return net
    if isinstance(net, MergeNet):
        return choose_merge(net.path, net.junction_id)
    return choose_merge(net, junction)


__all__ = [
    "DEFAULT_DOWNSTREAM_M",
    "DEFAULT_UPSTREAM_M",
    "Approach",
    "MergeSite",
    "RouteLane",
    "as_site",
    "choose_merge",
    "describe_net",
    "describe_site",
    "detect_merges",
]
