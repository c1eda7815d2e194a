"""``idas-sumo evaluate``: a method (or the paper's five) on a scenario suite with the paper's protocol;
CSVs, a summary table, optional plots. The method names come from evaluation/policies.py."""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from idas_sumo.cli.common import (
    EVAL_SEED,
    JUNCTION_HELP,
    add_worker_flags,
    check_backend,
    copies,
    input_file,
    out_path,
    scenario_count,
    seed,
)
from idas_sumo.env.actions import DEFAULT_SAFETY_MASK, SAFETY_MASKS
from idas_sumo.errors import InputError
from idas_sumo.evaluation import DEFAULT_EVAL_COPIES
from idas_sumo.evaluation.policies import METHODS, PAPER_METHODS, PAPER_RECIPE_METHODS
from idas_sumo.resources import DEFAULT_NET_NAME, resolve_user_path

if TYPE_CHECKING:
    import pandas as pd

    from idas_sumo.cli.common import Subparsers
    from idas_sumo.env.config import EnvConfig
    from idas_sumo.sim.merge_detect import MergeSite

RESULTS_DIR = Path("results")
"""Where ``evaluate`` without ``--out`` writes: a new ``<method>-<suite>-<seed>`` folder per run."""
MISSING = "–"
"""The table's cell for a value that does not exist (no perfect episode, so no speed)."""


def baseline_help(
    methods: tuple[str, ...] = METHODS,
    paper: tuple[str, ...] = PAPER_METHODS,
    recipe: tuple[str, ...] = PAPER_RECIPE_METHODS,
) -> str:
    """``--baseline``'s help: the registered methods (evaluation/policies.py), the paper's first, the paper's
    recipe as printed last."""
    ours = [m for m in methods if m not in paper and m not in recipe]
    text = f"method: {' | '.join(paper)} | all (those {len(paper)}: the paper's)"
    text = f"{text}; also {' | '.join(ours)} (ours, docs/results.md)" if ours else text
    printed = [m for m in methods if m in recipe]
    return f"{text}; {' | '.join(printed)} (the paper's recipe as printed)" if printed else text


def add_parser(sub: Subparsers) -> None:
    ev = sub.add_parser("evaluate", help="evaluate a method with the paper's protocol; write CSVs")
    ev.add_argument("--baseline", required=True, help=baseline_help())
    _add_scenario_flags(ev)
    _add_output_flags(ev)
    add_worker_flags(
        ev, "evaluation workers", "processes sharing the episodes", "default: %(default)s", workers_default=1
    )
    ev.add_argument(
        "--copies",
        type=copies,
        default=DEFAULT_EVAL_COPIES,
        help="episodes run side by side in one SUMO run; results do not depend on it (default: %(default)s)",
    )


def _add_scenario_flags(ev: argparse.ArgumentParser) -> None:
    """What is run: the net, the suite or scenario files, the seed, the other cars' method, the policy."""
    ev.add_argument(
        "--net", type=input_file, default=DEFAULT_NET_NAME, help="merge network (default: %(default)s)"
    )
    ev.add_argument("--junction", metavar="ID", help=JUNCTION_HELP)
    ev.add_argument(
        "--suite",
        default="paper",
        choices=("paper", "representative", "driver-types", "geometry"),
        help="scenario suite (default: %(default)s); geometry: the paper suite on held-out generated "
        "merges and the on-ramp sample net, one table each (--net is not used)",
    )
    ev.add_argument(
        "--scenarios",
        type=scenario_count,
        help="random scenarios of the paper suite (default: 100), start offsets per b_type of the "
        "driver-types suite (default: 10)",
    )
    ev.add_argument(
        "--config",
        type=input_file,
        help="TOML: [traffic] and max_episode_s for the paper suite "
        "(default: the built-in values, as in scenarios/eval_paper.toml)",
    )
    ev.add_argument(
        "--safety-mask",
        choices=SAFETY_MASKS,
        help="which car every method's safety mask follows: own_lane (the paper) or merge_aware "
        f"(a shield) (default: the --config file's safety_mask, else {DEFAULT_SAFETY_MASK})",
    )
    ev.add_argument(
        "--scenario",
        type=input_file,
        action="append",
        default=[],
        help="evaluate this scenario TOML instead of a suite (repeatable; ego = its first vehicle)",
    )
    ev.add_argument(
        "--seed",
        type=seed,
        default=EVAL_SEED,
        help="scenario seed in [0, 2^31) (default: %(default)s, not used in training)",
    )
    ev.add_argument(
        "--others", help="method for every non-ego vehicle (default: shipped IDAS if present, else idm)"
    )
    ev.add_argument(
        "--policy",
        type=input_file,
        help="checkpoint for the learned method instead of the shipped one",
    )
    ev.add_argument(
        "--others-policy",
        type=input_file,
        help="checkpoint the other vehicles' learned method loads instead of the shipped one (the paper runs "
        "them on the learned IDAS: e.g. --policy X --others-policy X evaluates X among its own kind)",
    )


def _add_output_flags(ev: argparse.ArgumentParser) -> None:
    """Where the CSVs go and what else is written or shown."""
    ev.add_argument(
        "--out",
        type=out_path,
        help=f"output directory (default: a new {RESULTS_DIR}/<method>-<suite>-<seed>, "
        "or the same name with -2, -3, ... when that exists)",
    )
    ev.add_argument(
        "--force",
        action="store_true",
        help="write into an existing, non-empty --out (without --out: reuse "
        "<method>-<suite>-<seed> instead of making a new one)",
    )
    ev.add_argument("--trajectories", action="store_true", help="also write per-step trajectories.csv")
    ev.add_argument("--sumo-output", action="store_true", help="also keep SUMO's tripinfo XML per episode")
    ev.add_argument("--plots", action="store_true", help="also write PNG plots next to the CSVs")
    ev.add_argument("--no-progress", action="store_true", help="no progress bar")
    ev.add_argument("--gui", action="store_true", help="show the episodes in sumo-gui (needs a display)")


def _default_out(args: argparse.Namespace) -> Path:
    suite = "scenario" if args.scenario else args.suite  # --scenario files replace the suite
    return RESULTS_DIR / f"{args.baseline}-{suite}-{args.seed}"


def run(args: argparse.Namespace) -> int:
    from idas_sumo.evaluation.policies import LEARNED_METHODS, METHOD_LABELS, check_method
    from idas_sumo.evaluation.runner import EvalRequest, default_others, run_evaluation

    check_backend(args)
    check_method(args.baseline, "--baseline", also=("all",))
    methods = PAPER_METHODS if args.baseline == "all" else (args.baseline,)
    if args.others is not None:
        check_method(args.others, "--others")
    others = args.others or default_others()
    if args.others_policy is not None and others not in LEARNED_METHODS:
        raise InputError(f"--others-policy: the other vehicles run {others}, which reads no policy file")
    if args.policy is not None and not any(m in LEARNED_METHODS for m in methods):
        # Silently ignored, a typo'd or missing file would pass unnoticed as "the policy evaluated".
        raise InputError(
            f"--policy only applies to the learned methods ({', '.join(LEARNED_METHODS)}); "
            f"--baseline {args.baseline} does not read it"
        )
    env = _eval_env(args)
    site = None
    if args.suite == "geometry":
        _check_geometry_args(args)
    else:
        site = _check_eval_net(args, env)
    out = args.out if args.out is not None else _default_out(args)
    request = EvalRequest(
        net=Path(args.net),
        env=env,
        site=site,
        methods=tuple(methods),
        suite=args.suite,
        scenarios=args.scenarios,
        seed=args.seed,
        others=others,
        policy=args.policy,
        others_policy=args.others_policy,
        out=out,
        force=args.force,
        fresh_out=args.out is None and not args.force,
        trajectories=args.trajectories,
        sumo_output=args.sumo_output,
        progress=not args.no_progress and sys.stderr.isatty(),
        gui=args.gui,
        config=args.config,
        scenario_files=tuple(args.scenario),
        copies=args.copies,
        workers=args.workers,
        ray_address=args.ray_address,
    )
    if args.suite == "geometry":
        return _evaluate_geometry(args, request, others)
    result = run_evaluation(request)
    if args.others is None and others == "idm":
        # Only after the run: before it, a bad input must stay the one line on stderr.
        print("note: no shipped IDAS policy found; the other vehicles run IDM", file=sys.stderr)
    from rich.console import Console

    title = f"{args.suite} suite, seed {args.seed}, others: {others}"
    Console().print(summary_table(result.summary, title, METHOD_LABELS))
    for line in result.verdicts:
        print(line)
    print(f"wrote {result.out}/: {', '.join(result.written)}")
    if args.plots:
        from idas_sumo.evaluation.plots import plot_directory

        for png in plot_directory(result.out):
            print(f"wrote {png}")
    return 0


def _check_geometry_args(args: argparse.Namespace) -> None:
    """``--suite geometry`` brings its own nets and the paper suite's random scenarios."""
    if Path(args.net) != resolve_user_path(DEFAULT_NET_NAME):
        raise InputError(
            "--suite geometry runs on its own nets (held-out merges, the on-ramp): leave out --net"
        )
    for flag, given in (("--junction", args.junction), ("--scenario", args.scenario), ("--gui", args.gui)):
        if given:
            raise InputError(f"--suite geometry runs the paper suite on each of its nets: leave out {flag}")


def _evaluate_geometry(args: argparse.Namespace, request: Any, others: str) -> int:
    """The paper suite on every geometry of ``evaluation/geometry.py``: one table each, then
    ``geometry.csv``."""
    from rich.console import Console

    from idas_sumo.evaluation.geometry import run_geometry_suite
    from idas_sumo.evaluation.policies import METHOD_LABELS

    def check(net: Path) -> MergeSite:
        fields = {**vars(args), "net": net, "suite": "paper", "junction": None}
        return _check_eval_net(argparse.Namespace(**fields), request.env)

    def show(name: str, output: Any) -> None:
        title = f"geometry {name}: paper suite, seed {args.seed}, others: {others}"
        Console().print(summary_table(output.summary, title, METHOD_LABELS))

    _, table = run_geometry_suite(request, check, show)
    print(f"wrote {request.out}/: one folder per geometry, {table.name}")
    return 0


def _eval_env(args: argparse.Namespace) -> EnvConfig:
    """The evaluation's episode rules: the ``--config`` file's (else the defaults), ``--safety-mask`` and
    ``--junction`` on top."""
    from idas_sumo.evaluation.protocol import EvalConfig, load_eval_config

    env = (load_eval_config(args.config) if args.config is not None else EvalConfig()).env
    return replace(env, safety_mask=args.safety_mask or env.safety_mask, junction=args.junction)


def _check_eval_net(args: argparse.Namespace, env: EnvConfig) -> MergeSite:
    """The evaluated merge (the one parse of the net); refuse a net whose roads are too short or too
    long for the scenarios evaluated (env/net_needs.py)."""
    from idas_sumo.env.net_needs import check_road_lengths, road_needs
    from idas_sumo.evaluation.protocol import EvalConfig, load_eval_config
    from idas_sumo.sim.merge_detect import choose_merge

    site = choose_merge(args.net, args.junction)
    config = load_eval_config(args.config) if args.config is not None else EvalConfig()
    # The paper suite draws starts over the traffic's start range; scenario files and the
    # representative suites place their cars themselves (checked against the roads when loaded).
    random_starts = args.suite == "paper" and not args.scenario
    start_range = config.traffic.start_range_m if random_starts else None
    source = f"{args.config}" if args.config is not None else "max_episode_s"
    check_road_lengths(site, road_needs(start_range, env.max_episode_s, source))
    # Cars placed by a file must start on the road (a car 1e308 m down a 250 m road once ran, exit 0).
    from idas_sumo.env.scenario import Road, check_against_net, load_scenario, start_room_m
    from idas_sumo.resources import SCENARIO_DIR

    files = args.scenario or (
        [] if random_starts else sorted((SCENARIO_DIR / "representative").glob("*.toml"))
    )
    speed_limits: dict[Road, float] = {
        "main": site.main.road.speed_limit_mps,
        "merge": site.merge.road.speed_limit_mps,
    }
    for path in files:
        scenario = load_scenario(path, speed_limits)
        check_against_net(scenario, speed_limits, start_room_m(site), str(path))
        for v in scenario.vehicles:  # SUMO refused 1e300 s after writing its tripinfo file into --out
            if v.depart_s >= env.max_episode_s:
                raise InputError(
                    f"{path}: vehicle {v.id!r} departs at {v.depart_s:g} s, not before the episode's "
                    f"{env.max_episode_s:g} s timeout (max_episode_s): it would never drive"
                )
    return site


def summary_table(summary: pd.DataFrame, title: str, labels: dict[str, str]) -> Any:
    """The summary as a rich Table; a speed that does not exist (no perfect episode) shows as MISSING."""
    from rich.console import Group
    from rich.table import Table

    table = Table(title=title)
    for col in ("method", "scenarios", "success %", "perfect %", "avg speed (perfect), m/s"):
        table.add_column(col)
    # Our further metrics in a second table: nine columns do not fit an 80-column terminal.
    more = Table(title="further metrics, % of scenarios")
    for col in ("method", "perfect w/o flow %", "collision %", "timeout %", "ego success %"):
        more.add_column(col)
    for row in summary.to_dict("records"):
        speed = float(row["avg_speed_perfect_mps"])
        label = labels.get(str(row["method"]), str(row["method"]))
        table.add_row(
            label,
            str(row["scenarios"]),
            f"{row['success_pct']:.0f}",
            f"{row['perfect_pct']:.0f}",
            f"{speed:.2f}" if math.isfinite(speed) else MISSING,
        )
        pcts = ("perfect_no_flow_pct", "collision_pct", "timeout_pct", "ego_success_pct")
        more.add_row(label, *(f"{row[c]:.0f}" for c in pcts))
    return Group(table, more)
