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


def test_copies_of_a_45_degree_merge_drive_alike(tmp_path: Path) -> None:
    """The junction outline is not pinned and differs in some copies of a 45 degree net; the same cars
    must still drive the same way in every copy (SUMO's collision check on junctions included)."""
    import subprocess

    from idas_sumo.sim.netgen import sumo_binary

    source = generate_net(tmp_path / "a45.net.xml", THRESHOLD_GEOMETRIES["angle-45"])
    built = build_copies(source, COPIES, tmp_path / "cache")
    root = ET.parse(built).getroot()
    junctions = {j.get("id", ""): j for j in root.iter("junction")}
    outlines = {jid: j.get("shape", "") for jid, j in junctions.items()}
    spacing = float(junctions["c01_main_start"].get("y", "")) - float(
        junctions["c00_main_start"].get("y", "")
    )

    def local(shape: str, k: int) -> str:
        return " ".join(
            f"{p.split(',')[0]},{float(p.split(',')[1]) - k * spacing:.2f}" for p in shape.split()
        )

    junction = outlines["c00_merge_point"]
    others = [k for k in range(1, COPIES) if local(outlines[f"c{k:02d}_merge_point"], k) != junction]
    assert others  # the case this test is about: some copy's outline differs from copy 0's
    cars = []
    for i in range(6):  # main and merging cars reach the merge point close together
        cars += [(2.0 * i, f"m{i}", "main", 10 + i), (2.0 * i + 0.5, f"r{i}", "merge", 12 - i)]
    vehicles = [
        f'<vehicle id="c{k:02d}_{vid}" type="t" depart="{t}" departSpeed="{v}">'
        f'<route edges="c{k:02d}_{road} c{k:02d}_out"/></vehicle>'
        for t, vid, road, v in sorted(cars)
        for k in [0, *others]
    ]
    routes = tmp_path / "r.rou.xml"
    routes.write_text('<routes><vType id="t" sigma="0" speedDev="0"/>' + "".join(vehicles) + "</routes>")
    fcd = tmp_path / "fcd.xml"
    sumo = [str(sumo_binary("sumo")), "-n", str(built), "-r", str(routes), "--step-length", "0.1"]
    checks = ["--collision.check-junctions", "true", "--collision.action", "remove", "--end", "60"]
    out = ["--fcd-output", str(fcd), "--no-step-log", "true"]
    subprocess.run([*sumo, *checks, *out], check=True, capture_output=True)
    trajectories: dict[str, list[tuple[str, ...]]] = {}
    for step in ET.parse(fcd).getroot().iter("timestep"):
        for car in step.iter("vehicle"):
            prefix, vid = car.get("id", "")[:4], car.get("id", "")[4:]
            lane = car.get("lane", "").replace(prefix, "")
            row = (step.get("time", ""), vid, lane, car.get("pos", ""), car.get("speed", ""))
            trajectories.setdefault(prefix, []).append(row)
    assert len(trajectories["c00_"]) > 100
    assert any(":merge_point_0" in row[2] for row in trajectories["c00_"])  # they crossed the junction
    for k in others:
        assert trajectories[f"c{k:02d}_"] == trajectories["c00_"]
