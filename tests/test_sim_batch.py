"""K scenarios in one SUMO run over a K-copy net move exactly as each scenario alone in a SumoBackend."""

from __future__ import annotations

import os
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from idas_sumo.env.scenario import Scenario, TrafficConfig, VehicleSpec, generate_scenario
from idas_sumo.errors import InputError, SimulationError
from idas_sumo.sim.backend import STEP_LENGTH_S, SumoBackend, slot_taken
from idas_sumo.sim.batch import BatchBackend
from idas_sumo.sim.multinet import MultiNet, build_copies, check_copies, global_edge_id, multi_net
from idas_sumo.sim.netgen import MergeNet, NetParams, generate_net, read_merge_net

pytestmark = pytest.mark.sumo

STEPS = 220  # 44 s: every scenario below runs to its end (or its collision) and past
ACCELS_MPS2 = (0.5, -1.0, 1.0, 0.0, -4.0, 2.0)

Series = dict[str, list[tuple[float, str, float, float, float]]]
"""vehicle id -> (time, edge, lane position, speed, acceleration) per step it was on the road."""


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("net_cache")


def _accel(vid: str, step: int) -> float:
    """A fixed, varied command schedule: the same for a car whichever backend drives it."""
    return ACCELS_MPS2[(zlib.crc32(vid.encode()) + step // 8) % len(ACCELS_MPS2)]


def _release_now(edge: str, pos: float) -> bool:
    """Controlled cars are handed back to SUMO 20 m into the outgoing road (as finished cars are)."""
    return edge == "out" and pos > 20.0


def _scenarios() -> list[Scenario]:
    rng_scenarios = [
        generate_scenario(
            np.random.default_rng([7, i]),
            TrafficConfig(max_controlled=3),
            {"main": 20.0, "merge": 15.0},
            name=f"random{i}",
        )
        for i in range(3)
    ]
    staggered = Scenario(
        "staggered",
        (
            VehicleSpec("a", "main", 60.0, 12.0),
            VehicleSpec("r1", "main", 20.0, 15.0, controlled=False),
            VehicleSpec("b", "merge", 90.0, 10.0, depart_s=1.4),
            VehicleSpec("r2", "merge", 10.0, 8.0, controlled=False, depart_s=3.0),
            VehicleSpec("c", "main", 5.0, 18.0, depart_s=6.2),
        ),
    )
    crash = Scenario(  # a rear-end crash on the main road, a robot car behind it, a merge car meanwhile
        "crash",
        (
            VehicleSpec("fast", "main", 100.0, 20.0),
            VehicleSpec("stop", "main", 130.0, 0.0),
            VehicleSpec("r", "main", 20.0, 10.0, controlled=False),
            VehicleSpec("m", "merge", 150.0, 12.0, controlled=False, depart_s=0.6),
        ),
    )
    return [*rng_scenarios, staggered, crash]


def _command(vid: str, step: int, speed: float) -> float:
    if vid == "stop":
        return 0.0
    if vid == "fast":
        return 20.0
    return max(speed + _accel(vid, step) * STEP_LENGTH_S, 0.0)


EventLog = list[tuple[float, tuple[tuple[str, str], ...], tuple[str, ...], tuple[str, ...]]]


def _run_alone(net: MergeNet, scenario: Scenario) -> tuple[Series, EventLog]:
    backend = SumoBackend(net)
    series: Series = {}
    events: EventLog = []
    controlled = set(scenario.controlled_ids)
    released: set[str] = set()
    try:
        backend.reset(scenario)
        for step in range(STEPS):
            ev = backend.step()
            events.append((ev.time_s, tuple(ev.collision_pairs), tuple(ev.departed), tuple(ev.arrived)))
            st = backend.vehicle_states()
            commands: dict[str, float] = {}
            for i, vid in enumerate(st.ids):
                row = (ev.time_s, st.edge[i], float(st.lane_pos_m[i]), float(st.speed_mps[i]))
                series.setdefault(vid, []).append((*row, float(st.accel_mps2[i])))
                if vid in controlled and vid not in released:
                    if _release_now(st.edge[i], row[2]):
                        backend.release(vid)
                        released.add(vid)
                    else:
                        commands[vid] = _command(vid, step, row[3])
            backend.set_speeds(commands)
    finally:
        backend.close()
    return series, events


def _run_batch(
    backend: BatchBackend, scenarios: list[Scenario], clear: tuple[int, int] | None = None
) -> tuple[list[Series], list[EventLog], list[tuple[str, ...]]]:
    """Drive every copy as ``_run_alone`` drives one; ``clear`` = (copy, step): empty that copy then."""
    series: list[Series] = [{} for _ in scenarios]
    events: list[EventLog] = [[] for _ in scenarios]
    orders: list[tuple[str, ...]] = []
    controlled = [set(s.controlled_ids) for s in scenarios]
    released: set[tuple[int, str]] = set()
    backend.reset(scenarios)
    for step in range(STEPS):
        if clear is not None and step == clear[1]:
            backend.clear_copy(clear[0])
        ev = backend.step()
        assert len(ev.copies) == len(scenarios)
        for k, e in enumerate(ev.copies):
            assert e.time_s == ev.time_s
            events[k].append((e.time_s, tuple(e.collision_pairs), tuple(e.departed), tuple(e.arrived)))
        st = backend.vehicle_states()
        assert list(st.copy) == sorted(st.copy)
        ids, copies, speeds = [], [], []
        for k in range(len(scenarios)):
            one = st.of_copy(k)
            orders.append(one.ids)
            assert set(st.copy[st.bounds[k] : st.bounds[k + 1]]) <= {k}
            for i, vid in enumerate(one.ids):
                row = (ev.time_s, one.edge[i], float(one.lane_pos_m[i]), float(one.speed_mps[i]))
                series[k].setdefault(vid, []).append((*row, float(one.accel_mps2[i])))
                if vid in controlled[k] and (k, vid) not in released:
                    if _release_now(one.edge[i], row[2]):
                        backend.release(vid, copy=k)
                        released.add((k, vid))
                    else:
                        ids.append(vid)
                        copies.append(k)
                        speeds.append(_command(vid, step, row[3]))
        backend.set_speeds(ids, np.array(speeds), copy=np.array(copies, dtype=np.int64))
    return series, events, orders


def test_each_copy_moves_exactly_as_its_scenario_alone(merge_net: MergeNet, cache: Path) -> None:
    scenarios = _scenarios()
    alone = [_run_alone(merge_net, s) for s in scenarios]
    # One copy more than scenarios: an empty copy changes nothing either.
    backend = BatchBackend(merge_net, copies=len(scenarios) + 1, cache_dir=cache)
    try:
        series, events, _ = _run_batch(backend, scenarios)
        # A second episode through libsumo.load, scenarios in another order: still exact.
        again, again_events, _ = _run_batch(backend, scenarios[::-1])
    finally:
        backend.close()
    assert not slot_taken()
    for k, (want_series, want_events) in enumerate(alone):
        assert series[k] == want_series, scenarios[k].name
        assert events[k] == want_events, scenarios[k].name
        assert again[len(scenarios) - 1 - k] == want_series
        assert again_events[len(scenarios) - 1 - k] == want_events
    # The runs did what the test means to check: cars came late, crashed, were released and left.
    crash_events = events[-1]
    assert any(pairs for _, pairs, _, _ in crash_events)
    assert {v for _, pairs, _, _ in crash_events for p in pairs for v in p} == {"fast", "stop"}
    assert "fast" not in {v for _, _, _, arrived in crash_events for v in arrived}
    departures = {v: t for t, _, departed, _ in events[3] for v in departed}
    assert departures["c"] == pytest.approx(6.4) and departures["b"] == pytest.approx(1.6)
    assert all(any(arrived for *_, arrived in ev) for ev in events[:4])
    robots_after_release = [s for s in series[3]["a"] if s[1] == "out" and s[2] > 21.0]
    assert robots_after_release, "car 'a' was never released"
    hard = [row for rows in series for seq in rows.values() for row in seq if row[4] <= -3.99]
    assert hard, "no hard brake was commanded"


def test_clearing_a_copy_leaves_the_others_exact(merge_net: MergeNet, cache: Path) -> None:
    scenarios = _scenarios()[2:4]  # the second one has cars still to depart when the first is cleared
    backend = BatchBackend(merge_net, copies=2, cache_dir=cache)
    try:
        series, events, _ = _run_batch(backend, scenarios, clear=(1, 5))
        assert backend.vehicle_states().of_copy(1).ids == ()
    finally:
        backend.close()
    assert (series[0], events[0]) == _run_alone(merge_net, scenarios[0])
    assert max(len(rows) for rows in series[1].values()) == 5  # seen for 5 steps, then gone
    assert "c" not in series[1]  # departs at 6.2 s: removed before it came
    assert not [e for e in events[1][5:] if any(e[1:])]  # a cleared copy reports nothing


def test_states_keep_sumo_order_within_each_copy(merge_net: MergeNet, cache: Path) -> None:
    scenarios = _scenarios()[:3]
    backend = BatchBackend(merge_net, copies=3, cache_dir=cache)
    try:
        backend.reset(scenarios)
        backend.step()
        st = backend.vehicle_states()
        alone = SumoBackend(merge_net)
        backend.close()
        for k, scenario in enumerate(scenarios):
            try:
                alone.reset(scenario)
                alone.step()
                assert st.of_copy(k).ids == alone.vehicle_states().ids
            finally:
                alone.close()
        assert [backend.net.edge_ids[j] for j in st.edge_index] == list(st.edge)
    finally:
        backend.close()


def test_one_simulation_per_process(merge_net: MergeNet, cache: Path) -> None:
    batch = BatchBackend(merge_net, copies=2, cache_dir=cache)
    single = SumoBackend(merge_net)
    try:
        batch.reset(_scenarios()[:2])
        assert slot_taken()
        with pytest.raises(SimulationError, match="already open"):
            single.reset(_scenarios()[0])
        other = BatchBackend(batch.net)
        with pytest.raises(SimulationError, match="already open"):
            other.reset(_scenarios()[:1])
        batch.close()
        assert not slot_taken()
        single.reset(_scenarios()[0])
        with pytest.raises(SimulationError, match="already open"):
            other.reset(_scenarios()[:1])
    finally:
        batch.close()
        single.close()
    assert not slot_taken()


def test_bad_commands_and_sizes_are_refused(merge_net: MergeNet, cache: Path) -> None:
    batch = BatchBackend(merge_net, copies=2, cache_dir=cache)
    try:
        with pytest.raises(InputError, match="3 scenarios for a 2-copy net"):
            batch.reset(_scenarios()[:3])
        batch.reset(_scenarios()[3:4])
        batch.step()
        for bad in (float("nan"), float("inf"), -1.0):
            with pytest.raises(SimulationError, match="invalid speed"):
                batch.set_speeds(["a"], [bad], copy=[0])
        batch.set_speeds(["c0_a"], [3.0])  # global id
        batch.step()
        st = batch.vehicle_states()
        assert st.speed_mps[st.ids.index("a")] == 3.0
        # A car SUMO removed (here: crashed) may still be commanded, as in SumoBackend: nothing happens.
        batch.reset([_scenarios()[-1], _scenarios()[3]])
        crashed: set[str] = set()
        for _ in range(20):
            batch.set_speeds(["fast", "stop", "a"], [20.0, 0.0, 5.0], copy=[0, 0, 1])
            crashed |= batch.step().copies[0].collided
        assert {"fast", "stop"} <= crashed
        st = batch.vehicle_states()
        assert "fast" not in st.of_copy(0).ids
        assert st.of_copy(1).speed_mps[st.of_copy(1).ids.index("a")] == 5.0
    finally:
        batch.close()


# -- the K-copy net ---------------------------------------------------------------------------------


def _lanes(path: Path) -> dict[str, tuple[float, float]]:
    import sumolib

    net = sumolib.net.readNet(str(path), withInternal=True)
    return {
        lane.getID(): (lane.getLength(), lane.getSpeed())
        for edge in net.getEdges(withInternal=True)
        for lane in edge.getLanes()
    }


@pytest.mark.parametrize("copies", [1, 3, 12])
def test_every_copy_keeps_the_source_lengths(merge_net: MergeNet, cache: Path, copies: int) -> None:
    multi = multi_net(merge_net, copies, cache_dir=cache)
    source = _lanes(merge_net.path)
    built = _lanes(multi.path)
    assert len(built) == copies * len(source)
    internal = [lane for lane in source if lane.startswith(":")]
    assert len(internal) == 2  # the two junction-internal lanes are compared too
    for k in range(copies):
        for lane, facts in source.items():
            assert built[global_edge_id(multi.prefix(k), lane)] == facts
    assert multi.copy_net(copies - 1).main.length_m == merge_net.main.length_m == 250.0
    assert multi.copy_net(0).merge.via_length_m == merge_net.merge.via_length_m


def test_another_geometry_is_copied_too(tmp_path: Path, cache: Path) -> None:
    path = generate_net(tmp_path / "long.net.xml", NetParams(main_length_m=700.0, angle_deg=60.0))
    multi = multi_net(path, 4, cache_dir=cache)
    last = multi.copy_net(3)
    assert (last.main.edge_id, last.junction_id) == ("c3_main", "c3_merge_point")
    assert last.main.length_m == read_merge_net(path).main.length_m == 700.0
    source = _lanes(path)
    built = _lanes(multi.path)
    assert all(built[global_edge_id("c3_", lane)] == facts for lane, facts in source.items())


def test_the_cache_returns_the_same_file(merge_net: MergeNet, tmp_path: Path) -> None:
    first = build_copies(merge_net.path, 2, tmp_path)
    stamp = first.stat().st_mtime_ns
    time.sleep(0.01)
    assert build_copies(merge_net.path, 2, tmp_path) == first
    assert first.stat().st_mtime_ns == stamp  # not rebuilt
    assert build_copies(merge_net.path, 3, tmp_path) != first
    changed = tmp_path / "changed.net.xml"
    changed.write_text(merge_net.path.read_text().replace('speed="15.00"', 'speed="14.00"'))
    assert build_copies(changed, 2, tmp_path) != first
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_the_cache_dir_comes_from_the_environment(
    merge_net: MergeNet, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("IDAS_SUMO_CACHE", str(tmp_path / "here"))
    assert build_copies(merge_net.path, 2).parent == tmp_path / "here"


def test_an_unfaithful_copy_is_caught(merge_net: MergeNet, tmp_path: Path) -> None:
    good = build_copies(merge_net.path, 2, tmp_path)
    check_copies(merge_net.path, good, 2)
    cases: list[tuple[str, Callable[[str], str]]] = [
        (
            "length",
            lambda t: t.replace(
                'id="c1_main_0" index="0" speed="20.00" length="250.00"',
                'id="c1_main_0" index="0" speed="20.00" length="249.00"',
            ),
        ),
        (
            "internal length",
            lambda t: t.replace(
                'id=":c1_merge_point_0_0" index="0" speed="14.22" length="9.41"',
                'id=":c1_merge_point_0_0" index="0" speed="14.22" length="9.51"',
            ),
        ),
        (
            "speed",
            lambda t: t.replace(
                'id="c0_merge_0" index="0" speed="15.00"', 'id="c0_merge_0" index="0" speed="16.00"'
            ),
        ),
    ]
    for what, edit in cases:
        text = good.read_text()
        bad = tmp_path / f"bad-{what.replace(' ', '-')}.net.xml"
        bad.write_text(edit(text))
        assert bad.read_text() != text, what
        with pytest.raises(SimulationError, match="not faithful"):
            check_copies(merge_net.path, bad, 2)
    with pytest.raises(SimulationError, match="not faithful"):
        check_copies(merge_net.path, good, 3)


def test_bad_requests_are_input_errors(merge_net: MergeNet, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="copies"):
        build_copies(merge_net.path, 0, tmp_path)
    with pytest.raises(InputError, match="not found"):
        build_copies(tmp_path / "missing.net.xml", 2, tmp_path)
    with pytest.raises(InputError, match="copies"):
        BatchBackend(merge_net)
    multi: MultiNet = multi_net(merge_net, 2, tmp_path)
    with pytest.raises(InputError, match="3 given with a 2-copy net"):
        BatchBackend(multi, copies=3)
    assert os.listdir(tmp_path)


CROSSING_NODES = """<nodes>
  <node id="C" x="0" y="0" type="traffic_light"/>
  <node id="N" x="0" y="200"/><node id="S" x="0" y="-200"/><node id="E" x="200" y="0"/><node id="W" x="-200" y="0"/>
</nodes>
"""
CROSSING_EDGES = """<edges>
  <edge id="WC" from="W" to="C" numLanes="2" speed="13.9"/><edge id="CE" from="C" to="E" numLanes="2" speed="13.9"/>
  <edge id="EC" from="E" to="C" numLanes="2" speed="13.9"/><edge id="CW" from="C" to="W" numLanes="2" speed="13.9"/>
  <edge id="NC" from="N" to="C" speed="10"/><edge id="CS" from="C" to="S" speed="10"/>
</edges>
"""


def test_any_net_is_copied(tmp_path: Path) -> None:
    """Not only the merge: a two-lane crossing with a traffic light, checked and loadable by SUMO."""
    import subprocess

    from idas_sumo.sim.netgen import sumo_binary

    (tmp_path / "x.nod.xml").write_text(CROSSING_NODES)
    (tmp_path / "x.edg.xml").write_text(CROSSING_EDGES)
    source = tmp_path / "crossing.net.xml"
    netconvert = [str(sumo_binary("netconvert")), "-n", str(tmp_path / "x.nod.xml")]
    subprocess.run([*netconvert, "-e", str(tmp_path / "x.edg.xml"), "-o", str(source)], check=True)
    built = build_copies(source, 3, tmp_path / "cache")  # check_copies ran inside
    text = built.read_text()
    assert [f'tlLogic id="c{k}_C"' in text for k in range(3)] == [True] * 3
    assert len(_lanes(built)) == 3 * len(_lanes(source))
    run = subprocess.run(
        [str(sumo_binary("sumo")), "-n", str(built), "--end", "5", "--no-step-log", "true"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr


def test_workers_building_the_same_net_at_once_agree(merge_net: MergeNet, tmp_path: Path) -> None:
    import subprocess
    import sys

    code = (
        "import sys; from idas_sumo.sim.multinet import build_copies; "
        "print(build_copies(sys.argv[1], 5, sys.argv[2]))"
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code, str(merge_net.path), str(tmp_path)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(3)
    ]
    outputs = {p.communicate(timeout=120)[0].strip() for p in procs}
    assert all(p.returncode == 0 for p in procs)
    assert len(outputs) == 1
    (path,) = outputs
    check_copies(merge_net.path, Path(path), 5)
    name = Path(path).name  # the net and its digest, no temp file left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == [name, f"{name}.sha256"]
