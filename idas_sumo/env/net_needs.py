"""What the scenarios need of a merge net's road lengths, and the check that refuses a net without it.

Merge detection (``sim/merge_detect.py``) finds where two roads join. A merge can still be useless: with
a 1 m road after the merge no car reaches the finish line before it leaves the net; with 100 km roads no
car reaches the merge before the timeout. Either run would end with exit
0 and a table of 0 % that means nothing, so ``train`` and ``evaluate`` refuse such a net up front.

The bounds come from what an episode uses:

- an incoming road may be as short as it is: the random starts lie on what it has (``[car length,
  start_range_m]`` from its start, counted along its edges, a car to spare before the merge point;
  on a shorter road the cars that do not fit enter later at its start, ``generate_scenario``), and on
  one shorter than the sensor range (``VISIBILITY_M``) the grid cells beyond its start stay empty,
  as no car can be there (SUMO's own example nets have 11 m and 26 m approaches);
- the outgoing road holds the finish line (``FINISH_DISTANCE_PAST_MERGE_M`` past the merge point, the
  merging zone's far edge) plus a car length, and the sensor range ahead of the merge point: a car
  must not leave the net before it counts as finished;
- every speed limit is positive and at most the robot cars' top speed (``ROBOT_MAX_SPEED_MPS``,
  SUMO's default; the controlled cars' top speed follows the net, ``controlled_top_speed``);
- a car at the very start of an incoming road, driving at the speed limits, reaches the finish line
  within the episode (the evaluation's ``DEFAULT_MAX_EPISODE_S`` or the run's own, if longer): a
  shorter run (a smoke test) may time out by choice, a road too long to drive may not;
- and the other way round, the run's episodes are long enough for the car starting nearest the merge
  to finish (else every episode times out).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from idas_sumo.env.config import DEFAULT_MAX_EPISODE_S
from idas_sumo.env.layout import VISIBILITY_M
from idas_sumo.env.rewards import FINISH_DISTANCE_PAST_MERGE_M
from idas_sumo.errors import InputError
from idas_sumo.sim.backend import ROBOT_MAX_SPEED_MPS, VEHICLE_LENGTH_M
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.netgen import MergeNet

__all__ = ["RoadNeeds", "check_road_lengths", "road_needs"]


@dataclass(frozen=True)
class RoadNeeds:
    """Bounds on a merge net's road lengths (``road_needs`` makes them)."""

    start_range_m: float | None
    """Random starts lie up to this far from an incoming road's start (None: the scenarios place
    their cars themselves, and ``check_against_net`` checks those positions against the roads)."""
    run_episode_s: float
    """The run's own episode length (``max_episode_s``)."""
    source: str = "max_episode_s"
    """Where ``run_episode_s`` comes from, for messages (a config file)."""

    @property
    def episode_s(self) -> float:
        """A car at an incoming road's start must reach the finish line within this, at the speed
        limits: the evaluation's episode, or the run's own if longer (a shorter run, a smoke test,
        may time out by choice)."""
        return max(self.run_episode_s, DEFAULT_MAX_EPISODE_S)

    @property
    def min_out_m(self) -> float:
        return max(FINISH_DISTANCE_PAST_MERGE_M + VEHICLE_LENGTH_M, VISIBILITY_M)

    def max_incoming_m(self, road: _Road, out: _Road) -> float:
        """The longest ``road`` on which a car starting a car length in reaches the finish in time."""
        to_finish_s = FINISH_DISTANCE_PAST_MERGE_M / out.speed_limit_mps
        return VEHICLE_LENGTH_M + road.speed_limit_mps * max(self.episode_s - to_finish_s, 0.0)


def road_needs(start_range_m: float | None, max_episode_s: float, source: str = "max_episode_s") -> RoadNeeds:
    """The bounds for scenarios whose random starts reach ``start_range_m`` from a road's start (None
    for scenarios that place their cars themselves) and whose episodes last ``max_episode_s`` (set
    in ``source``)."""
    return RoadNeeds(start_range_m, max_episode_s, source)


@dataclass(frozen=True)
class _Road:
    """What the check needs of a road: its edges (for messages), length to the merge point (from it,
    for the outgoing road) and speed limit."""

    edges: str
    length_m: float
    speed_limit_mps: float


@dataclass(frozen=True)
class _Roads:
    path: Path
    main: _Road
    merge: _Road
    out: _Road


def _roads(net: MergeSite | MergeNet) -> _Roads:
    """A site's approaches (their length to the merge point, their own road's limit) and the road after
    the merge (how far the shorter route goes on past the merge point, the first outgoing lane's
    limit); a ``MergeNet``'s three edges as they are."""
    if isinstance(net, MergeNet):
        return _Roads(
            net.path,
            *(_Road(r.edge_id, r.length_m, r.speed_limit_mps) for r in (net.main, net.merge, net.out)),
        )

    def approach(side: Literal["main", "merge"]) -> _Road:
        a = net.approach(side)
        return _Road("+".join(a.edge_ids), a.length_m, a.road.speed_limit_mps)

    past = min(
        net.route(side)[-1].length_m - net.route(side)[-1].start_to_merge_m for side in ("main", "merge")
    )
    out_edges = "+".join(lane.edge_id for lane in net.out if not lane.internal)
    return _Roads(
        net.path, approach("main"), approach("merge"), _Road(out_edges, past, net.out[0].speed_limit_mps)
    )


def check_road_lengths(site: MergeSite | MergeNet, needs: RoadNeeds) -> None:
    """An InputError naming the net, the road, its length and the bounds with their reasons, for the
    first road that misses them; nothing for a usable net."""
    net = _roads(site)
    for what, road in (("main", net.main), ("merge", net.merge), ("outgoing", net.out)):
        # Checked first: the bounds below divide by the limits. A car cannot drive a limit above its
        # own top speed: SUMO refused such a start ("departure speed too high") mid-run, exit 1.
        if not 0.0 < road.speed_limit_mps <= ROBOT_MAX_SPEED_MPS:
            raise InputError(
                f"{net.path}: the {what} road {road.edges!r} has a speed limit of {road.speed_limit_mps:g} m/s; "
                f"the cars need one above 0 and at most {ROBOT_MAX_SPEED_MPS:.2f} m/s (their top speed)"
            )
    for what, road in (("main", net.main), ("merge", net.merge)):
        hi = needs.max_incoming_m(road, net.out)
        if road.length_m > hi:
            raise InputError(
                f"{net.path}: the {what} road {road.edges!r} is {road.length_m:g} m long; the scenarios need "
                f"at most {hi:.0f} m (from its start a car must reach the finish {FINISH_DISTANCE_PAST_MERGE_M:g} m "
                f"past the merge within {needs.episode_s:g} s at the speed limits)"
            )
    if net.out.length_m < needs.min_out_m:
        raise InputError(
            f"{net.path}: the outgoing road {net.out.edges!r} is {net.out.length_m:g} m long; the "
            f"scenarios need at least {needs.min_out_m:g} m (the finish {FINISH_DISTANCE_PAST_MERGE_M:g} m "
            f"past the merge plus a {VEHICLE_LENGTH_M:g} m car, and the {VISIBILITY_M:g} m sensor range ahead)"
        )
    for what, road in (("main", net.main), ("merge", net.merge)):
        # The car starting nearest the merge (or at it, for scenario files) must be able to finish:
        # 0.5 s episodes ended every run as timeouts (0 %, exit 0), 0.01 s ones in a ZeroDivisionError.
        nearest_m = 0.0 if needs.start_range_m is None else max(road.length_m - needs.start_range_m, 0.0)
        need_s = nearest_m / road.speed_limit_mps + FINISH_DISTANCE_PAST_MERGE_M / net.out.speed_limit_mps
        if needs.run_episode_s < need_s:
            raise InputError(
                f"{needs.source}: max_episode_s = {needs.run_episode_s:g} s is shorter than the {need_s:.1f} s "
                f"a car starting nearest the merge on the {what} road of {net.path} needs to reach the finish "
                f"{FINISH_DISTANCE_PAST_MERGE_M:g} m past it at the speed limits: every episode would time out"
            )
