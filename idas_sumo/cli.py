"""``idas-sumo``: netgen | train | evaluate | plot. Exit codes: 0 ok, 1 runtime failure, 2 bad input, 130 Ctrl-C."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from idas_sumo.errors import IdasError, InputError
from idas_sumo.resources import DEFAULT_NET_NAME, DEFAULT_TRAIN_CONFIG_NAME, resolve_user_path


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        # One line, no usage dump: the project's contract for bad usage.
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="idas-sumo", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    net = sub.add_parser("netgen", help="generate the two-road merge network with netconvert")
    net.add_argument("--out", default=DEFAULT_NET_NAME, help="output .net.xml (default: %(default)s)")
    net.add_argument(
        "--main-length", type=float, default=250.0, help="main road length to the merge point, m"
    )
    net.add_argument(
        "--merge-length", type=float, default=250.0, help="merge road length to the merge point, m"
    )
    net.add_argument("--out-length", type=float, default=150.0, help="outgoing road length, m")
    net.add_argument("--main-speed", type=float, default=20.0, help="main road speed limit, m/s")
    net.add_argument("--merge-speed", type=float, default=15.0, help="merge road speed limit, m/s")
    net.add_argument("--out-speed", type=float, default=20.0, help="outgoing road speed limit, m/s")
    net.add_argument("--angle", type=float, default=30.0, help="angle between the two roads, degrees")

    train = sub.add_parser("train", help="train IDAS (robot world, intelligent world, or both)")
    train.add_argument(
        "--net", type=resolve_user_path, default=DEFAULT_NET_NAME, help="merge network (default: %(default)s)"
    )
    train.add_argument(
        "--config",
        type=resolve_user_path,
        help=f"training config TOML (default: {DEFAULT_TRAIN_CONFIG_NAME})",
    )
    train.add_argument(
        "--stage", choices=("robot", "intelligent", "direct", "curriculum"), help="what to train"
    )
    train.add_argument(
        "--episodes", type=_positive_int, help="episodes for every stage run (overrides config)"
    )
    train.add_argument("--workers", type=_positive_int, help="rollout processes (one SUMO each)")
    train.add_argument("--seed", type=int, help="the one seed everything random flows from")
    train.add_argument("--out", type=Path, help="run directory (default: runs/<stage>)")
    train.add_argument(
        "--resume", action="store_true", help="continue the run in --out from its last checkpoint"
    )
    train.add_argument("--no-progress", action="store_true", help="no progress bar")
    train.add_argument(
        "--gui", action="store_true", help="show the rollouts in sumo-gui (slow; needs a display)"
    )

    ev = sub.add_parser("evaluate", help="evaluate a method with the paper's protocol; write CSVs")
    ev.add_argument("--baseline", required=True, help="idas | idas_v | idas_direct | idm | fsm_idm | all")
    ev.add_argument(
        "--net", type=resolve_user_path, default=DEFAULT_NET_NAME, help="merge network (default: %(default)s)"
    )
    ev.add_argument("--suite", default="paper", choices=("paper", "representative", "driver-types"))
    ev.add_argument("--scenarios", type=_positive_int, default=100, help="random scenarios (paper suite)")
    ev.add_argument(
        "--config", type=resolve_user_path, help="TOML: [traffic] and max_episode_s for the paper suite"
    )
    ev.add_argument(
        "--scenario",
        type=resolve_user_path,
        action="append",
        default=[],
        help="evaluate this scenario TOML instead of a suite (repeatable; ego = its first vehicle)",
    )
    ev.add_argument(
        "--seed", type=int, default=2019, help="scenario seed (default: %(default)s, not used in training)"
    )
    ev.add_argument(
        "--others", help="method for every non-ego vehicle (default: shipped IDAS if present, else idm)"
    )
    ev.add_argument(
        "--policy",
        type=resolve_user_path,
        help="checkpoint for the learned method instead of the shipped one",
    )
    ev.add_argument(
        "--out", type=Path, default=Path("results"), help="output directory (default: %(default)s)"
    )
    ev.add_argument("--force", action="store_true", help="overwrite files in an existing --out")
    ev.add_argument("--trajectories", action="store_true", help="also write per-step trajectories.csv")
    ev.add_argument("--sumo-output", action="store_true", help="also keep SUMO's tripinfo XML per episode")
    ev.add_argument("--plots", action="store_true", help="also write PNG plots next to the CSVs")
    ev.add_argument("--no-progress", action="store_true", help="no progress bar")
    ev.add_argument("--gui", action="store_true", help="show the episodes in sumo-gui (needs a display)")

    plot = sub.add_parser("plot", help="draw PNG plots from an evaluation output directory")
    plot.add_argument("dir", type=Path, help="directory written by `idas-sumo evaluate`")
    return parser


def _netgen(args: argparse.Namespace) -> int:
    from idas_sumo.sim.netgen import NetParams, describe, generate_net, read_merge_net

    params = NetParams(
        main_length_m=args.main_length,
        merge_length_m=args.merge_length,
        out_length_m=args.out_length,
        main_speed_mps=args.main_speed,
        merge_speed_mps=args.merge_speed,
        out_speed_mps=args.out_speed,
        angle_deg=args.angle,
    )
    path = generate_net(args.out, params)
    print(describe(read_merge_net(path)))
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from idas_sumo.evaluation.policies import METHOD_LABELS, METHODS, check_method
    from idas_sumo.evaluation.runner import EvalRequest, default_others, run_evaluation

    methods = METHODS if args.baseline == "all" else (check_method(args.baseline),)
    if args.others is not None:
        check_method(args.others, "--others")
    others = args.others or default_others()
    summary = run_evaluation(
        EvalRequest(
            net=Path(args.net),
            methods=tuple(methods),
            suite=args.suite,
            scenarios=args.scenarios,
            seed=args.seed,
            others=others,
            policy=args.policy,
            out=args.out,
            force=args.force,
            trajectories=args.trajectories,
            sumo_output=args.sumo_output,
            progress=not args.no_progress and sys.stderr.isatty(),
            gui=args.gui,
            config=args.config,
            scenario_files=tuple(args.scenario),
        )
    )
    if args.others is None and others == "idm":
        # Only after the run: before it, a bad input must stay the one line on stderr.
        print("note: no shipped IDAS policy found; the other vehicles run IDM", file=sys.stderr)
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"{args.suite} suite, seed {args.seed}, others: {others}")
    for col in ("method", "scenarios", "success %", "perfect %", "avg speed (perfect), m/s"):
        table.add_column(col)
    for row in summary.itertuples(index=False):
        table.add_row(
            METHOD_LABELS.get(str(row.method), str(row.method)),
            str(row.scenarios),
            f"{row.success_pct:.0f}",
            f"{row.perfect_pct:.0f}",
            f"{row.avg_speed_perfect_mps:.2f}",
        )
    Console().print(table)
    print(f"wrote {args.out}/episodes.csv, summary.csv, flow.csv")
    if args.plots:
        from idas_sumo.evaluation.plots import plot_directory

        for png in plot_directory(args.out):
            print(f"wrote {png}")
    return 0


def _train(args: argparse.Namespace) -> int:
    from idas_sumo.training.cli import train_from_args

    return train_from_args(args)


def _plot(args: argparse.Namespace) -> int:
    from idas_sumo.evaluation.plots import plot_directory

    for png in plot_directory(args.dir):
        print(f"wrote {png}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s"
    )
    handlers = {"netgen": _netgen, "train": _train, "evaluate": _evaluate, "plot": _plot}
    try:
        return handlers[args.command](args)
    except KeyboardInterrupt:
        print("idas-sumo: interrupted; completed outputs were kept", file=sys.stderr)
        return 130
    except InputError as err:
        print(f"idas-sumo: error: {err}", file=sys.stderr)
        return 2
    except IdasError as err:
        print(f"idas-sumo: error: {err}", file=sys.stderr)
        return err.exit_code
    except OSError as err:  # disk full, I/O error: outputs are atomic, so earlier files are intact
        where = f"{err.filename}: " if err.filename else ""
        print(
            f"idas-sumo: error: {where}{err.strerror or err} (files written before are intact)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
