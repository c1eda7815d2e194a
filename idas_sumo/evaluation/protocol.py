"""The paper's evaluation protocol: scenarios from a seed, one ego per scenario running the method,
every other vehicle running ``others``; every method acts through the same masks.

Every (method, case) pair is one job of the episode engine (env/engine.py), which runs ``copies`` of
them side by side in one SUMO run; each job's numbers are those of its scenario alone, so the CSVs do
not depend on ``copies``."""

from __future__ import annotations

import functools
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
import pandas as pd

from idas_sumo.baselines.policies import EGO_ONLY_BASELINES
from idas_sumo.config import MAX_SCENARIOS, from_dict, load_toml
from idas_sumo.env.config import EnvConfig
from idas_sumo.env.engine import (
    AgentBatch,
    EpisodeOutcome,
    MergeEngine,
    Policy,
    StepResult,
)
from idas_sumo.env.episodes import EpisodeObserver, iter_episodes
from idas_sumo.env.rewards import FINISH_DISTANCE_PAST_MERGE_M, RewardConfig
from idas_sumo.env.scenario import (
    Road,
    Scenario,
    TrafficConfig,
    VehicleSpec,
    generate_scenario,
    load_scenario,
)
from idas_sumo.env.snapshot import ROAD_NAMES
from idas_sumo.errors import InputError
from idas_sumo.evaluation.metrics import TRAJECTORY_COLUMNS, EpisodeFacts, episode_row, flow_row
from idas_sumo.evaluation.sweep import DEFAULT_SWEEP_OFFSETS, sweep_scenarios
from idas_sumo.resources import SCENARIO_DIR

Suite = Literal["paper", "representative", "driver-types"]
SUITES: tuple[str, ...] = ("paper", "representative", "driver-types")
REPRESENTATIVE = ("s1", "s2", "s3", "s4")
DEFAULT_PAPER_SCENARIOS = 100
"""The paper suite's size (the paper's 100 random scenarios) when ``--scenarios`` is not given."""
DEFAULT_SUITE_SIZE: dict[str, int] = {"paper": DEFAULT_PAPER_SCENARIOS, "driver-types": DEFAULT_SWEEP_OFFSETS}
"""``--scenarios`` when not given: random scenarios of the paper suite, start offsets per b_type of the
driver-types suite (the representative suite has its four)."""


@dataclass(frozen=True)
class EvalCase:
    """One scenario to run every method on; ``method_vehicles`` run the method, the rest ``others``."""

    scenario: Scenario
    ego: str
    seed: int
    method_vehicles: tuple[str, ...]


@dataclass(frozen=True)
class EvalConfig:
    """``evaluate --config FILE.toml``: how the paper suite's random scenarios are drawn, and the episode
    rules as flat keys (``max_episode_s``: a timeout is not a success; ``safety_mask``: which car every
    method's mask follows, ``--safety-mask`` overrides it)."""

    FLAT_FIELDS: ClassVar[tuple[str, ...]] = ("env",)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    env: EnvConfig = field(default_factory=EnvConfig)

    def __post_init__(self) -> None:
        if self.env.reward != RewardConfig():
            raise ValueError("[reward]: every method is scored by the paper's reward (no [reward] table)")
        if self.env.junction is not None:
            raise ValueError("junction: the merge evaluated is the command's --junction")


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
    suite: Suite,
    n_scenarios: int,
    seed: int,
    speed_limits: dict,
    traffic: TrafficConfig,
    road_lengths_m: Mapping[str, float] | None = None,
    start_room_m: Mapping[Road, float] | None = None,
) -> list[EvalCase]:
    """The cases of a suite; the same cases (same scenarios, same egos) for every method.

    ``n_scenarios``: random scenarios of the paper suite; start offsets per b_type of the driver-types
    suite (evaluation/sweep.py), which needs the net's ``road_lengths_m`` to place its cars in projection.
    ``start_room_m``: each road's room for the paper suite's starts (``generate_scenario``).
    At most ``MAX_SCENARIOS``, as on the command line: the cases are drawn up front.
    """
    if not 0 <= n_scenarios <= MAX_SCENARIOS:
        raise InputError(f"scenarios: expected at most {MAX_SCENARIOS}, got {n_scenarios}")
    if suite == "paper":
        cases = []
        for i in range(n_scenarios):
            rng = np.random.default_rng([seed, i])
            scenario = generate_scenario(
                rng, traffic, speed_limits, name=f"paper-{i:03d}", start_room_m=start_room_m
            )
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
    if road_lengths_m is None:
        raise ValueError("the driver-types suite needs the net's road lengths")
    # The merge car runs the method; the main car, the others' method (IDAS by default).
    return [
        EvalCase(case.scenario, case.merge_car, seed, (case.merge_car,))
        for case in sweep_scenarios(n_scenarios, seed, speed_limits, road_lengths_m)
    ]


@dataclass
class EpisodeResult:
    episode: dict[str, object]
    """The episode's ``episodes.csv`` row."""
    flow: dict[str, object]
    """Its ``flow.csv`` row."""
    trajectory: pd.DataFrame = field(repr=False)
    """Every vehicle's row at every decision (``TRAJECTORY_COLUMNS``); ``no_trajectory()`` where it
    was not kept (an evaluation worker without ``--trajectories``)."""


@functools.cache
def no_trajectory() -> pd.DataFrame:
    """The one empty trajectory that stands for every dropped one (so a result costs its rows only)."""
    return pd.DataFrame(columns=list(TRAJECTORY_COLUMNS))


@dataclass(frozen=True)
class EvalJob:
    """One episode of an evaluation: ``case`` with ``method`` driving ``case.method_vehicles``."""

    method: str
    case: EvalCase


def eval_jobs(cases: Sequence[EvalCase], methods: Sequence[str]) -> list[EvalJob]:
    """Every (method, case) pair, method by method (the CSVs' row order)."""
    jobs = []
    for method in methods:
        for case in cases:
            if method in EGO_ONLY_BASELINES:  # no driver type: the paper runs FSM+IDM on one car only
                case = replace(case, method_vehicles=(case.ego,))
            jobs.append(EvalJob(method, case))
    return jobs


def _free_flow_times(engine: MergeEngine, vehicles: tuple[VehicleSpec, ...]) -> dict[str, float]:
    out_limit = engine.out_limit_mps
    times = {}
    for v in vehicles:
        to_merge = engine.road_lengths_m[v.road] - v.start_pos_m
        times[v.id] = to_merge / engine.speed_limits_mps[v.road] + FINISH_DISTANCE_PAST_MERGE_M / out_limit
    return times


class _Recorder:
    """The engine observer of an evaluation: every vehicle's row at each step a job's agents decide,
    and at its end; the job's ``EpisodeResult`` once it is over."""

    def __init__(self, jobs: Sequence[EvalJob], also: EpisodeObserver | None = None) -> None:
        self.jobs = jobs
        self.also = also
        """A further observer, called after this one (a replay's marks, evaluation/replay.py)."""
        self.rows: dict[int, list[tuple[object, ...]]] = {}
        self.results: dict[int, EpisodeResult] = {}

    def decided(
        self, engine: MergeEngine, jobs: Sequence[int], batch: AgentBatch, actions: np.ndarray
    ) -> None:
        copies = batch.copy.tolist()
        chosen = actions.tolist()
        per_copy: dict[int, tuple[dict[str, int], dict[str, str]]] = {}
        for i, (a, k) in enumerate(zip(batch.ids, copies, strict=True)):
            acts, masks = per_copy.setdefault(k, ({}, {}))
            acts[a] = chosen[i]
            masks[a] = "".join(map(str, batch.masks[i].tolist()))
        for k, (acts, masks) in per_copy.items():
            self._record(engine, k, jobs[k], acts, masks)
        if self.also is not None:
            self.also.decided(engine, jobs, batch, actions)

    def stepped(
        self,
        engine: MergeEngine,
        jobs: Sequence[int],
        batch: AgentBatch,
        actions: np.ndarray,
        result: StepResult,
    ) -> None:
        if self.also is not None:
            self.also.stepped(engine, jobs, batch, actions, result)

    def ended(self, engine: MergeEngine, slot: int, job: int, outcome: EpisodeOutcome) -> None:
        self._record(engine, slot, job, {}, {})
        self.results[job] = _result(engine, self.jobs[job], outcome, self.rows.pop(job))
        if self.also is not None:
            self.also.ended(engine, slot, job, outcome)

    def _record(
        self, engine: MergeEngine, k: int, job: int, actions: dict[str, int], masks: dict[str, str]
    ) -> None:
        snap = engine.snapshot
        case = self.jobs[job].case
        method = self.jobs[job].method
        method_set = set(case.method_vehicles)
        controlled = set(case.scenario.controlled_ids)
        t = round(engine.time_s, 3)
        rows = self.rows.setdefault(job, [])
        span = engine.rows_of(k)
        for i in range(span.start, span.stop):
            vid = snap.ids[i]
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
                    masks.get(vid, ""),
                )
            )


def _result(
    engine: MergeEngine, job: EvalJob, outcome: EpisodeOutcome, rows: list[tuple[object, ...]]
) -> EpisodeResult:
    """Measure one finished episode."""
    case = job.case
    scenario = case.scenario
    trajectory = pd.DataFrame(rows, columns=list(TRAJECTORY_COLUMNS))
    ego_spec = next(v for v in scenario.vehicles if v.id == case.ego)
    facts = EpisodeFacts(
        scenario=scenario.name,
        seed=case.seed,
        method=job.method,
        ego_id=case.ego,
        ego_road=ego_spec.road,
        ego_prio=scenario.prio(ego_spec.road),
        ego_type=ego_spec.b_type,
        collisions=outcome.collisions,
        hard_brakes=outcome.hard_brakes,
        hard_brakes_merge_zone=outcome.hard_brakes_merge_zone,
        impedes=outcome.impedes,
        all_finished=outcome.all_finished,
        ego_total_reward=outcome.returns.get(case.ego, 0.0),
        duration_s=outcome.duration_s,
        start_time_s=outcome.start_time_s,
        free_flow_time_s=_free_flow_times(engine, scenario.vehicles),
        timed_out=outcome.timed_out,
        ego_end_reason=outcome.end_reasons.get(case.ego, ""),
    )
    return EpisodeResult(episode_row(trajectory, facts), flow_row(trajectory, facts), trajectory)


def iterate_runs(
    engine: MergeEngine,
    cases: list[EvalCase],
    methods: dict[str, Policy],
    others_policy: Policy,
    tripinfo_dir: Path | None = None,
) -> Iterator[tuple[str, EvalCase, EpisodeResult]]:
    """Every (method, case) pair in a fixed order (method by method); results are yielded in that order
    as they complete. ``tripinfo_dir`` (SUMO's own per-episode output) needs an engine with one copy."""
    for job, result in run_jobs(
        engine, eval_jobs(cases, list(methods)), methods, others_policy, tripinfo_dir
    ):
        yield job.method, job.case, result


def tripinfo_path(directory: Path, job: EvalJob) -> Path:
    """Where SUMO writes ``job``'s own tripinfo output (``evaluate --sumo-output``)."""
    return directory / f"{job.method}-{job.case.scenario.name}.tripinfo.xml"


def run_jobs(
    engine: MergeEngine,
    jobs: Sequence[EvalJob],
    methods: dict[str, Policy],
    others_policy: Policy,
    tripinfo_dir: Path | None = None,
    observer: EpisodeObserver | None = None,
    sumo_options: Sequence[str] = (),
) -> Iterator[tuple[EvalJob, EpisodeResult]]:
    """Run ``jobs`` on the engine, ``engine.copies`` at a time; yield their results in job order.

    ``observer`` sees every step too; ``sumo_options`` go to every SUMO run (an engine with one copy,
    like ``tripinfo_dir``): a replay's sumo-gui settings."""
    names = list(methods)
    policies = [*methods.values(), others_policy]
    others = len(names)
    method_sets = [frozenset(job.case.method_vehicles) for job in jobs]
    method_index = [names.index(job.method) for job in jobs]

    def assign(j: int, agent: str) -> int:
        return method_index[j] if agent in method_sets[j] else others

    sumo_args = None
    if tripinfo_dir is not None or sumo_options:
        directory = tripinfo_dir

        def sumo_args(j: int) -> tuple[str, ...]:
            if directory is None:
                return tuple(sumo_options)
            job = jobs[j]
            return (
                *sumo_options,
                "--tripinfo-output",
                str(tripinfo_path(directory, job)),
                # The episode ends before every car has left the net; report those cars too.
                "--tripinfo-output.write-unfinished",
            )

    recorder = _Recorder(jobs, observer)
    for j, _ in iter_episodes(
        engine, [job.case.scenario for job in jobs], assign, policies, recorder, sumo_args
    ):
        yield jobs[j], recorder.results.pop(j)
