"""``idas-sumo sweep``: training runs over seeds and config values (one run folder each), one table."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from idas_sumo.cli.common import (
    EVAL_SEED,
    check_backend,
    input_file,
    out_path,
    ray_address,
    scenario_count,
    seed,
)
from idas_sumo.resources import DEFAULT_NET_NAME

if TYPE_CHECKING:
    from idas_sumo.cli.common import Subparsers


def add_parser(sub: Subparsers) -> None:
    sweep = sub.add_parser(
        "sweep", help="train over seeds and config values (one run folder each); write one table"
    )
    sweep.add_argument("config", type=input_file, help="training config TOML (validate_every > 0)")
    sweep.add_argument("--seeds", required=True, help="seeds of the runs: 0-4, 0,3,7 or a mix")
    sweep.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=V1,V2",
        help="sweep a config key over these values (nested keys with dots: learner.gamma); repeatable: "
        "the runs are every combination",
    )
    sweep.add_argument(
        "--net", type=input_file, default=DEFAULT_NET_NAME, help="merge network (default: %(default)s)"
    )
    sweep.add_argument(
        "--out", type=out_path, default=Path("runs/sweep"), help="sweep folder (default: %(default)s)"
    )
    sweep.add_argument(
        "--ray-address",
        type=ray_address,
        metavar="ADDRESS",
        help="run the runs as Ray tasks on this cluster (auto, HOST:PORT, or local), not one after another",
    )
    sweep.add_argument(
        "--evaluate", action="store_true", help="also evaluate each run's best checkpoint (paper suite)"
    )
    sweep.add_argument(
        "--eval-seed", type=seed, default=EVAL_SEED, help="scenario seed of --evaluate (default: %(default)s)"
    )
    sweep.add_argument(
        "--eval-scenarios",
        type=scenario_count,
        default=100,
        help="scenarios of --evaluate (default: %(default)s)",
    )


def run(args: argparse.Namespace) -> int:
    from functools import partial

    from idas_sumo.evaluation.best_checkpoint import evaluate_checkpoint
    from idas_sumo.training.sweep import parse_seeds, parse_sets, run_sweep

    check_backend(args)
    seeds, sets = parse_seeds(args.seeds), parse_sets(args.set)
    evaluate = (
        partial(evaluate_checkpoint, seed=args.eval_seed, scenarios=args.eval_scenarios)
        if args.evaluate
        else None
    )
    csv_path, png_path = run_sweep(
        Path(args.config),
        Path(args.net),
        seeds,
        sets,
        args.out,
        ray_address=args.ray_address,
        evaluate=evaluate,
        on_run=lambda row: print(f"run {row['run']}: best validation {row['best_joint_return']:.2f}"),
    )
    print(f"wrote {csv_path}, {png_path}")
    return 0
