"""The example nets SUMO ships (``sumo/tools/game/``): every merge ``nets inspect`` lists there runs.

Before issue 34, four of the five merges of ``ramp`` and ``highway`` were refused: the scenario
generator drew starts on junction-internal lanes between two edges (``gneJ7``, ``1658965310``, ``J3``)
and the cars' 40 m/s top speed was below a 44.44 m/s limit (``2024041878``); ``A10KW``'s lane drops
also started cars above their first edge's limit. Starts now count along an approach's edges
(``Approach.edge_point``), the controlled cars' top speed follows the net and a start speed is capped
by its departure lane's limit.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from idas_sumo.cli import main
from idas_sumo.env.scenario import Scenario, TrafficConfig, VehicleSpec, generate_scenario
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
}
TOO_SHORT = {  # approaches shorter than the 100 m sensor range: refused up front, one line
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
    assert found == RUNS | TOO_SHORT


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
    for _ in range(200):
        scenario = generate_scenario(rng, TrafficConfig(), limits)
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


@pytest.mark.parametrize(("net", "junction"), sorted(TOO_SHORT))
def test_merges_with_roads_shorter_than_the_sensor_range_are_one_line(
    net: str, junction: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["evaluate", "--baseline", "idm", "--net", str(GAME / net), "--junction", junction]
    assert main([*args, "--scenarios", "2", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "m long" in err and "the scenarios need" in err and "sensor range" in err


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
