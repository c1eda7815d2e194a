"""The paper's traffic (8 cars split over the roads, random entry times, random priorities) and staggered
departures everywhere: the generator, the engine, the evaluator, the environments, scenario files."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from idas_sumo.baselines.policies import RuleBasedPolicy
from idas_sumo.env.actions import safety_bound
from idas_sumo.env.engine import EnvConfig, MergeEngine
from idas_sumo.env.episodes import run_episodes
from idas_sumo.env.scenario import Scenario, TrafficConfig, VehicleSpec, generate_scenario, load_scenario
from idas_sumo.errors import InputError
from idas_sumo.evaluation.protocol import EvalCase, eval_jobs, load_eval_config, run_jobs
from idas_sumo.resources import SCENARIO_DIR

LIMITS = {"main": 20.0, "merge": 15.0}


def _draw(n: int, traffic: TrafficConfig | None = None, seed: int = 0) -> list[Scenario]:
    rng = np.random.default_rng(seed)
    return [generate_scenario(rng, traffic or TrafficConfig(), LIMITS) for _ in range(n)]


def test_paper_traffic_counts_entries_and_priorities() -> None:
    splits: set[int] = set()
    prios: set[tuple[int, int]] = set()
    later = at_start = 0
    for s in _draw(400):
        prios.add((s.main_prio, s.merge_prio))
        assert len(s.vehicles) == 8 and all(v.controlled for v in s.vehicles)
        n_main = sum(v.road == "main" for v in s.vehicles)
        assert 1 <= n_main <= 7
        splits.add(n_main)
        for v in s.vehicles:
            assert -2.0 <= v.b_type <= 2.0
            assert 0.0 <= v.speed_mps <= LIMITS[v.road] + 1e-3
            if v.depart_s == 0.0:
                at_start += 1
                assert 5.0 <= v.start_pos_m <= 200.0
            else:
                later += 1
                assert v.start_pos_m == 5.0  # enters at its road's start
                assert round(v.depart_s / 0.2, 6) == round(v.depart_s / 0.2)  # on a SUMO step
    assert splits == set(range(1, 8))
    assert {(1, 0), (1, 1), (0, 0)} <= prios
    assert 0.4 < later / (later + at_start) < 0.6  # p_depart_later = 0.5


def test_paper_traffic_is_deterministic_per_seed() -> None:
    assert _draw(5, seed=4) == _draw(5, seed=4)
    assert _draw(5, seed=4) != _draw(5, seed=5)


def test_later_entries_keep_their_distance_and_need_no_brake() -> None:
    """Each later entry appears at least min_start_gap_m behind the car ahead of it on its road (that car
    taken at constant speed, at least 1 m/s, since its own start), at a speed IDM does not brake from."""
    checked = 0
    for s in _draw(300, seed=2):
        for road in ("main", "merge"):
            cars = [v for v in s.vehicles if v.road == road]
            now = sorted((v for v in cars if v.depart_s == 0.0), key=lambda v: v.start_pos_m)
            queue = now[:1] + sorted((v for v in cars if v.depart_s > 0.0), key=lambda v: v.depart_s)
            for ahead, car in itertools.pairwise(queue):
                if car.depart_s == 0.0:
                    continue
                moved = max(ahead.speed_mps, 1.0) * (car.depart_s - ahead.depart_s)
                gap = ahead.start_pos_m + moved - 5.0 - car.start_pos_m
                assert gap >= 15.0 - 1e-6
                assert safety_bound([car.speed_mps], [gap], [ahead.speed_mps])[0] >= -0.01
                checked += 1
    assert checked > 100


def _slowest_ahead(ahead: VehicleSpec, elapsed_s: float, floor_mps: float = 3.0) -> tuple[float, float]:
    """Where and how fast the car ahead is ``elapsed_s`` after its start had it slowed at 2 m/s² (the
    strongest deceleration short of a hard brake) down to ``floor_mps``: worked out here, not imported."""
    v = max(ahead.speed_mps, floor_mps)
    slowing = (v - floor_mps) / 2.0
    if elapsed_s <= slowing:
        return ahead.start_pos_m + v * elapsed_s - elapsed_s**2, v - 2.0 * elapsed_s
    return ahead.start_pos_m + (v * v - floor_mps**2) / 4.0 + floor_mps * (elapsed_s - slowing), floor_mps


def _entry_pairs(s: Scenario) -> list[tuple[VehicleSpec, VehicleSpec]]:
    """(car ahead, later entry) on each road, the car ahead of the first entry the rearmost one at t = 0."""
    pairs = []
    for road in ("main", "merge"):
        cars = [v for v in s.vehicles if v.road == road]
        now = sorted((v for v in cars if v.depart_s == 0.0), key=lambda v: v.start_pos_m)
        queue = now[:1] + sorted((v for v in cars if v.depart_s > 0.0), key=lambda v: v.depart_s)
        pairs += [(ahead, car) for ahead, car in itertools.pairwise(queue) if car.depart_s > 0.0]
    return pairs


def test_feasible_entries_hold_against_a_car_ahead_that_slowed() -> None:
    """entries = "feasible" (the default): each later entry appears at least min_start_gap_m behind where the car ahead would
    be had it slowed at 2 m/s² to 3 m/s since its start, at a speed IDM does not brake from behind it. The same
    draw otherwise: cars, positions, types and t = 0 speeds as "as_drawn", whose entries miss this often."""
    feasible = _draw(300, seed=2)  # the default
    as_drawn = _draw(300, TrafficConfig(entries="as_drawn"), seed=2)
    checked = missed = 0
    for f, a in zip(feasible, as_drawn, strict=True):
        assert [(v.id, v.start_pos_m, v.b_type) for v in f.vehicles] == [
            (v.id, v.start_pos_m, v.b_type) for v in a.vehicles
        ]
        assert [v.speed_mps for v in f.vehicles if v.depart_s == 0.0] == [
            v.speed_mps for v in a.vehicles if v.depart_s == 0.0
        ]
        for scenario, counts in ((f, True), (a, False)):
            for ahead, car in _entry_pairs(scenario):
                pos, speed = _slowest_ahead(ahead, car.depart_s - ahead.depart_s)
                gap = pos - 5.0 - car.start_pos_m
                holds = gap >= 15.0 - 1e-6 and safety_bound([car.speed_mps], [gap], [speed])[0] >= -0.01
                if counts:
                    assert holds, (scenario.name, car.id)
                    checked += 1
                else:
                    missed += not holds
    assert checked > 100 and missed > 10


def test_entries_is_checked() -> None:
    with pytest.raises(ValueError, match="entries"):
        TrafficConfig(entries="sometimes")  # type: ignore[arg-type]


def test_no_later_entries_means_everyone_at_t0() -> None:
    for s in _draw(50, TrafficConfig(p_depart_later=0.0)):
        assert all(v.depart_s == 0.0 for v in s.vehicles)


def test_traffic_config_is_checked() -> None:
    with pytest.raises(ValueError, match="cannot be split"):
        TrafficConfig(n_vehicles=9, max_vehicles_per_road=4)
    with pytest.raises(ValueError, match="max_depart_s"):
        TrafficConfig(max_depart_s=0.0)
    with pytest.raises(ValueError, match="p_depart_later"):
        TrafficConfig(p_depart_later=1.5)


def test_dense_config_is_the_first_generator() -> None:
    dense = load_eval_config(SCENARIO_DIR / "eval_dense.toml")
    assert dense.env.safety_mask == "merge_aware"
    first = TrafficConfig(n_vehicles=0, min_vehicles_per_road=2, max_vehicles_per_road=8)
    assert _draw(20, dense.traffic) == _draw(20, first)
    for s in _draw(100, dense.traffic):
        assert all(v.depart_s == 0.0 for v in s.vehicles)
        for road in ("main", "merge"):
            assert 2 <= sum(v.road == road for v in s.vehicles) <= 8
    paper = load_eval_config(SCENARIO_DIR / "eval_paper.toml")
    assert paper.traffic == TrafficConfig() and paper.env.safety_mask == "own_lane"


@pytest.mark.parametrize("bad", ["", "a b", "a<b", "x&y", 'q"', "it's"])
def test_vehicle_ids_are_checked_in_scenario_files(tmp_path: Path, bad: str) -> None:
    path = tmp_path / "bad.toml"
    escaped = bad.replace("\\", "\\\\").replace('"', '\\"')
    path.write_text(f'[[vehicles]]\nid = "{escaped}"\nroad = "main"\nstart_pos_m = 10.0\nspeed_mps = 5.0\n')
    with pytest.raises(InputError) as err:
        load_scenario(path)
    assert str(path) in str(err.value) and repr(bad) in str(err.value)


def test_a_bad_vehicle_id_is_exit_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from idas_sumo.cli import main

    path = tmp_path / "bad.toml"
    path.write_text('[[vehicles]]\nid = "a b"\nroad = "main"\nstart_pos_m = 10.0\nspeed_mps = 5.0\n')
    assert main(["evaluate", "--baseline", "idm", "--scenario", str(path), "--out", str(tmp_path / "o")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and "'a b'" in lines[0]


# A car that departs onto another (SUMO removes both as they collide) and one that departs after the
# timeout. Before the fix the engine put the removed car among the acting agents: KeyError in observe().
LATE = Scenario(
    "late",
    (
        VehicleSpec("a", "main", 10.0, 10.0),
        VehicleSpec("b", "main", 30.0, 10.0, depart_s=2.0),
        VehicleSpec("c", "merge", 10.0, 10.0, depart_s=100.0),
        VehicleSpec("d", "merge", 100.0, 12.0),
    ),
)


@pytest.mark.sumo
@pytest.mark.parametrize("copies", [1, 2])
def test_a_car_entering_onto_another_and_one_after_the_timeout(net_path: Path, copies: int) -> None:
    engine = MergeEngine(net_path, copies=copies, config=EnvConfig(max_episode_s=30.0))
    try:
        outcomes = run_episodes(engine, [LATE] * copies, lambda j, a: 0, [RuleBasedPolicy("idm")])
    finally:
        engine.close()
    for outcome in outcomes:
        assert outcome.end_reasons["a"] == outcome.end_reasons["b"] == "collided"
        assert outcome.end_reasons["d"] == "finished"
        # c never entered: no end reason, not finished, so the scenario is not a success (and it timed out).
        assert "c" not in outcome.end_reasons and not outcome.all_finished
        assert outcome.timed_out and not outcome.success
        assert outcome.collisions == 1


@pytest.mark.sumo
def test_the_evaluator_runs_late_entries(net_path: Path) -> None:
    engine = MergeEngine(net_path, copies=2, config=EnvConfig(max_episode_s=30.0))
    try:
        cases = [EvalCase(LATE, "c", 0, ("c",)), EvalCase(LATE, "d", 0, ("d",))]
        policy = RuleBasedPolicy("idm")
        results = list(run_jobs(engine, eval_jobs(cases, ["idm"]), {"idm": policy}, policy))
    finally:
        engine.close()
    rows = [r.episode for _, r in results]
    assert [r["success"] for r in rows] == [0, 0]
    assert np.isnan(rows[0]["ego_finish_time_s"])  # the ego never entered  # type: ignore[arg-type]


@pytest.mark.sumo
def test_staggered_traffic_gives_the_same_outcomes_side_by_side(net_path: Path) -> None:
    scenarios = _draw(6, seed=9)
    assert any(v.depart_s > 0 for s in scenarios for v in s.vehicles)
    runs = []
    for copies in (1, 3):
        engine = MergeEngine(net_path, copies=copies, config=EnvConfig(max_episode_s=40.0))
        try:
            runs.append(run_episodes(engine, scenarios, lambda j, a: 0, [RuleBasedPolicy("idm")]))
        finally:
            engine.close()
    for one, three in zip(*runs, strict=True):
        assert one.end_reasons == three.end_reasons
        assert one.finish_times_s == three.finish_times_s
        assert (one.collisions, one.hard_brakes, one.impedes) == (
            three.collisions,
            three.hard_brakes,
            three.impedes,
        )


@pytest.mark.sumo
def test_gym_env_refuses_an_ego_that_never_drives(net_path: Path) -> None:
    from idas_sumo.env.gym_env import MergeEnv

    env = MergeEnv(net_path, scenario=LATE, ego="c", config=EnvConfig(max_episode_s=10.0))
    try:
        with pytest.raises(ValueError, match="never drives"):
            env.reset(seed=0)
    finally:
        env.close()


@pytest.mark.sumo
def test_gym_env_draws_again_until_its_ego_drives(net_path: Path) -> None:
    """With a 3 s timeout many random egos would enter too late: reset draws until the ego acts."""
    from idas_sumo.env.gym_env import MergeEnv

    env = MergeEnv(net_path, traffic=TrafficConfig(p_depart_later=0.8), config=EnvConfig(max_episode_s=3.0))
    try:
        for seed in range(6):
            obs, info = env.reset(seed=seed)
            assert info["ego"] in env.sim.active_agents
            assert obs.shape == env.observation_space.shape
    finally:
        env.close()
