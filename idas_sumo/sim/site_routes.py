"""SUMO route files for cars driving through a detected merge (``MergeSite``), placed by their distance
to the merge point.

A car on the ``main`` or ``merge`` approach ``d`` metres before the merge point departs on the ordinary
lane of its approach that holds that point (``Approach.lane_at``), on the approach's lane of that edge
(``departLane``: on a two-lane highway the lane that merges, unless the car asks for its neighbour),
and drives the
approach's remaining edges, then the outgoing ones. Each car carries its own route, so cars starting on
different edges of one approach need no route ids.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

from idas_sumo.errors import InputError
from idas_sumo.io_utils import atomic_open
from idas_sumo.sim.backend import VEHICLE_LENGTH_M
from idas_sumo.sim.merge_detect import MergeSite, Side

SITE_VTYPE = "site_car"
"""The vType of cars without one of their own: SUMO's default driver, the package's car length, no
random speed factor (a run is the same on every machine)."""
DEFAULT_VTYPE_XML = f'<vType id="{SITE_VTYPE}" length="{VEHICLE_LENGTH_M}" speedDev="0"/>'


@dataclass(frozen=True)
class SiteVehicle:
    """A car to depart on one approach of a merge."""

    id: str
    side: Side
    dist_to_merge_m: float
    """How far before the merge point its front bumper starts, along its approach."""
    depart_s: float = 0.0
    speed_mps: float = 0.0
    vtype: str = SITE_VTYPE
    lane_index: int | None = None
    """Its lane on the edge it departs from: None for the approach's lane (the one that merges), or
    another lane of that edge (a car on the highway's left lane, driven by SUMO)."""


def route_xml(
    site: MergeSite, vehicles: Sequence[SiteVehicle], vtypes_xml: Sequence[str] = (DEFAULT_VTYPE_XML,)
) -> str:
    """The route file's text: ``vtypes_xml`` (one ``<vType .../>`` each), then the vehicles sorted by
    departure; an InputError for a car whose start is not on its approach or a repeated id."""
    seen: set[str] = set()
    lines = ["<routes>", *(f"  {v}" for v in vtypes_xml)]
    for vehicle in sorted(vehicles, key=lambda v: (v.depart_s, v.id)):
        if vehicle.id in seen:
            raise InputError(f"vehicle {vehicle.id!r}: the id is used twice")
        seen.add(vehicle.id)
        if vehicle.side not in ("main", "merge"):
            raise InputError(f"vehicle {vehicle.id!r}: side {vehicle.side!r} is not main or merge")
        try:
            lane, pos = site.approach(vehicle.side).lane_at(vehicle.dist_to_merge_m)
        except InputError as err:
            raise InputError(f"vehicle {vehicle.id!r}: {err}") from None
        depart_lane = lane.lane_index if vehicle.lane_index is None else vehicle.lane_index
        if not 0 <= depart_lane < lane.lane_count:
            raise InputError(
                f"vehicle {vehicle.id!r}: lane {depart_lane} of edge {lane.edge_id!r}, which has {lane.lane_count} lanes"
            )
        edges = site.route_edge_ids(vehicle.side)
        onward = edges[edges.index(lane.edge_id) :]
        lines += [
            f'  <vehicle id={quoteattr(vehicle.id)} type={quoteattr(vehicle.vtype)} depart="{vehicle.depart_s:.2f}" '
            f'departLane="{depart_lane}" departPos="{pos:.3f}" departSpeed="{vehicle.speed_mps:.3f}">',
            f'    <route edges="{" ".join(onward)}"/>',
            "  </vehicle>",
        ]
    lines.append("</routes>")
    return "\n".join(lines) + "\n"


def write_routes(
    site: MergeSite,
    vehicles: Sequence[SiteVehicle],
    path: str | Path,
    vtypes_xml: Sequence[str] = (DEFAULT_VTYPE_XML,),
) -> Path:
    """Write ``route_xml`` to ``path`` atomically; the path."""
    out = Path(path)
    text = route_xml(site, vehicles, vtypes_xml)
    with atomic_open(out) as f:
        f.write(text)
    return out


__all__ = ["DEFAULT_VTYPE_XML", "SITE_VTYPE", "SiteVehicle", "route_xml", "write_routes"]
