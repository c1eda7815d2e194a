"""``idas-sumo plot``: PNG plots of an evaluation or a training run, or several training runs compared."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from idas_sumo.cli.common import out_path
from idas_sumo.errors import InputError

if TYPE_CHECKING:
    from idas_sumo.cli.common import Subparsers


def add_parser(sub: Subparsers) -> None:
    plot = sub.add_parser(
        "plot", help="draw PNG plots from an evaluation or a training run directory, or compare training runs"
    )
    plot.add_argument(
        "dir",
        type=out_path,
        nargs="+",
        help="directory written by `idas-sumo evaluate`, `train` or `cosim`; several training runs (seeds, variants) "
        "are drawn on one figure, written to --out",
    )
    plot.add_argument(
        "--out", type=out_path, help="the comparison's .png (with several training run directories)"
    )
    plot.add_argument("--force", action="store_true", help="replace an --out that idas-sumo did not write")


def run(args: argparse.Namespace) -> int:
    from idas_sumo.evaluation.plots import plot_directory
    from idas_sumo.io_utils import claim_output_file, ensure_writable_dir, is_matplotlib_png
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
        claim_output_file(args.out, args.force, is_matplotlib_png)
        ensure_writable_dir(args.out.parent, "--out")
        print(f"wrote {compare_runs(args.dir, args.out)}")
        return 0
    (directory,) = args.dir
    from idas_sumo.cosim.study import is_study
    from idas_sumo.cosim.study import plot_directory as plot_cosim

    if not (directory / "episodes.csv").exists() and is_study(directory):  # a cosim folder: flows.csv
        for png in plot_cosim(directory):
            print(f"wrote {png}")
        return 0
    # An evaluation has episodes.csv; a training run, metrics.csv or validation.csv.
    training = not (directory / "episodes.csv").exists() and is_training_run(directory)
    for png in plot_training_run(directory) if training else plot_directory(directory):
        print(f"wrote {png}")
    return 0
