"""What the subcommands share: the parser class, argument types, help fragments and the backend check."""

from __future__ import annotations

import argparse
import stat
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from idas_sumo.config import MAX_EPISODES, MAX_SCENARIOS
from idas_sumo.distributed import LOCAL, check_ray_address
from idas_sumo.errors import InputError
from idas_sumo.resources import DEFAULT_TRAIN_CONFIG, resolve_user_path
from idas_sumo.sim.multinet import MAX_COPIES
from idas_sumo.sim.processes import SEED_LIMIT, max_workers

RAY_ADDRESS_HELP = (
    "run the {what} as Ray actors: auto (the cluster `ray start` runs here), HOST:PORT (a head node), "
    "or local (a Ray instance on this machine only); needs the ray extra; results do not depend on it"
)
EVAL_SEED = 2019
"""``evaluate``'s default seed (scenarios drawn and SUMO's ``--seed``); never used in training."""
JUNCTION_HELP = (
    "the merge to run on, by junction id, in a net with several (idas-sumo nets inspect lists them; "
    "default: the net's only merge)"
)


class Parser(argparse.ArgumentParser):
    """The command line's parser: bad usage is one line on stderr and exit 2."""

    def error(self, message: str) -> NoReturn:
        # One line, no usage dump: the project's contract for bad usage.
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


if TYPE_CHECKING:
    Subparsers = argparse._SubParsersAction[Parser]
    """The main parser's ``add_subparsers()``, on which each subcommand module adds its parser."""


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def seed(text: str) -> int:
    """A seed SUMO can take (its ``--seed`` is a C int): an integer in [0, 2^31)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, {SEED_LIMIT}), got {text!r}") from None
    if not 0 <= value < SEED_LIMIT:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, {SEED_LIMIT}), got {value}")
    return value


def _positive_int_up_to(limit: int, name: str) -> Callable[[str], int]:
    """An argparse type: a positive integer no larger than ``limit``."""

    def parse(text: str) -> int:
        value = positive_int(text)
        if value > limit:
            raise argparse.ArgumentTypeError(f"expected at most {limit}, got {value}")
        return value

    parse.__name__ = name
    return parse


copies = _positive_int_up_to(MAX_COPIES, "copies")
episode_count = _positive_int_up_to(MAX_EPISODES, "episode_count")
scenario_count = _positive_int_up_to(MAX_SCENARIOS, "scenario_count")


def out_path(text: str) -> Path:
    """An output path; an empty one (``--out ""``, an unset shell variable) would mean the current
    directory without the user having named it."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    return Path(text)


def ray_address(text: str) -> str:
    """``--ray-address``: auto, local or HOST:PORT (checked here; Ray itself is imported only later)."""
    try:
        return check_ray_address(text)
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err).removeprefix("--ray-address: ")) from None


def input_file(text: str) -> Path:
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


class VersionAction(argparse.Action):
    """``--version``, looked up only when asked for (the package metadata scan costs every start)."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=kwargs.get("help"))

    def __call__(self, parser: argparse.ArgumentParser, *args: Any) -> None:
        print(f"{parser.prog} {_version()}")
        parser.exit()


def train_defaults() -> dict[str, Any]:
    """The shipped training config, for help texts; read with tomllib rather than TrainConfig so that
    ``--help`` does not import torch (a test keeps the file equal to TrainConfig's defaults)."""
    try:
        with DEFAULT_TRAIN_CONFIG.open("rb") as f:
            return tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError):
        return {}


def add_worker_flags(
    parser: argparse.ArgumentParser,
    what: str,
    processes: str,
    default: str,
    workers_default: int | None = None,
) -> None:
    """``--workers`` and ``--ray-address``, which ``train`` and ``evaluate`` share (``check_backend``
    checks both): ``what`` the workers are and the ``processes`` they run, for the help, and where
    the ``default`` comes from."""
    parser.add_argument(
        "--workers",
        type=positive_int,
        default=workers_default,
        help=f"{processes}, one SUMO each, at most the CPU count (with --ray-address: Ray actors, at most "
        f"the cluster's CPUs); results do not depend on it ({default})",
    )
    parser.add_argument(
        "--ray-address",
        type=ray_address,
        metavar="ADDRESS",
        help=RAY_ADDRESS_HELP.format(what=f"--workers {what}"),
    )


def _check_workers(args: argparse.Namespace) -> None:
    """``--workers``: a count this machine can run, one process (and one SUMO) per CPU at most; more
    only slows the run down and can exhaust memory (1000 workers once forked 200+ processes).
    Checked before anything starts. With ``--ray-address`` (but ``local``, this machine) the workers
    are actors on a cluster, whose CPUs bound them instead (distributed/ray_pool.py)."""
    workers = getattr(args, "workers", None)
    if workers is None or getattr(args, "ray_address", None) not in (None, LOCAL):
        return
    limit = max_workers()
    if workers > limit:
        raise InputError(f"--workers: {workers} is more than this machine's {limit} CPUs (at most {limit})")


def check_backend(args: argparse.Namespace) -> None:
    """Before anything runs: ``--workers`` within this machine's CPUs unless they run on a cluster,
    and ``--ray-address`` without the ray extra is exit 2 naming it."""
    _check_workers(args)
    if getattr(args, "ray_address", None) is not None:
        from idas_sumo.distributed import require_ray

        require_ray()
