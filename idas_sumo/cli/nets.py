"""``idas-sumo nets``: the merges a SUMO network holds, and the sample nets (sim/nets_cli.py does both)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from idas_sumo.sim.nets_cli import add_nets_parser, run_nets

if TYPE_CHECKING:
    from idas_sumo.cli.common import Subparsers


def add_parser(sub: Subparsers) -> None:
    add_nets_parser(sub)


def run(args: argparse.Namespace) -> int:
    return run_nets(args)
