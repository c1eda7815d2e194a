"""Merge detection on SUMO nets built here from plain XML: the generated T-junction, an on-ramp with an
acceleration lane, a net with two merges (``--junction`` chooses), nets without a merge; routes through a
detected merge."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
from conftest import run_cli

from idas_sumo.errors import InputError
from idas_sumo.sim.merge_detect import Approach, MergeSite, choose_merge, detect_merges
from idas_sumo.sim.netgen import NetParams, generate_net, read_merge_net
from idas_sumo.sim.sample_nets import HIGHWAY_SPEED_MPS, RAMP_SPEED_MPS, build_plain_net, build_sample_net
from idas_sumo.sim.site_routes import SiteVehicle, route_xml, write_routes


@pytest.fixture(scope="session")
def sample_nets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("sample_nets")
    names = ("onramp", "two_merges", "crossing", "straight")
    return {name: build_sample_net(name, folder / f"{name}.net.xml") for name in names}


def _check_distances(site: MergeSite) -> None:
    """Along each route, every lane starts where the one before it ends, measured to the merge point."""
    for side in ("main", "merge"):
        route = site.route(side)
        for before, after in itertools.pairwise(route):
            assert before.start_to_merge_m - before.length_m == pytest.approx(
                after.start_to_merge_m, abs=1e-6
            )
        approach = site.approach(side)
        assert approach.lanes[-1].start_to_merge_m == pytest.approx(approach.lanes[-1].length_m)
        assert route[len(approach.lanes)].start_to_merge_m == 0.0  # the junction starts at the merge point


# -- the generated T-junction: the same description as read_merge_net ---------------------------------


@pytest.mark.parametrize(
    "params",
    [
        NetParams(),
        NetParams(main_length_m=400.0, merge_length_m=180.0, out_length_m=260.0, angle_deg=60.0),
        NetParams(priority="equal", main_speed_mps=15.0, merge_speed_mps=15.0, angle_deg=15.0),
    ],
    ids=["paper", "long-steep", "equal-priority"],
)
def test_generated_t_junction_matches_read_merge_net(tmp_path: Path, params: NetParams) -> None:
    path = generate_net(tmp_path / "t.net.xml", params)
    sites = detect_merges(path)
    assert len(sites) == 1
    site = sites[0]
    assert site.kind == "junction"
    assert site.as_merge_net() == read_merge_net(path)
    assert site.main.edge_ids == ("main",) and site.merge.edge_ids == ("merge",)
    assert [lane.edge_id for lane in site.out if not lane.internal] == ["out"]
    assert site.main.length_m == params.main_length_m and site.merge.length_m == params.merge_length_m
    _check_distances(site)


def test_shipped_net_matches_read_merge_net(net_path: Path) -> None:
    assert choose_merge(net_path).as_merge_net() == read_merge_net(net_path)


# -- the on-ramp: a two-lane highway, a one-lane ramp, an acceleration lane ---------------------------


def test_onramp_test_net_is_what_it_claims(sample_nets: dict[str, Path]) -> None:
    import sumolib

    net = sumolib.net.readNet(str(sample_nets["onramp"]))
    hw_in, ramp, accel, hw_out = (net.getEdge(e) for e in ("hw_in", "ramp", "accel", "hw_out"))
    assert (hw_in.getLaneNumber(), ramp.getLaneNumber(), accel.getLaneNumber(), hw_out.getLaneNumber()) == (
        2,
        1,
        3,
        2,
    )
    assert (hw_in.getSpeed(), ramp.getSpeed()) == (HIGHWAY_SPEED_MPS, RAMP_SPEED_MPS)
    # Curved: the lanes bend (more than two shape points, headings differ along the lane).
    for edge in (hw_in, ramp, hw_out):
        shape = edge.getLanes()[0].getShape()
        headings = {round(math.atan2(b[1] - a[1], b[0] - a[0]), 2) for a, b in itertools.pairwise(shape)}
        assert len(shape) > 2 and len(headings) > 2, edge.getID()
    # The acceleration lane ends: no connection onward from accel_0.
    assert accel.getLanes()[0].getOutgoing() == []


def test_onramp_acceleration_lane_is_detected(sample_nets: dict[str, Path]) -> None:
    site = choose_merge(sample_nets["onramp"])
    assert (site.junction_id, site.kind) == ("drop", "lane_drop")
    main, merge = site.main, site.merge
    assert main.edge_ids == ("hw_in", "accel") and [x.lane_index for x in main.edges] == [0, 1]
    assert merge.edge_ids == ("ramp", "accel") and [x.lane_index for x in merge.edges] == [0, 0]
    assert merge.ending and not main.ending
    assert (main.road.edge_id, merge.road.edge_id) == ("hw_in", "ramp")
    assert (main.road.priority, merge.road.priority) == (3, 1)
    assert [x.speed_limit_mps for x in main.edges] == [HIGHWAY_SPEED_MPS, HIGHWAY_SPEED_MPS]
    assert [x.speed_limit_mps for x in merge.edges] == [RAMP_SPEED_MPS, HIGHWAY_SPEED_MPS]
    # Ramp cars change into the highway's lane: both routes cross the junction on the same lane.
    assert main.through == merge.through and main.through[0].edge_id == ":drop_0"
    assert [(x.edge_id, x.lane_index) for x in site.out if not x.internal] == [("hw_out", 0)]
    _check_distances(site)
    # The acceleration edge lies between the gore and the merge point on both routes.
    assert (
        site.distance_table("main")["accel"]
        == site.distance_table("merge")["accel"]
        == main.edges[-1].length_m
    )


_RAMP_NODES = (
    '<nodes><node id="a" x="-500" y="0"/><node id="r" x="-400" y="-100"/><node id="g" x="0" y="0"/>'
    '<node id="m" x="100" y="0"/><node id="d" x="250" y="0"/><node id="e" x="600" y="0"/></nodes>'
)
_RAMP_EDGES = (
    '<edge id="hw" from="a" to="g" numLanes="2" speed="33" priority="3"/>'
    '<edge id="ramp" from="r" to="g" numLanes="1" speed="22" priority="1"/>'
)


def test_an_acceleration_lane_over_two_edges(tmp_path: Path) -> None:
    edges = (
        f"<edges>{_RAMP_EDGES}"
        '<edge id="acc1" from="g" to="m" numLanes="3" speed="33" priority="3"/>'
        '<edge id="acc2" from="m" to="d" numLanes="3" speed="33" priority="3"/>'
        '<edge id="out" from="d" to="e" numLanes="2" speed="33" priority="3"/></edges>'
    )
    connections = (
        '<connections><connection from="ramp" to="acc1" fromLane="0" toLane="0"/>'
        '<connection from="hw" to="acc1" fromLane="0" toLane="1"/>'
        '<connection from="hw" to="acc1" fromLane="1" toLane="2"/></connections>'
    )
    site = choose_merge(build_plain_net(_RAMP_NODES, edges, connections, tmp_path / "acc2.net.xml"))
    assert (site.junction_id, site.kind) == ("d", "lane_drop")
    assert site.main.edge_ids == ("hw", "acc1", "acc2") and [x.lane_index for x in site.main.edges] == [
        0,
        1,
        1,
    ]
    assert site.merge.edge_ids == ("ramp", "acc1", "acc2") and [x.lane_index for x in site.merge.edges] == [
        0,
        0,
        0,
    ]
    assert (site.main.road.edge_id, site.merge.road.edge_id) == ("hw", "ramp")
    _check_distances(site)


def test_a_ramp_joining_a_two_lane_road_without_acceleration_lane(tmp_path: Path) -> None:
    """2 + 1 lanes into 2: netconvert joins the ramp's lane and the highway's right lane into one."""
    nodes = _RAMP_NODES.replace('<node id="m" x="100" y="0"/><node id="d" x="250" y="0"/>', "")
    edges = (
        f'<edges>{_RAMP_EDGES}<edge id="out" from="g" to="e" numLanes="2" speed="33" priority="3"/></edges>'
    )
    site = choose_merge(build_plain_net(nodes, edges, "", tmp_path / "direct.net.xml"))
    assert (site.junction_id, site.kind) == ("g", "junction")
    assert (site.main.edge_ids, site.merge.edge_ids) == (("hw",), ("ramp",))
    assert [(x.edge_id, x.lane_index) for x in (*site.main.edges, *site.merge.edges)] == [
        ("hw", 0),
        ("ramp", 0),
    ]
    assert [(x.edge_id, x.lane_index) for x in site.out if not x.internal] == [("out", 0)]
    assert site.main.through != site.merge.through  # each road crosses the junction on its own lane


def test_netconverts_guessed_acceleration_lane(tmp_path: Path) -> None:
    """An OSM import's on-ramps: ``netconvert --ramps.guess`` splits the highway after the ramp and adds
    the acceleration lane itself, under edge and junction names of its own."""
    import subprocess

    from idas_sumo.sim.netgen import sumo_binary

    nodes = tmp_path / "g.nod.xml"
    edges = tmp_path / "g.edg.xml"
    nodes.write_text(_RAMP_NODES.replace('<node id="m" x="100" y="0"/><node id="d" x="250" y="0"/>', ""))
    edges.write_text(f'<edges>{_RAMP_EDGES}<edge id="out" from="g" to="e" numLanes="2" speed="33"/></edges>')
    net = tmp_path / "guessed.net.xml"
    netconvert = [str(sumo_binary("netconvert")), "-n", str(nodes), "-e", str(edges), "-o", str(net)]
    subprocess.run(
        [*netconvert, "--ramps.guess", "true", "--no-warnings", "true"], check=True, capture_output=True
    )
    site = choose_merge(net)
    assert site.kind == "lane_drop" and site.merge.ending
    assert site.main.edge_ids[0] == "hw" and site.merge.edge_ids[0] == "ramp"
    assert site.main.edge_ids[1:] == site.merge.edge_ids[1:]  # the added acceleration edge, shared
    assert (site.main.edges[-1].lane_index, site.merge.edges[-1].lane_index) == (1, 0)
    _check_distances(site)


def test_a_lane_the_road_loses_is_no_merge(tmp_path: Path) -> None:
    """Three lanes narrowing to two, with no ramp: both lanes come from the same road."""
    nodes = (
        '<nodes><node id="a" x="0" y="0"/><node id="b" x="300" y="0"/><node id="c" x="600" y="0"/></nodes>'
    )
    edges = (
        '<edges><edge id="ab" from="a" to="b" numLanes="3" speed="30"/>'
        '<edge id="bc" from="b" to="c" numLanes="2" speed="30"/></edges>'
    )
    path = build_plain_net(nodes, edges, "", tmp_path / "drop.net.xml")
    assert detect_merges(path) == ()


def test_a_bike_lane_joining_is_no_merge(tmp_path: Path) -> None:
    """A bike path that becomes a road's bike lane, which ends: only lanes cars may use count."""
    nodes = (
        '<nodes><node id="a" x="-300" y="0"/><node id="p" x="-300" y="-60"/><node id="g" x="0" y="0"/>'
        '<node id="b" x="200" y="0"/><node id="c" x="500" y="0"/></nodes>'
    )
    edges = (
        '<edges><edge id="road" from="a" to="g" numLanes="1" speed="15"/>'
        '<edge id="bikepath" from="p" to="g" numLanes="1" speed="5" allow="bicycle"/>'
        '<edge id="shared" from="g" to="b" numLanes="2" speed="15"><lane index="0" allow="bicycle"/></edge>'
        '<edge id="onward" from="b" to="c" numLanes="1" speed="15"/></edges>'
    )
    connections = (
        '<connections><connection from="bikepath" to="shared" fromLane="0" toLane="0"/>'
        '<connection from="road" to="shared" fromLane="0" toLane="1"/></connections>'
    )
    path = build_plain_net(nodes, edges, connections, tmp_path / "bike.net.xml")
    assert detect_merges(path) == ()


def test_a_signalled_merge_is_no_merge(tmp_path: Path) -> None:
    generated = generate_net(tmp_path / "t.net.xml")
    nodes = (
        generated.with_name("t.nod.xml")
        .read_text()
        .replace(
            'id="merge_point" x="0.000" y="0.000" type="priority"',
            'id="merge_point" x="0.000" y="0.000" type="traffic_light"',
        )
    )
    assert "traffic_light" in nodes
    path = build_plain_net(nodes, generated.with_name("t.edg.xml").read_text(), "", tmp_path / "tl.net.xml")
    assert detect_merges(path) == ()
    assert detect_merges(generated) != ()


# -- two merges: --junction chooses -------------------------------------------------------------------


def test_two_merges_need_a_junction(sample_nets: dict[str, Path]) -> None:
    path = sample_nets["two_merges"]
    assert [s.junction_id for s in detect_merges(path)] == ["j1", "j2"]
    with pytest.raises(InputError) as info:
        choose_merge(path)
    message = str(info.value)
    assert str(path) in message and "2 merges (j1, j2)" in message and "--junction" in message
    second = choose_merge(path, "j2")
    assert second.junction_id == "j2"
    # Upstream of j2 the main road goes back to j1 and stops there: two lanes lead into j1_j2.
    assert second.main.edge_ids == ("j1_j2",) and second.merge.edge_ids == ("r2_j2",)
    first = choose_merge(path, "j1")
    assert first.main.edge_ids == ("a_j1",) and first.merge.edge_ids == ("r1_j1",)
    assert [x.edge_id for x in first.out if not x.internal] == ["j1_j2"]  # 392 m: past DEFAULT_DOWNSTREAM_M
    farther = choose_merge(path, "j1", downstream_m=500.0)  # on through j2, a single straight successor
    assert [x.edge_id for x in farther.out if not x.internal] == ["j1_j2", "j2_end"]
    with pytest.raises(InputError) as info:
        choose_merge(path, "j9")
    message = str(info.value)
    assert message.startswith("--junction j9:") and "j1 (junction)" in message and "j2 (junction)" in message


# -- no merge ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "fragment"),
    [("crossing", "c (priority, 4 in, 4 out)"), ("straight", "no junction where two roads meet")],
)
def test_no_merge_is_a_clear_error(sample_nets: dict[str, Path], name: str, fragment: str) -> None:
    path = sample_nets[name]
    assert detect_merges(path) == ()
    with pytest.raises(InputError) as info:
        choose_merge(path)
    message = str(info.value)
    assert message.startswith(f"{path}: no merge") and fragment in message


def test_nets_inspect_cli(sample_nets: dict[str, Path]) -> None:
    listed = run_cli("nets", "inspect", str(sample_nets["two_merges"]))
    assert listed.returncode == 0, listed.stderr
    lines = listed.stdout.strip().splitlines()
    assert [line.split()[0] for line in lines] == ["j1", "j2"]
    assert "main a_j1[0] 392.1 m, 15 m/s, priority 2" in lines[0]
    chosen = run_cli("nets", "inspect", str(sample_nets["onramp"]), "--junction", "drop")
    assert chosen.returncode == 0, chosen.stderr
    assert chosen.stdout.startswith("drop (lane drop): main hw_in[0]+accel[1]")
    assert "merge ramp_0" in chosen.stdout
    for args, fragment in (
        ((str(sample_nets["crossing"]),), "no merge"),
        (
            (str(sample_nets["two_merges"]), "--junction", "nope"),
            "--junction nope: no merge at that junction",
        ),
    ):
        bad = run_cli("nets", "inspect", *args)
        assert bad.returncode == 2
        assert len(bad.stderr.strip().splitlines()) == 1 and fragment in bad.stderr, bad.stderr


# -- routes through the chosen merge ----------------------------------------------------------------


def test_routes_place_cars_by_distance_to_the_merge(sample_nets: dict[str, Path]) -> None:
    import xml.etree.ElementTree as ET

    site = choose_merge(sample_nets["onramp"])
    accel = site.main.edges[-1].length_m
    vehicles = [
        SiteVehicle("m_far", "main", accel + 100.0),
        SiteVehicle("m_near", "main", 50.0),
        SiteVehicle("r_far", "merge", accel + 100.0),
        SiteVehicle("r_near", "merge", 50.0),
    ]
    root = ET.fromstring(route_xml(site, vehicles))
    cars = {v.get("id"): v for v in root.iter("vehicle")}
    route = {k: v.find("route").get("edges") for k, v in cars.items()}  # type: ignore[union-attr]
    assert route == {
        "m_far": "hw_in accel hw_out",
        "m_near": "accel hw_out",
        "r_far": "ramp accel hw_out",
        "r_near": "accel hw_out",
    }
    lane = {k: v.get("departLane") for k, v in cars.items()}
    assert lane == {"m_far": "0", "m_near": "1", "r_far": "0", "r_near": "0"}
    pos = {k: float(v.get("departPos", "nan")) for k, v in cars.items()}
    # 100 m before the acceleration edge, less the gore's junction lane, back from hw_in's end.
    hw_in, gore = site.main.lanes[0], site.main.lanes[1]
    assert (hw_in.edge_id, gore.internal) == ("hw_in", True)
    assert pos["m_far"] == pytest.approx(hw_in.length_m - (100.0 - gore.length_m), abs=1e-3)
    assert pos["m_near"] == pytest.approx(accel - 50.0, abs=1e-3) == pos["r_near"]


def test_routes_refuse_a_start_off_the_approach(sample_nets: dict[str, Path]) -> None:
    site = choose_merge(sample_nets["onramp"])
    beyond = site.merge.length_m + 1.0
    with pytest.raises(InputError, match="outside it"):
        route_xml(site, [SiteVehicle("far", "merge", beyond)])
    inside_gore = site.merge.edges[-1].length_m + 1.0  # on the gore's junction lane, between two edges
    with pytest.raises(InputError, match="between two of its edges"):
        route_xml(site, [SiteVehicle("gore", "merge", inside_gore)])
    with pytest.raises(InputError, match="lane 3 of edge 'hw_in', which has 2 lanes"):
        route_xml(site, [SiteVehicle("wide", "main", site.main.length_m - 1.0, lane_index=3)])
    with pytest.raises(InputError, match="used twice"):
        route_xml(site, [SiteVehicle("a", "main", 50.0), SiteVehicle("a", "merge", 60.0)])


@pytest.mark.sumo
def test_cars_on_both_approaches_reach_the_outgoing_road(
    sample_nets: dict[str, Path], tmp_path: Path
) -> None:
    import libsumo

    from idas_sumo.sim.backend import slot_taken
    from idas_sumo.sim.netgen import sumo_binary

    assert not slot_taken()
    site = choose_merge(sample_nets["onramp"])
    far = site.merge.edges[0].start_to_merge_m - 20.0  # near the start of the ramp and of the highway
    vehicles = [
        SiteVehicle(f"{side}_{d:.0f}", side, d, speed_mps=10.0)
        for side in ("main", "merge")
        for d in (far, 60.0)
    ]
    vehicles.append(SiteVehicle("left", "main", far - 30.0, speed_mps=10.0, lane_index=1))  # not merging
    routes = write_routes(site, vehicles, tmp_path / "site.rou.xml")
    out_edges = {x.edge_id for x in site.out if not x.internal}
    reached: set[str] = set()
    start_lane: dict[str, str] = {}
    libsumo.start(
        [
            str(sumo_binary("sumo")),
            "-n",
            str(site.path),
            "-r",
            str(routes),
            "--no-step-log",
            "true",
            "--no-warnings",
            "true",
        ]
    )
    try:
        for _ in range(120):  # 120 s: the farthest car drives ~650 m
            libsumo.simulationStep()
            for vid in libsumo.vehicle.getIDList():
                start_lane.setdefault(vid, libsumo.vehicle.getLaneID(vid))
                if libsumo.vehicle.getRoadID(vid) in out_edges:
                    reached.add(vid)
    finally:
        libsumo.close()
    assert start_lane == {
        "main_" + f"{far:.0f}": "hw_in_0",
        "main_60": "accel_1",
        "merge_" + f"{far:.0f}": "ramp_0",
        "merge_60": "accel_0",
        "left": "hw_in_1",
    }
    assert reached == {v.id for v in vehicles}


def test_approach_lane_at_roundtrip(sample_nets: dict[str, Path]) -> None:
    site = choose_merge(sample_nets["two_merges"], "j2")
    approach: Approach = site.main
    lane, pos = approach.lane_at(10.0)
    assert lane.edge_id == "j1_j2" and pos == pytest.approx(lane.length_m - 10.0)


def test_a_multi_copy_net_holds_each_copy_of_the_site(sample_nets: dict[str, Path], tmp_path: Path) -> None:
    """The engine runs K copies of a net in one SUMO run (sim/multinet.py): detection on the K-copy
    net finds K sites, each the source's with the copy's prefix."""
    from idas_sumo.sim.multinet import build_copies, copy_prefix, prefixed_site

    source = choose_merge(sample_nets["onramp"])
    copies = build_copies(source.path, 3, tmp_path / "cache")
    found = detect_merges(copies)
    assert found == tuple(prefixed_site(source, copy_prefix(k, 3), copies) for k in range(3))
    assert [s.junction_id for s in found] == ["c0_drop", "c1_drop", "c2_drop"]
    assert found[1].distance_table("merge")["c1_ramp"] == source.distance_table("merge")["ramp"]


def test_many_merges_are_named_and_a_few_described(tmp_path: Path) -> None:
    """Six side roads joining one road: the message names all six, describes four."""
    n = 6
    nodes = "".join(
        f'<node id="j{k}" x="{300 * (k + 1)}" y="0"/><node id="s{k}" x="{300 * (k + 1) - 150}" y="-150"/>'
        for k in range(n)
    )
    edges = "".join(
        f'<edge id="in{k}" from="{"a" if k == 0 else f"j{k - 1}"}" to="j{k}" numLanes="1" speed="15" priority="2"/>'
        f'<edge id="side{k}" from="s{k}" to="j{k}" numLanes="1" speed="15" priority="1"/>'
        for k in range(n)
    )
    path = build_plain_net(
        f'<nodes><node id="a" x="0" y="0"/>{nodes}<node id="z" x="{300 * (n + 1)}" y="0"/></nodes>',
        f'<edges>{edges}<edge id="last" from="j{n - 1}" to="z" numLanes="1" speed="15" priority="2"/></edges>',
        "",
        tmp_path / "six.net.xml",
    )
    with pytest.raises(InputError) as info:
        choose_merge(path)
    message = str(info.value)
    assert f"6 merges ({', '.join(f'j{k}' for k in range(n))})" in message
    assert message.count("(junction): main") == 4 and "and 2 more (idas-sumo nets inspect" in message


def test_with_equal_priority_and_limits_the_straight_road_is_main(tmp_path: Path) -> None:
    """A zipper merge whose side road's id sorts first: the straight road is still the main one."""
    nodes = (
        '<nodes><node id="s" x="-200" y="-120"/><node id="w" x="-250" y="0"/>'
        '<node id="m" x="0" y="0" type="zipper"/><node id="e" x="200" y="0"/></nodes>'
    )
    edges = (
        '<edges><edge id="a_side" from="s" to="m" numLanes="1" speed="15" priority="1"/>'
        '<edge id="b_straight" from="w" to="m" numLanes="1" speed="15" priority="1"/>'
        '<edge id="c_out" from="m" to="e" numLanes="1" speed="15" priority="1"/></edges>'
    )
    path = build_plain_net(nodes, edges, "", tmp_path / "zip.net.xml")
    site = choose_merge(path)
    assert (site.main.edge_ids, site.merge.edge_ids) == (("b_straight",), ("a_side",))
    assert site.as_merge_net() == read_merge_net(path)
