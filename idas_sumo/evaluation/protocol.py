"""The paper's evaluation protocol: scenarios from a seed, one ego per scenario running the method,
every other vehicle running ``others``; every method acts through the same masks."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from idas_sumo.config import from_dict, load_toml
from idas_sumo.env.core import DEFAULT_MAX_EPISODE_S, MergeSimulation
from idas_sumo.env.rewards import FINISH_DISTANCE_PAST_MERGE_M
from idas_sumo.env.scenario import (
    B_TYPE_RANGE,
    Scenario,
    TrafficConfig,
    VehicleSpec,
    generate_scenario,
    load_scenario,
)
from idas_sumo.env.snapshot import ROAD_NAMES
from idas_sumo.evaluation.metrics import TRAJECTORY_COLUMNS, EpisodeFacts, episode_row, flow_row
from idas_sumo.evaluation.policies import PolicyFn
from idas_sumo.resources import SCENARIO_DIR

Suite = Literal["paper", "representative", "driver-types"]
SUITES: tuple[str, ...] = ("paper", "representative", "driver-types")
REPRESENTATIVE = ("s1", "s2", "s3", "s4")
DRIVER_TYPE_SWEEP = tuple(float(x) for x in np.linspace(*B_TYPE_RANGE, 9))


@dataclass(frozen=True)
class EvalCase:
    """One scenario to run every method on; ``method_vehicles`` run the method, the rest ``others``."""

    scenario: Scenario
    ego: str
    seed: int
    method_vehicles: tuple[str, ...]


@dataclass(frozen=True)
class EvalConfig:
    """``evaluate --config FILE.toml``: how the paper suite's random scenarios are drawn, and the timeout."""

    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    max_episode_s: float = DEFAULT_MAX_EPISODE_S
    """Simulated seconds before an episode is cut off (a timeout is not a success)."""

    def __post_init__(self) -> None:
        if not self.max_episode_s > 0:
            raise ValueError(f"max_episode_s must be positive, got {self.max_episode_s}")


def load_eval_config(path: Path) -> EvalConfig:
    return from_dict(EvalConfig, load_toml(path), str(path))


def file_cases(paths: list[Path], seed: int, speed_limits: dict) -> list[EvalCase]:
    """One case per scenario file; the ego (running the method) is the file's first vehicle."""
    cases = []
    for path in paths:
        scenario = load_scenario(path, speed_limits)
        cases.append(EvalCase(scenario, scenario.vehicles[0].id, seed, (scenario.vehicles[0].id,)))
    return cases


def suite_cases(
    suite: Suite, n_scenarios: int, seed: int, speed_limits: dict, traffic: TrafficConfig
) -> list[EvalCase]:
    """The cases of a suite; the same cases (same scenarios, same egos) for every method."""
    if suite == "paper":
        cases = []
        for i in range(n_scenarios):
            rng = np.random.default_rng([seed, i])
            scenario = generate_scenario(rng, traffic, speed_limits, name=f"paper-{i:03d}")
            ego = str(rng.choice([v.id for v in scenario.vehicles]))
            cases.append(EvalCase(scenario, ego, seed, (ego,)))
        return cases
    if suite == "representative":
        cases = []
        for name in REPRESENTATIVE:
            scenario = load_scenario(SCENARIO_DIR / "representative" / f"{name}.toml", speed_limits)
            merge_car = next(v.id for v in scenario.vehicles if v.road == "merge")
            cases.append(EvalCase(scenario, merge_car, seed, tuple(v.id for v in scenario.vehicles)))
        return cases
    base = load_scenario(SCENARIO_DIR / "representative" / "s1.toml", speed_limits)
    cases = []
    for b_type in DRIVER_TYPE_SWEEP:
        vehicles = tuple(replace(v, b_type=b_type) if v.road == "merge" else v for v in base.vehicles)
        scenario = Scenario(f"s1-btype{b_type:+.1f}", vehicles, base.main_prio, base.merge_prio)
        merge_car = next(v.id for v in vehicles if v.road == "merge")
        cases.append(EvalCase(scenario, merge_car, seed, (merge_car,)))
    return cases


@dataclass
class EpisodeResult:
    episode: dict[str, object]
    flow: dict[str, object]
    trajectory: pd.DataFrame = field(repr=False)


def _free_flow_times(sim: MergeSimulation, vehicles: tuple[VehicleSpec, ...]) -> dict[str, float]:
    out_limit = sim.net.out.speed_limit_mps
    times = {}
    for v in vehicles:
        to_merge = sim.road_lengths_m[v.road] - v.start_pos_m
        times[v.id] = to_merge / sim.speed_limits_mps[v.road] + FINISH_DISTANCE_PAST_MERGE_M / out_limit
    return times


def run_case(
    sim: MergeSimulation,
    case: EvalCase,
    method: str,
    method_policy: PolicyFn,
    others_policy: PolicyFn,
    sumo_args: tuple[str, ...] = (),
) -> EpisodeResult:
    """Run one episode and measure it."""
    scenario = case.scenario
    sim.reset(scenario, sumo_args)
    start = sim.time_s
    rows: list[tuple[object, ...]] = []
    collisions = hard_brakes = merge_zone_brakes = impedes = 0
    ego_reward = 0.0
    method_set = set(case.method_vehicles)
    controlled = {v.id for v in scenario.vehicles if v.controlled}
    while True:
        agents = sim.active_agents
        obs, masks = sim.observe(agents)
        actions: dict[str, int] = {}
        mine = [i for i, a in enumerate(agents) if a in method_set]
        theirs = [i for i, a in enumerate(agents) if a not in method_set]
        for idx, policy in ((mine, method_policy), (theirs, others_policy)):
            if idx:
                ids = [agents[i] for i in idx]
                chosen = policy(sim, ids, obs[idx], masks[idx])
                actions.update({a: int(c) for a, c in zip(ids, chosen, strict=True)})
        _record(rows, sim, actions, dict(zip(agents, masks, strict=True)), method_set, method, controlled)
        if sim.episode_over:
            break
        outcome = sim.step(actions)
        collisions += len(outcome.collisions)
        hard_brakes += len(outcome.hard_brakes)
        merge_zone_brakes += outcome.hard_brakes_merge_zone
        impedes += sum(1 for parts in outcome.reward_parts.values() if parts["impede"] < 0)
        if case.ego in outcome.rewards:
            ego_reward += outcome.rewards[case.ego]
    trajectory = pd.DataFrame(rows, columns=list(TRAJECTORY_COLUMNS))
    ego_spec = next(v for v in scenario.vehicles if v.id == case.ego)
    facts = EpisodeFacts(
        scenario=scenario.name,
        seed=case.seed,
        method=method,
        ego_id=case.ego,
        ego_road=ego_spec.road,
        ego_prio=scenario.prio(ego_spec.road),
        ego_type=ego_spec.b_type,
        collisions=collisions,
        hard_brakes=hard_brakes,
        hard_brakes_merge_zone=merge_zone_brakes,
        impedes=impedes,
        all_finished=all(reason == "finished" for reason in sim.finished_agents.values())
        and not sim.active_agents,
        ego_total_reward=ego_reward,
        duration_s=sim.time_s - start,
        start_time_s=start,
        free_flow_time_s=_free_flow_times(sim, scenario.vehicles),
    )
    return EpisodeResult(episode_row(trajectory, facts), flow_row(trajectory, facts), trajectory)


def _record(
    rows: list[tuple[object, ...]],
    sim: MergeSimulation,
    actions: dict[str, int],
    masks: dict[str, np.ndarray],
    method_set: set[str],
    method: str,
    controlled: set[str],
) -> None:
    snap = sim.snapshot
    t = round(sim.time_s, 3)
    for i, vid in enumerate(snap.ids):
        mask = masks.get(vid)
        rows.append(
            (
                t,
                vid,
                vid in controlled,
                method if vid in method_set else ("others" if vid in controlled else "sumo"),
                ROAD_NAMES[int(snap.road[i])],
                round(float(snap.dist_to_merge_m[i]), 3),
                round(float(snap.speed_mps[i]), 4),
                round(float(snap.accel_mps2[i]), 4),
                actions.get(vid, -1),
                "".join(str(int(b)) for b in mask) if mask is not None else "",
            )
        )


def iterate_runs(
    sim: MergeSimulation,
    cases: list[EvalCase],
    methods: dict[str, PolicyFn],
    others_policy: PolicyFn,
    tripinfo_dir: Path | None = None,
) -> Iterator[tuple[str, EvalCase, EpisodeResult]]:
    """Every (method, case) pair in a fixed order; results are yielded as they complete."""
    for method, policy in methods.items():
        for case in cases:
            args: tuple[str, ...] = ()
            if tripinfo_dir is not None:
                args = (
                    "--tripinfo-output",
                    str(tripinfo_dir / f"{method}-{case.scenario.name}.tripinfo.xml"),
                    # The episode ends before every car has left the net; report those cars too.
                    "--tripinfo-output.write-unfinished",
                )
            if method == "fsm_idm":  # FSM+IDM has no driver type: the paper runs it on one car only
                case = replace(case, method_vehicles=(case.ego,))
            yield method, case, run_case(sim, case, method, policy, others_policy, args)
