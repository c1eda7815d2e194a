"""The merge-net generator and reader: exact geometry, and every bad net is one InputError naming the file."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from idas_sumo.errors import InputError
from idas_sumo.sim.netgen import NetParams, generate_net, read_merge_net, sumo_binary


def _check_default_geometry(path: Path) -> None:
    import sumolib

    net = read_merge_net(path)
    assert (net.main.length_m, net.merge.length_m, net.out.length_m) == (250.0, 250.0, 150.0)
    assert (net.main.speed_limit_mps, net.merge.speed_limit_mps, net.out.speed_limit_mps) == (
        20.0,
        15.0,
        20.0,
    )
    assert net.main.priority > net.merge.priority
    assert net.main.edge_id == "main" and net.merge.edge_id == "merge" and net.out.edge_id == "out"
    # Junction-internal lanes exist from both roads onto the outgoing road.
    assert net.main.via_length_m > 0 and net.merge.via_length_m > 0

    raw = sumolib.net.readNet(str(path))
    lane_lengths = {e.getID(): e.getLanes()[0].getLength() for e in raw.getEdges()}
    assert lane_lengths == {"main": 250.0, "merge": 250.0, "out": 150.0}
    merges = [n for n in raw.getNodes() if len(n.getIncoming()) >= 2]
    assert [n.getID() for n in merges] == [net.junction_id]
    assert sorted(e.getID() for e in merges[0].getIncoming()) == ["main", "merge"]
    assert [e.getID() for e in merges[0].getOutgoing()] == ["out"]


def test_generated_default_net_has_paper_geometry(fresh_net: Path) -> None:
    _check_default_geometry(fresh_net)
    # The plain XML it was built from is kept beside it.
    assert fresh_net.with_name("tjunction.nod.xml").is_file()
    assert fresh_net.with_name("tjunction.edg.xml").is_file()


def test_committed_net_reads_the_same(net_path: Path, fresh_net: Path) -> None:
    _check_default_geometry(net_path)
    committed, fresh = read_merge_net(net_path), read_merge_net(fresh_net)
    for road in ("main", "merge", "out"):
        a, b = getattr(committed, road), getattr(fresh, road)
        assert (a.edge_id, a.length_m, a.speed_limit_mps, a.priority) == (
            b.edge_id,
            b.length_m,
            b.speed_limit_mps,
            b.priority,
        )
        assert a.via_length_m == pytest.approx(b.via_length_m, abs=0.05)


def test_custom_params(tmp_path: Path) -> None:
    params = NetParams(main_length_m=400.0, merge_length_m=400.0, out_length_m=200.0, merge_speed_mps=12.0)
    net = read_merge_net(generate_net(tmp_path / "long.net.xml", params))
    assert (net.main.length_m, net.merge.length_m, net.out.length_m) == (400.0, 400.0, 200.0)
    assert (net.main.speed_limit_mps, net.merge.speed_limit_mps) == (20.0, 12.0)
    assert net.main.priority > net.merge.priority


@pytest.mark.parametrize(
    "kwargs",
    [{"main_length_m": 5.0}, {"merge_speed_mps": 0.0}, {"out_speed_mps": float("nan")}, {"angle_deg": 0.0}],
)
def test_bad_params_are_input_errors(kwargs: dict[str, float]) -> None:
    with pytest.raises(InputError):
        NetParams(**kwargs)


def _netconvert(tmp_path: Path, name: str, nodes: list[tuple[str, float, float]], edges: list[tuple]) -> Path:
    nod = tmp_path / f"{name}.nod.xml"
    edg = tmp_path / f"{name}.edg.xml"
    out = tmp_path / f"{name}.net.xml"
    nod.write_text(
        "<nodes>\n" + "".join(f'<node id="{n}" x="{x}" y="{y}"/>\n' for n, x, y in nodes) + "</nodes>\n"
    )
    edg.write_text(
        "<edges>\n"
        + "".join(f'<edge id="{e}" from="{f}" to="{t}" numLanes="1" speed="15"/>\n' for e, f, t in edges)
        + "</edges>\n"
    )
    subprocess.run(
        [str(sumo_binary("netconvert")), "-n", str(nod), "-e", str(edg), "-o", str(out), "--no-warnings"],
        check=True,
        capture_output=True,
    )
    return out


def _assert_input_error_naming(path: Path, fragment: str) -> None:
    with pytest.raises(InputError) as info:
        read_merge_net(path)
    message = str(info.value)
    assert str(path) in message, message
    assert fragment in message, message


def test_missing_file(tmp_path: Path) -> None:
    _assert_input_error_naming(tmp_path / "nope.net.xml", "not found")


def test_directory(tmp_path: Path) -> None:
    _assert_input_error_naming(tmp_path, "directory")


def test_not_xml(tmp_path: Path) -> None:
    p = tmp_path / "garbage.net.xml"
    p.write_text("this is not < xml at all")
    _assert_input_error_naming(p, "not valid XML")


def test_xml_but_not_a_net(tmp_path: Path) -> None:
    p = tmp_path / "routes.net.xml"
    p.write_text("<routes><vType id='a'/></routes>")
    _assert_input_error_naming(p, "not a SUMO network")


def test_straight_net_has_no_merge(tmp_path: Path) -> None:
    p = _netconvert(
        tmp_path,
        "straight",
        [("a", 0, 0), ("b", 100, 0), ("c", 200, 0)],
        [("ab", "a", "b"), ("bc", "b", "c")],
    )
    _assert_input_error_naming(p, "no merge junction")


def test_three_roads_into_the_merge(tmp_path: Path) -> None:
    p = _netconvert(
        tmp_path,
        "three",
        [("a", -200, 0), ("b", -150, -100), ("c", -150, 100), ("m", 0, 0), ("o", 100, 0)],
        [("am", "a", "m"), ("bm", "b", "m"), ("cm", "c", "m"), ("mo", "m", "o")],
    )
    _assert_input_error_naming(p, "3 incoming roads")
