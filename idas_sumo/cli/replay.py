"""``idas-sumo replay``: one evaluated episode again, in sumo-gui or as an animation
(evaluation/replay.py runs it)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from idas_sumo.cli.common import input_file, out_path

if TYPE_CHECKING:
    from idas_sumo.cli.common import Subparsers


def add_parser(sub: Subparsers) -> None:
    rep = sub.add_parser("replay", help="run one evaluated episode again: in sumo-gui or as an animation")
    rep.add_argument("dir", type=out_path, help="directory written by `idas-sumo evaluate`")
    rep.add_argument(
        "--scenario", required=True, help="scenario name as in episodes.csv (paper-037, s1) or its index (37)"
    )
    rep.add_argument("--method", help="which evaluated method's episode (default: the only one)")
    view = rep.add_mutually_exclusive_group()
    view.add_argument("--gui", action="store_true", help="show it in sumo-gui (needs a display)")
    view.add_argument("--out", type=out_path, help="write an animation: .gif, or .mp4 (needs ffmpeg)")
    rep.add_argument("--force", action="store_true", help="replace an existing --out file")
    rep.add_argument(
        "--policy", type=input_file, help="the evaluated checkpoint, if it moved (its SHA-256 must match)"
    )


def run(args: argparse.Namespace) -> int:
    from idas_sumo.evaluation.replay import replay_from_args
    from idas_sumo.io_utils import claim_output_file

    if args.out is not None:  # an animation has no mark of its own: any existing file needs --force
        claim_output_file(args.out, args.force, lambda path: False)
    return replay_from_args(args)
