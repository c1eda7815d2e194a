"""The example nets SUMO ships (``sumo/tools/game/``): every merge ``nets inspect`` lists there runs.

Before issue 34, four of the five merges of ``ramp`` and ``highway`` were refused: the scenario
generator drew starts on junction-internal lanes between two edges (``gneJ7``, ``1658965310``, ``J3``)
and the cars' 40 m/s top speed was below a 44.44 m/s limit (``2024041878``); ``A10KW``'s lane drops
also started cars above their first edge's limit. Starts now count along an approach's edges
(``Approach.edge_point``), the controlled cars' top speed follows the net and a start speed is capped
by its departure lane's limit. Three more were refused for approaches shorter than the 100 m sensor
range (``A10KW`` ``32500260``, 11 m of road of which 4.6 m on edges, and ``32500287``; ``bs3d``
``62004677``, 26 m): starts are now drawn on what a road has, the cars that do not fit entering later
at its start, and a road that splits just past the merge (``32500287``, 14 m on) goes on along its
straightest branch (``merge_detect.FOLLOW_SPLIT_M``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from idas_sumo.cli import main
from idas_sumo.env.scenario import Scenario, TrafficConfig, VehicleSpec, generate_scenario, start_room_m
from idas_sumo.errors import InputError
from idas_sumo.resources import DEFAULT_NET
from idas_sumo.sim.backend import (
    CONTROLLED_MAX_SPEED_MPS,
    CONTROLLED_TYPE,
    _route_xml,
    controlled_top_speed,
)
from idas_sumo.sim.merge_detect import MergeSite, choose_merge, detect_merges
from idas_sumo.sim.multinet import UnfaithfulCopies, build_copies, copies_run

sumo = pytest.importorskip("sumo")
GAME = Path(sumo.SUMO_HOME) / "tools" / "game"

RUNS = {  # every merge detected in tools/game that the scenarios can use
    ("ramp/ramp.net.xml", "gneJ14"),
    ("ramp/ramp.net.xml", "gneJ7"),
    ("highway/highway.net.xml", "1658965310"),
    ("highway/highway.net.xml", "2024041878"),
    ("highway/highway.net.xml", "J3"),
    # A 2018 net (format 0.27): netconvert rebuilds its edges 2.5 m shorter, so no multi-copy net is
    # faithful; its episodes run one at a time on the file itself (multinet.copies_run).
    ("A10KW/osm.net.xml", "2314229789"),
    ("A10KW/osm.net.xml", "2699976598"),
    # Approaches shorter than the 100 m sensor range (and than the 200 m start range).
    ("A10KW/osm.net.xml", "32500260"),
    ("A10KW/osm.net.xml", "32500287"),
    ("bs3d/bs.net.xml", "62004677"),
}


def _site(net: str, junction: str) -> MergeSite:
    return choose_merge(GAME / net, junction)


def test_the_merges_in_sumos_examples_are_the_ones_listed_here() -> None:
    found = {
        (f"{p.parent.name}/{p.name}", site.junction_id)
        for p in sorted(GAME.glob("*/*.net.xml"))
        for site in detect_merges(p)
    }
    assert found == RUNS


def test_edge_point_counts_along_the_edges_hand_worked() -> None:
    """ramp's on-ramp: gneE18 79.9 m, gneE13 16.8 m, gneE14 23.3 m, gneE7 110.7 m, with junction lanes
    of 5.3, 0.3 and 4.3 m between them. 129.14 m in was the refused point as a distance along the road
    (111.46 m before the merge point lies on :gneJ4_0_0); along the edges it lies 9.14 m into gneE7."""
    approach = _site("ramp/ramp.net.xml", "gneJ7").merge
    lengths = [lane.length_m for lane in approach.edges]
    assert approach.edge_ids == ("gneE18", "gneE13", "gneE14", "gneE7")
    assert lengths == pytest.approx([79.9, 16.8, 23.3, 110.7], abs=0.06)
    with pytest.raises(InputError, match="junction-internal lane"):
        approach.lane_at(111.46)
    lane, pos = approach.edge_point(129.14)
    assert lane.edge_id == "gneE7" and pos == pytest.approx(129.14 - sum(lengths[:3]))
    lane, pos = approach.edge_point(50.0)  # on the first edge: the position as given
    assert lane.edge_id == "gneE18" and pos == 50.0
    lane, pos = approach.edge_point(lengths[0])  # an edge's end is the next edge's start
    assert lane.edge_id == "gneE13" and pos == 0.0
    assert approach.edges_length_m == pytest.approx(sum(lengths))
    for outside in (-1.0, sum(lengths) + 0.01):
        with pytest.raises(InputError, match="outside its edges"):
            approach.edge_point(outside)


@pytest.mark.parametrize(("net", "junction"), sorted(RUNS))
def test_drawn_starts_land_on_edges_no_closer_than_drawn(net: str, junction: str) -> None:
    """200 drawn scenarios: every start is on an ordinary edge, and two cars of one road are at least
    as far apart along the route as they were drawn (junction lanes between them only add room)."""
    site = _site(net, junction)
    limits = {"main": site.main.road.speed_limit_mps, "merge": site.merge.road.speed_limit_mps}
    rng = np.random.default_rng(34)
    room = start_room_m(site)
    for _ in range(200):
        scenario = generate_scenario(rng, TrafficConfig(), limits, start_room_m=room)
        for side in ("main", "merge"):
            approach = site.approach(side)
            cars = sorted((v for v in scenario.vehicles if v.road == side), key=lambda v: v.start_pos_m)
            to_merge = []
            for v in cars:
                lane, pos = approach.edge_point(v.start_pos_m)
                assert not lane.internal and 0.0 <= pos < lane.length_m
                to_merge.append(lane.start_to_merge_m - pos)
            drawn = np.diff([v.start_pos_m for v in cars])
            driven = -np.diff(to_merge)
            assert np.all(driven >= drawn - 1e-9)


def test_controlled_top_speed_follows_the_net() -> None:
    fast = _site("highway/highway.net.xml", "2024041878")
    assert fast.fastest_limit_mps == pytest.approx(44.44)
    assert controlled_top_speed(fast) == fast.fastest_limit_mps
    # The shipped T-junction (20 m/s at most) keeps the 40 m/s vType, its route file unchanged.
    tjunction = choose_merge(DEFAULT_NET)
    assert controlled_top_speed(tjunction) == CONTROLLED_MAX_SPEED_MPS == 40.0
    car = VehicleSpec("main0", "main", 10.0, 40.0)
    root = ET.fromstring(_route_xml(Scenario("s", (car,)), fast))
    agent = next(t for t in root.iter("vType") if t.get("id") == CONTROLLED_TYPE)
    assert float(agent.get("maxSpeed", "0")) == pytest.approx(44.44)


def test_a_start_above_its_edges_limit_departs_at_that_limit() -> None:
    """A10KW's on-ramp: its first edge allows 19.44 m/s, its own road (which scales the drawn speeds)
    22.22; a car drawn at 21 m/s on the first edge departs at 19.44, one on the own road at 21."""
    site = _site("A10KW/osm.net.xml", "2314229789")
    first = site.merge.edges[0]
    assert (first.speed_limit_mps, site.merge.road.speed_limit_mps) == pytest.approx((19.44, 22.22))
    cars = (
        VehicleSpec("merge0", "merge", 10.0, 21.0),
        VehicleSpec("merge1", "merge", first.length_m + 10.0, 21.0),
    )
    root = ET.fromstring(_route_xml(Scenario("s", cars), site))
    speeds = {v.get("id"): float(v.get("departSpeed", "nan")) for v in root.iter("vehicle")}
    assert site.merge.edges[1].speed_limit_mps >= 21.0
    assert speeds == {"merge0": 19.44, "merge1": 21.0}


def test_a_net_no_copy_reproduces_runs_one_episode_at_a_time(tmp_path: Path) -> None:
    """A10KW's copies are refused once (the reason kept in the cache), and not built again; the
    T-junction's are built."""
    source = GAME / "A10KW" / "osm.net.xml"
    with pytest.raises(UnfaithfulCopies, match="not faithful"):
        build_copies(source, 2, tmp_path)
    assert not copies_run(source, 2, tmp_path)
    (marker,) = tmp_path.glob("*.unfaithful")
    assert "not faithful" in marker.read_text()
    assert not copies_run(source, 2, tmp_path)  # from the marker: no build (none left in the cache)
    assert not list(tmp_path.glob("*.net.xml"))
    assert copies_run(DEFAULT_NET, 2, tmp_path) and len(list(tmp_path.glob("*-k2.net.xml"))) == 1


@pytest.mark.sumo
@pytest.mark.parametrize("method", ["idm", "idas"])
@pytest.mark.parametrize(("net", "junction"), sorted(RUNS))
def test_every_merge_in_sumos_examples_evaluates(
    net: str, junction: str, method: str, tmp_path: Path
) -> None:
    config = tmp_path / "short.toml"
    config.write_text("max_episode_s = 40.0\n")
    out = tmp_path / "out"
    args = ["evaluate", "--baseline", method, "--net", str(GAME / net), "--junction", junction]
    args += ["--scenarios", "2", "--copies", "2", "--config", str(config), "--out", str(out), "--no-progress"]
    assert main(args) == 0
    episodes = pd.read_csv(out / "episodes.csv")
    assert len(episodes) == 2 and set(episodes["method"]) == {method}
    ended = episodes["success"] + episodes["timeout"] + (episodes["collisions"] > 0)
    assert (ended >= 1).all()


def test_a_scenario_file_start_past_the_edges_room_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """ramp's on-ramp is 240.6 m to the merge point, 230.7 m of it on edges: a file's car at 235 m is
    refused up front, naming the file and the car."""
    scenario = tmp_path / "far.toml"
    scenario.write_text(
        '[[vehicles]]\nid = "merge0"\nroad = "merge"\nstart_pos_m = 235.0\nspeed_mps = 5.0\n'
        '[[vehicles]]\nid = "main0"\nroad = "main"\nstart_pos_m = 100.0\nspeed_mps = 10.0\n'
    )
    args = ["evaluate", "--baseline", "idm", "--net", str(GAME / "ramp/ramp.net.xml"), "--junction", "gneJ7"]
    assert main([*args, "--scenario", str(scenario), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(scenario) in err and "'merge0'" in err and "230.7" in err


@pytest.mark.parametrize("n_vehicles", [8, 0])
def test_a_road_shorter_than_the_start_range_takes_later_entries(n_vehicles: int) -> None:
    """``32500260``'s main road has 4.6 m of edges, less than a car: no car fits on it at t = 0, so
    every one enters later, half way along them, one after another; ``62004677``'s merging road (26.2 m)
    holds one car at t = 0. Both generators (the paper's staggered traffic, and every car at t = 0)."""
    traffic = TrafficConfig(n_vehicles=n_vehicles)
    for net, junction, road, fits in (
        ("A10KW/osm.net.xml", "32500260", "main", 0),
        ("bs3d/bs.net.xml", "62004677", "merge", 1),
    ):
        site = _site(net, junction)
        room = start_room_m(site)
        limits = {"main": site.main.road.speed_limit_mps, "merge": site.merge.road.speed_limit_mps}
        rng = np.random.default_rng(34)
        for _ in range(100):
            cars = [
                v
                for v in generate_scenario(rng, traffic, limits, start_room_m=room).vehicles
                if v.road == road
            ]
            at_start = [v for v in cars if v.depart_s == 0.0 and v.start_pos_m >= 5.0]
            entries = [v for v in cars if v not in at_start]
            assert len(at_start) <= fits and all(0.0 < v.start_pos_m < room[road] for v in cars)
            assert {v.start_pos_m for v in entries} <= {min(5.0, room[road] // 0.002 / 1000)}
            departs = [v.depart_s for v in entries]
            assert departs == sorted(departs) and len(set(departs)) == len(departs)


def test_a_road_that_holds_the_start_range_draws_as_before() -> None:
    """The room changes nothing where the start range fits (the shipped net: 250 m roads)."""
    site = choose_merge(DEFAULT_NET)
    limits = {"main": site.main.road.speed_limit_mps, "merge": site.merge.road.speed_limit_mps}
    for seed in range(30):
        for traffic in (TrafficConfig(), TrafficConfig(n_vehicles=0)):
            plain = generate_scenario(np.random.default_rng(seed), traffic, limits)
            roomy = generate_scenario(
                np.random.default_rng(seed), traffic, limits, start_room_m=start_room_m(site)
            )
            assert plain == roomy


def test_a_split_just_past_the_merge_is_followed_along_its_straightest_branch() -> None:
    """``32500287``'s road after the merge splits 1.9 m on (253109040 into 4935289, back into the
    roundabout-like ring it sits on, or 4935300#0, away from it): the route goes on along the
    straighter one and never onto an approach's edge again."""
    site = _site("A10KW/osm.net.xml", "32500287")
    out = [lane.edge_id for lane in site.out if not lane.internal]
    assert out[:2] == ["253109040", "4935300#0"]
    for side in ("main", "merge"):
        edges = site.route_edge_ids(side)
        assert len(edges) == len(set(edges))
        past = site.route(side)[-1]
        assert past.length_m - past.start_to_merge_m >= 100.0
