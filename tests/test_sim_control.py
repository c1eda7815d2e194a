"""The SUMO backend does what it is told: commanded accelerations, no hidden limits, collisions,
finishing, and one in-process simulation (a second one goes to a subprocess)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from idas_sumo.baselines.policies import BASELINES
from idas_sumo.env.actions import SafetyMask
from idas_sumo.env.engine import EnvConfig
from idas_sumo.env.scenario import Scenario, VehicleSpec
from idas_sumo.env.single import SingleEpisode
from idas_sumo.errors import SimulationError
from idas_sumo.sim.backend import STEP_LENGTH_S, SubprocessBackend, SumoBackend, make_backend, slot_taken
from idas_sumo.sim.netgen import MergeNet

pytestmark = pytest.mark.sumo

DA0 = 2  # keep the current acceleration


@pytest.fixture
def backend(merge_net: MergeNet) -> Iterator[SumoBackend]:
    b = SumoBackend(merge_net)
    try:
        yield b
    finally:
        b.close()
    assert not slot_taken()


def _one_car(road: str, pos: float, speed: float) -> Scenario:
    return Scenario("one", (VehicleSpec("ego", road, pos, speed),))  # type: ignore[arg-type]


def _drive(backend: SumoBackend, accel: float, steps: int) -> list[tuple[str, float, float]]:
    """Command v + a·dt each step; return (edge, speed before, speed after) per step."""
    trace = []
    for _ in range(steps):
        states = backend.vehicle_states()
        if "ego" not in states.ids:
            break
        v = float(states.speed_mps[states.ids.index("ego")])
        backend.set_speeds({"ego": max(v + accel * STEP_LENGTH_S, 0.0)})
        backend.step()
        after = backend.vehicle_states()
        i = after.ids.index("ego")
        trace.append((after.edge[i], v, float(after.speed_mps[i])))
        if trace[-1][2] == 0.0:
            break
    return trace


@pytest.mark.parametrize("accel", [0.5, -1.0, -4.0])
def test_commanded_acceleration_is_applied(backend: SumoBackend, accel: float) -> None:
    # Start on the main road 20 m before the merge point so the car drives through the junction.
    backend.reset(_one_car("main", 230.0, 12.0))
    backend.step()  # insertion
    trace = _drive(backend, accel, 25)
    assert len(trace) >= 3
    for edge, before, after in trace:
        if before + accel * STEP_LENGTH_S > 0:
            assert after - before == pytest.approx(accel * STEP_LENGTH_S, abs=1e-6), (edge, before, after)
    edges = {e for e, _, _ in trace}
    if accel > -4.0:  # the hard-braking car stops before the junction
        assert any(e.startswith(":") for e in edges), edges  # the junction-internal lane
        assert "out" in edges
    # SUMO itself reports the commanded acceleration.
    i = backend.vehicle_states().ids.index("ego")
    if trace[-1][2] > 0:
        assert backend.vehicle_states().accel_mps2[i] == pytest.approx(accel, abs=1e-6)


def test_acceleration_applied_on_the_junction_lane_under_hard_braking(backend: SumoBackend) -> None:
    # Enter the junction fast, then brake hard on the internal lane: still exactly -4 m/s².
    backend.reset(_one_car("merge", 244.0, 14.0))
    backend.step()
    on_junction = []
    for edge, before, after in _drive(backend, -4.0, 20):
        if edge.startswith(":") and before > 0.8:
            on_junction.append(after - before)
    assert on_junction, "the car never braked on the junction-internal lane"
    assert on_junction == pytest.approx([-0.8] * len(on_junction), abs=1e-6)


def test_speed_above_the_road_limit_is_honoured(backend: SumoBackend) -> None:
    # The merge road's limit is 15 m/s; SUMO does not cap the controlled car (the rule mask must).
    backend.reset(_one_car("merge", 20.0, 14.0))
    backend.step()
    trace = _drive(backend, 2.0, 20)
    assert len(trace) == 20
    assert all(e == "merge" for e, _, _ in trace)  # > 100 m before the merge point: no exemption either
    for _, before, after in trace:
        assert after - before == pytest.approx(0.4, abs=1e-6)
    assert trace[-1][2] == pytest.approx(14.0 + 20 * 0.4)  # 22 m/s on a 15 m/s road
    backend.set_speeds({"ego": 25.0})
    backend.step()
    states = backend.vehicle_states()
    assert states.speed_mps[states.ids.index("ego")] == pytest.approx(25.0)


def test_invalid_speed_commands_are_refused(backend: SumoBackend) -> None:
    backend.reset(_one_car("main", 50.0, 10.0))
    backend.step()
    for bad in (float("nan"), float("inf"), -1.0):
        with pytest.raises(SimulationError):
            backend.set_speeds({"ego": bad})


def _level_pair(
    net: MergeNet, start_pos_m: float, speed_mps: float, safety_mask: SafetyMask = "own_lane"
) -> tuple[SingleEpisode, Scenario]:
    """A main-road car "m" and a merge-road car "g", level with each other, main road has priority."""
    cars = (
        VehicleSpec("m", "main", start_pos_m, speed_mps, b_type=0.0),
        VehicleSpec("g", "merge", start_pos_m, speed_mps, b_type=0.0),
    )
    scenario = Scenario("level", cars, main_prio=1, merge_prio=0)
    return SingleEpisode(net, config=EnvConfig(max_episode_s=20.0, safety_mask=safety_mask)), scenario


def test_merge_crash_is_collided_with_collide_reward(merge_net: MergeNet) -> None:
    # Both cars are level 3 m before the merge point at 15 m/s: even the masked hard brake comes too late.
    sim, scenario = _level_pair(merge_net, start_pos_m=247.0, speed_mps=15.0)
    try:
        sim.reset(scenario)
        ended: dict[str, str] = {}
        collide: dict[str, float] = {}
        arrived: list[str] = []
        while sim.active_agents:
            out = sim.step(dict.fromkeys(sim.active_agents, DA0))
            ended.update(out.end_reason)
            collide.update({a: p["collide"] for a, p in out.reward_parts.items()})
            arrived += [a for a, r in out.end_reason.items() if r == "removed"]
            if out.collisions:
                assert {c for pair in out.collisions for c in pair} == {"m", "g"}
        assert ended == {"m": "collided", "g": "collided"}
        # -5·b_prio - 5: main (prio 1) -10, merge (prio 0) -5.
        assert collide == {"m": -10.0, "g": -5.0}
        assert arrived == []
        assert sim.backend.vehicle_states().ids == ()  # removed by SUMO
    finally:
        sim.close()


def test_collided_vehicles_are_not_arrived(backend: SumoBackend) -> None:
    backend.reset(
        Scenario(
            "rear-end", (VehicleSpec("fast", "main", 100.0, 20.0), VehicleSpec("stop", "main", 110.0, 0.0))
        )
    )
    backend.step()
    collided: set[str] = set()
    arrived: list[str] = []
    for _ in range(5):
        backend.set_speeds({v: 20.0 if v == "fast" else 0.0 for v in backend.vehicle_states().ids})
        events = backend.step()
        collided |= events.collided
        arrived += events.arrived
    assert collided == {"fast", "stop"}
    assert arrived == []


def test_finish_50_m_past_the_merge_point(merge_net: MergeNet) -> None:
    scenario = Scenario("finish", (VehicleSpec("ego", "merge", 200.0, 15.0, b_type=1.0),))
    sim = SingleEpisode(merge_net, config=EnvConfig(max_episode_s=30.0))
    try:
        sim.reset(scenario)
        dist = [sim.agent_info("ego")["dist_to_merge_m"]]
        speeds = [sim.agent_info("ego")["speed_mps"]]
        while sim.active_agents:
            out = sim.step({"ego": DA0})
            info = sim.agent_info("ego")
            dist.append(info["dist_to_merge_m"])
            speeds.append(info["speed_mps"])
        assert out.end_reason == {"ego": "finished"}
        assert out.terminated == {"ego": True}
        assert out.reward_parts["ego"]["finish"] == (15.0 * 1.0 + 50.0) / 4.0 == 16.25
        assert out.reward_parts["ego"]["collide"] == 0.0
        assert out.rewards["ego"] == 16.25
        # The distance to the merge point falls by v·dt every step, through the junction and onto 'out'.
        for d0, d1, v in zip(dist, dist[1:], speeds[1:], strict=False):
            assert d0 - d1 == pytest.approx(v * STEP_LENGTH_S, abs=1e-3)
        assert -50.0 - 15.0 * STEP_LENGTH_S < dist[-1] <= -50.0
        assert dist[-2] > -50.0
        # Finished is not arrived: the car is still on the outgoing road, handed back to SUMO.
        assert "ego" in sim.backend.vehicle_states().ids
        assert sim.finished_agents == {"ego": "finished"}
        assert sim.episode_over
    finally:
        sim.close()


def test_second_backend_goes_to_a_subprocess(merge_net: MergeNet) -> None:
    first = make_backend(merge_net)
    assert isinstance(first, SumoBackend)
    first.reset(_one_car("main", 50.0, 10.0))
    first.step()
    second = make_backend(merge_net)
    try:
        assert isinstance(second, SubprocessBackend)
        second.reset(Scenario("other", (VehicleSpec("other", "merge", 60.0, 5.0),)))
        second.step()
        for _ in range(10):
            first.set_speeds({"ego": 10.0})
            second.set_speeds({"other": 5.0})
            first.step()
            second.step()
        a, b = first.vehicle_states(), second.vehicle_states()
        assert a.ids == ("ego",) and a.edge == ("main",)
        assert b.ids == ("other",) and b.edge == ("merge",)
        assert a.lane_pos_m[0] == pytest.approx(50.0 + 10 * 10.0 * STEP_LENGTH_S, abs=1e-6)
        assert b.lane_pos_m[0] == pytest.approx(60.0 + 10 * 5.0 * STEP_LENGTH_S, abs=1e-6)

        # Opening SumoBackend directly a second time in this process is refused.
        third = SumoBackend(merge_net)
        with pytest.raises(SimulationError, match="already open"):
            third.reset(_one_car("main", 50.0, 10.0))
        assert first.vehicle_states().ids == ("ego",)  # the first one is untouched
    finally:
        second.close()
        first.close()
    with pytest.raises(SimulationError):
        second.step()
    assert not slot_taken()


def test_safety_mask_makes_the_later_car_yield_at_the_merge(merge_net: MergeNet) -> None:
    # Level 20 m before the merge point, both driven by plain IDM (which ignores the other road): under
    # the literal own-lane mask they met side by side on the junction; the other-road front car makes the
    # merge car (level cars: main goes first) brake, and both finish. That is the merge-aware shield, not
    # the paper's own-lane mask (the default; tests/test_safety_mask.py has the own-lane collision).
    sim, scenario = _level_pair(merge_net, start_pos_m=230.0, speed_mps=10.0, safety_mask="merge_aware")
    try:
        sim.reset(scenario)
        ended: dict[str, str] = {}
        first_masks = dict(zip(sim.active_agents, sim.observe()[1].tolist(), strict=True))
        assert first_masks["m"][DA0] == 1 and first_masks["g"][DA0] == 0
        while sim.active_agents:
            agents = sim.active_agents
            _, masks = sim.observe(agents)
            prev = np.array([sim.prev_accel(a) for a in agents])
            actions = BASELINES["idm"](sim.snapshot, sim.snapshot.index(agents), prev, masks)
            out = sim.step(dict(zip(agents, actions.tolist(), strict=True)))
            ended.update(out.end_reason)
            assert out.collisions == []
        assert ended == {"m": "finished", "g": "finished"}
        assert list(ended) == ["m", "g"]  # the main car went first
    finally:
        sim.close()
