"""Every copy of a multi-copy net is faithful on geometries where netconvert sits at a threshold.

netconvert recomputes junction-internal lanes when it reads a net; on a copy shifted by its offset the
coordinates round differently, and a generated 45 degree merge used to get a 7.70 m internal lane in
some of its 16 copies for the source's 7.49 m (issue 17). ``sim/multinet.py`` now pins each internal
lane to the source's; these nets also guard what the pinning leaves alone (split internal lanes, the
junctions' shapes).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from idas_sumo.sim.multinet import build_copies, global_edge_id, pin_internal_lanes
from idas_sumo.sim.netgen import NetParams, generate_net
from idas_sumo.sim.sample_nets import build_sample_net

pytestmark = pytest.mark.sumo

COPIES = 16

THRESHOLD_GEOMETRIES = {
    "angle-45": NetParams(angle_deg=45.0),
    "angle-45-roads-20": NetParams(20.0, 20.0, 20.0, angle_deg=45.0),
    "angle-45-zipper": NetParams(angle_deg=45.0, priority="equal"),
}
"""Generated nets whose 16-copy net was not faithful before the internal lanes were pinned: of the
whole angles 5-90 (roads 250/250/150, 20/20/20 and 1000/600/400 m) and some fractional ones, only
45 degrees, with either priority."""


def _lanes(path: Path) -> dict[str, tuple[str, str]]:
    """Lane id -> (length, speed) as the file writes them (what SUMO reads)."""
    root = ET.parse(path).getroot()
    return {lane.get("id", ""): (lane.get("length", ""), lane.get("speed", "")) for lane in root.iter("lane")}


@pytest.mark.parametrize("name", sorted(THRESHOLD_GEOMETRIES))
def test_a_threshold_geometry_builds_faithful_copies(name: str, tmp_path: Path) -> None:
    source = generate_net(tmp_path / f"{name}.net.xml", THRESHOLD_GEOMETRIES[name])
    built = build_copies(source, COPIES, tmp_path / "cache")  # raised SimulationError before the fix
    want = _lanes(source)
    got = _lanes(built)
    internal = [lane for lane in want if lane.startswith(":")]
    assert len(internal) == 2
    for k in range(COPIES):
        prefix = f"c{k:02d}_"
        assert {lane: got[global_edge_id(prefix, lane)] for lane in want} == want


@pytest.mark.parametrize("name", ["crossing", "onramp", "two_merges"])
def test_sample_nets_stay_faithful(name: str, tmp_path: Path) -> None:
    """What pinning leaves alone: a crossing's left turns (internal lanes split by an internal
    junction) and nets whose edges take their length from where the junction's shape cuts them."""
    source = build_sample_net(name, tmp_path / f"{name}.net.xml")
    build_copies(source, COPIES, tmp_path / "cache")  # check_copies ran inside


def test_pinning_copies_each_internal_lane_onto_its_connection(tmp_path: Path) -> None:
    source = generate_net(tmp_path / "a45.net.xml", NetParams(angle_deg=45.0))
    pinned = tmp_path / "pinned.net.xml"
    pin_internal_lanes(source, pinned)
    root = ET.parse(pinned).getroot()
    lanes = {lane.get("id"): lane for lane in root.iter("lane")}
    through = [c for c in root.iter("connection") if not c.get("from", "").startswith(":")]
    assert len(through) == 2
    for connection in through:
        lane = lanes[connection.get("via")]
        assert [connection.get(a) for a in ("shape", "length", "speed")] == [
            lane.get(a) for a in ("shape", "length", "speed")
        ]
    assert _lanes(pinned) == _lanes(source)  # only connections gain attributes
