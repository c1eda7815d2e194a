"""netgen's geometry parameters (angle, lengths, limits, priority), their bounds, and the net cache."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
from conftest import run_cli

from idas_sumo.errors import InputError
from idas_sumo.sim.net_cache import cached_net, params_key
from idas_sumo.sim.netgen import NetParams, generate_net, read_merge_net


def _connection_states(path: Path) -> dict[str, str]:
    import sumolib

    net = sumolib.net.readNet(str(path))
    out = net.getEdge("out")
    return {e: net.getEdge(e).getConnections(out)[0].getState() for e in ("main", "merge")}


def _merge_angle_deg(path: Path) -> float:
    """The angle between the merge road's and the main road's directions, from their node positions."""
    import sumolib

    net = sumolib.net.readNet(str(path))

    def heading(edge_id: str) -> float:
        edge = net.getEdge(edge_id)
        (ax, ay), (bx, by) = edge.getFromNode().getCoord(), edge.getToNode().getCoord()
        return math.atan2(by - ay, bx - ax)

    return math.degrees(abs(heading("merge") - heading("main")))


def test_every_geometry_parameter_reaches_the_net(tmp_path: Path) -> None:
    params = NetParams(
        main_length_m=320.0,
        merge_length_m=180.0,
        out_length_m=240.0,
        main_speed_mps=25.0,
        merge_speed_mps=12.5,
        out_speed_mps=22.0,
        angle_deg=60.0,
    )
    path = generate_net(tmp_path / "g.net.xml", params)
    net = read_merge_net(path)
    assert (net.main.length_m, net.merge.length_m, net.out.length_m) == (320.0, 180.0, 240.0)
    assert (net.main.speed_limit_mps, net.merge.speed_limit_mps, net.out.speed_limit_mps) == (
        25.0,
        12.5,
        22.0,
    )
    assert net.main.priority > net.merge.priority
    assert _merge_angle_deg(path) == pytest.approx(60.0, abs=0.01)
    assert _connection_states(path) == {"main": "M", "merge": "m"}


def test_equal_priority_is_a_zipper(tmp_path: Path) -> None:
    """Equal edge priorities alone leave the straight road its right of way: the junction must be a zipper."""
    path = generate_net(tmp_path / "z.net.xml", NetParams(priority="equal"))
    net = read_merge_net(path)
    assert net.main.priority == net.merge.priority
    assert _connection_states(path) == {"main": "Z", "merge": "Z"}
    # The main road is still the straight one, whatever the order sumolib lists the roads in.
    assert (net.main.edge_id, net.merge.edge_id) == ("main", "merge")


def test_equal_priority_and_equal_limits_keep_the_straight_road_as_main(tmp_path: Path) -> None:
    params = NetParams(priority="equal", main_speed_mps=15.0, merge_speed_mps=15.0)
    net = read_merge_net(generate_net(tmp_path / "zz.net.xml", params))
    assert (net.main.edge_id, net.merge.edge_id) == ("main", "merge")


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"angle_deg": 4.9}, "--angle"),
        ({"angle_deg": 90.1}, "--angle"),
        ({"out_length_m": 19.0}, "--out-length"),
        ({"merge_length_m": 10_001.0}, "--merge-length"),
        ({"out_speed_mps": 70.5}, "--out-speed"),
        ({"main_speed_mps": float("inf")}, "--main-speed"),
        ({"priority": "merge"}, "--priority"),
    ],
)
def test_out_of_bounds_parameters_name_their_flag(kwargs: dict[str, object], fragment: str) -> None:
    with pytest.raises(InputError, match=fragment):
        NetParams(**kwargs)  # type: ignore[arg-type]


def test_cli_priority_and_bounds(tmp_path: Path) -> None:
    out = tmp_path / "cli.net.xml"
    ok = run_cli("netgen", "--out", str(out), "--priority", "equal", "--angle", "45", "--out-length", "200")
    assert ok.returncode == 0, ok.stderr
    assert _connection_states(out) == {"main": "Z", "merge": "Z"}
    assert _merge_angle_deg(out) == pytest.approx(45.0, abs=0.01)
    bad = run_cli("netgen", "--out", str(tmp_path / "bad.net.xml"), "--angle", "95")
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == ["idas-sumo: error: --angle: 95.0 degrees is outside [5, 90]"]
    assert not (tmp_path / "bad.net.xml").exists()
    bad = run_cli("netgen", "--out", str(tmp_path / "bad.net.xml"), "--priority", "left")
    assert bad.returncode == 2 and "--priority" in bad.stderr and "Traceback" not in bad.stderr


def test_cache_key_covers_every_parameter() -> None:
    base = NetParams()
    changed = [
        NetParams(main_length_m=251.0),
        NetParams(merge_length_m=251.0),
        NetParams(out_length_m=151.0),
        NetParams(main_speed_mps=21.0),
        NetParams(merge_speed_mps=16.0),
        NetParams(out_speed_mps=21.0),
        NetParams(angle_deg=31.0),
        NetParams(priority="equal"),
    ]
    keys = {params_key(p) for p in changed}
    assert len(keys) == len(changed) and params_key(base) not in keys
    assert params_key(NetParams()) == params_key(base)


def test_cache_builds_once_and_reuses(tmp_path: Path) -> None:
    params = NetParams(angle_deg=40.0, merge_length_m=300.0)
    first = cached_net(params, tmp_path)
    assert read_merge_net(first).merge.length_m == 300.0
    stamp = first.stat().st_mtime_ns
    os.utime(first, ns=(stamp - 10**9, stamp - 10**9))  # a rebuild would give a fresh mtime
    again = cached_net(params, tmp_path)
    assert again == first and again.stat().st_mtime_ns == stamp - 10**9
    other = cached_net(NetParams(angle_deg=50.0), tmp_path)
    assert other != first and other.parent == first.parent
    # Only the nets and their digests remain: no plain XML, no build folders or temp files.
    names = [first.name, other.name]
    assert sorted(p.name for p in first.parent.iterdir()) == sorted([*names, *(n + ".sha256" for n in names)])


def test_a_damaged_cached_net_is_built_again(tmp_path: Path) -> None:
    params = NetParams(angle_deg=35.0)
    path = cached_net(params, tmp_path)
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 2])  # a disk that filled up, an editor
    assert cached_net(params, tmp_path) == path
    assert read_merge_net(path).merge.length_m == params.merge_length_m
