"""How many of the headline's scenarios could any ego finish perfectly? A search over the ego's actions (issue 36,
"the ceiling").

The headline protocol (`idas-sumo evaluate --baseline M --scenarios 100 --seed S`: one random car of each scenario
is the ego and runs the method, every other car the shipped IDAS, greedy; the own-lane mask; feasible entries;
60 s episodes) is rebuilt here from the evaluation's own parts (``suite_cases``, ``run_jobs``, the default
``EvalConfig``), so that an episode here is the one ``evaluate`` runs for the same ego actions. Instead of one
greedy ego per method, each scenario is run ``--samples`` times with the ego *sampling* its actions from a
learned policy (``--sampler``: ``warm_start``, ``idas``, ...; temperature 1, one seeded generator per sampler):
a random search around what those policies would do. A scenario counts as reachable when at least one of its
runs is perfect (the paper's perfect success: every car finished and no car lost reward to a hard brake).

Scenarios: those in which none of the methods of the reference evaluations (``--reference PATH``: ``evaluate``'s
``episodes.csv`` files, or directories of them, e.g. results/headline-2030/*; their rows of ``--seed``) was perfect, plus ``--controls`` scenarios in which
every reference method was perfect (to show what sampling costs where greedy driving is perfect).

Writes to ``--out``: ``samples.csv`` (scenario, sampler, sample: the episode's row of ``evaluate``'s
``episodes.csv`` plus the hard brakes of the ego and of the other cars, how many of them the mask forced, and how
many of the other cars' came before the ego's first decision, where nothing it does can matter) and
``scenarios.csv`` (per scenario and sampler: runs, perfect runs, successful runs).

    python experiments/ego_ceiling/search.py --seed 2030 --reference results/headline-2030 \\
        --sampler warm_start --sampler idas --samples 128 --out results/ego_ceiling/seed2030
"""

from __future__ import annotations

import idas_sumo  # noqa: F401  (first: its OMP_WAIT_POLICY must be set before torch loads)

# isort: split
import argparse
import sys
from pathlib import Path

import pandas as pd
import torch

from idas_sumo.agents.checkpoint_file import load_actor
from idas_sumo.agents.policy import ActorPolicy
from idas_sumo.env.actions import HARD_BRAKE, N_ACTIONS
from idas_sumo.env.contracts import Policy
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.scenario import start_room_m
from idas_sumo.evaluation.policies import LEARNED_METHODS, resolve_policy
from idas_sumo.evaluation.protocol import EpisodeResult, EvalCase, EvalConfig, EvalJob, run_jobs, suite_cases
from idas_sumo.resources import DEFAULT_NET, POLICY_DIR
from idas_sumo.sim.merge_detect import MergeSite, choose_merge

FORCED = "".join("1" if a == HARD_BRAKE else "0" for a in range(N_ACTIONS))
"""The allowed-actions string of a step where the mask leaves only the hard brake."""
COPIES = 16


def headline_cases(seed: int, scenarios: int) -> tuple[MergeSite, EvalConfig, list[EvalCase]]:
    """The shipped merge, ``evaluate``'s default episode rules and the paper suite's cases of ``seed``."""
    site = choose_merge(DEFAULT_NET, None)
    config = EvalConfig()
    limits = {"main": site.main.road.speed_limit_mps, "merge": site.merge.road.speed_limit_mps}
    lengths = {"main": site.main.length_m, "merge": site.merge.length_m}
    cases = suite_cases("paper", scenarios, seed, limits, config.traffic, lengths, start_room_m(site))
    return site, config, cases


def _reference(paths: list[Path], seed: int) -> pd.DataFrame:
    """The reference episodes of ``seed``: each path an ``episodes.csv`` or a directory of ``*/episodes.csv``."""
    files = [p for path in paths for p in ([path] if path.is_file() else sorted(path.glob("*/episodes.csv")))]
    frames = [f for f in (pd.read_csv(p) for p in files) if len(f)]
    episodes = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if not len(episodes) or not (episodes["seed"] == seed).any():
        raise SystemExit(f"no reference episodes of seed {seed} in {', '.join(map(str, paths))}")
    return episodes[episodes["seed"] == seed]


def _chosen(cases: list[EvalCase], reference: pd.DataFrame, controls: int) -> list[EvalCase]:
    """The cases no reference method finished perfectly, then the first ``controls`` every method did."""
    perfect = reference.groupby("scenario")["perfect"]
    none = set(perfect.max().index[perfect.max() == 0])
    every = [c for c in cases if c.scenario.name in set(perfect.min().index[perfect.min() == 1])]
    return [c for c in cases if c.scenario.name in none] + every[:controls]


def _brakes(result: EpisodeResult) -> dict[str, int]:
    """Hard brakes chosen at a decision, by the ego and by the other cars, and how many the mask forced."""
    t = result.trajectory
    brake = t[t["action"] == HARD_BRAKE]
    ego = brake["method"] != "others"
    forced = brake["allowed_actions"] == FORCED
    ego_decides = t.loc[(t["method"] != "others") & (t["action"] >= 0), "time_s"]
    first = float(ego_decides.min()) if len(ego_decides) else float("inf")
    return {
        "ego_brakes": int(ego.sum()),
        "ego_brakes_forced": int((ego & forced).sum()),
        "others_brakes": int((~ego).sum()),
        "others_brakes_forced": int((~ego & forced).sum()),
        "others_brakes_before_ego": int((~ego & (brake["time_s"] < first)).sum()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--seed", type=int, required=True, help="the evaluation seed whose scenarios are searched"
    )
    parser.add_argument("--scenarios", type=int, default=100)
    parser.add_argument("--reference", type=Path, action="append", required=True)
    parser.add_argument("--sampler", action="append", required=True, choices=sorted(LEARNED_METHODS))
    parser.add_argument("--samples", type=int, default=128)
    parser.add_argument("--controls", type=int, default=10)
    parser.add_argument("--sample-seed", type=int, default=0)
    parser.add_argument(
        "--greedy", action="store_true", help="the samplers act greedily (checks the harness)"
    )
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    site, config, cases = headline_cases(args.seed, args.scenarios)
    chosen = _chosen(cases, _reference(args.reference, args.seed), args.controls)
    samplers: dict[str, Policy] = {
        name: ActorPolicy(
            load_actor(POLICY_DIR / LEARNED_METHODS[name]), seed=args.sample_seed, deterministic=args.greedy
        )
        for name in args.sampler
    }
    others = resolve_policy("idas", None, args.seed)  # as `evaluate` makes the shipped IDAS drive the others
    jobs = [EvalJob(name, case) for name in samplers for case in chosen for _ in range(args.samples)]
    print(f"{len(chosen)} scenarios x {len(samplers)} samplers x {args.samples} samples", file=sys.stderr)
    engine = MergeEngine(site, copies=COPIES, seed=args.seed, config=config.env)
    rows = []
    try:
        for i, (_job, result) in enumerate(run_jobs(engine, jobs, samplers, others)):
            rows.append({"sample": i % args.samples, **result.episode, **_brakes(result)})
            if (i + 1) % 256 == 0:
                print(f"{i + 1} / {len(jobs)}", file=sys.stderr, flush=True)
    finally:
        engine.close()
    samples = pd.DataFrame(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    samples.to_csv(args.out / "samples.csv", index=False)
    per = samples.groupby(["scenario", "method"], sort=False).agg(
        runs=("perfect", "size"), perfect_runs=("perfect", "sum"), success_runs=("success", "sum")
    )
    per.reset_index().to_csv(args.out / "scenarios.csv", index=False)
    print(per.to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
