"""``idas-sumo train``: train IDAS (robot world, intelligent world, or both); training/cli.py runs it."""

from __future__ import annotations

import argparse
import contextlib
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING

from idas_sumo.cli.common import (
    JUNCTION_HELP,
    add_worker_flags,
    check_backend,
    copies,
    episode_count,
    input_file,
    out_path,
    seed,
    train_defaults,
)
from idas_sumo.env.actions import SAFETY_MASKS
from idas_sumo.resources import DEFAULT_NET_NAME, DEFAULT_TRAIN_CONFIG_NAME
from idas_sumo.sim.processes import worker_fork_server
from idas_sumo.training.worker_count import ROLLOUT_PRELOAD, rollout_workers

if TYPE_CHECKING:
    from idas_sumo.cli.common import Subparsers


def add_parser(sub: Subparsers) -> None:
    train = sub.add_parser("train", help="train IDAS (robot world, intelligent world, or both)")
    train.add_argument(
        "--net", type=input_file, default=DEFAULT_NET_NAME, help="merge network (default: %(default)s)"
    )
    train.add_argument("--junction", metavar="ID", help=JUNCTION_HELP)
    train.add_argument(
        "--config",
        type=input_file,
        help=f"training config TOML (default: {DEFAULT_TRAIN_CONFIG_NAME})",
    )
    _add_config_flags(train)
    train.add_argument("--out", type=out_path, help="run directory (default: runs/<stage>)")
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


def _add_config_flags(train: argparse.ArgumentParser) -> None:
    """The flags that override the config file; their help names the shipped config's values."""
    shipped = train_defaults()

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
        type=episode_count,
        help="episodes of every stage the run trains; with --resume, a larger N extends a finished run "
        f"({from_config('robot_episodes', 'intelligent_episodes', 'direct_episodes')} for robot / "
        "intelligent / direct)",
    )
    add_worker_flags(
        train, "rollout workers", "rollout processes", f"{from_config('workers')}; 0: one per CPU"
    )
    train.add_argument(
        "--copies",
        type=copies,
        help="episodes a rollout process runs side by side in one SUMO; results do not depend on it "
        f"({from_config('copies')})",
    )
    train.add_argument(
        "--seed",
        type=seed,
        help=f"the one seed everything random flows from, in [0, 2^31) ({from_config('seed')})",
    )
    train.add_argument(
        "--safety-mask",
        choices=SAFETY_MASKS,
        help="which car the safety mask follows: own_lane (the paper) or merge_aware (a shield) "
        f"({from_config('safety_mask')})",
    )


def run(args: argparse.Namespace) -> int:
    check_backend(args)
    # The rollout workers' fork server imports torch and the trainer now, beside this process's own imports, and
    # loads what each worker's first round would (``workers.warm_up``).
    starts = contextlib.nullcontext() if _expected_workers(args) < 2 else worker_fork_server(ROLLOUT_PRELOAD)
    with starts:
        from idas_sumo.training.cli import train_from_args

        return train_from_args(args)


def _expected_workers(args: argparse.Namespace) -> int:
    """The rollout processes the run will most likely start (0 if it collects in this process, or on Ray): the
    config's rule on the flags and the config file, read as TOML so that nothing heavy is imported yet. A wrong
    guess costs a fork server started for nothing, or workers that import on their own; never a result."""
    if getattr(args, "ray_address", None) is not None:
        return 0
    values = train_defaults()
    path = getattr(args, "config", None)
    if path is not None:
        try:
            with Path(path).open("rb") as f:
                values = {**values, **tomllib.load(f)}
        except (OSError, ValueError):  # (not TOML, not UTF-8: the run itself says what is wrong with it)
            return 0
    stages = ("robot_episodes", "intelligent_episodes", "direct_episodes")
    try:
        budget = args.episodes if getattr(args, "episodes", None) else max(int(values[k]) for k in stages)
        count = rollout_workers(
            int(getattr(args, "workers", None) or values["workers"]),
            int(values["episodes_per_update"]),
            budget,
            gui=bool(getattr(args, "gui", False)),
        )
    except (KeyError, TypeError, ValueError):
        return 0
    return count if count > 1 else 0
