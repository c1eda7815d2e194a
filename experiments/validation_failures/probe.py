"""Which held-out scenarios fail, why, and whether any policy could have finished them (issue 36, "the ceiling").

Runs training's validation exactly as ``idas-sumo train`` computes it (``validation_tasks`` of the recipe's
intelligent traffic, its episode rules, every car on the method, the greedy actor through the same
``_LearningPolicy`` and episode loop as ``training/workers.py``), but through the evaluation's recorder so that
every car's row at every decision (road, distance to the merge, speed, action, allowed actions) is kept. Methods:
checkpoints by path (``--checkpoint [LABEL=]PATH``, read only) and methods by name (``--method``: ``warm_start``
and the other shipped policies, or the rules ``idm``, ``fsm_idm``, ``fsm_idm_smooth``).

For every scenario it also computes a bound that no policy can beat: each car driven alone on the empty road
(its own entry time, place and speed) by ``Fastest`` (the highest allowed acceleration step, every step), with
no time limit. A scenario whose slowest such car finishes after ``max_episode_s`` cannot succeed whatever the
cars do (a car behind others on its road can only be slower).

Writes to ``--out``: ``episodes.csv`` (method x scenario: outcome, the cars that timed out or collided, hard
brakes, forced hard brakes), ``scenarios.csv`` (each scenario's entries, its solo bound, which methods fail it),
``collisions.csv`` (each collided car: when, where, what its mask allowed in its last second), ``brakes.csv``
(each hard brake's first step: forced or chosen, the car ahead on either road and the road it came from),
``summary.csv`` (per method), ``cars.csv`` (each car's entry and solo finish) and, with ``--trajectories``,
``trajectories_failed.csv.gz`` (every failed episode, every car, every decision).

    python experiments/validation_failures/probe.py --out results/validation_failures \\
        --checkpoint /tmp/intelligent.pt --method warm_start --method fsm_idm_smooth [--seed 123 --scenarios 40]

Evaluation seeds (2019-2033) are refused.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from idas_sumo.agents.checkpoint_file import load_actor
from idas_sumo.agents.rollout import EpisodeStats, RolloutTask, _Collector, _LearningPolicy
from idas_sumo.baselines.policies import BASELINES, RuleBasedPolicy
from idas_sumo.env.actions import HARD_BRAKE, N_ACTIONS, RELEASE_BRAKE
from idas_sumo.env.contracts import AgentBatch, IntArray, Policy
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.episodes import run_episodes
from idas_sumo.env.rewards import FINISH_DISTANCE_PAST_MERGE_M
from idas_sumo.env.scenario import Scenario, start_room_m
from idas_sumo.evaluation.metrics import finish_times
from idas_sumo.evaluation.policies import LEARNED_METHODS
from idas_sumo.evaluation.protocol import EpisodeResult, EvalCase, EvalJob, run_jobs
from idas_sumo.resources import DEFAULT_NET, POLICY_DIR, SCENARIO_DIR
from idas_sumo.sim.merge_detect import MergeSite, choose_merge
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import TrainConfig, load_train_config
from idas_sumo.training.loop import _site_limits
from idas_sumo.training.validation import score_episodes, validation_tasks

EVALUATION_SEEDS = range(2019, 2034)
FORCED = "".join("1" if a == HARD_BRAKE else "0" for a in range(N_ACTIONS))  # the hard brake alone
LAST_SECOND_STEPS = 5  # decisions (0.2 s each) looked at before a collision
SOLO_LIMIT_S = 600.0  # the solo bound's episode: long enough for any car to finish


class Fastest:
    """The highest allowed acceleration step every step (release after a hard brake, the brake if forced):
    alone on the road, about the quickest a car may finish under its own mask."""

    ORDER = (4, 3, 2, 1, 0, RELEASE_BRAKE, HARD_BRAKE)

    def act(self, batch: AgentBatch, rows: IntArray) -> IntArray:
        masks = np.asarray(batch.masks[rows]) != 0
        ranked = masks[:, list(self.ORDER)]
        return np.asarray(self.ORDER, dtype=np.int64)[ranked.argmax(axis=1)]


@dataclasses.dataclass(frozen=True)
class Method:
    label: str
    path: Path | None  # a learned actor's weights; None: a rule
    rule: str = ""

    def policy(self, tasks: Sequence[RolloutTask]) -> Policy:
        if self.path is None:
            return RuleBasedPolicy(self.rule)
        # Validation's own policy: greedy on the compiled forward (Learner.rollout_logits), one stream per episode.
        return _LearningPolicy(load_actor(self.path), tasks)


def parse_methods(checkpoints: list[str], names: list[str]) -> list[Method]:
    methods = []
    for spec in checkpoints:
        label, _, path = spec.rpartition("=")
        p = Path(path)
        if not p.is_file():
            sys.exit(f"probe: error: {p}: no such checkpoint")
        methods.append(Method(label or f"{p.parent.name}/{p.stem}", p))
    for name in names:
        if name in BASELINES:
            methods.append(Method(name, None, name))
        elif name in LEARNED_METHODS:
            methods.append(Method(name, POLICY_DIR / LEARNED_METHODS[name]))
        else:
            sys.exit(f"probe: error: --method {name!r}: not a rule or shipped policy")
    return methods


def run_method(
    site: MergeSite, config: TrainConfig, tasks: list[RolloutTask], method: Method
) -> tuple[list[EpisodeStats], list[EpisodeResult]]:
    """Every task with every car on ``method``: validation's stats and the evaluation recorder's rows."""
    engine = MergeEngine(site, copies=config.copies, seed=config.seed, config=config.env)
    try:
        jobs = [
            EvalJob(
                method.label, EvalCase(t.scenario, t.scenario.vehicles[0].id, 0, t.scenario.controlled_ids)
            )
            for t in tasks
        ]
        collector = _Collector()
        policy = method.policy(tasks)
        results = [r for _, r in run_jobs(engine, jobs, {method.label: policy}, policy, observer=collector)]
    finally:
        engine.close()
    return [collector.episodes[j].stats for j in range(len(tasks))], results


def solo_bounds(site: MergeSite, config: TrainConfig, scenarios: list[Scenario]) -> pd.DataFrame:
    """Each car of each scenario alone on the road, driven by ``Fastest``: when it would finish."""
    solo = [
        Scenario(f"{s.name}-{v.id}", (v,), s.main_prio, s.merge_prio) for s in scenarios for v in s.vehicles
    ]
    env = dataclasses.replace(config.env, max_episode_s=SOLO_LIMIT_S)
    engine = MergeEngine(site, copies=config.copies, seed=config.seed, config=env)
    try:
        outcomes = run_episodes(engine, solo, lambda job, agent: 0, [Fastest()])
    finally:
        engine.close()
    rows = []
    for s, o in zip(solo, outcomes, strict=True):
        v = s.vehicles[0]
        rows.append(
            {
                "scenario": s.name.rsplit("-", 1)[0],
                "vehicle": v.id,
                "road": v.road,
                "depart_s": v.depart_s,
                "start_pos_m": v.start_pos_m,
                "start_speed_mps": v.speed_mps,
                "solo_finish_s": o.finish_times_s.get(v.id, np.nan),
            }
        )
    return pd.DataFrame(rows)


def scenario_table(scenarios: list[Scenario], cars: pd.DataFrame, limit_s: float) -> pd.DataFrame:
    rows = []
    for s in scenarios:
        mine = cars[cars.scenario == s.name]
        worst = mine.loc[mine.solo_finish_s.idxmax()]
        rows.append(
            {
                "scenario": s.name,
                "main_prio": s.main_prio,
                "merge_prio": s.merge_prio,
                "cars_main": int((mine.road == "main").sum()),
                "cars_merge": int((mine.road == "merge").sum()),
                "later_entries": int((mine.depart_s > 0).sum()),
                "last_entry_main_s": float(mine[mine.road == "main"].depart_s.max()),
                "last_entry_merge_s": float(mine[mine.road == "merge"].depart_s.max()),
                "solo_bound_s": round(float(worst.solo_finish_s), 2),
                "solo_bound_car": worst.vehicle,
                "finishable_alone": bool(worst.solo_finish_s <= limit_s),
            }
        )
    return pd.DataFrame(rows)


def collision_rows(label: str, scenario: str, stats: EpisodeStats, traj: pd.DataFrame) -> list[dict]:
    """Each collided car: its last decision (time, road, distance, speed), and what its mask allowed then."""
    rows = []
    for vid, reason in stats.end_reasons.items():
        if reason != "collided":
            continue
        mine = traj[(traj.vehicle == vid) & (traj.action >= 0)]
        last = mine.tail(LAST_SECOND_STEPS)
        end = mine.iloc[-1]
        rows.append(
            {
                "method": label,
                "scenario": scenario,
                "vehicle": vid,
                "time_s": end.time_s,
                "road": end.road,
                "dist_to_merge_m": end.dist_to_merge_m,
                "speed_mps": end.speed_mps,
                "last_masks": " ".join(last.allowed_actions),
                "last_actions": " ".join(map(str, last.action)),
                "forced_in_last_second": int((last.allowed_actions == FORCED).sum()),
                "chose_hard_brake_in_last_second": int(
                    ((last.action == HARD_BRAKE) & (last.allowed_actions != FORCED)).sum()
                ),
            }
        )
    return rows


def episode_row(label: str, scenario: str, stats: EpisodeStats, traj: pd.DataFrame) -> dict:
    decided = traj[traj.action >= 0]
    late = [v for v, r in stats.end_reasons.items() if r == "timeout"]
    left = (
        traj[traj.vehicle.isin(late)].groupby("vehicle").dist_to_merge_m.last() + FINISH_DISTANCE_PAST_MERGE_M
    )
    return {
        "method": label,
        "scenario": scenario,
        "success": int(stats.success),
        "perfect": int(stats.perfect),
        "collisions": stats.collisions,
        "timed_out": int(stats.timed_out),
        "end_time_s": stats.sim_time_s,
        "joint_return": round(sum(stats.reward_parts.values()), 4),
        "timeout_cars": " ".join(late),
        "timeout_most_left_m": round(float(left.max()), 2) if len(left) else np.nan,
        "last_finish_s": float(finish_times(traj).max()),
        "collided_cars": " ".join(v for v, r in stats.end_reasons.items() if r == "collided"),
        "hard_brakes": int((decided.action == HARD_BRAKE).sum()),
        "forced_hard_brakes": int(
            ((decided.action == HARD_BRAKE) & (decided.allowed_actions == FORCED)).sum()
        ),
        "cars_forced_before_free": forced_before_free(decided),
        "impede": round(stats.reward_parts["impede"], 4),
        "flow": round(stats.reward_parts["flow"], 4),
    }


def brake_rows(label: str, scenario: str, traj: pd.DataFrame) -> list[dict]:
    """Each hard brake's first step: forced or chosen, and the nearest car ahead on either road (the one r_impede
    blames) with the road it came from: another road's car is one the own-lane mask did not see coming."""
    decided = traj[traj.action >= 0]
    origin = traj.groupby("vehicle").road.first()
    rows = []
    for vid, steps in decided.groupby("vehicle", sort=False):
        braking = steps.action.to_numpy() == HARD_BRAKE
        onsets = np.flatnonzero(braking & ~np.concatenate([[False], braking[:-1]]))
        first_t = float(steps.time_s.iloc[0])
        for i in onsets.tolist():
            step = steps.iloc[i]
            now = traj[(traj.time_s == step.time_s) & (traj.vehicle != vid)]
            ahead = now[now.dist_to_merge_m < step.dist_to_merge_m]
            before = steps.iloc[max(0, i - LAST_SECOND_STEPS) : i]
            row = {
                "method": label,
                "scenario": scenario,
                "vehicle": vid,
                "origin": origin[vid],
                "time_s": step.time_s,
                "since_entry_s": round(step.time_s - first_t, 2),
                "road": step.road,
                "dist_to_merge_m": step.dist_to_merge_m,
                "speed_mps": step.speed_mps,
                "forced": int(step.allowed_actions == FORCED),
                "free_steps_last_second": int(
                    before.allowed_actions.str[:HARD_BRAKE].str.contains("1").sum()
                ),
            }
            if len(ahead):
                car = ahead.loc[ahead.dist_to_merge_m.idxmax()]
                row |= {
                    "ahead": car.vehicle,
                    "ahead_origin": origin[car.vehicle],
                    "ahead_gap_m": round(step.dist_to_merge_m - car.dist_to_merge_m, 2),
                    "ahead_speed_mps": car.speed_mps,
                    "ahead_other_road": int(origin[car.vehicle] != origin[vid]),
                }
            rows.append(row)
    return rows


def forced_before_free(decided: pd.DataFrame) -> int:
    """Cars whose mask forced the hard brake before their first step with a Δa action allowed: a brake no
    policy of theirs could have avoided (experiments/forced_entry_brakes.py, 'before_free')."""
    count = 0
    for _, steps in decided.groupby("vehicle", sort=False):
        masks = steps.allowed_actions.tolist()
        free = next((i for i, m in enumerate(masks) if "1" in m[:HARD_BRAKE]), len(masks))
        count += any(m == FORCED for m in masks[:free])
    return count


def summarise(episodes: pd.DataFrame, scenarios: pd.DataFrame) -> pd.DataFrame:
    finishable = set(scenarios[scenarios.finishable_alone].scenario)
    rows = []
    for label, e in episodes.groupby("method", sort=False):
        ok = e[e.scenario.isin(finishable)]
        rows.append(
            {
                "method": label,
                "scenarios": len(e),
                "success": round(e.success.mean(), 4),
                "perfect": round(e.perfect.mean(), 4),
                "timeouts": int(e.timed_out.sum()),
                "collision_scenarios": int((e.collisions > 0).sum()),
                "failed_unfinishable": int((e.success == 0).sum() - (ok.success == 0).sum()),
                "finishable_scenarios": len(ok),
                "success_of_finishable": round(ok.success.mean(), 4) if len(ok) else np.nan,
                "perfect_of_finishable": round(ok.perfect.mean(), 4) if len(ok) else np.nan,
                "joint_return": round(e.joint_return.mean(), 4),
            }
        )
    return pd.DataFrame(rows)


def check_stored_validation(method: Method, stats: list[EpisodeStats], config: TrainConfig, args) -> None:
    """A ``<stage>_best.pt`` holds the validation that picked it: say whether this run reproduces it."""
    if (
        method.path is None
        or args.safety_mask
        or args.max_episode_s
        or args.entries
        or args.seed != config.validation_seed
        or args.scenarios != config.validation_scenarios
    ):
        return
    try:
        stored = load_checkpoint(method.path).validation
    except Exception:  # a shipped policy file is no training checkpoint
        return
    if stored is not None:
        same = score_episodes(stats) == stored
        print(f"  {method.label}: stored validation {stored}; reproduced: {'yes' if same else 'NO'}")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", action="append", default=[], help="[LABEL=]PATH of a checkpoint")
    parser.add_argument("--method", action="append", default=[], help="a shipped policy or a rule, by name")
    parser.add_argument(
        "--config", type=Path, default=SCENARIO_DIR / "train_ours.toml", help="training recipe"
    )
    parser.add_argument(
        "--seed", type=int, default=None, help="scenario seed (default: the recipe's validation_seed)"
    )
    parser.add_argument(
        "--scenarios", type=int, default=None, help="default: the recipe's validation_scenarios"
    )
    parser.add_argument("--safety-mask", choices=("own_lane", "merge_aware"), default=None)
    parser.add_argument("--max-episode-s", type=float, default=None, help="default: the recipe's")
    parser.add_argument(
        "--entries", choices=("as_drawn", "feasible"), default=None, help="default: the recipe's"
    )
    parser.add_argument("--trajectories", action="store_true", help="write trajectories_failed.csv.gz")
    parser.add_argument("--out", type=Path, required=True)
    return parser.parse_args()


def recipe(args: argparse.Namespace) -> TrainConfig:
    config = load_train_config(args.config)
    env = config.env
    if args.safety_mask:
        env = dataclasses.replace(env, safety_mask=args.safety_mask)
    if args.max_episode_s:
        env = dataclasses.replace(env, max_episode_s=args.max_episode_s)
    if args.entries:
        traffic = dataclasses.replace(config.intelligent_traffic, entries=args.entries)
        config = dataclasses.replace(config, intelligent_traffic=traffic)
    args.seed = config.validation_seed if args.seed is None else args.seed
    args.scenarios = config.validation_scenarios if args.scenarios is None else args.scenarios
    if args.seed in EVALUATION_SEEDS:
        sys.exit(f"probe: error: --seed {args.seed} is a reserved evaluation seed (2019-2033)")
    return dataclasses.replace(config, env=env)


def main() -> None:
    args = parse_args()
    config = recipe(args)
    methods = parse_methods(args.checkpoint, args.method)
    site = choose_merge(DEFAULT_NET, config.env.junction)
    traffic = config.intelligent_traffic
    tasks = validation_tasks(traffic, _site_limits(site), args.scenarios, args.seed, start_room_m(site))
    scenarios = [t.scenario for t in tasks]
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"{len(tasks)} scenarios of seed {args.seed}; {config.env}; entries {traffic.entries}")
    cars = solo_bounds(site, config, scenarios)
    table = scenario_table(scenarios, cars, config.env.max_episode_s)
    episodes, collisions, brakes, failed = [], [], [], []
    for method in methods:
        start = time.perf_counter()
        stats, results = run_method(site, config, tasks, method)
        check_stored_validation(method, stats, config, args)
        for s, r, scenario in zip(stats, results, scenarios, strict=True):
            episodes.append(episode_row(method.label, scenario.name, s, r.trajectory))
            collisions += collision_rows(method.label, scenario.name, s, r.trajectory)
            brakes += brake_rows(method.label, scenario.name, r.trajectory)
            if not s.success:
                failed.append(r.trajectory.assign(method=method.label, scenario=scenario.name))
        print(f"  {method.label}: {time.perf_counter() - start:.0f} s")
    ep = pd.DataFrame(episodes)
    fails = ep[ep.success == 0].groupby("scenario").method.agg(lambda m: " ".join(m))
    table["failed_by"] = table.scenario.map(fails).fillna("")
    table["failed_by_count"] = table.failed_by.str.split().str.len().fillna(0).astype(int)
    summary = summarise(ep, table)
    ep.to_csv(args.out / "episodes.csv", index=False)
    table.to_csv(args.out / "scenarios.csv", index=False)
    cars.to_csv(args.out / "cars.csv", index=False)
    pd.DataFrame(collisions).to_csv(args.out / "collisions.csv", index=False)
    pd.DataFrame(brakes).to_csv(args.out / "brakes.csv", index=False)
    if failed and args.trajectories:
        pd.concat(failed).to_csv(args.out / "trajectories_failed.csv.gz", index=False)
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(summary.to_string(index=False))
        print(
            table[table.failed_by_count > 0].drop(columns=["main_prio", "merge_prio"]).to_string(index=False)
        )
    summary.to_csv(args.out / "summary.csv", index=False)


if __name__ == "__main__":
    main()
