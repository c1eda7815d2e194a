"""``idas-sumo``: netgen | nets | train | evaluate | plot | replay | sweep. Exit codes: 0 ok, 1 runtime failure, 2 bad input,
130 Ctrl-C, 143 SIGTERM (129 SIGHUP)."""

from __future__ import annotations

import argparse
import atexit
import contextlib
import errno
import logging
import math
import os
import signal
import stat
import sys
import threading
import tomllib
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from idas_sumo.distributed import LOCAL, check_ray_address
from idas_sumo.env.actions import DEFAULT_SAFETY_MASK, SAFETY_MASKS
from idas_sumo.errors import IdasError, InputError
from idas_sumo.evaluation import DEFAULT_EVAL_COPIES
from idas_sumo.resources import (
    DEFAULT_NET_NAME,
    DEFAULT_TRAIN_CONFIG,
    DEFAULT_TRAIN_CONFIG_NAME,
    resolve_user_path,
)
from idas_sumo.sim.multinet import MAX_COPIES
from idas_sumo.sim.netgen import PRIORITIES, NetParams
from idas_sumo.sim.nets_cli import add_nets_parser, run_nets
from idas_sumo.sim.processes import SEED_LIMIT, max_workers

if TYPE_CHECKING:
    import pandas as pd

DESCRIPTION = (
    "Train and evaluate IDAS merging policies in SUMO. "
    "Exit codes: 0 ok, 1 runtime failure, 2 bad input, 130 Ctrl-C, 143 SIGTERM."
)
RESULTS_DIR = Path("results")
"""Where ``evaluate`` without ``--out`` writes: a new ``<method>-<suite>-<seed>`` folder per run."""
MISSING = "–"
"""The table's cell for a value that does not exist (no perfect episode, so no speed)."""
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))
"""Signals that stop a run like Ctrl-C does (cleanup, checkpoint), with exit 128 + the signal."""
TERMINATED = "idas-sumo: terminated ({}); completed outputs were kept"
PATH_ERRNOS = frozenset({errno.ENAMETOOLONG, errno.ELOOP})
"""OS errors that say a path the user typed cannot name a file (too long, a symlink loop): bad input."""
MAX_SCENARIOS = 100_000
"""``evaluate --scenarios`` at most: the suite's scenarios are drawn up front (10^9 filled the memory
before the first episode); 100 000 already take hours per method (the paper uses 100)."""
NETGEN_FLAGS: dict[str, tuple[str, str]] = {
    "main_length_m": ("--main-length", "main road length to the merge point, m"),
    "merge_length_m": ("--merge-length", "merge road length to the merge point, m"),
    "out_length_m": ("--out-length", "outgoing road length, m"),
    "main_speed_mps": ("--main-speed", "main road speed limit, m/s"),
    "merge_speed_mps": ("--merge-speed", "merge road speed limit, m/s"),
    "out_speed_mps": ("--out-speed", "outgoing road speed limit, m/s"),
    "angle_deg": ("--angle", "angle between the two roads, degrees"),
}
"""``netgen``'s flags: NetParams field -> (flag, help); the defaults are NetParams's."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP), raised where Ctrl-C would be so that the same cleanup runs (checkpoint,
    temp files)."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__(signum)
        self.signum = signum


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


def _seed(text: str) -> int:
    """A seed SUMO can take (its ``--seed`` is a C int): an integer in [0, 2^31)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, {SEED_LIMIT}), got {text!r}") from None
    if not 0 <= value < SEED_LIMIT:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, {SEED_LIMIT}), got {value}")
    return value


def _check_workers(args: argparse.Namespace) -> None:
    """``--workers``: a count this machine can run, one process (and one SUMO) per CPU at most; more
    only slows the run down and can exhaust memory (1000 workers once forked 200+ processes and 8 GB).
    Checked before anything starts. With ``--ray-address`` (but ``local``, this machine) the workers
    are actors on a cluster, whose CPUs bound them instead (distributed/ray_pool.py)."""
    workers = getattr(args, "workers", None)
    if workers is None or getattr(args, "ray_address", None) not in (None, LOCAL):
        return
    limit = max_workers()
    if workers > limit:
        raise InputError(f"--workers: {workers} is more than this machine's {limit} CPUs (at most {limit})")


def _copies(text: str) -> int:
    value = _positive_int(text)
    if value > MAX_COPIES:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_COPIES}, got {value}")
    return value


def _scenario_count(text: str) -> int:
    value = _positive_int(text)
    if value > MAX_SCENARIOS:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_SCENARIOS}, got {value}")
    return value


def _out_path(text: str) -> Path:
    """An output path; an empty one (``--out ""``, an unset shell variable) would mean the current
    directory without the user having named it."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    return Path(text)


def _ray_address(text: str) -> str:
    """``--ray-address``: auto, local or HOST:PORT (checked here; Ray itself is imported only later)."""
    try:
        return check_ray_address(text)
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err).removeprefix("--ray-address: ")) from None


RAY_ADDRESS_HELP = (
    "run the {what} as Ray actors: auto (the cluster `ray start` runs here), HOST:PORT (a head node), "
    "or local (a Ray instance on this machine only); needs the ray extra; results do not depend on it"
)


def _input_file(text: str) -> Path:
    """An input file flag's path (``resolve_user_path``); a FIFO, device or socket is refused here, since
    reading one can block forever or never end. A missing file or a directory is left to the reader,
    whose message names what it expected."""
    path = resolve_user_path(text)
    try:
        mode = path.stat().st_mode
    except OSError:
        return path
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise argparse.ArgumentTypeError(
            f"{path}: not a regular file (a FIFO, device or socket); give a file"
        )
    return path


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("idas-sumo")
    except PackageNotFoundError:  # run from a source tree that was never installed
        from idas_sumo import __version__

        return __version__


class _VersionAction(argparse.Action):
    """``--version``, looked up only when asked for (the package metadata scan costs every start)."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=kwargs.get("help"))

    def __call__(self, parser: argparse.ArgumentParser, *args: Any) -> None:
        print(f"{parser.prog} {_version()}")
        parser.exit()


def _train_defaults() -> dict[str, Any]:
    """The shipped training config, for help texts; read with tomllib rather than TrainConfig so that
    ``--help`` does not import torch (a test keeps the file equal to TrainConfig's defaults)."""
    try:
        with DEFAULT_TRAIN_CONFIG.open("rb") as f:
            return tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError):
        return {}


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="idas-sumo", description=DESCRIPTION)
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    parser.add_argument("--version", action=_VersionAction, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    net = sub.add_parser("netgen", help="generate the two-road merge network with netconvert")
    net.add_argument(
        "--out", type=_out_path, default=DEFAULT_NET_NAME, help="output .net.xml (default: %(default)s)"
    )
    defaults = NetParams()
    for field, (flag, what) in NETGEN_FLAGS.items():
        net.add_argument(
            flag,
            dest=field,
            metavar=flag.removeprefix("--").replace("-", "_").upper(),
            type=float,
            default=getattr(defaults, field),
            help=f"{what} (default: %(default)s)",
        )
    net.add_argument(
        "--priority",
        choices=PRIORITIES,
        default=defaults.priority,
        help="right of way: the main road's, or equal (a zipper junction) (default: %(default)s)",
    )
    add_nets_parser(sub)

    train = sub.add_parser("train", help="train IDAS (robot world, intelligent world, or both)")
    train.add_argument(
        "--net", type=_input_file, default=DEFAULT_NET_NAME, help="merge network (default: %(default)s)"
    )
    train.add_argument("--junction", metavar="ID", help=JUNCTION_HELP)
    train.add_argument(
        "--config",
        type=_input_file,
        help=f"training config TOML (default: {DEFAULT_TRAIN_CONFIG_NAME})",
    )
    shipped = _train_defaults()

    def from_config(*keys: str) -> str:
        values = " / ".join(str(shipped.get(k, "?")) for k in keys)
        return f"default: from --config, else {DEFAULT_TRAIN_CONFIG_NAME}: {values}"

    train.add_argument(
        "--stage",
        choices=("robot", "intelligent", "direct", "curriculum"),
        help=f"what to train ({from_config('stage')})",
    )
    train.add_argument(
        "--episodes",
        type=_positive_int,
        help="episodes of every stage the run trains; with --resume, a larger N extends a finished run "
        f"({from_config('robot_episodes', 'intelligent_episodes', 'direct_episodes')} for robot / "
        "intelligent / direct)",
    )
    train.add_argument(
        "--workers",
        type=_positive_int,
        help="rollout processes, one SUMO each, at most the CPU count (with --ray-address: Ray actors, at "
        f"most the cluster's CPUs) ({from_config('workers')})",
    )
    train.add_argument(
        "--copies",
        type=_copies,
        help="episodes a rollout process runs side by side in one SUMO; results do not depend on it "
        f"({from_config('copies')})",
    )
    train.add_argument(
        "--seed",
        type=_seed,
        help=f"the one seed everything random flows from, in [0, 2^31) ({from_config('seed')})",
    )
    train.add_argument(
        "--safety-mask",
        choices=SAFETY_MASKS,
        help="which car the safety mask follows: own_lane (the paper) or merge_aware (a shield) "
        f"({from_config('safety_mask')})",
    )
    train.add_argument("--out", type=_out_path, help="run directory (default: runs/<stage>)")
    again = train.add_mutually_exclusive_group()
    again.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from its last checkpoint, with the run's own config "
        "(flags you give override it: --workers, --copies, --episodes; others are ignored with a warning)",
    )
    again.add_argument(
        "--force", action="store_true", help="start over in an --out that holds a run (replaces its files)"
    )
    train.add_argument("--no-progress", action="store_true", help="no progress bar")
    train.add_argument(
        "--gui", action="store_true", help="show the rollouts in sumo-gui (slow; needs a display)"
    )
    train.add_argument(
        "--ray-address",
        type=_ray_address,
        metavar="ADDRESS",
        help=RAY_ADDRESS_HELP.format(what="--workers rollout workers"),
    )

    ev = sub.add_parser("evaluate", help="evaluate a method with the paper's protocol; write CSVs")
    ev.add_argument(
        "--baseline",
        required=True,
        help="method: idas | idas_v | idas_direct | idm | fsm_idm | all (those five: the paper's); also idas_geometry | idas_brakes | idas_manoeuvre | idas_explored10_collide | idas_cooperative | idas_anchored | fsm_idm_smooth (ours, docs/results.md)",
    )
    ev.add_argument(
        "--net", type=_input_file, default=DEFAULT_NET_NAME, help="merge network (default: %(default)s)"
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
        type=_scenario_count,
        help="random scenarios of the paper suite (default: 100), start offsets per b_type of the "
        "driver-types suite (default: 10)",
    )
    ev.add_argument(
        "--config",
        type=_input_file,
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
        type=_input_file,
        action="append",
        default=[],
        help="evaluate this scenario TOML instead of a suite (repeatable; ego = its first vehicle)",
    )
    ev.add_argument(
        "--seed",
        type=_seed,
        default=2019,
        help="scenario seed in [0, 2^31) (default: %(default)s, not used in training)",
    )
    ev.add_argument(
        "--others", help="method for every non-ego vehicle (default: shipped IDAS if present, else idm)"
    )
    ev.add_argument(
        "--policy",
        type=_input_file,
        help="checkpoint for the learned method instead of the shipped one",
    )
    ev.add_argument(
        "--out",
        type=_out_path,
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
    ev.add_argument(
        "--workers",
        type=_positive_int,
        default=1,
        help="processes sharing the episodes, one SUMO each, at most the CPU count (2 keeps both cores busy; "
        "with --ray-address: Ray actors, at most the cluster's CPUs); results do not depend on it "
        "(default: %(default)s)",
    )
    ev.add_argument(
        "--copies",
        type=_copies,
        default=DEFAULT_EVAL_COPIES,
        help="episodes run side by side in one SUMO run; results do not depend on it (default: %(default)s)",
    )
    ev.add_argument(
        "--ray-address",
        type=_ray_address,
        metavar="ADDRESS",
        help=RAY_ADDRESS_HELP.format(what="--workers evaluation workers"),
    )

    _add_sweep_parser(sub)

    plot = sub.add_parser(
        "plot", help="draw PNG plots from an evaluation or a training run directory, or compare training runs"
    )
    plot.add_argument(
        "dir",
        type=_out_path,
        nargs="+",
        help="directory written by `idas-sumo evaluate` or `train`; several training runs (seeds, variants) "
        "are drawn on one figure, written to --out",
    )
    plot.add_argument(
        "--out", type=_out_path, help="the comparison's .png (with several training run directories)"
    )

    rep = sub.add_parser("replay", help="run one evaluated episode again: in sumo-gui or as an animation")
    rep.add_argument("dir", type=_out_path, help="directory written by `idas-sumo evaluate`")
    rep.add_argument(
        "--scenario", required=True, help="scenario name as in episodes.csv (paper-037, s1) or its index (37)"
    )
    rep.add_argument("--method", help="which evaluated method's episode (default: the only one)")
    view = rep.add_mutually_exclusive_group()
    view.add_argument("--gui", action="store_true", help="show it in sumo-gui (needs a display)")
    view.add_argument("--out", type=_out_path, help="write an animation: .gif, or .mp4 (needs ffmpeg)")
    rep.add_argument(
        "--policy", type=_input_file, help="the evaluated checkpoint, if it moved (its SHA-256 must match)"
    )
    return parser


def _add_sweep_parser(sub: Any) -> None:
    sweep = sub.add_parser(
        "sweep", help="train over seeds and config values (one run folder each); write one table"
    )
    sweep.add_argument("config", type=_input_file, help="training config TOML (validate_every > 0)")
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
        "--net", type=_input_file, default=DEFAULT_NET_NAME, help="merge network (default: %(default)s)"
    )
    sweep.add_argument(
        "--out", type=_out_path, default=Path("runs/sweep"), help="sweep folder (default: %(default)s)"
    )
    sweep.add_argument(
        "--ray-address",
        type=_ray_address,
        metavar="ADDRESS",
        help="run the runs as Ray tasks on this cluster (auto, HOST:PORT, or local), not one after another",
    )
    sweep.add_argument(
        "--evaluate", action="store_true", help="also evaluate each run's best checkpoint (paper suite)"
    )
    sweep.add_argument(
        "--eval-seed", type=_seed, default=2019, help="scenario seed of --evaluate (default: %(default)s)"
    )
    sweep.add_argument(
        "--eval-scenarios",
        type=_scenario_count,
        default=100,
        help="scenarios of --evaluate (default: %(default)s)",
    )


JUNCTION_HELP = (
    "the merge to run on, by junction id, in a net with several (idas-sumo nets inspect lists them; "
    "default: the net's only merge)"
)


def _netgen(args: argparse.Namespace) -> int:
    from idas_sumo.env.engine import DEFAULT_MAX_EPISODE_S
    from idas_sumo.env.net_needs import check_road_lengths, road_needs
    from idas_sumo.env.scenario import TrafficConfig
    from idas_sumo.sim.netgen import describe, generate_net, read_merge_net

    params = NetParams(**{field: getattr(args, field) for field in NETGEN_FLAGS}, priority=args.priority)
    path = generate_net(args.out, params)
    net = read_merge_net(path)
    print(describe(net))
    try:  # a net for other scenarios is fine to write, but say now what train/evaluate will say
        check_road_lengths(net, road_needs(TrafficConfig().start_range_m, DEFAULT_MAX_EPISODE_S))
    except InputError as err:
        print(
            f"idas-sumo: warning: with the default scenarios, train and evaluate refuse it: {err}",
            file=sys.stderr,
        )
    return 0


def _default_out(args: argparse.Namespace) -> Path:
    suite = "scenario" if args.scenario else args.suite  # --scenario files replace the suite
    return RESULTS_DIR / f"{args.baseline}-{suite}-{args.seed}"


def _evaluate(args: argparse.Namespace) -> int:
    from idas_sumo.evaluation.policies import LEARNED_METHODS, METHOD_LABELS, PAPER_METHODS, check_method
    from idas_sumo.evaluation.runner import EvalRequest, default_others, run_evaluation

    _check_backend(args)
    check_method(args.baseline, "--baseline", also=("all",))
    methods = PAPER_METHODS if args.baseline == "all" else (args.baseline,)
    if args.others is not None:
        check_method(args.others, "--others")
    if args.policy is not None and not any(m in LEARNED_METHODS for m in methods):
        # Silently ignored, a typo'd or missing file would pass unnoticed as "the policy evaluated".
        raise InputError(
            f"--policy only applies to the learned methods ({', '.join(LEARNED_METHODS)}); "
            f"--baseline {args.baseline} does not read it"
        )
    if args.suite == "geometry":
        _check_geometry_args(args)
    else:
        _check_eval_net(args)
    out = args.out if args.out is not None else _default_out(args)
    if args.force and out.is_dir():
        from idas_sumo.io_utils import remove_stale_temps

        # Writes killed before their rename (SIGKILL, power loss) leave their temp files behind.
        remove_stale_temps(out)
    others = args.others or default_others()
    request = EvalRequest(
        net=Path(args.net),
        junction=args.junction,
        methods=tuple(methods),
        suite=args.suite,
        scenarios=args.scenarios,
        seed=args.seed,
        others=others,
        policy=args.policy,
        out=out,
        force=args.force,
        fresh_out=args.out is None and not args.force,
        trajectories=args.trajectories,
        sumo_output=args.sumo_output,
        progress=not args.no_progress and sys.stderr.isatty(),
        gui=args.gui,
        config=args.config,
        safety_mask=args.safety_mask,
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

    def check(net: Path) -> None:
        _check_eval_net(argparse.Namespace(**{**vars(args), "net": net, "suite": "paper", "junction": None}))

    def show(name: str, output: Any) -> None:
        title = f"geometry {name}: paper suite, seed {args.seed}, others: {others}"
        Console().print(summary_table(output.summary, title, METHOD_LABELS))

    _, table = run_geometry_suite(request, check, show)
    print(f"wrote {request.out}/: one folder per geometry, {table.name}")
    return 0


def _check_eval_net(args: argparse.Namespace) -> None:
    """Refuse a net whose roads are too short or too long for the scenarios evaluated (env/net_needs.py)."""
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
    check_road_lengths(site, road_needs(start_range, config.max_episode_s, source))
    # Cars placed by a file must start on the road (a car 1e308 m down a 250 m road once ran, exit 0).
    from idas_sumo.env.scenario import Road, check_against_net, load_scenario
    from idas_sumo.resources import SCENARIO_DIR

    files = args.scenario or (
        [] if random_starts else sorted((SCENARIO_DIR / "representative").glob("*.toml"))
    )
    speed_limits: dict[Road, float] = {
        "main": site.main.road.speed_limit_mps,
        "merge": site.merge.road.speed_limit_mps,
    }
    lengths: dict[Road, float] = {"main": site.main.length_m, "merge": site.merge.length_m}
    for path in files:
        check_against_net(load_scenario(path, speed_limits), speed_limits, lengths, str(path))


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


def _check_backend(args: argparse.Namespace) -> None:
    """Before anything runs: ``--workers`` within this machine's CPUs unless they run on a cluster,
    and ``--ray-address`` without the ray extra is exit 2 naming it."""
    _check_workers(args)
    if getattr(args, "ray_address", None) is not None:
        from idas_sumo.distributed import require_ray

        require_ray()


def _train(args: argparse.Namespace) -> int:
    from idas_sumo.training.cli import train_from_args

    _check_backend(args)
    return train_from_args(args)


def _sweep(args: argparse.Namespace) -> int:
    from functools import partial

    from idas_sumo.evaluation.best_checkpoint import evaluate_checkpoint
    from idas_sumo.training.sweep import parse_seeds, parse_sets, run_sweep

    _check_backend(args)
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


def _replay(args: argparse.Namespace) -> int:
    from idas_sumo.evaluation.replay import replay_from_args

    return replay_from_args(args)


def _plot(args: argparse.Namespace) -> int:
    from idas_sumo.evaluation.plots import plot_directory
    from idas_sumo.io_utils import ensure_writable_dir
    from idas_sumo.training.plots import compare_runs, is_training_run, plot_training_run

    for directory in args.dir:
        for csv in sorted(directory.glob("*.csv")) if directory.is_dir() else []:
            if csv.exists() and not csv.is_file():  # reading a FIFO blocks until written to
                raise InputError(f"{csv}: not a regular file (a FIFO, device or socket), expected a CSV file")
    if len(args.dir) > 1 or args.out is not None:
        if len(args.dir) < 2:
            raise InputError(
                "--out writes a comparison of several training runs: name two run directories or more"
            )
        if args.out is None or args.out.suffix.lower() != ".png":
            raise InputError("comparing several training runs needs --out FILE.png")
        ensure_writable_dir(args.out.parent, "--out")
        print(f"wrote {compare_runs(args.dir, args.out)}")
        return 0
    (directory,) = args.dir
    # An evaluation has episodes.csv; a training run, metrics.csv or validation.csv.
    training = not (directory / "episodes.csv").exists() and is_training_run(directory)
    for png in plot_training_run(directory) if training else plot_directory(directory):
        print(f"wrote {png}")
    return 0


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM, and SIGHUP (the terminal closed) unless it is ignored (``nohup``), raise
    ``Terminated`` (a KeyboardInterrupt) while the command runs, so a stopped run cleans up as after
    Ctrl-C; the previous handlers come back afterwards (main may run in a test)."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be set from the main thread
        return

    def terminate(signum: int, frame: object) -> None:
        raise Terminated(signum)

    previous = {
        signum: signal.signal(signum, terminate)
        for signum in STOP_SIGNALS
        if signal.getsignal(signum) is not signal.SIG_IGN
    }
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


INTERRUPTED = "idas-sumo: interrupted; completed outputs were kept"


def _stopped(signum: int) -> int:
    """Say that a signal stopped the run; its exit code (130 for Ctrl-C, 143 for SIGTERM, ...)."""
    line = INTERRUPTED if signum == signal.SIGINT else TERMINATED.format(signal.Signals(signum).name)
    with contextlib.suppress(OSError):  # after SIGHUP the terminal may be gone
        print(line, file=sys.stderr)
    return 128 + signum


class _LateSignals:
    """Ctrl-C or SIGTERM after the command is done: recorded, not raised.

    Raised there, it would interrupt an exit handler (closing SUMO, removing temp folders) with an
    "Exception ignored in atexit callback" traceback, and the process would still exit 0. Instead the
    cleanup runs to its end and the process exits 130 / 143 with the usual line: the last exit handler
    (registered before any other, so it runs after them all) ends the process with that code.
    """

    def __init__(self) -> None:
        self.caught: int | None = None
        self.reported = False
        atexit.register(self._exit_if_caught)

    def install(self) -> None:
        for signum in (signal.SIGINT, *STOP_SIGNALS):
            if signal.getsignal(signum) is not signal.SIG_IGN:
                signal.signal(signum, self._record)

    def _record(self, signum: int, frame: object) -> None:
        self.caught = self.caught or signum

    def exit_code(self, code: int) -> int:
        """``code``, unless a signal came while it was being reported: then the signal's code."""
        if self.caught is None or self.reported:
            return code
        self.reported = True
        return _stopped(self.caught)

    def _exit_if_caught(self) -> None:
        if self.caught is None or self.reported:
            return
        code = self.exit_code(0)
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def main(argv: Sequence[str] | None = None) -> int:
    """The command line. ``argv`` None (the ``idas-sumo`` script, ``python -m idas_sumo.cli``): the
    process is ours, so signals that come after the command are handled too (``_LateSignals``);
    with ``argv`` (a caller in Python) the caller's signal handlers are left alone."""
    late = _LateSignals() if argv is None and _in_main_thread() else None
    return late.exit_code(_run(argv, late)) if late is not None else _run(argv, None)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _run(argv: Sequence[str] | None, late: _LateSignals | None) -> int:
    handlers = {
        "netgen": _netgen,
        "nets": run_nets,
        "train": _train,
        "evaluate": _evaluate,
        "plot": _plot,
        "replay": _replay,
        "sweep": _sweep,
    }
    try:
        try:
            args = build_parser().parse_args(argv)
            logging.basicConfig(
                level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s"
            )
            with _sigterm_as_interrupt():
                return handlers[args.command](args)
        finally:
            if late is not None:
                late.install()
    except Terminated as stop:
        return _stopped(stop.signum)
    except KeyboardInterrupt:
        return _stopped(signal.SIGINT)
    except InputError as err:
        print(f"idas-sumo: error: {err}", file=sys.stderr)
        return 2
    except IdasError as err:
        print(f"idas-sumo: error: {err}", file=sys.stderr)
        return err.exit_code
    except OSError as err:  # disk full, I/O error: outputs are atomic, so earlier files are intact
        where = f"{err.filename}: " if err.filename else ""
        if err.errno in PATH_ERRNOS:  # the name itself is unusable, wherever the OS noticed
            print(f"idas-sumo: error: {where}{err.strerror}", file=sys.stderr)
            return 2
        print(
            f"idas-sumo: error: {where}{err.strerror or err} (files written before are intact)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
